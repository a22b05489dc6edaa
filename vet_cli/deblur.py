"""vet deblur: joint estimation of the sharp HDR image and the motion of a capture."""

from __future__ import annotations

import click

from ._common import Progress, command, log, verbosity_options
from .outputs import Output, check_outputs, force_option
from .params import SCHEDULER


def _tile_value(value: str) -> int | str:
    if value in ("auto", "none"):
        return value
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 64:
        raise click.BadParameter(f"{value!r}: give auto, none or a tile size >= 64 pixels")
    return n


@click.command(
    "deblur",
    help="""Recover the sharp HDR scene at the start of the frame from a moving CAPTURE.

Estimates the scene L0 and a per-pixel velocity u (px/s) jointly from the variable
exposure image I, the exposure time image T and the measuring images. --method vet (the
default) estimates a layered motion (still background and translating layers, with
occlusion) from all the measuring images and solves a noise-weighted misfit on I and
the measuring images with conjugate gradients, coarse to fine (2x2 blocks first),
robust at occlusions; pixels whose integration path does not move take the value of
all their data (I and the measuring images) when anything moves, and hdr-static's when
nothing does (a still capture comes out as hdr-static; --fuse-still and --keep-still
choose one always); --method paper reproduces the published method (least squares on
I, Laplacian and histogram-intersection priors, steepest descent); --method burst is
the comparison baseline of a burst camera: the measuring images alone, aligned tile by
tile to the first and merged robustly (Hasinoff et al. 2016, HDR+), the VET image
unused. --motion-init truth
uses the simulator's true motion: an oracle for research.
Output is float32 EXR in the units of hdr-static, with its mask and T.

\b
Example:
  vet simulate builtin:interior --motion translate:30,0 -o cap.exr
  vet deblur cap.exr -o sharp.exr --motion-out motion.exr
""",
)
@click.argument("capture")
@click.option(
    "-o", "--output", required=True, help="HDR image (.exr or .npz), or - for stdout (EXR)."
)
@click.option(
    "--method",
    type=click.Choice(["vet", "paper", "burst"]),
    default="vet",
    show_default=True,
    help="Reconstruction method.",
)
@click.option(
    "--motion-init",
    type=click.Choice(["layers", "paths", "farneback", "dis", "truth", "zero"]),
    default=None,
    help="Motion estimate: layered (default for --method vet; along the measured path when "
    "the whole frame's path changes within it, a camera shake), layers along paths "
    "whenever some region's path changes (paths, experimental), dense Farnebäck (default "
    "for --method paper) or DIS flow, the simulator's truth, or none.",
)
@click.option(
    "--motion-out",
    default=None,
    metavar="MOTION.exr",
    help="Also write the estimated motion (layer 'motion', channels u, v, px/s).",
)
@click.option(
    "--motion-picture",
    default=None,
    metavar="MOTION.png",
    help="Also write a colour-wheel picture of the estimated motion.",
)
@click.option(
    "--fuse-still/--keep-still",
    default=None,
    help="What pixels no moving path touches take: --fuse-still the maximum-likelihood "
    "value of the VET image and the measuring images together, a still capture too; "
    "--keep-still hdr-static's (the VET data alone). Default: fused when some pixel "
    "moves, hdr-static's when none does. --method vet only.",
)
@click.option(
    "--tile",
    default="auto",
    show_default=True,
    metavar="N|auto|none",
    callback=lambda ctx, param, value: _tile_value(value),
    help="Solve in overlapping tiles of at most the pixels of an N x N core and its halo "
    "(longer along the motion), the motion estimated once for the frame: memory bounded by "
    "a tile. auto: N 512 (640 for one channel) on frames over 1024 pixels on a side; "
    "none: one solve. --method vet only.",
)
@click.option(
    "-j",
    "--jobs",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Tiles in parallel on an embedded Dask cluster of N worker processes.",
)
@click.option(
    "--scheduler",
    type=SCHEDULER,
    metavar="ADDRESS",
    default=None,
    help="Run the tiles on the existing Dask cluster at ADDRESS (tcp://HOST:PORT); a frame "
    "solved in one piece does not use it (said on stderr).",
)
@force_option
@verbosity_options
@command("deblur")
def cli(
    capture: str,
    output: str,
    method: str,
    motion_init: str | None,
    motion_out: str | None,
    motion_picture: str | None,
    fuse_still: bool | None,
    tile: int | str,
    jobs: int,
    scheduler: str | None,
    force: bool,
) -> None:
    from stages.deblur import deblur
    from stages.flow import motion_picture as picture
    from stages.flow import write_motion
    from stages.formats import read_capture, resolve_capture_path, write_hdr
    from stages.formats.images import write_display_image
    from stages.provenance import record_inputs

    if fuse_still is not None and method != "vet":
        flag = "--fuse-still" if fuse_still else "--keep-still"
        raise click.UsageError(f"{flag} applies to --method vet only")
    if method == "burst":
        given = [
            flag
            for flag, value in (
                ("--motion-init", motion_init),
                ("--motion-out", motion_out),
                ("--motion-picture", motion_picture),
            )
            if value is not None
        ]
        if given:
            raise click.UsageError(f"{given[0]} does not apply to --method burst (no motion field)")
    check_outputs(
        [
            Output("-o", output),
            Output("--motion-out", motion_out),
            Output("--motion-picture", motion_picture, "display"),
        ],
        force,
        inputs=[("CAPTURE", capture)],
    )
    source = resolve_capture_path(capture)
    # (the simulator's truth layers only for the truth's motion: a reconstruction
    # holds no more than it uses)
    cap = read_capture(source, truth=motion_init == "truth")
    _say_if_not_distributed(method, tile, cap, jobs, scheduler)
    if method == "burst":
        from stages.burst import burst_hdr

        with Progress("deblur burst") as progress:
            img = burst_hdr(cap, progress=progress)
        record_inputs(img.meta, [source])
        write_hdr(output, img)
        return
    with Progress(f"deblur {method}") as progress:
        img, vel = deblur(
            cap,
            method=method,
            motion_init=motion_init,
            progress=progress,
            fuse_still=fuse_still,
            tile=tile if method == "vet" else None,
            workers=jobs,
            scheduler=scheduler,
            release_stream=True,  # (cap's stream is not used again here)
        )
    record_inputs(img.meta, [source])
    log.debug("deblur: %s in %.1f s", img.meta["method"], img.meta["runtime_s"])
    write_hdr(output, img)
    if motion_out:
        write_motion(
            motion_out,
            vel,
            {"source": capture, "method": img.meta["method"], "provenance": img.meta["provenance"]},
        )
    if motion_picture:
        write_display_image(motion_picture, picture([(f"estimated ({img.meta['method']})", vel)]))


def _say_if_not_distributed(
    method: str, tile: int | str, cap: object, jobs: int, scheduler: str | None
) -> None:
    """Warn that -j / --scheduler go unused where the frame is not solved in tiles
    (only tiles run on Dask), rather than let the user believe the cluster did the work."""
    if jobs <= 1 and scheduler is None:
        return
    from stages.deblur.tiles import MIN_TILE_PX, resolve_tile

    h, w = cap.shape
    size = resolve_tile(tile, (h, w), len(cap.channels)) if method == "vet" else None
    if size is not None and max(h, w) > size:
        return
    given = f"--scheduler {scheduler}" if scheduler is not None else f"-j {jobs}"
    if method != "vet":
        why = f"--method {method} runs in one piece"
    elif max(h, w) <= MIN_TILE_PX:
        why = f"the {w}x{h} frame is solved in one piece (too small for tiles)"
    else:
        why = (
            f"the {w}x{h} frame is solved in one piece (--tile N, {MIN_TILE_PX} <= N < "
            f"{max(h, w)}, solves it in tiles there)"
        )
    log.warning("deblur: %s not used: %s", given, why)
