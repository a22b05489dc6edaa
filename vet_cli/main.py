"""The ``vet`` command group. Subcommands load lazily so ``vet --help`` stays fast."""

from __future__ import annotations

import importlib
from typing import Any

import click

from stages import __version__

from ._common import State, verbosity_options

# name -> (module, short help). Modules are imported only when the command runs.
COMMANDS = {
    "simulate": (
        "vet_cli.simulate",
        "Render what a VET rig records from an HDR scene with motion.",
    ),
    "hdr-static": (
        "vet_cli.hdr_static",
        "Static HDR from a capture: I/T corrected for leakage, dark current.",
    ),
    "deblur": (
        "vet_cli.deblur",
        "Jointly estimate the sharp HDR image and the motion of a capture.",
    ),
    "tonemap": (
        "vet_cli.tonemap",
        "Tone-map an HDR image (or picture T and the mask) to PNG/JPEG/TIFF.",
    ),
    "calibrate": (
        "vet_cli.calibrate",
        "Calibrate a rig: homographies, dark, leakage and gain maps.",
    ),
    "capture": (
        "vet_cli.capture",
        "Capture a frame with a rig (real hardware or the emulated 'sim').",
    ),
    "evaluate": (
        "vet_cli.evaluate",
        "Run every method on a scene and motion; table, charts, pictures.",
    ),
    "batch": (
        "vet_cli.batch",
        "Process a folder of captures (hdr-static, deblur, tonemap) in parallel.",
    ),
    "info": ("vet_cli.info", "Print a vet file's metadata as JSON."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, _help = COMMANDS[name]
        return importlib.import_module(module).cli

    def main(self, *args: Any, **kwargs: Any) -> Any:
        # "vet" whether run as the console script or as python -m vet_cli, so that shell
        # completion is always _VET_COMPLETE (eval "$(_VET_COMPLETE=bash_source vet)").
        State.verbosity = 0  # -v/-q count per invocation (several may share a process)
        kwargs.setdefault("prog_name", "vet")
        kwargs.setdefault("complete_var", "_VET_COMPLETE")
        return super().main(*args, **kwargs)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, hlp) for name, (_m, hlp) in COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "-V", "--version", prog_name="vet")
@verbosity_options
def cli() -> None:
    """vet: variable exposure time (VET) HDR imaging.

    A VET rig stops each pixel's exposure once it has gathered enough light. vet
    simulates such rigs, drives real ones, and turns what they record into unblurred
    HDR images. Every command reads and writes files (EXR or npz; '-' for stdin and
    stdout), so commands chain through pipes and Makefiles:

    \b
      vet simulate builtin:interior -o - | vet hdr-static - -o - | vet tonemap - -o out.png

    Exit status: 0 success, 1 runtime failure (one-line message), 2 usage error.
    Existing outputs are replaced only with --force. Shell completion: in ~/.bashrc,
    eval "$(_VET_COMPLETE=bash_source vet)" (zsh_source, fish_source for zsh, fish).
    """
