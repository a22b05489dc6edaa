"""vet batch: process a folder of captures, incrementally, in parallel on Dask."""

from __future__ import annotations

import os
import sys
from typing import Any

import click

from ._common import Progress, State, command, log, verbosity_options
from .params import SCHEDULER, STOPS, TIMEOUT


def _parse_param(text: str) -> tuple[str, str, Any]:
    import json

    name, sep, value = text.partition("=")
    step, dot, key = name.partition(".")
    if not sep or not dot or not step or not key:
        raise click.BadParameter(
            f"{text!r}: expected STEP.NAME=VALUE, e.g. tonemap.exposure=1", param_hint="--param"
        )
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError:
        parsed = value
    return step, key, parsed


@click.command(
    "batch",
    help="""Run --steps on every capture under ROOT, writing into OUT with ROOT's layout.

Captures are capture files (.exr/.npz whose metadata says kind "capture"; other EXRs
are ignored) and capture folders. ROOT/d/a.exr gives OUT/d/a.hdr.exr (hdr-static),
OUT/d/a.deblur.exr (deblur) and OUT/d/a.png (tonemap, of deblur's result when it runs,
else of hdr-static's); the capture folder ROOT/d/x/ gives OUT/d/x.hdr.exr, OUT/d/x.png.

A manifest (OUT/.vet-batch-manifest.json) records input and output hashes, steps,
parameters and the vet version: a rerun only redoes what changed, and resumes a run
that was interrupted, even by kill -9. One bad capture never stops the others; every
failure is named with its reason on stderr and in OUT/batch-summary.json, and is not
retried until its input or parameters change (--retry-failed retries it).

Work runs on Dask: an embedded local cluster of -j worker processes on 127.0.0.1, or the
existing cluster at --scheduler (its workers must see ROOT and OUT at the same paths).
-j 1 without --scheduler runs in this process. Each capture runs in a process of its
own: one that runs past --timeout is stopped and fails alone.

OUT must be apart from ROOT (neither inside the other, through any link), and no two
captures may write one output: both are checked before any work.

Exit status: 0 every capture done or up to date; 3 the run completed but some captures
failed (listed); 1 the run could not proceed (ROOT unreadable, OUT not apart from ROOT,
colliding output names, step unavailable, scheduler unreachable, OUT locked by another
run); 2 usage error; 130/143/129 interrupted (rerun to resume).

\b
Examples:
  vet batch captures/ -o results/ -j 2
  vet batch captures/ -o results/ --steps hdr-static,deblur,tonemap --exposure 1
  vet batch captures/ -o results/ --scheduler tcp://10.0.0.5:8786
""",
)
@click.argument("root", type=click.Path(exists=True, file_okay=False))
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder (created if needed).",
)
@click.option(
    "--steps",
    default="hdr-static,tonemap",
    show_default=True,
    help="Comma-separated steps: hdr-static, deblur, tonemap.",
)
@click.option(
    "-j",
    "--jobs",
    type=click.IntRange(min=1),
    default=None,
    help="Worker processes of the embedded cluster [number of cores].",
)
@click.option(
    "--scheduler",
    type=SCHEDULER,
    metavar="ADDRESS",
    default=None,
    help="Use the existing Dask cluster at ADDRESS (tcp://HOST:PORT) instead.",
)
@click.option("--operator", default=None, help="Tone-mapping operator of the tonemap step [log].")
@click.option("--exposure", type=STOPS, default=None, help="Tone-mapping exposure, stops [0].")
@click.option(
    "--param",
    "params",
    multiple=True,
    metavar="STEP.NAME=VALUE",
    help="Any step parameter (JSON value), e.g. deblur.method=paper. Repeatable.",
)
@click.option(
    "--timeout",
    type=TIMEOUT,
    default="auto",
    show_default=True,
    metavar="SECONDS|auto|none",
    help="Time each capture (all its steps) may run before it is stopped and fails alone; "
    "auto: 10 minutes plus 30 s per MB of the capture file; none: no limit.",
)
@click.option("--force", is_flag=True, help="Rerun every step of every capture.")
@click.option(
    "--retry-failed", is_flag=True, help="Retry captures that failed before with the same input."
)
@click.option("-n", "--dry-run", is_flag=True, help="Only list what would run.")
@verbosity_options
@command("batch")
def cli(
    root: str,
    output: str,
    steps: str,
    jobs: int | None,
    scheduler: str | None,
    operator: str | None,
    exposure: float | None,
    params: tuple[str, ...],
    timeout: float | str | None,
    force: bool,
    retry_failed: bool,
    dry_run: bool,
) -> None:
    from stages.batch import EXIT_SOME_FAILED, BatchOptions, StepSpecError, run_batch

    options = BatchOptions(
        steps=steps,
        params=_overrides(params, operator, exposure),
        jobs=jobs or os.cpu_count() or 1,
        scheduler=scheduler,
        force=force,
        retry_failed=retry_failed,
        dry_run=dry_run,
        timeout=timeout,
    )
    progress = Progress("batch")
    try:
        with progress:
            report = run_batch(root, output, options, on_event=_events(root, progress))
    except StepSpecError as exc:
        raise click.UsageError(str(exc)) from None
    _tell(report, output, dry_run)
    if report.failures:
        sys.exit(EXIT_SOME_FAILED)


def _overrides(
    params: tuple[str, ...], operator: str | None, exposure: float | None
) -> dict[str, dict[str, Any]]:
    """``--param`` and the tonemap shortcuts as ``{step: {name: value}}``."""
    overrides: dict[str, dict[str, Any]] = {}
    for text in params:
        step, key, value = _parse_param(text)
        overrides.setdefault(step, {})[key] = value
    if operator is not None:
        overrides.setdefault("tonemap", {})["operator"] = operator
    if exposure is not None:
        overrides.setdefault("tonemap", {})["exposure"] = exposure
    return overrides


def _events(root: str, progress: Progress) -> Any:
    """The run's events on stderr: the plan, the executor, each result."""

    def on_event(kind: str, data: dict[str, Any]) -> None:
        if kind == "plan":
            log.info(
                "batch: %d captures under %s: %d to run, %d up to date, %d failed before%s",
                data["captures"],
                root,
                data["to_run"],
                data["up_to_date"],
                data["failed_before"],
                f"; {data['ignored']} non-capture files ignored" if data["ignored"] else "",
            )
        elif kind == "start":
            log.debug(
                "batch: running on %s (started in %.1f s)", data["executor"], data["startup_s"]
            )
        elif kind == "result":
            o = data["outcome"]
            if o["status"] == "failed":
                log.debug("batch: %s: failed at %s: %s", o["capture"], o["step"], o["reason"])
            else:
                log.debug("batch: %s: done in %.2f s", o["capture"], o.get("elapsed_s", 0.0))
            progress(data["done"], data["total"])

    return on_event


def _tell(report: Any, output: str, dry_run: bool) -> None:
    """The run's end on stderr: what would run, or the counts and the failures."""
    s = report.summary
    c = s["counts"]
    where = os.path.join(output, "batch-summary.json")
    if dry_run:
        for o in s["captures"]:
            if o["status"] == "would-run":
                click.echo(f"{o['capture']}: {', '.join(o['steps'])}", err=True)
        log.info("batch: dry run: %d of %d captures would run", c["would_run"], c["captures"])
        return
    log.info(
        "batch: %d captures: %d done, %d up to date, %d failed in %.1f s (%s); summary in %s",
        c["captures"],
        c["done"],
        c["up_to_date"],
        c["failed"],
        s["timing_s"]["total"],
        s["executor"],
        where,
    )
    if report.failures:
        _print_failures(report.failures)
        click.echo(
            f"vet batch: error: {c['failed']} of {c['captures']} captures failed "
            f"(listed above and in {where})",
            err=True,
        )


def _print_failures(failures: list[dict[str, Any]]) -> None:
    rows = [
        (
            f["capture"],
            f["step"] or "-",
            (f["reason"] or "") + (" [unchanged since it failed]" if f["cached"] else ""),
        )
        for f in failures
    ]
    w0 = max(len("capture"), *(len(r[0]) for r in rows))
    w1 = max(len("step"), *(len(r[1]) for r in rows))
    lines = [f"{'capture':<{w0}}  {'step':<{w1}}  reason", f"{'-' * w0}  {'-' * w1}  {'-' * 6}"]
    lines += [f"{a:<{w0}}  {b:<{w1}}  {r}" for a, b, r in rows]
    if State.verbosity >= -1:
        click.echo("vet batch: failures:\n" + "\n".join("  " + line for line in lines), err=True)
