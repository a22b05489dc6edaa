"""A folder of calibration frames rendered from the emulated rig's truth, in the layout
that :func:`.recorded.calibrate_from_folder` reads (docs/calibration.md), and the errors
of a calibration made from such a folder against the emulated truth. (``vet calibrate
--rig sim --save-frames`` records the emulated rig live instead, :mod:`.live`; this
rendering is the reference it is compared with, and the tests' fixture.)

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
from pathlib import Path
from typing import Any

import numpy as np

from ..rig import RigParams
from .acquire import AcquisitionSettings, acquire_frames
from .calfile import Calibration
from .emulated import open_sim_calibration_rig
from .folder_out import build_folder, frame_stem, save_frame, write_rig_toml
from .frame_clock import TIMESTAMPS_FILE, emulated_timestamps, write_timestamps
from .frames import ProgressFn
from .meas_flat import measure_part_errors
from .parts import (
    emulated_switching_frames,
    emulated_target_stack,
    find_corners,
    mapping_error_px,
)

log = logging.getLogger("vet.calibrate")

#: Subframe at which the emulated switching series closes every cell.
SWITCH_SUBFRAME = 20
#: Frames recorded per window of the switching series.
SWITCH_FRAMES = 4
#: The switching series' windows: from this long before ``c tau`` (s) ...
SWITCH_BEFORE_S = 2e-3
#: ... to this long after it (s) ...
SWITCH_AFTER_S = 5e-3
#: ... this far apart (s).
SWITCH_STEP_S = 2.5e-4
#: Target poses: board square (px) and shift (x, y) px from the centre.
TARGET_POSES = ((12, (0.0, 0.0)), (12, (5.3, 3.7)))


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
    frame counts. The folder is written whole or not at all
    (:func:`.folder_out.build_folder`: a non-empty folder only with ``force``).

    Raises
    ------
    InputError
        ``folder`` is a file, or a non-empty folder without ``force``, or its parent
        cannot be written.
    """
    return build_folder(
        folder, force, lambda tmp: _record(tmp, size, overrides, seed, profile, settings, progress)
    )


def _record(
    root: Path,
    size: tuple[int, int] | None,
    overrides: dict[str, Any] | None,
    seed: int,
    profile: str,
    settings: AcquisitionSettings | None,
    progress: ProgressFn | None,
) -> RigParams:
    with open_sim_calibration_rig(size, overrides, None, seed, None, profile) as sim:
        rig = sim.params

        def sink(tag: tuple[str, float], i: int, img: np.ndarray) -> None:
            save_frame(root, frame_stem(tag, i), img, rig.black_level_dn)

        acquire_frames(sim, settings, progress, sink)

    def save(name: str, dn: np.ndarray) -> None:
        save_frame(root, name, dn, rig.black_level_dn)

    pattern = None
    for p, (square, shift) in enumerate(TARGET_POSES):
        vet, meas, pattern = emulated_target_stack(rig, seed + 1 + p, square, offset_px=shift)
        if find_corners(np.mean(vet, axis=0), pattern) is None:
            log.warning("calibrate: emulated target pose %d not detectable at this size", p)
        for n, (v, m) in enumerate(zip(vet, meas, strict=True)):
            save(f"target_vet_{p:02d}_{n:02d}", v)
            save(f"target_meas_{p:02d}_{n:02d}", m)

    c = min(SWITCH_SUBFRAME, rig.n_subframes - 1)
    wins = switch_windows(rig, c)
    reps = np.repeat(wins, SWITCH_FRAMES)
    rate = 0.5 * rig.full_well_e / float(wins.max())
    frames = emulated_switching_frames(rig, c, reps, rate, seed, dark=True)
    for k, (w, dn) in enumerate(zip(reps, frames, strict=True)):
        save(f"switch_{c}_{w:.9g}s_{k % SWITCH_FRAMES:02d}", dn)

    write_timestamps(root / TIMESTAMPS_FILE, *emulated_timestamps(rig, seed=seed))
    write_rig_toml(
        root, rig, pattern, "the emulated rig's settings (its parts are what calibration finds)"
    )
    return rig


def switch_windows(
    rig: RigParams,
    c: int,
    before_s: float = SWITCH_BEFORE_S,
    after_s: float = SWITCH_AFTER_S,
    step_s: float = SWITCH_STEP_S,
) -> np.ndarray:
    """Exposure windows (s, rounded to 1 us) of a switching series closing at subframe
    ``c``: ``step_s`` apart from ``before_s`` before its nominal time ``c tau`` to
    ``after_s`` after, those in ``(0, frame_s]``."""
    wins = np.round(c * rig.subframe_s + np.arange(-before_s, after_s + 1e-9, step_s), 6)
    return wins[(wins > 0) & (wins <= rig.frame_s)]


def compare_parts_to_truth(cal: Calibration, truth: RigParams) -> dict[str, float]:
    """Errors of the parts in ``cal`` against the emulated rig's ``truth``:
    ``mapping_rms_px`` (:func:`.parts.mapping_error_px`), ``trigger_offset_err_s``
    (signed, s), ``switch_rel_err`` and ``relay_blur_rel_err`` (signed, relative), and for the per-pixel leakage map
    against the relay-blurred per-cell truth ``leakage_px_max_rel_err`` and
    ``leakage_px_rms_rel_err`` (over the pixels where it is finite), for the per-cell
    map's layer against the leakage of each pixel's true cell
    ``cell_leakage_px_median_rel_err`` and ``cell_leakage_px_max_rel_err``, and the
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
    if cal.cell_leakage is not None and tuple(cal.sensor_size) == tuple(truth.sensor_size):
        w, h = truth.sensor_size
        rel = np.abs(cal.cell_leakage / pixel_leakage(truth, CellMap.for_rig(truth, (h, w))) - 1)
        rel = rel[np.isfinite(rel)]
        if rel.size:
            out["cell_leakage_px_median_rel_err"] = float(np.median(rel))
            out["cell_leakage_px_max_rel_err"] = float(rel.max())
    return out
