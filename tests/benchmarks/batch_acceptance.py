"""Issue 5 acceptance at the issue's scale, printing the figures for the closing note.

1. 20 simulated captures (files in nested folders, npz, a capture folder) plus 2 corrupt
   ones: ``vet batch`` produces 20 results, names the 2 failures with reasons, exits 3.
2. A rerun does no work (time).
3. ``kill -9`` midway, rerun: completes, every output readable, no temporaries left.
4. The same against a separately started Dask scheduler with two workers (loopback).
5. ``make -j2`` with make/vet.mk builds the same outputs; touching one capture rebuilds
   only its outputs.

Run: python -m tests.benchmarks.batch_acceptance [WORKDIR]   (`make batch-acceptance`)
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from tests.benchmarks.common import ROOT, vet_cmd

SIZE = (320, 256)


def make_tree(root: Path) -> list[str]:
    from stages.formats import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:chart", SIZE)
    rig = RigParams(sensor_size=SIZE)
    rels = []
    for i in range(20):
        if i == 19:
            rel = "day2/folder19/capture.exr"
        else:
            rel = f"day{1 + i % 2}/cap{i:02d}.{'npz' if i % 5 == 0 else 'exr'}"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        cap = simulate(scene, parse_motion("none"), rig, seed=i, measure_bins=2)["vet"]
        write_capture(root / rel, cap)
        rels.append(rel)
    (root / "day1" / "garbage.exr").write_bytes(np.random.default_rng(0).bytes(4096))
    data = (root / rels[1]).read_bytes()  # day2/cap01.exr
    (root / "day2" / "truncated.exr").write_bytes(data[: len(data) // 2])
    return rels


def outputs(out: Path) -> list[Path]:
    return sorted(
        p
        for p in out.rglob("*")
        if p.suffix in (".exr", ".png") and not p.name.startswith(".vet-tmp")
    )


def readable(p: Path) -> bool:
    if p.suffix == ".png":
        return cv2.imread(str(p)) is not None
    from stages.formats import read_hdr

    try:
        return bool(np.isfinite(read_hdr(p).radiance).all())
    except Exception:  # noqa: BLE001 - any failure means not readable
        return False


def batch(root: Path, out: Path, *extra: str) -> tuple[int, float, dict]:
    t0 = time.perf_counter()
    res = subprocess.run(
        vet_cmd("-q", "batch", root, "-o", out, *extra), capture_output=True, text=True
    )
    dt = time.perf_counter() - t0
    summary = (
        json.loads((out / "batch-summary.json").read_text())
        if (out / "batch-summary.json").exists()
        else {}
    )
    return res.returncode, dt, summary


def report(label: str, code: int, dt: float, summary: dict, out: Path) -> None:
    outs = outputs(out)
    ok = sum(readable(p) for p in outs)
    counts = summary.get("counts", {})
    print(f"{label}: exit {code}, {dt:.2f} s, counts {counts}, outputs {len(outs)} ({ok} readable)")
    for f in summary.get("failures", []):
        print(f"    failure: {f.get('capture')}: {f.get('reason')}")


def kill_midway(root: Path, out: Path, *extra: str) -> None:
    proc = subprocess.Popen(
        vet_cmd("-q", "batch", root, "-o", out, *extra),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 120
    while not any(out.rglob("*.png")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.01)
    finished_early = proc.poll() is not None
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = outputs(out)
    temps = list(out.rglob(".vet-tmp-*"))
    print(
        f"  kill -9 after the first outputs: {len(before)} outputs present, all readable: "
        f"{all(readable(p) for p in before)}; temporaries left by the kill: {len(temps)}"
        f"{' (run had already finished)' if finished_early else ''}"
    )


def make_recipes(root: Path, work: Path) -> None:
    good = work / "good"
    shutil.copytree(root, good)
    for bad in ("day1/garbage.exr", "day2/truncated.exr"):
        (good / bad).unlink()
    out = work / "make_out"
    vet = Path(sys.executable).parent / "vet"
    args = [
        "make",
        "-f",
        str(ROOT / "make" / "vet.mk"),
        f"VET={vet}",
        f"CAPTURES={good}",
        f"OUT={out}",
    ]
    t0 = time.perf_counter()
    res = subprocess.run([*args, "-j2", "vet-all"], capture_output=True, text=True)
    outs = outputs(out)
    print(
        f"make -j2 vet-all: exit {res.returncode}, {time.perf_counter() - t0:.1f} s, {len(outs)} outputs, "
        f"all readable: {all(readable(p) for p in outs)}"
    )
    time.sleep(1.1)
    (good / "day2" / "cap03.exr").touch()
    dry = subprocess.run([*args, "-n", "vet-all"], capture_output=True, text=True)
    cmds = [ln for ln in dry.stdout.splitlines() if " hdr-static " in ln or " tonemap " in ln]
    print(f"after touch day2/cap03.exr, make -n would run {len(cmds)} commands:")
    for c in cmds:
        print(f"    {c.replace(str(vet), 'vet').replace(str(work) + '/', '')}")


def main(argv: list[str]) -> int:
    from tests.dask_local import separate_dask_cluster

    work = Path(argv[0]) if argv else Path(tempfile.mkdtemp(prefix="vet-batch-acceptance-"))
    work.mkdir(parents=True, exist_ok=True)
    root = work / "captures"
    if root.exists():
        shutil.rmtree(root)
    root.mkdir()
    t0 = time.perf_counter()
    make_tree(root)
    print(
        f"20 simulated captures ({SIZE[0]}x{SIZE[1]}) + 2 corrupt, written in {time.perf_counter() - t0:.1f} s"
    )
    for label, extra in (
        ("local Dask, -j 2", ("-j", "2")),
        ("separate scheduler + 2 workers", None),
    ):
        out = work / ("out_local" if extra else "out_sched")
        out2 = work / ("kill_local" if extra else "kill_sched")
        for d in (out, out2):
            if d.exists():
                shutil.rmtree(d)
        print(f"\n== {label} ==")
        if extra is None:
            with separate_dask_cluster(work, workers=2) as address:
                extra = ("--scheduler", address)
                run_all(root, out, out2, extra)
        else:
            run_all(root, out, out2, extra)
    print("\n== make recipes ==")
    make_recipes(root, work)
    return 0


def run_all(root: Path, out: Path, out2: Path, extra: tuple[str, ...]) -> None:
    report("first run", *batch(root, out, *extra), out)
    report("rerun", *batch(root, out, *extra), out)
    kill_midway(root, out2, *extra)
    report("  rerun after kill -9", *batch(root, out2, *extra), out2)
    print(f"  temporaries after the rerun: {len(list(out2.rglob('.vet-tmp-*')))}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
