"""The whole measuring stream as one observation of the scene at t = 0.

A capture that keeps every measuring subframe ``m_k`` (DN, the measurement sensor's
light fraction ``a`` of the VET sensor's) observes the scene at t = 0, ``L0``
(electrons/s at the VET sensor), once per subframe: with the motion's displacement
``D(y, t)`` (the scene point ``y`` of t = 0 is at ``y + D(y, t)`` at time ``t``), each
subframe pulled back along the motion (``m_k(y + D(y, t_k))``, bilinear) is ``a dt_k
L0(y)`` plus its noise, where the point is visible (in the frame, not covered by a
layer in front, not clipped). Their noise-weighted mean is the maximum-likelihood
estimate of ``L0`` from the stream (:func:`stream_term`), with a variance that carries
each subframe's own read noise; a second pass drops the samples more than
:data:`REJECT_SIGMA` standard deviations from the first mean (what the motion model
does not explain). Over the subframes the sufficient statistic of ``L0`` under the model
is this mean, so fitting it loses nothing the model can use, at the cost of one image
instead of K.

Bilinear twice. The rig's image of the moving scene is ``L0`` sampled bilinearly at
``x - D`` (the model of :mod:`stages.deblur.operator`), and pulling it back samples
bilinearly again, so the aligned mean sees ``L0`` through a small blur: per subframe
with fractional displacement ``f`` (per axis), the kernel ``[f(1-f), 1 - 2f(1-f),
f(1-f)]``, averaged over the subframes that reached the pixel. :class:`StreamTerm`
keeps that 3 x 3 kernel per pixel as the term's operator (exact adjoint by
construction, checked by the dot-product test), so the deblur deconvolves it instead of
inheriting it.

References
----------
S. Uda, F. Sakaue, J. Sato, "Variable exposure time imaging for obtaining unblurred HDR
images", IPSJ Trans. Computer Vision and Applications 8, 2016 (Eq. 8: the motion any
function of time).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..physics import brightest_channel
from ..rig import RigParams

#: Second-pass rejection: samples further than this many standard deviations (of one
#: subframe's noise about the first-pass mean) are not the model's scene point.
REJECT_SIGMA = 4.0

#: The 3 x 3 kernel's offsets (dy, dx), row-major.
OFFSETS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]


@dataclass
class StreamTerm:
    """The stream's estimate of ``L0`` and the blur through which it sees it.

    Attributes
    ----------
    shape : (H, W, C)
    y : ndarray of shape (H W, C), float32
        Aligned noise-weighted mean of the subframes, electrons/s at the VET sensor.
    w : ndarray of shape (H W, C), float32
        Its inverse variance, (electrons/s)^-2; 0 where no subframe saw the point.
    kernel : ndarray of shape (9, H, W), float32, or None
        Per-pixel 3 x 3 kernel (offsets :data:`OFFSETS`): ``y ~ K L0``; None: identity.
    """

    shape: tuple[int, int, int]
    y: np.ndarray
    w: np.ndarray
    kernel: np.ndarray | None = None

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``K x`` for ``x`` of shape (H W, C) (edge pixels replicate), float64."""
        h, wd, c = self.shape
        if self.kernel is None:
            return np.asarray(x, np.float64)
        img = np.asarray(x, np.float64).reshape(h, wd, c)
        p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
        out = np.zeros((h, wd, c))
        for j, (dy, dx) in enumerate(OFFSETS):
            out += self.kernel[j][..., None] * p[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + wd]
        return out.reshape(h * wd, c)

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """``K^T r`` for ``r`` of shape (H W, C), float64."""
        h, wd, c = self.shape
        if self.kernel is None:
            return np.asarray(r, np.float64)
        img = np.asarray(r, np.float64).reshape(h, wd, c)
        p = np.zeros((h + 2, wd + 2, c))
        for j, (dy, dx) in enumerate(OFFSETS):
            p[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + wd] += self.kernel[j][..., None] * img
        # Adjoint of the edge padding: the pad rows/columns fold onto the edge.
        p[1] += p[0]
        p[-2] += p[-1]
        p[:, 1] += p[:, 0]
        p[:, -2] += p[:, -1]
        return p[1:-1, 1:-1].reshape(h * wd, c)

    def diag_normal(self, w: np.ndarray) -> np.ndarray:
        """Diagonal of ``K^T diag(w) K`` (``w`` of shape (H W, C)), float64."""
        if self.kernel is None:
            return np.asarray(w, np.float64)
        # Taps that the edge replication sends to the same column add before squaring.
        eff = self.kernel.astype(np.float64).copy()
        for axis in (1, 0):  # all the column merges first, then the rows'
            for j, (dy, dx) in enumerate(OFFSETS):
                d = dx if axis == 1 else dy
                if d == 0:
                    continue
                edge = 0 if d < 0 else -1
                to = OFFSETS.index((dy, 0) if axis == 1 else (0, dx))
                sl = (slice(None), edge) if axis == 1 else (edge, slice(None))
                eff[to][sl] += eff[j][sl]
                eff[j][sl] = 0.0
        sq = StreamTerm(self.shape, self.y, self.w, np.square(eff))
        return sq.adjoint(w)

    def moving(self) -> np.ndarray:
        """Pixels whose row is not the identity (their kernel spreads), bool (H W,)."""
        h, wd, _c = self.shape
        if self.kernel is None:
            return np.zeros(h * wd, bool)
        centre = self.kernel[OFFSETS.index((0, 0))]
        return (np.abs(centre - 1.0) > 1e-6).reshape(-1)

    def reached(self, rows: np.ndarray) -> np.ndarray:
        """Columns that the rows ``rows`` (bool (H W,)) touch, bool (H W,)."""
        h, wd, c = self.shape
        if self.kernel is None:
            return rows.copy()
        ones = np.broadcast_to(rows.reshape(-1, 1).astype(np.float64), (h * wd, 1))
        saved = self.shape
        self.shape = (h, wd, 1)
        try:
            out = self.adjoint(ones).reshape(-1) != 0
        finally:
            self.shape = saved
        return out

    def coarsen(self) -> StreamTerm:
        """The term on 2 x 2 blocks (block means; identity kernel at the coarse level)."""

        def block_sum(a: np.ndarray) -> np.ndarray:
            return (
                a[: 2 * h2 : 2, : 2 * w2 : 2]
                + a[1 : 2 * h2 : 2, : 2 * w2 : 2]
                + a[: 2 * h2 : 2, 1 : 2 * w2 : 2]
                + a[1 : 2 * h2 : 2, 1 : 2 * w2 : 2]
            )

        h, wd, c = self.shape
        h2, w2 = h // 2, wd // 2
        y = block_sum(self.y.reshape(h, wd, c).astype(np.float64)) / 4.0
        with np.errstate(divide="ignore"):
            var = np.where(self.w > 0, 1.0 / np.where(self.w > 0, self.w, 1.0), np.inf)
        s = block_sum(var.reshape(h, wd, c)) / 16.0
        w = np.where(np.isfinite(s), 1.0 / s, 0.0)
        return StreamTerm(
            (h2, w2, c),
            y.reshape(h2 * w2, c).astype(np.float32),
            w.reshape(h2 * w2, c).astype(np.float32),
        )


def _kernel_1d(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Side and centre weights of bilinear-twice at fractional shift ``f``."""
    side = f * (1.0 - f)
    return side, 1.0 - 2.0 * side


def stream_term(
    measure: np.ndarray,
    times: np.ndarray,
    rig: RigParams,
    displacement: Callable[[float], np.ndarray],
    visible: Callable[[float, np.ndarray], np.ndarray] | None = None,
) -> StreamTerm:
    """Align and merge the measuring subframes into :class:`StreamTerm`.

    Parameters
    ----------
    measure : ndarray of shape (K, H, W, C)
        Measuring images, DN (black level subtracted), any numeric type; each may be the
        sum of several subframes (``times`` says how long it is).
    times : ndarray of shape (K, 2)
        ``[start, end)`` of each, seconds.
    rig : RigParams
    displacement : callable
        ``displacement(t) -> (H, W, 2)`` float32: where the scene point of each pixel of
        the t = 0 grid is at time ``t``, as ``(dx, dy)`` pixels from it.
    visible : callable, optional
        ``visible(t, D) -> (H, W) bool``: whether the point is seen at time ``t`` (not
        covered by another layer); default everywhere.

    Returns
    -------
    StreamTerm
    """
    import cv2

    k_n, h, w, c = measure.shape
    g = float(rig.gain_dn_per_e)
    a = float(rig.measure_fraction)
    dark = float(rig.dark_current_e_s)
    rn2 = float(rig.read_noise_e) ** 2 + 1.0 / (12.0 * g * g)
    sat = np.float32(rig.saturation_dn)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    dur = np.diff(np.asarray(times, np.float64), axis=1)[:, 0]
    n_sub = np.maximum(np.rint(dur / rig.subframe_s), 1.0)
    mid = np.asarray(times, np.float64).mean(axis=1)

    def sample(k: int):
        """Subframe ``k`` pulled back to the t = 0 grid: electrons, usable mask, D."""
        d = displacement(float(mid[k]))
        mx = xx + d[..., 0]
        my = yy + d[..., 1]
        frame = np.ascontiguousarray(measure[k], np.float32)
        pulled = cv2.remap(frame, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        pulled = pulled.reshape(h, w, c)
        clipped = (brightest_channel(frame) >= sat / n_sub[k]).astype(np.float32)
        ok = cv2.remap(clipped, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT) == 0
        ok &= (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        if visible is not None:
            ok &= visible(float(mid[k]), d)
        e = pulled / np.float32(g) - np.float32(dark * dur[k])
        return e, ok, d

    # Pass 1: the plain mean of what each point's subframes saw.
    acc_e = np.zeros((h, w, c), np.float64)
    acc_t = np.zeros((h, w, 1), np.float64)
    for k in range(k_n):
        e, ok, _d = sample(k)
        acc_e += np.where(ok[..., None], e, 0.0)
        acc_t += ok[..., None] * (a * dur[k])
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = np.where(acc_t > 0, acc_e / np.where(acc_t > 0, acc_t, 1.0), 0.0)
    mu = np.maximum(mu, 0.0)
    # Pass 2: drop the samples the first mean does not explain; the kernel of the rest.
    acc_e[...] = 0.0
    acc_t = np.zeros((h, w, c), np.float64)
    acc_v = np.zeros((h, w, c), np.float64)
    kern = np.zeros((9, h, w), np.float64)
    kern_t = np.zeros((h, w), np.float64)
    for k in range(k_n):
        e, ok, d = sample(k)
        expect = a * dur[k] * mu
        var = expect + dark * dur[k] + n_sub[k] * rn2
        use = ok[..., None] & (np.abs(e - expect) <= REJECT_SIGMA * np.sqrt(var))
        acc_e += np.where(use, e, 0.0)
        acc_t += use * (a * dur[k])
        acc_v += use * var
        # Kernel weights by the share of the channel-mean exposure the sample carries.
        wk = use.mean(axis=2) * (a * dur[k])
        if np.any(wk):
            fx = np.round(d[..., 0] * 32.0) / 32.0
            fy = np.round(d[..., 1] * 32.0) / 32.0
            sx, cx = _kernel_1d(fx - np.floor(fx))
            sy, cy = _kernel_1d(fy - np.floor(fy))
            kx = {-1: sx, 0: cx, 1: sx}
            ky = {-1: sy, 0: cy, 1: sy}
            for j, (oy, ox) in enumerate(OFFSETS):
                kern[j] += wk * ky[oy] * kx[ox]
            kern_t += wk
    with np.errstate(divide="ignore", invalid="ignore"):
        y = np.where(acc_t > 0, acc_e / np.where(acc_t > 0, acc_t, 1.0), 0.0)
        wt = np.where(acc_v > 0, acc_t * acc_t / np.where(acc_v > 0, acc_v, 1.0), 0.0)
        kernel = np.where(kern_t > 0, kern / np.where(kern_t > 0, kern_t, 1.0), 0.0)
    kernel[OFFSETS.index((0, 0))][kern_t <= 0] = 1.0
    return StreamTerm(
        (h, w, c),
        y.reshape(h * w, c).astype(np.float32),
        wt.reshape(h * w, c).astype(np.float32),
        kernel.astype(np.float32),
    )


def layer_motion(layers, velocity: np.ndarray | None = None):
    """``(displacement, visible)`` callables for :func:`stream_term` from a motion.

    ``layers`` is a :class:`stages.deblur.operator.Layers` (each layer moves rigidly,
    front layers occlude the ones behind; see that module) or None, in which case the
    dense ``velocity`` (H, W, 2) px/s moves each point by ``u t`` and nothing occludes.
    """
    if layers is None:
        vel = np.asarray(velocity, np.float32)
        return (lambda t: vel * np.float32(t)), None
    h, w = layers.label.shape
    label = layers.label

    def disp_of(t: float) -> np.ndarray:
        return np.asarray(layers.displacement(t), np.float32)  # (K, 2)

    def displacement(t: float) -> np.ndarray:
        return disp_of(t)[label]

    def visible(t: float, d: np.ndarray) -> np.ndarray:
        if not layers.front:
            return np.ones((h, w), bool)
        dk = disp_of(t)
        # Which layer each image pixel shows at t: the front-most one covering it.
        iy, ix = np.mgrid[0:h, 0:w]
        seen = np.full((h, w), layers.background, np.int32)
        done = np.zeros((h, w), bool)
        for k in layers.front:
            sx = np.floor(ix - dk[k, 0] + 0.5).astype(np.int64)
            sy = np.floor(iy - dk[k, 1] + 0.5).astype(np.int64)
            inside = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
            hit = ~done & inside & (label[np.clip(sy, 0, h - 1), np.clip(sx, 0, w - 1)] == k)
            seen[hit] = k
            done |= hit
        px = np.clip(np.floor(ix + d[..., 0] + 0.5).astype(np.int64), 0, w - 1)
        py = np.clip(np.floor(iy + d[..., 1] + 0.5).astype(np.int64), 0, h - 1)
        return seen[py, px] == label

    return displacement, visible
