"""Benchmark: writing and reading a capture that keeps its whole measuring stream.

A capture (``builtin:interior`` at the size, RGB, translate:30,0, 131 subframes kept as
int16) is simulated once in a child process and written as EXR and as npz; each file is
then read in a fresh child process. Prints, per format: the file's size, the write time,
the read time and how far reading raised the process's high-water mark (``VmHWM``, which
a child does not inherit, unlike ``ru_maxrss``) against the stream's own size in memory.

Run: ``.venv/bin/python -m tests.benchmarks.bench_capture_io [WxH]`` (default 1280x1024,
the published rig's sensor).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _high_water() -> int:
    with open("/proc/self/status") as f:
        return next(int(v.split()[1]) for v in f if v.startswith("VmHWM:")) * 1024


def _write(size: str, tmp: str) -> dict:
    """Child: simulate, then write the capture as EXR and npz; the write times."""
    from stages.formats import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    scene = load_scene("builtin:interior", (w, h))
    cap = simulate(scene, parse_motion("translate:30,0"), RigParams(sensor_size=(w, h)), seed=0)
    cap = cap["vet"]
    out = {"stream_bytes": int(cap.measure.nbytes), "frames": int(cap.measure.shape[0])}
    for ext in ("exr", "npz"):
        t0 = time.perf_counter()
        write_capture(Path(tmp) / f"cap.{ext}", cap)
        out[f"{ext}_write_s"] = time.perf_counter() - t0
    return out


def _read(path: str) -> dict:
    """Child: read the capture; the read time and the rise of the high-water mark."""
    from stages.formats import read_capture

    before = _high_water()
    t0 = time.perf_counter()
    cap = read_capture(path)
    return {
        "read_s": time.perf_counter() - t0,
        "rise_bytes": _high_water() - before,
        "stream_bytes": int(cap.measure.nbytes),
    }


def _child(*args: str) -> dict:
    cmd = [sys.executable, "-m", "tests.benchmarks.bench_capture_io", "--child", *args]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(size: str = "1280x1024") -> None:
    if not Path("/proc/self/status").is_file():
        print("bench capture_io: needs Linux's /proc (VmHWM); skipped")
        return
    with tempfile.TemporaryDirectory(prefix="vet-bench-io-") as tmp:
        wrote = _child("write", size, tmp)
        print(
            f"{size} RGB capture, {wrote['frames']} measuring frames"
            f" ({wrote['stream_bytes'] / 1e9:.2f} GB in memory)",
            flush=True,
        )
        print(f"{'format':>6} {'file GB':>8} {'write s':>8} {'read s':>7} {'read rise GB':>13}")
        for ext in ("exr", "npz"):
            path = Path(tmp) / f"cap.{ext}"
            got = _child("read", str(path))
            print(
                f"{ext:>6} {path.stat().st_size / 1e9:8.3f} {wrote[f'{ext}_write_s']:8.1f}"
                f" {got['read_s']:7.1f} {got['rise_bytes'] / 1e9:13.2f}",
                flush=True,
            )


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        what, *rest = sys.argv[2:]
        print(json.dumps(_write(*rest) if what == "write" else _read(*rest)))
    else:
        main(*sys.argv[1:])
