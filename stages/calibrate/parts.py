"""Calibrating the parts of a real rig (:mod:`stages.optics`) from what a lab records.

- **Measurement -> VET mapping** (homography and the measurement camera's radial
  distortion): a chessboard target both cameras see (:func:`chessboard_target`); its
  inner corners found in each camera's frame to subpixel accuracy
  (:func:`find_corners`) and the model fitted to the pairs by least squares
  (:func:`fit_measure_mapping`); :func:`mapping_error_px` scores a fit over the frame.
- **Switching time and trigger offset**: every cell commanded closed at a known
  subframe ``c`` on a flat field, the VET camera exposed for windows ``W`` that end
  around the closure; its exposure ``E(W) = eps W + (1 - eps) (min(W, t) + O(W - t))``
  (:func:`stages.optics.open_integral`) rises until the cell is applied closed at
  ``t = c tau + offset`` and bends over the switching time; :func:`fit_switching` finds
  ``t`` and ``switch_s`` from the measured ``E(W)``.
- **Leakage map**: :mod:`.cell_leakage`.

The ``emulated_*`` functions record the same frames on the emulated rig's physics (its
truth in ``RigParams``), for the tests and ``python -m stages.calibrate --selftest``.
"""

from __future__ import annotations

import numpy as np

from ..optics import (
    MeasureGeometry,
    distort,
    measure_to_vet,
    open_integral,
    pixel_leakage,
    relay_blur,
    slot_transmittance,
    subframe_clock,
    timing_rng,
)
from ..physics import CellMap, expose
from ..rig import RigParams

# --- the measurement -> VET mapping -------------------------------------------------------


def chessboard_target(
    size: tuple[int, int],
    square_px: int = 12,
    blur_px: float = 0.7,
    offset_px: tuple[float, float] = (0.0, 0.0),
):
    """A chessboard radiance (H, W, 1) float32 of ``square_px`` squares (values 0.05 and
    1), centred and then moved by ``offset_px`` (x, y; a few pixels at most: it must stay
    in the frame), softened by a Gaussian of ``blur_px`` as optics would; and its inner
    corner pattern (columns, rows)."""
    w, h = size
    nx, ny = w // square_px - 2, h // square_px - 2
    x0 = (w - (nx + 1) * square_px) / 2 + offset_px[0]
    y0 = (h - (ny + 1) * square_px) / 2 + offset_px[1]
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ix = np.floor((xx - x0) / square_px)
    iy = np.floor((yy - y0) / square_px)
    inside = (ix >= 0) & (ix <= nx) & (iy >= 0) & (iy <= ny)
    board = np.where(inside & ((ix + iy) % 2 == 0), 1.0, 0.05).astype(np.float32)
    return relay_blur(board, blur_px)[..., None], (nx, ny)


def find_corners(img: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """Inner corners of a chessboard of ``pattern`` (columns, rows) in an (H, W) image,
    (N, 2) float64 in vet's pixel coordinates (pixel (0, 0) covers [0, 1)), row-major
    from the top-left corner; None when not found."""
    import cv2

    a = np.asarray(img, np.float64)
    lo, hi = np.percentile(a, 1), np.percentile(a, 99)
    img8 = np.clip((a - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    ok, corners = cv2.findChessboardCornersSB(img8, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not ok:
        return None
    pts = corners.reshape(-1, 2).astype(np.float64) + 0.5
    # One order for both cameras: rows top to bottom, each left to right.
    grid = pts.reshape(pattern[1], pattern[0], 2)
    if grid[0, 0, 1] > grid[-1, 0, 1]:
        grid = grid[::-1]
    if grid[0, 0, 0] > grid[0, -1, 0]:
        grid = grid[:, ::-1]
    return grid.reshape(-1, 2)


def fit_measure_mapping(
    vet_pts: np.ndarray, meas_pts: np.ndarray, measure_shape: tuple[int, int]
) -> dict:
    """The measurement camera's mapping from corresponding points: ``measure_homography``
    (undistorted measurement -> VET pixel coordinates), ``measure_k1``, ``measure_k2``
    (:func:`stages.optics.distort`), and the fit's RMS residual in measurement pixels.
    ``vet_pts``, ``meas_pts``: (N, 2) in vet's pixel coordinates; ``measure_shape``
    (H, W)."""
    import cv2
    from scipy.optimize import least_squares

    h0, _ = cv2.findHomography(meas_pts, vet_pts, 0)
    h0 = h0 / h0[2, 2]

    def predict(p: np.ndarray) -> np.ndarray:
        hm = np.append(p[:8], 1.0).reshape(3, 3)
        hinv = np.linalg.inv(hm)
        q = np.c_[vet_pts, np.ones(len(vet_pts))] @ hinv.T
        dx, dy = distort(q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], measure_shape, p[8], p[9])
        return np.c_[dx, dy]

    def resid(p: np.ndarray) -> np.ndarray:
        return (predict(p) - meas_pts).ravel()

    p0 = np.r_[h0.ravel()[:8], 0.0, 0.0]
    fit = least_squares(resid, p0, x_scale="jac", method="lm")
    r = resid(fit.x).reshape(-1, 2)
    return {
        "measure_homography": np.append(fit.x[:8], 1.0).reshape(3, 3).tolist(),
        "measure_k1": float(fit.x[8]),
        "measure_k2": float(fit.x[9]),
        "rms_px": float(np.sqrt(np.mean(np.sum(r * r, axis=1)))),
    }


def mapping_error_px(est: RigParams, truth: RigParams, step: int = 4) -> float:
    """RMS over the measurement camera's frame (every ``step``-th pixel) of the distance,
    in VET pixels, between where ``est`` and ``truth`` map its pixel centres."""
    xe, ye = measure_to_vet(est)
    xt, yt = measure_to_vet(truth)
    d2 = (xe - xt) ** 2 + (ye - yt) ** 2
    return float(np.sqrt(np.mean(d2[::step, ::step])))


def emulated_target_stack(
    rig: RigParams,
    seed: int = 0,
    square_px: int = 12,
    frames: int = 4,
    offset_px: tuple[float, float] = (0.0, 0.0),
) -> tuple[list[np.ndarray], list[np.ndarray], tuple[int, int]]:
    """The chessboard target (:func:`chessboard_target`) as the emulated rig's VET camera
    (all cells open, half the full well on white) and measurement camera record it,
    ``frames`` frames each: lists of (H, W) and (Hm, Wm) float32 DN (black level
    subtracted, integer codes), and the corner pattern."""
    target, pattern = chessboard_target(rig.sensor_size, square_px, offset_px=offset_px)
    rng = np.random.default_rng(seed)
    lam = target * np.float32(0.5 * rig.full_well_e)
    vet = [expose(lam.copy(), rig, rng)[..., 0] for _ in range(frames)]
    geom = MeasureGeometry(rig)
    meas = [geom.expose(lam, 0.0, rng)[..., 0] for _ in range(frames)]
    return vet, meas, pattern


def emulated_target_frames(
    rig: RigParams, seed: int = 0, square_px: int = 12, frames: int = 4
) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """The chessboard target as the emulated rig's VET camera (all cells open, half the
    full well on white) and measurement camera record it, each the mean of ``frames``
    frames: (H, W) and (Hm, Wm) DN, and the corner pattern."""
    vet, meas, pattern = emulated_target_stack(rig, seed, square_px, frames)
    return np.mean(vet, axis=0), np.mean(meas, axis=0), pattern


def emulated_corner_pairs(rig: RigParams, seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """Chessboard corners found in both emulated cameras' frames, ``(vet_pts, meas_pts)``,
    trying square sizes from 12 px until the detector finds the whole board in both (as
    a lab moves the board nearer or farther); None if it never does."""
    for square in (12, 16, 10, 20, 8, 24):
        vet, meas, pattern = emulated_target_frames(rig, seed=seed, square_px=square)
        if min(pattern) < 3:
            continue
        pv, pm = find_corners(vet, pattern), find_corners(meas, pattern)
        if pv is not None and pm is not None:
            return pv, pm
    return None


# --- switching time and trigger offset ------------------------------------------------


def switching_exposure(
    windows_s: np.ndarray, t_close: float, switch_s: float, leakage: float
) -> np.ndarray:
    """``E(W)``: exposure (s) of a still pixel whose cell is applied closed at
    ``t_close`` when the VET camera integrates ``[0, W]``."""
    w = np.asarray(windows_s, np.float64)
    open_s = open_integral(w - t_close, switch_s) - open_integral(-t_close + 0 * w, switch_s)
    return leakage * w + (1.0 - leakage) * open_s


def fit_switching(
    windows_s: np.ndarray, exposure_s: np.ndarray, leakage: float, t_guess: float
) -> tuple[float, float]:
    """``(t_close, switch_s)`` fitted by least squares to exposures ``E(W)`` measured for
    windows ``W`` (s) around a closure applied near ``t_guess`` (s), the cell's
    ``leakage`` known (:func:`switching_exposure`)."""
    from scipy.optimize import least_squares

    w = np.asarray(windows_s, np.float64)
    e = np.asarray(exposure_s, np.float64)

    def resid(p: np.ndarray) -> np.ndarray:
        return (switching_exposure(w, p[0], abs(p[1]), leakage) - e) * 1e3

    best = None
    for s0 in (0.5e-3, 2e-3, 5e-3):
        fit = least_squares(resid, [t_guess, s0], x_scale=[1e-3, 1e-3])
        if best is None or fit.cost < best.cost:
            best = fit
    return float(best.x[0]), float(abs(best.x[1]))


def fit_switching_scaled(
    windows_s: np.ndarray, signal: np.ndarray, leakage: float, t_guess: float
) -> tuple[float, float, float]:
    """``(t_close, switch_s, rate)``: as :func:`fit_switching` for a signal proportional
    to the exposure, ``signal = rate * E(W)`` with the rate unknown (DN/s of a flat field
    whose level is not otherwise known; dark-subtracted). The windows before the closure
    pin the rate, so the series must start before it. For each ``(t, s)`` the rate is
    the linear least-squares one (variable projection)."""
    from scipy.optimize import least_squares

    w = np.asarray(windows_s, np.float64)
    y = np.asarray(signal, np.float64)
    scale = float(np.max(np.abs(y))) or 1.0
    y = y / scale

    def rate(p: np.ndarray) -> tuple[float, np.ndarray]:
        e = switching_exposure(w, p[0], abs(p[1]), leakage)
        return float(e @ y / max(e @ e, 1e-300)), e

    def resid(p: np.ndarray) -> np.ndarray:
        r, e = rate(p)
        return (r * e - y) * 1e3

    best = None
    for s0 in (0.5e-3, 2e-3, 5e-3):
        fit = least_squares(resid, [t_guess, s0], x_scale=[1e-3, 1e-3])
        if best is None or fit.cost < best.cost:
            best = fit
    r, _ = rate(best.x)
    return float(best.x[0]), float(abs(best.x[1])), r * scale


def emulated_switching_frames(
    rig: RigParams,
    close_at: int,
    windows_s: np.ndarray,
    rate_e_s: float,
    seed: int = 0,
    dark: bool = False,
) -> list[np.ndarray]:
    """VET frames of a flat field, one per window ``W`` (s): every cell commanded closed
    at subframe ``close_at`` (applied on the emulated rig's jittered trigger clock, one
    frame per window, its own draw), ``rate_e_s`` electrons per second, through the
    sensor chain (with the dark current when ``dark``): (H, W) float32 DN each, black
    level subtracted."""
    h, w = rig.sensor_size[1], rig.sensor_size[0]
    cm = CellMap.for_rig(rig, (h, w))
    eps = pixel_leakage(rig, cm).astype(np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for k, win in enumerate(windows_s):
        starts, _ = subframe_clock(rig, timing_rng(seed * 1000 + k))
        t = np.full((h, w), starts[close_at])
        trans = relay_blur(slot_transmittance(t, 0.0, float(win), eps, rig), rig.relay_blur_px)
        lam = trans * np.float32(rate_e_s * win)
        if dark:
            lam = lam + np.float32(rig.dark_current_e_s * win)
        out.append(expose(lam[..., None].astype(np.float32), rig, rng)[..., 0])
    return out


def emulated_switching_series(
    rig: RigParams,
    close_at: int,
    windows_s: np.ndarray,
    rate_e_s: float,
    seed: int = 0,
) -> np.ndarray:
    """Mean exposure (s) of a flat field's VET pixels for each window ``W``
    (:func:`emulated_switching_frames` without dark current, divided back by the gain
    and the rate)."""
    frames = emulated_switching_frames(rig, close_at, windows_s, rate_e_s, seed)
    g = rig.gain_dn_per_e
    return np.asarray([float(np.mean(dn)) / g / rate_e_s for dn in frames])


# --- the relay blur ----------------------------------------------------------------------


def fit_edge_blur(diff: np.ndarray, axis: int = 1, step: int = 4, half: int = 8) -> float | None:
    """The relay blur's Gaussian sigma (VET px) from an (H, W) image holding one edge
    between two flat levels of opposite sign, across ``axis`` (1: a vertical edge, each
    row crosses it once): e.g. the first Gray-code bit's pattern minus its inverse. Every
    ``step``-th line is fitted with ``b + a erf((x - x0) / (sqrt(2) sigma))`` over
    ``half`` pixels either side of its sign change; the median sigma. None when no line
    crosses the edge once with a clear step (at least 10 noise sigmas)."""
    from scipy.optimize import least_squares
    from scipy.special import erf

    a = np.asarray(diff, np.float64)
    if axis == 0:
        a = a.T
    sigmas = []
    x = np.arange(2 * half) + 0.5
    for line in a[::step]:
        sign = np.sign(line)
        cross = np.flatnonzero(sign[1:] * sign[:-1] < 0)
        if cross.size == 0:
            continue
        mid = int(np.median(cross))
        if mid < half or mid + half >= line.size or np.any(np.abs(cross - mid) > half // 2):
            continue
        seg = line[mid - half + 1 : mid + half + 1]
        lo, hi = np.median(line[: mid - half]), np.median(line[mid + half + 1 :])
        noise = float(np.std(line[: mid - half] - lo)) + 1e-12
        if abs(hi - lo) < 10 * noise:
            continue

        def resid(p: np.ndarray, seg: np.ndarray = seg) -> np.ndarray:
            return p[0] + p[1] * erf((x - p[2]) / (np.sqrt(2) * max(abs(p[3]), 1e-3))) - seg

        p0 = [(hi + lo) / 2, (hi - lo) / 2, float(half), 1.0]
        fit = least_squares(resid, p0, x_scale=[abs(hi - lo), abs(hi - lo), 1.0, 1.0])
        sigmas.append(abs(fit.x[3]))
    return float(np.median(sigmas)) if sigmas else None


def calibrate_parts(rig: RigParams, seed: int = 0) -> tuple[dict, dict]:
    """The parts of the emulated ``rig`` found from the frames its physics records: the
    measurement -> VET mapping (chessboard), the trigger offset and switching time
    (closures at subframe 20). Returns the RigParams fields found and their errors
    against the truth (``mapping_rms_px``, ``trigger_offset_err_s``,
    ``switch_rel_err``)."""
    found: dict = {}
    errors: dict = {}
    if not rig.ideal_geometry:
        pairs = emulated_corner_pairs(rig, seed)
        if pairs is not None:
            fit = fit_measure_mapping(*pairs, rig.measure_shape)
            found = {k: fit[k] for k in ("measure_homography", "measure_k1", "measure_k2")}
            errors["mapping_rms_px"] = mapping_error_px(rig.replace(**found), rig)
    if rig.switch_s > 0 or rig.trigger_offset_s > 0:
        c = min(20, rig.n_subframes - 1)
        t_true = c * rig.subframe_s + rig.trigger_offset_s
        wins = t_true + np.linspace(-2e-3, 5e-3, 15)
        wins = wins[(wins > 0) & (wins <= rig.frame_s)]
        e = emulated_switching_series(rig, c, wins, 0.5 * rig.full_well_e / wins.max(), seed)
        t_fit, s_fit = fit_switching(wins, e, rig.leakage, c * rig.subframe_s)
        found["trigger_offset_s"] = max(0.0, t_fit - c * rig.subframe_s)
        found["switch_s"] = s_fit
        errors["trigger_offset_err_s"] = found["trigger_offset_s"] - rig.trigger_offset_s
        if rig.switch_s > 0:
            errors["switch_rel_err"] = s_fit / rig.switch_s - 1
    return found, errors


def selftest(size: tuple[int, int] = (320, 240), seed: int = 0) -> dict:
    """Each part calibrated on the emulated realistic rig against its truth: the mapping's
    RMS error over the frame (VET px), the trigger offset and switching time (s, found
    and true), the per-pixel leakage's largest relative error and the per-cell one's
    median, 99th percentile and largest (:func:`.cell_leakage.calibrate_cell_leakage`, the truth's
    geometry)."""
    from ..optics import rig_profile
    from .cell_leakage import calibrate_cell_leakage, emulated_leakage_frames, leakage_from_halves

    rig = rig_profile("realistic", size)
    pairs = emulated_corner_pairs(rig, seed)
    if pairs is None:
        raise RuntimeError("chessboard corners not found")
    fit = fit_measure_mapping(*pairs, rig.measure_shape)
    est = rig.replace(
        measure_homography=fit["measure_homography"],
        measure_k1=fit["measure_k1"],
        measure_k2=fit["measure_k2"],
    )
    c = 20
    t_true = c * rig.subframe_s + rig.trigger_offset_s
    wins = t_true + np.linspace(-2e-3, 5e-3, 15)
    e = emulated_switching_series(rig, c, wins, 0.5 * rig.full_well_e / wins.max(), seed)
    t_fit, s_fit = fit_switching(wins, e, rig.leakage, c * rig.subframe_s)
    ratio, _ = leakage_from_halves(*emulated_leakage_frames(rig, seed=seed))
    cm = CellMap.for_rig(rig, (size[1], size[0]))
    true_px = relay_blur(pixel_leakage(rig, cm), rig.relay_blur_px)
    px_err = float(np.abs(ratio / true_px - 1).max())
    _, cell_errors = calibrate_cell_leakage(rig, rig, seed=seed, margins_px=(0.0,))
    return {
        "mapping_rms_px": mapping_error_px(est, rig),
        "k1": (fit["measure_k1"], rig.measure_k1),
        "trigger_offset_s": (t_fit - c * rig.subframe_s, rig.trigger_offset_s),
        "switch_s": (s_fit, rig.switch_s),
        "leakage_per_pixel_max_rel_err": px_err,
        **cell_errors,
    }


if __name__ == "__main__":
    import json
    import sys

    wh = sys.argv[1] if len(sys.argv) > 1 else "320x240"
    w, h = (int(v) for v in wh.split("x"))
    print(json.dumps(selftest((w, h)), indent=1))
