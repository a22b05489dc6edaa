"""What runs on a worker: all pending steps of one capture, never raising.

:func:`process_capture` is a plain top-level function of plain dataclasses so that Dask
pickles it by reference; workers need ``stages`` importable and the same paths visible.
"""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass, field
from typing import Any

from ..cluster import limit_threads
from ..errors import VetError
from .manifest import file_stat, plan_key, sha256_file, step_key
from .steps import STEPS


@dataclass
class StepCall:
    """One step to run: its input and output files (absolute) and parameters.

    ``input_sha256`` is known for a step whose input is an output that is already up to
    date; otherwise (the capture, or an output made earlier in the same job) the worker
    hashes the input itself.
    """

    step: str
    input: str
    output: str
    output_rel: str
    params: dict[str, Any]
    input_sha256: str | None = None


@dataclass
class CaptureJob:
    """All pending steps of one capture, plus what the worker needs to fingerprint them."""

    rel: str
    capture: str
    calls: list[StepCall]
    capture_sha256: str | None = None
    #: All chosen steps (name, version, params) for the capture's plan key.
    plan: list[tuple[str, str, dict[str, Any]]] = field(default_factory=list)
    limit_threads: bool = True
    #: Every output of the capture (relative to the output folder), pending or not.
    outputs: list[str] = field(default_factory=list)


@dataclass
class CaptureResult:
    """What became of a :class:`CaptureJob`.

    ``steps`` holds a manifest record (see :mod:`stages.batch.manifest`) for each step
    that succeeded; ``failure`` is ``None`` on success, else ``{"step", "reason",
    "key"}`` where ``key`` (the plan key) is set only for failures that are the input's
    fault and will recur unchanged (a :class:`~stages.errors.VetError`), so reruns can
    skip them until the input or the parameters change.
    """

    rel: str
    input: dict[str, Any] = field(default_factory=dict)
    steps: dict[str, dict[str, Any]] = field(default_factory=dict)
    failure: dict[str, Any] | None = None
    elapsed_s: float = 0.0
    cpu_s: float = 0.0
    worker: str = ""
    traceback: str | None = None

    @property
    def ok(self) -> bool:
        return self.failure is None


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def process_capture(job: CaptureJob) -> CaptureResult:
    """Run a capture's pending steps in order; stop at the first failure.

    Never raises: every failure becomes ``result.failure`` with a one-line reason, so one
    bad capture cannot stop the others.
    """
    t0 = time.monotonic()
    c0 = time.process_time()
    if job.limit_threads:
        limit_threads()
    res = CaptureResult(rel=job.rel, worker=f"{os.uname().nodename}:{os.getpid()}")
    current_step = job.calls[0].step if job.calls else ""
    try:
        size, mtime = file_stat(job.capture)
        sha = job.capture_sha256 or sha256_file(job.capture)
        res.input = {"size": size, "mtime_ns": mtime, "sha256": sha}
        key = plan_key(sha, job.plan)
        made: dict[str, str] = {}  # output path -> sha256, for steps chained in this job
        for call in job.calls:
            current_step = call.step
            step = STEPS[call.step]
            if call.input == job.capture:
                in_sha = sha
            else:
                in_sha = call.input_sha256 or made.get(call.input) or sha256_file(call.input)
            t1 = time.monotonic()
            os.makedirs(os.path.dirname(call.output), exist_ok=True)
            try:
                step.run(call.input, call.output, dict(call.params))
            except VetError as exc:
                res.failure = {"step": call.step, "reason": _one_line(exc), "key": key}
                break
            out_sha = sha256_file(call.output)
            made[call.output] = out_sha
            osize, omtime = file_stat(call.output)
            res.steps[call.step] = {
                "key": step_key(call.step, step.version, call.params, in_sha),
                "params": dict(call.params),
                "version": step.version,
                "output": call.output_rel,
                "sha256": out_sha,
                "size": osize,
                "mtime_ns": omtime,
                "elapsed_s": round(time.monotonic() - t1, 4),
            }
    except MemoryError:
        res.failure = {
            "step": current_step,
            "reason": "out of memory (capture too large for this worker)",
            "key": None,
        }
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        res.failure = {
            "step": current_step,
            "reason": _one_line(f"{where}{exc.strerror or exc}"),
            "key": None,
        }
    except Exception as exc:  # a bug: keep going with the other captures
        res.failure = {
            "step": current_step,
            "key": None,
            "reason": _one_line(f"internal error ({type(exc).__name__}: {exc})"),
        }
        res.traceback = traceback.format_exc()
    res.elapsed_s = round(time.monotonic() - t0, 4)
    res.cpu_s = round(time.process_time() - c0, 4)
    return res
