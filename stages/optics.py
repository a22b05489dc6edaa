"""The parts of a real rig that the ideal model leaves out, one physics for everyone.

:class:`~stages.rig.RigParams` names them (every default is the ideal rig, where they
vanish and :mod:`stages.physics` alone is the model); this module computes with them, for
``simulate``, the emulated rig, ``capture`` and the reconstructions alike:

- the **measurement camera**'s own pixel grid: its pixel coordinates, undistorted by the
  radial model (k1, k2 about the image centre, radius in half-diagonals), map onto the
  VET sensor through ``measure_homography``; its gain and its vignetting
  ``(1 + a r**2) ** -2`` scale what it records (:class:`MeasureGeometry`);
- the **relay optics** blur the LCoS image on the VET sensor (a Gaussian of
  ``relay_blur_px``), and each cell leaks its own amount (:func:`leakage_map`);
- the **liquid crystal switches** in ``switch_s``: a cell applied closed at time t passes
  ``eps + (1 - eps) ramp(t' - t)`` at t' >= t, ``ramp`` falling linearly from 1 to 0
  (:func:`open_integral`), so the closing subframe is partly exposed;
- the **trigger**: measuring subframe j starts at ``trigger_offset_s + j tau`` plus a
  Gaussian jitter; the LCoS applies closures on the measurement camera's frame clock,
  and measuring subframes drop with probability ``drop_rate`` (:func:`subframe_clock`).

Coordinates are continuous with pixel (0, 0) covering ``[0, 1) x [0, 1)`` (as in
:func:`stages.rig.default_homography`); resampling puts pixel centres on integers, hence
the half-pixel shifts below.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FormatError, InputError
from .physics import CellMap, cells_near
from .rig import REAL_RIG_PARTS, RigParams

#: Named rig profiles of ``--rig-profile``.
PROFILES = ("ideal", "realistic")


def realistic_parts(sensor_size: tuple[int, int]) -> dict[str, Any]:
    """The ``realistic`` profile's parts for a VET sensor of ``sensor_size`` (W, H).

    Plausible for the published rig (two 1280x1024 machine-vision cameras behind a beam
    splitter, an LCoS from a projector): the same camera model on both arms with a small
    rotation, scale and shift between them, mild barrel distortion, a slightly lower gain
    and vignetting on the measurement arm, relay blur of about a pixel, leakage varying
    from cell to cell about its mean, milliseconds of switching, a trigger offset of a
    fraction of a millisecond with jitter, rare dropped frames; and the LCoS grid in the
    published rig's proportion to the sensor (1024 x 600 cells on 1280 x 1024 pixels: a
    cell 1.25 x 1.7 pixels at any size: a working size is that rig scaled down, not one
    whose cells are finer than its pixels). RigParams fields, as a dict (pixel quantities
    in the given sensor's pixels); the profile's LCoS homography is
    :func:`relay_homography` of the grid in force.
    """
    w, h = sensor_size
    cx, cy = w / 2.0, h / 2.0
    ang, s = math.radians(0.3), 1.004
    c, si = s * math.cos(ang), s * math.sin(ang)
    tx, ty = 2.4, -1.7
    hom = [
        [c, -si, cx + tx - (c * cx - si * cy)],
        [si, c, cy + ty - (si * cx + c * cy)],
        [0.0, 0.0, 1.0],
    ]
    return {
        "lcos_cells": (max(1, round(w * 1024 / 1280)), max(1, round(h * 600 / 1024))),
        "measure_size": (w, h),
        "measure_homography": hom,
        "measure_k1": -0.05,
        "measure_k2": 0.01,
        "measure_gain": 0.96,
        "measure_vignetting": 0.12,
        "relay_blur_px": 1.0,
        "leakage": 0.0035,
        "leakage_spread": 0.0015 / 0.0035,
        "leakage_seed": 20,
        "switch_s": 0.0025,
        "trigger_offset_s": 0.0005,
        "trigger_jitter_s": 0.00005,
        "drop_rate": 0.002,
    }


#: The fields of the parts this module models (the rest of a rig is the ideal model's).
PARTS = REAL_RIG_PARTS


def ideal_rig(rig: RigParams) -> RigParams:
    """``rig`` with every part of a real rig at its ideal value (what a reader that
    ignores the calibration assumes); the mean leakage and the rest stay."""
    defaults = RigParams(sensor_size=rig.sensor_size)
    return rig.replace(**{k: getattr(defaults, k) for k in PARTS})


def rig_profile(spec: str, sensor_size: tuple[int, int], **overrides: Any) -> RigParams:
    """The rig of ``spec`` for a VET sensor of ``sensor_size`` (W, H), with ``overrides``.

    ``spec`` is a profile name (:data:`PROFILES`) or a TOML file: an optional top-level
    ``profile = "ideal" | "realistic"`` to start from (ideal by default) and a
    ``[params]`` table of :class:`~stages.rig.RigParams` fields, checked against the
    declared schema (a rig file of :mod:`stages.devices.rigs` serves as it is). The
    sensor size is the caller's unless the file sets it. Raises :class:`InputError`
    (an unknown name) or :class:`~stages.errors.FormatError` (a bad file).
    """
    params: dict[str, Any] = {}
    base = spec
    if spec not in PROFILES:
        params, base = _profile_file(spec)
    parts = realistic_parts(sensor_size) if base == "realistic" else {}
    if "sensor_size" in params and base == "realistic":
        parts = realistic_parts(tuple(params["sensor_size"]))
    merged = {"sensor_size": tuple(sensor_size), **parts, **params, **overrides}
    if base == "realistic" and "homography" not in params and "homography" not in overrides:
        merged["homography"] = relay_homography(
            tuple(merged["lcos_cells"]), tuple(merged["sensor_size"])
        )
    try:
        return RigParams.from_dict(merged)
    except InputError as exc:
        if spec in PROFILES:
            raise
        w, h = merged["sensor_size"]
        raise FormatError(f"{spec}: [params] on a {w}x{h} sensor: {exc}") from None


#: Where the realistic profile's relay optics put the LCoS image against the ideal
#: alignment: a shift (VET px) and a rotation (degrees) about the sensor's centre.
RELAY_SHIFT_PX = (0.31, -0.17)
RELAY_ROTATION_DEG = 0.02


def relay_homography(lcos_cells: tuple[int, int], sensor_size: tuple[int, int]) -> list:
    """The realistic profile's cell -> VET pixel homography: the whole LCoS on the whole
    sensor (:func:`stages.rig.default_homography`), then shifted by
    :data:`RELAY_SHIFT_PX` and turned by :data:`RELAY_ROTATION_DEG` about the sensor's
    centre (relay optics never align cell edges exactly on pixel centres, as the ideal
    alignment does). Returns a 3x3 list."""
    from .rig import default_homography

    w, h = sensor_size
    a = math.radians(RELAY_ROTATION_DEG)
    c, s = math.cos(a), math.sin(a)
    cx, cy = w / 2.0, h / 2.0
    turn = np.array(
        [
            [c, -s, cx - c * cx + s * cy + RELAY_SHIFT_PX[0]],
            [s, c, cy - s * cx - c * cy + RELAY_SHIFT_PX[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    return (turn @ np.asarray(default_homography(lcos_cells, sensor_size), float)).tolist()


def _profile_file(path: str) -> tuple[dict[str, Any], str]:
    from .formats.limits import parse_toml
    from .formats.schema import check_rig_params

    p = Path(path)
    if not p.is_file():
        raise InputError(
            f"{path}: no such rig profile (choose {', '.join(PROFILES)} or a TOML file)"
        )
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    data = parse_toml(raw, path)
    base = data.get("profile", "ideal")
    if base not in PROFILES:
        raise FormatError(f"{path}: profile: {base!r}; allowed {', '.join(PROFILES)}")
    params = check_rig_params(data, path, whole=False) if "params" in data else {}
    return params, base


# --- the measurement camera ------------------------------------------------------------


def measure_homography(rig: RigParams) -> np.ndarray:
    """Measurement (undistorted) -> VET pixel coordinates, 3x3 float64."""
    return np.asarray(rig.measure_homography, float) if rig.measure_homography else np.eye(3)


def _centre_norm(shape: tuple[int, int]) -> tuple[float, float, float]:
    h, w = shape
    return w / 2.0, h / 2.0, math.hypot(w, h) / 2.0


def distort(
    x: np.ndarray, y: np.ndarray, shape: tuple[int, int], k1: float, k2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted -> recorded coordinates of a camera of ``shape`` (H, W)."""
    cx, cy, r0 = _centre_norm(shape)
    qx, qy = (x - cx) / r0, (y - cy) / r0
    r2 = qx * qx + qy * qy
    f = 1 + k1 * r2 + k2 * r2 * r2
    return cx + r0 * qx * f, cy + r0 * qy * f


def undistort(
    x: np.ndarray, y: np.ndarray, shape: tuple[int, int], k1: float, k2: float, iters: int = 20
) -> tuple[np.ndarray, np.ndarray]:
    """Recorded -> undistorted coordinates (fixed-point inverse of :func:`distort`; exact
    to 1e-9 px for |k| <= 0.2 within the image)."""
    cx, cy, r0 = _centre_norm(shape)
    dx, dy = (x - cx) / r0, (y - cy) / r0
    qx, qy = dx, dy
    for _ in range(iters):
        r2 = qx * qx + qy * qy
        f = 1 + k1 * r2 + k2 * r2 * r2
        qx, qy = dx / f, dy / f
    return cx + r0 * qx, cy + r0 * qy


def _apply_h(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


def measure_to_vet(rig: RigParams) -> tuple[np.ndarray, np.ndarray]:
    """VET coordinates (x, y) of every measurement pixel centre, two (Hm, Wm) float64."""
    shape = rig.measure_shape
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64) + 0.5
    ux, uy = undistort(xx, yy, shape, rig.measure_k1, rig.measure_k2)
    return _apply_h(measure_homography(rig), ux, uy)


def vet_to_measure(rig: RigParams) -> tuple[np.ndarray, np.ndarray]:
    """Measurement coordinates (u, v) of every VET pixel centre, two (H, W) float64."""
    w, h = rig.sensor_size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    ux, uy = _apply_h(np.linalg.inv(measure_homography(rig)), xx, yy)
    return distort(ux, uy, rig.measure_shape, rig.measure_k1, rig.measure_k2)


def radius2(shape: tuple[int, int]) -> np.ndarray:
    """Squared radius of each pixel centre of an (H, W) image from the image's centre, in
    half-diagonals (the vignetting's and the distortion's radius): (H, W) float64."""
    cx, cy, r0 = _centre_norm(shape)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64) + 0.5
    return ((xx - cx) ** 2 + (yy - cy) ** 2) / (r0 * r0)


def vignetting(rig: RigParams) -> np.ndarray:
    """Relative illumination of the measurement camera, (Hm, Wm) float32, 1 at the centre."""
    r2 = radius2(rig.measure_shape)
    return (1.0 / (1.0 + rig.measure_vignetting * r2) ** 2).astype(np.float32)


def bilinear_matrix(mx: np.ndarray, my: np.ndarray, src: tuple[int, int]):
    """Bilinear sampling of a (H, W) image at the points ``(mx, my)`` (pixel centres on
    integers, edges replicated) as a scipy CSR matrix (points, H W) float32: exact weights,
    where OpenCV's ``remap`` rounds them to 1/32."""
    import scipy.sparse as sp

    h, w = src
    x = np.clip(np.asarray(mx, np.float64).ravel(), 0, w - 1)
    y = np.clip(np.asarray(my, np.float64).ravel(), 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    rows = np.repeat(np.arange(x.size), 4)
    cols = np.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], axis=1).ravel()
    vals = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return sp.csr_matrix((vals.ravel().astype(np.float32), (rows, cols)), shape=(x.size, h * w))


def _apply(m, img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``m @ img`` per channel of an (h, w[, C]) image, as (*shape[, C]) float32."""
    flat = np.asarray(img, np.float32).reshape(m.shape[1], -1)
    out = np.empty((m.shape[0], flat.shape[1]), np.float32)
    for c in range(flat.shape[1]):
        out[:, c] = m @ np.ascontiguousarray(flat[:, c])
    return out.reshape(shape + img.shape[2:])


#: How far (VET px) from a pixel centre the host still thresholds an LCoS cell that no
#: pixel centre lands in (only cells narrower than a pixel can be such): the error of a
#: homography calibrated on such cells (hundredths of a pixel) with a margin.
HOST_CELL_MARGIN_PX = 0.05


class MeasureGeometry:
    """The measurement camera against the VET sensor, maps computed once.

    :meth:`render` samples a VET-grid image where each measurement pixel looks (the light
    it receives, vignetting included); :meth:`register` brings a measurement-grid image
    onto the VET grid, divided by the camera's gain and vignetting, so that it reads as
    the ideal rig's measuring image would; :attr:`shot_scale` and :attr:`read_scale`
    (H, W) scale the ideal rig's shot and read variances of a registered image (the
    vignetting and the bilinear weights' sum of squares).
    """

    def __init__(self, rig: RigParams):
        self.rig = rig
        self.shape_m = rig.measure_shape
        self.shape_v = (rig.sensor_size[1], rig.sensor_size[0])
        xv, yv = measure_to_vet(rig)
        self.xv, self.yv = xv, yv
        self._to_meas = bilinear_matrix(xv - 0.5, yv - 0.5, self.shape_v)
        um, vm = vet_to_measure(rig)
        self._to_vet = bilinear_matrix(um - 0.5, vm - 0.5, self.shape_m)
        self.vign = vignetting(rig)
        self.flat = (1.0 / (self.vign * np.float32(rig.measure_gain))).astype(np.float32)
        v_reg = _apply(self._to_vet, self.vign, self.shape_v)
        s = np.asarray(self._to_vet.multiply(self._to_vet).sum(axis=1)).reshape(self.shape_v)
        self.shot_scale = (s / v_reg).astype(np.float32)
        self.read_scale = (s / (v_reg * v_reg)).astype(np.float32)

    def render(self, vet_img: np.ndarray) -> np.ndarray:
        """Light of a VET-grid (H, W, C) image as each measurement pixel receives it,
        vignetting included: (Hm, Wm, C) float32."""
        out = _apply(self._to_meas, vet_img, self.shape_m)
        out *= self.vign.reshape(self.shape_m + (1,) * (out.ndim - 2))
        return out

    def expose(self, light_e: np.ndarray, dark_e: float, rng: np.random.Generator) -> np.ndarray:
        """One measuring subframe in DN on the measurement grid, (Hm, Wm, C) float32, from
        the light (e-, dark current apart) the ideal rig's measurement sensor would
        receive on the VET grid: :meth:`render`, dark current, the sensor chain at the
        camera's gain."""
        from .physics import expose

        lam = self.render(light_e)
        lam += np.float32(dark_e)
        return expose(lam, self.rig, rng, gain=self.rig.measure_gain)

    def register(self, meas_img: np.ndarray) -> np.ndarray:
        """A measurement-grid (Hm, Wm, C) image in DN onto the VET grid, in the DN the
        ideal rig's measurement sensor would record: (H, W, C) float32."""
        flat = self.flat.reshape(self.shape_m + (1,) * (meas_img.ndim - 2))
        return _apply(self._to_vet, np.asarray(meas_img, np.float32) * flat, self.shape_v)

    def register_mask(self, mask: np.ndarray) -> np.ndarray:
        """A measurement-grid (Hm, Wm) boolean onto the VET grid: True where any of the
        pixels a VET pixel's value is interpolated from is True."""
        return _apply(self._to_vet, mask.astype(np.float32), self.shape_v) > 0

    def operator(self):
        """The measurement camera as a sparse matrix on the VET grid: row ``u`` (a
        measurement pixel, row-major) holds the bilinear weights of the VET pixels its
        centre lands among (edges replicated), the sampling :meth:`render` does, so that
        ``render(img) == vign * (A @ img)`` per channel. scipy CSR (Hm Wm, H W) float32."""
        return self._to_meas

    def host_cells(self, cellmap_vet: CellMap) -> tuple[CellMap, np.ndarray, np.ndarray]:
        """How the host thresholds the LCoS cells on the measuring pixels that image them.

        Returns the measurement grid's :class:`CellMap` (each pixel governs the cell its
        centre lands in, through measurement -> VET -> LCoS), and, for the cells smaller
        than a pixel that no pixel centre lands in, a CSR list pixel -> extra cells
        (``starts`` of length ``Hm Wm + 1``, ``cells``): the pixel that images the cell's
        centre governs it too. Listed are the cells within :data:`HOST_CELL_MARGIN_PX` of
        a VET pixel centre of ``cellmap_vet``'s grid (sampled at that spacing), not only
        those a centre lands in through the host's homography: a homography off by a
        hundredth of a pixel puts some pixel centres in a neighbouring cell, which must
        close with its pixel too.
        """
        rig = self.rig
        hom = np.asarray(rig.homography, float)
        cm = CellMap(hom, rig.lcos_cells, self.shape_m, points=(self.xv, self.yv))
        h, w = cellmap_vet.pixel_cell.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w] + 0.5
        near = np.zeros(cm.n_cells + 1, bool)  # (the last: outside the LCoS)
        near[cells_near(hom, rig.lcos_cells, xx, yy, HOST_CELL_MARGIN_PX).ravel()] = True
        owned = np.zeros(cm.n_cells + 1, bool)
        owned[cm.pixel_cell.ravel()] = True
        orphans = np.flatnonzero(near[:-1] & ~owned[:-1])
        cw = rig.lcos_cells[0]
        centres = np.stack([orphans % cw + 0.5, orphans // cw + 0.5, np.ones(orphans.size)])
        hv = hom @ centres
        vx, vy = hv[0] / hv[2], hv[1] / hv[2]
        ux, uy = _apply_h(np.linalg.inv(measure_homography(rig)), vx, vy)
        dx, dy = distort(ux, uy, self.shape_m, rig.measure_k1, rig.measure_k2)
        hm, wm = self.shape_m
        px = np.clip(np.floor(dx).astype(np.int64), 0, wm - 1)
        py = np.clip(np.floor(dy).astype(np.int64), 0, hm - 1)
        pix = py * wm + px
        order = np.argsort(pix, kind="stable")
        starts = np.searchsorted(pix[order], np.arange(hm * wm + 1)).astype(np.int64)
        return cm, starts, orphans[order].astype(np.int64)


# --- the LCoS on the VET sensor ---------------------------------------------------------


@functools.lru_cache(maxsize=4)
def _leakage_map(mean: float, spread: float, seed: int, cells: tuple[int, int]) -> np.ndarray:
    cw, ch = cells
    u = np.random.default_rng(seed).uniform(-1.0, 1.0, (ch, cw))
    out = (mean * (1.0 + spread * u)).astype(np.float32)
    out.flags.writeable = False
    return out


def leakage_map(rig: RigParams) -> np.ndarray:
    """Per-cell leakage, (cells_h, cells_w) float32: uniform in ``leakage * [1 - s, 1 + s]``
    from ``leakage_seed`` (every cell ``leakage`` when ``leakage_spread`` is 0)."""
    return _leakage_map(
        float(rig.leakage), float(rig.leakage_spread), int(rig.leakage_seed), rig.lcos_cells
    )


def pixel_leakage(rig: RigParams, cellmap: CellMap) -> np.ndarray:
    """Leakage of the cell each pixel of ``cellmap`` sees, (H, W) float32 (the mean
    leakage outside the LCoS footprint, where no cell ever closes)."""
    per_cell = np.append(leakage_map(rig).ravel(), np.float32(rig.leakage))
    return cellmap.to_pixels(per_cell)


def capture_leakage(
    rig: RigParams, shape: tuple[int, int], cell_leakage: np.ndarray | None = None
) -> np.ndarray:
    """Leakage of the cell each VET pixel of a capture sees, (H, W) float64: the
    calibrated layer it carries (``Capture.cell_leakage``) where it has one, else the
    rig's configured per-cell pattern (:func:`pixel_leakage`)."""
    if cell_leakage is not None:
        return np.asarray(cell_leakage, np.float64)
    return pixel_leakage(rig, CellMap.for_rig(rig, shape)).astype(np.float64)


def relay_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """The relay optics' Gaussian blur of a VET-grid (H, W) image (mirrored edges);
    the image itself (float32) when ``sigma_px`` is 0."""
    img = np.asarray(img, np.float32)
    if sigma_px <= 0:
        return img
    import cv2

    return cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def open_integral(u: np.ndarray, switch_s: float) -> np.ndarray:
    """``O(u)``: the open-equivalent time of a cell applied closed at 0, integrated from 0
    to ``u`` (seconds): ``u`` for ``u <= 0`` (open), ``u - u**2 / (2 s)`` while switching,
    ``s / 2`` after. The open fraction of ``[a, b]`` for a closure at t is
    ``(O(b - t) - O(a - t)) / (b - a)``."""
    u = np.asarray(u, np.float64)
    if switch_s <= 0:
        return np.minimum(u, 0.0)
    v = np.clip(u, 0.0, switch_s)
    return np.minimum(u, 0.0) + v - v * v / (2.0 * switch_s)


def close_times(close_subframe: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """When each cell was actually applied closed (s; inf where never: a negative index or
    int32 max): the start of its closing subframe on the trigger clock ``starts``
    (:func:`subframe_clock`), float64 like ``close_subframe``'s shape."""
    c = np.asarray(close_subframe)
    never = (c < 0) | (c >= np.iinfo(np.int32).max)
    idx = np.clip(c, 0, len(starts) - 1)
    return np.where(never, np.inf, starts[idx])


def slot_transmittance(
    t_close: np.ndarray, a: float, b: float, eps: np.ndarray, rig: RigParams
) -> np.ndarray:
    """Mean transmittance over ``[a, b]`` of pixels whose cell was applied closed at
    ``t_close`` (s, inf: open), before the relay blur: (H, W) float32."""
    closed = np.isfinite(t_close)
    frac = np.ones(t_close.shape, np.float64)
    tc = t_close[closed]
    frac[closed] = (open_integral(b - tc, rig.switch_s) - open_integral(a - tc, rig.switch_s)) / (
        b - a
    )
    return (eps + (1.0 - eps) * frac).astype(np.float32)


def vet_exposure(
    T: np.ndarray, eps: np.ndarray | float, window_s: float, rig: RigParams
) -> np.ndarray:
    """Light-weighted exposure (s) of each VET pixel of a still scene, (H, W) float32:
    ``blur(eps W + (1 - eps) (T + O(W - T)))`` for closures applied at ``T`` (the capture's
    T; ``W`` where never), the switching ramp :func:`open_integral` and the relay blur
    (the jitter, unknown to any reader, averages out)."""
    t = np.asarray(T, np.float64)
    open_s = np.where(t >= window_s, window_s, t + open_integral(window_s - t, rig.switch_s))
    e = eps * window_s + (1.0 - eps) * open_s
    return relay_blur(e.astype(np.float32), rig.relay_blur_px)


# --- the trigger ---------------------------------------------------------------------


def timing_rng(seed: int) -> np.random.Generator:
    """The stream of a capture's trigger jitter and dropped frames (apart from the noise
    streams of :func:`stages.physics.noise_streams`, so the ideal rig's draws stay)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), 0x716]))


def subframe_clock(
    rig: RigParams, rng: np.random.Generator, subframes: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Actual start times (s, after the VET exposure's start) of measuring subframes
    ``0 .. K + latency + 1`` (offset plus jitter: the LCoS applies a closure at the start
    of a subframe), and which of the K subframes are dropped, bool (K,). ``K`` is the
    frame's ``n_subframes``, or ``subframes`` for a clock run that long without a break."""
    k = rig.n_subframes if subframes is None else int(subframes)
    n = k + rig.latency_subframes + 2
    starts = rig.trigger_offset_s + np.arange(n) * rig.subframe_s
    if rig.trigger_jitter_s > 0:
        starts = starts + rng.normal(0.0, rig.trigger_jitter_s, n)
    dropped = rng.random(k) < rig.drop_rate if rig.drop_rate > 0 else np.zeros(k, bool)
    return starts, dropped


#: Stream (added to the seed) of the emulated measurement camera's free-running clock.
FREE_RUN_STREAM = 0x7C1


def free_running_clock(
    rig: RigParams, subframes: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """The emulated measurement camera's trigger clock run without a break for
    ``subframes`` subframes (:func:`subframe_clock`: the rig's offset, jitter and drops,
    seeded by ``seed`` on its own stream): start times (subframes,) float64 s and which
    subframes drop, (subframes,) bool."""
    starts, dropped = subframe_clock(rig, timing_rng(seed + FREE_RUN_STREAM), subframes)
    return starts[:subframes], dropped
