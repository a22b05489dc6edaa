"""The published deblur (Uda, Sakaue and Sato 2016), reproduced as faithfully as the paper
allows, for comparison with the default method.

Energy, over the scene at t = 0 ``L`` and the per-pixel velocity ``u = (u, v)``::

    E(L, u) = |A(u) L - y|^2 / Tf^2                      plain least squares on I
            + lam_L |Lap L|^2                             Laplacian smoothness of the image
            + lam_u (|Lap u|^2 + |Lap v|^2)               ... and of both motion components
            + lam_h (1 - HI(h(grad log L), h_ref))        histogram-intersection prior

minimised by steepest descent from the hdr-static image and Farnebäck flow. The misfit
uses the VET image only (not the measuring images) and no noise weighting, as published;
dividing by ``Tf^2`` only puts it in units of rate^2 so the weights below are readable.

Histogram prior: ``h`` is a soft (Gaussian-kernel) histogram of the horizontal and
vertical differences of ``log L`` (HDR: the log makes the statistics independent of
brightness), ``HI`` the histogram intersection ``sum_b min(h_b, h_ref_b)``. The reference
``h_ref`` is the same histogram of the **hdr-static estimate over the pixels that closed
early** (``T < Tf``): those were exposed only a few subframes, so they are sharp, and they
come from the same scene and optics as the blurred dark region. When fewer than
:data:`MIN_REFERENCE_PIXELS` pixels closed early, a heavy-tailed (Laplacian,
scale 0.05 in log units) natural-image gradient distribution is used instead (the
heavy-tailed shape of natural-image gradient statistics: Field 1987, Fergus et al. 2006).

Descent: steepest descent on ``z = log L`` (so the image stays positive without a
clamp, and steps are relative, as befits an HDR image and the log-gradient prior), with
an Armijo backtracking line search on the whole energy: a step is taken only if it
lowers it. The motion step is a fixed normalised step, accepted only if it lowers the
data misfit.

Weights: the misfit is in rate^2 units, ``(e-/s)^2`` summed over pixels, so the prior
weights are not the paper's numbers (its images were 8-bit). ``lam_L`` is set on the
builtin interior, not on the evaluation scenes: the Laplacian of an HDR image is largest
at its bright edges, so a weight large enough to compete with the misfit there sets the
global step and leaves the dark pixels at hdr-static; a small one lets the misfit move
them. The histogram-intersection term is bounded by ``lam_h`` (``1 - HI`` lies in
[0, 1]), so at any weight that keeps the misfit in charge it only nudges the gradient
statistics.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..formats.hdr import HDRImage
from .problem import Observations, build_operators, laplacian

log = logging.getLogger(__name__)

MIN_REFERENCE_PIXELS = 500
BINS = np.linspace(-2.0, 2.0, 81)
KERNEL_SIGMA = 0.05


@dataclass
class PaperOptions:
    """Weights and iteration counts of :func:`deblur_paper`."""

    outer: int = 2
    sd_iters: int = 20
    lam_L: float = 0.001
    lam_u: float = 0.1
    lam_h: float = 10.0
    motion_step: float = 1.0
    step_px: float = 1.0
    history: list = field(default_factory=list)


def soft_histogram(g: np.ndarray) -> np.ndarray:
    """Gaussian-kernel histogram of values ``g`` on :data:`BINS` (sums to ~1)."""
    d = (g.reshape(-1, 1) - BINS.reshape(1, -1)) / KERNEL_SIGMA
    k = np.exp(-0.5 * d * d)
    h = k.sum(axis=0)
    return h / max(g.size, 1)


def reference_histogram(static: HDRImage, T: np.ndarray, frame_s: float) -> tuple[np.ndarray, str]:
    """Reference gradient histogram: sharp early-closed pixels of hdr-static, or a prior."""
    lum = static.radiance.mean(axis=2)
    logl = np.log(np.maximum(lum, 1e-30))
    bright = T < frame_s * (1 - 1e-6)
    gx = (logl[:, 1:] - logl[:, :-1])[bright[:, 1:] & bright[:, :-1]]
    gy = (logl[1:] - logl[:-1])[bright[1:] & bright[:-1]]
    g = np.concatenate([gx, gy])
    if g.size >= MIN_REFERENCE_PIXELS:
        if g.size > 200_000:
            g = np.random.default_rng(0).choice(
                g, 200_000, replace=False
            )  # fixed seed: reproducible
        return soft_histogram(
            np.clip(g, BINS[0], BINS[-1])
        ), "hdr-static gradients of early-closed pixels"
    p = np.exp(-np.abs(BINS) / 0.05)
    return p / p.sum(), "Laplacian natural-image prior (scale 0.05)"


def _hist_grad_table(h: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d HI / d g as a lookup table over g (per sample, before the 1/N factor)."""
    active = (h < ref).astype(np.float64)
    grid = np.linspace(BINS[0] - 0.5, BINS[-1] + 0.5, 2048)
    d = (grid.reshape(-1, 1) - BINS.reshape(1, -1)) / KERNEL_SIGMA
    kprime = -d / KERNEL_SIGMA * np.exp(-0.5 * d * d)
    return grid, kprime @ active


def _hist_term(L: np.ndarray, ref: np.ndarray) -> tuple[float, np.ndarray]:
    """Histogram-intersection energy ``1 - HI`` and its gradient w.r.t. ``L`` (H, W, C)."""
    lum = np.maximum(L.mean(axis=2), 1e-30)
    logl = np.log(lum)
    gx = logl[:, 1:] - logl[:, :-1]
    gy = logl[1:] - logl[:-1]
    g = np.concatenate([gx.ravel(), gy.ravel()])
    sub = g[:: max(1, g.size // 100_000)]
    h = soft_histogram(np.clip(sub, BINS[0], BINS[-1]))
    energy = 1.0 - float(np.minimum(h, ref).sum())
    grid, table = _hist_grad_table(h, ref)
    n = g.size
    dx = -np.interp(gx, grid, table) / n  # d(1 - HI)/d gx
    dy = -np.interp(gy, grid, table) / n
    dlog = np.zeros_like(logl)
    dlog[:, 1:] += dx
    dlog[:, :-1] -= dx
    dlog[1:] += dy
    dlog[:-1] -= dy
    dL = dlog / lum / L.shape[2]
    return energy, np.repeat(dL[..., None], L.shape[2], axis=2)


def deblur_paper(
    obs: Observations,
    L_init: np.ndarray,
    velocity: np.ndarray,
    T: np.ndarray,
    frame_s: float,
    subframe_s: float,
    leakage: float,
    static: HDRImage,
    saturated: np.ndarray,
    opts: PaperOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    truth_cb: Callable[[np.ndarray], float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Steepest descent on the published energy (see the module docstring).

    Returns ``L0`` (H, W, C) electrons/s and the velocity (H, W, 2) px/s.
    """
    from .motion_steps import motion_step_gradient

    opts = opts or PaperOptions()
    h, w, c = obs.shape
    n = h * w
    ref_hist, source = reference_histogram(static, T, frame_s)
    log.debug("deblur paper: reference histogram from %s", source)
    L = L_init.astype(np.float64).copy()
    vel = velocity.astype(np.float32).copy()
    y = obs.y.reshape(h, w, c)
    valid = (obs.w > 0).reshape(h, w, c).astype(np.float64)
    s2 = 1.0 / frame_s**2
    # Noise-equivalent floor (as hdr-static's): one electron over the pixel's exposure.
    expo = (T + leakage * (frame_s - T))[..., None]
    floor = np.broadcast_to(1.0 / expo, (h, w, c))
    k = 0

    def data_res(A: sp.csr_matrix, img: np.ndarray) -> np.ndarray:
        return (
            np.asarray(A @ img.reshape(n, c).astype(np.float32), np.float64).reshape(h, w, c) - y
        ) * valid

    def at(A: sp.csr_matrix, r: np.ndarray) -> np.ndarray:
        return np.asarray(A.T @ r.reshape(n, c).astype(np.float32), np.float64).reshape(h, w, c)

    A, _ = build_operators(obs, vel, step_px=opts.step_px, subframe_s=subframe_s, lean=False)
    free = ~np.broadcast_to(saturated[..., None], L.shape)

    def energy(A_: sp.csr_matrix, img: np.ndarray) -> float:
        r = data_res(A_, img)
        lap = laplacian(img)
        e_h, _ = _hist_term(img, ref_hist)
        return float(s2 * np.sum(r * r) + opts.lam_L * np.sum(lap * lap) + opts.lam_h * e_h)

    L = np.maximum(L, floor)
    alpha = None
    total = opts.outer * opts.sd_iters
    for outer in range(opts.outer):
        e_cur = energy(A, L)
        for it in range(opts.sd_iters):
            if progress:
                progress(outer * opts.sd_iters + it, total)
            r = data_res(A, L)
            _e_h, g_h = _hist_term(L, ref_hist)
            grad_L = 2 * s2 * at(A, r) + 2 * opts.lam_L * laplacian(laplacian(L)) + opts.lam_h * g_h
            g = np.where(free, grad_L * L, 0.0)  # d E / d log L
            gg = float(np.sum(g * g))
            if gg <= 0:
                break
            if alpha is None:
                alpha = 0.1 / float(np.abs(g).max())  # at most a 10% change in the first trial
            else:
                alpha *= 2.0
            for _bt in range(30):  # Armijo backtracking
                trial = L * np.exp(np.clip(-alpha * g, -5.0, 5.0))
                e_new = energy(A, trial)
                if e_new <= e_cur - 1e-4 * alpha * gg:
                    break
                alpha *= 0.5
            else:
                break
            L, e_cur = trial, e_new
            k += 1
            if truth_cb is not None and k % 5 == 0:
                opts.history.append((k, None, truth_cb(L)))
        if outer == opts.outer - 1:
            break
        # Motion: one steepest-descent step (normalised), kept if the misfit falls.
        r = data_res(A, L)
        g_u = motion_step_gradient(
            obs, L, vel, r.reshape(n, c) * s2, valid.reshape(n, c), T, frame_s, leakage
        )
        g_u = g_u + 2 * opts.lam_u * np.stack(
            [laplacian(laplacian(vel[..., i])) for i in range(2)], -1
        )
        gmax = float(np.abs(g_u).max())
        if gmax > 0:
            trial = (vel - opts.motion_step * g_u / gmax).astype(np.float32)
            A_new, _ = build_operators(
                obs, trial, step_px=opts.step_px, subframe_s=subframe_s, lean=False
            )
            if np.sum(data_res(A_new, L) ** 2) < np.sum(r**2):
                vel, A = trial, A_new
    if progress:
        progress(total, total)
    return L.astype(np.float32), vel
