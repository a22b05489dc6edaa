"""Benchmark: how much of the deblur's excess over the oracle along a camera path is one
global sub-pixel shift (the path's anchor).

A camera shake (``shake:4``) of a scene at a working size (default 320x240) over several
noise seeds (default 0-3): the default deblur's and the oracle's (the true path)
all-pixel RMS error in stops, their ratio, and the ratio once the deblur's result is
moved by the global shift (a 0.01 px grid over +-0.05 px, bicubic) that fits the truth
best, with that shift. The result is the scene at t = 0, placed by the path's value
there, which only the first samples of the frame measure: an error in it moves the whole
image. Where most of the excess goes with the shift, and the shift's sign changes from
seed to seed, the excess is that measurement's noise. The scene is ../shared/data/hdr's
Cannon (sharp, bright, its error small, so that a few hundredths of a pixel show) when
present, else ``builtin:interior``.

Run: ``.venv/bin/python -m tests.benchmarks.bench_path_anchor [WxH] [SCENE] [--seeds 0,1,2,3]``.
"""

from __future__ import annotations

import sys

from tests.benchmarks.common import SHARED_HDR

#: Largest global shift tried (px) and the grid's step.
SHIFT_MAX_PX = 0.05
SHIFT_STEP_PX = 0.01


def best_shift(image, score) -> tuple[float, float, float]:
    """The global shift ``(dx, dy)`` px of ``image`` (H, W, C) that scores lowest, and
    that score: ``score(moved image)`` over the grid of :data:`SHIFT_STEP_PX`."""
    import cv2
    import numpy as np

    h, w = image.shape[:2]
    steps = np.arange(-SHIFT_MAX_PX, SHIFT_MAX_PX + 1e-9, SHIFT_STEP_PX)
    best = (float("inf"), 0.0, 0.0)
    for dx in steps:
        for dy in steps:
            m = np.float32([[1, 0, dx], [0, 1, dy]])
            moved = cv2.warpAffine(
                image, m, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
            )
            best = min(best, (score(np.maximum(moved, 0).reshape(image.shape)), dx, dy))
    return best[1], best[2], best[0]


def main(size: tuple[int, int] = (320, 240), scene: str | None = None, seeds=(0, 1, 2, 3)) -> None:
    from stages.evaluate import run_evaluation
    from stages.metrics import stops_error

    if scene is None:
        cannon = SHARED_HDR / "Cannon.exr"
        scene = str(cannon) if cannon.is_file() else "builtin:interior"
    w, h = size
    name = scene.rsplit("/", 1)[-1].removesuffix(".exr")
    print(f"{name} {w}x{h} shake:4: all-pixel RMS (stops), deblur against the true path")
    print("| seed | deblur | oracle | ratio | best shift (px) | deblur shifted | ratio shifted |")
    print("|---|---|---|---|---|---|---|")
    for seed in seeds:
        ev = run_evaluation(
            scene, "shake:4", size, seed=seed, rows=("vet-deblur", "vet-deblur-oracle")
        )

        def score(img, ev=ev):
            return stops_error(img, ev.truth, ev.T, ev.frame_s, floor=ev.floor)["all"]["rms"]

        d, o = ev.scores["vet-deblur"]["all"]["rms"], ev.scores["vet-deblur-oracle"]["all"]["rms"]
        dx, dy, moved = best_shift(ev.images["vet-deblur"], score)
        print(
            f"| {seed} | {d:.4f} | {o:.4f} | {d / o:.3f} | ({dx:+.2f}, {dy:+.2f}) "
            f"| {moved:.4f} | {moved / o:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    from stages.scenes import parse_size
    from tests.benchmarks.evaluate_shared import option_value

    args = sys.argv[1:]
    seeds = tuple(int(s) for s in option_value(args, "--seeds", "0,1,2,3").split(","))
    if "--seeds" in args:
        del args[args.index("--seeds") : args.index("--seeds") + 2]
    dims = parse_size(args.pop(0)) if args and "x" in args[0] else (320, 240)
    main(dims, args[0] if args else None, seeds)
