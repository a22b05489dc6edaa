"""Benchmark: the burst merge (``vet deblur --method burst``) against the deblur's oracle.

For each size (default 320x240 and 1280x1024, RGB: Cannon of ../shared/data/hdr, else
``builtin:interior``) and motion (a pan ``translate:30,0``, ``shake:4`` and a
quarter-frame object moving (40, 10) px/s), one capture (seed 0, every one of the 131
subframes kept, the ideal rig) is reconstructed by the burst merge and by the deblur along
the true motion (``motion_init="truth"``, the oracle), one after the other in this
process. Printed per run: wall and CPU seconds of each, and the all-pixel median / RMS
error in stops of each (and of hdr-static) against the truth. With ``--profile`` the
burst merge's top cProfile entries follow each run.

Run: ``.venv/bin/python -m tests.benchmarks.bench_burst [WxH ...] [--motions TAG,...]
[--profile]`` (TAG: pan, shake, object).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "hdr"
MOTIONS = {"pan": "translate:30,0", "shake": "shake:4", "object": None}


def _scene() -> str:
    cannon = SHARED / "Cannon.exr"
    return str(cannon) if cannon.is_file() else "builtin:interior"


def _spec(tag: str, w: int, h: int) -> str:
    if tag == "object":
        return f"object:{w // 4},{h // 4},{w // 2},{h // 2}:40,10"
    return MOTIONS[tag]


def _timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def run(size: tuple[int, int], tag: str, profile: bool = False) -> str:
    """One row: the burst merge and the oracle on one capture (module docstring)."""
    import cProfile
    import io
    import pstats

    from stages.burst import burst_hdr
    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.metrics import measurable_floor, stops_error
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    w, h = size
    spec = _spec(tag, w, h)
    rig = RigParams(sensor_size=size)
    cap = simulate(load_scene(_scene(), size), parse_motion(spec), rig, seed=0)["vet"]
    floor = measurable_floor(rig, cap.radiance_scale)

    def err(img) -> str:
        e = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s, floor=floor)["all"]
        return f"{e['median']:.4f} / {e['rms']:.4f}"

    prof = cProfile.Profile() if profile else None
    if prof:
        prof.enable()
    burst, bw, bc = _timed(lambda: burst_hdr(cap))
    if prof:
        prof.disable()
    (oracle, _), ow, oc = _timed(lambda: deblur(cap, motion_init="truth"))
    row = (
        f"| {w}x{h} | {tag} | {bw:.1f} / {bc:.1f} | {ow:.1f} / {oc:.1f} | {bw / ow:.2f} |"
        f" {err(burst)} | {err(oracle)} | {err(hdr_static(cap))} |"
    )
    if prof:
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(12)
        row += "\n" + buf.getvalue()
    return row


def main(argv: list[str] | None = None) -> None:
    import logging

    argv = sys.argv[1:] if argv is None else argv
    logging.getLogger("stages").setLevel(logging.ERROR)
    sizes = [tuple(int(v) for v in a.split("x")) for a in argv if "x" in a and a[0].isdigit()]
    sizes = sizes or [(320, 240), (1280, 1024)]
    tags = MOTIONS
    if "--motions" in argv:
        tags = argv[argv.index("--motions") + 1].split(",")
    print(f"scene {Path(_scene()).name}, ideal rig, 131 subframes, seed 0")
    print(
        "| size | motion | burst s wall / CPU | oracle s wall / CPU | burst / oracle wall |"
        " burst median / RMS | oracle median / RMS | hdr-static median / RMS |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size in sizes:
        for tag in tags:
            print(run(size, tag, "--profile" in argv), flush=True)


if __name__ == "__main__":
    main()
