"""What runs on a worker: all pending steps of one capture, never raising.

:func:`process_capture` is a plain top-level function of plain dataclasses
(:mod:`.jobs`) so that Dask pickles it by reference; workers need ``stages`` importable
and the same paths visible. A job with a time limit runs in a process of its own
(:mod:`.child`), so that a capture past its limit is stopped and fails alone.
"""

from __future__ import annotations

import os
import time
import traceback
from collections.abc import Callable
from typing import Any

from ..cluster import limit_threads
from ..errors import VetError
from .child import can_isolate, run_limited
from .jobs import CaptureJob, CaptureResult, StepCall
from .manifest import file_stat, plan_key, sha256_file, step_key
from .steps import STEPS, Step

__all__ = ["CaptureJob", "CaptureResult", "StepCall", "process_capture"]


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def process_capture(job: CaptureJob) -> CaptureResult:
    """Run a capture's pending steps in order; stop at the first failure.

    Never raises: every failure becomes ``result.failure`` with a one-line reason, so one
    bad capture cannot stop the others. With ``job.timeout_s`` (on POSIX) the
    steps run in a child process, stopped at the limit (:func:`.child.run_limited`).
    """
    if job.timeout_s is not None and can_isolate():
        return run_limited(run_steps, job, job.timeout_s)
    return run_steps(job)


def run_steps(job: CaptureJob, on_step: Callable[[str], None] | None = None) -> CaptureResult:
    """Run the job's steps here (``on_step(name)`` as each starts); never raises."""
    if job.limit_threads:
        limit_threads()
    t0 = time.monotonic()
    c0 = time.process_time()
    res = CaptureResult(rel=job.rel, worker=f"{os.uname().nodename}:{os.getpid()}")
    current = [job.calls[0].step if job.calls else ""]

    def starting(step: str) -> None:
        current[0] = step
        if on_step is not None:
            on_step(step)

    try:
        _steps(job, res, starting)
    except MemoryError:
        res.failure = _failure(current[0], "out of memory (capture too large for this worker)")
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        res.failure = _failure(current[0], f"{where}{exc.strerror or exc}")
    except Exception as exc:  # a bug: keep going with the other captures
        res.failure = _failure(current[0], f"internal error ({type(exc).__name__}: {exc})")
        res.traceback = traceback.format_exc()
    res.elapsed_s = round(time.monotonic() - t0, 4)
    res.cpu_s = round(time.process_time() - c0, 4)
    return res


def _failure(step: str, reason: str, key: str | None = None) -> dict[str, Any]:
    return {"step": step, "reason": _one_line(reason), "key": key}


def _steps(job: CaptureJob, res: CaptureResult, starting: Callable[[str], None]) -> None:
    """The steps in order, each recorded in ``res.steps``; the first failure that is
    the input's fault (a VetError) is recorded with the plan key and ends the job."""
    size, mtime = file_stat(job.capture)
    sha = job.capture_sha256 or sha256_file(job.capture)
    res.input = {"size": size, "mtime_ns": mtime, "sha256": sha}
    key = plan_key(sha, job.plan)
    made: dict[str, str] = {}  # output path -> sha256, for steps chained in this job
    for call in job.calls:
        starting(call.step)
        if call.input == job.capture:
            in_sha = sha
        else:
            in_sha = call.input_sha256 or made.get(call.input) or sha256_file(call.input)
        t1 = time.monotonic()
        os.makedirs(os.path.dirname(call.output), exist_ok=True)
        try:
            _step(job, call.step).run(call.input, call.output, dict(call.params))
        except VetError as exc:
            res.failure = _failure(call.step, str(exc), key)
            return
        made[call.output] = sha256_file(call.output)
        res.steps[call.step] = _step_record(
            _step(job, call.step), call, in_sha, made[call.output], t1
        )


def _step(job: CaptureJob, name: str) -> Step:
    return job.steps.get(name) or STEPS[name]


def _step_record(
    step: Step, call: StepCall, in_sha: str, out_sha: str, t1: float
) -> dict[str, Any]:
    """The manifest's record of a step that made ``call.output``."""
    osize, omtime = file_stat(call.output)
    return {
        "key": step_key(call.step, step.version, call.params, in_sha),
        "params": dict(call.params),
        "version": step.version,
        "output": call.output_rel,
        "sha256": out_sha,
        "size": osize,
        "mtime_ns": omtime,
        "elapsed_s": round(time.monotonic() - t1, 4),
    }
