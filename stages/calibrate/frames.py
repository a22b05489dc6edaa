"""Calibration frames (averaged per exposure) and the calibration computed from them.

:func:`calibrate_frames` computes every part the frames allow: the homography from the
Gray code (:mod:`.gray_code`, :mod:`.geometry`), bias and dark current, leakage
(:mod:`.sensor_models`) and the gain ratio, measurement-camera over VET-camera signal
rate (all open) on the same flat field, per pixel, median: the ``measure_fraction`` of
the rig.

The measurement camera is not behind the LCoS, so the Gray code says nothing about it:
its mapping onto the VET sensor (homography and distortion) comes from a chessboard both
cameras see (:mod:`.parts`; from a folder, :mod:`.recorded_parts`). The gain ratio here
assumes the two grids coincide (see docs/calibration.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import RigParams
from .calfile import Calibration
from .geometry import fit_homography
from .gray_code import decode_gray
from .meas_flat import flat_rates
from .sensor_models import dark_model, leakage_map, signal_rate

log = logging.getLogger("vet.calibrate")

ProgressFn = Callable[[int, int], None]


@dataclass
class CalibrationFrames:
    """Frames for a calibration, averaged per exposure (DN, ``ndarray of shape (H, W)``).

    Attributes
    ----------
    dark : dict of float -> ndarray
        VET camera, no light: exposure (s) -> mean frame.
    open, closed : dict of float -> ndarray
        VET camera, flat field, LCoS all open / all closed: exposure (s) -> mean frame.
    gray_diffs : list of ndarray or None
        ``pattern - inverse`` per Gray-code bit (order of :func:`gray_code_patterns`).
    meas_flat : dict of float -> ndarray
        Measurement camera, same flat field: exposure (s) -> mean frame.
    meas_dark : dict of float -> ndarray
        Measurement camera, no light, at the same exposures (optional).
    counts : dict
        Frames averaged per part (provenance).
    halves : dict of str -> (ndarray, ndarray)
        ``"open"``, ``"closed"``: at their longest exposure, the means of the even- and
        of the odd-numbered frames (the per-cell leakage's noise, :mod:`.cell_leakage`);
        present where two or more frames were recorded.
    """

    dark: dict[float, np.ndarray] = field(default_factory=dict)
    open: dict[float, np.ndarray] = field(default_factory=dict)
    closed: dict[float, np.ndarray] = field(default_factory=dict)
    gray_diffs: list[np.ndarray] | None = None
    meas_flat: dict[float, np.ndarray] = field(default_factory=dict)
    meas_dark: dict[float, np.ndarray] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    halves: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def shape(self) -> tuple[int, int] | None:
        """(H, W) of the frames held, or None when there are none."""
        for group in (self.dark, self.open, self.closed, self.meas_flat):
            for v in group.values():
                return v.shape
        if self.gray_diffs:
            return self.gray_diffs[0].shape
        return None


def calibrate_frames(
    frames: CalibrationFrames,
    params: RigParams,
    provenance: dict[str, Any] | None = None,
    min_contrast_dn: float | None = None,
) -> Calibration:
    """Compute every part of the calibration the frames allow; warn about the others.

    Parameters
    ----------
    frames : CalibrationFrames
    params : RigParams
        Gives the LCoS grid and the conversion gain (DN per electron).
    provenance : dict, optional
        Stored with the result.
    min_contrast_dn : float, optional
        Gray-code contrast floor, DN (default: 8 read-noise sigmas, at least 4 DN).

    Returns
    -------
    Calibration

    Raises
    ------
    InputError
        No part of the calibration could be computed.
    """
    shape = frames.shape()
    if shape is None:
        raise InputError(
            "no calibration frames: need dark, open/closed, Gray-code or flat-field frames"
        )
    h, w = shape
    gain = params.gain_dn_per_e
    cal = Calibration(
        sensor_size=(w, h),
        lcos_cells=tuple(params.lcos_cells),
        rig=params.to_dict(),
        provenance=dict(provenance or {}),
    )
    skipped: list[str] = []

    if frames.gray_diffs:
        floor = (
            min_contrast_dn
            if min_contrast_dn is not None
            else max(4.0, 8.0 * params.read_noise_e * gain)
        )
        cx, cy, valid = decode_gray(frames.gray_diffs, params.lcos_cells, min_contrast_dn=floor)
        cal.cell_x, cal.cell_y = cx.astype(np.float32), cy.astype(np.float32)
        try:
            fit = fit_homography(cx, cy, valid)
        except InputError as exc:
            skipped.append(f"homography ({exc})")
        else:
            cal.homography = fit.homography
            cal.homography_fit = {
                "n_points": fit.n_points,
                "n_inliers": fit.n_inliers,
                "reprojection_rms_px": fit.reprojection_rms_px,
                "decode_agreement": fit.decode_agreement,
                "decoded_fraction": float(valid.mean()),
            }
    else:
        skipped.append("homography (no Gray-code frames)")

    bias: np.ndarray | float = 0.0
    dark_dn_s: np.ndarray | float = 0.0
    if len(frames.dark) >= 2:
        b, d = dark_model(frames.dark, gain)
        cal.bias_dn, cal.dark_current_e_s = b, d
        bias, dark_dn_s = b, d * gain
        cal.summary["dark_current_median_e_s"] = float(np.median(d))
        cal.summary["bias_median_dn"] = float(np.median(b))
    else:
        skipped.append("dark current and bias (need dark frames at two exposure times)")
        if frames.open or frames.meas_flat:
            log.warning(
                "calibrate: without dark frames the leakage and gain ratio are not dark-corrected "
                "(exact only for black-subtracted frames with negligible dark current)"
            )

    # Pixels under the LCoS: decoded ones when the Gray code was measured.
    footprint = None if cal.homography is None else cal.cell_x >= 0

    open_rate = None
    if frames.open:
        t_o = max(frames.open)
        open_rate = signal_rate(frames.open[t_o], t_o, bias, dark_dn_s)
    if frames.open and frames.closed:
        t_c = max(frames.closed)
        closed_rate = signal_rate(frames.closed[t_c], t_c, bias, dark_dn_s)
        noise_dn = params.read_noise_e * gain
        leak = leakage_map(open_rate, closed_rate, min_rate=20.0 * max(noise_dn, 1.0) / t_o)
        cal.leakage = leak
        sel = np.isfinite(leak)
        if footprint is not None:
            sel &= footprint
        else:
            sel &= leak < 0.5  # outside the LCoS footprint the "closed" pixel sees full light
        if sel.any():
            cal.summary["leakage_median"] = float(np.median(leak[sel]))
        else:
            log.warning("calibrate: no pixel had a usable open/closed ratio; leakage not measured")
    else:
        skipped.append("leakage (need open and closed flat-field frames)")

    if frames.meas_flat and open_rate is not None:
        # Its own dark frames, else the VET sensor's dark model (same sensor type:
        # DESIGN.md §2; its medians for a camera of another size).
        meas_rate, _ = flat_rates(frames.meas_flat, frames.meas_dark, frames.open, bias, dark_dn_s)
        if meas_rate.shape != open_rate.shape:
            skipped.append(
                "gain ratio (measurement and VET frames differ in size; the measurement "
                "camera's gain and vignetting are fitted through its chessboard mapping "
                "instead, under parts)"
            )
        else:
            ok = open_rate > 1e-6 * max(float(np.max(open_rate)), 1e-30)
            ratio = np.full(open_rate.shape, np.nan, np.float32)
            ratio[ok] = meas_rate[ok] / open_rate[ok]
            cal.gain_ratio = ratio
            if ok.any():
                cal.summary["gain_ratio_median"] = float(np.median(ratio[ok]))
    else:
        skipped.append("gain ratio (need measurement-camera flat frames and VET open frames)")

    cal.provenance["skipped"] = skipped
    for s in skipped:
        log.warning("calibrate: skipped %s", s)
    if cal.homography is None and not cal.summary:
        raise InputError("no part of the calibration could be measured from these frames")
    return cal


def software_version() -> str:
    """``"vet <version>"`` as installed, or ``"vet (uninstalled)"`` (provenance)."""
    try:
        from importlib.metadata import version

        return f"vet {version('vet')}"
    except Exception:  # noqa: BLE001 - an uninstalled checkout still calibrates
        return "vet (uninstalled)"
