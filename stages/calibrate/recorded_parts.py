"""The parts of a real rig (:mod:`.parts`) fitted from a folder of recorded frames.

Called by :func:`.recorded.calibrate_from_folder` once the flat-field calibration
(:func:`.frames.calibrate_frames`) is made, with the frames it read averaged:

- **chessboard poses** (``target_vet_PP`` / ``target_meas_PP``): the inner corners in
  both cameras' frames of each pose (:func:`find_board`; the pattern from the folder's
  ``rig.toml`` or found by :func:`estimate_pattern`), every pose's pairs pooled into one
  :func:`.parts.fit_measure_mapping`: ``measure_homography``, ``measure_k1``,
  ``measure_k2`` (and ``measure_size`` when the measurement camera's frames differ in
  size from the VET camera's);
- **switching series** (``switch_C_Ws``): per window ``W`` the flat field's mean DN over
  the LCoS footprint, bias and dark current subtracted, fitted with an unknown light
  level by :func:`.parts.fit_switching_scaled` (the cells' mean leakage from the
  calibration's leakage map): ``trigger_offset_s`` (the applied closure's time minus
  ``C tau``) and ``switch_s``;
- **Gray-code frames**: the first column bit's and the first row bit's pattern minus
  inverse each hold one edge of the LCoS image, whose width is the relay blur
  (:func:`.parts.fit_edge_blur`): ``relay_blur_px``;
- **measurement flat field** (``meas_flat_*`` against ``open_*``, dark-subtracted): the
  measurement camera's vignetting and gain through the fitted mapping
  (:func:`.meas_flat.measure_flat_parts`): ``measure_vignetting``, ``measure_gain``,
  ``measure_fraction``;
- **frame ids and timestamps** (``meas_timestamps.csv``): the trigger's jitter and the
  dropped frames (:func:`.frame_clock.clock_parts`): ``trigger_jitter_s``,
  ``drop_rate``.

The per-pixel leakage needs nothing here: it is the calibration's ``leakage`` map
(all-closed over all-open rates, :func:`.sensor_models.leakage_map`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from ..rig import RigParams
from .calfile import Calibration
from .frames import CalibrationFrames
from .gray_code import gray_bit_counts
from .parts import find_corners, fit_edge_blur, fit_measure_mapping, fit_switching_scaled

log = logging.getLogger("vet.calibrate")

#: The fewest windows a switching series needs (three unknowns: closure, switch, rate).
MIN_WINDOWS = 6


def estimate_pattern(img: np.ndarray) -> list[tuple[int, int]]:
    """Candidate inner-corner patterns (columns, rows) of the chessboard in an (H, W)
    frame, most corners first: from the median count of dark/bright transitions along
    rows and columns through the middle of the frame (a board with ``n`` inner corners
    across gives ``n`` to ``n + 2`` transitions, the margins unknown)."""
    import cv2

    a = cv2.GaussianBlur(np.asarray(img, np.float32), (0, 0), 1.0)
    lo, hi = np.percentile(a, 1), np.percentile(a, 99)
    if hi <= lo:
        return []
    b = (a > 0.5 * (lo + hi)).astype(np.int8)
    h, w = b.shape
    rows = b[np.linspace(0.3 * h, 0.7 * h, 9).astype(int)]
    cols = b[:, np.linspace(0.3 * w, 0.7 * w, 9).astype(int)].T
    tx = int(np.median(np.count_nonzero(np.diff(rows, axis=1), axis=1)))
    ty = int(np.median(np.count_nonzero(np.diff(cols, axis=1), axis=1)))
    cands = [
        (nx, ny)
        for nx in range(tx + 1, tx - 3, -1)
        for ny in range(ty + 1, ty - 3, -1)
        if nx >= 3 and ny >= 3
    ]
    return sorted(cands, key=lambda p: -p[0] * p[1])


def find_board(
    img: np.ndarray, pattern: tuple[int, int] | None = None
) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The chessboard's inner corners in an (H, W) frame and its pattern: ``pattern``
    (columns, rows) when given, else the first of :func:`estimate_pattern`'s candidates
    that :func:`.parts.find_corners` finds. None when not found."""
    for p in [pattern] if pattern is not None else estimate_pattern(img):
        pts = find_corners(img, p)
        if pts is not None:
            return pts, p
    return None


def fit_mapping_from_poses(
    poses: dict[str, tuple[np.ndarray, np.ndarray]], pattern: tuple[int, int] | None
) -> tuple[dict | None, list[str]]:
    """The measurement -> VET mapping from chessboard poses ``{name: (vet (H, W),
    meas (Hm, Wm))}`` (DN, averaged frames). Returns the :func:`.parts.fit_measure_mapping`
    result with ``poses`` (names used), ``corners`` and ``pattern`` added (None if no pose
    was found in both cameras), and a note per pose left out."""
    vet_pts, meas_pts, used, notes = [], [], [], []
    shape_m = None
    found_pattern = pattern
    for name, (vet, meas) in sorted(poses.items()):
        bv = find_board(vet, pattern)
        if bv is None:
            notes.append(f"{name}: chessboard not found in the VET camera's frame")
            continue
        pm = find_corners(meas, bv[1])
        if pm is None:
            notes.append(
                f"{name}: chessboard ({bv[1][0]}x{bv[1][1]}) not found in the measurement "
                "camera's frame"
            )
            continue
        if shape_m is not None and meas.shape != shape_m:
            notes.append(f"{name}: measurement frame size differs from the other poses'")
            continue
        shape_m, found_pattern = meas.shape, bv[1]
        vet_pts.append(bv[0])
        meas_pts.append(pm)
        used.append(name)
    if not used:
        return None, notes
    fit = fit_measure_mapping(np.concatenate(vet_pts), np.concatenate(meas_pts), shape_m)
    fit.update(
        poses=used,
        corners=int(sum(len(p) for p in vet_pts)),
        pattern=list(found_pattern),
        measure_shape=list(shape_m),
    )
    return fit, notes


def fit_switching_from_means(
    series: dict[int, tuple[np.ndarray, np.ndarray]], leakage: float, subframe_s: float
) -> dict | None:
    """Trigger offset and switching time from switching series ``{c: (windows_s,
    signal)}`` (signal: dark-subtracted mean DN of the flat field per window, the cells
    applied closed at subframe ``c``). Each closure is fitted on its own and the results
    averaged: ``trigger_offset_s``, ``switch_s``, ``closures``, ``windows``. None if no
    series has :data:`MIN_WINDOWS` windows starting before ``c tau``."""
    offsets, switches, used, n_win = [], [], [], 0
    for c, (wins, sig) in sorted(series.items()):
        t_nom = c * subframe_s
        if len(wins) < MIN_WINDOWS or float(np.min(wins)) >= t_nom:
            log.warning(
                "calibrate: switching series at subframe %d has %d windows%s; skipped "
                "(need %d or more, from before the closure)",
                c,
                len(wins),
                "" if len(wins) < MIN_WINDOWS else ", none before the closure",
                MIN_WINDOWS,
            )
            continue
        t, s, _ = fit_switching_scaled(wins, sig, leakage, t_nom)
        offsets.append(t - t_nom)
        switches.append(s)
        used.append(c)
        n_win += len(wins)
    if not used:
        return None
    offset = float(np.mean(offsets))
    if offset < -1e-4:
        log.warning(
            "calibrate: the switching series put the closure %.3g ms before its subframe; "
            "trigger offset set to 0 (is C the subframe the LCoS applied it at?)",
            -offset * 1e3,
        )
    return {
        "trigger_offset_s": max(0.0, offset),
        "switch_s": float(np.mean(switches)),
        "closures": used,
        "windows": n_win,
    }


def fit_folder_parts(
    cal: Calibration,
    params: RigParams,
    poses: dict[str, tuple[np.ndarray, np.ndarray]],
    switch_means: dict[int, dict[float, np.ndarray]],
    pattern: tuple[int, int] | None,
    gray_diffs: list[np.ndarray] | None = None,
    frames: CalibrationFrames | None = None,
    clock: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Fit the parts the folder's frames allow into ``cal`` (in place): ``cal.parts``
    (RigParams fields), ``cal.provenance["parts_fit"]`` (what each fit used and its
    residual), and a warning plus a ``provenance["skipped"]`` entry for each part
    missing. ``switch_means``: ``{c: {W: mean frame (H, W) DN}}``; ``gray_diffs``: the
    Gray-code differences of :class:`.frames.CalibrationFrames`; ``frames``: those
    frames (the flat fields); ``clock``: the measurement camera's frame ids and
    timestamps (:func:`.frame_clock.read_timestamps`)."""
    skipped = cal.provenance.setdefault("skipped", [])
    info: dict = {}

    def skip(what: str) -> None:
        skipped.append(what)
        log.warning("calibrate: skipped %s", what)

    mapping = None
    if poses:
        fit, notes = fit_mapping_from_poses(poses, pattern)
        for n in notes:
            log.warning("calibrate: target %s; pose left out", n)
        if fit is None:
            skip("measurement -> VET mapping (no chessboard pose found in both cameras)")
        else:
            cal.parts.update(
                {k: fit[k] for k in ("measure_homography", "measure_k1", "measure_k2")}
            )
            hm, wm = fit["measure_shape"]
            if (wm, hm) != tuple(cal.sensor_size):
                cal.parts["measure_size"] = [wm, hm]
            info["mapping"] = {
                k: fit[k] for k in ("rms_px", "poses", "corners", "pattern", "measure_shape")
            }
            mapping = fit
    else:
        skip("measurement -> VET mapping (no target_vet_PP / target_meas_PP frames)")

    if switch_means:
        fitted = _switching(cal, params, switch_means)
        if fitted is None:
            skip("trigger offset and switching time (no usable switching series)")
        else:
            cal.parts["trigger_offset_s"] = fitted.pop("trigger_offset_s")
            cal.parts["switch_s"] = fitted.pop("switch_s")
            info["switching"] = fitted
    else:
        skip("trigger offset and switching time (no switch_C_Ws frames)")

    if gray_diffs:
        nx, _ = gray_bit_counts(cal.lcos_cells)
        found = [
            s
            for s in (fit_edge_blur(gray_diffs[0], 1), fit_edge_blur(gray_diffs[nx], 0))
            if s is not None
        ]
        if found:
            cal.parts["relay_blur_px"] = float(np.mean(found))
            info["relay_blur"] = {"edges": len(found), "sigmas_px": found}
        else:
            skip("relay blur (no clean edge in the first Gray-code bits)")
    else:
        skip("relay blur (no Gray-code frames)")

    _measure_flat(cal, params, frames, mapping, info, skip)
    if not params.ideal_shutter or cal.parts.get("relay_blur_px", 0.0) > 0:
        _cell_leakage(cal, params, frames, info, skip)
    if clock is None:
        skip("trigger jitter and drop rate (no meas_timestamps.csv)")
    else:
        from .frame_clock import clock_parts

        got = clock_parts(*clock, params)
        if got is None:
            skip("trigger jitter and drop rate (meas_timestamps.csv not usable)")
        else:
            cal.parts.update(got[0])
            info["frame_clock"] = got[1]
    if info:
        cal.provenance["parts_fit"] = info


def _switching(
    cal: Calibration, params: RigParams, switch_means: dict[int, dict[float, np.ndarray]]
) -> dict | None:
    """The switching fit on the footprint's mean, bias and dark current subtracted."""
    bias: np.ndarray | float = 0.0 if cal.bias_dn is None else cal.bias_dn
    dark_dn_s: np.ndarray | float = (
        0.0 if cal.dark_current_e_s is None else cal.dark_current_e_s * params.gain_dn_per_e
    )
    if cal.bias_dn is None:
        log.warning(
            "calibrate: no dark frames: the switching series is not bias-subtracted (exact only "
            "for black-subtracted frames)"
        )
    leakage = float(params.leakage)
    sel: np.ndarray | None = None
    if cal.leakage is not None:
        sel = np.isfinite(cal.leakage) & (cal.leakage < 0.5)  # under the LCoS
        if sel.any():
            leakage = float(np.mean(cal.leakage[sel]))
        else:
            sel = None
    mean: Callable[[np.ndarray], float] = (
        (lambda a: float(np.mean(a))) if sel is None else (lambda a: float(np.mean(a[sel])))
    )
    series = {}
    for c, by_w in switch_means.items():
        wins = np.asarray(sorted(by_w), np.float64)
        sig = np.asarray([mean(by_w[w] - bias - dark_dn_s * w) for w in wins])
        series[c] = (wins, sig)
    out = fit_switching_from_means(series, leakage, params.subframe_s)
    if out is not None:
        out["leakage_mean"] = leakage
    return out


def _measure_flat(
    cal: Calibration,
    params: RigParams,
    frames: CalibrationFrames | None,
    mapping: dict | None,
    info: dict,
    skip: Callable[[str], None],
) -> None:
    """The measurement camera's gain and vignetting into ``cal.parts`` (or skipped)."""
    from .meas_flat import flat_rates, measure_flat_parts

    rates = None
    if frames is not None:
        dark = None if cal.dark_current_e_s is None else cal.dark_current_e_s * params.gain_dn_per_e
        rates = flat_rates(frames.meas_flat, frames.meas_dark, frames.open, cal.bias_dn, dark)
    if rates is None:
        skip("measurement gain and vignetting (need meas_flat_* and open_* frames)")
        return
    got = measure_flat_parts(*rates, params, mapping)
    if got is None:
        skip("measurement gain and vignetting (no usable fit)")
        return
    cal.parts.update(got[0])
    info["measure_flat"] = got[1]


def _cell_leakage(
    cal: Calibration,
    params: RigParams,
    frames: CalibrationFrames | None,
    info: dict,
    skip: Callable[[str], None],
) -> None:
    """The per-cell leakage (:mod:`.cell_leakage`) into ``cal.cell_leakage`` from the
    halves of the open and closed flat fields at their longest exposure, through the
    homography and relay blur found (or skipped)."""
    from .cell_leakage import leakage_from_halves, leakage_per_cell
    from .sensor_models import signal_rate

    halves = {} if frames is None else frames.halves
    if "open" not in halves or "closed" not in halves or cal.homography is None:
        skip(
            "per-cell leakage (need two or more open_ and closed_ frames at the longest "
            "exposure, and the Gray code)"
        )
        return
    bias = 0.0 if cal.bias_dn is None else cal.bias_dn
    dark = 0.0 if cal.dark_current_e_s is None else cal.dark_current_e_s * params.gain_dn_per_e
    t_o, t_c = max(frames.open), max(frames.closed)
    closed = np.stack([signal_rate(f, t_c, bias, dark) for f in halves["closed"]])
    opened = np.stack([signal_rate(f, t_o, bias, dark) for f in halves["open"]])
    ratio, noise = leakage_from_halves(closed, opened)
    ratio = np.nan_to_num(ratio, nan=float(np.nanmedian(ratio)), posinf=1.0, neginf=0.0)
    rig = params.replace(
        sensor_size=tuple(cal.sensor_size),
        lcos_cells=tuple(cal.lcos_cells),
        homography=np.asarray(cal.homography, float).tolist(),
        relay_blur_px=float(cal.parts.get("relay_blur_px", params.relay_blur_px)),
    )
    cells, _, cal.cell_leakage, fit = leakage_per_cell(np.clip(ratio, 0.0, 1.0), rig, noise)
    info["cell_leakage"] = {
        "frames": int(min(frames.counts[f"open_{t_o:g}s"], frames.counts[f"closed_{t_c:g}s"])),
        "noise": noise,
        "cells": int(cells.size),
        **fit,
    }
