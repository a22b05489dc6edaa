"""Benchmark: hdr-static on the realistic rig against the ideal one, on the shared scenes.

For each scene of ../shared/data/hdr (the builtins when it is absent), still, at a working
size (default 320x240), seed 0: the all-pixel median and RMS error in stops of hdr-static
on a capture of the ideal rig, on one of the realistic rig (``--rig-profile realistic``)
reconstructed with its parts, and on the same capture reconstructed with the ideal rig
assumed (``vet hdr-static --assume-ideal-rig``: the parts ignored); the ratios to the
ideal rig's RMS.

Then the same through the emulated rig behind ``vet capture``: the ideal rig
uncalibrated; the realistic rig calibrated first (``vet calibrate --rig sim --rig-profile
realistic``, its parts found) and captured with what that calibration found, the emulated
rig keeping its own truth; hdr-static with the calibrated parts (the calibration's
per-cell leakage map stored with the capture, as ``vet capture --calibration`` does), with
the ideal rig assumed, with one leakage for every cell, with the rig's configured per-cell
pattern in place of the map, and on a capture whose host knew the truth. The emulated rig
runs in real time: on a busy
machine the host falls behind, closures come late (T records them) and the figures move.

Run: ``.venv/bin/python -m tests.benchmarks.bench_rig_model [WxH] [--simulate|--capture]``
(both tables by default, as ``make bench`` runs it); ``--calibrate`` prints the
calibration's errors against the emulated truth alone (``1280x1024 --calibrate``: the
published rig's size).
"""

from __future__ import annotations

import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "hdr"


def _scenes() -> list[str]:
    found = sorted(str(p) for p in SHARED.glob("*.exr")) if SHARED.is_dir() else []
    return found or ["builtin:interior", "builtin:chart"]


def main(size: tuple[int, int] = (320, 240)) -> None:
    """``make bench``: both tables, the simulated captures' and the capture chain's."""
    print("simulate (the reconstruction knows the rig's truth):")
    simulated(size)
    print("calibrate then capture (the host knows what calibration found):")
    capture_chain(size)


def simulated(size: tuple[int, int] = (320, 240)) -> list[dict]:
    from stages.hdr_static import hdr_static
    from stages.metrics import stops_error
    from stages.motion import parse_motion
    from stages.optics import rig_profile
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rows = []
    print(
        f"{'scene':12s} {'ideal med/rms':>16s} {'realistic':>16s} {'ideal assumed':>16s}"
        f" {'ratio':>6s} {'ratio ign':>9s}"
    )
    for src in _scenes():
        scene = load_scene(src, size)
        out = {"scene": Path(src).stem}
        for name, profile, assume in (
            ("ideal", "ideal", False),
            ("realistic", "realistic", False),
            ("ignored", "realistic", True),
        ):
            if name != "ignored":
                cap = simulate(scene, parse_motion("none"), rig_profile(profile, size), seed=0)
                cap = cap["vet"]
            img = hdr_static(cap, assume_ideal_rig=assume)
            e = stops_error(img.radiance, cap.truth, cap.T, cap.rig.frame_s)["all"]
            out[name] = (e["median"], e["rms"])
        r = out["realistic"][1] / out["ideal"][1]
        ri = out["ignored"][1] / out["ideal"][1]
        out["ratio"], out["ratio_ignored"] = r, ri
        print(
            f"{out['scene']:12s} {out['ideal'][0]:7.4f}/{out['ideal'][1]:.4f}"
            f" {out['realistic'][0]:7.4f}/{out['realistic'][1]:.4f}"
            f" {out['ignored'][0]:7.4f}/{out['ignored'][1]:.4f} {r:6.2f} {ri:9.2f}",
            flush=True,
        )
        rows.append(out)
    return rows


def calibration_errors(size: tuple[int, int]) -> dict:
    """``vet calibrate --rig sim --rig-profile realistic`` at ``size``: its errors against
    the emulated truth, one per line."""
    from stages.calibrate import run_calibration

    errors = run_calibration("sim", size=size, profile="realistic").provenance["errors_vs_truth"]
    print(f"calibration errors vs truth, realistic rig {size[0]}x{size[1]}:")
    for k, v in errors.items():
        print(f"  {k:32s} {v:.4g}")
    return errors


def capture_chain(size: tuple[int, int] = (320, 240)) -> list[dict]:
    import dataclasses
    import tempfile

    from stages.calibrate import calibration_changes, run_calibration
    from stages.capture import capture_frame
    from stages.devices.rigs import SimOptions, open_rig
    from stages.hdr_static import hdr_static
    from stages.metrics import stops_error

    cal = run_calibration("sim", size=size, profile="realistic")
    print("calibration errors vs truth:", cal.provenance["errors_vs_truth"])
    changes = calibration_changes(cal)
    rows = []
    print(
        f"{'scene':12s} {'ideal med/rms':>16s} {'calibrated':>16s} {'ideal assumed':>16s}"
        f" {'ratio':>6s} {'ratio ign':>9s} {'ratio uniform':>13s} {'ratio pattern':>13s}"
        f" {'ratio truth':>11s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for src in _scenes():
            out = {"scene": Path(src).stem}
            for name, profile, known in (
                ("ideal", "ideal", {}),
                ("real", "realistic", changes),
                ("real-truth", "realistic", {}),
            ):
                # The emulated rig keeps its truth; the host knows what calibration found.
                opts = SimOptions(scene=src, size=size, profile=profile)
                with open_rig("sim", opts, known=known) as rig:
                    cap = capture_frame(
                        rig,
                        Path(tmp) / f"{out['scene']}-{name}",
                        raw_stream=False,
                        cell_leakage=cal.cell_leakage if name == "real" else None,
                    )
                variants = {name: (cap, False)}
                if name == "real":
                    variants["real-ignored"] = (cap, True)
                    # In place of the calibrated per-cell leakage: none (one leakage), and
                    # the rig's configured pattern (here the emulated truth's).
                    flat = dataclasses.replace(
                        cap, rig=cap.rig.replace(leakage_spread=0.0), cell_leakage=None
                    )
                    variants["real-uniform"] = (flat, False)
                    variants["real-pattern"] = (dataclasses.replace(cap, cell_leakage=None), False)
                for key, (c, assume) in variants.items():
                    img = hdr_static(c, assume_ideal_rig=assume)
                    e = stops_error(img.radiance, c.truth, c.T, c.rig.frame_s)["all"]
                    out[key] = (e["median"], e["rms"])
            print(
                f"{out['scene']:12s} {out['ideal'][0]:7.4f}/{out['ideal'][1]:.4f}"
                f" {out['real'][0]:7.4f}/{out['real'][1]:.4f}"
                f" {out['real-ignored'][0]:7.4f}/{out['real-ignored'][1]:.4f}"
                f" {out['real'][1] / out['ideal'][1]:6.2f}"
                f" {out['real-ignored'][1] / out['ideal'][1]:9.2f}"
                f" {out['real-uniform'][1] / out['ideal'][1]:13.2f}"
                f" {out['real-pattern'][1] / out['ideal'][1]:13.2f}"
                f" {out['real-truth'][1] / out['ideal'][1]:11.2f}",
                flush=True,
            )
            rows.append(out)
    near = sum(r["real"][1] <= 1.25 * r["ideal"][1] for r in rows)
    worse = sum(r["real-ignored"][1] > r["real"][1] for r in rows)
    print(
        f"calibrated within 1.25x of the ideal rig's RMS: {near} of {len(rows)}; "
        f"worse with the calibration withheld: {worse} of {len(rows)}"
    )
    return rows


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    wh = args[0] if args else "320x240"
    w, h = (int(v) for v in wh.split("x"))
    if "--calibrate" in sys.argv:
        calibration_errors((w, h))
    elif "--capture" in sys.argv:
        capture_chain((w, h))
    elif "--simulate" in sys.argv:
        simulated((w, h))
    else:
        main((w, h))
