"""The output rule every command follows, checked before any work starts.

- A command never replaces an existing output file, nor writes into an output folder
  that already holds the files it makes (a capture, a report), unless ``--force`` is
  given. ``vet batch`` is the exception: its manifest decides what is out of date.
- ``-`` (standard output) may stand for one output of a command only, and never for a
  terminal: binary data is for a file or a pipe. Two outputs never name one file.
- Names are checked as :func:`stages.formats.io.check_output` checks them (extension,
  existing folder) before the command reads its inputs.
- An output never is, lies inside or contains one of the command's input files or
  folders, through any link, ``..`` or hard link (:mod:`stages.formats.places`), with
  ``--force`` too: exit 1, one line naming both.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import click

from stages.errors import InputError

#: Files a capture folder holds (stages.capture.capture_frame writes them).
CAPTURE_FOLDER_FILES = (
    "capture.exr",
    "capture.npz",
    "capture.json",
    "capture.log",
    "measure_raw.npy",
    "measure_raw.json",
)
#: Files a report folder holds (stages.evaluate.write_report writes them).
REPORT_FOLDER_FILES = (
    "results.csv",
    "results.md",
    "errors.png",
    "contact_sheet.png",
    "exposure_time.png",
    "motion.png",
)


def force_option(f: Callable) -> Callable:
    """``--force``: replace existing outputs (see the module docstring)."""
    return click.option(
        "-f", "--force", is_flag=True, help="Replace existing outputs (refused otherwise)."
    )(f)


@dataclass(frozen=True)
class Output:
    """One output of a command: the option that names it, the path, and its kind.

    ``kind``: ``"data"`` (.exr/.npz), ``"display"`` (.png/.jpg/.tif) or ``"folder"``
    (``holds`` the names of the files the command writes into it). ``parents`` as
    :func:`stages.formats.io.check_output`.
    """

    option: str
    path: str | None
    kind: str = "data"
    holds: tuple[str, ...] = ()
    parents: bool = True


def scene_file(spec: str | None) -> str | None:
    """The file a SCENE argument names (None for ``builtin:NAME``)."""
    return None if spec is None or spec.startswith("builtin:") else spec


def motion_file(spec: str | None) -> str | None:
    """The file a ``--motion field:PATH`` names (None for the other motions)."""
    text = (spec or "").strip()
    return text[len("field:") :] if text.startswith("field:") else None


def profile_file(spec: str | None) -> str | None:
    """The file a ``--rig-profile`` names (None for a profile's name)."""
    from stages.optics import PROFILES

    return None if spec is None or spec in PROFILES else spec


def check_outputs(
    outputs: Iterable[Output],
    force: bool = False,
    inputs: Iterable[tuple[str, str | None]] = (),
) -> None:
    """Apply the output rule to a command's outputs, before it reads anything.

    ``inputs``: ``(role, path)`` of every file or folder the command reads (``None``
    and ``-`` skipped), which no output may be, lie inside or contain.

    Raises
    ------
    click.UsageError
        ``-`` given for more than one output, or for standard output that is a terminal;
        two outputs naming one file (exit 2).
    stages.errors.InputError
        A bad name (extension, missing folder), or an existing output without
        ``force`` (exit 1).
    stages.errors.OutputError
        An output that is, lies inside or contains an input (exit 1).
    """
    from stages.formats.io import check_output
    from stages.formats.places import check_apart, locate

    outputs = [o for o in outputs if o.path is not None]
    to_stdout = [o.option for o in outputs if str(o.path) == "-"]
    if len(to_stdout) > 1:
        raise click.UsageError(
            f"only one output may go to standard output (-); {' and '.join(to_stdout)} both "
            "ask for it: give the others file names"
        )
    if to_stdout and _stdout_is_terminal():
        raise click.UsageError(
            f"{to_stdout[0]} -: standard output is a terminal; redirect it to a file "
            "(> out.exr) or pipe it into another command"
        )
    files = [o for o in outputs if str(o.path) != "-"]
    seen: dict[Path, str] = {}
    for o in files:
        key = Path(o.path).resolve()
        if key in seen:
            raise click.UsageError(
                f"{seen[key]} and {o.option} both name {o.path}: one would replace the other"
            )
        seen[key] = o.option
    for o in files:
        check_output(o.path, o.kind, parents=o.parents)
    check_apart(
        [locate(o.path, o.option) for o in files],
        [locate(path, role) for role, path in inputs if path is not None and str(path) != "-"],
    )
    for o in files:
        if not force:
            refuse_existing(Path(o.path), o.holds if o.kind == "folder" else None)


def refuse_existing(target: Path, holds: tuple[str, ...] | None = None) -> None:
    """InputError if ``target`` exists (a file), or, for a folder (``holds`` given), if
    it already holds one of those files."""
    if holds is None:
        if target.exists() or target.is_symlink():
            raise InputError(f"{target}: already exists; give --force to replace it")
        return
    found = [n for n in holds if (target / n).exists()] if target.is_dir() else []
    if found:
        raise InputError(
            f"{target}: already holds {found[0]}"
            + (f" and {len(found) - 1} more of its outputs" if len(found) > 1 else "")
            + "; give --force to replace them, or choose another folder"
        )


def _stdout_is_terminal() -> bool:
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False
