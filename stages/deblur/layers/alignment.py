"""Measuring bins resampled along a motion, and how well they agree there."""

from __future__ import annotations

import numpy as np


def compensated(
    lv: np.ndarray,
    v: np.ndarray,
    centres: np.ndarray,
    nearest: bool = False,
    at: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Bins resampled at ``y + v c_b`` (the scene point ``y`` of t = 0 in each bin).

    ``v`` is one velocity (2,) or a field of them (H, W, 2), px/s. ``nearest``: no
    interpolation, so the noise of the resampled bins does not depend on ``v`` (bilinear
    interpolation averages noise down at fractional shifts, which would favour moving
    layers in noise-dominated regions). ``at``: the points ``y`` as float32 coordinates
    ``(yy, xx)`` of one shape (of :func:`point_grid`'s; one velocity), each resampled as on
    the whole grid; by default every pixel, (B, H, W).
    """
    import cv2

    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    nb, h, w = lv.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) if at is None else at
    vx, vy = components(v)
    out = np.empty((nb, *yy.shape), lv.dtype)
    for b in range(nb):
        out[b] = cv2.remap(
            lv[b],
            xx + vx * np.float32(centres[b]),
            yy + vy * np.float32(centres[b]),
            interp,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out


def components(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` of one velocity (2,) or a field (H, W, 2), as float32."""
    v = np.asarray(v, np.float32)
    return v[..., 0], v[..., 1]


def _grid(v: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(yy, xx)``, float32: full (H, W) grids for a velocity field,
    a column (H, 1) and a row (1, W) for one velocity (what depends on ``x + v c`` is
    then computed once per row and column and broadcast, to the same values)."""
    if np.ndim(v) > 1:
        return tuple(np.mgrid[0:h, 0:w].astype(np.float32))
    return (
        np.arange(h, dtype=np.float32).reshape(h, 1),
        np.arange(w, dtype=np.float32).reshape(1, w),
    )


#: Points per row of :func:`point_grid` (OpenCV's remap takes maps under 32767 a side).
POINT_ROW = 4096


def point_grid(ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points ``(ys, xs)`` (P,) as index maps of shape (R, :data:`POINT_ROW`) or
    (1, P), in order, padded with the last point."""
    p = ys.size
    cols = min(p, POINT_ROW)
    rows = -(-p // cols)
    pad = rows * cols - p
    return tuple(np.concatenate([a, np.repeat(a[-1:], pad)]).reshape(rows, cols) for a in (ys, xs))


def median_where(a: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Median over axis 0 of the floats ``a`` (B, H, W) where ``valid`` (every value where
    None), 0 where none is.

    The value of ``np.nan_to_num(np.nanmedian(np.where(valid, a, np.nan), axis=0))`` (the
    mean of the two middle values for an even count; ``np.median(a, axis=0)`` with every
    value valid), from one sort of the B values of every point at once
    (:func:`sort_lanes`; with a NaN among the values, numpy's sort along axis 0).
    """
    count = np.int16 if a.shape[0] < 2**15 else np.int64  # (a short sum of the booleans)
    n = np.full(a.shape[1:], a.shape[0], count) if valid is None else valid.sum(0, dtype=count)
    if np.isnan(a).any():
        s = np.sort(a if valid is None else np.where(valid, a, np.nan), axis=0)  # NaN last
    else:  # (invalid values as +inf, last like NaN: the middle ones are the same)
        s = sort_lanes(a if valid is None else np.where(valid, a, np.inf))
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(s, np.maximum(n // 2 - (n == 0), 0)[None], axis=0)[0]
    return np.where(n > 0, (lo + hi) / a.dtype.type(2), 0).astype(a.dtype, copy=False)


def median0(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=0)`` of floats (B, ...), the same numbers, from one sort of
    every point's B values at once (:func:`median_where`; numpy's own where a value is
    NaN, which numpy's median propagates)."""
    if np.isnan(a).any():
        return np.median(a, axis=0)
    return median_where(a)


def _merge_pairs(n: int) -> list[tuple[int, int]]:
    """Compare-exchange pairs ``(i, j)``, ``i < j < n``, of Batcher's odd-even merge sort
    (on the next power of two; pairs that reach past ``n`` are left out: the missing
    values count as the largest, which those pairs would not move)."""
    size = 1
    while size < n:
        size *= 2
    pairs = []
    p = 1
    while p < size:
        k = p
        while k >= 1:
            for j in range(k % p, size - k, 2 * k):
                for i in range(min(k, size - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p) and i + j + k < n:
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return pairs


def sort_lanes(a: np.ndarray) -> np.ndarray:
    """``np.sort(a, axis=0)`` of a float array with no NaN, (B, ...): a sorting network on
    whole planes (a few elementwise minima and maxima per pair, fast for a small B where
    numpy sorts each short lane on its own)."""
    planes = list(np.array(a, copy=True))
    for i, j in _merge_pairs(len(planes)):
        lo = np.minimum(planes[i], planes[j])
        np.maximum(planes[i], planes[j], out=planes[j])
        planes[i] = lo
    return np.stack(planes) if planes else np.array(a, copy=True)


def inside(v: np.ndarray, centres: np.ndarray, h: int, w: int, sel=None) -> np.ndarray:
    """Per bin, the scene points whose compensated position lies in the image, (B, H, W);
    ``sel``: at those indices alone (one velocity), (B, *sel[0].shape), the same values
    (a point's row and column are each tested once for all the points)."""
    if sel is not None and np.ndim(v) > 1:
        raise ValueError("inside: points (sel) need one velocity, not a field")
    yy, xx = _grid(v, h, w)
    vx, vy = components(v)
    ok = np.empty((len(centres), *((h, w) if sel is None else sel[0].shape)), bool)
    for b, c in enumerate(centres):
        x = xx + vx * np.float32(c)
        y = yy + vy * np.float32(c)
        okx, oky = (x >= 0) & (x <= w - 1), (y >= 0) & (y <= h - 1)
        if sel is None:
            np.logical_and(oky, okx, out=ok[b])
        else:  # (1-D gathers of the row's and the column's tests)
            np.logical_and(oky.reshape(-1)[sel[0]], okx.reshape(-1)[sel[1]], out=ok[b])
    return ok


def track_score(lv, slv, v, centres, trunc=9.0):
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
    comp = compensated(lv, v, centres, True)
    sig = compensated(slv, v, centres, True)
    first = compensated(np.broadcast_to(lv[0], lv.shape), v, centres, True)
    sfirst = compensated(np.broadcast_to(slv[0], slv.shape), v, centres, True)
    h, w = lv.shape[1:]
    ins = inside(v, centres, h, w)
    moving = np.minimum((comp[1:] - comp[0]) ** 2 / (sig[1:] ** 2 + sig[0] ** 2), trunc)
    still = np.minimum((comp[1:] - first[1:]) ** 2 / (sig[1:] ** 2 + sfirst[1:] ** 2), trunc)
    ok = ins[1:] & ins[0]
    per_bin = np.where(ok, still - moving, 0.0).mean(axis=0).astype(np.float32)
    return per_bin * np.float32(0.5 * (len(centres) - 1))


def interpolation_noise(v: np.ndarray, centres: np.ndarray, h: int, w: int) -> np.ndarray:
    """Noise of bilinearly resampled bins relative to the samples', per bin, (B, H, W).

    A bilinear sample at fractional offsets ``(fx, fy)`` from its pixel is a weighted
    mean of four independent samples of equal noise, whose standard deviation is
    ``sqrt(((1 - fx)**2 + fx**2) ((1 - fy)**2 + fy**2))`` times theirs: 1 at whole-pixel
    shifts, 1/2 half-way between four pixels.
    """
    grid = _grid(v, h, w)
    out = np.empty((len(centres), h, w), np.float32)
    for b, c in enumerate(centres):
        out[b] = _noise_plane(grid, v, c)
    return out


def _noise_plane(grid: tuple[np.ndarray, np.ndarray], v: np.ndarray, c: float, sel=None):
    """:func:`interpolation_noise` of one bin at time ``c``, on ``grid`` (:func:`_grid`);
    ``sel``: at those indices alone (one velocity: its row and column factors read
    there)."""
    yy, xx = grid
    vx, vy = components(v)
    fx = np.mod(xx + vx * np.float32(c), np.float32(1.0))
    fy = np.mod(yy + vy * np.float32(c), np.float32(1.0))
    gx, gy = (1 - fx) ** 2 + fx**2, (1 - fy) ** 2 + fy**2
    if sel is not None:
        gy, gx = gy.reshape(-1)[sel[0]], gx.reshape(-1)[sel[1]]  # (1-D gathers: fast)
    return np.sqrt(gx * gy)


def layer_cost(lv, slv, v, centres, trunc=9.0, visible=None, points=None):
    """Per-point truncated chi-square of the compensated bins about their median, per bin.

    The bins are resampled bilinearly (a sharp edge moving a fractional number of pixels
    per bin stays aligned) and each residual is normalised by the noise of its resampled
    value (:func:`interpolation_noise`), so that noise scores alike whatever the shift:
    neither whole-pixel nor fractional velocities are favoured where the bins hold only
    noise. Only the bins in which the point is still inside the image (and ``visible``,
    (B, H, W) bool, if given) are evidence; each other bin counts as a consistent one
    (cost 1, the expectation of a chi-square term), so that a layer gains nothing from
    points it moves off the image or behind another layer. Returns (H, W) float32.

    ``points``: ``(ys, xs)`` integer arrays (P,) with one velocity ``v``: the cost at
    those points alone, (P,), the same numbers as at those pixels of the whole map (each
    point's cost is its own).

    Only the resampled bins are held whole (their median needs them); their noise and
    the residuals are made one bin at a time.
    """
    import cv2

    nb, h, w = lv.shape
    if points is None:
        at = sel = None
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)  # (compensated's maps)
    else:  # (what depends on the row or column alone: made for all, read at the points)
        sel = point_grid(*points)
        yy, xx = at = tuple(a.astype(np.float32) for a in sel)
    comp = compensated(lv, v, centres, at=at)
    ins = inside(v, centres, h, w, sel)
    if visible is not None:
        ins &= visible
    med = median_where(comp, None if ins.all() else ins)
    grid = _grid(v, h, w)
    vx, vy = components(v)
    cost = None
    for b, c in enumerate(centres):
        c32 = np.float32(c)
        sig = cv2.remap(
            slv[b], xx + vx * c32, yy + vy * c32, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        sig *= _noise_plane(grid, v, c, sel)
        z2 = comp[b] - med
        z2 /= sig
        z2 *= z2
        np.minimum(z2, np.float32(trunc), out=z2)
        z2 = np.where(ins[b], z2, np.float32(1.0))
        if cost is None:
            cost = z2
        else:
            cost += z2
    cost = np.true_divide(cost, nb, out=cost, casting="unsafe")
    return cost if points is None else cost.reshape(-1)[: points[0].size]
