"""The layered velocity field of a capture: the steps of :mod:`stages.deblur.layers` in order."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ...formats.capture import Capture
from .alignment import median0
from .bins import binned_work_frames, rate_frame_centres, rate_frames, work_frames
from .labels import SAME_LAYER_PX_S, assign_labels, kept_layers, merge_alike, refine_boundaries
from .model_check import ModelCheck, layered_model_check
from .velocities import dense_long_baseline, refine_velocity, velocity_modes

log = logging.getLogger(__name__)


#: Layers slower than this (px/s: under one pixel of travel in a 1 s frame) are still.
MIN_SPEED_PX_S = 1.0
#: Estimation runs on images no larger than this (longer side, pixels).
MAX_WORK_PX = 400
#: Time bins of a capture that keeps its stream that the track evidence reads (the
#: labels, their boundaries and the velocities' refinement); the flow and the model
#: check read :data:`~stages.formats.capture.MOTION_BINS`. Shorter bins place the
#: moment an object covers a still point more sharply, while the flow between two bins
#: needs their light.
TRACK_BINS = 16


@dataclass
class LayerEstimate:
    """Output of :func:`estimate_layers`."""

    velocity: np.ndarray  # (H, W, 2) px/s, few distinct values
    layer_velocities: np.ndarray  # (K, 2)
    label: np.ndarray  # (H, W) int
    dense: np.ndarray  # (H, W, 2) the per-pixel long-baseline fit
    confidence: np.ndarray  # (H, W)
    check: ModelCheck | None = None  # does the layered model explain the bins?


def estimate_layers(cap: Capture) -> LayerEstimate:
    """Layered velocity field of a capture (see the module docstring)."""
    import cv2

    h, w = cap.shape
    lum, noise, valid_full = rate_frames(cap)  # (a stream's motion bins, one at a time)
    centres = rate_frame_centres(cap)
    n_binned = len(centres)
    lv, slv, valid, (sx, sy) = work_frames(lum, noise, valid_full, MAX_WORK_PX)
    del valid_full
    hw, ww = lv.shape[1:]
    votes, wts, vel_d, conf = dense_long_baseline(lv, slv, centres)
    # The track evidence: on TRACK_BINS bins of a stream, else on the same bins; the
    # boundaries at full resolution from them too where the frame is the working grid
    # (a larger frame's would hold all of them at full resolution: its motion bins').
    lum_t, noise_t, lvt, slvt, centres_t = lum, noise, lv, slv, centres
    centres_b = centres
    if cap.keeps_stream and cap.measure_shape[0] > TRACK_BINS > n_binned:
        if max(h, w) <= MAX_WORK_PX:  # (the working grid: full resolution, small)
            fine = cap.time_bins(TRACK_BINS)
            lum_t, noise_t, valid_t = rate_frames(fine)
            lvt, slvt, _valid, _scale = work_frames(lum_t, noise_t, valid_t, MAX_WORK_PX)
            centres_t = centres_b = fine.measure_times.mean(axis=1).astype(np.float64)
        else:
            lvt, slvt, _valid, _scale, centres_t = binned_work_frames(cap, TRACK_BINS, MAX_WORK_PX)
    ok = valid.all(axis=0)
    conf_raw = median0(wts) * ok
    conf = conf * ok
    modes = velocity_modes(votes, wts * ok[None])
    del votes, wts  # (their modes are all the rest reads: not held through the search)
    # Candidates: zero plus each mode (in working-grid px/s), refined on its voters.
    cands: list[np.ndarray] = [np.zeros(2)]
    sel = conf > np.percentile(conf, 50)
    for m in modes:
        if np.hypot(*m) < MIN_SPEED_PX_S:
            continue
        near = np.hypot(vel_d[..., 0] - m[0], vel_d[..., 1] - m[1]) < max(
            3.0, 0.15 * float(np.hypot(*m))
        )
        wgt = (conf * (near & sel)).astype(np.float64)
        v = refine_velocity(lvt, slvt, m, centres_t, wgt)
        if np.hypot(*v) >= MIN_SPEED_PX_S and all(
            np.hypot(*(v - c)) > SAME_LAYER_PX_S for c in cands[1:]
        ):
            cands.append(v)
    label = np.zeros((hw, ww), np.int32)
    if len(cands) > 1:
        label = assign_labels(lvt, slvt, cands, centres_t)
        keep = [0] + [k for k in range(1, len(cands)) if np.any(label == k)]
        remap = np.zeros(len(cands), np.int32)
        remap[keep] = np.arange(len(keep))
        cands = [cands[k] for k in keep]
        label = remap[label]
        # Second pass: refine each moving layer's velocity on the interior of its
        # points (better voters than the flow's); layers that then move alike are one
        # (refined again on their union); assign again.
        for _ in range(len(cands)):
            for k in range(1, len(cands)):
                inner = cv2.erode((label == k).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
                if inner.sum() >= 50:
                    cands[k] = refine_velocity(
                        lvt,
                        slvt,
                        cands[k],
                        centres_t,
                        (conf_raw * inner).astype(np.float64),
                        steps=(0.25, 0.125, 0.0625),
                    )
            n_before = len(cands)
            label, cands = merge_alike(label, cands)
            if len(cands) == n_before:
                break
        if len(cands) > 1:  # (no point kept a moving layer: the scene is still)
            label = assign_labels(lvt, slvt, cands, centres_t)
    check = layered_model_check(lv, slv, label, np.asarray(cands), vel_d, conf, centres)
    log.debug("layers: model check %s", check)
    # Back to the full grid: nearest-neighbour labels, velocities rescaled.
    lab_full = cv2.resize(label.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(
        np.int32
    )
    vels = np.array([[v[0] / sx, v[1] / sy] for v in cands], np.float32)
    lab_full, vels = kept_layers(lab_full, vels)
    if len(vels) > 1:  # (also on a frame no larger than the working grid: pooled labels)
        lab_full, vels = kept_layers(
            refine_boundaries(lum_t, noise_t, lab_full, vels, centres_b), vels
        )
    velocity = vels[lab_full]
    dense = np.stack(
        [cv2.resize(vel_d[..., 0] / sx, (w, h)), cv2.resize(vel_d[..., 1] / sy, (w, h))], -1
    )
    confidence = cv2.resize(conf, (w, h))
    if check.affine is not None:  # (affine on the working grid: affine on the full one)
        aff = check.affine
        check.affine = np.stack(
            [cv2.resize(aff[..., 0] / sx, (w, h)), cv2.resize(aff[..., 1] / sy, (w, h))], -1
        ).astype(np.float32)
    log.debug(
        "layers: velocities %s, shares %s",
        vels.tolist(),
        [float((lab_full == k).mean()) for k in range(len(vels))],
    )
    return LayerEstimate(
        velocity.astype(np.float32),
        vels,
        lab_full,
        dense.astype(np.float32),
        confidence.astype(np.float32),
        check,
    )
