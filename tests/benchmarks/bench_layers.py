"""Benchmark: the layered motion estimate on the shared scenes' moving objects.

For each scene in ../shared/data/hdr and both object placements of ``make
evaluate-shared`` (the central quarter-area rectangle and the one on the scene's dark
content, moving at 40,10 px/s), plus ``translate:30,0`` and a still capture, and first
the README's ``builtin:interior`` object and the same object at two placements away from
the lamp: the layer velocities found, the share of the frame whose estimated velocity is
more than 5 px/s off the truth (the wrong layer), that share among the dark pixels, the
share of the truly moving points estimated still, the model check's share of what the
layers miss that a dense field explains (the layers stand below 0.1;
:func:`stages.deblur.layers.layered_model_check`), and the estimate's run time. The
shared scenes are skipped cleanly when ../shared is absent. Run: ``.venv/bin/python -m
tests.benchmarks.bench_layers``.
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

    out = {}
    print(
        "| scene | motion | layer velocities (px/s) | wrong layer: frame | dark "
        "| moving points estimated still | model check: missed share | time s |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|")

    def row(name: str, tag: str, scene, spec: str) -> None:
        h, w = scene.radiance.shape[:2]
        rig = RigParams(sensor_size=(w, h))
        cap = simulate(scene, parse_motion(spec), rig, seed=0, methods=["vet"])["vet"]
        t0 = time.perf_counter()
        est = estimate_layers(cap)
        dt = time.perf_counter() - t0
        err = np.hypot(*(est.velocity - cap.truth_motion).transpose(2, 0, 1))
        dark = cap.T >= rig.frame_s * (1 - 1e-6)
        wrong = float((err > 5).mean())
        wrong_dark = float((err[dark] > 5).mean()) if dark.any() else float("nan")
        moving = np.any(cap.truth_motion != 0, axis=2)
        missed = moving & ~np.any(est.velocity != 0, axis=2)
        missed_share = float(missed.sum() / moving.sum()) if moving.any() else float("nan")
        vels = ", ".join(f"({u:.2f}, {v:.2f})" for u, v in est.layer_velocities)
        print(
            f"| {name} | {tag} | {vels} | {100 * wrong:.2f}% | {100 * wrong_dark:.2f}% |"
            f" {100 * missed_share:.2f}% | {est.check.missed_share:.3f}"
            f"{'' if est.check.fits else ' (rejected)'} | {dt:.1f} |",
            flush=True,
        )
        out[(name, tag)] = wrong

    # The README's evaluate example: a lamp-lit object whose dark part (the wall, ~8 e-
    # per pixel and measuring bin) the bins cannot show moving; then the same object
    # placed where the lamp is not (bottom left, top right): all dark wall and floor.
    interior = load_scene("builtin:interior", (320, 256))
    for xy in ("80,64", "0,128", "160,0"):
        spec = f"object:{xy},160,128:40,10"
        row("builtin:interior 320x256", spec, interior, spec)
    if not SHARED_HDR.is_dir():
        print("bench layers: ../shared/data/hdr absent, shared scenes skipped")
        return out
    for name in SCENES:
        path = SHARED_HDR / f"{name}.exr"
        scene = load_scene(str(path))
        h, w = scene.radiance.shape[:2]
        row(name, "none", scene, "none")  # a still capture: no layer may be invented
        for tag, spec in sweep_motions(path, w, h).items():
            row(name, tag, scene, spec)
    return out


if __name__ == "__main__":
    main()
