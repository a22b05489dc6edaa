"""Issue 3 acceptance sweep: `vet evaluate` on every scene in ../shared/data/hdr with
``translate:30,0`` and ``object:X,Y,W,H:40,10`` (a rectangle of half the width and half
the height, a quarter of the frame's area), at the scenes' own resolution; then one
summary of dark-pixel RMS with each acceptance comparison.

The rectangle is the central one (``object``) and, where it differs, the one placed on
the scene's dark content (``object-dark``): of the nine placements on a quarter-frame
grid, the one holding the most pixels below the 99.9th-percentile luminance / K (which
stay open for the whole frame). The dark criteria are about deblurring moving dark
pixels, and GoldenGate's central rectangle holds none.

Run: python -m tests.benchmarks.evaluate_shared OUT_DIR [--size-scale F]
[--reach-subframes N] [SCENE ...] (`make evaluate-shared` writes eval_out/ at DESIGN.md's
radiance scale, N = 1; a larger N dims every scene alike, as `vet evaluate
--reach-subframes N` does; the rectangles stay where they are at N = 1). It ends with the
number of runs on which each acceptance point holds, over all runs and over the set of
translate plus the object on dark content. ``--summary-only`` prints the tables from the
results.csv files a finished run left in OUT_DIR (give it that run's options) without
running anything. Skips cleanly when ../shared is absent.
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


def object_rectangle(path: Path, w: int, h: int) -> tuple[int, int, int, int]:
    """The quarter-area rectangle placed on the scene's dark content (module docstring)."""
    import numpy as np

    from stages.rig import RigParams
    from stages.scenes import load_scene, luminance

    lum = luminance(load_scene(str(path), (w, h)).radiance)
    dark = lum < np.percentile(lum, 99.9) / RigParams().n_subframes
    rw, rh = w // 2, h // 2
    spots = [(w // 4, h // 4)] + [
        (x, y)
        for y in (0, h // 4, h - rh)
        for x in (0, w // 4, w - rw)
        if (x, y) != (w // 4, h // 4)
    ]
    counts = [int(dark[y : y + rh, x : x + rw].sum()) for x, y in spots]
    x, y = spots[int(np.argmax(counts))]
    return x, y, rw, rh


def sweep_motions(path: Path, w: int, h: int) -> dict[str, str]:
    """The sweep's motions of one scene, by tag (module docstring)."""
    central = (w // 4, h // 4, w // 2, h // 2)
    on_dark = object_rectangle(path, w, h)
    motions = {
        "translate": "translate:30,0",
        "object": "object:{},{},{},{}:40,10".format(*central),
    }
    if on_dark != central:
        motions["object-dark"] = "object:{},{},{},{}:40,10".format(*on_dark)
    return motions


def option_value(argv: list[str], name: str, default: str) -> str:
    """The word after ``name`` in ``argv``, else ``default``."""
    return argv[argv.index(name) + 1] if name in argv else default


def run_evaluate(
    path: Path, spec: str, size: tuple[int, int], folder: Path, *extra: str, seed: int = 0
) -> dict[str, dict[str, str]] | None:
    """`vet evaluate` (plus ``extra`` options) into ``folder``; its results.csv rows by
    method, or None (and a line saying why) when it failed."""
    w, h = size
    t0 = time.perf_counter()
    cmd = vet_cmd("-q", "evaluate", path, "--motion", spec, "--size", f"{w}x{h}")
    cmd += ["--seed", str(seed)]
    # --force: a rerun of the sweep replaces its own earlier reports
    res = subprocess.run(
        [*cmd, *extra, "-o", str(folder), "--force"], capture_output=True, text=True
    )
    run = f"{path.stem} {spec} {' '.join(extra)} seed {seed} ({w}x{h})"
    if res.returncode != 0:
        why = (res.stderr.strip().splitlines() or [f"exit status {res.returncode}"])[-1]
        print(f"{run}: FAILED: {why}", flush=True)
        return None
    print(f"{run}: {time.perf_counter() - t0:.0f} s", flush=True)
    return read_results(folder)


def main(argv: list[str]) -> int:
    if not SHARED_HDR.is_dir():
        print("evaluate-shared: ../shared/data/hdr absent, skipped")
        return 0
    out = Path(argv[0]) if argv else Path("eval_out")
    scale = float(option_value(argv, "--size-scale", "1"))
    reach = option_value(argv, "--reach-subframes", "1")
    extra = () if float(reach) == 1 else ("--reach-subframes", reach)
    names = [a for a in argv[1:] if a in SCENES] or SCENES
    summary_only = "--summary-only" in argv
    out.mkdir(exist_ok=True)
    rows = []
    for name in names:
        path = SHARED_HDR / f"{name}.exr"
        w, h = scene_size(path)
        w, h = int(round(w * scale)), int(round(h * scale))
        motions = sweep_motions(path, w, h)
        for tag, spec in motions.items():
            folder = out / f"{name}_{tag}"
            if summary_only:
                table = read_results(folder)
            else:
                table = run_evaluate(path, spec, (w, h), folder, *extra)
            if table is None:
                continue
            rows.append((name, tag, table, tag == "translate" or _placed_on_dark(tag, motions)))
    print(
        f"\nN = {reach}: the scenes' 99.9th-percentile luminance reaches the threshold in N subframes"
    )
    print(
        "dark-pixel RMS, stops (acceptance: deblur >= 30% below static; deblur < paper <= static"
        " < adaptive; deblur <= 1.25 x oracle; long, short worse than static on all-pixel RMS)"
    )
    print(
        "| scene | motion | deblur | paper | static | adaptive | oracle | cut vs static |"
        " deblur/oracle | ranking | all: deblur | all: static | all: long | all: short |"
        " long, short > static |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    verdicts = []
    for name, tag, t, in_set in rows:
        v = _verdicts(t)
        verdicts.append((v, in_set))
        print(
            f"| {name} | {tag} | {_f(v['d'], '.4f')} | {_f(v['p'], '.4f')} | {_f(v['s'], '.4f')} |"
            f" {_f(v['a'], '.4f')} | {_f(v['o'], '.4f')} | {_f(100 * v['cut value'], '.0f', '%')} |"
            f" {_f(v['ratio'], '.2f')} | {_yes(v['ranking'])} | {v['all d']:.3f} |"
            f" {v['all s']:.3f} | {v['all l']:.3f} | {v['all sh']:.3f} |"
            f" {_yes(v['long worse'])}, {_yes(v['short worse'])} |"
        )
    print(
        "\nRuns on which each point holds (dark-pixel points: runs with dark pixels only;"
        " 'set': translate and the object on dark content, the central one where the"
        " scene has no other)"
    )
    print("| point | all runs | set |")
    print("|---|---:|---:|")
    for point, label in POINTS.items():
        cells = []
        for chosen in (False, True):
            marks = [v[point] for v, in_set in verdicts if in_set or not chosen]
            marks = [m for m in marks if m is not None]
            cells.append(f"{sum(marks)} of {len(marks)}")
        print(f"| {label} | {cells[0]} | {cells[1]} |")
    return 0


#: The acceptance points the summary counts, by the key :func:`_verdicts` gives them.
POINTS = {
    "cut": "deblur's dark RMS >= 30% below static's",
    "ranking": "dark RMS deblur < paper <= static < adaptive",
    "oracle": "deblur <= 1.25 x oracle (dark RMS)",
    "long worse": "long worse than static (all-pixel RMS)",
    "short worse": "short worse than static (all-pixel RMS)",
}


def _placed_on_dark(tag: str, motions: dict[str, str]) -> bool:
    """Is this object run the one placed on dark content (module docstring)?"""
    return tag == "object-dark" or (tag == "object" and "object-dark" not in motions)


def read_results(folder: Path) -> dict[str, dict[str, str]] | None:
    """A finished run's results.csv rows by method, or None (and a line) if it has none."""
    try:
        with open(folder / "results.csv") as f:
            return {r["method"]: r for r in csv.DictReader(f)}
    except OSError:
        print(f"{folder}: no results.csv", flush=True)
        return None


def _verdicts(t: dict[str, dict[str, str]]) -> dict[str, float | bool | None]:
    """One run's figures and, per acceptance point, True/False (None: no dark pixel)."""

    def g(m: str, col: str = "dark_rms") -> float:
        try:
            return float(t[m][col])
        except (KeyError, ValueError):
            return float("nan")

    names = ("vet-deblur", "vet-deblur-paper", "vet-static", "adaptive-attenuation")
    d, p, s, a = (g(m) for m in names)
    o = g("vet-deblur-oracle")
    dark = s == s
    cut = 1 - d / s if dark and s > 0 else float("nan")
    ratio = d / o if o else float("nan")
    sa, la, sh = g("vet-static", "all_rms"), g("long", "all_rms"), g("short", "all_rms")
    return {
        "d": d,
        "p": p,
        "s": s,
        "a": a,
        "o": o,
        "cut value": cut,
        "ratio": ratio,
        "all d": g("vet-deblur", "all_rms"),
        "all s": sa,
        "all l": la,
        "all sh": sh,
        "cut": (cut >= 0.30) if dark else None,
        "ranking": (d < p <= s < a) if dark else None,
        "oracle": (ratio <= 1.25) if dark else None,
        "long worse": la > sa,
        "short worse": sh > sa,
    }


def _yes(flag: bool | None) -> str:
    return "-" if flag is None else ("yes" if flag else "no")


def _f(value: float, spec: str, unit: str = "") -> str:
    """A summary cell; '-' where the scene has no dark pixel (NaN)."""
    return "-" if value != value else f"{value:{spec}}{unit}"


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
