"""Layered motion estimation from the measuring images.

The motion model of the deblur is a few rigid layers, each translating at a constant
velocity over the 1 s frame (a still background, moving objects, or one global
translation): see :class:`stages.deblur.operator.Layers`. Dense optical flow between two
short, noisy measuring bins gives a noisy per-pixel velocity in the dark, and the
deblur's accuracy is limited by it; a layered model pools every pixel of a layer into
two numbers, so it is far more accurate where the model holds. The estimate:

1. **Long baselines.** Optical flow (Farnebäck or DIS) from the first measuring bin to
   every later bin, on the log-compressed, equalised bins of :mod:`stages.flow`; each
   flow is a displacement ``u (c_b - c_0)`` (``c_b`` the bin centres), so a per-pixel
   velocity is the least-squares fit of displacement against time over all pairs (long
   baselines dominate, as they should: their displacement is least affected by the flow's
   fixed error). Each long-baseline flow is also started from the displacement the
   shorter baseline before it predicts, and each pixel keeps whichever flow better
   explains the pair (a displacement of a sizeable share of the frame is beyond the
   flow's pyramid on its own). A pixel's confidence is its signal-to-noise ratio times
   texture times the agreement of the pairs.
2. **Modes.** The confident velocities vote in a 2-D histogram (0.5 px/s cells); its
   peaks are the candidate layer velocities (a peak must hold a minimum share of the
   confident pixels); zero velocity is always a candidate.
3. **Refinement.** Each candidate's velocity is refined to sub-pixel-per-second
   precision by maximising the agreement of the motion-compensated bins (every bin
   sampled at ``y + v c_b`` should show the same scene point ``y``) over the pixels that
   voted for it, weighted by their signal-to-noise ratio (coarse-to-fine grid search);
   after the first assignment, again over each layer's interior. Moving layers then
   closer than :data:`SAME_LAYER_PX_S` are one layer.
4. **Assignment.** Each scene point at t = 0 takes the moving layer with the most
   evidence that the pixels along its path show it (:func:`_track_score`, a likelihood
   ratio against stillness pooled over a small neighbourhood); points without clear
   evidence (:data:`EVIDENCE_NATS`) are tested again over wider neighbourhoods
   (:data:`POOL_SIGMAS`, the threshold falling with the noise of the pooled mean), so
   that a dark, faintly textured moving region is found; points clear at no scale take
   a default layer (the still one if the scene has clearly still parts, else the moving
   layer most points clearly follow: a global motion); the label map is then cleaned
   with a median filter. A layer slower than :data:`MIN_SPEED_PX_S` is still; one
   that keeps under 1% of the points is merged into the largest.
   Limitation: the evidence is in the measuring bins only. (The VET image alone cannot
   tell: a pixel exposed the whole frame gathers the light of the sum of its bins,
   whatever the motion; it could serve as a low-noise reference for the bins, but their
   read noise remains.) Where a bin's read noise swamps the texture
   (``builtin:interior``'s dark wall gathers a few electrons per pixel and bin against
   about 20 e- of read noise), no scale makes it clear, and the moving points there
   stay with the default (still) layer: 63% of the points of the object
   ``80,64,160,128`` on a 320x256 interior, 88% of the same object placed at ``0,128``
   and all of it at ``160,0``, where no part of it is lit enough for its velocity to be
   found (``make bench``, bench_layers).
   Lower thresholds (tried: a control velocity's evidence subtracted, four standard
   errors of the pooled mean) found them but also labelled still floor as moving.
5. **Boundaries at full resolution.** Where the working grid is coarser than the
   capture, the labels within :data:`BOUNDARY_BAND_PX` of a layer boundary are decided
   again from the full-resolution bins (:func:`_refine_boundaries`): on the moving
   objects of Desk, GoldenGate, Bonita and Cannon this cuts the share of the frame with
   the wrong layer by 34-76%, to 0.14-1.51% (``make bench``, bench_layers; CandleGlass's
   2.7% and 14.2% lie on its flat black background, where motion changes nothing).

6. **Model check.** A rotation, a zoom or a non-rigid motion is no set of translating
   layers: the estimate then settles on the translation that fits best, and deblurring
   along it is worse than not deblurring. :func:`layered_model_check` scores the layers
   (with their occlusions), the smoothed dense long-baseline field and no motion by how
   well the bins agree along them; where the dense field explains a clear share of what
   the layers miss (:data:`LAYERED_MISS_SHARE`), the estimate says so (``check.fits``)
   and deblur starts from dense flow instead (:func:`stages.deblur.start_motion`). On
   the shared scenes' still captures, translations and objects the share is at most
   0.007, on rotations 0.28 to 0.65. Deblur of ``rotate:4`` on the four shared scenes
   with dark pixels (half size) then comes within 1.06-1.17x of deblur from the true
   motion over dark pixels, against 1.6-3.0x from the layers; on Cannon (no dark pixel)
   1.38x over all pixels, against 6.4x (``make bench``: bench_layers,
   bench_motion_models).

The result is a velocity field with a handful of distinct values that
:func:`stages.deblur.operator.blur_matrix` reads as layers with occlusion.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..formats.capture import Capture

log = logging.getLogger(__name__)

#: Layers slower than this (px/s: under one pixel of travel in a 1 s frame) are still.
MIN_SPEED_PX_S = 1.0
#: A mode must gather this share of the confident pixels to become a layer.
MIN_MODE_SHARE = 0.04
#: At most this many moving layers.
MAX_MOVING_LAYERS = 3
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
#: Estimation runs on images no larger than this (longer side, pixels).
MAX_WORK_PX = 400
#: Full-resolution pixels about a working-grid layer boundary whose labels are decided
#: again from the full-resolution bins.
BOUNDARY_BAND_PX = 8
#: Gaussian (full-resolution px) over which that evidence is pooled.
BOUNDARY_SIGMA_PX = 1.5
#: Evidence (nats) by which a pixel's working-grid layer is favoured there.
BOUNDARY_PRIOR_NATS = 1.0
#: The layered model is rejected when the dense long-baseline field explains this share
#: (or more) of what motion explains in the bins that the layers leave unexplained
#: (:func:`layered_model_check`).
LAYERED_MISS_SHARE = 0.1
#: ... and when motion explains at least this much of the bins at all (mean truncated
#: chi-square per bin and point, confidence-weighted; a still scene explains nothing).
LAYERED_MIN_GAIN = 0.05
#: Gaussian (working-grid px) of the confidence-weighted smoothing of the dense field.
DENSE_SMOOTH_PX = 2.0


@dataclass
class ModelCheck:
    """How well motion fields explain the measuring bins (:func:`layered_model_check`).

    Costs are confidence-weighted means of the truncated chi-square of the motion-
    compensated bins about their median, per bin and point (about 0.85 where the bins
    hold only noise); lower explains the bins better.
    """

    zero: float  # no motion
    layered: float  # the layered estimate
    dense: float  # the smoothed dense long-baseline field
    missed_share: float  # (layered - dense) / (zero - dense): what the layers miss
    fits: bool  # the layered model stands (else a dense field describes the motion)


@dataclass
class LayerEstimate:
    """Output of :func:`estimate_layers`."""

    velocity: np.ndarray  # (H, W, 2) px/s, few distinct values
    layer_velocities: np.ndarray  # (K, 2)
    label: np.ndarray  # (H, W) int
    dense: np.ndarray  # (H, W, 2) the per-pixel long-baseline fit
    confidence: np.ndarray  # (H, W)
    check: ModelCheck | None = None  # does the layered model explain the bins?


def _rate_frames(cap: Capture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Luminance rate of each measuring bin (B, H, W), its noise, and validity."""
    from ..flow import measure_rates

    rate, sigma, valid = measure_rates(cap)
    lum = rate.mean(axis=3)
    noise = sigma.mean(axis=3) / np.float32(np.sqrt(rate.shape[3]))
    return lum, noise, valid


def _log_frames(lum: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log rates and their noise in log units (first order)."""
    floor = np.median(noise, axis=0)
    pos = np.maximum(lum, 0) + floor
    lv = np.log(pos).astype(np.float32)
    # Floored so that very bright pixels do not get infinite weight (flow and
    # interpolation errors dominate there).
    slv = np.maximum(noise / pos, 0.02).astype(np.float32)
    return lv, slv


def _work_frames(lum: np.ndarray, noise: np.ndarray, valid: np.ndarray, max_px: int):
    """Log-rate bins, their noise in log units and validity, at a working scale."""
    import cv2

    nb, h, w = lum.shape
    scale = min(1.0, max_px / max(h, w))
    if scale < 1.0:
        size = (max(8, int(round(w * scale))), max(8, int(round(h * scale))))
        lum = np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in lum])
        noise = np.stack(
            [cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in noise]
        ) * np.float32(scale)
        valid = np.stack(
            [
                cv2.resize(v.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
                for v in valid
            ]
        )
        scale_xy = (size[0] / w, size[1] / h)
    else:
        scale_xy = (1.0, 1.0)
    lv, slv = _log_frames(lum, noise)
    return lv, slv, valid, scale_xy


def _equalise_all(lv: np.ndarray) -> list[np.ndarray]:
    import cv2

    from ..flow import _equalise

    sample = lv[:, ::2, ::2].ravel()
    levels = np.unique(np.quantile(sample, np.linspace(0, 1, 257)))
    if len(levels) < 2:
        levels = np.array([float(sample.min()), float(sample.min()) + 1.0])
    return [_equalise(cv2.GaussianBlur(f, (0, 0), 1.0), levels) for f in lv]


def _compensated(
    lv: np.ndarray, v: np.ndarray, centres: np.ndarray, nearest: bool = False
) -> np.ndarray:
    """Bins resampled at ``y + v c_b`` (the scene point ``y`` of t = 0 in each bin).

    ``v`` is one velocity (2,) or a field of them (H, W, 2), px/s. ``nearest``: no
    interpolation, so the noise of the resampled bins does not depend on ``v`` (bilinear
    interpolation averages noise down at fractional shifts, which would favour moving
    layers in noise-dominated regions).
    """
    import cv2

    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    nb, h, w = lv.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    vx, vy = _components(v)
    out = np.empty_like(lv)
    for b in range(nb):
        out[b] = cv2.remap(
            lv[b],
            xx + vx * np.float32(centres[b]),
            yy + vy * np.float32(centres[b]),
            interp,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out


def _components(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` of one velocity (2,) or a field (H, W, 2), as float32."""
    v = np.asarray(v, np.float32)
    return v[..., 0], v[..., 1]


def _inside(v: np.ndarray, centres: np.ndarray, h: int, w: int) -> np.ndarray:
    """Per bin, the scene points whose compensated position lies in the image, (B, H, W)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    vx, vy = _components(v)
    ok = np.empty((len(centres), h, w), bool)
    for b, c in enumerate(centres):
        x = xx + vx * np.float32(c)
        y = yy + vy * np.float32(c)
        ok[b] = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return ok


def _track_score(lv, slv, v, centres, trunc=9.0):
    """Evidence (log-likelihood ratio, nats) that a scene point at t = 0 moves with ``v``.

    Follow the point ``y`` of t = 0 along ``v``: in bin ``b`` the pixel ``x = y + v c_b``
    shows, if ``y`` moves with ``v``, the point ``y`` (its appearance in the first bin, at
    ``y + v c_0``); if ``y`` is still, the pixel ``x`` is not on its path and keeps showing
    what it showed in the first bin. Both hypotheses predict the same observation, so the
    difference of their noise-normalised, truncated squared residuals is the evidence.
    The test is local and needs no knowledge of the other points' layers: a background
    point that an object covers later scores still (the pixels ahead of it do not change),
    an object point scores moving even where the object uncovers its own position.
    Bins in which the path has left the image give no evidence (0). The ratio is half the
    summed difference over the ``B - 1`` later bins.
    """
    comp = _compensated(lv, v, centres, True)
    sig = _compensated(slv, v, centres, True)
    first = _compensated(np.broadcast_to(lv[0], lv.shape), v, centres, True)
    sfirst = _compensated(np.broadcast_to(slv[0], slv.shape), v, centres, True)
    h, w = lv.shape[1:]
    ins = _inside(v, centres, h, w)
    moving = np.minimum((comp[1:] - comp[0]) ** 2 / (sig[1:] ** 2 + sig[0] ** 2), trunc)
    still = np.minimum((comp[1:] - first[1:]) ** 2 / (sig[1:] ** 2 + sfirst[1:] ** 2), trunc)
    ok = ins[1:] & ins[0]
    per_bin = np.where(ok, still - moving, 0.0).mean(axis=0).astype(np.float32)
    return per_bin * np.float32(0.5 * (len(centres) - 1))


def _layer_cost(lv, slv, v, centres, trunc=9.0, nearest=True, visible=None):
    """Per-point truncated chi-square of the compensated bins about their median, per bin.

    Only the bins in which the point is still inside the image (and ``visible``, (B, H,
    W) bool, if given) are evidence; each other bin counts as a consistent one (cost 1,
    the expectation of a chi-square term), so that a layer gains nothing from points it
    moves off the image or behind another layer.
    """
    comp = _compensated(lv, v, centres, nearest)
    sig = _compensated(slv, v, centres, nearest)
    h, w = lv.shape[1:]
    ins = _inside(v, centres, h, w)
    if visible is not None:
        ins &= visible
    if ins.all():
        med = np.median(comp, axis=0)
    else:
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nan_to_num(np.nanmedian(np.where(ins, comp, np.nan), axis=0))
    z2 = np.minimum(((comp - med[None]) / sig) ** 2, trunc)
    cost = np.where(ins, z2, 1.0).mean(axis=0)
    return cost.astype(np.float32)


def _refine(
    lv, slv, v0, centres, weight, steps=(1.0, 0.5, 0.25, 0.125, 0.0625), max_moves=8
) -> np.ndarray:
    """Pattern search for the velocity that best aligns the motion-compensated bins.

    The cost (:func:`_layer_cost`, averaged with ``weight``) is evaluated on the 3 x 3
    neighbours of the current velocity at each step size, moving to the best until the
    centre is best (at most ``max_moves`` moves), then halving the step. Only the
    bounding box of the weighted points is resampled.
    """
    v = np.asarray(v0, np.float64)
    if weight.sum() <= 0:
        return v
    ys, xs = np.nonzero(weight > 0)
    pad = int(np.ceil(np.hypot(*v) * float(np.max(centres)))) + 8
    h, w = weight.shape
    y0, y1 = max(0, ys.min() - pad), min(h, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(w, xs.max() + pad + 1)
    lv_c, slv_c, wt_c = lv[:, y0:y1, x0:x1], slv[:, y0:y1, x0:x1], weight[y0:y1, x0:x1]
    total = float(wt_c.sum())
    cache: dict[tuple[float, float], float] = {}

    def cost(c: np.ndarray) -> float:
        key = (round(float(c[0]), 6), round(float(c[1]), 6))
        if key not in cache:
            cache[key] = float(
                (_layer_cost(lv_c, slv_c, c, centres, trunc=25.0, nearest=False) * wt_c).sum()
                / total
            )
        return cache[key]

    grid = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
    for st in steps:
        for _ in range(max_moves):
            vals = [cost(v + st * np.array(d)) for d in grid]
            dx, dy = grid[int(np.argmin(vals))]
            if dx == 0 and dy == 0:
                break
            v = v + st * np.array([dx, dy])
    return v


def dense_long_baseline(lv: np.ndarray, slv: np.ndarray, centres: np.ndarray, method: str = "dis"):
    """Velocity votes from flows over long baselines, and a per-pixel least-squares fit.

    Flows run from the first bin to every later one and from every bin to the last (in
    the earlier bin's coordinates), each pair computed twice: from scratch, and started
    from the displacement its predecessor's velocity predicts for its baseline (a moving
    object's long-baseline displacement can be far beyond what the flow's pyramid finds
    on its own: 30 px on a 128 px image); each pixel keeps the flow that better explains
    the pair (:func:`stages.flow.warp_residual`). Returns ``votes`` (P, H, W, 2) px/s with
    weights ``(P, H, W)`` (confidence times baseline), the per-pixel fit of the flows from the
    first bin (H, W, 2), and the per-pixel confidence (H, W).
    """
    import cv2

    from ..flow import _flow_pair, warp_residual

    frames = _equalise_all(lv)
    nb, h, w = lv.shape
    pairs = [(0, b) for b in range(1, nb)] + [(b, nb - 1) for b in range(1, nb - 1)]
    snr = 1.0 / np.median(slv, axis=0)
    base = lv.mean(axis=0).astype(np.float32)
    gx = cv2.Sobel(base, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(base, cv2.CV_32F, 0, 1)
    texture = np.hypot(gx, gy)
    conf = ((snr / (snr + 5.0)) * (texture / (texture + 0.2))).astype(np.float32)
    votes = np.empty((len(pairs), h, w, 2), np.float32)
    wts = np.empty((len(pairs), h, w), np.float32)
    for i, (a, b) in enumerate(pairs):
        dt = np.float32(centres[b] - centres[a])
        flow = _flow_pair(frames[a], frames[b], method)
        if i > 0:
            predicted = np.dstack([cv2.medianBlur(votes[i - 1][..., c], 5) for c in (0, 1)])
            guided = _flow_pair(frames[a], frames[b], method, init=predicted * dt)
            better = warp_residual(frames[a], frames[b], guided) < warp_residual(
                frames[a], frames[b], flow
            )
            flow[better] = guided[better]
        votes[i] = flow / dt
        wts[i] = conf * dt
    first = votes[: nb - 1]
    dts = (centres[1:] - centres[0]).reshape(-1, 1, 1, 1)
    vel = (first * dts**2).sum(axis=0) / float(np.sum(dts**2))
    spread = np.sqrt(np.median(np.sum((votes - vel[None]) ** 2, axis=3), axis=0))
    conf = conf / (1.0 + spread / 2.0)
    return votes, wts, vel.astype(np.float32), conf.astype(np.float32)


def _modes(votes: np.ndarray, wts: np.ndarray, cell: float = 0.5) -> list[np.ndarray]:
    """Peaks of the weighted histogram of velocity votes."""
    import cv2

    sel = wts > np.percentile(wts, 50)
    u = votes[sel]
    c = wts[sel]
    if u.size == 0:
        return []
    vmax = float(np.percentile(np.abs(u), 99.5)) + 4.0
    nbin = int(np.ceil(2 * vmax / cell)) + 1
    edges = np.linspace(-vmax, vmax, nbin + 1)
    hist, _, _ = np.histogram2d(u[:, 0], u[:, 1], bins=[edges, edges], weights=c)
    hist = cv2.GaussianBlur(hist.astype(np.float32), (0, 0), 1.5)
    total = float(hist.sum())
    centres = 0.5 * (edges[:-1] + edges[1:])
    out = []
    radius = max(2, int(round(3.0 / cell)))
    for _ in range(MAX_MOVING_LAYERS + 1):
        i, j = np.unravel_index(int(np.argmax(hist)), hist.shape)
        lo_i, hi_i = max(0, i - radius), i + radius + 1
        lo_j, hi_j = max(0, j - radius), j + radius + 1
        mass = float(hist[lo_i:hi_i, lo_j:hi_j].sum())
        if total <= 0 or mass < MIN_MODE_SHARE * total:
            break
        out.append(np.array([centres[i], centres[j]]))
        hist[lo_i:hi_i, lo_j:hi_j] = 0
    return out


def _assign(
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
    # cannot carry a flat neighbourhood. Points clear at no scale take a default layer:
    # the still one where the scene has clearly still parts, else (a global motion)
    # the moving layer most points clearly follow.
    raw = [_track_score(lv, slv, v, centres) for v in cands[1:]]
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
        if 0 < shares[k] < 0.01:
            label[label == k] = big
    return label


def _refine_boundaries(
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
    lv, slv = _log_frames(lum[crop], noise[crop])
    sub = label[y0:y1, x0:x1]
    llr = np.zeros((len(vels), *sub.shape), np.float32)
    for k in range(1, len(vels)):
        llr[k] = cv2.GaussianBlur(
            _track_score(lv, slv, vels[k], centres), (0, 0), BOUNDARY_SIGMA_PX
        )
    for k in range(len(vels)):
        llr[k][sub == k] += np.float32(BOUNDARY_PRIOR_NATS)
    fine = cv2.medianBlur(np.argmax(llr, axis=0).astype(np.uint8), 3).astype(np.int32)
    out = label.copy()
    inband = band[y0:y1, x0:x1]
    out[y0:y1, x0:x1][inband] = fine[inband]
    return out


def _merge_alike(label: np.ndarray, cands: list[np.ndarray]) -> tuple[np.ndarray, list]:
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


def _kept_layers(label: np.ndarray, vels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The labels renumbered over the layers some pixel keeps, and those layers' velocities."""
    used = np.unique(label)
    return np.searchsorted(used, label).astype(np.int32), vels[used]


def _visible(label: np.ndarray, vels: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Per bin, whether each scene point of t = 0 is in front at its position, (B, H, W).

    The blur operator's own reading of the layers decides
    (:func:`stages.deblur.operator.motion_layers`, whose front-most covering layer a
    pixel sees): the point ``y`` of layer ``k`` is at the pixel ``x = y + v_k c_b`` in
    bin ``b`` and is seen there if that pixel then shows ``y``, not a point of a layer
    in front of it.
    """
    from .operator import _layered_positions, motion_layers

    h, w = label.shape
    field = np.asarray(vels, np.float32)[label]
    vis = np.ones((len(centres), h, w), bool)
    layers = motion_layers(field)
    if layers is None or not layers.front:  # one layer: nothing hides anything
        return vis
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    for b, c in enumerate(centres):
        px = np.rint(xx + field[..., 0] * c)
        py = np.rint(yy + field[..., 1] * c)
        sx, sy = _layered_positions(layers, px, py, np.full((h, w), float(c)), h, w)
        vis[b] = (np.abs(sx - xx) <= 0.5 + 1e-6) & (np.abs(sy - yy) <= 0.5 + 1e-6)
    return vis


def layered_model_check(
    lv: np.ndarray,
    slv: np.ndarray,
    label: np.ndarray,
    vels: np.ndarray,
    dense: np.ndarray,
    conf: np.ndarray,
    centres: np.ndarray,
) -> ModelCheck:
    """Does the layered motion explain the bins as well as a dense field does?

    The layered model (a few rigidly translating layers) cannot describe a rotation, a
    zoom or a non-rigid motion: there it settles on the one translation that fits best
    and deblurs along wrong paths, which is worse than not deblurring (``rotate:6`` on a
    320x256 interior: dark RMS 0.70 stops against hdr-static's 0.65). The dense
    long-baseline field follows any smooth motion, noisily. Both fields (and no motion)
    are scored by how well the bins, resampled along them, agree
    (:func:`_layer_cost`, nearest-neighbour so that noise scores alike under every
    field), averaged over the confident points away from the border (points whose paths
    leave the image are scored by neither). The layered model is rejected when the
    dense field explains at least :data:`LAYERED_MISS_SHARE` of the motion's effect that
    the layers miss, ``(layered - dense) / (zero - dense)``, and motion explains at
    least :data:`LAYERED_MIN_GAIN` at all. On layered motions the share is at most
    0.007 (the shared scenes' still captures, translations and objects); on rotations it
    is 0.28 or more (``make bench``: bench_layers, bench_motion_models).

    The layered field is scored with its occlusions (a point hidden behind a layer in
    front of it is no evidence, :func:`_visible`), as the blur operator models them; the
    dense field, which cannot describe them, is scored on every bin.

    ``label`` (H, W) and ``vels`` (K, 2) are the layers, ``dense`` an (H, W, 2) field and
    ``conf`` (H, W) weights, all on the grid of ``lv``.
    """
    from ..flow import smooth_by_confidence

    vels = np.asarray(vels, np.float32)
    layered = vels[label]
    smooth = smooth_by_confidence(dense, conf, DENSE_SMOOTH_PX, min_weight=1e-6)
    reach = max(float(np.abs(layered).max()), float(np.abs(smooth).max())) * float(np.max(centres))
    band = int(np.ceil(reach)) + 2
    wt = np.zeros_like(conf, dtype=np.float64)
    h, w = conf.shape
    if h > 2 * band and w > 2 * band:
        wt[band : h - band, band : w - band] = conf[band : h - band, band : w - band]
    if wt.sum() <= 0:
        return ModelCheck(0.0, 0.0, 0.0, 0.0, True)
    wt /= wt.sum()

    def cost(field: np.ndarray, visible: np.ndarray | None = None) -> float:
        per_point = _layer_cost(lv, slv, field, centres, trunc=25.0, visible=visible)
        return float((per_point * wt).sum())

    zero = cost(np.zeros(2))
    lay, den_cost = cost(layered, _visible(label, vels, centres)), cost(smooth)
    gain = zero - den_cost
    share = (lay - den_cost) / gain if gain > 0 else 0.0
    fits = not (gain >= LAYERED_MIN_GAIN and share >= LAYERED_MISS_SHARE)
    return ModelCheck(zero, lay, den_cost, float(share), fits)


def estimate_layers(cap: Capture) -> LayerEstimate:
    """Layered velocity field of a capture (see the module docstring)."""
    import cv2

    h, w = cap.shape
    lum, noise, valid_full = _rate_frames(cap)
    lv, slv, valid, (sx, sy) = _work_frames(lum, noise, valid_full, MAX_WORK_PX)
    hw, ww = lv.shape[1:]
    centres = cap.measure_times.mean(axis=1).astype(np.float64)
    votes, wts, vel_d, conf = dense_long_baseline(lv, slv, centres)
    ok = valid.all(axis=0)
    conf_raw = np.median(wts, axis=0) * ok
    conf = conf * ok
    modes = _modes(votes, wts * ok[None])
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
        v = _refine(lv, slv, m, centres, wgt)
        if np.hypot(*v) >= MIN_SPEED_PX_S and all(
            np.hypot(*(v - c)) > SAME_LAYER_PX_S for c in cands[1:]
        ):
            cands.append(v)
    label = np.zeros((hw, ww), np.int32)
    if len(cands) > 1:
        label = _assign(lv, slv, cands, centres)
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
                    cands[k] = _refine(
                        lv,
                        slv,
                        cands[k],
                        centres,
                        (conf_raw * inner).astype(np.float64),
                        steps=(0.25, 0.125, 0.0625),
                    )
            n_before = len(cands)
            label, cands = _merge_alike(label, cands)
            if len(cands) == n_before:
                break
        if len(cands) > 1:  # (no point kept a moving layer: the scene is still)
            label = _assign(lv, slv, cands, centres)
    check = layered_model_check(lv, slv, label, np.asarray(cands), vel_d, conf, centres)
    log.debug("layers: model check %s", check)
    # Back to the full grid: nearest-neighbour labels, velocities rescaled.
    lab_full = cv2.resize(label.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(
        np.int32
    )
    vels = np.array([[v[0] / sx, v[1] / sy] for v in cands], np.float32)
    lab_full, vels = _kept_layers(lab_full, vels)
    if len(vels) > 1 and (sx < 1.0 or sy < 1.0):
        lab_full, vels = _kept_layers(_refine_boundaries(lum, noise, lab_full, vels, centres), vels)
    velocity = vels[lab_full]
    dense = np.stack(
        [cv2.resize(vel_d[..., 0] / sx, (w, h)), cv2.resize(vel_d[..., 1] / sy, (w, h))], -1
    )
    confidence = cv2.resize(conf, (w, h))
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
