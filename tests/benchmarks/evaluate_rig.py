"""Issue 20 acceptance sweep: deblur on the realistic rig profile, every scene of
../shared/data/hdr at SIZE (default 320x240), with ``translate:30,0`` and a quarter-frame
object on the scene's dark content moving at (40, 10) px/s.

Each run is ``vet evaluate --rig-profile realistic --methods vet-deblur,vet-static,
vet-deblur-oracle``. Printed: dark-pixel RMS error (stops) of each method, deblur's cut of
hdr-static's (acceptance: at least 30%) and its ratio to the oracle's (at most 1.25), and
the tally. Run: python -m tests.benchmarks.evaluate_rig OUT_DIR [--size WxH]
[--summary-only] [SCENE ...] (`make evaluate-rig` writes eval_rig/). Skips cleanly when
../shared is absent.
"""

from __future__ import annotations

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

METHODS = "vet-deblur,vet-static,vet-deblur-oracle"


def dark_rms(t: dict[str, dict[str, str]], method: str) -> float:
    try:
        return float(t[method]["dark_rms"])
    except (KeyError, ValueError):
        return float("nan")


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-rig: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv and not argv[0].startswith("-") else Path("eval_rig")
    w, h = (int(v) for v in option_value(argv, "--size", "320x240").split("x"))
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    out.mkdir(exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        motions = {
            "translate": "translate:30,0",
            "object-dark": "object:{},{},{},{}:40,10".format(*object_rectangle(path, w, h)),
        }
        for tag, spec in motions.items():
            folder = out / f"{name}_{tag}"
            if "--summary-only" in argv:
                table = read_results(folder)
            else:
                extra = ("--rig-profile", "realistic", "--methods", METHODS)
                table = run_evaluate(path, spec, (w, h), folder, *extra)
            if table is not None:
                rows.append((name, tag, table))
    print(f"\nrealistic rig profile, {w}x{h}: dark-pixel RMS error, stops")
    print("| scene | motion | deblur | vet-static | oracle | cut vs static | deblur/oracle |")
    print("|---|---|---|---|---|---|---|")
    n_dark = ok_cut = ok_ratio = 0
    for name, tag, t in rows:
        d, s, o = (dark_rms(t, m) for m in ("vet-deblur", "vet-static", "vet-deblur-oracle"))
        if d != d:  # no dark pixel
            print(f"| {name} | {tag} | - | - | - | - | - |")
            continue
        n_dark += 1
        cut, ratio = 1 - d / s, d / o
        ok_cut += cut >= 0.3
        ok_ratio += ratio <= 1.25
        print(f"| {name} | {tag} | {d:.4f} | {s:.4f} | {o:.4f} | {100 * cut:.0f}% | {ratio:.2f} |")
    print(f"\ndeblur cuts hdr-static's dark RMS by at least 30%: {ok_cut} of {n_dark} runs")
    print(f"deblur within 1.25x of the oracle's dark RMS: {ok_ratio} of {n_dark} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
