"""Issue 3 acceptance sweep: `vet evaluate` on every scene in ../shared/data/hdr with
``translate:30,0`` and ``object:X,Y,W,H:40,10`` (the central rectangle, a quarter of the
frame's area), at the scenes' own resolution; then one summary of dark-pixel RMS.

Run: python -m tests.benchmarks.evaluate_shared OUT_DIR [--size-scale F] [SCENE ...]
(`make evaluate-shared` writes eval_out/). Skips cleanly when ../shared is absent.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import time
from pathlib import Path

from tests.benchmarks.common import SHARED_HDR, vet_cmd

SCENES = ["Desk", "CandleGlass", "GoldenGate", "Bonita", "Cannon"]


def scene_size(path: Path) -> tuple[int, int]:
    from stages.formats.layered import read_oiio

    pixels, _, _ = read_oiio(path, str(path))
    return pixels.shape[1], pixels.shape[0]


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-shared: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv else Path("eval_out")
    scale = 1.0
    if "--size-scale" in argv:
        scale = float(argv[argv.index("--size-scale") + 1])
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    out.mkdir(exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        w, h = scene_size(path)
        w, h = int(round(w * scale)), int(round(h * scale))
        motions = {
            "translate": "translate:30,0",
            "object": f"object:{w // 4},{h // 4},{w // 2},{h // 2}:40,10",
        }
        for tag, spec in motions.items():
            folder = out / f"{name}_{tag}"
            t0 = time.perf_counter()
            cmd = vet_cmd(
                "-q",
                "evaluate",
                path,
                "--motion",
                spec,
                "--size",
                f"{w}x{h}",
                "--seed",
                "0",
                "-o",
                folder,
            )
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                print(f"{name} {spec}: FAILED: {res.stderr.strip().splitlines()[-1:]}")
                continue
            print(f"{name} {spec} ({w}x{h}): {time.perf_counter() - t0:.0f} s", flush=True)
            with open(folder / "results.csv") as f:
                table = {r["method"]: r for r in csv.DictReader(f)}
            rows.append((name, tag, table))
    print(
        "\ndark-pixel RMS, stops (acceptance: deblur >= 30% below static; deblur < paper <= static < adaptive;"
        " deblur <= 1.25 x oracle; long, short worse than static on all-pixel RMS)"
    )
    print(
        "| scene | motion | deblur | paper | static | adaptive | oracle | cut vs static | deblur/oracle |"
        " all: static | all: long | all: short |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, tag, t in rows:

        def g(m, col="dark_rms", t=t):
            try:
                return float(t[m][col])
            except (KeyError, ValueError):
                return float("nan")

        d, p, s, a, o = (
            g(m)
            for m in (
                "vet-deblur",
                "vet-deblur-paper",
                "vet-static",
                "adaptive-attenuation",
                "vet-deblur-oracle",
            )
        )
        cut = 1 - d / s if s == s and s > 0 else float("nan")
        print(
            f"| {name} | {tag} | {d:.3f} | {p:.3f} | {s:.3f} | {a:.3f} | {o:.3f} | {100 * cut:.0f}% | "
            f"{d / o if o else float('nan'):.2f} | {g('vet-static', 'all_rms'):.3f} | {g('long', 'all_rms'):.3f} | "
            f"{g('short', 'all_rms'):.3f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
