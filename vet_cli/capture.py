"""vet capture: not built yet."""

from __future__ import annotations

import click

from ._common import command, verbosity_options


@click.command("capture", context_settings={"ignore_unknown_options": True},
               help="Not built yet in this version of vet (see the project's issues).")
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
@verbosity_options
@command("capture")
def cli(args: tuple[str, ...]) -> None:
    from stages.errors import VetError

    raise VetError("this command is not built yet in this version of vet")
