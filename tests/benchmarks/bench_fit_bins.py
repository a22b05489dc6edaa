"""Benchmark: how many time bins of a stream capture the default deblur fits.

A capture that keeps its whole measuring stream (131 subframes) is deblurred through
time bins of it, as many as the motion needs (:func:`stages.deblur.problem.fit_bins`:
51 for this 30 px/s pan at 640x512). For 16, 32 and 64 bins held fixed, and the default,
each in its own process (so that the peak memory is that run's): the deblur's time,
peak memory (ru_maxrss) and dark / bright / all-pixel error in stops, on
builtin:interior (mono) and builtin:chart (RGB) with translate:30,0 and the estimated
motion.
Run: ``.venv/bin/python -m tests.benchmarks.bench_fit_bins [WxH]``.
"""

from __future__ import annotations

import json
import subprocess
import sys

SCENES = (("builtin:interior", "mono"), ("builtin:chart", "rgb"))
BINS = (16, 32, 64, 0)  # (0: the default, fit_bins)


def one(size: str, scene: str, colour: str, bins: int) -> dict:
    """One deblur in this process; returns its figures."""
    import resource
    import time

    import numpy as np

    import stages.deblur.problem as problem
    from stages.deblur import deblur
    from stages.metrics import measurable_floor, stops_error
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import Scene, load_scene, luminance, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    sc = load_scene(scene, (w, h))
    if colour == "mono":
        sc = Scene(luminance(sc.radiance)[..., None].astype(np.float32), ["Y"], sc.source)
    rig = RigParams(sensor_size=(w, h))
    cap = simulate(sc, parse_motion("translate:30,0"), rig, seed=0, methods=["vet"])["vet"]
    if bins:
        problem.FIT_BINS = problem.FIT_BINS_MAX = bins
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    img, _ = deblur(cap)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    floor = measurable_floor(rig, cap.radiance_scale)
    err = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s, floor=floor)
    return {
        "time_s": dt,
        "peak_gb": rss / 1e6,
        "peak_before_gb": rss0 / 1e6,
        "dark_rms": err["dark"]["rms"],
        "dark_median": err["dark"]["median"],
        "bright_rms": err["bright"]["rms"],
        "bins": img.meta.get("fit_bins"),
        "all_rms": err["all"]["rms"],
        "all_median": err["all"]["median"],
    }


def main(size: str = "640x512") -> None:
    print(f"deblur of a stream capture through N time bins, {size}, translate:30,0")
    print(
        "scene             bins  time_s  peak_GB  dark_rms  dark_med  bright_rms  all_rms  all_med"
    )
    for scene, colour in SCENES:
        for bins in BINS:
            code = (
                "import json,sys; from tests.benchmarks.bench_fit_bins import one; "
                f"print(json.dumps(one({size!r}, {scene!r}, {colour!r}, {bins})))"
            )
            out = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, check=True
            )
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(
                f"{scene + ' ' + colour:18s}{r['bins']:4d}{'' if bins else '*'}"
                f"  {r['time_s']:6.1f}  {r['peak_gb']:7.2f}"
                f"  {r['dark_rms']:8.3f}  {r['dark_median']:8.3f}  {r['bright_rms']:10.3f}"
                f"  {r['all_rms']:7.3f}"
                f"  {r['all_median']:7.3f}",
                flush=True,
            )
    print("(*: the default, as many bins as the motion needs)")


if __name__ == "__main__":
    main(*sys.argv[1:])
