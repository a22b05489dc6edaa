"""Gauss-Newton steps on a measured camera path: the knots of one layer's trajectory.

A camera shake moves the whole image along a path ``D(t)`` (px), measured from the
stream by :mod:`stages.deblur.layers.paths` as displacements ``D_k`` at knot times
``tau_k``, linear in between (``D(t) = sum_k phi_k(t) D_k``, hat functions). Registered
group by group, each knot carries the noise of a few subframes; the deblur's misfit,
which all the data enter, refines them: the model of a pixel ``x`` is
``sum_s w_s(x) L(x - D(t_s))`` over samples ``s`` of its exposure windows, whose
derivative in ``D_k`` is ``-sum_s w_s(x) phi_k(t_s) grad L(x - D(t_s))``. The normal
equations in the ``2 K`` knot coordinates (``D`` at t = 0 stays 0: the image is the
scene at t = 0) are summed over the VET image's pixels (on a subsampled grid for large
frames) and over each measuring bin's, whose samples touch only the knots about the
bin. The step is a plain (damped) Gauss-Newton step: the knots' many parameters,
each fitted from a short stretch of the data, do not take the affine motion's scaled
steps (:func:`stages.deblur.motion_steps.scaled_step`), which overshoot here.

**The anchor.** The image is the scene at t = 0, so ``D(0) = 0``; but moving every later
knot by ``c`` and the image by ``c`` changes only the model of the samples before the
first knot after 0, so the alternation of image and path steps leaves such an offset
where the path's first estimate put it (the registration's extrapolation to t = 0, a
few hundredths of a pixel to a tenth). The step therefore frees ``D(0)`` too, fitted to
the early samples with the image held under a prior of :data:`ANCHOR_PX` (the early
samples may be few: a long first bin), and moves the path and the image back by what
it found (:func:`anchor_image`): the same model, now with ``D(0) = 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .operator import Layers

#: At most this many pixels (times channels) enter the VET image's normal equations;
#: larger frames are subsampled on a regular grid.
MAX_ROWS = 400_000

#: Samples per knot interval along the frame.
SAMPLES_PER_KNOT = 2

#: Tikhonov weight on the knots' second differences, relative to the normal matrix's
#: mean diagonal (a path is smooth on the scale of its knots).
SMOOTH_REL = 1e-3


#: How far (px) the registered path's anchor ``D(0)`` may be from the truth, a priori:
#: the spread of the start's extrapolation (module docstring, "The anchor"), which the
#: path steps move by up to a few tenths of a pixel in all; tighter, the prior holds the
#: anchor where the extrapolation put it against what the early samples say.
ANCHOR_PX = 0.2


#: Each rejected path step halves the next one's length (:class:`PathSearch`).
REJECT_SHRINK = 0.5


def robust_misfit(
    r: np.ndarray, w: np.ndarray, rb: np.ndarray | None, wb: np.ndarray | None, k: float
) -> float:
    """The Cauchy misfit ``sum k^2 log(1 + w r^2 / k^2)`` of the VET image's residuals
    ``r`` (weights ``w``) and the bins' ``rb`` (``wb``), whose reweighted least squares
    the image steps solve: the objective by which :class:`PathSearch` compares paths."""
    k2 = float(k) * float(k)

    def part(res: np.ndarray, wt: np.ndarray) -> float:
        z = np.square(res, dtype=np.float64)
        z *= wt
        z /= k2
        return k2 * float(np.log1p(z).sum())

    return part(r, w) + (part(rb, wb) if rb is not None else 0.0)


class PathSearch:
    """The alternation of image and path steps as a descent on :func:`robust_misfit`.

    A Gauss-Newton step on the knots holds the image; the image step after it may fit
    the data worse than before (the step overshoots what the image then absorbs). Each
    state after an image step is kept when its misfit is the lowest so far; otherwise
    the search returns to the best state and the next path step from there is shorter
    (:data:`REJECT_SHRINK`). The deblur's result is then never a state that fits the
    data worse than an earlier one.
    """

    def __init__(self) -> None:
        self.best: tuple | None = None
        self.gain = 1.0

    def keep_best(self, misfit: float, L: np.ndarray, layers: Layers, r, rb):
        """``(L, layers, r, rb)`` of the best state, this one if it is (then True)."""
        if self.best is None or misfit <= self.best[0]:
            self.best = (misfit, L, layers, r, rb)
            return L, layers, r, rb, True
        self.gain *= REJECT_SHRINK
        return (*self.best[1:], False)


def single_path(layers: Layers | None) -> bool:
    """Whether ``layers`` is one layer moving along a trajectory (a camera shake)."""
    return (
        layers is not None and layers.trajectory is not None and len(np.unique(layers.label)) == 1
    )


def _hats(t: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Hat-function weights ``phi_k(t)`` (S, K) of linear interpolation, held at the ends."""
    k = len(knots)
    out = np.zeros((len(t), k))
    eye = np.eye(k)
    for j in range(k):
        out[:, j] = np.interp(t, knots, eye[j])
    return out


def _weight_at(windows: list, t: float, shape: tuple[int, int]) -> np.ndarray:
    """Light weight of each pixel at time ``t`` over its exposure windows (H, W)."""
    w = np.zeros(shape)
    for win in windows:
        inside = (np.asarray(win.start) <= t) & (t < np.asarray(win.end))
        w = w + np.where(inside, win.weight, 0.0)
    return w


def _warped_gradients(L: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``grad L(x - d)`` (each (H, W, C)), border reflected as the background layer."""
    import cv2

    gy, gx = np.gradient(L, axis=(0, 1))
    h, w, c = L.shape
    m = np.float32([[1, 0, -d[0]], [0, 1, -d[1]]])  # dst(x) = src(x - d)

    def warp(img: np.ndarray) -> np.ndarray:
        out = cv2.warpAffine(
            img.astype(np.float32),
            m,
            (w, h),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REFLECT,
        )
        return out.reshape(h, w, c)

    return warp(gx), warp(gy)


def path_step(
    obs: Any,
    L: np.ndarray,
    layers: Layers,
    r: np.ndarray,
    w: np.ndarray,
    rb: np.ndarray | None,
    wb: np.ndarray | None,
    frame_s: float,
    gain: float = 1.0,
) -> tuple[Layers, np.ndarray]:
    """One Gauss-Newton step on the knots of a single layer's trajectory, ``D(0)`` included,
    times ``gain`` (a shortened step: :class:`PathSearch`).

    ``L`` (H W, C) electrons/s, ``r``/``w`` the VET residual and weights (H W, C), ``rb``/
    ``wb`` the bins' (B H W, C) or None. Returns new :class:`Layers` with the refined
    trajectory, moved so that ``D(0) = 0``, and what it was moved by (2,) px: the image
    moves by as much (:func:`anchor_image`) for the model to stay the same.
    """
    from .motion_steps import scaled_step

    h, wd, c = obs.shape
    img = L.reshape(h, wd, c)
    knots, disp = layers.trajectory
    knots = np.asarray(knots, np.float64)
    path = np.asarray(disp, np.float64)[0]  # (K, 2)
    k = len(knots)
    free = np.ones(k, bool)  # D(0) too: the anchor (module docstring)
    stride = max(1, int(np.ceil(np.sqrt(h * wd * c / MAX_ROWS))))
    sub = (slice(None, None, stride), slice(None, None, stride))
    normal = np.zeros((2 * k, 2 * k))
    grad = np.zeros(2 * k)

    def add(samples: np.ndarray, weights: list[np.ndarray], res: np.ndarray, wt: np.ndarray):
        """Accumulate one image's normal equations from its samples (times, (H, W) weights)."""
        phi = _hats(samples, knots)
        cols = np.nonzero(phi.any(axis=0))[0]
        hs, ws = res[sub].shape[:2]
        jac = np.zeros((len(cols), 2, hs * ws * c), np.float32)
        for s, t in enumerate(samples):
            d = np.array([np.interp(t, knots, path[:, 0]), np.interp(t, knots, path[:, 1])])
            gx, gy = _warped_gradients(img, d)
            a = np.repeat(weights[s][sub].reshape(-1), c).astype(np.float32)
            ax, ay = a * gx[sub].reshape(-1), a * gy[sub].reshape(-1)
            for j, col in enumerate(cols):
                if phi[s, col] != 0:
                    jac[j, 0] -= np.float32(phi[s, col]) * ax
                    jac[j, 1] -= np.float32(phi[s, col]) * ay
        flat = jac.reshape(2 * len(cols), -1)
        idx = np.stack([2 * cols, 2 * cols + 1], -1).reshape(-1)
        ww = wt[sub].reshape(-1).astype(np.float32)
        normal[np.ix_(idx, idx)] += (flat * ww) @ flat.T
        grad[idx] += flat @ (ww * res[sub].reshape(-1).astype(np.float32))

    knot_dt = float(np.median(np.diff(knots))) if k > 1 else frame_s
    n_samples = max(2, SAMPLES_PER_KNOT * (k - 1))
    dt = frame_s / n_samples
    times = (np.arange(n_samples) + 0.5) * dt
    add(
        times,
        [_weight_at(obs.windows, float(t), (h, wd)) * dt for t in times],
        r.reshape(h, wd, c),
        w.reshape(h, wd, c),
    )
    if rb is not None:
        nb = len(obs.windows_b)
        rb4, wb4 = rb.reshape(nb, h, wd, c), wb.reshape(nb, h, wd, c)
        for b, wins in enumerate(obs.windows_b):
            t0, t1 = float(np.min(wins[0].start)), float(np.max(wins[0].end))
            # As many samples as the knots' hats need (a long bin spans several).
            ns = max(3, int(np.ceil(SAMPLES_PER_KNOT * (t1 - t0) / knot_dt)))
            tb = t0 + (np.arange(ns) + 0.5) * (t1 - t0) / ns
            add(
                tb,
                [_weight_at(wins, float(t), (h, wd)) * (t1 - t0) / ns for t in tb],
                rb4[b],
                wb4[b],
            )
    # Smoothness of the path on the knots' scale, and the fixed knot at t = 0.
    scale = float(np.mean(np.diag(normal))) + 1e-30
    if k >= 3:
        d2 = np.zeros((k - 2, k))
        for i in range(k - 2):
            d2[i, i : i + 3] = (1.0, -2.0, 1.0)
        reg = SMOOTH_REL * scale * (d2.T @ d2)
        for a in range(2):
            normal[a::2, a::2] += reg
            grad[a::2] += reg @ path[:, a]
    # The anchor's prior: D(0) stays near 0 (the registration's) unless the early samples
    # say otherwise with confidence (the normal matrix is the inverse covariance, the
    # weights being inverse variances; subsampled rows count stride**2 times).
    normal[0, 0] += 1.0 / (ANCHOR_PX * stride) ** 2
    normal[1, 1] += 1.0 / (ANCHOR_PX * stride) ** 2
    keep = np.repeat(free, 2)
    step = np.zeros(2 * k)
    step[keep] = gain * scaled_step(normal[np.ix_(keep, keep)], grad[keep], {}, 1.0)  # (plain)
    new = path + step.reshape(k, 2)
    d0 = new[0].copy()
    new -= d0
    new_disp = np.asarray(disp, np.float64).copy()
    new_disp[0] = new
    span = max(float(knots[-1]), 1e-12)
    velocity = (new[-1] / span)[None].astype(np.float32)
    return Layers(layers.label, velocity, layers.front, layers.background, (knots, new_disp)), d0


def anchor_image(L: np.ndarray, shape: tuple[int, int, int], d0: np.ndarray) -> np.ndarray:
    """``L`` (H W, C) moved by ``d0`` px (x, y): ``L'(y) = L(y - d0)`` (cubic spline,
    :func:`scipy.ndimage.shift`; border reflected as the background layer), so that
    ``L'(x - D(t) + d0)`` is ``L(x - D(t))``: the image of a path moved by ``-d0``
    (:func:`path_step`). (H W, C) float64."""
    from scipy.ndimage import shift

    h, w, c = shape
    img = np.asarray(L, np.float64).reshape(h, w, c)
    by = (float(d0[1]), float(d0[0]))
    out = np.stack([shift(img[..., k], by, order=3, mode="reflect") for k in range(c)], -1)
    return out.reshape(h * w, c)
