"""Running a batch: discover, plan against the manifest, execute, record, summarise.

Execution is in-process for one job at a time without a scheduler, else on Dask
distributed (:mod:`.executors`). Results stream back as they complete and the manifest
is rewritten atomically after each batch of completions, so a run killed at any moment
(even by ``kill -9``) loses at most the captures in flight; their outputs are either
complete or absent (every writer is atomic), and the next run redoes exactly what is
missing.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import InputError
from ..formats.io import atomic_output
from .discover import CaptureUnit, discover_captures, output_stems
from .executors import results_dask, results_in_process
from .manifest import (
    Manifest,
    file_stat,
    now_iso,
    output_lock,
    plan_key,
    remove_stale_temporaries,
    sha256_file,
    step_key,
)
from .steps import STEPS, check_available, parse_steps, resolve_params
from .worker import CaptureJob, CaptureResult, StepCall

log = logging.getLogger("vet.batch")

SUMMARY_NAME = "batch-summary.json"
#: Exit status when every capture is done or up to date.
EXIT_OK = 0
#: Exit status when the run completed but some captures failed (see the summary).
EXIT_SOME_FAILED = 3
#: Seconds to wait for an existing cluster's scheduler, then for its first worker.
CONNECT_TIMEOUT_S = 30.0

EventHandler = Callable[[str, dict[str, Any]], None]


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


def _output_intact(path: Path, srec: dict[str, Any]) -> bool:
    """Whether the output a step record describes is still there, unchanged."""
    try:
        size, mtime = file_stat(path)
    except OSError:
        return False
    if size == srec.get("size") and mtime == srec.get("mtime_ns"):
        return True
    try:
        same = sha256_file(path) == srec.get("sha256")
    except OSError:
        return False
    if same:  # touched or copied, not changed: remember the new stat
        srec["size"], srec["mtime_ns"] = size, mtime
    return same


def _plan_unit(
    unit: CaptureUnit,
    stem: str,
    out: Path,
    names: list[str],
    params: dict[str, dict[str, Any]],
    rec: dict[str, Any] | None,
    retry_failed: bool,
) -> tuple[CaptureJob | None, dict[str, Any] | None]:
    """A job for a capture with work to do, or its outcome when there is none."""
    plan = [(n, STEPS[n].version, params[n]) for n in names]
    cap_sha: str | None = None
    if rec is not None:
        irec = rec.get("input", {})
        try:
            size, mtime = file_stat(unit.path)
            if irec.get("size") == size and irec.get("mtime_ns") == mtime:
                cap_sha = irec.get("sha256")
            elif irec.get("sha256"):
                cap_sha = sha256_file(unit.path)
                if cap_sha == irec["sha256"]:
                    irec["size"], irec["mtime_ns"] = size, mtime
        except OSError:
            cap_sha = None
    if rec is not None and cap_sha and rec.get("status") == "failed" and not retry_failed:
        failure = rec.get("failure") or {}
        if failure.get("key") and failure["key"] == plan_key(cap_sha, plan):
            return None, {
                "capture": unit.rel,
                "status": "failed",
                "cached": True,
                "step": failure.get("step"),
                "reason": failure.get("reason"),
                "outputs": [],
            }
    calls: list[StepCall] = []
    pending: set[str] = set()
    hdr_in: tuple[str, str | None] | None = None  # (path, sha256) of the last HDR output
    outputs: list[str] = []
    for n in names:
        step = STEPS[n]
        out_rel = stem + step.suffix
        out_abs = out / out_rel
        outputs.append(out_rel)
        if step.consumes == "capture":
            in_path, in_sha = str(unit.path), cap_sha
        else:
            assert hdr_in is not None  # parse_steps guarantees an HDR step before
            in_path, in_sha = hdr_in
        srec = (rec or {}).get("steps", {}).get(n)
        fresh = (
            rec is not None
            and in_path not in pending
            and in_sha is not None
            and srec is not None
            and srec.get("output") == out_rel
            and srec.get("key") == step_key(n, step.version, params[n], in_sha)
            and _output_intact(out_abs, srec)
        )
        if not fresh:
            calls.append(
                StepCall(
                    n,
                    in_path,
                    str(out_abs),
                    out_rel,
                    params[n],
                    input_sha256=None if in_path in pending else in_sha,
                )
            )
            pending.add(str(out_abs))
        if step.produces == "hdr":
            hdr_in = (str(out_abs), None if not fresh else srec.get("sha256"))
    if not calls:
        return None, {
            "capture": unit.rel,
            "status": "up-to-date",
            "cached": False,
            "outputs": outputs,
        }
    job = CaptureJob(
        rel=unit.rel,
        capture=str(unit.path),
        calls=calls,
        capture_sha256=cap_sha,
        plan=[(n, v, dict(p)) for n, v, p in plan],
        outputs=outputs,
    )
    return job, None


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


def run_batch(
    root: str | Path,
    out: str | Path,
    steps: str | list[str] | None = None,
    params: dict[str, dict[str, Any]] | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    force: bool = False,
    retry_failed: bool = False,
    dry_run: bool = False,
    on_event: EventHandler | None = None,
) -> BatchReport:
    """Process every capture under ``root`` into ``out``, skipping what is up to date.

    Parameters
    ----------
    root : str or Path
        Folder searched recursively for capture files and capture folders
        (:func:`~stages.batch.discover.discover_captures`).
    out : str or Path
        Output folder, created if needed; mirrors ``root``'s layout: ``root/d/a.exr``
        gives ``out/d/a.hdr.exr``, ``out/d/a.deblur.exr``, ``out/d/a.png``; the capture
        folder ``root/d/x/`` gives ``out/d/x.hdr.exr`` and so on.
    steps : str or list of str, optional
        Steps to run (:data:`~stages.batch.steps.STEPS`), comma-separated; default
        ``hdr-static,tonemap``.
    params : dict, optional
        ``{step: {parameter: value}}`` overriding the steps' defaults.
    jobs : int
        Worker processes for the embedded cluster; 1 without ``scheduler`` runs in
        this process, without Dask.
    scheduler : str, optional
        Address of an existing Dask scheduler; ``jobs`` is then ignored.
    force : bool
        Rerun every step of every capture, whatever the manifest says.
    retry_failed : bool
        Retry captures whose failure was recorded for the same input and parameters
        (by default they are reported again without being rerun).
    dry_run : bool
        Plan only: report what would run, write nothing.
    on_event : callable, optional
        ``on_event(kind, data)`` for progress: ``"plan"`` (counts), ``"start"``
        (executor), ``"result"`` (``{"outcome", "done", "total"}``).

    Returns
    -------
    BatchReport

    Raises
    ------
    StepSpecError
        Unknown step or parameter (a usage error).
    VetError
        The run itself cannot proceed: ``root`` is not a folder, a chosen step is not
        available, the output folder is locked by another run, the scheduler cannot be
        reached. Failures of single captures never raise; they are in the report.
    """
    t_start = time.monotonic()
    emit = on_event or (lambda kind, data: None)
    root = Path(root).absolute()
    out = Path(out).absolute()
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    if out == root:
        raise InputError("the output folder must differ from the capture folder ROOT")
    names = parse_steps(steps)
    step_params = resolve_params(names, params)
    check_available(names)
    if jobs < 1:
        raise InputError(f"-j must be at least 1, not {jobs}")
    if not dry_run:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    with output_lock(out) if not dry_run else contextlib.nullcontext():
        return _run_locked(
            root,
            out,
            names,
            step_params,
            jobs,
            scheduler,
            force,
            retry_failed,
            dry_run,
            emit,
            t_start,
        )


def _run_locked(
    root: Path,
    out: Path,
    names: list[str],
    params: dict[str, dict[str, Any]],
    jobs: int,
    scheduler: str | None,
    force: bool,
    retry_failed: bool,
    dry_run: bool,
    emit: EventHandler,
    t_start: float,
) -> BatchReport:
    started = now_iso()
    if not dry_run:
        n_tmp = remove_stale_temporaries(out)
        if n_tmp:
            log.debug("batch: removed %d temporary files left by an interrupted run", n_tmp)
    manifest = Manifest.load(out)
    if manifest.load_warning:
        log.warning("%s", manifest.load_warning)
    units, ignored = discover_captures(root, exclude=[out])
    by_rel = {u.rel: u for u in units}
    stems = output_stems(units, root.name)
    t_disc = time.monotonic()

    outcomes: dict[str, dict[str, Any]] = {}
    job_list: list[CaptureJob] = []
    for u in units:
        rec = None if force else manifest.captures.get(u.rel)
        job, outcome = _plan_unit(u, stems[u.rel], out, names, params, rec, retry_failed)
        if job is not None:
            job_list.append(job)
        else:
            outcomes[u.rel] = outcome
    t_plan = time.monotonic()
    n_cached = sum(1 for o in outcomes.values() if o["status"] == "failed")
    emit(
        "plan",
        {
            "captures": len(units),
            "to_run": len(job_list),
            "up_to_date": len(outcomes) - n_cached,
            "failed_before": n_cached,
            "ignored": len(ignored),
        },
    )

    info: dict[str, Any] = {"executor": "none (nothing to do)", "startup_s": 0.0}
    done = len(outcomes)
    total = len(units)
    if job_list and not dry_run:
        if scheduler is None and jobs <= 1:
            info["executor"] = "in-process (-j 1)"
            info["process_started"] = time.monotonic()
            results = results_in_process(job_list)
        else:
            results = results_dask(
                job_list, min(jobs, len(job_list)), scheduler, info, CONNECT_TIMEOUT_S
            )
        started_emitted = False
        jobs_by_rel = {j.rel: j for j in job_list}
        for burst in results:
            if not started_emitted:
                emit("start", dict(info))
                started_emitted = True
            for res in burst:
                _record(manifest, by_rel[res.rel], root, res)
                done += 1
                outcome = _outcome(res, jobs_by_rel[res.rel].outputs)
                outcomes[res.rel] = outcome
                if res.traceback:
                    log.debug("batch: %s: traceback from worker:\n%s", res.rel, res.traceback)
                emit("result", {"outcome": outcome, "done": done, "total": total})
            manifest.save(root)
        info["process_s"] = round(
            time.monotonic() - info.pop("process_started", time.monotonic()), 3
        )
    elif dry_run:
        for j in job_list:
            outcomes[j.rel] = {
                "capture": j.rel,
                "status": "would-run",
                "cached": False,
                "steps": [c.step for c in j.calls],
                "outputs": [c.output_rel for c in j.calls],
            }
    elif not dry_run and manifest.captures:
        manifest.save(root)  # stats refreshed by the fast path

    ordered = [outcomes[u.rel] for u in units]
    failures = [
        {
            "capture": o["capture"],
            "step": o.get("step"),
            "reason": o.get("reason"),
            "cached": o["cached"],
        }
        for o in ordered
        if o["status"] == "failed"
    ]
    counts = {
        "captures": total,
        "done": sum(1 for o in ordered if o["status"] == "done"),
        "up_to_date": sum(1 for o in ordered if o["status"] == "up-to-date"),
        "failed": len(failures),
        "would_run": sum(1 for o in ordered if o["status"] == "would-run"),
        "ignored_files": len(ignored),
    }
    exit_status = EXIT_SOME_FAILED if failures else EXIT_OK
    info.pop("process_started", None)
    summary = {
        "format": "vet-batch-summary",
        "vet_version": __version__,
        "root": str(root),
        "output": str(out),
        "steps": names,
        "params": params,
        "started": started,
        "finished": now_iso(),
        "dry_run": dry_run,
        "exit_status": exit_status,
        "counts": counts,
        "timing_s": {
            "discover": round(t_disc - t_start, 3),
            "plan": round(t_plan - t_disc, 3),
            "startup": info.get("startup_s", 0.0),
            "process": info.get("process_s", 0.0),
            "total": round(time.monotonic() - t_start, 3),
        },
        "executor": info.get("executor"),
        "workers": info.get(
            "workers", 1 if info.get("executor", "").startswith("in-process") else 0
        ),
        "failures": failures,
        "captures": ordered,
        "ignored": [{"path": i.rel, "reason": i.reason} for i in ignored],
    }
    if not dry_run:
        with atomic_output(out / SUMMARY_NAME, suffix=".json") as tmp:
            tmp.write_text(json.dumps(summary, indent=1, default=str))
    return BatchReport(summary=summary, exit_status=exit_status, failures=failures)


def _outcome(res: CaptureResult, outputs: list[str]) -> dict[str, Any]:
    if res.ok:
        return {
            "capture": res.rel,
            "status": "done",
            "cached": False,
            "outputs": outputs,
            "elapsed_s": res.elapsed_s,
            "cpu_s": res.cpu_s,
            "worker": res.worker,
        }
    return {
        "capture": res.rel,
        "status": "failed",
        "cached": False,
        "step": res.failure.get("step"),
        "reason": res.failure.get("reason"),
        "outputs": [s["output"] for s in res.steps.values()],
        "elapsed_s": res.elapsed_s,
        "cpu_s": res.cpu_s,
        "worker": res.worker,
    }
