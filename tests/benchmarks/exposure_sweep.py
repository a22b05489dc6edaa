"""How the standard exposures compare with hdr-static as the scene gets dimmer.

Issue 3 asks that long and short exposures be worse than hdr-static (VET without
optimisation) overall. At DESIGN.md's radiance scale (the scene's 99.9th-percentile
luminance reaches the threshold in one subframe) a one-subframe exposure is a
well-exposed, unblurred picture of most of each scene, so `make evaluate-shared` finds
short better than hdr-static on half the runs. This sweep measures that dependence: the
same scenes and motions as evaluate-shared (seed 0, the scenes' own resolution), the
comparison methods only (`vet evaluate --methods vet-static,adaptive-attenuation,long,short`),
with the scene dimmed so that its 99.9th-percentile luminance takes N subframes to reach
the threshold (`--reach-subframes N`; N = 8 is three stops dimmer). It prints the
all-pixel RMS error in stops per run and, per N, on how many runs long and short are each
worse than hdr-static.

Run: python -m tests.benchmarks.exposure_sweep OUT_DIR [--reach 1,2,4,8,16]
[--size-scale F] [SCENE ...] (`make evaluate-exposure` writes eval_exposure/). Skips
cleanly when ../shared is absent.
"""

from __future__ import annotations

import sys
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR
from tests.benchmarks.evaluate_shared import SCENES, run_evaluate, scene_size, sweep_motions

METHODS = ("vet-static", "adaptive-attenuation", "long", "short")


def _option(argv: list[str], name: str, default: str) -> str:
    return argv[argv.index(name) + 1] if name in argv else default


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-exposure: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv else Path("eval_exposure")
    reaches = [float(n) for n in _option(argv, "--reach", "1,2,4,8,16").split(",")]
    size_scale = float(_option(argv, "--size-scale", "1"))
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    out.mkdir(exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        w, h = scene_size(path)
        w, h = int(round(w * size_scale)), int(round(h * size_scale))
        for tag, spec in sweep_motions(path, w, h).items():
            for n in reaches:
                folder = out / f"{name}_{tag}_reach{n:g}"
                extra = ("--methods", ",".join(METHODS), "--reach-subframes", f"{n:g}")
                table = run_evaluate(path, spec, (w, h), folder, *extra)
                if table is not None:
                    rms = {m: float(table[m]["all_rms"]) for m in METHODS}
                    rows.append((name, tag, n, int(table["vet-static"]["n_dark"]), rms))

    print("\nall-pixel RMS error, stops, by subframes N for p99.9 to reach the threshold")
    print(
        "| scene | motion | N | dark pixels | static | adaptive | long | short | long, short > static |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---|")
    for name, tag, n, n_dark, r in rows:
        s = r["vet-static"]
        worse = f"{'yes' if r['long'] > s else 'no'}, {'yes' if r['short'] > s else 'no'}"
        print(
            f"| {name} | {tag} | {n:g} | {n_dark} | {s:.3f} | {r['adaptive-attenuation']:.3f} |"
            f" {r['long']:.3f} | {r['short']:.3f} | {worse} |"
        )
    print("\n| N | runs | long > static | short > static | both |")
    print("|---:|---:|---:|---:|---:|")
    for n in reaches:
        at = [r for _, _, m, _, r in rows if m == n]
        longer = sum(r["long"] > r["vet-static"] for r in at)
        shorter = sum(r["short"] > r["vet-static"] for r in at)
        both = sum(min(r["long"], r["short"]) > r["vet-static"] for r in at)
        print(f"| {n:g} | {len(at)} | {longer} | {shorter} | {both} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
