"""What a batch hands a worker, and what it hands back: plain dataclasses that pickle.

A :class:`CaptureJob` is all pending steps of one capture (:class:`StepCall` each), a
:class:`CaptureResult` what became of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .steps import Step


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
    #: Seconds the capture may run (all its steps), or None for no limit.
    timeout_s: float | None = None
    #: The steps the calls name (what the run's registry held when it was planned, so
    #: that a worker or a capture's own process runs the same ones).
    steps: dict[str, Step] = field(default_factory=dict)


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
