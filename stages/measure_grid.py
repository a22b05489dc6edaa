"""A real rig's measuring images on the VET sensor's grid, with their noise.

The measurement camera of a real rig (:class:`stages.optics.MeasureGeometry`) records on
its own pixel grid. Readers that compare its images with the VET image pixel by pixel
(hdr-static, the motion estimates, the deblur's misfit in tiles) take them onto the VET
grid here: interpolated (:func:`register_measure`), or inverted through the camera's
sampling (:func:`fit_bin`), which keeps what the interpolation smooths. The deblur's
misfit of a whole frame needs neither: it fits the bins on the camera's own grid through
its sampling (:func:`stages.deblur.problem.observations`).
"""

from __future__ import annotations

import numpy as np

from .formats.capture import Capture
from .optics import MeasureGeometry

#: Weight of the smoothness term of :func:`fit_bin`, relative to what one measuring
#: pixel of the neighbours' brightness weighs: enough to fix the frequencies the
#: sampling is blind to (half-pixel offsets), far below what a pixel's own data says.
FIT_SMOOTHNESS = 0.001


def fit_bin(
    geom: MeasureGeometry,
    bin_dn: np.ndarray,
    n_sub: int,
    start_e: np.ndarray,
    extra: tuple[np.ndarray, np.ndarray] | None = None,
    iters: int = 60,
) -> np.ndarray:
    """A measuring bin inverted onto the VET grid through the camera's sampling.

    ``bin_dn`` (Hm, Wm, C): the sum of ``n_sub`` subframes as the camera recorded them.
    Finds the VET-grid image ``x`` (electrons the ideal rig's measurement sensor would
    have collected, dark current included) minimising ``sum w (A x - y)^2`` over the
    measuring pixels (``y`` the flat-fielded bin, ``w`` its inverse Poisson-Gaussian
    variance, 0 where a subframe may have clipped; ``A``: :meth:`MeasureGeometry.operator`)
    plus ``extra`` rows ``sum w_v (x - y_v)^2`` ((H, W, C) each, e.g. the VET image's own
    pixels) plus a weak smoothness (:data:`FIT_SMOOTHNESS`), by preconditioned conjugate
    gradients from ``start_e`` (H, W, C), at most ``iters`` iterations. Returns
    (H, W, C) float64.
    """
    from .physics import bin_may_clip

    rig = geom.rig
    A = geom.operator().astype(np.float64)
    AT = A.T.tocsr()
    A2T = A.multiply(A).T.tocsr()
    h, w = geom.shape_v
    nc = bin_dn.shape[-1]
    g = rig.gain_dn_per_e
    clipped = bin_may_clip(np.asarray(bin_dn, np.float32) / np.float32(n_sub), rig).ravel()
    v = geom.vign.astype(np.float64).ravel()[:, None]
    y_m = np.asarray(bin_dn, np.float64).reshape(v.size, nc) / (g * rig.measure_gain * v)
    read = n_sub * (rig.read_noise_e**2 + 1 / (12 * g * g))
    w_m = 1.0 / (np.maximum(y_m, 0) / v + read / v**2)
    w_m[clipped] = 0.0
    start_e = np.asarray(start_e, np.float64).reshape(h, w, nc)
    out = np.empty((h, w, nc))
    for c in range(nc):
        wm = w_m[:, c]
        wv = extra[0][..., c].ravel() if extra is not None else np.zeros(h * w)
        yv = extra[1][..., c].ravel() if extra is not None else np.zeros(h * w)
        # Smoothness between neighbours in proportion to what one measuring pixel of
        # their brightness weighs (1 / variance), so it means as much in the dark.
        wp = 1.0 / (np.maximum(start_e[..., c], 0) + read)
        cx = FIT_SMOOTHNESS * np.minimum(wp[:, :-1], wp[:, 1:])
        cy = FIT_SMOOTHNESS * np.minimum(wp[:-1, :], wp[1:, :])

        def normal(x, wm=wm, wv=wv, cx=cx, cy=cy):
            return AT @ (wm * (A @ x)) + wv * x + _smoothness(x.reshape(h, w), cx, cy).ravel()

        diag = A2T @ wm + wv + _smoothness_diag(cx, cy).ravel()
        b = AT @ (wm * y_m[:, c]) + wv * yv
        out[..., c] = pcg(normal, b, diag, start_e[..., c].ravel(), iters).reshape(h, w)
    return out


def pcg(normal, b: np.ndarray, diag: np.ndarray, x: np.ndarray, iters: int) -> np.ndarray:
    """Jacobi-preconditioned conjugate gradients, relative residual 1e-7. Inner products
    as elementwise sums, not BLAS calls, whose threads fight on a busy machine."""
    x = x.copy()
    r = b - normal(x)
    z = r / diag
    p = z.copy()
    rz = float((r * z).sum())
    stop = 1e-14 * float((b * b).sum())
    for _ in range(iters):
        if float((r * r).sum()) <= stop:
            break
        q = normal(p)
        alpha = rz / float((p * q).sum())
        x += alpha * p
        r -= alpha * q
        z = r / diag
        rz, rz_old = float((r * z).sum()), rz
        p *= rz / rz_old
        p += z
    return x


def _smoothness(x: np.ndarray, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """``D^T C D x`` for forward differences weighted ``cx`` (H, W-1) and ``cy`` (H-1, W)."""
    out = np.zeros_like(x)
    dx = cx * np.diff(x, axis=1)
    dy = cy * np.diff(x, axis=0)
    out[:, :-1] -= dx
    out[:, 1:] += dx
    out[:-1, :] -= dy
    out[1:, :] += dy
    return out


def _smoothness_diag(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    d = np.zeros((cy.shape[0] + 1, cx.shape[1] + 1))
    d[:, :-1] += cx
    d[:, 1:] += cx
    d[:-1, :] += cy
    d[1:, :] += cy
    return d


def register_measure(cap: Capture, fit: bool = False, fit_iters: int = 60) -> Capture:
    """A capture whose measuring images lie on the VET grid, as the ideal rig's would.

    Each measuring image (the measurement camera's DN) is flat-fielded for the camera's
    gain and vignetting and resampled through measurement -> VET (homography and radial
    distortion, bilinear: :class:`MeasureGeometry`); ``measure_noise`` (2, H, W) carries
    the factors on the ideal rig's shot and read variances. Where a subframe may have
    clipped (any of the pixels interpolated from reached the saturation code), the
    registered pixel is set to the top code per subframe, flat-fielded (a lower bound,
    above the saturation code), so the clipped-bin test
    (:func:`stages.physics.bin_may_clip`) still finds it. A stream (int16) stays int16
    (whole DN; the rounding adds 1/12 DN^2, below the read noise). The capture itself
    when the measurement camera is the VET sensor's grid or the images are registered
    already.

    With ``fit`` each image is inverted through the camera's sampling instead
    (:func:`fit_bin`, ``fit_iters`` iterations from the interpolation; for a few time
    bins, not a stream): sharper, and each pixel's noise is then about one measuring
    pixel's (``measure_noise`` without the interpolation's averaging).
    """
    from dataclasses import replace

    from .physics import bin_may_clip

    rig = cap.rig
    if cap.measure is None or rig.ideal_geometry or cap.measure_noise is not None:
        return cap
    geom = MeasureGeometry(rig)
    n = cap.measure_counts()
    h, w = geom.shape_v
    out = np.empty((cap.measure.shape[0], h, w, cap.measure.shape[3]), cap.measure.dtype)
    top = np.float32(rig.max_dn)
    flat_v = geom.register(np.ones((*geom.shape_m, 1), np.float32))[..., 0]
    g = np.float32(rig.gain_dn_per_e)
    for b in range(cap.measure.shape[0]):
        raw = np.asarray(cap.measure[b], np.float32)
        reg = geom.register(raw)
        if fit:
            reg = (fit_bin(geom, raw, int(n[b]), reg / g, iters=fit_iters) * g).astype(np.float32)
        clipped = bin_may_clip(raw / np.float32(n[b]), rig)
        if clipped.any():
            hit = geom.register_mask(clipped)
            reg[hit] = (top * np.float32(n[b]) * flat_v[hit])[:, None]
        if out.dtype == np.int16:
            np.rint(reg, out=reg)
            np.clip(reg, -32768, 32767, out=reg)
        out[b] = reg
    noise = np.stack([geom.shot_scale, geom.read_scale])
    if fit:
        noise = noise / np.asarray(geom._to_vet.multiply(geom._to_vet).sum(axis=1)).reshape(
            1, *geom.shape_v
        )
    return replace(cap, measure=out, measure_noise=noise.astype(np.float32))
