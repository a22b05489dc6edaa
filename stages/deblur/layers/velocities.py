"""Candidate layer velocities: long-baseline flow votes, their modes, refinement."""

from __future__ import annotations

import numpy as np

from ...cluster import in_order
from .alignment import layer_cost, median0
from .bins import equalise_all

#: A mode must gather this share of the confident pixels to become a layer.
MIN_MODE_SHARE = 0.02
#: At most this many moving layers.
MAX_MOVING_LAYERS = 3
#: The velocity search (:func:`refine_velocity`) reads at most this many of a layer's
#: points, a fixed draw of them: each of its evaluations costs in proportion to the
#: points it reads, while a layer's alignment is as clear in this many as in all.
REFINE_POINTS = 32768


def refine_velocity(
    lv, slv, v0, centres, weight, steps=(1.0, 0.5, 0.25, 0.125, 0.0625), max_moves=8
) -> np.ndarray:
    """Pattern search for the velocity that best aligns the motion-compensated bins.

    The cost (:func:`layer_cost`, averaged with ``weight``) is evaluated on the 3 x 3
    neighbours of the current velocity at each step size, moving to the best until the
    centre is best (at most ``max_moves`` moves), then halving the step. Only the
    weighted points are resampled, in the bounding box of them (and their paths) cut
    out of the bins; at most :data:`REFINE_POINTS` of them, drawn with a fixed seed (the
    same velocity every run).
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
    # The cost at the weighted points alone (each point's is its own); at most
    # REFINE_POINTS of them, a fixed draw.
    points = np.nonzero(wt_c > 0)
    if points[0].size > REFINE_POINTS:
        keep = np.sort(
            np.random.default_rng(0).choice(points[0].size, REFINE_POINTS, replace=False)
        )
        points = (points[0][keep], points[1][keep])
    wt_p = wt_c[points]
    total = float(wt_p.sum())
    cache: dict[tuple[float, float], float] = {}

    def key(c: np.ndarray) -> tuple[float, float]:
        return (round(float(c[0]), 6), round(float(c[1]), 6))

    def costs(cands: list[np.ndarray]) -> list[float]:
        """The cost of each candidate; those not yet known on the process's threads."""
        todo = list({key(c): c for c in cands if key(c) not in cache}.values())

        def one(i: int) -> float:
            c = todo[i]
            cost = layer_cost(lv_c, slv_c, c, centres, trunc=25.0, points=points)
            return float((cost * wt_p).sum() / total)

        for c, val in zip(todo, in_order(one, len(todo)), strict=True):
            cache[key(c)] = val
        return [cache[key(c)] for c in cands]

    grid = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
    for st in steps:
        for _ in range(max_moves):
            vals = costs([v + st * np.array(d) for d in grid])
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

    from ...flow import _flow_pair, warp_residual

    frames = equalise_all(lv)
    nb, h, w = lv.shape
    pairs = [(0, b) for b in range(1, nb)] + [(b, nb - 1) for b in range(1, nb - 1)]
    snr = 1.0 / median0(slv)
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
    spread = np.sqrt(median0(np.sum((votes - vel[None]) ** 2, axis=3)))
    conf = conf / (1.0 + spread / 2.0)
    return votes, wts, vel.astype(np.float32), conf.astype(np.float32)


def velocity_modes(votes: np.ndarray, wts: np.ndarray, cell: float = 0.5) -> list[np.ndarray]:
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
