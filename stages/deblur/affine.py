"""A global affine velocity field: the motion of a rotating, zooming or panning camera.

A camera that rotates about its optical axis, zooms, or pans over a distant scene moves
the image by a velocity field that is affine in the pixel position::

    u(x, y) = a + B (x - cx, y - cy)^T        (px/s; six parameters)

Dense optical flow measures such a field pixel by pixel, with the flow's noise and its
bias at edges; six parameters fitted to the whole frame average both away, and the
deblur's misfit then refines them (:func:`affine_step`): each Gauss-Newton step of the
misfit in the velocity, projected onto the six parameters. The image step that
alternates with it absorbs part of a motion error (it blurs the image to match), so a
plain Gauss-Newton step falls short of the misfit's minimum by a roughly constant factor;
the steps are scaled by ``JointOptions.affine_gain``.

Coordinates are normalised (``(x - W/2) / W``, ``(y - H/2) / H``) so that the six
parameters are of comparable size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: A motion the layers cannot describe is read as an affine field when that field
#: misses at most this share of what the dense field explains in the measuring bins
#: (``ModelCheck.affine_share`` of :func:`stages.deblur.layers.model_check.
#: layered_model_check`, scored as the layers are).
AFFINE_MISS_SHARE = 0.2

#: Largest distance (px over the frame) between the flow and the fitted field counted
#: as agreeing.
FIT_TOL_PX = 1.0


@dataclass
class AffineFit:
    """A fitted affine field: ``theta`` (6: ``a_x, b_xx, b_xy, a_y, b_yx, b_yy`` in
    normalised coordinates), the share of pixels it explains, and the field itself."""

    theta: np.ndarray
    inlier_share: float
    field: np.ndarray


def basis(shape: tuple[int, int]) -> np.ndarray:
    """The affine basis ``(1, x', y')`` at every pixel, shape ``(H W, 3)``, float64."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([np.ones(h * w), ((xx - w / 2) / w).ravel(), ((yy - h / 2) / h).ravel()], 1)


def affine_field(theta: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The velocity field ``(H, W, 2)`` float32 of parameters ``theta`` (6,)."""
    p = basis(shape)
    return np.stack([(p @ theta[:3]), (p @ theta[3:])], -1).reshape(*shape, 2).astype(np.float32)


def fit_affine(
    velocity: np.ndarray,
    frame_s: float,
    weights: np.ndarray | None = None,
    iterations: int = 6,
) -> AffineFit:
    """Robust least-squares affine fit to a dense velocity field ``(H, W, 2)`` px/s.

    ``weights`` (H, W), optional: the flow's confidence. Iteratively reweighted (Huber
    weights at twice the residuals' robust spread) so that flow outliers (occlusions,
    textureless patches) do not pull the fit. The inlier share counts the pixels within
    :data:`FIT_TOL_PX` of the fit over ``frame_s``.
    """
    h, w = velocity.shape[:2]
    p = basis((h, w))
    v = velocity.reshape(-1, 2).astype(np.float64)
    prior = np.ones(h * w) if weights is None else np.asarray(weights, np.float64).ravel()
    wt = prior.copy()
    theta = np.zeros(6)
    res = np.zeros(h * w)
    for _ in range(iterations):
        pw = p * wt[:, None]
        gram = pw.T @ p + 1e-12 * np.eye(3)
        theta = np.concatenate([np.linalg.solve(gram, pw.T @ v[:, k]) for k in range(2)])
        res = np.hypot(v[:, 0] - p @ theta[:3], v[:, 1] - p @ theta[3:])
        spread = 1.4826 * float(np.median(res)) + 1e-9
        wt = prior / np.maximum(1.0, res / (2 * spread))
    share = float(np.mean(res * frame_s <= FIT_TOL_PX))
    return AffineFit(theta, share, affine_field(theta, (h, w)))


def affine_step(
    obs: Any,
    L: np.ndarray,
    vel: np.ndarray,
    r: np.ndarray,
    w: np.ndarray,
    rb: np.ndarray | None,
    wb: np.ndarray | None,
    T: np.ndarray,
    frame_s: float,
    leakage: float,
    opts: Any,
    state: dict | None = None,
) -> np.ndarray:
    """One Gauss-Newton step on the misfit in the six affine parameters.

    Takes the per-pixel normal terms of :func:`stages.deblur.motion_steps.motion_terms`
    (the misfit's Jacobian in each pixel's velocity, evaluated along its integration
    paths) and sums them through the affine basis: ``N = sum P^T H_x P``, ``g = sum P^T
    b_x``; the step (:func:`stages.deblur.motion_steps.scaled_step`, from
    ``opts.affine_gain``; ``state`` a dict kept between the calls of one solve) is added to
    ``vel``, which must be affine. Returns the new ``(H, W, 2)`` float32 field.
    """
    from .motion_steps import motion_terms, scaled_step

    h, wd = vel.shape[:2]
    hxx, hxy, hyy, bx, by = (
        a.ravel() for a in motion_terms(obs, L, vel, r, w, rb, wb, T, frame_s, leakage)
    )
    p = basis((h, wd))
    normal = np.zeros((6, 6))
    for i, j, hh in ((0, 0, hxx), (0, 1, hxy), (1, 1, hyy)):
        blk = (p * hh[:, None]).T @ p
        normal[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = blk
        normal[3 * j : 3 * j + 3, 3 * i : 3 * i + 3] = blk.T
    grad = np.concatenate([p.T @ bx, p.T @ by])
    step = scaled_step(normal, grad, {} if state is None else state, opts.affine_gain)
    return (vel + affine_field(step, (h, wd))).astype(np.float32)
