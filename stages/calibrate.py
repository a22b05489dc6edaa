"""Rig calibration: LCoS-to-camera homography, dark current, bias, leakage, gain ratio.

What is measured, and from which frames (all frames in DN as the camera delivers them):

- **Homography** LCoS cell coordinates -> VET sensor pixel coordinates. The LCoS shows
  the Gray-code patterns of ``cv2.structured_light.GrayCodePattern`` (columns then rows,
  most significant bit first), each followed by its inverse; the VET camera images a
  flat bright field through them. A pixel's bit is 1 where it is brighter under the
  pattern than under the inverse (the standard pattern/inverse comparison, which needs
  no per-pixel threshold and cancels the scene, vignetting and leakage); the bits are a
  Gray code of the cell index that covers the pixel. OpenCV's own ``decode`` targets
  projector-camera stereo pairs and ``getProjPixel`` is a per-pixel call, so the bits
  are decoded here, vectorised, from the same patterns. Every decoded pixel gives one
  correspondence (pixel centre, cell centre); the cell index is the quantised quantity,
  so the fit runs pixel -> cell (errors in the fitted variable), RANSAC on a sample,
  then least squares on all inliers, and is inverted.
- **Dark frames** (no light) at two or more exposure times: per pixel, a straight line
  DN = bias + g * d * t gives the bias (black-level residual, DN) and the dark current
  d (electrons/s; g the conversion gain in DN per electron).
- **Leakage**: a flat field with the LCoS all open and all closed, each dark-subtracted
  and divided by its exposure time; the ratio per pixel is the closed cells'
  transmittance. The closed frame gets a longer exposure so both are well exposed.
- **Gain ratio**: measurement-camera signal rate over VET-camera signal rate (all open)
  on the same flat field, per pixel, median: the ``measure_fraction`` of the rig.

The measurement camera is not behind the LCoS, so the Gray code says nothing about it;
on the emulated rig the measurement sensor and the VET sensor share their pixel grid.
A real rig needs a second homography measurement -> VET, found from a textured target
imaged by both (chessboard corners or ECC, ``cv2.findTransformECC`` with
``MOTION_HOMOGRAPHY``); that is not implemented yet (see docs/calibration.md).

The result is a :class:`Calibration`, stored as a :class:`~stages.formats.layered.Layered`
file with ``kind = "calibration"`` (EXR or npz). :func:`apply_calibration` turns it into
:class:`~stages.rig.RigParams` for ``capture`` and ``hdr-static``.

References
----------
.. [1] Gray, F. (1953). Pulse code communication. US Patent 2,632,058.
.. [2] Inokuchi, S., Sato, K., Matsuda, F. (1984). Range imaging system for 3-D object
   recognition. Proc. ICPR, 806-808 (Gray-code structured light).
.. [3] Hartley, R., Zisserman, A. (2004). Multiple View Geometry, 2nd ed., ch. 4
   (homography estimation, RANSAC).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FormatError, InputError
from .rig import RigParams

log = logging.getLogger("vet.calibrate")

ProgressFn = Callable[[int, int], None]

#: File extensions read by :func:`calibrate_from_folder`: OpenCV images and camera raws.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")
RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")

CALIBRATION_KIND = "calibration"


# --- Gray code ----------------------------------------------------------------------------


def gray_bit_counts(lcos_cells: tuple[int, int]) -> tuple[int, int]:
    """Number of Gray-code bits for columns and rows, ``ceil(log2(n))`` each.

    Parameters
    ----------
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.

    Returns
    -------
    (int, int)
        Bits along x (columns) and along y (rows).
    """
    w, h = lcos_cells
    return math.ceil(math.log2(w)), math.ceil(math.log2(h))


def gray_code_patterns(lcos_cells: tuple[int, int]) -> list[np.ndarray]:
    """The Gray-code patterns of ``cv2.structured_light.GrayCodePattern``, as open masks.

    Parameters
    ----------
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.

    Returns
    -------
    list of ndarray of shape (H_cells, W_cells), bool
        True where the cell is open (white). Order as OpenCV generates them: for each
        column bit (most significant first) the pattern then its inverse, then the
        same for the row bits; ``2 * (bits_x + bits_y)`` images.
    """
    import cv2

    w, h = lcos_cells
    gen = cv2.structured_light.GrayCodePattern_create(width=int(w), height=int(h))
    ok, patterns = gen.generate()
    if not ok:  # pragma: no cover - OpenCV refuses only absurd sizes
        raise ValueError(f"OpenCV could not generate Gray-code patterns for {w}x{h} cells.")
    nx, ny = gray_bit_counts(lcos_cells)
    if len(patterns) != 2 * (nx + ny):  # pragma: no cover - guards an OpenCV change
        raise RuntimeError(
            f"unexpected Gray-code pattern count {len(patterns)} (expected {2 * (nx + ny)})"
        )
    return [np.asarray(p) > 127 for p in patterns]


def decode_gray(
    diffs: Sequence[np.ndarray],
    lcos_cells: tuple[int, int],
    min_contrast_dn: float = 8.0,
    rel_contrast: float = 0.25,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode per-pixel Gray-code bits into the LCoS cell seen by each pixel.

    Parameters
    ----------
    diffs : sequence of ndarray of shape (H, W)
        ``image(pattern) - image(inverse)`` for each bit, in the order of
        :func:`gray_code_patterns` (column bits MSB first, then row bits), DN.
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.
    min_contrast_dn : float
        A pixel whose strongest pattern/inverse difference is below this (DN) is not
        modulated by the LCoS (outside its footprint, or dark) and stays undecoded.
    rel_contrast : float
        A bit is trusted when ``|diff|`` is at least this fraction of the pixel's
        strongest difference; pixels with an untrusted bit (on a cell edge, blurred)
        stay undecoded.

    Returns
    -------
    cell_x, cell_y : ndarray of shape (H, W), int32
        Decoded cell column and row (-1 where undecoded).
    valid : ndarray of shape (H, W), bool
    """
    nx, ny = gray_bit_counts(lcos_cells)
    if len(diffs) != nx + ny:
        raise ValueError(
            f"need {nx + ny} pattern/inverse differences for {lcos_cells[0]}x{lcos_cells[1]} "
            f"cells, got {len(diffs)}."
        )
    stack = [np.asarray(d, dtype=np.float32) for d in diffs]
    shape = stack[0].shape
    if any(d.shape != shape for d in stack):
        raise ValueError("all pattern differences must have the same shape.")
    amp = np.zeros(shape, np.float32)
    for d in stack:
        np.maximum(amp, np.abs(d), out=amp)
    valid = amp >= min_contrast_dn
    floor = rel_contrast * amp
    for d in stack:
        valid &= np.abs(d) >= floor

    def _to_binary(bits: list[np.ndarray]) -> np.ndarray:
        value = np.zeros(shape, np.int32)
        b = np.zeros(shape, bool)
        for g in bits:  # MSB first: b_i = b_{i-1} xor g_i
            b = b ^ g
            value = (value << 1) | b
        return value

    cx = _to_binary([d > 0 for d in stack[:nx]])
    cy = _to_binary([d > 0 for d in stack[nx:]])
    valid &= (cx < lcos_cells[0]) & (cy < lcos_cells[1])
    cx = np.where(valid, cx, -1).astype(np.int32)
    cy = np.where(valid, cy, -1).astype(np.int32)
    return cx, cy, valid


# --- homography ---------------------------------------------------------------------------


@dataclass
class HomographyFit:
    """Result of :func:`fit_homography`.

    Attributes
    ----------
    homography : ndarray of shape (3, 3)
        LCoS cell coordinates -> VET pixel coordinates (``H[2, 2] == 1``).
    n_points : int
        Decoded pixels used as correspondences.
    n_inliers : int
        Those within the RANSAC threshold.
    reprojection_rms_px : float
        RMS distance, in pixels, between each inlier pixel centre and the image under
        the homography of the centre of the cell it decoded to. Cell quantisation alone
        makes this about ``pitch / sqrt(6)`` (pitch = cell size in pixels), not zero.
    decode_agreement : float
        Fraction of decoded pixels whose decoded cell is the cell the fitted homography
        assigns them (how :class:`~stages.physics.CellMap` will use it).
    """

    homography: np.ndarray
    n_points: int
    n_inliers: int
    reprojection_rms_px: float
    decode_agreement: float


def _apply_h(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to points of shape (N, 2)."""
    p = np.asarray(pts, dtype=np.float64)
    q = p @ h[:, :2].T + h[:, 2]
    return q[:, :2] / q[:, 2:3]


def fit_homography(
    cell_x: np.ndarray,
    cell_y: np.ndarray,
    valid: np.ndarray,
    ransac_threshold_cells: float = 1.0,
    max_ransac_points: int = 50_000,
    seed: int = 0,
) -> HomographyFit:
    """Fit the cell -> pixel homography from per-pixel decoded cells (RANSAC + least squares).

    Parameters
    ----------
    cell_x, cell_y : ndarray of shape (H, W), int
        Decoded cell per pixel (from :func:`decode_gray`).
    valid : ndarray of shape (H, W), bool
        Pixels that decoded.
    ransac_threshold_cells : float
        RANSAC inlier threshold, in cells (quantisation alone reaches 0.71 cell).
    max_ransac_points : int
        RANSAC runs on a random sample of at most this many correspondences (speed);
        the final least-squares refinement uses every inlier.
    seed : int
        Seed of that sample (deterministic results).

    Returns
    -------
    HomographyFit

    Raises
    ------
    InputError
        Too few decoded pixels, or no consistent homography.
    """
    import cv2

    ys, xs = np.nonzero(valid)
    n = xs.size
    if n < 16:
        raise InputError(
            f"only {n} pixels decoded the Gray code: is the LCoS in front of the VET camera "
            "and the flat field bright enough?"
        )
    pix = np.stack([xs + 0.5, ys + 0.5], axis=1).astype(np.float64)
    cell = np.stack([cell_x[ys, xs] + 0.5, cell_y[ys, xs] + 0.5], axis=1).astype(np.float64)
    rng = np.random.default_rng(seed)  # seeded: the same frames give the same fit
    sample = rng.choice(n, size=min(n, max_ransac_points), replace=False)
    h_pc, _ = cv2.findHomography(
        pix[sample],
        cell[sample],
        cv2.RANSAC,
        ransac_threshold_cells,
        maxIters=4000,
        confidence=0.999,
    )
    if h_pc is None:
        raise InputError("no homography fits the decoded Gray code (RANSAC failed)")
    resid = np.linalg.norm(_apply_h(h_pc, pix) - cell, axis=1)
    inl = resid <= ransac_threshold_cells
    if inl.sum() < 16:
        raise InputError("no homography fits the decoded Gray code (too few inliers)")
    h_ref, _ = cv2.findHomography(pix[inl], cell[inl], 0)
    if h_ref is not None:
        h_pc = h_ref
    h_cp = np.linalg.inv(h_pc)
    h_cp /= h_cp[2, 2]
    err = np.linalg.norm(_apply_h(h_cp, cell[inl]) - pix[inl], axis=1)
    pred = _apply_h(h_pc, pix)
    agree = (np.floor(pred[:, 0]) == cell[:, 0] - 0.5) & (np.floor(pred[:, 1]) == cell[:, 1] - 0.5)
    return HomographyFit(
        homography=h_cp,
        n_points=int(n),
        n_inliers=int(inl.sum()),
        reprojection_rms_px=float(np.sqrt(np.mean(err**2))),
        decode_agreement=float(agree.mean()),
    )


def homography_error_px(
    h_est: np.ndarray,
    h_true: np.ndarray,
    lcos_cells: tuple[int, int],
    sensor_size: tuple[int, int],
    step_cells: float = 4.0,
) -> tuple[float, float]:
    """Distance between two cell -> pixel homographies over the frame.

    Parameters
    ----------
    h_est, h_true : array_like of shape (3, 3)
    lcos_cells : (int, int)
        LCoS grid (width, height), cells.
    sensor_size : (int, int)
        Sensor (width, height), pixels; only cell points whose true image lies on the
        sensor count.
    step_cells : float
        Grid spacing of the cell points, cells.

    Returns
    -------
    max_px, rms_px : float
        Largest and RMS ``|H_est(p) - H_true(p)|`` over the grid, pixels.
    """
    cw, ch = lcos_cells
    gx, gy = np.meshgrid(
        np.arange(0.0, cw + 1e-9, step_cells), np.arange(0.0, ch + 1e-9, step_cells)
    )
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    ht = _apply_h(np.asarray(h_true, float), pts)
    he = _apply_h(np.asarray(h_est, float), pts)
    w, h = sensor_size
    on = (ht[:, 0] >= 0) & (ht[:, 0] <= w) & (ht[:, 1] >= 0) & (ht[:, 1] <= h)
    if not on.any():
        raise ValueError("no cell point of the true homography lands on the sensor.")
    d = np.linalg.norm(he[on] - ht[on], axis=1)
    return float(d.max()), float(np.sqrt(np.mean(d**2)))


def example_homography(
    lcos_cells: tuple[int, int],
    sensor_size: tuple[int, int],
    angle_deg: float = 1.0,
    zoom: float = 1.06,
    shift_frac: tuple[float, float] = (0.0025, -0.002),
    perspective: float = 0.02,
) -> np.ndarray:
    """A realistic misaligned cell -> pixel homography whose LCoS image covers the sensor.

    The nominal full-frame scale, then about the frame centre a rotation by
    ``angle_deg``, a magnification ``zoom`` and a shift by ``shift_frac`` of the sensor
    size (3.2, -2.0 px at 1280x1024), and a keystone that changes the scale by about
    ``perspective`` (relative) from one side of the LCoS to the other.

    Returns
    -------
    ndarray of shape (3, 3)

    Raises
    ------
    ValueError
        If the LCoS image would not cover every sensor pixel.
    """
    cw, ch = lcos_cells
    w, h = sensor_size
    a = math.radians(angle_deg)
    t_cell = np.array([[1, 0, -cw / 2], [0, 1, -ch / 2], [0, 0, 1]], float)
    persp = np.array([[1, 0, 0], [0, 1, 0], [perspective / cw, 0.5 * perspective / ch, 1]], float)
    scale = np.diag([w / cw * zoom, h / ch * zoom, 1.0])
    rot = np.array(
        [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], float
    )
    t_pix = np.array(
        [[1, 0, w / 2 + shift_frac[0] * w], [0, 1, h / 2 + shift_frac[1] * h], [0, 0, 1]], float
    )
    hom = t_pix @ rot @ scale @ persp @ t_cell
    hom /= hom[2, 2]
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], float)
    c = _apply_h(np.linalg.inv(hom), corners)
    if not np.all((c[:, 0] > 0) & (c[:, 0] < cw) & (c[:, 1] > 0) & (c[:, 1] < ch)):
        raise ValueError(
            "this homography leaves part of the sensor outside the LCoS image; raise zoom."
        )
    return hom


# --- dark, leakage, gain ------------------------------------------------------------------


def dark_model(
    dark: dict[float, np.ndarray], gain_dn_per_e: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel bias and dark current from dark frames at two or more exposure times.

    Parameters
    ----------
    dark : dict of float -> ndarray of shape (H, W)
        Exposure time (s) -> mean dark frame at that exposure (DN).
    gain_dn_per_e : float
        Conversion gain, DN per electron.

    Returns
    -------
    bias_dn : ndarray of shape (H, W), float32
        Intercept at zero exposure, DN (the black level as delivered: about 0 for
        black-subtracted frames, the pedestal for raw ones).
    dark_current_e_s : ndarray of shape (H, W), float32
        Slope divided by the gain, electrons per second.
    """
    times = np.array(sorted(dark), dtype=np.float64)
    if times.size < 2 or times[-1] - times[0] <= 0:
        raise ValueError("dark current needs dark frames at two or more different exposure times.")
    tm = times.mean()
    denom = float(np.sum((times - tm) ** 2))
    mean_img = sum(np.asarray(dark[t], np.float64) for t in times) / times.size
    slope = sum((t - tm) * np.asarray(dark[t], np.float64) for t in times) / denom
    bias = mean_img - slope * tm
    return bias.astype(np.float32), (slope / gain_dn_per_e).astype(np.float32)


def signal_rate(
    frame: np.ndarray, exposure_s: float, bias_dn: np.ndarray | float, dark_dn_s: np.ndarray | float
) -> np.ndarray:
    """Dark-subtracted signal per second, DN/s: ``(frame - bias - dark * t) / t``."""
    return (
        (np.asarray(frame, np.float64) - bias_dn - np.asarray(dark_dn_s) * exposure_s) / exposure_s
    ).astype(np.float32)


def leakage_map(open_rate: np.ndarray, closed_rate: np.ndarray, min_rate: float) -> np.ndarray:
    """Closed-cell transmittance per pixel: closed over open signal rate.

    Parameters
    ----------
    open_rate, closed_rate : ndarray of shape (H, W)
        Dark-subtracted signal rates (DN/s) with the LCoS all open / all closed.
    min_rate : float
        Pixels whose open rate is below this (DN/s) get NaN (too dark to tell).

    Returns
    -------
    ndarray of shape (H, W), float32
    """
    ok = open_rate > min_rate
    out = np.full(open_rate.shape, np.nan, np.float32)
    out[ok] = closed_rate[ok] / open_rate[ok]
    return out


# --- the calibration ----------------------------------------------------------------------


@dataclass
class Calibration:
    """A rig calibration; any part may be missing (None) when its frames were.

    Attributes
    ----------
    sensor_size : (int, int)
        VET sensor (width, height), pixels.
    lcos_cells : (int, int)
        LCoS grid (width, height), cells.
    homography : ndarray of shape (3, 3) or None
        LCoS cell coordinates -> VET pixel coordinates.
    homography_fit : dict
        ``n_points``, ``n_inliers``, ``reprojection_rms_px``, ``decode_agreement``.
    cell_x, cell_y : ndarray of shape (H, W) or None
        Decoded cell per pixel (-1 undecoded).
    bias_dn : ndarray of shape (H, W) or None
        Dark-frame intercept, DN.
    dark_current_e_s : ndarray of shape (H, W) or None
        Dark current, electrons per second.
    leakage : ndarray of shape (H, W) or None
        Closed-cell transmittance per pixel (NaN where unmeasurable; about 1 outside
        the LCoS footprint).
    gain_ratio : ndarray of shape (H, W) or None
        Measurement-camera over VET-camera signal rate per pixel.
    summary : dict
        Scalars: ``leakage_median``, ``dark_current_median_e_s``, ``bias_median_dn``,
        ``gain_ratio_median``.
    rig : dict
        The rig parameters used (gain etc.), :meth:`RigParams.to_dict`.
    provenance : dict
        Source (rig or folder), settings, frames used, skipped parts, software.
    """

    sensor_size: tuple[int, int]
    lcos_cells: tuple[int, int]
    homography: np.ndarray | None = None
    homography_fit: dict[str, Any] = field(default_factory=dict)
    cell_x: np.ndarray | None = None
    cell_y: np.ndarray | None = None
    bias_dn: np.ndarray | None = None
    dark_current_e_s: np.ndarray | None = None
    leakage: np.ndarray | None = None
    gain_ratio: np.ndarray | None = None
    summary: dict[str, float] = field(default_factory=dict)
    rig: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    _LAYERS = ("cell_x", "cell_y", "bias_dn", "dark_current_e_s", "leakage", "gain_ratio")
    _LAYER_NAMES = {
        "cell_x": "cell_x",
        "cell_y": "cell_y",
        "bias_dn": "bias",
        "dark_current_e_s": "dark_current",
        "leakage": "leakage",
        "gain_ratio": "gain_ratio",
    }

    def to_layered(self):
        """As a :class:`~stages.formats.layered.Layered` (``kind = "calibration"``)."""
        from .formats.layered import Layered

        meta: dict[str, Any] = {
            "kind": CALIBRATION_KIND,
            "sensor_size": list(self.sensor_size),
            "lcos_cells": list(self.lcos_cells),
            "homography": None if self.homography is None else np.asarray(self.homography).tolist(),
            "homography_fit": self.homography_fit,
            "rig": self.rig,
            "provenance": self.provenance,
            "layer_units": {
                "cell_x": "cell",
                "cell_y": "cell",
                "bias": "DN",
                "dark_current": "e-/s",
                "leakage": "transmittance",
                "gain_ratio": "measurement/VET",
            },
            **self.summary,
        }
        out = Layered(meta=meta)
        for attr in self._LAYERS:
            arr = getattr(self, attr)
            if arr is not None:
                out.add(self._LAYER_NAMES[attr], arr, ["Y"])
        if not out.layers:
            raise InputError("the calibration measured nothing that can be stored")
        return out

    @classmethod
    def from_layered(cls, data, what: str = "calibration") -> Calibration:
        """From a :class:`~stages.formats.layered.Layered` read from a file."""
        meta = data.meta
        if meta.get("kind") != CALIBRATION_KIND:
            raise FormatError(
                f"{what}: not a calibration (kind: {meta.get('kind') or 'not a vet file'})"
            )
        try:
            hom = meta.get("homography")
            cal = cls(
                sensor_size=tuple(int(v) for v in meta["sensor_size"]),
                lcos_cells=tuple(int(v) for v in meta["lcos_cells"]),
                homography=None if hom is None else np.asarray(hom, dtype=np.float64).reshape(3, 3),
                homography_fit=dict(meta.get("homography_fit") or {}),
                rig=dict(meta.get("rig") or {}),
                provenance=dict(meta.get("provenance") or {}),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"{what}: calibration metadata is damaged ({exc})") from None
        for key in (
            "leakage_median",
            "dark_current_median_e_s",
            "bias_median_dn",
            "gain_ratio_median",
        ):
            if meta.get(key) is not None:
                cal.summary[key] = float(meta[key])
        for attr in cls._LAYERS:
            arr = data.layers.get(cls._LAYER_NAMES[attr])
            if arr is not None:
                setattr(cal, attr, arr[:, :, 0])
        return cal


def write_calibration(path: str | Path, cal: Calibration) -> None:
    """Write atomically (EXR or npz by extension; ``-`` is stdout)."""
    from .formats.layered import write_layered

    write_layered(path, cal.to_layered())


def read_calibration(path: str | Path) -> Calibration:
    """Read a calibration file written by :func:`write_calibration`."""
    from .formats.layered import read_layered

    what = "standard input" if str(path) == "-" else str(path)
    return Calibration.from_layered(read_layered(path), what)


def apply_calibration(params: RigParams, cal: Calibration) -> RigParams:
    """Rig parameters with the calibrated homography, leakage, dark current and gain ratio.

    Parameters
    ----------
    params : RigParams
        The rig as configured.
    cal : Calibration
        Must have been measured on a rig with the same LCoS grid and sensor size.

    Returns
    -------
    RigParams
        A copy; parts missing from the calibration keep their configured values.

    Raises
    ------
    InputError
        The calibration belongs to a different LCoS grid or sensor.
    """
    return params.replace(**calibration_changes(cal, params))


def calibration_changes(cal: Calibration, params: RigParams | None = None) -> dict[str, Any]:
    """The RigParams fields a calibration sets (checked against ``params`` if given)."""
    if params is not None:
        if tuple(params.lcos_cells) != tuple(cal.lcos_cells):
            raise InputError(
                f"calibration is for a {cal.lcos_cells[0]}x{cal.lcos_cells[1]} LCoS, the rig has "
                f"{params.lcos_cells[0]}x{params.lcos_cells[1]}"
            )
        if tuple(params.sensor_size) != tuple(cal.sensor_size):
            raise InputError(
                f"calibration is for a {cal.sensor_size[0]}x{cal.sensor_size[1]} sensor, the rig "
                f"has {params.sensor_size[0]}x{params.sensor_size[1]}"
            )
    out: dict[str, Any] = {"lcos_cells": tuple(cal.lcos_cells)}
    if cal.homography is not None:
        out["homography"] = np.asarray(cal.homography, float).tolist()
    s = cal.summary
    if s.get("leakage_median") is not None and np.isfinite(s["leakage_median"]):
        out["leakage"] = float(min(max(s["leakage_median"], 0.0), 0.999))
    if s.get("dark_current_median_e_s") is not None and np.isfinite(s["dark_current_median_e_s"]):
        out["dark_current_e_s"] = float(max(s["dark_current_median_e_s"], 0.0))
    if (
        s.get("gain_ratio_median") is not None
        and np.isfinite(s["gain_ratio_median"])
        and s["gain_ratio_median"] > 0
    ):
        out["measure_fraction"] = float(s["gain_ratio_median"])
    return out


def calibration_overrides(path: str | Path) -> dict[str, Any]:
    """RigParams overrides from a calibration file (for ``vet capture --calibration``).

    The calibration holds only for the sensor size it was measured at
    (``Calibration.sensor_size``); :func:`apply_calibration` checks that, this does not.
    """
    return calibration_changes(read_calibration(path))


# --- frames -> calibration ----------------------------------------------------------------


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
    """

    dark: dict[float, np.ndarray] = field(default_factory=dict)
    open: dict[float, np.ndarray] = field(default_factory=dict)
    closed: dict[float, np.ndarray] = field(default_factory=dict)
    gray_diffs: list[np.ndarray] | None = None
    meas_flat: dict[float, np.ndarray] = field(default_factory=dict)
    meas_dark: dict[float, np.ndarray] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def shape(self) -> tuple[int, int] | None:
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
        t_m = max(frames.meas_flat)
        if t_m in frames.meas_dark:
            meas_rate = ((frames.meas_flat[t_m] - frames.meas_dark[t_m]) / t_m).astype(np.float32)
        else:  # same sensor type: borrow the VET sensor's dark model (DESIGN.md §2)
            meas_rate = signal_rate(frames.meas_flat[t_m], t_m, bias, dark_dn_s)
        if meas_rate.shape != open_rate.shape:
            skipped.append(
                "gain ratio (measurement and VET frames differ in size; a measurement->VET "
                "homography is not implemented)"
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


# --- acquisition on a rig -----------------------------------------------------------------


@dataclass
class AcquisitionSettings:
    """How :func:`calibrate_rig` exposes (emulated rig; a real camera keeps its own exposure).

    Attributes
    ----------
    frames_per_exposure : int
        Frames averaged for each dark, open, closed and measurement exposure.
    gray_frames : int
        Frames averaged per Gray-code pattern.
    dark_exposures_s : tuple of float
        Dark-frame exposure times, seconds (two or more).
    target_fill : float
        Flat-field exposures aim the 99th-percentile pixel at this fraction of full scale.
    max_exposure_s : float
        Longest exposure (the all-closed frame asks for long ones), seconds.
    """

    frames_per_exposure: int = 4
    gray_frames: int = 1
    dark_exposures_s: tuple[float, ...] = (0.01, 2.0)
    target_fill: float = 0.5
    max_exposure_s: float = 10.0


class _RigExposer:
    """One exposure of either camera on any rig, averaged, as (H, W) float32 DN."""

    def __init__(self, rig: Any):
        self.rig = rig
        self.emulated_vet = hasattr(rig.vet, "expose_pattern")
        self.emulated_meas = hasattr(rig.measurement, "render")
        self.n_cells = rig.params.lcos_cells[0] * rig.params.lcos_cells[1]
        self._meas_k = 0
        self._stale = False

    @staticmethod
    def _mono(img: np.ndarray) -> np.ndarray:
        a = np.asarray(img, np.float32)
        return a.mean(axis=2) if a.ndim == 3 else a

    def vet_fixed_exposure_s(self) -> float:
        exp = getattr(self.rig.vet, "exposure", None)
        return float(exp) * 1e-4 if exp else self.rig.params.frame_s  # V4L2 units: 100 us

    def meas_fixed_exposure_s(self) -> float:
        exp = getattr(self.rig.measurement, "exposure", None)
        return float(exp) * 1e-4 if exp else self.rig.params.subframe_s

    def show(self, closed: np.ndarray | None) -> None:
        """Put a mask on the LCoS (None: all open) and wait for the device to apply it."""
        mask = np.zeros(self.n_cells, bool) if closed is None else np.asarray(closed, bool).ravel()
        self.rig.lcos.send_full_mask(mask, wait=True)
        self._stale = True  # a real camera's next frame may have started before the mask

    def vet(
        self, closed: np.ndarray | None, exposure_s: float, n: int, light: bool = True
    ) -> np.ndarray:
        acc = None
        for _ in range(n):
            if self.emulated_vet:
                open_cells = None if closed is None else ~np.asarray(closed, bool).ravel()
                img = self.rig.vet.expose_pattern(open_cells, exposure_s, light=light)
            else:
                if self._stale:
                    self.rig.vet.grab()
                    self._stale = False
                img = self.rig.vet.grab().data
            img = self._mono(img)
            acc = img.astype(np.float64) if acc is None else acc + img
        return (acc / n).astype(np.float32)

    def meas(self, n: int) -> np.ndarray:
        acc = None
        for _ in range(n):
            if self.emulated_meas:
                img = self.rig.measurement.render(
                    self._meas_k % max(self.rig.params.n_subframes, 1)
                )
                self._meas_k += 1
            else:
                img = self.rig.measurement.grab().data
            img = self._mono(img)
            acc = img.astype(np.float64) if acc is None else acc + img
        return (acc / n).astype(np.float32)


def acquire_frames(
    rig: Any, settings: AcquisitionSettings | None = None, progress: ProgressFn | None = None
) -> CalibrationFrames:
    """Drive a rig through the calibration sequence and collect averaged frames.

    Order: dark frames (emulated VET camera only: a real one needs its lens capped, so
    record them and use :func:`calibrate_from_folder`), all-open flat field (exposure
    found from a probe), all-closed flat field (longer exposure, capped), the Gray-code
    patterns and inverses, the measurement camera on the flat field. The LCoS is left
    all open.

    Parameters
    ----------
    rig : stages.devices.rigs.Rig
        An open rig viewing a flat, bright, still field.
    settings : AcquisitionSettings, optional
    progress : callable(done, total), optional

    Returns
    -------
    CalibrationFrames
    """
    s = settings or AcquisitionSettings()
    ex = _RigExposer(rig)
    params = rig.params
    patterns = gray_code_patterns(params.lcos_cells)
    n_gray = len(patterns)
    total = (len(s.dark_exposures_s) if ex.emulated_vet else 0) + 4 + n_gray // 2
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    frames = CalibrationFrames()
    n = s.frames_per_exposure
    full = params.max_dn
    if ex.emulated_vet:
        for t in s.dark_exposures_s:
            frames.dark[float(t)] = ex.vet(None, float(t), n, light=False)
            tick()
    else:
        log.warning(
            "calibrate: a real camera cannot take dark frames unattended; record them with the lens "
            "capped and calibrate from a folder (--frames) for dark current and bias"
        )

    ex.show(None)
    if ex.emulated_vet:
        t_probe = params.subframe_s
        probe = ex.vet(None, t_probe, 1)
        rate = max(float(np.percentile(probe, 99)), 1.0) / t_probe
        t_open = min(s.max_exposure_s, s.target_fill * full / rate)
    else:
        t_open = ex.vet_fixed_exposure_s()
    frames.open[t_open] = ex.vet(None, t_open, n)
    tick()

    ex.show(np.ones(ex.n_cells, bool))
    if ex.emulated_vet:
        probe = ex.vet(np.ones(ex.n_cells, bool), t_open, 1)
        # pixels outside the LCoS footprint stay bright: size the exposure on the dim majority
        rate_c = max(float(np.percentile(probe, 50)), 0.05) / t_open
        t_closed = float(min(s.max_exposure_s, max(t_open, s.target_fill * full / rate_c)))
    else:
        t_closed = ex.vet_fixed_exposure_s()
    frames.closed[t_closed] = ex.vet(np.ones(ex.n_cells, bool), t_closed, n)
    tick()

    diffs = []
    for k in range(0, n_gray, 2):
        imgs = []
        for pat in (patterns[k], patterns[k + 1]):
            closed = ~pat
            ex.show(closed)
            imgs.append(ex.vet(closed, t_open, s.gray_frames))
        diffs.append(imgs[0] - imgs[1])
        tick()
    frames.gray_diffs = diffs
    ex.show(None)
    tick()

    t_meas = params.subframe_s if ex.emulated_meas else ex.meas_fixed_exposure_s()
    frames.meas_flat[t_meas] = ex.meas(n)
    tick()
    sat = float(np.mean(frames.meas_flat[t_meas] >= params.saturation_dn))
    if sat > 0.01:
        log.warning(
            "calibrate: %.0f%% of the measurement camera's flat field is saturated; the gain ratio "
            "is biased low",
            100 * sat,
        )
    frames.counts = {"dark": n, "open": n, "closed": n, "gray": s.gray_frames, "meas_flat": n}
    return frames


def calibrate_rig(
    rig: Any, progress: ProgressFn | None = None, settings: AcquisitionSettings | None = None
) -> Calibration:
    """Calibrate a rig (emulated or real) that views a flat, bright, still field.

    Parameters
    ----------
    rig : stages.devices.rigs.Rig
    progress : callable(done, total), optional
    settings : AcquisitionSettings, optional

    Returns
    -------
    Calibration
    """
    t0 = time.monotonic()
    s = settings or AcquisitionSettings()
    frames = acquire_frames(rig, s, progress)
    prov = {
        "source": f"rig:{rig.name}",
        "rig_meta": dict(rig.meta),
        "exposures_s": {
            "dark": sorted(frames.dark),
            "open": sorted(frames.open),
            "closed": sorted(frames.closed),
            "meas_flat": sorted(frames.meas_flat),
        },
        "frames_averaged": frames.counts,
        "software": _software(),
    }
    cal = calibrate_frames(frames, rig.params, prov)
    cal.provenance["elapsed_s"] = round(time.monotonic() - t0, 3)
    return cal


def _software() -> str:
    try:
        from importlib.metadata import version

        return f"vet {version('vet')}"
    except Exception:  # noqa: BLE001 - an uninstalled checkout still calibrates
        return "vet (uninstalled)"


# --- recorded frames ----------------------------------------------------------------------

_NUM = r"(?P<t>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)"
_TIMED = re.compile(rf"^(?P<kind>dark|open|closed|meas_flat|meas_dark)_{_NUM}s_(?P<n>\d+)$")
_GRAY = re.compile(r"^gray_(?P<k>\d+)(?:_(?P<n>\d+))?$")


def read_frame(path: str | Path) -> np.ndarray:
    """One recorded frame as ``ndarray of shape (H, W)`` float32 DN, unprocessed.

    PNG/TIFF/PGM through ``cv2.imread(IMREAD_UNCHANGED)`` (colour averaged to one
    channel); camera raws through rawpy's ``raw_image_visible`` (the mosaic as read
    out: no demosaicing, no black-level subtraction, no white balance).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in RAW_SUFFIXES:
        import rawpy

        try:
            with rawpy.imread(str(p)) as raw:
                img = np.array(raw.raw_image_visible, dtype=np.float32)
        except (rawpy.LibRawError, OSError) as exc:
            raise FormatError(f"{p}: not a readable raw file ({exc})") from None
    else:
        import cv2

        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FormatError(f"{p}: not a readable image")
        img = np.asarray(img, dtype=np.float32)
        if img.ndim == 3:
            img = img[:, :, :3].mean(axis=2) if img.shape[2] >= 3 else img[:, :, 0]
    if img.ndim != 2 or min(img.shape) < 1:
        raise FormatError(f"{p}: frame has no pixels")
    return img


def calibrate_from_folder(
    folder: str | Path, params: RigParams | None = None, progress: ProgressFn | None = None
) -> Calibration:
    """Calibrate from recorded frames (layout in docs/calibration.md).

    File names (any of .png .tif .tiff .pgm, or camera raws .dng .nef .cr2 ...)::

        dark_<t>s_<NN>        VET camera, lens capped, exposure t seconds (two t or more)
        open_<t>s_<NN>        VET camera, flat field, LCoS all open
        closed_<t>s_<NN>      VET camera, flat field, LCoS all closed
        gray_<KK>[_<NN>]      VET camera, flat field, LCoS showing Gray pattern KK of
                              gray_code_patterns() (even KK pattern, odd KK its inverse)
        meas_flat_<t>s_<NN>   measurement camera, same flat field
        meas_dark_<t>s_<NN>   measurement camera, lens capped, same t (optional)

    e.g. ``dark_0.5s_00.tif``, ``gray_07.png``. An optional ``rig.toml`` in the folder
    with a ``[params]`` table (as in a rig file) gives the LCoS grid and the sensor's
    gain; ``params`` overrides it. Missing parts are skipped with a warning.

    Raises
    ------
    InputError
        Not a folder, no usable frame, frames of different sizes, or an incomplete set
        of Gray-code patterns with nothing else usable.
    """
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{root}: no such folder of calibration frames")
    if params is None:
        params = _folder_params(root)
    timed: dict[str, dict[float, list[Path]]] = {}
    gray: dict[int, list[Path]] = {}
    for p in sorted(root.iterdir()):
        if not p.is_file() or p.suffix.lower() not in IMAGE_SUFFIXES + RAW_SUFFIXES:
            continue
        m = _TIMED.match(p.stem)
        if m:
            timed.setdefault(m["kind"], {}).setdefault(float(m["t"]), []).append(p)
            continue
        m = _GRAY.match(p.stem)
        if m:
            gray.setdefault(int(m["k"]), []).append(p)
            continue
        log.debug("calibrate: ignoring %s (name does not follow the layout)", p.name)
    if not timed and not gray:
        raise InputError(
            f"{root}: no calibration frames (expected names like dark_0.5s_00.tif, open_0.01s_00.png, "
            "gray_00.png; see docs/calibration.md)"
        )

    n_files = sum(len(v) for g in timed.values() for v in g.values()) + sum(
        len(v) for v in gray.values()
    )
    done = 0
    shape: list[tuple[int, int]] = []

    def mean_of(paths: list[Path]) -> np.ndarray:
        nonlocal done
        acc = None
        for p in paths:
            img = read_frame(p)
            if not shape:
                shape.append(img.shape)
                from .formats.io import check_size

                check_size(img.size * 4 * 32, str(p))  # the maps we will hold at this size
            elif img.shape != shape[0]:
                raise InputError(
                    f"{p}: frame is {img.shape[1]}x{img.shape[0]}, the others are "
                    f"{shape[0][1]}x{shape[0][0]}"
                )
            acc = img.astype(np.float64) if acc is None else acc + img
            done += 1
            if progress is not None:
                progress(done, n_files)
        return (acc / len(paths)).astype(np.float32)

    frames = CalibrationFrames()
    for kind in ("dark", "open", "closed", "meas_flat", "meas_dark"):
        for t, paths in sorted(timed.get(kind, {}).items()):
            if t <= 0:
                log.warning("calibrate: ignoring %s frames with exposure %g s", kind, t)
                continue
            getattr(frames, kind)[t] = mean_of(paths)
            frames.counts[f"{kind}_{t:g}s"] = len(paths)
    if gray:
        nx, ny = gray_bit_counts(params.lcos_cells)
        needed = 2 * (nx + ny)
        missing = [k for k in range(needed) if k not in gray]
        if missing:
            log.warning(
                "calibrate: Gray-code set for %dx%d cells needs gray_00 .. gray_%02d; missing %s",
                params.lcos_cells[0],
                params.lcos_cells[1],
                needed - 1,
                ", ".join(f"{k:02d}" for k in missing[:8]) + (" ..." if len(missing) > 8 else ""),
            )
        else:
            frames.gray_diffs = [
                mean_of(gray[k]) - mean_of(gray[k + 1]) for k in range(0, needed, 2)
            ]
            frames.counts["gray"] = min(len(v) for v in gray.values())
    if frames.shape() is None:
        raise InputError(f"{root}: no usable calibration frames (see the warnings above)")
    if params.sensor_size != (shape[0][1], shape[0][0]):
        log.info(
            "calibrate: frames are %dx%d; using that as the sensor size", shape[0][1], shape[0][0]
        )
        params = params.replace(sensor_size=(shape[0][1], shape[0][0]), homography=[])
    prov = {"source": f"folder:{root}", "frames_averaged": frames.counts, "software": _software()}
    return calibrate_frames(frames, params, prov)


def _folder_params(root: Path) -> RigParams:
    toml = root / "rig.toml"
    if not toml.is_file():
        return RigParams()
    import sys

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    try:
        with open(toml, "rb") as f:
            data = tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{toml}: not valid TOML ({exc})") from None
    from .formats.schema import check_rig_params

    return RigParams.from_dict(check_rig_params(data, str(toml)))


# --- emulated rig for calibration ---------------------------------------------------------


def parse_homography(
    text: str, lcos_cells: tuple[int, int] | None = None, sensor_size: tuple[int, int] | None = None
) -> np.ndarray:
    """``"a,b,c,d,e,f,g,h,i"`` (row-major) or a JSON file holding a 3x3 list (or
    ``{"homography": [[...], ...]}``, as in a calibration's metadata) -> 3x3 array.

    ``"example"`` gives :func:`example_homography` for ``lcos_cells`` and ``sensor_size``
    (default rig sizes when not given).
    """
    import json

    if text.strip().lower() == "example":
        d = RigParams()
        try:
            return example_homography(lcos_cells or d.lcos_cells, sensor_size or d.sensor_size)
        except ValueError as exc:
            raise InputError(f"--true-homography example: {exc}") from None
    p = Path(text)
    if p.is_file():
        try:
            data = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"{p}: not a JSON homography ({exc})") from None
        if isinstance(data, dict):
            data = data.get("homography")
        values = data
    else:
        try:
            values = [float(v) for v in text.replace(";", ",").split(",")]
        except ValueError:
            raise InputError(
                f"invalid homography {text!r}: expected 9 numbers a,b,c,d,e,f,g,h,i or a JSON file"
            ) from None
    try:
        hom = np.asarray(values, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError):
        raise InputError(
            f"invalid homography {text!r}: expected 9 numbers (a 3x3 matrix)"
        ) from None
    if not np.all(np.isfinite(hom)) or abs(np.linalg.det(hom)) < 1e-12:
        raise InputError(f"invalid homography {text!r}: must be finite and invertible")
    return hom / hom[2, 2] if hom[2, 2] != 0 else hom


@contextmanager
def open_sim_calibration_rig(
    size: tuple[int, int] | None = None,
    overrides: dict[str, Any] | None = None,
    true_homography: np.ndarray | None = None,
    seed: int = 0,
    scene: str | None = None,
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

    from .devices.rigs import SimOptions, open_rig

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
        )
        rig = open_rig("sim", opts)
    try:
        yield rig
    finally:
        rig.close()


def _write_flat_exr(path: str, w: int, h: int) -> None:
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
) -> Calibration:
    """Calibrate the emulated rig and record how far the result is from its truth.

    Parameters are those of :func:`open_sim_calibration_rig`. The provenance gets
    ``emulated_truth`` (the true homography, leakage, dark current, gain ratio) and
    ``errors_vs_truth`` (:func:`compare_to_truth`).

    Returns
    -------
    Calibration
    """
    with open_sim_calibration_rig(size, overrides, true_homography, seed, scene) as rig:
        cal = calibrate_rig(rig, progress, settings)
        p = rig.params
        true_h = np.asarray(p.homography if true_homography is None else true_homography, float)
    cal.provenance["emulated_truth"] = {
        "homography": true_h.tolist(),
        "leakage": p.leakage,
        "dark_current_e_s": p.dark_current_e_s,
        "measure_fraction": p.measure_fraction,
    }
    cal.provenance["errors_vs_truth"] = compare_to_truth(
        cal, true_h, p.leakage, p.dark_current_e_s, p.measure_fraction
    )
    return cal


def run_calibration(
    rig_spec: str | None,
    frames: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    *,
    size: tuple[int, int] | None = None,
    true_homography: str | None = None,
    seed: int = 0,
    scene: str | None = None,
    settings: AcquisitionSettings | None = None,
    progress: ProgressFn | None = None,
) -> Calibration:
    """What ``vet calibrate`` does: from recorded ``frames``, the emulated rig, or a rig file.

    Parameters
    ----------
    rig_spec : str or None
        ``"sim"``, a rig TOML file, or None (only with ``frames``).
    frames : path, optional
        Folder of recorded frames (:func:`calibrate_from_folder`); a rig file's
        ``[params]`` and ``overrides`` then describe the rig.
    overrides : dict, optional
        RigParams overrides (on ``sim``: the emulated truth).
    size, true_homography, seed, scene :
        Emulated rig only: sensor (width, height); the true homography as text for
        :func:`parse_homography`; noise seed; a scene instead of the flat field.
    settings : AcquisitionSettings, optional
    progress : callable(done, total), optional

    Returns
    -------
    Calibration
    """
    overrides = dict(overrides or {})
    if frames is not None:
        params = None
        if rig_spec not in (None, "sim") or overrides:
            base: dict[str, Any] = {}
            if rig_spec not in (None, "sim"):
                from .devices.rigs import load_rig_file

                base = dict(load_rig_file(rig_spec).get("params", {}))
            params = RigParams.from_dict({**base, **overrides})
        return calibrate_from_folder(frames, params, progress=progress)
    if rig_spec is None:
        raise InputError("nothing to calibrate: give a rig or a folder of frames")
    if rig_spec == "sim":
        wh = size or RigParams().sensor_size
        cells = overrides.get("lcos_cells", RigParams().lcos_cells)
        true_h = None if true_homography is None else parse_homography(true_homography, cells, wh)
        return calibrate_sim(wh, overrides, true_h, seed, scene, progress, settings)
    from .devices.rigs import open_rig

    if overrides or true_homography or size or scene:
        log.warning(
            "calibrate: emulated-rig and rig options are ignored with a rig file "
            "(rig parameters belong in its [params])"
        )
    with open_rig(rig_spec) as rig:
        return calibrate_rig(rig, progress, settings)


def selftest(
    size: tuple[int, int] = (320, 256),
    lcos_cells: tuple[int, int] = (256, 150),
    leakage: float = 0.003,
    dark_current_e_s: float = 15.0,
    seed: int = 1,
) -> dict[str, Any]:
    """The acceptance point: calibrate the emulated rig with a known misalignment.

    Returns
    -------
    dict
        The figures of :func:`compare_to_truth` plus the measured values and timing.
    """
    true_h = example_homography(lcos_cells, size)
    t0 = time.monotonic()
    cal = calibrate_sim(
        size,
        {"lcos_cells": lcos_cells, "leakage": leakage, "dark_current_e_s": dark_current_e_s},
        true_h,
        seed,
    )
    elapsed = time.monotonic() - t0
    figures: dict[str, Any] = {
        "size": f"{size[0]}x{size[1]}",
        "lcos": f"{lcos_cells[0]}x{lcos_cells[1]}",
        **cal.provenance["errors_vs_truth"],
        "leakage_median": cal.summary.get("leakage_median"),
        "dark_current_median_e_s": cal.summary.get("dark_current_median_e_s"),
        "gain_ratio_median": cal.summary.get("gain_ratio_median"),
        **cal.homography_fit,
        "elapsed_s": round(elapsed, 2),
    }
    return figures


def _main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(
        prog="python -m stages.calibrate", description="Calibration acceptance on the emulated rig."
    )
    ap.add_argument(
        "--selftest", action="store_true", help="run the acceptance point and print its figures"
    )
    ap.add_argument(
        "--full", action="store_true", help="at the default 1280x1024 sensor / 1024x600 LCoS"
    )
    args = ap.parse_args(argv)
    if not args.selftest:
        ap.print_help()
        return 2
    logging.basicConfig(level=logging.WARNING, format="vet: %(message)s")
    kw = {"size": (1280, 1024), "lcos_cells": (1024, 600)} if args.full else {}
    print(json.dumps(selftest(**kw), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
