"""Benchmark: what the measurement camera's sub-pixel placement costs hdr-static.

A still capture (no motion) of a scene at a working size (default 320x240, seed 0):
hdr-static's all-pixel error (stops) on the ideal rig, on the realistic rig, and on the
realistic rig with its measurement camera moved: aligned with the VET sensor (no
homography, no distortion), shifted by whole pixels, and shifted by half a pixel in x
and y. Where the VET pixels saturate, hdr-static's value comes from the measuring
images; a camera that samples the VET grid between its pixels (bilinear weights of four
neighbours) averages away the finest detail there, which no reconstruction gets back.
The scene is ../shared/data/hdr's Cannon (most of whose VET pixels saturate) when
present, else ``builtin:interior``.

Run: ``.venv/bin/python -m tests.benchmarks.bench_camera_offset [WxH] [SCENE ...]``.
"""

from __future__ import annotations

import sys

from tests.benchmarks.common import SHARED_HDR

IDENTITY = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def placements() -> list[tuple[str, str, dict]]:
    """(label, profile, rig changes) of each measurement camera measured."""

    def shifted(dx: float, dy: float) -> dict:
        hom = [[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]
        return {"measure_homography": hom, "measure_k1": 0.0, "measure_k2": 0.0}

    return [
        ("ideal rig", "ideal", {}),
        ("realistic", "realistic", {}),
        ("realistic, camera aligned", "realistic", shifted(0.0, 0.0)),
        ("realistic, shifted (2, -2) px", "realistic", shifted(2.0, -2.0)),
        ("realistic, shifted (0.5, 0.5) px", "realistic", shifted(0.5, 0.5)),
    ]


def main(size: tuple[int, int] = (320, 240), scenes: list[str] | None = None) -> None:
    from stages.evaluate import run_evaluation

    if scenes is None:
        cannon = SHARED_HDR / "Cannon.exr"
        scenes = [str(cannon)] if cannon.is_file() else ["builtin:interior"]
    w, h = size
    print(f"hdr-static of a still capture per measurement camera placement, {w}x{h}, seed 0")
    print(f"{'scene':12s} {'rig':34s} {'all_med':>8s} {'all_rms':>8s}")
    for scene in scenes:
        for label, profile, changes in placements():
            ev = run_evaluation(
                scene,
                "none",
                size,
                rows=("vet-static",),
                rig_profile=profile,
                rig_changes=changes,
            )
            s = ev.scores["vet-static"]
            name = scene.rsplit("/", 1)[-1].removesuffix(".exr")
            print(
                f"{name:12s} {label:34s} {s['all']['median']:8.4f} {s['all']['rms']:8.4f}",
                flush=True,
            )
        print(f"{name:12s} VET pixels saturated (realistic rig): {saturated(scene, size):.2f}")


def saturated(scene: str, size: tuple[int, int]) -> float:
    """Share of the realistic rig's VET pixels that saturate on a still ``scene``."""
    import numpy as np

    from stages.motion import parse_motion
    from stages.optics import rig_profile
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = rig_profile("realistic", size)
    cap = simulate(load_scene(scene, size), parse_motion("none"), rig, seed=0, methods=["vet"])
    return float(np.mean(cap["vet"].I.max(axis=-1) >= rig.saturation_dn))


if __name__ == "__main__":
    from stages.scenes import parse_size

    args = sys.argv[1:]
    dims = parse_size(args.pop(0)) if args and "x" in args[0] else (320, 240)
    main(dims, args or None)
