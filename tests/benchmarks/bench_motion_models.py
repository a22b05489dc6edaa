"""Benchmark: deblur of motions that are no set of translating layers (rotations).

The default deblur starts from the layered motion estimate unless its model check
(:func:`stages.deblur.layers.layered_model_check`) finds that a dense field explains the
measuring bins clearly better; then it starts from one affine field where that explains
the bins about as well as the dense field (refining its six parameters on the misfit),
else from dense flow. For rotations of the
builtin interior (320x256) and of each scene in ../shared/data/hdr (at half size, so
that the module runs in minutes; skipped cleanly when ../shared is absent) this prints
the check's figures (the share of what the layers miss that the dense field explains,
whether the layered model stands, the share of what the dense field explains that the
affine field misses, and the model the default took) and the RMS error in stops over
dark pixels (over all pixels in brackets; Cannon has no dark pixel, '-') of hdr-static,
of deblur from the layered estimate (what deblur did before the check), from dense flow
(what it did before the affine field), of the default deblur, and of deblur from the
true motion, with the default's time.
Run: ``.venv/bin/python -m tests.benchmarks.run motion_models``.
"""

from __future__ import annotations

import time
from dataclasses import replace


def main() -> dict:
    import stages.deblur.affine as affine
    from stages.deblur import deblur
    from stages.deblur.layers import estimate_layers
    from stages.hdr_static import hdr_static
    from stages.metrics import measurable_floor, stops_error
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate
    from tests.benchmarks.common import SHARED_HDR
    from tests.benchmarks.evaluate_shared import SCENES, scene_size

    out = {}
    print(
        "| scene | motion | missed share | layered model | affine misses | model |"
        " dark RMS: hdr-static | deblur, layered start | deblur, dense flow |"
        " deblur (default) | deblur, true motion | default / true | default s |"
    )
    print("|---|---|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")

    def row(name: str, scene, spec: str) -> None:
        h, w = scene.radiance.shape[:2]
        rig = RigParams(sensor_size=(w, h))
        cap = simulate(scene, parse_motion(spec), rig, seed=0, methods=["vet"])["vet"]
        floor = measurable_floor(rig, cap.radiance_scale)

        def dark(radiance) -> tuple[float, float]:
            e = stops_error(radiance, cap.truth, cap.T, rig.frame_s, floor=floor)
            return e["dark"]["rms"], e["all"]["rms"]

        def cell(rms: tuple[float, float]) -> str:
            d, a = rms
            return f"{'-' if d != d else f'{d:.4f}'} ({a:.4f})"

        est = estimate_layers(cap)
        # Deblur along the layered estimate whatever its check says: given as the motion.
        along_layers = replace(cap, truth_motion=est.velocity)
        layered = dark(deblur(along_layers, motion_init="truth")[0].radiance)
        t0 = time.perf_counter()
        img, _vel = deblur(cap)
        dt = time.perf_counter() - t0
        default = dark(img.radiance)
        gate = affine.AFFINE_MISS_SHARE
        affine.AFFINE_MISS_SHARE = -float("inf")
        try:
            dense = dark(deblur(cap)[0].radiance)
        finally:
            affine.AFFINE_MISS_SHARE = gate
        oracle = dark(deblur(cap, motion_init="truth")[0].radiance)
        fits = "stands" if est.check.fits else "rejected"
        ratio = default[0] / oracle[0] if default[0] == default[0] else default[1] / oracle[1]
        print(
            f"| {name} | {spec} | {est.check.missed_share:.3f} | {fits} |"
            f" {est.check.affine_share:.3f} | {img.meta['motion_model']} |"
            f" {cell(dark(hdr_static(cap).radiance))} | {cell(layered)} | {cell(dense)} |"
            f" {cell(default)} |"
            f" {cell(oracle)} | {ratio:.2f} | {dt:.1f} |",
            flush=True,
        )
        out[(name, spec)] = (default, oracle)

    interior = load_scene("builtin:interior", (320, 256))
    for spec in ("rotate:3", "rotate:6", "rotate:-10"):
        row("builtin:interior 320x256", interior, spec)
    if not SHARED_HDR.is_dir():
        print("bench motion_models: ../shared/data/hdr absent, shared scenes skipped")
        return out
    for name in SCENES:
        path = SHARED_HDR / f"{name}.exr"
        w, h = scene_size(path)
        size = (w // 2, h // 2)
        row(f"{name} {size[0]}x{size[1]}", load_scene(str(path), size), "rotate:4")
    return out


if __name__ == "__main__":
    main()
