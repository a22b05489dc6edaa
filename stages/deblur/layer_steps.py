"""Gauss-Newton steps on the velocities of translating layers (model ``layers``).

The layered estimate (:mod:`stages.deblur.layers`) measures each moving layer's
velocity from the motion estimate's eight time bins; the deblur's misfit, which all the
data enter (the VET image and every fit bin), refines it as it refines an affine field
(:mod:`stages.deblur.affine`): the per-pixel normal terms of the misfit in the velocity
(:func:`stages.deblur.motion_steps.motion_terms`) summed over the layer's pixels give two
normal equations per layer, and the step is scaled as the affine one's
(:func:`stages.deblur.motion_steps.scaled_step`, ``JointOptions.affine_gain``). Those
terms follow each pixel along its own velocity (no occlusion), which is the layered model
away from other layers only, so the pixels within :data:`BOUNDARY_PX` of another layer
are left out. The labels are kept. Only a motion with no still layer is refined (a
global translation, or layers that all move): beside a still background the objects'
boundaries are where the labels err, and the robust weights of a solve along one
velocity, carried into the next, pull a refined object's velocity off its true value.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .operator import motion_layers

#: Pixels within this distance (px) of another layer do not enter a layer's equations.
BOUNDARY_PX = 4
#: A layer with fewer pixels than this away from the others is not refined.
MIN_PIXELS = 64


def layer_step(
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
    state: dict,
) -> np.ndarray:
    """One scaled Gauss-Newton step on each layer's velocity when every layer moves
    (else ``vel`` unchanged).

    ``vel`` (H, W, 2) px/s holds a few distinct velocities (the layers); ``L`` (H W, C)
    electrons/s, ``r``/``w`` the VET residual and weights (H W, C), ``rb``/``wb`` the bins'
    (B H W, C) or None. ``state``: a dict kept between the calls of one solve (the labels
    of the first call, each layer's step history). Each step is at most
    ``opts.motion_step_max`` px/s. Returns the new (H, W, 2) float32 field.
    """
    import cv2

    from .motion_steps import motion_terms, scaled_step

    if "label" not in state:
        layers = motion_layers(vel)
        if layers is None:
            return vel
        state["label"] = layers.label
        state["velocity"] = layers.velocity.astype(np.float64)
    label, velocity = state["label"], state["velocity"]
    moving = [k for k in range(len(velocity)) if np.any(velocity[k] != 0)]
    if len(moving) < len(velocity):  # (a still layer: objects over a still background)
        return vel
    hxx, hxy, hyy, bx, by = motion_terms(obs, L, vel, r, w, rb, wb, T, frame_s, leakage)
    box = np.ones((2 * BOUNDARY_PX + 1, 2 * BOUNDARY_PX + 1), np.uint8)
    for k in moving:
        inner = (
            cv2.erode((label == k).astype(np.uint8), box) > 0
        )  # (the frame's edge is no layer's)
        if inner.sum() < MIN_PIXELS:
            continue
        sxy = float(hxy[inner].sum())
        normal = np.array([[float(hxx[inner].sum()), sxy], [sxy, float(hyy[inner].sum())]])
        grad = np.array([float(bx[inner].sum()), float(by[inner].sum())])
        if not np.all(np.isfinite(normal)) or normal[0, 0] + normal[1, 1] <= 0:
            continue
        step = scaled_step(normal, grad, state.setdefault(("steps", k), {}), opts.affine_gain)
        norm = float(np.hypot(*step))
        if norm > opts.motion_step_max:
            step *= opts.motion_step_max / norm
        velocity[k] = velocity[k] + step
    return velocity[label].astype(np.float32)
