"""Where a batch's captures run: in this process, or on Dask distributed.

Dask runs on the engine of :mod:`stages.cluster` (shared with tiled deblur): an embedded
:class:`distributed.LocalCluster` on the loopback interface (``n_workers`` processes, one
thread each, no dashboard), or an existing cluster through ``scheduler``
(``tcp://HOST:PORT``). Results stream back as they complete
(:func:`distributed.as_completed`), one list per burst of completions; a task whose
worker dies becomes a failed :class:`~stages.batch.jobs.CaptureResult`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

from ..cluster import dask_client
from .jobs import CaptureJob, CaptureResult
from .worker import process_capture


def results_in_process(jobs: list[CaptureJob]) -> Iterator[list[CaptureResult]]:
    """Run jobs one at a time in this process; yield each result as a one-item list."""
    for job in jobs:
        job.limit_threads = False  # one at a time: let OpenCV use every core
        yield [process_capture(job)]


def _lost(job: CaptureJob, exc: BaseException) -> CaptureResult:
    """A failed result for a job whose task raised or whose worker died (one line)."""
    step = job.calls[0].step if job.calls else ""
    reason = " ".join(f"worker lost or task failed ({type(exc).__name__}: {exc})".split())
    return CaptureResult(rel=job.rel, failure={"step": step, "reason": reason, "key": None})


def results_dask(
    jobs: list[CaptureJob],
    n_workers: int,
    scheduler: str | None,
    info: dict[str, Any],
    connect_timeout_s: float,
) -> Iterator[list[CaptureResult]]:
    """Run jobs on Dask; yield the results of each burst of completions.

    Parameters
    ----------
    jobs : list of CaptureJob
    n_workers : int
        Worker processes of the embedded :class:`distributed.LocalCluster` (one thread
        each); unused with ``scheduler``.
    scheduler : str or None
        ``tcp://HOST:PORT`` of an existing cluster, or None for an embedded one.
    info : dict
        Filled with ``executor``, ``workers``, ``startup_s`` and ``process_started``.
    connect_timeout_s : float
        Seconds to wait for the scheduler, then again for its first worker.

    Raises
    ------
    VetError
        The scheduler is unreachable or no worker joins it in time.
    """
    import distributed

    with dask_client(n_workers, scheduler, info, timeout_s=connect_timeout_s) as client:
        info["process_started"] = time.monotonic()
        by_key = {}
        futures = []
        for job in jobs:
            fut = client.submit(process_capture, job, pure=False)
            by_key[fut.key] = job
            futures.append(fut)
        for burst in distributed.as_completed(futures, loop=client.loop).batches():
            out: list[CaptureResult] = []
            for fut in burst:
                job = by_key[fut.key]
                try:
                    out.append(fut.result())
                except Exception as exc:  # KilledWorker, CancelledError, unpicklable...
                    out.append(_lost(job, exc))
                fut.release()
            yield out
