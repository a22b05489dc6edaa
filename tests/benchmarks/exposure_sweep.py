"""How the comparison methods rank against hdr-static as the scene gets dimmer.

Issue 3 asks that long and short exposures be worse than hdr-static (VET without
optimisation) overall, and that adaptive attenuation be worse than hdr-static over dark
pixels. At DESIGN.md's radiance scale (the scene's 99.9th-percentile luminance reaches
the threshold in one subframe) a one-subframe exposure is a well-exposed, unblurred
picture of most of each scene, so `make evaluate-shared` finds short better than
hdr-static on half the runs. This sweep measures that dependence: the same scenes and
motions as evaluate-shared (the scenes' own resolution), the comparison methods only
(`vet evaluate --methods vet-static,adaptive-attenuation,long,short`), with the scene
dimmed so that its 99.9th-percentile luminance takes N subframes to reach the threshold
(`--reach-subframes N`; N = 8 is three stops dimmer).

It prints, per run, the all-pixel RMS error in stops of each method and the dark-pixel
RMS of hdr-static and adaptive attenuation; then, per N, on how many runs long and short
are each worse than hdr-static; and, with several seeds, on how many seeds hdr-static's
dark RMS is below adaptive attenuation's (in the dark both expose the whole frame through
an open LCoS unless adaptive attenuation mis-attenuates a pixel; `simulate` exposes both
with the same noise, so elsewhere they record the same values, and only the
mis-attenuated pixels separate them).

Run: python -m tests.benchmarks.exposure_sweep OUT_DIR [--reach 1,2,4,8,16]
[--seeds 0] [--size-scale F] [SCENE ...] (`make evaluate-exposure` runs it twice, into
eval_exposure/ and, at N = 1 with seeds 0-4, eval_exposure/seeds/). Skips cleanly when
../shared is absent.
"""

from __future__ import annotations

import sys
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR
from tests.benchmarks.evaluate_shared import (
    SCENES,
    option_value,
    run_evaluate,
    scene_size,
    sweep_motions,
)

METHODS = ("vet-static", "adaptive-attenuation", "long", "short")


def _cells(table: dict[str, dict[str, str]]) -> dict[str, float]:
    out = {m: float(table[m]["all_rms"]) for m in METHODS}
    out["dark static"] = float(table["vet-static"]["dark_rms"])
    out["dark adaptive"] = float(table["adaptive-attenuation"]["dark_rms"])
    out["n_dark"] = int(table["vet-static"]["n_dark"])
    return out


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-exposure: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv else Path("eval_exposure")
    reaches = [float(n) for n in option_value(argv, "--reach", "1,2,4,8,16").split(",")]
    seeds = [int(s) for s in option_value(argv, "--seeds", "0").split(",")]
    size_scale = float(option_value(argv, "--size-scale", "1"))
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        w, h = scene_size(path)
        w, h = int(round(w * size_scale)), int(round(h * size_scale))
        for tag, spec in sweep_motions(path, w, h).items():
            for n in reaches:
                for seed in seeds:
                    folder = out / f"{name}_{tag}_reach{n:g}_seed{seed}"
                    extra = ("--methods", ",".join(METHODS), "--reach-subframes", f"{n:g}")
                    table = run_evaluate(path, spec, (w, h), folder, *extra, seed=seed)
                    if table is not None:
                        rows.append((name, tag, n, seed, _cells(table)))

    print("\nRMS error in stops by N, the subframes for p99.9 to reach the threshold")
    print(
        "| scene | motion | N | seed | dark pixels | all: static | all: adaptive | all: long |"
        " all: short | long, short > static | dark: static | dark: adaptive |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|")
    for name, tag, n, seed, c in rows:
        s = c["vet-static"]
        worse = f"{'yes' if c['long'] > s else 'no'}, {'yes' if c['short'] > s else 'no'}"
        print(
            f"| {name} | {tag} | {n:g} | {seed} | {c['n_dark']} | {s:.3f} |"
            f" {c['adaptive-attenuation']:.3f} | {c['long']:.3f} | {c['short']:.3f} | {worse} |"
            f" {_dark(c['dark static'])} | {_dark(c['dark adaptive'])} |"
        )
    print("\n| N | runs | long > static | short > static | both |")
    print("|---:|---:|---:|---:|---:|")
    for n in reaches:
        at = [c for _, _, m, _, c in rows if m == n]
        longer = sum(c["long"] > c["vet-static"] for c in at)
        shorter = sum(c["short"] > c["vet-static"] for c in at)
        both = sum(min(c["long"], c["short"]) > c["vet-static"] for c in at)
        print(f"| {n:g} | {len(at)} | {longer} | {shorter} | {both} |")
    if len(seeds) > 1:
        print("\ndark RMS, hdr-static below adaptive attenuation, by seed")
        print("| scene | motion | N | seeds | static < adaptive | mean adaptive - static |")
        print("|---|---|---:|---:|---:|---:|")
        for key in dict.fromkeys((name, tag, n) for name, tag, n, _, _ in rows):
            at = [c for name, tag, n, _, c in rows if (name, tag, n) == key]
            diff = [c["dark adaptive"] - c["dark static"] for c in at]
            if any(d != d for d in diff):
                print(f"| {key[0]} | {key[1]} | {key[2]:g} | {len(at)} | - | no dark pixel |")
                continue
            wins = sum(d > 0 for d in diff)
            print(
                f"| {key[0]} | {key[1]} | {key[2]:g} | {len(at)} | {wins} |"
                f" {sum(diff) / len(diff):+.6f} |"
            )
    return 0


def _dark(value: float) -> str:
    return "-" if value != value else f"{value:.4f}"


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
