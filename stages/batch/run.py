"""Running a batch: resolve the places, discover, plan against the manifest, execute,
record, summarise.

Execution is in-process for one job at a time without a scheduler, else on Dask
distributed (:mod:`.executors`); each capture within its time limit (:mod:`.child`).
Results stream back as they complete and the manifest is rewritten atomically after
each batch of completions, so a run killed at any moment (even by ``kill -9``) loses at
most the captures in flight; their outputs are either complete or absent (every writer
is atomic), and the next run redoes exactly what is missing.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..cluster import parse_scheduler_address
from ..errors import InputError, UsageError
from ..formats.io import atomic_output
from ..formats.places import Place, check_apart, locate
from .discover import CaptureUnit, IgnoredFile, discover_captures
from .executors import results_dask, results_in_process
from .jobs import CaptureJob, CaptureResult
from .manifest import Manifest, now_iso, output_lock, remove_stale_temporaries
from .plan import Planner, check_names, check_places, output_names
from .steps import check_available, parse_steps, resolve_params

log = logging.getLogger("vet.batch")

SUMMARY_NAME = "batch-summary.json"
#: Exit status when every capture is done or up to date.
EXIT_OK = 0
#: Exit status when the run completed but some captures failed (see the summary).
EXIT_SOME_FAILED = 3
#: Seconds to wait for an existing cluster's first worker.
CONNECT_TIMEOUT_S = 30.0

EventHandler = Callable[[str, dict[str, Any]], None]


@dataclass(frozen=True)
class BatchOptions:
    """What a batch runs and how (``vet batch``'s options).

    Attributes
    ----------
    steps : str or list of str, optional
        Steps to run (:data:`~stages.batch.steps.STEPS`), comma-separated; default
        ``hdr-static,tonemap``.
    params : mapping, optional
        ``{step: {parameter: value}}`` overriding the steps' defaults.
    jobs : int
        Worker processes for the embedded cluster; 1 without ``scheduler`` runs in
        this process, without Dask.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://HOST:PORT``); ``jobs`` is then
        ignored.
    force : bool
        Rerun every step of every capture, whatever the manifest says.
    retry_failed : bool
        Retry captures whose failure was recorded for the same input and parameters.
    dry_run : bool
        Plan only: report what would run, write nothing.
    timeout : float, ``"auto"`` or None
        Seconds each capture (all its steps) may run before it is stopped and fails
        alone; ``"auto"`` derives them from the capture's size
        (:func:`~stages.batch.plan.capture_timeout`); None for no limit.
    """

    steps: str | list[str] | tuple[str, ...] | None = None
    params: Mapping[str, Mapping[str, Any]] | None = None
    jobs: int = 1
    scheduler: str | None = None
    force: bool = False
    retry_failed: bool = False
    dry_run: bool = False
    timeout: float | str | None = "auto"


@dataclass
class BatchReport:
    """The result of :func:`run_batch`.

    Attributes
    ----------
    summary : dict
        What ``OUT/batch-summary.json`` holds.
    exit_status : int
        :data:`EXIT_OK` or :data:`EXIT_SOME_FAILED`.
    failures : list of dict
        ``{"capture", "step", "reason", "cached"}`` per failed capture.
    """

    summary: dict[str, Any]
    exit_status: int
    failures: list[dict[str, Any]] = field(default_factory=list)


def run_batch(
    root: str | Path,
    out: str | Path,
    options: BatchOptions | None = None,
    on_event: EventHandler | None = None,
) -> BatchReport:
    """Process every capture under ``root`` into ``out``, skipping what is up to date.

    Parameters
    ----------
    root : str or Path
        Folder searched recursively for capture files and capture folders
        (:func:`~stages.batch.discover.discover_captures`).
    out : str or Path
        Output folder, created if needed, apart from ``root`` (neither is, holds or lies
        inside the other, through any link); mirrors ``root``'s layout: ``root/d/a.exr``
        gives ``out/d/a.hdr.exr``, ``out/d/a.deblur.exr``, ``out/d/a.png``; the capture
        folder ``root/d/x/`` gives ``out/d/x.hdr.exr`` and so on.
    options : BatchOptions, optional
        Steps, parameters, parallelism, reruns, time limit.
    on_event : callable, optional
        ``on_event(kind, data)`` for progress: ``"plan"`` (counts), ``"start"``
        (executor), ``"result"`` (``{"outcome", "done", "total"}``).

    Returns
    -------
    BatchReport

    Raises
    ------
    StepSpecError, UsageError
        Unknown step or parameter, a malformed scheduler address or time limit.
    VetError
        The run itself cannot proceed, before any capture runs: ``root`` is not a
        folder; ``out`` is, holds or lies inside ``root``; two captures would write one
        output (:class:`~stages.batch.plan.PlanError`); a chosen step is not available;
        the output folder is locked by another run; the scheduler cannot be reached.
        Failures of single captures never raise; they are in the report.
    """
    t_start = time.monotonic()
    opts = options or BatchOptions()
    root_place, out_place = _places(root, out)
    names = parse_steps(opts.steps)
    params = resolve_params(names, opts.params)
    check_available(names)
    _check_options(opts)
    run = _Run(root_place, out_place, names, params, opts, on_event, t_start)
    found = run.discover()  # (refused here, nothing is written: not even OUT)
    if opts.dry_run:
        return run.go(*found)
    try:
        Path(out_place.real).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    with output_lock(out_place.real):
        return run.go(*found)


def _places(root: str | Path, out: str | Path) -> tuple[Place, Place]:
    """ROOT and OUT resolved once; refused when not apart."""
    root_place, out_place = locate(root, "ROOT"), locate(out, "-o")
    if not Path(root_place.real).is_dir():
        raise InputError(f"{root}: not a folder")
    check_apart([out_place], [root_place])
    return root_place, out_place


def _check_options(opts: BatchOptions) -> None:
    if opts.jobs < 1:
        raise UsageError(f"-j must be at least 1, not {opts.jobs}", "-j")
    if opts.scheduler is not None:
        parse_scheduler_address(opts.scheduler)
    t = opts.timeout
    if t not in (None, "auto") and not (
        isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t) and t > 0
    ):
        raise UsageError(f"{t!r}: give a number of seconds > 0, auto or none", "--timeout")


class _Run:
    """One run, with the lock held: its steps in the order they happen."""

    def __init__(
        self,
        root: Place,
        out: Place,
        names: list[str],
        params: dict[str, dict[str, Any]],
        opts: BatchOptions,
        on_event: EventHandler | None,
        t_start: float,
    ):
        self.root, self.out = Path(root.real), Path(out.real)
        self.root_shown, self.out_place = root.path, out
        self.names, self.params, self.opts = names, params, opts
        self.emit = on_event or (lambda kind, data: None)
        self.timing = {"start": t_start}
        self.info: dict[str, Any] = {"executor": "none (nothing to do)", "startup_s": 0.0}
        self.outcomes: dict[str, dict[str, Any]] = {}

    def discover(self) -> tuple[list[CaptureUnit], list[IgnoredFile], dict[str, list[str]]]:
        """The captures, the files ignored and each capture's outputs, checked: names
        distinct, places apart from the inputs (before anything is written)."""
        units, ignored = discover_captures(self.root)
        outputs = output_names(units, self.root.name, self.names)
        check_names(outputs, self.root_shown)
        check_places(units, outputs, self.out_place)
        self.timing["discover"] = time.monotonic()
        return units, ignored, outputs

    def go(
        self,
        units: list[CaptureUnit],
        ignored: list[IgnoredFile],
        outputs: dict[str, list[str]],
    ) -> BatchReport:
        started = now_iso()
        manifest = self._manifest()
        jobs = self._plan(units, ignored, outputs, manifest)
        self.timing["plan"] = time.monotonic()
        if self.opts.dry_run:
            self._would_run(jobs)
        elif jobs:
            self._execute(jobs, {u.rel: u for u in units}, manifest)
        elif manifest.captures:
            manifest.save(self.root)  # stats refreshed by the fast path
        return self._report(units, ignored, started)

    def _manifest(self) -> Manifest:
        if not self.opts.dry_run:
            n_tmp = remove_stale_temporaries(self.out)
            if n_tmp:
                log.debug("batch: removed %d temporary files left by an interrupted run", n_tmp)
        manifest = Manifest.load(self.out)
        if manifest.load_warning:
            log.warning("%s", manifest.load_warning)
        return manifest

    def _plan(
        self,
        units: list[CaptureUnit],
        ignored: list[IgnoredFile],
        outputs: dict[str, list[str]],
        manifest: Manifest,
    ) -> list[CaptureJob]:
        planner = Planner(
            self.out, self.names, self.params, self.opts.retry_failed, self.opts.timeout
        )
        jobs: list[CaptureJob] = []
        for u in units:
            rec = None if self.opts.force else manifest.captures.get(u.rel)
            job, outcome = planner.unit(u, outputs[u.rel], rec)
            if job is not None:
                jobs.append(job)
            else:
                self.outcomes[u.rel] = outcome
        n_cached = sum(1 for o in self.outcomes.values() if o["status"] == "failed")
        self.emit(
            "plan",
            {
                "captures": len(units),
                "to_run": len(jobs),
                "up_to_date": len(self.outcomes) - n_cached,
                "failed_before": n_cached,
                "ignored": len(ignored),
            },
        )
        return jobs

    def _would_run(self, jobs: list[CaptureJob]) -> None:
        for j in jobs:
            self.outcomes[j.rel] = {
                "capture": j.rel,
                "status": "would-run",
                "cached": False,
                "steps": [c.step for c in j.calls],
                "outputs": [c.output_rel for c in j.calls],
            }

    def _results(self, jobs: list[CaptureJob]) -> Iterator[list[CaptureResult]]:
        if self.opts.scheduler is None and self.opts.jobs <= 1:
            self.info["executor"] = "in-process (-j 1)"
            self.info["process_started"] = time.monotonic()
            return results_in_process(jobs)
        n = min(self.opts.jobs, len(jobs))
        return results_dask(jobs, n, self.opts.scheduler, self.info, CONNECT_TIMEOUT_S)

    def _execute(
        self, jobs: list[CaptureJob], by_rel: dict[str, CaptureUnit], manifest: Manifest
    ) -> None:
        """Run the jobs, recording each result as it comes; on an interrupt, what is
        recorded stays and the temporary outputs go."""
        done, total = len(self.outcomes), len(by_rel)
        outputs = {j.rel: j.outputs for j in jobs}
        try:
            for k, burst in enumerate(self._results(jobs)):
                if k == 0:
                    self.emit("start", {k: v for k, v in self.info.items()})
                for res in burst:
                    _record(manifest, by_rel[res.rel], self.root, res)
                    done += 1
                    self.outcomes[res.rel] = _outcome(res, outputs[res.rel])
                    if res.traceback:
                        log.debug("batch: %s: traceback from worker:\n%s", res.rel, res.traceback)
                    self.emit(
                        "result", {"outcome": self.outcomes[res.rel], "done": done, "total": total}
                    )
                manifest.save(self.root)
        except KeyboardInterrupt:
            remove_stale_temporaries(self.out)  # (the lock is held: all are this run's)
            raise
        started = self.info.pop("process_started", time.monotonic())
        self.info["process_s"] = round(time.monotonic() - started, 3)

    def _report(
        self, units: list[CaptureUnit], ignored: list[IgnoredFile], started: str
    ) -> BatchReport:
        ordered = [self.outcomes[u.rel] for u in units]
        failures = [
            {k: o.get(k) for k in ("capture", "step", "reason", "cached")}
            for o in ordered
            if o["status"] == "failed"
        ]
        exit_status = EXIT_SOME_FAILED if failures else EXIT_OK
        summary = {
            "format": "vet-batch-summary",
            "vet_version": __version__,
            "root": str(self.root),
            "output": str(self.out),
            "steps": self.names,
            "params": self.params,
            "timeout": self.opts.timeout,
            "started": started,
            "finished": now_iso(),
            "dry_run": self.opts.dry_run,
            "exit_status": exit_status,
            "counts": _counts(ordered, failures, ignored),
            "timing_s": self._timings(),
            "executor": self.info.get("executor"),
            "workers": self.info.get(
                "workers", 1 if self.info.get("executor", "").startswith("in-process") else 0
            ),
            "failures": failures,
            "captures": ordered,
            "ignored": [{"path": i.rel, "reason": i.reason} for i in ignored],
        }
        if not self.opts.dry_run:
            with atomic_output(self.out / SUMMARY_NAME, suffix=".json") as tmp:
                tmp.write_text(json.dumps(summary, indent=1, default=str))
        return BatchReport(summary=summary, exit_status=exit_status, failures=failures)

    def _timings(self) -> dict[str, float]:
        t = self.timing
        return {
            "discover": round(t["discover"] - t["start"], 3),
            "plan": round(t["plan"] - t["discover"], 3),
            "startup": self.info.get("startup_s", 0.0),
            "process": self.info.get("process_s", 0.0),
            "total": round(time.monotonic() - t["start"], 3),
        }


def _counts(
    ordered: list[dict[str, Any]], failures: list[dict[str, Any]], ignored: list[IgnoredFile]
) -> dict[str, int]:
    def n(status: str) -> int:
        return sum(1 for o in ordered if o["status"] == status)

    return {
        "captures": len(ordered),
        "done": n("done"),
        "up_to_date": n("up-to-date"),
        "failed": len(failures),
        "would_run": n("would-run"),
        "ignored_files": len(ignored),
    }


def _record(manifest: Manifest, unit: CaptureUnit, root: Path, res: CaptureResult) -> None:
    """Merge a capture's result into its manifest record."""
    old = manifest.captures.get(res.rel) or {}
    steps = dict(old.get("steps", {}))
    steps.update(res.steps)
    if res.failure is not None:
        steps.pop(res.failure.get("step"), None)
    manifest.captures[res.rel] = {
        "input": {"path": unit.path.relative_to(root).as_posix(), **res.input},
        "status": "ok" if res.ok else "failed",
        "steps": steps,
        "failure": res.failure,
        "time": now_iso(),
        "elapsed_s": res.elapsed_s,
        "cpu_s": res.cpu_s,
    }


def _outcome(res: CaptureResult, outputs: list[str]) -> dict[str, Any]:
    common = {
        "capture": res.rel,
        "cached": False,
        "elapsed_s": res.elapsed_s,
        "cpu_s": res.cpu_s,
        "worker": res.worker,
    }
    if res.ok:
        return {**common, "status": "done", "outputs": outputs}
    return {
        **common,
        "status": "failed",
        "step": res.failure.get("step"),
        "reason": res.failure.get("reason"),
        "outputs": [s["output"] for s in res.steps.values()],
    }
