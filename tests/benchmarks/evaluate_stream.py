"""Issues 18 and 51 acceptance sweep: the default deblur against the burst merge of its
own measuring stream and hdr-static, on every scene of ../shared/data/hdr.

Motions, by tag (:func:`motions`; R is the quarter-frame rectangle on the scene's dark
content, :func:`tests.benchmarks.evaluate_shared.object_rectangle`):

- ``translate``: ``translate:30,0``; ``object-dark``: R moving (40, 10) px/s;
  ``rotate``: ``rotate:4``; ``shake``: ``shake:4``;
- ``oscillate-30px-0.5hz``, ``oscillate-12px-1.5hz``, ``oscillate-5px-3hz``: R swinging
  horizontally (amplitude and frequency in the tag);
- ``accel``: R from 60 px/s braking at 100 px/s^2 (it stops at 0.6 s and comes back);
- ``two-objects``: two rectangles of an eighth of the frame's side in opposite quarters,
  one gliding (30, 0) px/s, one swinging 12 px vertically at 1 Hz;
- ``spin``: a square of a quarter of the frame's height at the centre turning 20 deg/s
  over the still rest;
- ``real-pan``, ``real-object``, ``real-oscillate``: the realistic rig
  (``--rig-profile realistic``) with ``translate:30,0``, R moving (40, 10) px/s, and R
  swinging 12 px at 1 Hz.

Each run is ``vet evaluate --methods vet-deblur,burst-merge,vet-static,
vet-deblur-oracle`` at SIZE (default 320x240).

Then, per scene, a still capture (no motion): the median change deblur makes to
hdr-static (at most 0.01 stops), the model deblur found and its time.

Printed: one row per run with the all-pixel median and RMS error (stops) of each method,
then the tally of the acceptance points: deblur's median and RMS at most burst-merge's
and vet-static's on every run; the geometric mean, over the runs with dark pixels, of
deblur's median and RMS over the better of the two (at most 0.85); deblur's RMS within
1.1x of the oracle's (deblur along the true motion) on how many runs, and every run
outside 1.25x named.

Run: python -m tests.benchmarks.evaluate_stream OUT_DIR [--size WxH] [--summary-only]
[--no-still] [--motions TAG,...] [SCENE ...] (TAG: those above; default all) (`make
evaluate-stream` writes eval_stream/). Skips cleanly when ../shared is absent.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR
from tests.benchmarks.evaluate_shared import (
    SCENES,
    object_rectangle,
    option_value,
    read_results,
    run_evaluate,
)

METHODS = "vet-deblur,burst-merge,vet-static,vet-deblur-oracle"


#: The options a tag's run adds to ``vet evaluate`` (the others: none).
RIG_OPTIONS = {
    tag: ("--rig-profile", "realistic") for tag in ("real-pan", "real-object", "real-oscillate")
}


def motions(path: Path, w: int, h: int) -> dict[str, str]:
    """The sweep's motions of one scene, by tag (module docstring)."""
    r = "{},{},{},{}".format(*object_rectangle(path, w, h))
    a, b = max(8, w // 8), max(8, h // 8)
    side = max(8, h // 4)
    return {
        "translate": "translate:30,0",
        "object-dark": f"object:{r}:40,10",
        "rotate": "rotate:4",
        "shake": "shake:4",
        "oscillate-30px-0.5hz": f"oscillate:{r}:30,0,0.5",
        "oscillate-12px-1.5hz": f"oscillate:{r}:12,0,1.5",
        "oscillate-5px-3hz": f"oscillate:{r}:5,0,3",
        "accel": f"accel:{r}:60,0:-100,0",
        "two-objects": f"object:{w // 8},{h // 8},{a},{b}:30,0"
        f"+oscillate:{w - w // 8 - a},{h - h // 8 - b},{a},{b}:0,12,1",
        "spin": f"spin:{(w - side) // 2},{(h - side) // 2},{side},{side}:20",
        "real-pan": "translate:30,0",
        "real-object": f"object:{r}:40,10",
        "real-oscillate": f"oscillate:{r}:12,0,1",
    }


def figures(t: dict[str, dict[str, str]]) -> dict[str, float]:
    """One run's all-pixel median and RMS per method, and its dark-pixel count."""
    out: dict[str, float] = {}
    for m, key in (("vet-deblur", "d"), ("burst-merge", "b"), ("vet-static", "s")):
        for col in ("median", "rms"):
            try:
                out[f"{key} {col}"] = float(t[m][f"all_{col}"])
            except (KeyError, ValueError):
                out[f"{key} {col}"] = float("nan")
    try:
        out["o rms"] = float(t["vet-deblur-oracle"]["all_rms"])
    except (KeyError, ValueError):
        out["o rms"] = float("nan")
    out["n dark"] = float(t["vet-deblur"].get("n_dark", 0) or 0)
    return out


def still_changes(names: list[str], w: int, h: int) -> None:
    """Per scene, a still capture's median change from hdr-static to deblur (stops)."""
    import time

    import numpy as np

    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    print(f"\nstill captures ({w}x{h}): median |log2(deblur / hdr-static)| (acceptance: < 0.01)")
    print("| scene | median change, stops | motion model | deblur s |")
    print("|---|---|---|---|")
    for name in names:
        scene = load_scene(str(SHARED_HDR / f"{name}.exr"), (w, h))
        rig = RigParams(sensor_size=(w, h))
        cap = simulate(scene, parse_motion("none"), rig, seed=0, methods=["vet"])["vet"]
        static = hdr_static(cap).radiance
        t0 = time.perf_counter()
        img, _ = deblur(cap)
        dt = time.perf_counter() - t0
        ok = (static > 0) & (img.radiance > 0)
        change = float(np.median(np.abs(np.log2(img.radiance[ok] / static[ok]))))
        print(f"| {name} | {change:.4f} | {img.meta['motion_model']} | {dt:.1f} |", flush=True)


def geomean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values else float("nan")


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-stream: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv and not argv[0].startswith("-") else Path("eval_stream")
    w, h = (int(v) for v in option_value(argv, "--size", "320x240").split("x"))
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    every = list(motions(SHARED_HDR / f"{names[0]}.exr", w, h))
    tags = option_value(argv, "--motions", ",".join(every)).split(",")
    unknown = [t for t in tags if t not in every]
    if unknown:
        print(f"evaluate-stream: unknown motion tags {unknown}; choose from {', '.join(every)}")
        return 2
    out.mkdir(exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        for tag, spec in motions(path, w, h).items():
            if tag not in tags:
                continue
            folder = out / f"{name}_{tag}"
            if "--summary-only" in argv:
                table = read_results(folder)
            else:
                extra = ("--methods", METHODS, *RIG_OPTIONS.get(tag, ()))
                table = run_evaluate(path, spec, (w, h), folder, *extra)
            if table is not None:
                rows.append((name, tag, figures(table)))
    tally(rows, w, h)
    if "--summary-only" not in argv and "--no-still" not in argv:
        still_changes(names, w, h)
    return 0


def tally(rows: list[tuple[str, str, dict[str, float]]], w: int, h: int) -> None:
    """The table of every run and the acceptance tally (module docstring)."""
    print(
        f"\nall-pixel error in stops, median / RMS ({w}x{h}); oracle: deblur along the true motion"
    )
    print(
        "| scene | motion | deblur | burst-merge | vet-static | oracle RMS | deblur/oracle |"
        " <= burst | <= static |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    ok_b = ok_s = ok_o = 0
    ratios_med: list[float] = []
    ratios_rms: list[float] = []
    far: list[str] = []
    for name, tag, f in rows:
        vb = f["d median"] <= f["b median"] and f["d rms"] <= f["b rms"]
        vs = f["d median"] <= f["s median"] and f["d rms"] <= f["s rms"]
        ratio = f["d rms"] / f["o rms"]
        ok_b, ok_s, ok_o = ok_b + vb, ok_s + vs, ok_o + (ratio <= 1.1)
        if not ratio <= 1.25:
            far.append(f"{name} {tag} ({ratio:.2f}x)")
        if f["n dark"] > 0:
            ratios_med.append(f["d median"] / min(f["b median"], f["s median"]))
            ratios_rms.append(f["d rms"] / min(f["b rms"], f["s rms"]))
        print(
            f"| {name} | {tag} | {f['d median']:.4f} / {f['d rms']:.4f} |"
            f" {f['b median']:.4f} / {f['b rms']:.4f} | {f['s median']:.4f} / {f['s rms']:.4f} |"
            f" {f['o rms']:.4f} | {ratio:.2f} | {'yes' if vb else 'NO'} | {'yes' if vs else 'NO'} |"
        )
    n = len(rows)
    print(f"\ndeblur median and RMS <= burst-merge's: {ok_b} of {n} runs")
    print(f"deblur median and RMS <= vet-static's: {ok_s} of {n} runs")
    print(
        f"geometric mean over the {len(ratios_rms)} runs with dark pixels of deblur / the better"
        f" of burst-merge and vet-static: median {geomean(ratios_med):.3f},"
        f" RMS {geomean(ratios_rms):.3f} (acceptance: at most 0.85)"
    )
    print(f"deblur RMS within 1.1x of the oracle's: {ok_o} of {n} runs")
    print(f"runs outside 1.25x of the oracle's RMS: {', '.join(far) if far else 'none'}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
