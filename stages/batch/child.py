"""One capture in a process of its own, within a time limit.

:func:`run_limited` runs a capture's steps in a child process, so that a capture that
runs past its limit, wedged in Python or in a native call that never returns, is
stopped and fails alone while the rest of the batch goes on; a capture that crashes its
process (a segmentation fault, the out-of-memory killer) fails alone as well, and its
memory goes back to the system when it ends.

The children come from :mod:`multiprocessing`'s fork server: one clean process per
parent (a Dask worker, or ``vet batch -j 1`` itself), started once with the steps'
modules imported and no thread pool ever used, from which each child is forked in
milliseconds. (Forking the parent itself would be as quick but not safe: a child of a
process whose OpenImageIO or OpenEXR thread pool has run waits forever on threads that
did not follow it across the fork.) Dask's worker processes are daemonic, which
multiprocessing takes to forbid children; a capture's child ends with its parent (it
watches it), so the flag is lifted while one starts (:func:`_children_allowed`).

The child tells the parent each step as it starts and then its
:class:`~stages.batch.jobs.CaptureResult`. At the limit the parent sends SIGTERM (the
child unwinds: its temporary files are removed), then SIGKILL after :data:`GRACE_S`,
and removes the temporary outputs the child left (``.vet-tmp-PID-*`` in the job's
output folders). Children start with SIGINT and SIGHUP blocked (the terminal sends them
to the whole process group: the parent decides) and end themselves (SIGTERM to
themselves) when their parent closes a pipe it holds for them: when it is done with
them, or dies.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..cluster import group_signals_held
from ..formats.io import temporary_prefix
from .jobs import CaptureJob, CaptureResult

#: Seconds between SIGTERM and SIGKILL for a child past its limit.
GRACE_S = 5.0
#: Modules the fork server imports before forking, with those of the first job's steps
#: (their modules and their functions').
PRELOAD = ("stages.batch.worker", "stages.formats", "stages.formats.images", "stages.provenance")

Runner = Callable[[CaptureJob, Callable[[str], None]], CaptureResult]


class CaptureStopped(BaseException):
    """SIGTERM in a capture's process: unwind (temporary files removed), then end."""


def can_isolate() -> bool:
    """Whether captures can run in children of a fork server here (POSIX)."""
    return "forkserver" in multiprocessing.get_all_start_methods()


def run_limited(run: Runner, job: CaptureJob, timeout_s: float) -> CaptureResult:
    """``run(job, on_step)`` in a child process; its result, or a failed one when the
    child ran past ``timeout_s`` seconds or ended without one. An exception here (the
    parent interrupted) stops the child first."""
    ctx = multiprocessing.get_context("forkserver")
    steps = job.steps.values()
    ctx.set_forkserver_preload(
        [*PRELOAD, *(s.module for s in steps), *(s.run.__module__ for s in steps)]
    )
    receive, send = ctx.Pipe(duplex=False)
    alive, alive_here = ctx.Pipe(duplex=False)  # (closed here: the child ends itself)
    child = ctx.Process(target=_child, args=(run, job, send, alive), name=f"vet-capture:{job.rel}")
    try:
        with _children_allowed(), group_signals_held():
            child.start()  # (a signal held meanwhile is raised as the block ends)
        send.close()
        alive.close()
        messages, finished = _receive(receive, time.monotonic() + timeout_s)
    except BaseException:
        if child.pid is not None:
            _stop(child, job)
        raise
    finally:
        for conn in (send, alive, receive, alive_here):
            conn.close()
    steps = [m[1] for m in messages if m[0] == "step"]
    result = next((m[1] for m in messages if m[0] == "result"), None)
    if not finished:
        _stop(child, job)
        return _failed(job, steps, f"timed out after {timeout_s:g} s (the batch's --timeout)")
    child.join()
    if isinstance(result, CaptureResult):
        return result
    _sweep(child.pid, job)
    how = child.exitcode
    ended = f"killed by signal {-how}" if how is not None and how < 0 else f"exit status {how}"
    return _failed(job, steps, f"the capture's process ended without a result ({ended})")


@contextlib.contextmanager
def _children_allowed() -> Iterator[None]:
    """Lift multiprocessing's daemonic flag from this process while a child starts."""
    config = multiprocessing.current_process()._config  # (no public way to ask)
    daemon = config.pop("daemon", None)
    try:
        yield
    finally:
        if daemon is not None:
            config["daemon"] = daemon


def _failed(job: CaptureJob, steps: list[str], reason: str) -> CaptureResult:
    step = steps[-1] if steps else (job.calls[0].step if job.calls else "")
    return CaptureResult(rel=job.rel, failure={"step": step, "reason": reason, "key": None})


def _child(run: Runner, job: CaptureJob, send: Any, alive: Any) -> None:
    """The child's life: the steps and their result sent; quiet when stopped or when
    its parent is gone (``alive`` ends: the parent closed it, or died)."""
    try:
        for name in ("SIGINT", "SIGHUP"):  # (the fork server restores Python's SIGINT)
            if hasattr(signal, name):
                signal.signal(getattr(signal, name), signal.SIG_IGN)
        signal.signal(signal.SIGTERM, _stopped)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
        threading.Thread(target=_watch_parent, args=(alive,), daemon=True).start()
        try:
            result = run(job, lambda step: send.send(("step", step)))
            send.send(("result", result))
        finally:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # (done: nothing more to unwind)
    except (CaptureStopped, OSError):  # stopped, or the parent is gone (a broken pipe)
        pass


def _stopped(signum: int, frame: object) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # (once: let the unwinding finish)
    raise CaptureStopped()


def _watch_parent(alive: Any) -> None:
    """Stop this child when its parent closes ``alive`` (done, or gone)."""
    with contextlib.suppress(EOFError, OSError):
        while True:
            alive.recv()
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(GRACE_S)
    os._exit(1)


def _receive(conn: Any, deadline: float) -> tuple[list[tuple], bool]:
    """Messages until the child closes its end (True) or ``deadline`` passes (False)."""
    messages: list[tuple] = []
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return messages, False
        if not conn.poll(left):
            continue
        try:
            messages.append(conn.recv())
        except (EOFError, OSError):
            return messages, True


def _stop(child: Any, job: CaptureJob) -> None:
    """SIGTERM, SIGKILL after :data:`GRACE_S`, then remove what the child left."""
    with contextlib.suppress(OSError):
        child.terminate()
    child.join(GRACE_S)
    if child.exitcode is None:
        with contextlib.suppress(OSError):
            child.kill()
        child.join()
    _sweep(child.pid, job)


def _sweep(pid: int | None, job: CaptureJob) -> None:
    """Remove the temporary outputs process ``pid`` left in the job's output folders."""
    if pid is None:
        return
    prefix = temporary_prefix(pid)
    for folder in {Path(c.output).parent for c in job.calls}:
        with contextlib.suppress(OSError):
            for p in folder.iterdir():
                if p.name.startswith(prefix):
                    with contextlib.suppress(OSError):
                        p.unlink()
