"""A Dask cluster started as separate processes on loopback, for tests and the batch
acceptance script (never anything but 127.0.0.1)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _wait_for_file(path: Path, proc: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            raise RuntimeError(f"process exited early with {proc.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} did not appear")
        time.sleep(0.05)


@contextlib.contextmanager
def separate_dask_cluster(tmp_path: Path, workers: int = 2) -> Iterator[str]:
    """A Dask scheduler and ``workers`` single-thread workers, started as separate
    processes on loopback (as on a real cluster); yields the scheduler address and
    stops everything at the end, whatever happens."""
    bindir = Path(sys.executable).parent
    sched_file = tmp_path / "scheduler.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT), DASK_DISTRIBUTED__WORKER__DAEMON="False")
    procs: list[subprocess.Popen] = []
    logs = open(tmp_path / "dask.log", "wb")  # noqa: SIM115 - closed in the finalizer
    try:
        procs.append(
            subprocess.Popen(
                [
                    str(bindir / "dask"),
                    "scheduler",
                    "--host",
                    "127.0.0.1",
                    "--port",
                    "0",
                    "--no-dashboard",
                    "--scheduler-file",
                    str(sched_file),
                ],
                stdout=logs,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=tmp_path,
            )
        )
        _wait_for_file(sched_file, procs[0])
        for i in range(workers):
            procs.append(
                subprocess.Popen(
                    [
                        str(bindir / "dask"),
                        "worker",
                        "--scheduler-file",
                        str(sched_file),
                        "--host",
                        "127.0.0.1",
                        "--nthreads",
                        "1",
                        "--nworkers",
                        "1",
                        "--no-dashboard",
                        "--name",
                        f"w{i}",
                        "--death-timeout",
                        "60",
                    ],
                    stdout=logs,
                    stderr=subprocess.STDOUT,
                    env=env,
                    cwd=tmp_path,
                )
            )
        address = json.loads(sched_file.read_text())["address"]
        if not address.startswith("tcp://127.0.0.1:"):
            raise RuntimeError(f"scheduler not on loopback: {address}")
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(workers, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in reversed(procs):
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        logs.close()
