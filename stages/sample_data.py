"""Regenerate sample_data/ deterministically: ``python -m stages.sample_data sample_data``.

Writes a small scene and small captures made by vet's own generators (same pixels for
the same seed), used by the README examples and the Make recipes:

- ``scenes/interior.exr``: the builtin lamp-lit interior, 256x192, linear RGB scene units;
- ``captures/interior_still.exr``: a VET capture of it, still, seed 1, 4 measuring bins;
- ``captures/interior_pan.exr``: a VET capture panning at 30 px/s, seed 1, 4 measuring bins;
- ``interior_hdr.png`` and ``interior_T.png``: the README's pictures.
"""

from __future__ import annotations

import sys
from pathlib import Path

SIZE = (256, 192)
SEED = 1


def generate(folder: Path) -> list[Path]:
    from .falsecolor import render_exposure_time_map
    from .formats import HDRImage, write_capture, write_hdr
    from .formats.images import write_display_image
    from .hdr_static import hdr_static
    from .motion import parse_motion
    from .rig import RigParams
    from .scenes import load_scene
    from .simulate import simulate
    from .tonemap import tonemap

    (folder / "scenes").mkdir(parents=True, exist_ok=True)
    (folder / "captures").mkdir(exist_ok=True)
    scene = load_scene("builtin:interior", SIZE)
    rig = RigParams(sensor_size=SIZE)
    written = []
    scene_file = folder / "scenes" / "interior.exr"
    write_hdr(
        scene_file,
        HDRImage(scene.radiance, scene.channels, {"units": "scene", "scene": scene.source}),
    )
    written.append(scene_file)
    for name, motion in (("interior_still", "none"), ("interior_pan", "translate:30,0")):
        cap = simulate(scene, parse_motion(motion), rig, seed=SEED, measure_bins=4)["vet"]
        cap.meta["provenance"][0]["command"] = "python -m stages.sample_data"
        cap.meta["provenance"][0]["time"] = ""
        write_capture(folder / "captures" / f"{name}.exr", cap)
        written.append(folder / "captures" / f"{name}.exr")
        if motion == "none":
            img = hdr_static(cap)
            write_display_image(folder / "interior_hdr.png", tonemap(img.radiance, "log"))
            write_display_image(
                folder / "interior_T.png",
                render_exposure_time_map(cap.T, rig.frame_s, rig.subframe_s),
            )
            written += [folder / "interior_hdr.png", folder / "interior_T.png"]
    return written


if __name__ == "__main__":
    for p in generate(Path(sys.argv[1] if len(sys.argv) > 1 else "sample_data")):
        print(p)
