"""Which layer each scene point belongs to: assignment, boundaries, merging."""

from __future__ import annotations

import logging

import numpy as np

from .alignment import track_score
from .bins import log_frames
from .potts import complete_labels

log = logging.getLogger(__name__)


#: Candidate layers whose refined velocities differ by less than this (working-grid
#: px/s) are one layer: the vote histogram resolves modes about 3 px/s apart (its peak
#: suppression radius), and a partly converged long-baseline flow on one object votes a
#: second, slower mode near the first.
SAME_LAYER_PX_S = 4.0
#: Log-likelihood ratio (nats) a point needs to leave the default layer.
EVIDENCE_NATS = 3.0
#: Neighbourhoods (Gaussian sigma, working-grid px) over which the evidence is pooled.
POOL_SIGMAS = (2.0, 4.0, 8.0, 16.0)
#: Per-point evidence (nats) is clipped at this for the wider neighbourhoods.
POOL_CLIP_NATS = 2.0
#: Share of the points a layer must keep, else it is merged into the largest.
MIN_SHARE = 0.01
#: Points clear at no scale are labelled together (:mod:`.potts`), each by its own
#: evidence (unclipped: clipping would bias it, as its negative tail is the longer one
#: where an occlusion makes both hypotheses misfit), with this cost (nats) for each pair
#: of 4-neighbours in different layers ...
BOUNDARY_NATS = 2.0
#: ... and a prior (nats per point) for the default layer: flat, noisy content scores a
#: little evidence for any motion (up to about this much on average, on still captures of
#: ../shared's scenes), which must not move it.
DEFAULT_PRIOR_NATS = 0.2
#: Full-resolution pixels about a working-grid layer boundary whose labels are decided
#: again from the full-resolution bins.
BOUNDARY_BAND_PX = 8
#: Gaussian (full-resolution px) over which that evidence is pooled: enough to steady a
#: pixel's evidence with its nearest neighbours', little enough not to carry it a pixel
#: across the boundary (each pixel mislabelled along a moving edge smears the edge over
#: the path; tests/test_deblur_layers.py measures it on a sharp scene).
BOUNDARY_SIGMA_PX = 0.7
#: Evidence (nats) by which a pixel's working-grid layer is favoured there.
BOUNDARY_PRIOR_NATS = 1.0


def assign_labels(
    lv: np.ndarray, slv: np.ndarray, cands: list[np.ndarray], centres: np.ndarray
) -> np.ndarray:
    """Label map of the scene points at t = 0 over the candidate layers (step 4)."""
    import cv2

    hw, ww = lv.shape[1:]
    # Evidence for each moving layer against stillness (log-likelihood ratios, nats
    # per point), pooled over a neighbourhood: a Gaussian of POOL_SIGMAS[0] first.
    # Points with no clear evidence there are tested again over wider neighbourhoods,
    # the threshold on the pooled mean falling as 1/sigma (the noise of a mean over
    # ~4 pi sigma^2 points): weak but consistent evidence (a dark, faintly textured
    # moving region) decides at a coarser scale. Each point's evidence is clipped at
    # +-POOL_CLIP_NATS for the wider tests, so that a few strongly textured points
    # cannot carry a flat neighbourhood. Points clear at no scale favour a default layer:
    # the still one where the scene has clearly still parts, else (a global motion) the
    # moving layer most points clearly follow.
    raw = [track_score(lv, slv, v, centres) for v in cands[1:]]
    zero = np.zeros((hw, ww), np.float32)

    def pooled(sigma: float, src: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pooled evidence (K, H, W), its best layer and where that is clear at ``sigma``."""
        llr = np.stack([zero] + [cv2.GaussianBlur(r, (0, 0), sigma) for r in src])
        top2 = np.partition(llr, -2, axis=0)[-2:]
        clear = (top2[1] - top2[0]) > EVIDENCE_NATS * POOL_SIGMAS[0] / sigma
        return llr, np.argmax(llr, axis=0), clear

    llr0, best, clear = pooled(POOL_SIGMAS[0], raw)
    counts = np.bincount(best[clear], minlength=len(cands)).astype(np.float64)
    label = np.where(clear, best, -1).astype(np.int32)
    clipped = [np.clip(r, -POOL_CLIP_NATS, POOL_CLIP_NATS) for r in raw]
    for sigma in POOL_SIGMAS[1:]:
        _llr, best, clear = pooled(sigma, clipped)
        take = clear & (label < 0)
        label[take] = best[take]
    wider = int((label >= 0).sum() - counts.sum())
    default = 0 if counts[0] >= 0.05 * max(counts.sum(), 1.0) else int(np.argmax(counts))
    if len(cands) == 2:
        # One moving layer: the rest are labelled together, each taking the layer its
        # evidence favours where a region's evidence in sum outweighs the boundary that
        # labelling makes; an undecided pocket takes the layer about it; flat content
        # with no evidence the default layer. (With more, undecided points between
        # moving layers are where a field is not layered, a rotation's, and the model
        # check must see them misfit: they take the default layer.)
        if counts[1 - default] < MIN_SHARE * label.size:  # (a layer that is not kept, below)
            label[label < 0] = default
        else:
            cost = np.stack([zero, -raw[0]])
            cost[default] -= np.float32(DEFAULT_PRIOR_NATS)
            label = complete_labels(label, cost, BOUNDARY_NATS)
    else:
        llr0[default] += EVIDENCE_NATS
        rest = label < 0
        label[rest] = np.argmax(llr0, axis=0)[rest]
    log.debug(
        "layers: clear evidence counts %s, %d points decided at wider scales, default layer %d",
        counts.tolist(),
        wider,
        default,
    )
    label = cv2.medianBlur(label.astype(np.uint8), 5).astype(np.int32)
    # Layers that keep too few points are merged into the largest one.
    shares = np.bincount(label.ravel(), minlength=len(cands)) / label.size
    big = int(np.argmax(shares))
    for k in range(len(cands)):
        if 0 < shares[k] < MIN_SHARE:
            label[label == k] = big
    return label


def refine_boundaries(
    lum: np.ndarray,
    noise: np.ndarray,
    label: np.ndarray,
    vels: np.ndarray,
    centres: np.ndarray,
) -> np.ndarray:
    """Full-resolution labels in a band about the layer boundaries of the working grid.

    The working grid's labels, upsampled, put each boundary up to a few pixels off (a
    cell is several pixels, and the pooled evidence of a point near a boundary mixes in
    its neighbours across it), and each mislabelled pixel of a moving edge smears it over
    the whole path. Within :data:`BOUNDARY_BAND_PX` of a boundary the track evidence of
    every layer is recomputed from the full-resolution bins, pooled over a small
    Gaussian (:data:`BOUNDARY_SIGMA_PX`), and each pixel takes the layer with the most
    evidence, its working-grid layer favoured by :data:`BOUNDARY_PRIOR_NATS`; a 3 x 3
    median then removes isolated pixels. Only a crop about the band is resampled.
    """
    import cv2

    lab8 = label.astype(np.uint8)
    box = np.ones((3, 3), np.uint8)
    edge = cv2.dilate(lab8, box) != cv2.erode(lab8, box)
    if not edge.any():
        return label
    r = BOUNDARY_BAND_PX
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    band = cv2.dilate(edge.astype(np.uint8), disc) > 0
    h, w = label.shape
    ys, xs = np.nonzero(band)
    pad = int(np.ceil(float(np.max(np.hypot(vels[:, 0], vels[:, 1]))) * float(np.max(centres)))) + 2
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
    crop = (slice(None), slice(y0, y1), slice(x0, x1))
    lv, slv = log_frames(lum[crop], noise[crop])
    sub = label[y0:y1, x0:x1]
    llr = np.zeros((len(vels), *sub.shape), np.float32)
    for k in range(1, len(vels)):
        llr[k] = cv2.GaussianBlur(track_score(lv, slv, vels[k], centres), (0, 0), BOUNDARY_SIGMA_PX)
    for k in range(len(vels)):
        llr[k][sub == k] += np.float32(BOUNDARY_PRIOR_NATS)
    fine = cv2.medianBlur(np.argmax(llr, axis=0).astype(np.uint8), 3).astype(np.int32)
    out = label.copy()
    inband = band[y0:y1, x0:x1]
    out[y0:y1, x0:x1][inband] = fine[inband]
    return out


def merge_alike(label: np.ndarray, cands: list[np.ndarray]) -> tuple[np.ndarray, list]:
    """Moving layers whose velocities differ by less than :data:`SAME_LAYER_PX_S` join the
    one of them with the most points; returns the relabelled map and the velocities."""
    sizes = np.bincount(label.ravel(), minlength=len(cands))
    into = np.arange(len(cands))
    kept: list[int] = []
    for k in sorted(range(1, len(cands)), key=lambda k: -sizes[k]):
        alike = [j for j in kept if np.hypot(*(cands[k] - cands[j])) < SAME_LAYER_PX_S]
        if alike:
            into[k] = alike[0]
        else:
            kept.append(k)
    keep = [0] + sorted(kept)
    number = np.zeros(len(cands), np.int32)
    number[keep] = np.arange(len(keep))
    return number[into[label]], [cands[k] for k in keep]


def kept_layers(label: np.ndarray, vels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The labels renumbered over the layers some pixel keeps, and those layers' velocities.

    ``label`` (H, W) holds indices into ``vels`` (K, 2): which are used is counted, and
    each pixel's new number looked up (not the labels sorted)."""
    counts = np.bincount(label.reshape(-1), minlength=len(vels))
    used = np.flatnonzero(counts)
    number = np.zeros(counts.size, np.int32)
    number[used] = np.arange(used.size, dtype=np.int32)
    return number[label], vels[used]
