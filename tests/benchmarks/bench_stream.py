"""Benchmark: what the measuring stream gives the deblur, on the shared HDR scenes.

Three tables at a working size (default 320x240; the scenes of ../shared/data/hdr, the
builtins when it is absent), seed 0:

1. **Path detector.** The departure from a constant velocity of the path most tiles
   follow (:attr:`stages.deblur.layers.paths.TilePaths.main_deviation_px`) and of any
   path, for motions that change within the frame (shake) and ones that do not; the
   default deblur follows measured paths where the first reaches ``MIN_DEVIATION_PX``.
2. **Path groups.** The default deblur of ``shake:4`` with the stream registered in 16,
   32 and 48 groups (:data:`stages.deblur.layers.paths.GROUPS`), all-pixel median / RMS
   error in stops, beside the burst merge.
3. **Edge scale.** The default deblur with the true motion, ``translate:30,0``, with the
   smoothness's edge scale fixed (``JointOptions.edge_snr`` 0) and adapted (3).

Run: ``.venv/bin/python -m tests.benchmarks.bench_stream [WxH]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "hdr"


def _scenes() -> list[str]:
    found = sorted(str(p) for p in SHARED.glob("*.exr")) if SHARED.is_dir() else []
    return found or ["builtin:interior", "builtin:chart"]


def _capture(src: str, spec: str, size: tuple[int, int]):
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = RigParams(sensor_size=size)
    return simulate(load_scene(src, size), parse_motion(spec), rig, seed=0)["vet"]


def _errors(cap, img) -> str:
    from stages.metrics import measurable_floor, stops_error

    floor = measurable_floor(cap.rig, cap.radiance_scale)
    e = stops_error(img.radiance, cap.truth, cap.T, cap.rig.frame_s, floor=floor)["all"]
    return f"{e['median']:.3f}/{e['rms']:.3f}"


def main(size: str = "320x240") -> None:
    import logging

    import stages.deblur.layers.paths as paths
    from stages.burst import burst_hdr
    from stages.deblur import deblur
    from stages.deblur.joint import JointOptions
    from stages.scenes import parse_size

    logging.getLogger("stages").setLevel(logging.ERROR)  # (scene clean-up warnings)
    wh = parse_size(size)
    scenes = _scenes()
    name = {s: Path(s).stem if not s.startswith("builtin:") else s for s in scenes}

    print(f"1. path detector, {size}: departure from a constant velocity, px")
    print(f"   (main path / any path; the default follows paths at >= {paths.MIN_DEVIATION_PX})")
    for spec in ("translate:30,0", "rotate:4", "object:80,60,120,100:40,10", "shake:2"):
        row = []
        for s in scenes:
            cap = _capture(s, spec, wh)
            tp = paths.tile_paths(cap.measure, cap.measure_times, cap.rig)
            row.append(f"{name[s]} {tp.main_deviation_px:.2f}/{tp.deviation_px:.2f}")
        print(f"   {spec:28s} " + "  ".join(row), flush=True)

    print(f"2. default deblur of shake:4, {size}, all-pixel median/RMS stops, by path groups")
    groups = paths.GROUPS
    try:
        for s in scenes:
            cap = _capture(s, "shake:4", wh)
            row = []
            for g in (16, 32, 48):
                paths.GROUPS = g
                row.append(f"{g}: {_errors(cap, deblur(cap)[0])}")
            row.append(f"burst-merge: {_errors(cap, burst_hdr(cap))}")
            print(f"   {name[s]:18s} " + "  ".join(row), flush=True)
    finally:
        paths.GROUPS = groups

    print(f"3. deblur with the true motion, translate:30,0, {size}: edge scale fixed / adapted")
    for s in scenes:
        cap = _capture(s, "translate:30,0", wh)
        row = []
        for k in (0.0, 3.0):
            img, _ = deblur(cap, motion_init="truth", options=JointOptions(edge_snr=k))
            row.append(f"edge_snr {k:g}: {_errors(cap, img)}")
        print(f"   {name[s]:18s} " + "  ".join(row), flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
