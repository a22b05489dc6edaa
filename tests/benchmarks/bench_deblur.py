"""Benchmark: deblur of a 1280x1024 mono capture, 131 subframes, translate:30,0.

Prints run time, peak memory (ru_maxrss), the dark-pixel RMS error against conjugate-
gradient iterations for the default method, and the paper method's time and error; then
the dot-product (adjoint) test of the benchmark capture's own operators (VET image and
measuring bins, true motion), and the median change deblur makes to hdr-static on a
capture of a still scene (640x512 RGB, the layered motion estimate).
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
    from stages.metrics import measurable_floor, stops_error
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
    floor = measurable_floor(rig, scale)  # as vet evaluate scores

    def dark_rms(img_rate: np.ndarray) -> float:
        return stops_error(img_rate / scale, cap.truth, cap.T, rig.frame_s, floor=floor)["dark"][
            "rms"
        ]

    static = stops_error(hdr_static(cap).radiance, cap.truth, cap.T, rig.frame_s, floor=floor)[
        "dark"
    ]["rms"]
    print(f"hdr-static dark RMS {static:.3f} stops", flush=True)
    out = {"size": size, "static_dark_rms": static}
    for method in ("vet", "paper"):
        opts = JointOptions() if method == "vet" else None
        t0 = time.perf_counter()
        img, _ = deblur(cap, method, options=opts, truth_cb=dark_rms if method == "vet" else None)
        dt = time.perf_counter() - t0
        err = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s, floor=floor)["dark"]["rms"]
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
    out["adjoint_rel"] = adjoint_error(cap)
    out["still_median"] = still_scene_change()
    return out


def adjoint_error(cap) -> float:
    """Worst relative error of ``<A x, y> = <x, A^T y>`` over the capture's operators."""
    import numpy as np

    from stages.deblur.problem import build_operators, observations

    obs = observations(cap)
    A, Ab = build_operators(obs, cap.truth_motion, subframe_s=cap.rig.subframe_s)
    rng = np.random.default_rng(0)
    worst = 0.0
    for M in [A] + Ab.blurs:
        x = rng.random(M.shape[1])
        y = rng.random(M.shape[0])
        lhs = float(np.dot(M @ x, y))
        rhs = float(np.dot(x, M.T @ y))
        worst = max(worst, abs(lhs - rhs) / abs(lhs))
    print(
        f"adjoint test, {1 + len(Ab.blurs)} operators of {A.shape[0]} x {A.shape[1]}"
        f" ({A.nnz + sum(M.nnz for M in Ab.blurs)} non-zeros): worst relative error {worst:.2e}",
        flush=True,
    )
    return worst


def still_scene_change(size: str = "640x512") -> float:
    """Median |log2(deblur / hdr-static)| on a capture of a still scene."""
    import numpy as np

    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import builtin_interior, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    rig = RigParams(sensor_size=(w, h))
    cap = simulate(builtin_interior(w, h), parse_motion("none"), rig, seed=0, methods=["vet"])[
        "vet"
    ]
    static = hdr_static(cap).radiance
    img, vel = deblur(cap, "vet")
    d = np.abs(np.log2(img.radiance / static))
    med = float(np.median(d))
    print(
        f"still scene {size} RGB: deblur vs hdr-static median {med:.4f} stops, max {d.max():.4f},"
        f" estimated speed max {float(np.hypot(vel[..., 0], vel[..., 1]).max()):.2f} px/s",
        flush=True,
    )
    return med


if __name__ == "__main__":
    main(*sys.argv[1:2])
