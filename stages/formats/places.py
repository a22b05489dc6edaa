"""Where an output may go: outputs and inputs compared by what they are on disk.

A name is not an identity: ``d/./sub/..``, a symbolic link to ``d`` and ``d`` itself
are one folder, and a hard link is one file under two names. :func:`locate` resolves a
path once, before any work, to its real path (every link followed, ``..`` taken
physically) and the identities (device, inode) of it and of each folder above it;
:func:`check_apart` then refuses an output that *is* an input (the same file, through
any link), *lies inside* an input folder (a capture folder, a batch's ROOT), or
*contains* an input (an output folder above one): the rule every command and each
batch job follows, ``--force`` included.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from ..errors import OutputError

Identity = tuple[int, int]


@dataclass(frozen=True)
class Place:
    """A path resolved once.

    Attributes
    ----------
    role : str
        How the command names it (``"-o"``, ``"CAPTURE"``, ``"ROOT"``), for messages.
    path : str
        The path as given.
    real : str
        Its real path (``os.path.realpath``: links followed, ``..`` taken physically),
        also where it does not exist yet.
    identity : (int, int) or None
        ``(st_dev, st_ino)`` of what it names, None when nothing is there yet.
    above : tuple of (int, int)
        Identities of the existing folders above it on its real path, nearest first.
    """

    role: str
    path: str
    real: str
    identity: Identity | None
    above: tuple[Identity, ...]

    @property
    def exists(self) -> bool:
        return self.identity is not None


def _identity(path: str) -> Identity | None:
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError:  # (a name too long, a loop of links: not an input we can read)
        return None
    return (st.st_dev, st.st_ino)


def locate(path: str | Path, role: str = "") -> Place:
    """Resolve ``path`` (see :class:`Place`); it need not exist."""
    real = os.path.realpath(os.fspath(path))
    above: list[Identity] = []
    parent = os.path.dirname(real)
    while True:
        ident = _identity(parent)
        if ident is not None:
            above.append(ident)
        up = os.path.dirname(parent)
        if up == parent:
            break
        parent = up
    return Place(role, os.fspath(path), real, _identity(real), tuple(above))


def _under(inner: str, outer: str) -> bool:
    """Whether real path ``inner`` lies strictly below real path ``outer``."""
    return inner != outer and inner.startswith(outer.rstrip(os.sep) + os.sep)


def relation(output: Place, source: Place) -> str | None:
    """``"is"``, ``"inside"`` or ``"contains"``: how ``output`` overlaps ``source``;
    None when they are apart. By identity where both exist (hard links, bind mounts),
    by real path where the output does not exist yet."""
    if output.exists and output.identity == source.identity:
        return "is"
    if output.real == source.real:
        return "is"
    if source.exists and source.identity in output.above:
        return "inside"
    if _under(output.real, source.real):
        return "inside"
    if output.exists and output.identity in source.above:
        return "contains"
    if _under(source.real, output.real):
        return "contains"
    return None


def _named(p: Place) -> str:
    return f"{p.role} {p.path}" if p.role else p.path


def overlap_message(output: Place, source: Place, how: str) -> str:
    """One line saying how an output overlaps an input, and what to do."""
    if how == "is":
        same = os.path.normpath(output.path) == os.path.normpath(source.path)
        link = "" if same else " (the same file or folder, through a link or another name)"
        return (
            f"{_named(output)}: is the input {_named(source)}{link}; an output never "
            "replaces an input, --force included: name another output"
        )
    if how == "inside":
        return (
            f"{_named(output)}: lies inside the input {_named(source)}; an output never goes "
            "into an input folder, --force included: name a place outside it"
        )
    return (
        f"{_named(output)}: contains the input {_named(source)}; an output folder never "
        "holds an input, --force included: name a folder apart from the inputs"
    )


def check_apart(outputs: Iterable[Place], inputs: Iterable[Place]) -> None:
    """Refuse any output that is, lies inside or contains an existing input.

    Inputs that do not exist are skipped (the command reports them itself).

    Raises
    ------
    OutputError
        One line naming the output, the input and how they overlap.
    """
    sources = [p for p in inputs if p.exists]
    for out in outputs:
        for src in sources:
            how = relation(out, src)
            if how is not None:
                raise OutputError(overlap_message(out, src, how))
