"""Benchmark: deblur time and peak memory against frame size (translate:30,0).

Each capture (``builtin:interior`` resampled to the size, or a scene given, mono or RGB,
131 subframes) is simulated in one subprocess and written to a temporary ``.npz``; the default deblur then
runs in a fresh subprocess that reads it, so the peak resident memory it reports
(``ru_maxrss``) is the deblur's alone (reading the capture included). Prints one row per
size: megapixels, channels, seconds (wall clock, and CPU: user + system, steadier on a
shared machine), peak GB and the dark-pixel RMS error (stops, as ``vet evaluate`` scores).
The deblur runs as ``vet deblur`` runs it: the simulator's truth layers left unread,
``--tile auto`` (frames over 1024 pixels on a side in tiles) and the capture's stream let
go of once binned.

Run: ``.venv/bin/python -m tests.benchmarks.bench_deblur_scaling
[WxH[:mono|rgb[:SCENE]] ...]`` (default: mono at 640x512, 1280x1024 and 2560x2048 (0.3,
1.3 and 5.2 MP), and RGB at 1280x1024, of builtin:interior, a smooth scene, and RGB at
1280x1024 of ../shared/data/hdr's Desk, textured all over, where ../shared is present;
``4096x3072:mono`` adds 12.6 MP where the machine has the memory for it).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR

DEFAULT_CASES = ("640x512:mono", "1280x1024:mono", "1280x1024:rgb", "2560x2048:mono")
#: A textured real scene (where ../shared is present): motion paths in every tile.
TEXTURED_CASE = f"1280x1024:rgb:{SHARED_HDR / 'Desk.exr'}"


def _simulate(size: str, mono: bool, path: str, scene: str = "builtin:interior") -> None:
    """Child: simulate the capture and write it to ``path`` (.npz)."""
    import numpy as np

    from stages.formats.capture import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import Scene, load_scene, luminance, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    sc = load_scene(scene, (w, h))
    if mono:
        sc = Scene(luminance(sc.radiance)[..., None].astype(np.float32), ["Y"], sc.source)
    rig = RigParams(sensor_size=(w, h))
    cap = simulate(sc, parse_motion("translate:30,0"), rig, seed=0, methods=["vet"])["vet"]
    write_capture(path, cap)


def _deblur(path: str) -> None:
    """Child: deblur the capture at ``path``; print time, peak RSS and error as JSON."""
    import resource
    import time

    from stages.deblur import deblur
    from stages.formats.capture import read_capture
    from stages.metrics import measurable_floor, stops_error

    def cpu_s() -> float:
        use = resource.getrusage(resource.RUSAGE_SELF)
        return use.ru_utime + use.ru_stime

    t0, c0 = time.perf_counter(), cpu_s()
    cap = read_capture(path, truth=False)  # as vet deblur runs it
    img, _ = deblur(cap, "vet", tile="auto", release_stream=True)
    dt, cpu = time.perf_counter() - t0, cpu_s() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # kB -> GB
    cap.truth = read_capture(path).truth  # (for the score, after the peak is taken)
    floor = measurable_floor(cap.rig, cap.radiance_scale)
    err = stops_error(img.radiance, cap.truth, cap.T, cap.rig.frame_s, floor=floor)
    print(json.dumps({"time_s": dt, "cpu_s": cpu, "peak_gb": peak, "dark_rms": err["dark"]["rms"]}))


def measure(case: str, tmp: Path) -> dict:
    """Simulate then deblur one ``WxH[:mono|rgb[:SCENE]]`` case in subprocesses."""
    size, _, rest = case.partition(":")
    kind, _, scene = rest.partition(":")
    kind, scene = kind or "mono", scene or "builtin:interior"
    path = str(tmp / f"{size}_{kind}.npz")
    me = [sys.executable, "-m", "tests.benchmarks.bench_deblur_scaling"]
    subprocess.run([*me, "--simulate", size, kind, path, scene], check=True)
    res = subprocess.run([*me, "--deblur", path], check=True, capture_output=True, text=True)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    w, h = (int(v) for v in size.split("x"))
    out.update(size=size, kind=kind, mp=w * h / 1e6, scene=Path(scene).stem)
    return out


def main(*cases: str) -> list[dict]:
    rows = []
    print(
        f"{'size':>10} {'MP':>5} {'kind':>4} {'time s':>7} {'CPU s':>7} {'peak GB':>8}"
        f" {'dark RMS':>8}  scene"
    )
    if not cases:
        cases = DEFAULT_CASES + ((TEXTURED_CASE,) if SHARED_HDR.is_dir() else ())
    with tempfile.TemporaryDirectory(prefix="vet-bench-") as tmp:
        for case in cases:
            r = measure(case, Path(tmp))
            rows.append(r)
            print(
                f"{r['size']:>10} {r['mp']:5.2f} {r['kind']:>4} {r['time_s']:7.1f}"
                f" {r['cpu_s']:7.1f} {r['peak_gb']:8.2f} {r['dark_rms']:8.4f}  {r['scene']}",
                flush=True,
            )
    return rows


if __name__ == "__main__":
    if sys.argv[1:2] == ["--simulate"]:
        _simulate(sys.argv[2], sys.argv[3] == "mono", sys.argv[4], sys.argv[5])
    elif sys.argv[1:2] == ["--deblur"]:
        _deblur(sys.argv[2])
    else:
        main(*sys.argv[1:])
