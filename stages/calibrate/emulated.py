"""Calibration of the emulated rig against its known truth."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import RigParams
from .acquire import AcquisitionSettings, calibrate_rig_frames
from .calfile import Calibration
from .frames import ProgressFn
from .geometry import homography_error_px


@contextmanager
def open_sim_calibration_rig(
    size: tuple[int, int] | None = None,
    overrides: dict[str, Any] | None = None,
    true_homography: np.ndarray | None = None,
    seed: int = 0,
    scene: str | None = None,
    profile: str = "ideal",
) -> Iterator[Any]:
    """The emulated rig looking at a flat field (or ``scene``), ready for :func:`calibrate_rig`.

    Parameters
    ----------
    size : (int, int), optional
        Sensor (width, height) [1280x1024].
    overrides : dict, optional
        RigParams overrides: the emulated truth (``leakage``, ``dark_current_e_s``,
        ``lcos_cells``, ...). The rig's nominal homography stays the default one.
    true_homography : ndarray of shape (3, 3), optional
        The homography the emulated VET camera really has [the nominal one].
    seed : int
        Noise seed.
    scene : str, optional
        A scene instead of the flat field (a real rig would image a diffuser).
    """
    import tempfile

    from ..devices.rigs import SimOptions, open_rig

    w, h = size or RigParams().sensor_size
    with tempfile.TemporaryDirectory(prefix="vet-cal-") as tmp:
        if scene is None:
            scene = str(Path(tmp) / "flat.exr")
            _write_flat_exr(scene, w, h)
        opts = SimOptions(
            scene=scene,
            size=(w, h),
            seed=seed,
            realtime=False,
            true_homography=None
            if true_homography is None
            else np.asarray(true_homography).tolist(),
            overrides=dict(overrides or {}),
            profile=profile,
        )
        rig = open_rig("sim", opts)
    try:
        yield rig
    finally:
        rig.close()


def _write_flat_exr(path: str, w: int, h: int) -> None:
    """Write a ``w`` x ``h`` EXR of ones (channel ``Y``); InputError if it cannot."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(w, h, 1, "float")
    spec.channelnames = ("Y",)
    out = oiio.ImageOutput.create(path)
    if out is None or not out.open(path, spec):
        raise InputError(f"{path}: cannot write the flat field ({oiio.geterror()})")
    try:
        out.write_image(np.ones((h, w, 1), np.float32))
    finally:
        out.close()


def compare_to_truth(
    cal: Calibration,
    true_homography: np.ndarray,
    leakage: float,
    dark_current_e_s: float,
    measure_fraction: float = 1.0,
) -> dict[str, float]:
    """Errors of a calibration against the emulated rig's truth (the acceptance figures).

    Returns
    -------
    dict
        ``homography_max_px``, ``homography_rms_px`` (over a 4-cell grid of cell points
        that land on the sensor), ``leakage_rel_err``, ``dark_current_rel_err``,
        ``gain_ratio_rel_err`` (relative, signed); missing parts are left out.
    """
    out: dict[str, float] = {}
    if cal.homography is not None:
        mx, rms = homography_error_px(
            cal.homography, true_homography, cal.lcos_cells, cal.sensor_size
        )
        out["homography_max_px"], out["homography_rms_px"] = mx, rms
    s = cal.summary
    if "leakage_median" in s and leakage > 0:
        out["leakage_rel_err"] = s["leakage_median"] / leakage - 1
    if "dark_current_median_e_s" in s and dark_current_e_s > 0:
        out["dark_current_rel_err"] = s["dark_current_median_e_s"] / dark_current_e_s - 1
    if "gain_ratio_median" in s:
        out["gain_ratio_rel_err"] = s["gain_ratio_median"] / measure_fraction - 1
    return out


def calibrate_sim(
    size: tuple[int, int] | None = None,
    overrides: dict[str, Any] | None = None,
    true_homography: np.ndarray | None = None,
    seed: int = 0,
    scene: str | None = None,
    progress: ProgressFn | None = None,
    settings: AcquisitionSettings | None = None,
    profile: str = "ideal",
) -> Calibration:
    """Calibrate the emulated rig and record how far the result is from its truth.

    Parameters are those of :func:`open_sim_calibration_rig`. The provenance gets
    ``emulated_truth`` (the true homography, leakage, dark current, gain ratio and the
    parts of a real rig: what ``vet capture --rig sim`` rebuilds the rig from) and
    ``errors_vs_truth`` (:func:`compare_to_truth`). A rig ``profile`` with the parts of
    a real rig (:func:`stages.optics.rig_profile`) has them found too, on frames the
    emulated rig's physics records (:func:`.parts.calibrate_parts`): ``parts`` and
    their errors against the truth, and the per-cell leakage (``cell_leakage``).

    Returns
    -------
    Calibration
    """
    with open_sim_calibration_rig(size, overrides, true_homography, seed, scene, profile) as rig:
        cal, frames = calibrate_rig_frames(rig, progress, settings)
        p = rig.params
        true_h = np.asarray(p.homography if true_homography is None else true_homography, float)
    from ..optics import PARTS

    d = p.to_dict()
    cal.provenance["emulated_truth"] = {
        "homography": true_h.tolist(),
        "leakage": p.leakage,
        "dark_current_e_s": p.dark_current_e_s,
        "measure_fraction": p.measure_fraction,
        **{k: d[k] for k in PARTS if k in d},
    }
    cal.provenance["errors_vs_truth"] = compare_to_truth(
        cal, true_h, p.leakage, p.dark_current_e_s, p.measure_fraction
    )
    if not (p.ideal_geometry and p.ideal_shutter):
        from .parts import calibrate_parts

        cal.parts, errors = calibrate_parts(p, seed)
        _measure_parts(cal, frames, p, seed)
        cal.provenance["errors_vs_truth"].update(errors)
    if p.relay_blur_px > 0 or p.leakage_spread > 0:
        from .calfile import apply_calibration
        from .cell_leakage import LEAKAGE_FRAMES, calibrate_cell_leakage

        truth = p.replace(homography=true_h.tolist())  # (p keeps the nominal one)
        known = apply_calibration(p, cal)
        cal.cell_leakage, errors = calibrate_cell_leakage(truth, known, LEAKAGE_FRAMES, seed)
        cal.provenance["errors_vs_truth"].update(errors)
        cal.provenance.setdefault("parts_fit", {})["cell_leakage"] = {"flat_frames": LEAKAGE_FRAMES}
    return cal


def _measure_parts(cal: Calibration, frames: Any, truth: RigParams, seed: int) -> None:
    """The measurement camera's gain and vignetting from the flat fields just acquired
    (through the mapping in ``cal.parts``, when found), and the trigger jitter and drop
    rate from the frame ids and timestamps the emulated camera gives over
    :data:`.frame_clock.EMULATED_FRAMES` subframes, into ``cal.parts`` with their
    errors against ``truth`` (``provenance["errors_vs_truth"]``)."""
    from .frame_clock import clock_parts, emulated_timestamps
    from .meas_flat import flat_rates, measure_flat_parts, measure_part_errors

    info: dict = {}
    if not truth.ideal_geometry:
        dark = None if cal.dark_current_e_s is None else cal.dark_current_e_s * truth.gain_dn_per_e
        rates = flat_rates(frames.meas_flat, frames.meas_dark, frames.open, cal.bias_dn, dark)
        mapping = cal.parts if "measure_homography" in cal.parts else None
        got = None if rates is None else measure_flat_parts(*rates, truth, mapping)
        if got is not None:
            cal.parts.update(got[0])
            info["measure_flat"] = got[1]
    if truth.trigger_jitter_s > 0 or truth.drop_rate > 0:
        got = clock_parts(*emulated_timestamps(truth, seed=seed), truth)
        if got is not None:
            cal.parts.update(got[0])
            info["frame_clock"] = got[1]
    if info:
        cal.provenance.setdefault("parts_fit", {}).update(info)
        cal.provenance["errors_vs_truth"].update(measure_part_errors(cal.parts, truth))
