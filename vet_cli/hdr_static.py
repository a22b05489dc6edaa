"""vet hdr-static: static HDR reconstruction of a capture."""

from __future__ import annotations

import click

from ._common import command, log, verbosity_options
from .outputs import Output, check_outputs, force_option


@click.command(
    "hdr-static",
    help="""Recover HDR radiance from CAPTURE assuming a still scene.

L = (I/g - d Tf) / (T + eps (Tf - T)): the exposure-time image T already holds when
each pixel's LCoS cell closed (latency included); eps is the leakage, d the dark
current. Output is float32 EXR in the scene's units for simulated captures, else DN/s,
with a mask layer (0 valid, 1 recovered from measuring images, 2 saturated lower bound,
3 below noise floor). CAPTURE may be a file, a capture folder, or - (stdin).

\b
Example:
  vet hdr-static cap.exr -o hdr.exr
  vet simulate builtin:chart -o - | vet hdr-static - -o - | vet tonemap - -o chart.png
""",
)
@click.argument("capture")
@click.option(
    "-o", "--output", required=True, help="HDR image (.exr or .npz), or - for stdout (EXR)."
)
@click.option(
    "--assume-ideal-rig",
    is_flag=True,
    help="Ignore the rig's measured parts (measurement camera geometry, gain and "
    "vignetting, relay blur, per-cell leakage, switching time, trigger offset): "
    "reconstruct as if it were the ideal rig, to see what they cost.",
)
@force_option
@verbosity_options
@command("hdr-static")
def cli(capture: str, output: str, assume_ideal_rig: bool, force: bool) -> None:
    import numpy as np

    from stages.formats import read_capture, resolve_capture_path, write_hdr
    from stages.hdr_static import hdr_static
    from stages.provenance import record_inputs

    check_outputs([Output("-o", output)], force, inputs=[("CAPTURE", capture)])
    source = resolve_capture_path(capture)
    cap = read_capture(source)
    img = hdr_static(cap, assume_ideal_rig=assume_ideal_rig)
    record_inputs(img.meta, [source])
    counts = np.bincount(img.mask.ravel(), minlength=4)
    log.debug("hdr-static: mask counts valid=%d recovered=%d saturated=%d floor=%d", *counts[:4])
    if counts[2]:
        log.warning(
            "%d pixels saturated in every image: values are lower bounds (mask code 2)", counts[2]
        )
    write_hdr(output, img)
