"""How a signal ends a ``vet`` process: one line, status 128 + its number, nothing left.

SIGINT (Ctrl-C), SIGTERM and SIGHUP end a command with ``vet <command>: interrupted``
on standard error and exit status 130, 143 or 129, at any moment: no traceback, and
every temporary file the process made is removed (atomic outputs, a spool of standard
input). The console script installs the handlers first thing (:func:`install`),
before click and the rest are imported:

- until a command's body runs (:func:`armed`), a signal ends the process at once: the
  line, then ``os._exit`` (nothing has been written yet);
- while it runs, the first signal raises :class:`Interrupted` in the main thread, so
  that every ``finally`` and ``with`` unwinds (temporary files removed, a Dask cluster
  closed, a batch's lock released) and the command's wrapper prints the line;
- a second signal while that unwinds ends the process at once, after removing the
  temporary files still registered (:func:`stages.formats.io.remove_live_temporaries`).

This module imports only the standard library: it runs before anything else.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Iterator

#: The signals that end a command cleanly.
SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


class Interrupted(KeyboardInterrupt):
    """A command stopped by ``signum`` (a KeyboardInterrupt, so that code catching
    ``Exception`` lets it through)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


class _State:
    installed = False
    armed = False
    unwinding = False
    name = ""


def _command_name(argv: list[str]) -> str:
    """The subcommand named on the command line (the first word that is no option)."""
    for word in argv[1:]:
        if not word.startswith("-"):
            return word if word.replace("-", "").isalpha() else ""
    return ""


def _line() -> bytes:
    who = f"vet {_State.name}" if _State.name else "vet"
    return f"{who}: interrupted\n".encode()


def _exit_now(signum: int) -> None:
    io = sys.modules.get("stages.formats.io")  # (imported only if a command got that far)
    if io is not None:
        with contextlib.suppress(Exception):
            io.remove_live_temporaries()
    with contextlib.suppress(OSError):
        os.write(2, _line())
    os._exit(128 + signum)


def _handler(signum: int, frame: object) -> None:
    if _State.armed and not _State.unwinding:
        _State.unwinding = True
        raise Interrupted(signum)
    _exit_now(signum)


def install(argv: list[str] | None = None) -> None:
    """Install the handlers (the console script's first step; main thread only)."""
    _State.name = _command_name(sys.argv if argv is None else argv)
    for signum in SIGNALS:
        signal.signal(signum, _handler)
    _State.installed = True


@contextlib.contextmanager
def armed(name: str) -> Iterator[None]:
    """While a command's body runs, a signal raises :class:`Interrupted` (where the
    handlers are installed: in the ``vet`` process, not in a program calling a command
    in-process, whose own handling is left alone)."""
    if not _State.installed:
        yield
        return
    _State.name, _State.armed, _State.unwinding = name, True, False
    try:
        yield
    finally:
        _State.armed = False
