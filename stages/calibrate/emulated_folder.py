"""A folder of calibration frames recorded on the emulated rig, in the layout that
:func:`.recorded.calibrate_from_folder` reads (docs/calibration.md), and the errors of a
calibration made from it against the emulated truth.

What :func:`write_emulated_folder` records, every frame a 16-bit PNG of the camera's
codes with the black level added back (a raw camera's pedestal, which the dark frames'
bias measures):

- the acquisition of :func:`.acquire.acquire_frames` on the emulated rig (dark, open,
  closed, Gray-code and measurement flat-field frames), each frame it averages;
- the chessboard target in two poses (:func:`.parts.emulated_target_stack`), both
  cameras, and ``[calibration] chessboard`` in ``rig.toml``;
- the switching series (:func:`.parts.emulated_switching_frames`): every cell applied
  closed at subframe :data:`SWITCH_SUBFRAME`, windows 0.25 ms apart from 2 ms before
  its nominal time to 5 ms after, :data:`SWITCH_FRAMES` frames each;
- the measurement camera's frame ids and timestamps over
  :data:`.frame_clock.EMULATED_FRAMES` subframes of its clock
  (:func:`.frame_clock.emulated_timestamps`: the rig's jitter and drops) as
  ``meas_timestamps.csv``.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import RigParams
from .acquire import AcquisitionSettings, acquire_frames
from .calfile import Calibration
from .emulated import open_sim_calibration_rig
from .frame_clock import TIMESTAMPS_FILE, emulated_timestamps, write_timestamps
from .frames import ProgressFn
from .meas_flat import measure_part_errors
from .parts import (
    emulated_switching_frames,
    emulated_target_stack,
    find_corners,
    mapping_error_px,
)
from .recorded import LAYOUT

log = logging.getLogger("vet.calibrate")

#: Subframe at which the emulated switching series closes every cell.
SWITCH_SUBFRAME = 20
#: Frames recorded per window of the switching series.
SWITCH_FRAMES = 4
#: Target poses: board square (px) and shift (x, y) px from the centre.
TARGET_POSES = ((12, (0.0, 0.0)), (12, (5.3, 3.7)))
#: rig.toml [params] written: what a reader needs that is not measured.
_PARAMS = (
    "sensor_size",
    "lcos_cells",
    "frame_s",
    "subframe_s",
    "full_well_e",
    "read_noise_e",
    "adc_bits",
    "black_level_dn",
    "latency_subframes",
)


def write_emulated_folder(
    folder: str | Path,
    size: tuple[int, int] | None = None,
    overrides: dict[str, Any] | None = None,
    seed: int = 0,
    profile: str = "realistic",
    settings: AcquisitionSettings | None = None,
    force: bool = False,
    progress: ProgressFn | None = None,
) -> RigParams:
    """Record the emulated rig's calibration frames into ``folder`` (layout in the module
    docstring) and return the emulated truth (its RigParams).

    ``size`` (W, H), ``overrides``, ``seed``, ``profile``: the emulated rig as for
    :func:`.emulated.calibrate_sim`; ``settings``: the acquisition's exposures and
    frame counts. The folder is written whole or not at all (built beside it, then moved
    in). An existing folder that holds anything is refused unless ``force``; then the
    files of the layout (and ``rig.toml``) already there are replaced, others kept.

    Raises
    ------
    InputError
        ``folder`` is a file, or a non-empty folder without ``force``, or its parent
        cannot be written.
    """
    target = Path(folder)
    if target.exists() and not target.is_dir():
        raise InputError(f"{target}: is a file, not a folder")
    if target.is_dir() and any(target.iterdir()) and not force:
        raise InputError(
            f"{target}: folder is not empty; give --force to replace its calibration frames, "
            "or choose another folder"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        truth = _record(tmp, size, overrides, seed, profile, settings, progress)
        _move_into(tmp, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return truth


def _record(
    root: Path,
    size: tuple[int, int] | None,
    overrides: dict[str, Any] | None,
    seed: int,
    profile: str,
    settings: AcquisitionSettings | None,
    progress: ProgressFn | None,
) -> RigParams:
    import cv2

    def save(name: str, dn: np.ndarray, rig: RigParams) -> None:
        img = np.clip(np.rint(np.asarray(dn, np.float64) + rig.black_level_dn), 0, 65535)
        if not cv2.imwrite(str(root / f"{name}.png"), img.astype(np.uint16)):
            raise InputError(f"{root / name}.png: cannot write the frame")

    with open_sim_calibration_rig(size, overrides, None, seed, None, profile) as sim:
        rig = sim.params

        def sink(tag: tuple[str, float], i: int, img: np.ndarray) -> None:
            kind, key = tag
            stem = f"gray_{int(key):02d}" if kind == "gray" else f"{kind}_{key:.9g}s"
            save(f"{stem}_{i:02d}", img, rig)

        acquire_frames(sim, settings, progress, sink)

    pattern = None
    for p, (square, shift) in enumerate(TARGET_POSES):
        vet, meas, pattern = emulated_target_stack(rig, seed + 1 + p, square, offset_px=shift)
        if find_corners(np.mean(vet, axis=0), pattern) is None:
            log.warning("calibrate: emulated target pose %d not detectable at this size", p)
        for n, (v, m) in enumerate(zip(vet, meas, strict=True)):
            save(f"target_vet_{p:02d}_{n:02d}", v, rig)
            save(f"target_meas_{p:02d}_{n:02d}", m, rig)

    c = min(SWITCH_SUBFRAME, rig.n_subframes - 1)
    wins = np.round(c * rig.subframe_s + np.arange(-2e-3, 5e-3 + 1e-9, 2.5e-4), 6)
    wins = wins[(wins > 0) & (wins <= rig.frame_s)]
    reps = np.repeat(wins, SWITCH_FRAMES)
    rate = 0.5 * rig.full_well_e / float(wins.max())
    frames = emulated_switching_frames(rig, c, reps, rate, seed, dark=True)
    for k, (w, dn) in enumerate(zip(reps, frames, strict=True)):
        save(f"switch_{c}_{w:.9g}s_{k % SWITCH_FRAMES:02d}", dn, rig)

    write_timestamps(root / TIMESTAMPS_FILE, *emulated_timestamps(rig, seed=seed))

    d = rig.to_dict()
    lines = ["# the emulated rig's settings (its parts are what calibration finds)", "[params]"]
    for key in _PARAMS:
        v = d[key]
        lines.append(f"{key} = {list(v) if isinstance(v, (list, tuple)) else repr(v)}")
    if pattern is not None:
        lines += ["", "[calibration]", f"chessboard = [{pattern[0]}, {pattern[1]}]"]
    (root / "rig.toml").write_text("\n".join(lines) + "\n")
    return rig


def _move_into(tmp: Path, target: Path) -> None:
    """Move the recorded files of ``tmp`` into ``target`` (replacing layout files)."""
    if not target.exists():
        os.replace(tmp, target)
        return
    for p in target.iterdir():
        named = p.name in ("rig.toml", TIMESTAMPS_FILE)
        if p.is_file() and (named or any(r.match(p.stem) for r in LAYOUT)):
            p.unlink()
    for p in tmp.iterdir():
        os.replace(p, target / p.name)


def compare_parts_to_truth(cal: Calibration, truth: RigParams) -> dict[str, float]:
    """Errors of the parts in ``cal`` against the emulated rig's ``truth``:
    ``mapping_rms_px`` (:func:`.parts.mapping_error_px`), ``trigger_offset_err_s``
    (signed, s), ``switch_rel_err`` and ``relay_blur_rel_err`` (signed, relative), and for the per-pixel leakage map
    against the relay-blurred per-cell truth ``leakage_px_max_rel_err`` and
    ``leakage_px_rms_rel_err`` (over the pixels where it is finite), and the
    measurement camera's (:func:`.meas_flat.measure_part_errors`). Parts missing from
    ``cal`` are left out."""
    from ..optics import pixel_leakage, relay_blur
    from ..physics import CellMap

    out: dict[str, float] = {}
    p = cal.parts
    if "measure_homography" in p:
        est = truth.replace(
            measure_homography=p["measure_homography"],
            measure_k1=p["measure_k1"],
            measure_k2=p["measure_k2"],
        )
        out["mapping_rms_px"] = mapping_error_px(est, truth)
    if "trigger_offset_s" in p:
        out["trigger_offset_err_s"] = p["trigger_offset_s"] - truth.trigger_offset_s
    if "switch_s" in p and truth.switch_s > 0:
        out["switch_rel_err"] = p["switch_s"] / truth.switch_s - 1
    if "relay_blur_px" in p and truth.relay_blur_px > 0:
        out["relay_blur_rel_err"] = p["relay_blur_px"] / truth.relay_blur_px - 1
    out.update(measure_part_errors(p, truth))
    if cal.leakage is not None and tuple(cal.sensor_size) == tuple(truth.sensor_size):
        w, h = truth.sensor_size
        true_px = relay_blur(
            pixel_leakage(truth, CellMap.for_rig(truth, (h, w))), truth.relay_blur_px
        )
        rel = cal.leakage / true_px - 1
        rel = rel[np.isfinite(rel)]
        if rel.size:
            out["leakage_px_max_rel_err"] = float(np.abs(rel).max())
            out["leakage_px_rms_rel_err"] = float(np.sqrt(np.mean(rel * rel)))
    return out
