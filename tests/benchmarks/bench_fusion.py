"""Benchmark: what pixels that no moving path touches take (``fuse_still``).

Such a pixel's value has a closed form: hdr-static's (the maximum-likelihood value of
its VET data) or the maximum-likelihood value of the VET image and the measuring images
together (:func:`stages.deblur.joint.fuse_still`). The default deblur fuses them when
the motion moves some pixel and keeps hdr-static when it moves none;
``vet deblur --fuse-still`` always fuses them and ``--keep-still`` never does
(``deblur(..., fuse_still=True|False)``). This prints what that trades:

1. a capture of a still scene (640x512 RGB ``builtin:interior``): the median change to
   hdr-static (the issue's target for a still scene is under 0.01 stops) and the
   dark-pixel RMS error, of the default and of ``--fuse-still``;
2. GoldenGate with the central quarter-area object, ``object:W/4,H/4,W/2,H/2:40,10``
   (needs ../shared; no dark pixel there moves, so the ranking default deblur < paper
   deblur rests on the still pixels): dark-pixel RMS error of hdr-static, the paper
   method, the default deblur and ``--keep-still``;
3. Cannon with the central quarter-area object (needs ../shared; a bright scene, no
   pixel exposed the whole frame): over the pixels no moving path touches, the error of
   hdr-static's value (``--keep-still``) and of the fused one (the default), split by
   exposure time, with the global scale (2 ** median signed error: a bias shows there).

Errors are scored as ``vet evaluate`` scores them (stops, measurable floor, 8 px
border). Run: ``.venv/bin/python -m tests.benchmarks.run fusion``.
"""

from __future__ import annotations

import time


def main() -> dict:
    return {
        "still": still_scene(),
        "goldengate_object": goldengate_object(),
        "cannon_object": cannon_object(),
    }


def _dark_rms(cap):
    """Dark-pixel RMS error in stops of an image of ``cap``'s scene, as evaluate scores."""
    from stages.metrics import measurable_floor, stops_error

    floor = measurable_floor(cap.rig, float(cap.radiance_scale))
    return lambda radiance: stops_error(radiance, cap.truth, cap.T, cap.rig.frame_s, floor=floor)[
        "dark"
    ]["rms"]


def still_scene(size: str = "640x512") -> dict:
    import numpy as np

    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import builtin_interior, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    rig = RigParams(sensor_size=(w, h))
    cap = simulate(builtin_interior(w, h), parse_motion("none"), rig, seed=0, methods=["vet"])[
        "vet"
    ]
    dark_rms = _dark_rms(cap)
    static = hdr_static(cap).radiance
    out = {"static_dark_rms": dark_rms(static)}
    print(
        f"still scene {size} RGB ({float(np.mean(cap.T == cap.T.max())):.1%} of pixels exposed"
        f" the whole frame): hdr-static dark RMS {out['static_dark_rms']:.4f} stops",
        flush=True,
    )
    for name, fuse in (("default", None), ("--fuse-still", True)):
        img, _ = deblur(cap, "vet", fuse_still=fuse)
        change = float(np.median(np.abs(np.log2(img.radiance / static))))
        out[name] = {"median_change": change, "dark_rms": dark_rms(img.radiance)}
        print(
            f"  deblur {name}: median change to hdr-static {change:.4f} stops (target < 0.01),"
            f" dark RMS {out[name]['dark_rms']:.4f} stops",
            flush=True,
        )
    return out


def _central_object(name: str):
    """Capture (seed 0) of shared scene ``name`` with its central quarter-area object
    moving at (40, 10) px/s, and the motion spec; None without ../shared."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate
    from tests.benchmarks.common import SHARED_HDR

    path = SHARED_HDR / f"{name}.exr"
    if not path.exists():
        print(f"{name} object: skipped ({path} not present)", flush=True)
        return None, None
    scene = load_scene(str(path), None)
    h, w = scene.radiance.shape[:2]
    spec = f"object:{w // 4},{h // 4},{w // 2},{h // 2}:40,10"
    rig = RigParams(sensor_size=(w, h))
    return simulate(scene, parse_motion(spec), rig, seed=0, methods=["vet"])["vet"], spec


def goldengate_object() -> dict | None:
    from stages.deblur import deblur
    from stages.hdr_static import hdr_static

    cap, spec = _central_object("GoldenGate")
    if cap is None:
        return None
    h, w = cap.shape
    dark_rms = _dark_rms(cap)
    rows = {
        "hdr-static": lambda: hdr_static(cap),
        "paper": lambda: deblur(cap, "paper")[0],
        "default": lambda: deblur(cap, "vet")[0],
        "--keep-still": lambda: deblur(cap, "vet", fuse_still=False)[0],
    }
    print(f"GoldenGate {w}x{h} {spec}, seed 0, dark pixels (RMS, stops):", flush=True)
    out = {}
    for name, run in rows.items():
        t0 = time.perf_counter()
        out[name] = dark_rms(run().radiance)
        print(f"  {name:13s} {out[name]:.7f}  ({time.perf_counter() - t0:.1f} s)", flush=True)
    for name in ("default", "--keep-still"):
        holds = out[name] < out["paper"] <= out["hdr-static"]
        print(f"  ranking deblur {name} < paper <= hdr-static: {'holds' if holds else 'fails'}")
    return out


def cannon_object() -> dict | None:
    import numpy as np

    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.metrics import measurable_floor, stops_error

    cap, spec = _central_object("Cannon")
    if cap is None:
        return None
    h, w = cap.shape
    static = hdr_static(cap).radiance
    kept, _ = deblur(cap, "vet", fuse_still=False)
    fused, _ = deblur(cap, "vet")
    assert fused.meta["still_pixels"] == "fused"
    # Pixels no moving path touches: exactly hdr-static's with --keep-still.
    still = np.all(kept.radiance == static, axis=2)
    floor = measurable_floor(cap.rig, float(cap.radiance_scale))
    tf = cap.rig.frame_s
    groups = {
        "T < 50 ms": still & (cap.T < 0.05),
        "50 ms <= T < frame": still & (cap.T >= 0.05) & (cap.T < tf * (1 - 1e-6)),
        "whole frame": still & (cap.T >= tf * (1 - 1e-6)),
    }
    print(
        f"Cannon {w}x{h} {spec}, seed 0: {float(still.mean()):.1%} of pixels still;"
        " still pixels (stops):",
        flush=True,
    )
    out = {}
    for gname, mask in groups.items():
        row = {}
        for name, img in (("--keep-still", kept), ("default (fused)", fused)):
            err = stops_error(img.radiance, cap.truth, floor=floor, mask=mask)
            row[name] = {"rms": err["all"]["rms"], "n": err["all"]["n"], "scale": err["scale"]}
        out[gname] = row
        k, f = row["--keep-still"], row["default (fused)"]
        if k["n"] == 0:
            print(f"  {gname:19s} n={0:7d}  (no still pixel with this exposure time)", flush=True)
            continue
        print(
            f"  {gname:19s} n={k['n']:7d}  RMS --keep-still {k['rms']:.4f}, default {f['rms']:.4f};"
            f" scale {k['scale']:.4f}, {f['scale']:.4f}",
            flush=True,
        )
    return out


if __name__ == "__main__":
    main()
