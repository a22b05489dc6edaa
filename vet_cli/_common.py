"""Shared command plumbing: verbosity, logging to stderr, error mapping, progress.

Exit status: 0 success; 1 runtime failure (one line ``vet <command>: error: ...`` on
stderr, traceback only with ``-v``); 2 usage error (click's convention).
"""

from __future__ import annotations

import functools
import logging
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

import click

log = logging.getLogger("vet")


class State:
    verbosity = 0


def _set_verbosity(ctx: click.Context, param: click.Parameter, value: int) -> int:
    if value:
        State.verbosity += value if param.name == "verbose" else -value
    return value


def verbosity_options(f: Callable) -> Callable:
    """``-v`` (repeatable: more detail, tracebacks) and ``-q`` (warnings only)."""
    f = click.option(
        "-q",
        "--quiet",
        count=True,
        expose_value=False,
        callback=_set_verbosity,
        help="Less output on stderr (warnings and errors only).",
    )(f)
    f = click.option(
        "-v",
        "--verbose",
        count=True,
        expose_value=False,
        callback=_set_verbosity,
        help="More output on stderr; -v also shows tracebacks on errors.",
    )(f)
    return f


def setup_logging() -> None:
    level = (
        logging.INFO
        if State.verbosity == 0
        else logging.DEBUG
        if State.verbosity > 0
        else logging.WARNING
    )
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("vet: %(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
    logging.getLogger("distributed").setLevel(max(level, logging.WARNING))
    logging.getLogger("matplotlib").setLevel(logging.WARNING)


def command(name: str) -> Callable:
    """Wrap a command body: logging, and runtime errors -> one line + exit 1."""

    def deco(f: Callable) -> Callable:
        @functools.wraps(f)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            from stages.errors import VetError

            setup_logging()
            try:
                return f(*args, **kwargs)
            except click.exceptions.Exit:
                raise
            except click.ClickException:
                raise
            except VetError as exc:
                _fail(name, str(exc))
            except KeyboardInterrupt:
                click.echo(f"vet {name}: interrupted", err=True)
                sys.exit(130)
            except MemoryError:
                _fail(name, "out of memory (input too large for this machine)")
            except OSError as exc:
                where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
                _fail(name, f"{where}{exc.strerror or exc}")
            except Exception as exc:  # a bug: still one line, traceback with -v
                _fail(
                    name,
                    f"internal error ({type(exc).__name__}: {exc}); rerun with -v for the traceback",
                )

        return wrapper

    return deco


def _fail(name: str, message: str) -> None:
    if State.verbosity > 0:
        traceback.print_exc(file=sys.stderr)
    first = " ".join(str(message).split())
    click.echo(f"vet {name}: error: {first}", err=True)
    sys.exit(1)


class Progress:
    """Progress on stderr for work that takes more than a second; silent with -q."""

    def __init__(self, label: str, delay_s: float = 1.0, every_s: float = 0.5):
        self.label = label
        self.start = time.monotonic()
        self.delay_s = delay_s
        self.every_s = every_s
        self.last = 0.0
        self.shown = False
        self.tty = sys.stderr.isatty()

    def __call__(self, done: int, total: int) -> None:
        if State.verbosity < 0:
            return
        now = time.monotonic()
        if now - self.start < self.delay_s or (now - self.last < self.every_s and done < total):
            return
        self.last = now
        self.shown = True
        pct = 100.0 * done / max(total, 1)
        msg = f"vet: {self.label}: {done}/{total} ({pct:.0f}%)"
        if self.tty:
            sys.stderr.write("\r" + msg + ("\n" if done >= total else ""))
        else:
            sys.stderr.write(msg + "\n")
        sys.stderr.flush()

    def finish(self) -> None:
        if self.shown and self.tty:
            sys.stderr.write("\n")
