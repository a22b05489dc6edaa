"""Benchmark: deblur of a 1280x1024 mono capture, 131 subframes, translate:30,0.

Prints run time, peak memory (ru_maxrss), the dark-pixel RMS error against conjugate-
gradient iterations for the default method, and the paper method's time and error.
Run: ``.venv/bin/python -m tests.benchmarks.bench_deblur [WxH]``.
"""

from __future__ import annotations

import resource
import sys
import time


def main(size: str = "1280x1024") -> dict:
    import numpy as np

    from stages.deblur import deblur
    from stages.deblur.joint import JointOptions
    from stages.hdr_static import hdr_static
    from stages.metrics import stops_error
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import Scene, builtin_interior, luminance, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    sc = builtin_interior(w, h)
    mono = Scene(luminance(sc.radiance)[..., None].astype(np.float32), ["Y"], sc.source + " (mono)")
    rig = RigParams(sensor_size=(w, h))
    t0 = time.perf_counter()
    cap = simulate(mono, parse_motion("translate:30,0"), rig, seed=0, methods=["vet"])["vet"]
    print(f"simulate {w}x{h} mono: {time.perf_counter() - t0:.1f} s", flush=True)
    scale = cap.radiance_scale

    def dark_rms(img_rate: np.ndarray) -> float:
        return stops_error(img_rate / scale, cap.truth, cap.T, rig.frame_s)["dark"]["rms"]

    static = stops_error(hdr_static(cap).radiance, cap.truth, cap.T, rig.frame_s)["dark"]["rms"]
    print(f"hdr-static dark RMS {static:.3f} stops", flush=True)
    out = {"size": size, "static_dark_rms": static}
    for method in ("vet", "paper"):
        opts = JointOptions() if method == "vet" else None
        t0 = time.perf_counter()
        img, _ = deblur(cap, method, options=opts, truth_cb=dark_rms if method == "vet" else None)
        dt = time.perf_counter() - t0
        err = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s)["dark"]["rms"]
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
        print(
            f"{method}: {dt:.1f} s, dark RMS {err:.3f} stops, peak RSS so far {peak:.2f} GB",
            flush=True,
        )
        out[method] = {"time_s": dt, "dark_rms": err, "peak_gb": peak}
        if method == "vet":
            print("  CG iteration  dark RMS (stops)")
            for it, _t, e in opts.history:
                print(f"  {it:12d}  {e:.3f}")
            out["history"] = [(it, e) for it, _t, e in opts.history]
    return out


if __name__ == "__main__":
    main(*sys.argv[1:2])
