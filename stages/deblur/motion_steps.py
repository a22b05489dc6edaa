"""Gauss-Newton steps on a dense velocity field for the deblur (``update_motion``) and
the gradient the published method descends: the misfit's derivatives in the velocity,
evaluated matrix-free along the integration paths; and the scaled step that the
parametric motions (:mod:`stages.deblur.affine`, :mod:`stages.deblur.path_steps`) take."""

from __future__ import annotations

from typing import Any

import numpy as np

from .operator import trajectory_sum
from .problem import Observations, laplacian


def motion_terms(
    obs: Observations,
    L: np.ndarray,
    vel: np.ndarray,
    r: np.ndarray,
    w: np.ndarray,
    rb: np.ndarray | None,
    wb: np.ndarray | None,
    T: np.ndarray,
    frame_s: float,
    leakage: float,
    n_time: int = 24,
) -> tuple[np.ndarray, ...]:
    """Per-pixel Gauss-Newton terms ``(Hxx, Hxy, Hyy, bx, by)`` of the misfit in ``u``.

    The Jacobian of a pixel's model ``sum_s w_s L(x - u t_s)`` w.r.t. its velocity is
    ``-sum_s w_s t_s grad L(x - u t_s)``, evaluated matrix-free on ``n_time`` samples of
    the frame (and three per measuring bin); ``b = J^T W r``, ``H = J^T W J``.
    """
    h, wd, c = obs.shape
    img = L.reshape(h, wd, c).astype(np.float32)
    gys, gxs = np.gradient(img, axis=(0, 1))
    hxx = np.zeros((h, wd))
    hxy = np.zeros((h, wd))
    hyy = np.zeros((h, wd))
    bx = np.zeros((h, wd))
    by = np.zeros((h, wd))

    grads = np.concatenate([gxs, gys], axis=2)  # (H, W, 2C): both sampled on one path

    def accumulate(times, weights, rr, ww):
        j = trajectory_sum(grads, vel, times, weights * times.reshape(-1, 1, 1))
        jx = -j[..., :c].astype(np.float64)
        jy = -j[..., c:].astype(np.float64)
        hxx[...] += (ww * jx * jx).sum(axis=2)
        hxy[...] += (ww * jx * jy).sum(axis=2)
        hyy[...] += (ww * jy * jy).sum(axis=2)
        bx[...] += (ww * jx * rr).sum(axis=2)
        by[...] += (ww * jy * rr).sum(axis=2)

    dt = frame_s / n_time
    times = (np.arange(n_time) + 0.5) * dt
    weights = np.where(times.reshape(-1, 1, 1) < T[None], 1.0, leakage) * dt
    accumulate(times, weights, r.reshape(h, wd, c), w.reshape(h, wd, c))
    if rb is not None:
        nb = len(obs.windows_b)
        rb4 = rb.reshape(nb, h, wd, c)
        wb4 = wb.reshape(nb, h, wd, c)
        for b, wins in enumerate(obs.windows_b):
            win = wins[0]
            t0, t1, frac = float(win.start), float(win.end), float(win.weight)
            k = 3
            tb = t0 + (np.arange(k) + 0.5) * (t1 - t0) / k
            wgt = np.full((k, 1, 1), frac * (t1 - t0) / k)
            accumulate(tb, wgt, rb4[b], wb4[b])
    return hxx, hxy, hyy, bx, by


#: Largest gain of a parametric Gauss-Newton step (:func:`scaled_step`).
MAX_GAIN = 20.0


def scaled_step(normal: np.ndarray, grad: np.ndarray, state: dict, gain0: float) -> np.ndarray:
    """A Gauss-Newton step ``-gain N^-1 g`` on a few motion parameters, ``N`` (P, P) the
    misfit's curvature with the image held fixed and ``g`` (P,) its gradient.

    The image re-solved between steps absorbs part of each motion error, so the curvature
    that matters (of the misfit minimised over the image) is lower than ``N``'s and a
    plain step falls short. ``gain`` starts at ``gain0``; later steps measure the ratio
    along the previous step ``s`` (kept in ``state``, a dict kept between the calls of one
    solve): ``s^T N s / s^T (g - g')`` (a secant estimate, within [1, :data:`MAX_GAIN`]),
    and double it where the gradient did not turn. Levenberg damping 1e-3 of the diagonal.
    """
    normal = normal + 1e-3 * np.diag(np.diag(normal)) + 1e-12 * np.eye(len(grad))
    gain = float(state.get("gain", gain0))
    if "step" in state and len(state["step"]) == len(grad):
        s_prev = state["step"]
        turn = float(s_prev @ (grad - state["grad"]))
        if turn > 0:
            gain = float(np.clip((s_prev @ normal @ s_prev) / turn, 1.0, MAX_GAIN))
        else:  # the gradient did not turn along the last step: it fell short
            gain = min(2.0 * gain, MAX_GAIN)
    step = -gain * np.linalg.solve(normal, grad)
    state.update(step=step, grad=grad, gain=gain)
    return step


def motion_step_gradient(
    obs: Observations,
    L: np.ndarray,
    vel: np.ndarray,
    r: np.ndarray,
    w: np.ndarray,
    T: np.ndarray,
    frame_s: float,
    leakage: float,
) -> np.ndarray:
    """Gradient of ``sum w r^2`` (VET image only) w.r.t. the velocity, ``(H, W, 2)``."""
    _hxx, _hxy, _hyy, bx, by = motion_terms(obs, L, vel, r, w, None, None, T, frame_s, leakage)
    return 2 * np.stack([bx, by], axis=-1)


def motion_step(
    obs: Observations,
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
) -> np.ndarray:
    """One damped Gauss-Newton step on the velocity field with Laplacian smoothness
    (``opts``: :class:`stages.deblur.joint.JointOptions`)."""
    import scipy.sparse.linalg as spla

    h, wd, _c = obs.shape
    hxx, hxy, hyy, bx, by = motion_terms(obs, L, vel, r, w, rb, wb, T, frame_s, leakage)
    tr = hxx + hyy
    scale = float(np.median(tr[tr > 0])) if np.any(tr > 0) else 1.0
    alpha = opts.motion_alpha * scale
    damp = 0.1 * tr + 1e-6 * scale
    n = h * wd

    def apply(x: np.ndarray) -> np.ndarray:
        du = x[:n].reshape(h, wd)
        dv = x[n:].reshape(h, wd)
        ox = (hxx + damp) * du + hxy * dv - alpha * laplacian(du)
        oy = hxy * du + (hyy + damp) * dv - alpha * laplacian(dv)
        return np.concatenate([ox.ravel(), oy.ravel()])

    rhs = -np.concatenate(
        [
            (bx - alpha * laplacian(vel[..., 0])).ravel(),
            (by - alpha * laplacian(vel[..., 1])).ravel(),
        ]
    )
    dg = np.concatenate([(hxx + damp + 4 * alpha).ravel(), (hyy + damp + 4 * alpha).ravel()])
    op = spla.LinearOperator((2 * n, 2 * n), matvec=apply, dtype=np.float64)
    pre = spla.LinearOperator((2 * n, 2 * n), matvec=lambda x: x / dg, dtype=np.float64)
    sol, _ = spla.cg(op, rhs, M=pre, maxiter=60)
    du = np.stack([sol[:n].reshape(h, wd), sol[n:].reshape(h, wd)], axis=-1)
    du = np.clip(du, -opts.motion_step_max, opts.motion_step_max)
    return (vel + du).astype(np.float32)
