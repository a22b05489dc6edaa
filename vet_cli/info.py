"""vet info: a vet file's metadata as JSON on stdout."""

from __future__ import annotations

import click

from ._common import command, verbosity_options


@click.command(
    "info",
    help="""Print FILE's metadata (rig, units, provenance) and layers as JSON.

FILE is any vet file (capture, HDR image, motion, calibration; EXR or npz), a capture
folder, or - for stdin. A capture's measuring images (one per subframe) are summarised
as one entry (count, time span, statistics over them all), and so are the metadata's
per-image lists; --full lists every layer and prints the metadata as stored. Names are
in natural order (M2 before M10: time order).

\b
Example:
  vet info cap.exr
  vet info cap.exr --full | python -m json.tool > cap-full.json
""",
)
@click.argument("file")
@click.option(
    "--layers/--no-layers", default=True, show_default=True, help="Include per-layer statistics."
)
@click.option(
    "--full",
    is_flag=True,
    help="Every layer (each measuring image) and the metadata's per-image lists in full.",
)
@verbosity_options
@command("info")
def cli(file: str, layers: bool, full: bool) -> None:
    import json

    from stages.info import describe

    click.echo(json.dumps(describe(file, layers=layers, full=full), indent=2))
