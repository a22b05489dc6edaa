"""Shared command plumbing: verbosity, logging to stderr, error mapping, progress.

Exit status: 0 success; 1 runtime failure (one line ``vet <command>: error: ...`` on
stderr, traceback only with ``-v``); 2 usage error (click's convention, also for a
:class:`stages.errors.UsageError` that a stage raises); 130, 143 or 129 when SIGINT,
SIGTERM or SIGHUP stopped it (one line ``vet <command>: interrupted``; :mod:`.signals`).
"""

from __future__ import annotations

import functools
import logging
import math
import re
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import click

from . import signals

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


class _Formatter(logging.Formatter):
    """Log lines as error lines are: the spool file of standard input named as such."""

    def format(self, record: logging.LogRecord) -> str:
        return _STDIN_SPOOL.sub("standard input", super().format(record))


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
    handler.setFormatter(_Formatter("vet: %(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
    logging.getLogger("distributed").setLevel(max(level, logging.WARNING))
    logging.getLogger("matplotlib").setLevel(logging.WARNING)


def command(name: str) -> Callable:
    """Wrap a command body: logging, and runtime errors -> one line + exit 1."""

    def deco(f: Callable) -> Callable:
        @functools.wraps(f)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            from stages.errors import UsageError, VetError

            setup_logging()
            try:
                with signals.armed(name):
                    return f(*args, **kwargs)
            except click.exceptions.Exit:
                raise
            except click.ClickException:
                raise
            except UsageError as exc:  # known late (a scene's size): still exit 2
                ctx = click.get_current_context(silent=True)
                if exc.option:
                    raise click.BadParameter(
                        user_message(str(exc)), ctx=ctx, param_hint=f"'{exc.option}'"
                    ) from None
                raise click.UsageError(user_message(str(exc)), ctx=ctx) from None
            except VetError as exc:
                _fail(name, str(exc))
            except KeyboardInterrupt as exc:  # (a signals.Interrupted: SIGTERM, SIGHUP too)
                click.echo(f"vet {name}: interrupted", err=True)
                sys.exit(getattr(exc, "exit_status", 130))
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


#: The file that stages.formats.io.spooled_input makes of standard input: an unlinked
#: one read through /proc/self/fd (Linux), else a named temporary file.
_STDIN_SPOOL = re.compile(
    r"/proc/self/fd/\d+|[^\s:'\"()]*vet-stdin-[A-Za-z0-9_]+(?:\.(?:exr|npz))?"
)


def user_message(message: str) -> str:
    """One line; the temporary file that holds piped-in data is named "standard input"."""
    text = " ".join(str(message).split())
    return _STDIN_SPOOL.sub("standard input", text)


def _fail(name: str, message: str) -> None:
    if State.verbosity > 0:
        traceback.print_exc(file=sys.stderr)
    first = user_message(message)
    click.echo(f"vet {name}: error: {first}", err=True)
    sys.exit(1)


class Progress:
    """Progress of one long step on stderr, fed by a stage's ``progress(done, total)``.

    A terminal gets an updating bar (tqdm); a pipe or a log gets a line at most every
    ``every_s`` seconds and one at the end. Once the first report arrives a ticker keeps
    the display alive between reports (a long first step still shows, its elapsed time
    moving). Steps shorter than ``delay_s`` show nothing, and ``-q`` shows nothing.
    :meth:`note` names the part under way (a bar's label, a line on a pipe).
    ``counts=False`` shows the percentage alone (for a stage whose units are not steps).
    Call :meth:`finish` (or use it as a context manager) at the end.
    """

    def __init__(
        self,
        label: str,
        delay_s: float = 2.0,
        every_s: float = 5.0,
        stream: Any = None,
        counts: bool = True,
        tick_s: float = 1.0,
    ):
        self.label = label
        self.counts = counts
        self.stream = stream if stream is not None else sys.stderr
        self.start = time.monotonic()
        self.delay_s = delay_s
        self.every_s = every_s
        self.tick_s = tick_s
        self.last = -math.inf
        self.shown = False
        self.ended = False
        self.done, self.total = 0, 0
        self.part = ""
        self.bar: Any = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        try:
            self.tty = bool(self.stream.isatty())
        except (AttributeError, ValueError):
            self.tty = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()

    def _quiet(self) -> bool:
        return State.verbosity < 0

    def __call__(self, done: int, total: int) -> None:
        if self._quiet():
            return
        with self._lock:
            self.done, self.total = int(done), max(int(total), 1)
            self._show(time.monotonic(), ticking=False)
        self._start_ticker()

    def note(self, part: str) -> None:
        """Name the part of the step now under way."""
        if self._quiet():
            return
        with self._lock:
            self.part = part
            if self.tty:
                if self.bar is None and time.monotonic() - self.start >= self.delay_s:
                    self._open_bar()
                if self.bar is not None:
                    self.bar.set_description_str(self._desc(), refresh=True)
            else:
                self.last = time.monotonic()
                self._line(f"{part} ({self._amount()})" if self.total else part)
        self._start_ticker()

    def _show(self, now: float, ticking: bool) -> None:
        """Update the display (the lock held)."""
        if self.ended:
            return
        if self.tty:
            if self.bar is None:
                if now - self.start < self.delay_s:
                    return
                self._open_bar()
            if self.bar.total != self.total:
                self.bar.total = self.total
            self.bar.n = min(self.done, self.total)
            self.bar.refresh()
            self.shown = True
            return
        at_end = self.done >= self.total
        if at_end and not ticking:
            if self.shown or now - self.start >= self.delay_s:
                self.ended = True
                self._line(self._amount())
            return
        if now - self.start < self.delay_s or now - self.last < self.every_s:
            return
        if self.done == 0 and not ticking:
            return
        self.last = now
        self._line(f"{self.part} ({self._amount()})" if self.part else self._amount())

    def _start_ticker(self) -> None:
        if self._ticker is None and self.tick_s > 0 and not self._stop.is_set():
            self._ticker = threading.Thread(target=self._tick, name="vet-progress", daemon=True)
            self._ticker.start()

    def _tick(self) -> None:
        while not self._stop.wait(self.tick_s):
            with self._lock:
                if not self._stop.is_set() and self.total:
                    self._show(time.monotonic(), ticking=True)

    def _amount(self) -> str:
        pct = f"{100.0 * self.done / max(self.total, 1):.0f}%"
        return f"{self.done}/{self.total} ({pct})" if self.counts else pct

    def _desc(self) -> str:
        return f"vet: {self.label}" + (f" ({self.part})" if self.part else "")

    def _open_bar(self) -> None:
        from tqdm import tqdm

        self.bar = tqdm(
            total=max(self.total, 1),
            initial=min(self.done, max(self.total, 1)),
            desc=self._desc(),
            file=self.stream,
            leave=True,
            dynamic_ncols=True,
            bar_format="{desc}: {percentage:3.0f}%|{bar}|"
            + (" {n_fmt}/{total_fmt}" if self.counts else "")
            + " [{elapsed}<{remaining}]",
        )
        self.bar.start_t -= time.monotonic() - self.start  # elapsed since the step began
        self.bar.refresh()

    def _line(self, text: str) -> None:
        elapsed = time.monotonic() - self.start
        self.stream.write(f"vet: {self.label}: {text} [{elapsed:.0f} s]\n")
        self.stream.flush()
        self.shown = True

    def finish(self) -> None:
        """Stop the ticker; close the bar (a terminal), or print the last line (a pipe)
        if any was shown."""
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join()
        with self._lock:
            if self.bar is not None:
                self.bar.n = self.bar.total if self.done >= self.total else self.bar.n
                self.bar.close()
                self.bar = None
            elif self.shown and not self.ended and not self._quiet() and self.total:
                self.ended = True
                self._line(self._amount())
