"""vet tonemap: display pictures of HDR images, exposure-time maps and masks."""

from __future__ import annotations

import os

import click

from ._common import command, verbosity_options
from .outputs import Output, check_outputs, force_option
from .params import STOPS, positive

OPERATORS = ["log", "reinhard", "drago", "mantiuk"]


@click.command(
    "tonemap",
    help="""Tone-map INPUT (an HDR image from hdr-static or deblur; - for stdin) to OUT.

The extension of OUT picks the format: .png (8 or 16 bits), .jpg (8), .tif (8 or 16);
- writes PNG to stdout. --operator log is the VET paper's global logarithmic mapping;
reinhard, drago and mantiuk are OpenCV's. --exposure-time-map pictures the exposure
time image T instead (INPUT may then also be a capture or a capture folder), --mask
the quality mask.

\b
Example:
  vet tonemap hdr.exr -o hdr.png --operator reinhard
  vet tonemap cap.exr --exposure-time-map -o T.png
""",
)
@click.argument("input")
@click.option(
    "-o", "--output", required=True, help="Picture file (.png/.jpg/.tif) or - (PNG on stdout)."
)
@click.option("--operator", type=click.Choice(OPERATORS), default="log", show_default=True)
@click.option(
    "--exposure", type=STOPS, default=0.0, show_default=True, help="Exposure shift in stops."
)
@click.option(
    "--gamma", type=positive(), default=None, help="Display gamma, > 0 [operator's default]."
)
@click.option(
    "--bits",
    type=click.Choice(["8", "16"]),
    default="8",
    show_default=True,
    help="Bits per channel (16: PNG or TIFF only).",
)
@click.option(
    "--exposure-time-map", "t_map", is_flag=True, help="Picture T in false colour with a scale."
)
@click.option("--mask", is_flag=True, help="Picture the quality mask with a legend.")
@force_option
@verbosity_options
@command("tonemap")
def cli(
    input: str,
    output: str,
    operator: str,
    exposure: float,
    gamma: float | None,
    bits: str,
    t_map: bool,
    mask: bool,
    force: bool,
) -> None:
    from stages.errors import FormatError, InputError
    from stages.formats import resolve_capture_path
    from stages.formats.images import write_display_image
    from stages.formats.layered import read_layered
    from stages.rig import RigParams

    if t_map and mask:
        raise click.UsageError("give --exposure-time-map or --mask, not both")
    what = "T" if t_map else "mask" if mask else None
    check_outputs([Output("-o", output, "display")], force, inputs=[("INPUT", input)])
    if input != "-" and os.path.isdir(input):
        input = resolve_capture_path(input)  # a capture folder: its capture
        if what != "T":
            raise InputError(
                f"{input}: is a capture, not an HDR image; run hdr-static or deblur on "
                "its folder first (or use --exposure-time-map)"
            )
    name = "standard input" if input == "-" else input
    data = read_layered(input)
    kind = data.meta.get("kind")
    if what == "T":
        from stages.falsecolor import render_exposure_time_map

        if "T" not in data.layers or not isinstance(data.meta.get("rig"), dict):
            raise FormatError(f"{name}: has no exposure time image (T) with its rig parameters")
        rig = RigParams.from_dict(data.meta["rig"])
        picture = render_exposure_time_map(data.layers["T"][:, :, 0], rig.frame_s, rig.subframe_s)
        write_display_image(output, picture, bits=8)
        return
    if kind == "capture":
        raise InputError(
            f"{name}: is a capture, not an HDR image; run hdr-static or deblur first "
            "(or use --exposure-time-map)"
        )
    if kind not in (None, "hdr"):
        raise InputError(f"{name}: is a {kind} file, not an HDR image")
    from stages.formats.hdr import MASK_CODES, HDRImage, _foreign_to_hdr

    img = HDRImage.from_layered(data if kind == "hdr" else _foreign_to_hdr(data, name), name)
    if what == "mask":
        from stages.falsecolor import render_mask

        if img.mask is None:
            raise FormatError(f"{name}: has no quality mask")
        write_display_image(output, render_mask(img.mask, MASK_CODES), bits=8)
        return
    if img.meta.get("display_referred"):
        click.echo(f"vet tonemap: warning: {name} is already display-referred", err=True)
    from stages.tonemap import tonemap

    display = tonemap(img.radiance, operator=operator, exposure=exposure, gamma=gamma)
    write_display_image(output, display, bits=int(bits))
