"""The ``vet`` console script: signal handling first, then the command line.

The handlers go in before click and the stages are imported (a few hundred
milliseconds), so that Ctrl-C at any moment ends with one line (:mod:`.signals`).
"""

from __future__ import annotations

from . import signals


def main() -> None:
    signals.install()
    from .main import cli

    cli(prog_name="vet")
