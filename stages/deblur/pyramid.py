"""The deblur problem one level coarser: 2 x 2 pixel blocks, for a coarse-to-fine solve.

A coarse pixel observes the sum of its four children's data, so its row of the blur
operator is the sum of their rows. With the scene piecewise constant on the blocks (the
prolongation of the coarse unknown) and the children's trajectories started at the
block centre (half a coarse pixel away at most), that sum is one trajectory with a
time-varying weight: all four children open until the first of them closes, then
three, ... and leaking after the last. Those are the windows of :func:`block_windows`,
exact up to the children's sub-block offsets; the noise variances of the children add.
The coarse unknown is the block's mean rate, so the coarse solution is directly a start
for the fine level (:func:`prolong_correction`).
"""

from __future__ import annotations

import numpy as np

from .operator import Window
from .problem import Observations


def _blocks(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(H, W, ...)`` cropped to even size and split into ``(H/2, W/2, 4, ...)``."""
    h2, w2 = h // 2, w // 2
    a = a[: 2 * h2, : 2 * w2]
    a = a.reshape(h2, 2, w2, 2, *a.shape[2:])
    a = np.moveaxis(a, 2, 1)  # (h2, w2, 2, 2, ...)
    return a.reshape(h2, w2, 4, *a.shape[4:])


def block_sum(a: np.ndarray) -> np.ndarray:
    """Sum over 2 x 2 blocks of ``(H, W, ...)`` (odd last row/column dropped), in the
    children's row-major order; integers and booleans are counted in int64."""
    h2, w2 = a.shape[0] // 2, a.shape[1] // 2
    if a.dtype.kind in "biu":
        a = a.astype(np.int64)
    out = a[0 : 2 * h2 : 2, 0 : 2 * w2 : 2] + a[0 : 2 * h2 : 2, 1 : 2 * w2 : 2]
    out += a[1 : 2 * h2 : 2, 0 : 2 * w2 : 2]
    out += a[1 : 2 * h2 : 2, 1 : 2 * w2 : 2]
    return out


def block_sum_matrix(h: int, w: int):
    """:func:`block_sum` of an (H, W) image as a scipy CSR matrix (H/2 W/2, H W) float32
    (its transpose is the piecewise-constant prolongation)."""
    import scipy.sparse as sp

    h2, w2 = h // 2, w // 2
    yy, xx = np.mgrid[0 : 2 * h2, 0 : 2 * w2]
    rows = (yy // 2) * w2 + xx // 2
    cols = yy * w + xx
    ones = np.ones(rows.size, np.float32)
    return sp.csr_matrix((ones, (rows.ravel(), cols.ravel())), shape=(h2 * w2, h * w))


def block_windows(T: np.ndarray, frame_s: float, leakage: float) -> list[Window]:
    """Windows of a block's summed row: weight ``(open children) + eps (closed ones)``."""
    t = np.sort(_blocks(np.asarray(T, np.float64), T.shape[0], T.shape[1]), axis=2)
    wins = []
    start: np.ndarray | float = 0.0
    for k in range(4):
        wins.append(Window(start, t[..., k], float(4 - k) + k * float(leakage)))
        start = t[..., k]
    wins.append(Window(start, float(frame_s), 4.0 * float(leakage)))
    return wins


def coarsen(
    obs: Observations, T: np.ndarray, frame_s: float, leakage: float
) -> tuple[Observations, np.ndarray]:
    """The coarse problem of ``obs`` and its exposure time (block mean), see the module."""
    h, w, c = obs.shape
    h2, w2 = h // 2, w // 2

    def var_sum(wt: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        with np.errstate(divide="ignore"):
            var = np.where(wt > 0, 1.0 / np.where(wt > 0, wt, 1.0), np.inf).reshape(shape)
        s = block_sum(var)
        return np.where(np.isfinite(s), 1.0 / s, 0.0)

    y = block_sum(obs.y.reshape(h, w, c)).reshape(h2 * w2, c)
    wt = var_sum(obs.w, (h, w, c)).reshape(h2 * w2, c)
    yb = wb = None
    wins_b: list[list[Window]] = []
    sampling = None
    if obs.yb is not None:
        nb = len(obs.windows_b)
        # The bins' own grid: the VET grid, or a camera's (2 x 2 blocks of it, sampling
        # the coarse image as its fine pixels sample the coarse pixels' children).
        hm, wm = (h, w) if obs.sampling is None else obs.meas_shape
        yb4 = obs.yb.reshape(nb, hm, wm, c)
        wb4 = obs.wb.reshape(nb, hm, wm, c)
        m2 = (hm // 2) * (wm // 2)
        yb = np.concatenate([block_sum(yb4[b]).reshape(m2, c) for b in range(nb)])
        wb = np.concatenate([var_sum(wb4[b], (hm, wm, c)).reshape(m2, c) for b in range(nb)])
        if obs.sampling is not None:
            sampling = (block_sum_matrix(hm, wm) @ obs.sampling @ block_sum_matrix(h, w).T).tocsr()
        # A coarse bin pixel on the VET grid sums four children's rows; through a camera's
        # sampling the sum is the sampling's, of the prolonged (unsummed) blur.
        k = 4.0 if obs.sampling is None else 1.0
        wins_b = [
            [Window(win.start, win.end, k * np.asarray(win.weight)) for win in wins]
            for wins in obs.windows_b
        ]
    coarse = Observations(
        (h2, w2, c),
        y,
        wt,
        block_windows(T, frame_s, leakage),
        yb,
        wb,
        wins_b,
        sampling=sampling,
        meas_shape=None if sampling is None else (obs.meas_shape[0] // 2, obs.meas_shape[1] // 2),
    )
    t_mean = block_sum(np.asarray(T, np.float64)) / 4.0
    return coarse, t_mean.astype(np.float32)


def restrict_mean(img: np.ndarray) -> np.ndarray:
    """Block means of ``(H, W, ...)``."""
    return block_sum(img) / 4.0


def prolong_correction(correction: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A coarse ``(H/2, W/2, C)`` correction on the fine grid ``shape`` (bilinear)."""
    import cv2

    h, w = shape
    out = np.stack(
        [
            cv2.resize(
                correction[..., k].astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR
            )
            for k in range(correction.shape[2])
        ],
        -1,
    )
    return out.astype(np.float64)
