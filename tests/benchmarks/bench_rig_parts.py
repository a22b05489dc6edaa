"""Benchmark: what each part of a real rig costs the deblur along the true motion.

For a scene of ../shared/data/hdr (builtin:interior when it is absent) with
``translate:30,0`` at a working size (default 320x240), seed 0: the oracle deblur's
(``vet-deblur-oracle``: the true motion, so that only the rig's model is measured)
dark-pixel RMS and all-pixel median and RMS error in stops, on the ideal rig, on the
ideal rig with the LCoS parts alone (relay blur, per-cell leakage, switching time:
the VET image's exposure, which the deblur models through the equivalent exposure
time of :func:`stages.deblur.problem.effective_T`), on the realistic rig without them
(the measurement camera's grid, distortion, gain, vignetting and the trigger), and on
the realistic rig.

Run: ``.venv/bin/python -m tests.benchmarks.bench_rig_parts [WxH] [SCENE ...]``.
"""

from __future__ import annotations

import sys

from tests.benchmarks.common import SHARED_HDR

#: The LCoS parts of the realistic profile (:func:`stages.optics.realistic_parts`).
LCOS_PARTS = ("relay_blur_px", "leakage", "leakage_spread", "leakage_seed", "switch_s")
SCENES = ("Desk", "CandleGlass")


def variants(size: tuple[int, int]) -> list[tuple[str, str, dict]]:
    """(label, profile, rig changes) of each rig measured."""
    from stages.optics import realistic_parts

    real = realistic_parts(size)
    lcos = {k: real[k] for k in LCOS_PARTS}
    ideal_lcos = {"relay_blur_px": 0.0, "leakage_spread": 0.0, "switch_s": 0.0}
    return [
        ("ideal", "ideal", {}),
        ("ideal + LCoS parts", "ideal", lcos),
        ("realistic - LCoS parts", "realistic", ideal_lcos),
        ("realistic", "realistic", {}),
    ]


def main(size: tuple[int, int] = (320, 240), scenes: list[str] | None = None) -> None:
    from stages.evaluate import run_evaluation

    if scenes is None:
        found = [
            str(SHARED_HDR / f"{s}.exr") for s in SCENES if (SHARED_HDR / f"{s}.exr").is_file()
        ]
        scenes = found or ["builtin:interior"]
    w, h = size
    print(f"oracle deblur (true motion) per rig, translate:30,0, {w}x{h}, seed 0")
    print(
        f"{'scene':14s} {'rig':24s} {'dark_rms':>8s} {'all_med':>8s} {'all_rms':>8s} {'time_s':>6s}"
    )
    for scene in scenes:
        for label, profile, changes in variants(size):
            ev = run_evaluation(
                scene,
                "translate:30,0",
                size,
                rows=("vet-deblur-oracle",),
                rig_profile=profile,
                rig_changes=changes,
            )
            s = ev.scores["vet-deblur-oracle"]
            name = scene.rsplit("/", 1)[-1].removesuffix(".exr")
            print(
                f"{name:14s} {label:24s} {s['dark']['rms']:8.4f} {s['all']['median']:8.4f}"
                f" {s['all']['rms']:8.4f} {ev.runtime_s['vet-deblur-oracle']:6.0f}",
                flush=True,
            )


if __name__ == "__main__":
    from stages.scenes import parse_size

    args = sys.argv[1:]
    dims = parse_size(args.pop(0)) if args and "x" in args[0] else (320, 240)
    main(dims, args or None)
