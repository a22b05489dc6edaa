"""vet info: a vet file's metadata as JSON on stdout."""

from __future__ import annotations

import click

from ._common import command, verbosity_options


@click.command(
    "info",
    help="""Print FILE's metadata (rig, units, provenance) and layers as JSON.

FILE is any vet file (capture, HDR image, motion, calibration; EXR or npz), a capture
folder, or - for stdin.

\b
Example:
  vet info cap.exr | python -m json.tool
""",
)
@click.argument("file")
@click.option(
    "--layers/--no-layers", default=True, show_default=True, help="Include per-layer statistics."
)
@verbosity_options
@command("info")
def cli(file: str, layers: bool) -> None:
    import json

    from stages.info import describe

    click.echo(json.dumps(describe(file, layers=layers), indent=2, sort_keys=True))
