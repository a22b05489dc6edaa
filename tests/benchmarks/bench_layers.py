"""Benchmark: the layered motion estimate on the shared scenes' moving objects.

For each scene in ../shared/data/hdr and both object placements of ``make
evaluate-shared`` (the central quarter-area rectangle and the one on the scene's dark
content, moving at 40,10 px/s), plus ``translate:30,0``: the layer velocities found, the
share of the frame whose estimated velocity is more than 5 px/s off the truth (the wrong
layer), that share among the dark pixels, and the estimate's run time. Skips cleanly
when ../shared is absent. Run: ``.venv/bin/python -m tests.benchmarks.bench_layers``.
"""

from __future__ import annotations

import time


def main() -> dict:
    import numpy as np

    from stages.deblur.layers import estimate_layers
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate
    from tests.benchmarks.common import SHARED_HDR
    from tests.benchmarks.evaluate_shared import SCENES, sweep_motions

    if not SHARED_HDR.is_dir():
        print("bench layers: ../shared/data/hdr absent, skipped")
        return {}
    out = {}
    print("| scene | motion | layer velocities (px/s) | wrong layer: frame | dark | time s |")
    print("|---|---|---|---:|---:|---:|")
    for name in SCENES:
        path = SHARED_HDR / f"{name}.exr"
        scene = load_scene(str(path))
        h, w = scene.radiance.shape[:2]
        for tag, spec in sweep_motions(path, w, h).items():
            rig = RigParams(sensor_size=(w, h))
            cap = simulate(scene, parse_motion(spec), rig, seed=0, methods=["vet"])["vet"]
            t0 = time.perf_counter()
            est = estimate_layers(cap)
            dt = time.perf_counter() - t0
            err = np.hypot(*(est.velocity - cap.truth_motion).transpose(2, 0, 1))
            dark = cap.T >= rig.frame_s * (1 - 1e-6)
            wrong = float((err > 5).mean())
            wrong_dark = float((err[dark] > 5).mean()) if dark.any() else float("nan")
            vels = ", ".join(f"({u:.2f}, {v:.2f})" for u, v in est.layer_velocities)
            print(
                f"| {name} | {tag} | {vels} | {100 * wrong:.2f}% | {100 * wrong_dark:.2f}% |"
                f" {dt:.1f} |",
                flush=True,
            )
            out[(name, tag)] = wrong
    return out


if __name__ == "__main__":
    main()
