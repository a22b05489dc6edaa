"""Benchmark of ``vet batch``: hdr-static + tonemap over 20 captures of 1280x1024.

Figures printed (target in brackets):

- time to generate the 20 captures (once; cached in ``bench_out/batch/captures``);
- throughput on a Dask cluster of 1 worker process and of 2 (one thread each), cluster
  start excluded, and their ratio [>= 1.7x on 2 cores];
- ``vet batch -j 2`` and ``-j 1`` end to end from the command line, cluster start
  included, and a rerun with nothing to do [< 3 s].

Run: ``.venv/bin/python -m tests.benchmarks.bench_batch`` (or ``make bench``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
CACHE = REPO / "bench_out" / "batch"
N_CAPTURES = 20
SIZE = (1280, 1024)
SCENE = "builtin:chart"
REPEATS = 2


def _make_capture(path: str, seed: int) -> None:
    from stages.formats import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene(SCENE, SIZE)
    rig = RigParams(sensor_size=SIZE)
    # Seeded so the cache is reproducible; no measuring images, to save time.
    write_capture(
        path, simulate(scene, parse_motion("none"), rig, seed=seed, measure_bins=0)["vet"]
    )


def generate_captures(folder: Path = CACHE / "captures") -> tuple[Path, float, int]:
    """Make the captures that are missing; return (folder, seconds spent, how many made)."""
    from stages.batch import probe_kind

    folder.mkdir(parents=True, exist_ok=True)
    missing = [i for i in range(N_CAPTURES) if probe_kind(folder / f"cap{i:02d}.exr") != "capture"]
    t0 = time.perf_counter()
    if missing:
        with ProcessPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
            list(
                pool.map(_make_capture, [str(folder / f"cap{i:02d}.exr") for i in missing], missing)
            )
    return folder, time.perf_counter() - t0, len(missing)


def _throughput(captures: Path, n_workers: int) -> dict[str, float]:
    """Best of REPEATS runs on a LocalCluster of ``n_workers`` single-thread processes."""
    from distributed import LocalCluster

    from stages.batch import BatchOptions, run_batch
    from stages.cluster import WORKER_ENV

    best: dict[str, float] = {}
    t0 = time.perf_counter()
    with LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        env=dict(WORKER_ENV),
    ) as cluster:
        startup = time.perf_counter() - t0
        for _ in range(REPEATS):
            out = CACHE / f"out-{n_workers}w"
            shutil.rmtree(out, ignore_errors=True)
            report = run_batch(
                captures,
                out,
                BatchOptions(jobs=n_workers, scheduler=cluster.scheduler_address),
            )
            assert report.exit_status == 0 and report.summary["counts"]["done"] == N_CAPTURES
            process_s = report.summary["timing_s"]["process"]
            task_s = [o["elapsed_s"] for o in report.summary["captures"]]
            cpu_s = [o["cpu_s"] for o in report.summary["captures"]]
            if not best or process_s < best["process_s"]:
                best = {
                    "process_s": process_s,
                    "captures_per_s": N_CAPTURES / process_s,
                    "cluster_start_s": startup,
                    "task_mean_s": sum(task_s) / len(task_s),
                    "task_cpu_mean_s": sum(cpu_s) / len(cpu_s),
                    "load_average": os.getloadavg()[0],
                }
    return best


def _cli(*args: str) -> tuple[float, int]:
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "vet_cli", "-q", *args],
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        capture_output=True,
    )
    return time.perf_counter() - t0, r.returncode


def measure() -> dict[str, Any]:
    """Run the benchmark; return its figures."""
    captures, gen_s, made = generate_captures()
    fig: dict[str, Any] = {
        "captures": N_CAPTURES,
        "size": f"{SIZE[0]}x{SIZE[1]}",
        "scene": SCENE,
        "generated": made,
        "generate_s": round(gen_s, 1),
        "cpus": os.cpu_count(),
    }
    one = _throughput(captures, 1)
    two = _throughput(captures, 2)
    fig["dask_1_worker"] = {k: round(v, 3) for k, v in one.items()}
    fig["dask_2_workers"] = {k: round(v, 3) for k, v in two.items()}
    fig["speedup_2_vs_1"] = round(two["captures_per_s"] / one["captures_per_s"], 3)
    for j in (2, 1):
        out = CACHE / f"cli-j{j}"
        shutil.rmtree(out, ignore_errors=True)
        wall, rc = _cli("batch", str(captures), "-o", str(out), "-j", str(j))
        fig[f"cli_j{j}_s"] = round(wall, 2)
        fig[f"cli_j{j}_exit"] = rc
    wall, rc = _cli("batch", str(captures), "-o", str(CACHE / "cli-j2"), "-j", "2")
    fig["cli_rerun_s"] = round(wall, 2)
    fig["cli_rerun_exit"] = rc
    return fig


def main() -> None:
    """Print the figures (and save them to bench_out/batch/figures.json)."""
    fig = measure()
    print(
        f"bench_batch: {fig['captures']} captures {fig['size']} ({fig['scene']}), {fig['cpus']} CPUs"
    )
    print(
        f"  generate captures:        {fig['generate_s']:.1f} s for {fig['generated']} new (cached in {CACHE})"
    )
    for label, key in (("1 worker", "dask_1_worker"), ("2 workers", "dask_2_workers")):
        d = fig[key]
        print(
            f"  dask {label:<9}:          {d['process_s']:.2f} s  = {d['captures_per_s']:.2f} captures/s "
            f"(one capture {d['task_mean_s']:.2f} s wall, {d['task_cpu_mean_s']:.2f} s CPU; cluster start {d['cluster_start_s']:.1f} s, "
            f"not counted; load average {d['load_average']:.1f})"
        )
    print(f"  throughput 2 vs 1 worker: {fig['speedup_2_vs_1']:.2f}x  [target >= 1.7x]")
    print(
        f"  vet batch -j 2 (CLI):     {fig['cli_j2_s']:.2f} s end to end, exit {fig['cli_j2_exit']}"
    )
    print(
        f"  vet batch -j 1 (CLI):     {fig['cli_j1_s']:.2f} s end to end, in-process, exit {fig['cli_j1_exit']}"
    )
    print(
        f"  rerun, nothing to do:     {fig['cli_rerun_s']:.2f} s, exit {fig['cli_rerun_exit']}  [target < 3 s]"
    )
    CACHE.mkdir(parents=True, exist_ok=True)
    (CACHE / "figures.json").write_text(json.dumps(fig, indent=1))


if __name__ == "__main__":
    main()
