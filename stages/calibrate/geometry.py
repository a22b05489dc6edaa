"""The LCoS cell -> VET pixel homography: fitting, comparing, example and parsed ones.

Every decoded pixel gives one correspondence (pixel centre, cell centre); the cell index
is the quantised quantity, so :func:`fit_homography` fits pixel -> cell (errors in the
fitted variable), RANSAC on a sample, then least squares on all inliers, and inverts.

References
----------
.. [1] Hartley, R., Zisserman, A. (2004). Multiple View Geometry, 2nd ed., ch. 4
   (homography estimation, RANSAC).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..rig import RigParams


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
        RANSAC inlier threshold, in cells (cell quantisation alone reaches half a cell's
        diagonal, ``sqrt(2) / 2``).
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
