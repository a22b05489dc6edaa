"""Benchmark: how much the measuring stream says about which points move, by brightness.

A quarter-frame object on a scene's dark content moving at (40, 10) px/s (the placement
of ``make evaluate-stream``), and the same scene still, at a working size (default
320x240, seed 0). Printed:

- the layered estimate's labels against the truth: object points it missed, background
  points it took;
- per band of the points' signal-to-noise ratio in the track bins (the median of
  ``1 / sigma`` of their log rates), the mean track evidence (log-likelihood ratio of
  moving with the object's velocity against stillness, nats, clipped at +-1 as the
  labels' wider pooling clips it: :func:`stages.deblur.layers.alignment.track_score`)
  of the still capture's points, and of the moving capture's background and object
  points.

Where a band's object points score no higher than the still capture's points, the
stream holds no evidence that a pooling of them could add up: the labels there are
limited by the data. The scene is ../shared/data/hdr's CandleGlass when present, else
``builtin:interior``.

Run: ``.venv/bin/python -m tests.benchmarks.bench_label_evidence [WxH] [SCENE]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR

BANDS = ((1.0, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, float("inf")))
VELOCITY = (40.0, 10.0)


def _evidence(cap):
    """Track evidence (H, W) for the object's velocity, and the points' SNR (H, W)."""
    import numpy as np

    from stages.deblur.layers.alignment import track_score
    from stages.deblur.layers.bins import rate_frames, work_frames
    from stages.deblur.layers.estimate import MAX_WORK_PX, TRACK_BINS

    fine = cap.time_bins(TRACK_BINS)
    lum, noise, valid = rate_frames(fine)
    lv, slv, _valid, _scale = work_frames(lum, noise, valid, MAX_WORK_PX)
    centres = fine.measure_times.mean(axis=1)
    raw = track_score(lv, slv, np.array(VELOCITY), centres)
    return np.clip(raw, -1.0, 1.0), np.median(1.0 / slv, axis=0)


def main(size: tuple[int, int] = (320, 240), scene: str | None = None) -> None:
    import numpy as np

    from stages.deblur.layers import estimate_layers
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate
    from tests.benchmarks.evaluate_shared import object_rectangle

    if scene is None:
        cg = SHARED_HDR / "CandleGlass.exr"
        scene = str(cg) if cg.is_file() else "builtin:interior"
    w, h = size
    rect = object_rectangle(Path(scene), w, h) if scene.endswith(".exr") else (0, 0, w // 2, h // 2)
    spec = "object:{},{},{},{}:{:g},{:g}".format(*rect, *VELOCITY)
    sc = load_scene(scene, size)
    rig = RigParams(sensor_size=size)
    moving = simulate(sc, parse_motion(spec), rig, seed=0, methods=["vet"])["vet"]
    still = simulate(sc, parse_motion("none"), rig, seed=0, methods=["vet"])["vet"]
    obj = np.hypot(moving.truth_motion[..., 0], moving.truth_motion[..., 1]) > 1
    est = estimate_layers(moving).label > 0
    name = scene.rsplit("/", 1)[-1].removesuffix(".exr")
    print(f"{name} {w}x{h}, {spec}: layered labels against the truth")
    print(
        f"  object points {int(obj.sum())}: missed {int((obj & ~est).sum())};"
        f" background points {int((~obj).sum())}: taken {int((~obj & est).sum())}"
    )
    ev_m, snr_m = _evidence(moving)
    ev_s, snr_s = _evidence(still)
    print("  mean track evidence (nats, clipped at +-1) per SNR band:")
    print(f"  {'SNR band':>10s} {'still capture':>22s} {'background':>22s} {'object':>22s}")

    def cell(ev, m):
        return f"{ev[m].mean():8.3f} ({int(m.sum()):6d} pts)" if m.any() else f"{'-':>22s}"

    for lo, hi in BANDS:
        bs = (snr_s >= lo) & (snr_s < hi)
        bm = (snr_m >= lo) & (snr_m < hi)
        print(
            f"  {lo:4.1f}-{hi:<5.1f} {cell(ev_s, bs):>22s} {cell(ev_m, bm & ~obj):>22s}"
            f" {cell(ev_m, bm & obj):>22s}",
            flush=True,
        )


if __name__ == "__main__":
    from stages.scenes import parse_size

    args = sys.argv[1:]
    dims = parse_size(args.pop(0)) if args and "x" in args[0] else (320, 240)
    main(dims, args[0] if args else None)
