"""The embedded Dask cluster (stages.cluster) closes without a traceback, and what its
workers log while they work still shows."""

from __future__ import annotations

import logging

from distributed import WorkerPlugin
from distributed.comm.core import CommClosedError


def _log_while_working(message: str) -> bool:
    logging.getLogger("distributed.worker").error(message)
    return True


class _HeartbeatFailsAtClose(WorkerPlugin):
    """What a loaded machine does at shutdown, made certain: once its worker is closing,
    the heartbeat meets the closed scheduler and Dask logs it with its traceback (as
    distributed.worker.Worker.heartbeat does)."""

    def teardown(self, worker) -> None:
        try:
            raise CommClosedError("in <TCP (closed) ConnectionPool.heartbeat_worker>: closed")
        except OSError:
            logging.getLogger("distributed.worker").exception(
                "Failed to communicate with scheduler during heartbeat."
            )


def test_an_embedded_cluster_closes_quietly_and_shows_errors_while_working(capfd):
    from stages.cluster import dask_client

    with dask_client(1) as client:
        client.register_plugin(_HeartbeatFailsAtClose(), name="heartbeat-fails-at-close")
        assert client.submit(_log_while_working, "an error logged by a task", pure=False).result()
    err = capfd.readouterr().err
    assert "an error logged by a task" in err, err
    assert "Traceback" not in err and "Failed to communicate" not in err, err


def _worker_omp() -> str | None:
    import os

    return os.environ.get("OMP_NUM_THREADS")


def test_a_cluster_started_here_leaves_this_process_its_threads_and_environment(monkeypatch):
    # A Dask nanny sets its workers' OMP_NUM_THREADS=1 in the process that spawns them
    # (distributed.nanny.pre-spawn-environ). The workers get it; this process keeps its
    # environment (what it starts later inherits) and its threads (solve_threads reads
    # the variable as the process started, so a cluster started by anyone here, or the
    # variable set later, leaves them).
    import os
    import subprocess
    import sys

    from stages import cluster

    monkeypatch.setattr(cluster.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(cluster, "_threads_limited", False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = dict(os.environ)
    with cluster.dask_client(1) as client:
        assert client.submit(_worker_omp, pure=False).result() == "1"
    assert dict(os.environ) == before
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # (as a cluster started by another hand)
    assert cluster.solve_threads() == 2
    code = "import stages.cluster as c; print(c.solve_threads())"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1"]  # (a process started so is limited)


def test_two_embedded_clusters_at_once_start_without_a_warning():
    # Two vet runs on one machine (two batches, a batch and a tiled deblur): Dask's
    # scheduler serves HTTP on 8787 unless told otherwise, and the second warns that the
    # port is taken ("Perhaps you already have a cluster running?") on the user's stderr.
    import warnings

    from stages.cluster import dask_client

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with dask_client(1) as first, dask_client(1) as second:
            assert first.submit(_worker_omp, pure=False).result() == "1"
            assert second.submit(_worker_omp, pure=False).result() == "1"


def test_a_worker_lets_its_heap_reuse_freed_arrays():
    # A Dask nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 (every array over
    # 128 kB a fresh mmap); limit_threads, which every worker task calls first, sets
    # glibc's thresholds back. (In a child: limit_threads changes the process for good.)
    import os
    import platform
    import subprocess
    import sys

    import pytest

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc's mallopt")
    code = (
        "import stages.cluster as c; calls = []; real = c.reuse_heap;"
        "c.reuse_heap = lambda: calls.append(1) or real(); c.limit_threads(); c.limit_threads();"
        "print(len(calls), real())"
    )
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "True"]


def test_one_thread_here_and_opencv_on_one_thread_from_several_threads():
    # solve_threads() is 1 on a thread inside one_thread_here, not on the others; OpenCV's
    # thread count is 1 while any thread is inside opencv_single_threaded, and the
    # process's setting comes back when the last one leaves, in whatever order they do.
    import threading

    import cv2

    from stages import cluster

    before = cv2.getNumThreads()
    inside, leave_first, seen = threading.Event(), threading.Event(), {}

    def first():
        with cluster.one_thread_here(), cluster.opencv_single_threaded():
            seen["first"] = cluster.solve_threads()
            inside.set()
            leave_first.wait(10)

    t = threading.Thread(target=first)
    t.start()
    assert inside.wait(10)
    seen["main"] = cluster.solve_threads()
    with cluster.opencv_single_threaded():
        leave_first.set()
        t.join(10)
        assert cv2.getNumThreads() == 1  # (the first thread left; this block has not)
    assert cv2.getNumThreads() == before
    assert seen["first"] == 1
    assert seen["main"] == cluster.solve_threads()


def _imported(name: str) -> bool:
    import sys

    return name in sys.modules


def test_a_client_started_soon_has_its_workers_import_what_it_was_asked_to():
    # (vet deblur starts its cluster while the motion is estimated: the workers then
    # hold the solve's modules before the first tile reaches them)
    from stages.cluster import ClientSoon

    with ClientSoon(1, warm=("stages.deblur.joint",)) as soon:
        client = soon.client()
        assert soon.info["workers"] == 1
        assert list(client.run(_imported, "stages.deblur.joint").values()) == [True]
        assert list(client.run(_imported, "stages.deblur.paper").values()) == [False]
        assert client.submit(_worker_omp, pure=False).result() == "1"


def test_a_client_started_soon_says_when_its_scheduler_cannot_be_reached(monkeypatch):
    import time

    import pytest

    from stages import cluster
    from stages.errors import VetError

    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)
    t0 = time.monotonic()
    with cluster.ClientSoon(1, "tcp://127.0.0.1:9") as soon:  # (nothing listens there)
        with pytest.raises(VetError, match="cannot reach the Dask scheduler at tcp://127.0.0.1:9"):
            soon.client()
    assert time.monotonic() - t0 < 20
