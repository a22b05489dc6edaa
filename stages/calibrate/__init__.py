"""Rig calibration: LCoS-to-camera homography, dark current, bias, leakage, gain ratio.

What is measured, and from which frames (all frames in DN as the camera delivers them):

- **Homography** LCoS cell coordinates -> VET sensor pixel coordinates, from Gray-code
  patterns and their inverses (:mod:`.gray_code`) fitted by RANSAC and least squares
  (:mod:`.geometry`).
- **Dark frames** at two or more exposure times give the bias and the dark current;
  **leakage** is the all-closed over all-open signal rate (:mod:`.sensor_models`).
- **Gain ratio**: measurement-camera over VET-camera signal rate on the same flat field,
  the ``measure_fraction`` of the rig (:mod:`.frames`).

The modules, each importing only those above it:

- :mod:`.gray_code`: Gray-code patterns and their per-pixel decoding.
- :mod:`.geometry`: the cell -> pixel homography (fit, error, example, parsing).
- :mod:`.sensor_models`: bias and dark current, signal rate, leakage.
- :mod:`.frame_clock`: the measurement camera's frame ids and timestamps
  (``meas_timestamps.csv``): trigger jitter and drop rate.
- :mod:`.meas_flat`: the measurement camera's vignetting and gain from its flat field
  against the VET camera's, through the measurement -> VET mapping.
- :mod:`.calfile`: :class:`Calibration`, the calibration file, :func:`apply_calibration`.
- :mod:`.frames`: :class:`CalibrationFrames` and :func:`calibrate_frames`.
- :mod:`.acquire`: driving a rig through the calibration sequence.
- :mod:`.parts`: the parts of a real rig (:mod:`stages.optics`): the measurement ->
  VET mapping and distortion from a chessboard both cameras see, the switching time and
  trigger offset from closures at a known subframe, the leakage map per pixel and per
  cell (``python -m stages.calibrate.parts``; the emulated rig's mapping, trigger
  offset and switching time in ``vet calibrate --rig sim --rig-profile``).
- :mod:`.recorded_parts`: those parts fitted from a folder's chessboard poses,
  switching series, Gray code, measurement flat field and timestamps.
- :mod:`.recorded`: reading a folder of recorded frames or camera raws.
- :mod:`.folder_out`: writing such a folder whole or not at all.
- :mod:`.emulated`: the emulated rig and the errors against its truth.
- :mod:`.emulated_folder`: the emulated rig's frames rendered from its truth as such a
  folder, and the parts' errors against its truth.
- :mod:`.live`: recording a rig's frames live, through its device interfaces, as such a
  folder (``vet calibrate --rig sim|RIG.toml --save-frames DIR``).
- :mod:`.run`: :func:`run_calibration`, what ``vet calibrate`` does.
- :mod:`.selftest`: the acceptance point, ``python -m stages.calibrate --selftest``.

The result is a :class:`Calibration`, stored as a :class:`~stages.formats.layered.Layered`
file with ``kind = "calibration"`` (EXR or npz). :func:`apply_calibration` turns it into
:class:`~stages.rig.RigParams` for ``capture`` and ``hdr-static``.
"""

from .acquire import AcquisitionSettings, acquire_frames, calibrate_rig
from .calfile import (
    CALIBRATION_KIND,
    Calibration,
    apply_calibration,
    calibration_changes,
    calibration_overrides,
    emulated_rig_truth,
    read_calibration,
    write_calibration,
)
from .emulated import calibrate_sim, compare_to_truth, open_sim_calibration_rig
from .emulated_folder import compare_parts_to_truth, write_emulated_folder
from .frames import CalibrationFrames, ProgressFn, calibrate_frames
from .geometry import (
    HomographyFit,
    example_homography,
    fit_homography,
    homography_error_px,
    parse_homography,
)
from .gray_code import decode_gray, gray_bit_counts, gray_code_patterns
from .live import LiveSettings, record_rig_folder
from .recorded import IMAGE_SUFFIXES, RAW_SUFFIXES, calibrate_from_folder, read_frame
from .run import calibrate_live, run_calibration
from .selftest import selftest
from .sensor_models import dark_model, leakage_map, signal_rate

__all__ = [
    "CALIBRATION_KIND",
    "IMAGE_SUFFIXES",
    "RAW_SUFFIXES",
    "AcquisitionSettings",
    "Calibration",
    "CalibrationFrames",
    "HomographyFit",
    "LiveSettings",
    "ProgressFn",
    "acquire_frames",
    "apply_calibration",
    "calibrate_frames",
    "calibrate_live",
    "calibrate_from_folder",
    "calibrate_rig",
    "calibrate_sim",
    "calibration_changes",
    "calibration_overrides",
    "compare_parts_to_truth",
    "compare_to_truth",
    "emulated_rig_truth",
    "dark_model",
    "decode_gray",
    "example_homography",
    "fit_homography",
    "gray_bit_counts",
    "gray_code_patterns",
    "homography_error_px",
    "leakage_map",
    "open_sim_calibration_rig",
    "parse_homography",
    "read_calibration",
    "read_frame",
    "record_rig_folder",
    "run_calibration",
    "selftest",
    "signal_rate",
    "write_calibration",
    "write_emulated_folder",
]
