"""The measurement camera's gain and vignetting from a flat field both cameras record.

On a flat field the measurement camera's dark-subtracted rate at its pixel ``u``, over
the VET camera's rate (all cells open) where ``u`` lands on the VET sensor, is
``measure_fraction * measure_gain * (1 + a r(u)**2) ** -2`` (:class:`stages.optics.
MeasureGeometry`): ``r`` the radius of ``u``'s centre from the measurement image's centre
in its half-diagonals (:func:`stages.optics.vignetting`), so the falloff lives on the
measurement camera's grid and the VET rate is what is resampled (bilinearly, through the
fitted measurement -> VET mapping). :func:`fit_vignetting` fits the centre value ``P``
and ``a`` to that ratio by least squares.

``measure_fraction`` (the beam splitter's share of the light) and ``measure_gain`` (the
camera's conversion gain) multiply in every frame the measurement camera records, so no
flat field separates them; what vet's readers need is the product (they divide the
registered frames by both). :func:`measure_flat_parts` therefore keeps the rig's
configured ``measure_fraction`` (the splitter's nominal share, 1.0 for 50/50) and puts
the rest of ``P`` into ``measure_gain``; both go into ``parts`` so that a capture made
with the calibration has the measured product.
"""

from __future__ import annotations

import logging

import numpy as np

from ..optics import radius2
from ..rig import RigParams
from .sensor_models import signal_rate

log = logging.getLogger("vet.calibrate")

#: Fewest measurement pixels a vignetting fit needs.
MIN_PIXELS = 100


def rate_ratio(meas_rate: np.ndarray, open_rate: np.ndarray, rig: RigParams) -> np.ndarray:
    """Measurement rate over the VET open rate resampled at each measurement pixel's
    place on the VET sensor (``rig``'s mapping, :func:`stages.optics.measure_to_vet`):
    (Hm, Wm) float64, NaN where the pixel lands outside the VET frame (half a pixel in)
    or the VET rate is not positive."""
    from ..optics import bilinear_matrix, measure_to_vet

    xv, yv = measure_to_vet(rig.replace(measure_size=(meas_rate.shape[1], meas_rate.shape[0])))
    h, w = open_rate.shape
    inside = (xv >= 0.5) & (xv <= w - 0.5) & (yv >= 0.5) & (yv <= h - 0.5)
    # (the sampling the measurement camera's model renders with: MeasureGeometry)
    sample = bilinear_matrix(xv - 0.5, yv - 0.5, (h, w))
    vet = (sample @ np.asarray(open_rate, np.float32).ravel()).reshape(xv.shape).astype(np.float64)
    ok = inside & np.isfinite(vet) & (vet > 1e-6 * max(float(np.nanmax(open_rate)), 1e-30))
    out = np.full(meas_rate.shape, np.nan)
    out[ok] = np.asarray(meas_rate, np.float64)[ok] / vet[ok]
    return out


def fit_vignetting(ratio: np.ndarray) -> dict | None:
    """``P (1 + a r**2) ** -2`` fitted to a measurement-grid (Hm, Wm) ratio (NaN:
    unusable) by least squares (soft L1 beyond three robust sigmas, so a few hot or dead
    pixels do not pull it), from the linear fit of ``ratio ** -1/2 = (1 + a r**2) /
    sqrt(P)``; ``a`` below 0 (no falloff in the model) gives ``a = 0`` and ``P`` the
    median ratio. Returns ``centre`` (P), ``vignetting`` (a), ``rms_rel`` (the residual's
    RMS over P) and ``pixels``; None with fewer than :data:`MIN_PIXELS` usable pixels."""
    from scipy.optimize import least_squares

    r2 = radius2(ratio.shape)
    ok = np.isfinite(ratio) & (ratio > 0)
    if ok.sum() < MIN_PIXELS or np.ptp(r2[ok]) <= 0:
        return None
    x, y = r2[ok], ratio[ok]
    c1, c0 = np.polyfit(x, y**-0.5, 1)
    if c0 <= 0:
        return None
    p0 = np.array([c0**-2, c1 / c0])

    def resid(p: np.ndarray) -> np.ndarray:
        return p[0] / (1.0 + p[1] * x) ** 2 - y

    r0 = resid(p0)
    scale = 1.4826 * float(np.median(np.abs(r0 - np.median(r0)))) or 1e-6
    fit = least_squares(resid, p0, loss="soft_l1", f_scale=3 * scale, x_scale=[p0[0], 0.1])
    p, a = float(fit.x[0]), float(fit.x[1])
    if a < 0:  # brighter towards the edges: not vignetting; the model's best is a flat gain
        p, a = float(np.median(y)), 0.0
    r = resid(np.array([p, a]))
    return {
        "centre": p,
        "vignetting": a,
        "rms_rel": float(np.sqrt(np.mean(r * r)) / p),
        "pixels": int(ok.sum()),
    }


def flat_rates(
    meas_frames: dict[float, np.ndarray],
    meas_dark: dict[float, np.ndarray],
    open_frames: dict[float, np.ndarray],
    bias: np.ndarray | float | None,
    dark_dn_s: np.ndarray | float | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Dark-subtracted rates (DN/s) of the measurement camera's flat field (its longest
    exposure; its own dark frame at that exposure when recorded, else the VET camera's
    bias and dark current, per pixel when the grids match in size, else their medians)
    and of the VET camera's all-open one: ``(meas (Hm, Wm), vet (H, W))``; None without
    both."""
    if not meas_frames or not open_frames:
        return None
    t_o = max(open_frames)
    b = 0.0 if bias is None else bias
    d = 0.0 if dark_dn_s is None else dark_dn_s
    open_rate = signal_rate(open_frames[t_o], t_o, b, d)
    t_m = max(meas_frames)
    if t_m in meas_dark:
        meas_rate = ((meas_frames[t_m] - meas_dark[t_m]) / t_m).astype(np.float32)
    else:
        if np.ndim(b) and np.shape(b) != meas_frames[t_m].shape:
            b, d = float(np.median(b)), float(np.median(d))
        meas_rate = signal_rate(meas_frames[t_m], t_m, b, d)
    return meas_rate, open_rate


def measure_flat_parts(
    meas_rate: np.ndarray, open_rate: np.ndarray, params: RigParams, mapping: dict | None
) -> tuple[dict, dict] | None:
    """``(parts, info)``: the measurement camera's ``measure_vignetting``,
    ``measure_gain`` and ``measure_fraction`` (the configured one, ``params``'s: the
    product of the two is what the flat field gives; module docstring), and the fit's
    figures for the provenance. ``mapping``: the fitted ``measure_homography``,
    ``measure_k1``, ``measure_k2`` (None: the two grids taken to coincide, which needs
    frames of one size). None (logged) when it cannot be fitted."""
    if mapping is None and meas_rate.shape != open_rate.shape:
        log.warning(
            "calibrate: measurement and VET flat fields differ in size and no chessboard "
            "mapping was found; measurement gain and vignetting not fitted"
        )
        return None
    rig = RigParams(sensor_size=(open_rate.shape[1], open_rate.shape[0]))
    if mapping is not None:
        rig = rig.replace(
            **{k: mapping[k] for k in ("measure_homography", "measure_k1", "measure_k2")}
        )
    fit = fit_vignetting(rate_ratio(meas_rate, open_rate, rig))
    if fit is None or not (0 <= fit["vignetting"] <= 10) or fit["centre"] <= 0:
        log.warning("calibrate: the measurement flat field gave no usable vignetting fit")
        return None
    mf = float(params.measure_fraction)
    parts = {
        "measure_vignetting": fit["vignetting"],
        "measure_gain": fit["centre"] / mf,
        "measure_fraction": mf,
    }
    info = {
        "centre_ratio": fit["centre"],
        "rms_rel": fit["rms_rel"],
        "pixels": fit["pixels"],
        "mapping": "chessboard" if mapping is not None else "identity",
    }
    return parts, info


#: The errors of :func:`measure_part_errors`.
MEASURE_ERRORS = (
    "measure_vignetting_rel_err",
    "measure_gain_product_rel_err",
    "trigger_jitter_rel_err",
    "drop_rate_err",
)


def measure_part_errors(parts: dict, truth: RigParams) -> dict[str, float]:
    """Errors of the measurement camera's parts in ``parts`` (RigParams fields) against
    the emulated ``truth``: ``measure_vignetting_rel_err``,
    ``measure_gain_product_rel_err`` (of ``measure_fraction * measure_gain``, what a
    flat field measures), ``trigger_jitter_rel_err`` (signed, relative) and
    ``drop_rate_err`` (signed, absolute); parts missing (or a truth of 0 for a relative
    error) are left out."""
    out: dict[str, float] = {}
    if "measure_vignetting" in parts and truth.measure_vignetting > 0:
        out["measure_vignetting_rel_err"] = (
            parts["measure_vignetting"] / truth.measure_vignetting - 1
        )
    if "measure_gain" in parts:
        est = parts["measure_gain"] * parts.get("measure_fraction", truth.measure_fraction)
        out["measure_gain_product_rel_err"] = (
            est / (truth.measure_gain * truth.measure_fraction) - 1
        )
    if "trigger_jitter_s" in parts and truth.trigger_jitter_s > 0:
        out["trigger_jitter_rel_err"] = parts["trigger_jitter_s"] / truth.trigger_jitter_s - 1
    if "drop_rate" in parts:
        out["drop_rate_err"] = parts["drop_rate"] - truth.drop_rate
    return out
