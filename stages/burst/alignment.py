"""The burst merge's tile alignment (Hasinoff et al. 2016, §4).

Each frame is aligned to the reference tile by tile, coarse to fine, on a Gaussian
pyramid of the frames' channel mean (:data:`PYRAMID_LEVELS` levels, each half the size
of the one below): at each level every :data:`TILE` x :data:`TILE` tile (stride
``TILE / 2``) searches :data:`SEARCH` pixels (1 at the finest, as the paper) around the
displacement the coarser level proposes (the best of its own and its two nearest
neighbours' upsampled proposals), minimising the sum of squared differences at the
coarse levels and of absolute differences at the finest, in whole pixels.

A tile whose best match is not clearly better than its average match
(:data:`CONFIDENT_COST`: no texture above the noise, a dark or flat tile) keeps the
displacement the coarser level proposed, and at the coarsest level the median of the
confident tiles' (departures from the paper, which aligns bright, well-exposed frames).

No step loops over tiles: a shift that many tiles of a level try costs one whole-image
difference (OpenCV) reduced to sums over half-tile blocks, and the few (tile, shift)
pairs of rarer shifts are scored together from strided views; the tiles then pick their
best shift together. (Correlating each tile's search window by FFT, as §4 suggests for
the coarse levels, costs more here: a level's candidates are few, so the whole-image
differences do little work the tiles do not need.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tile side (merge and alignment), pixels; tiles overlap by half.
TILE = 16
#: Search radius per pyramid level, pixels of that level.
SEARCH = 4
#: Pyramid levels for the alignment (each half the size of the one below).
PYRAMID_LEVELS = 4
#: A tile's alignment counts when its best cost is below this share of its mean cost.
CONFIDENT_COST = 0.7


def pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    """Gaussian pyramid of a (H, W) float32 image, finest first, down to a level under
    two tiles on a side or ``levels`` levels."""
    import cv2

    out = [img]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 2 * TILE:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def align(ref_pyr: list[np.ndarray], alt: np.ndarray) -> np.ndarray:
    """Per-tile whole-pixel displacement of ``alt`` onto the reference (module
    docstring): (n_ty, n_tx, 2) int64 as ``(dy, dx)``: the tile at ``y`` of the
    reference is at ``y + d`` in ``alt``. ``ref_pyr`` is :func:`pyramid` of the
    reference; ``alt`` (H, W) float32 the frame of its finest level's size."""
    alt_pyr = pyramid(np.asarray(alt, np.float32), len(ref_pyr))
    disp = None
    for lev in range(len(ref_pyr) - 1, -1, -1):
        disp = align_level(ref_pyr[lev], alt_pyr[lev], disp, lev == 0)
    return disp


def tile_counts(shape: tuple[int, int]) -> tuple[int, int]:
    """Tiles per column and per row of an image of ``shape`` (H, W) (at least one)."""
    step = TILE // 2
    return max(1, (shape[0] - TILE) // step + 1), max(1, (shape[1] - TILE) // step + 1)


def align_level(
    ref: np.ndarray, cur: np.ndarray, coarser: np.ndarray | None, finest: bool
) -> np.ndarray:
    """One pyramid level: each tile's best shift within its radius (1 at the ``finest``
    level, else :data:`SEARCH`) of its candidates (the ``coarser`` level's proposals, or
    zero at the coarsest), by L1 at the finest level and L2 elsewhere: (n_ty, n_tx, 2)."""
    n_ty, n_tx = tile_counts(ref.shape)
    cands = candidates(coarser, n_ty, n_tx)
    trials = Trials.around(cands, 1 if finest else SEARCH)
    cost = shift_costs(ref, cur, trials, l1=finest)
    # The best shift; among equal costs the first in (dy, dx) order.
    starts = trials.starts
    best = np.minimum.reduceat(cost, starts)
    first = np.where(cost == best[trials.tile], trials.index, len(trials.shifts))
    best_d = trials.shifts[np.minimum.reduceat(first, starts)].reshape(n_ty, n_tx, 2)
    mean = np.add.reduceat(cost, starts, dtype=np.float64) / np.diff(np.append(starts, len(cost)))
    # A tile whose best match is not clearly better than its average one holds no
    # texture above the noise: it keeps the coarser level's proposal, and at the
    # coarsest level the median displacement of the confident tiles.
    confident = (best < CONFIDENT_COST * mean).reshape(n_ty, n_tx)
    fallback = cands[0]
    if coarser is None and confident.any():
        fallback = np.broadcast_to(
            np.median(best_d[confident], axis=0).round().astype(np.int64), best_d.shape
        )
    return np.where(confident[..., None], best_d, fallback)


@dataclass
class Trials:
    """The shifts a level's tiles try, every distinct one of a tile once (neighbouring
    candidates' windows overlap): ``shifts`` (S, 2) ``(dy, dx)`` the distinct ones, in
    lexicographic order; per try, in the order of the tiles (row-major), its ``tile``
    and its ``index`` into ``shifts`` (P,); ``starts`` (tiles,) each tile's first try."""

    shifts: np.ndarray
    tile: np.ndarray
    index: np.ndarray
    starts: np.ndarray

    @classmethod
    def around(cls, cands: np.ndarray, radius: int) -> Trials:
        """The tries within ``radius`` of the candidates (n_c, n_ty, n_tx, 2)."""
        n_c = cands.shape[0]
        span = np.arange(-radius, radius + 1)
        window = np.stack(np.meshgrid(span, span, indexing="ij"), -1).reshape(-1, 2)
        flat = cands.reshape(n_c, -1, 2)  # (n_c, tiles, 2)
        counted = np.ones((n_c, flat.shape[1], len(window)), bool)
        for c in range(1, n_c):  # (a try within the radius of an earlier candidate)
            for e in range(c):
                dy, dx = (flat[c] - flat[e]).T[:, :, None]
                counted[c] &= (np.abs(dy + window[:, 0]) > radius) | (
                    np.abs(dx + window[:, 1]) > radius
                )
        # Shifts as one integer each (row-major in a square of side 2 bound + 1).
        bound = int(np.abs(flat).max()) + radius
        side = 2 * bound + 1
        starts = (flat[..., 0] + bound) * side + (flat[..., 1] + bound)  # (n_c, tiles)
        offsets = window[:, 0] * side + window[:, 1]
        uniq = np.unique(np.unique(starts)[:, None] + offsets)
        lookup = np.zeros(side * side, np.int64)
        lookup[uniq] = np.arange(len(uniq))
        tile, c, w = np.nonzero(counted.transpose(1, 0, 2))  # (tile-major)
        return cls(
            shifts=np.stack([uniq // side - bound, uniq % side - bound], axis=1),
            tile=tile,
            index=lookup[starts[c, tile] + offsets[w]],
            starts=np.flatnonzero(np.diff(tile, prepend=-1)),
        )


def candidates(coarser: np.ndarray | None, n_ty: int, n_tx: int) -> np.ndarray:
    """The displacements a level's tiles start from, (n_c, n_ty, n_tx, 2) int64: zero
    at the coarsest level; else the coarser level's proposal of the tile it lies in,
    and of the coarser tiles before it in y and in x (its nearest neighbours), doubled."""
    if coarser is None:
        return np.zeros((1, n_ty, n_tx, 2), np.int64)
    up = coarser.astype(np.int64) * 2
    cy, cx = up.shape[:2]
    iy = np.minimum(np.arange(n_ty) // 2, cy - 1)
    ix = np.minimum(np.arange(n_tx) // 2, cx - 1)
    ny = np.minimum(np.maximum(np.arange(n_ty) - 1, 0) // 2, cy - 1)
    nx = np.minimum(np.maximum(np.arange(n_tx) - 1, 0) // 2, cx - 1)
    return np.stack([up[iy][:, ix], up[ny][:, ix], up[iy][:, nx]])


#: A shift is scored on the whole image when the tiles that try it hold at least this
#: share of its pixels (scoring a tile on its own costs a gather several times a pass);
#: else tile by tile.
WHOLE_IMAGE_SHARE = 0.25


def shift_costs(ref: np.ndarray, cur: np.ndarray, trials: Trials, l1: bool) -> np.ndarray:
    """Each try's absolute (``l1``) or squared difference between ``ref`` and ``cur``
    moved by its shift (edges replicated), summed over the tile over a quarter of its
    pixels: (P,) float32."""
    import cv2

    step = TILE // 2
    n_ty, n_tx = tile_counts(ref.shape)
    hb, wb = (n_ty + 1) * step, (n_tx + 1) * step
    shifts = trials.shifts
    margin = int(np.abs(shifts).max())
    # (an image under one tile is padded to it; else cut to whole half-tile blocks)
    extra_y, extra_x = max(0, hb - ref.shape[0]), max(0, wb - ref.shape[1])
    ref = np.ascontiguousarray(ref, np.float32)
    ref = cv2.copyMakeBorder(ref, 0, extra_y, 0, extra_x, cv2.BORDER_REPLICATE)[:hb, :wb]
    cur = np.ascontiguousarray(cur, np.float32)
    cur = cv2.copyMakeBorder(
        cur, margin, margin + extra_y, margin, margin + extra_x, cv2.BORDER_REPLICATE
    )
    cost = np.empty(len(trials.index), np.float32)
    tries = np.bincount(trials.index, minlength=len(shifts))
    whole = tries * TILE * TILE >= WHOLE_IMAGE_SHARE * hb * wb
    on_whole = np.flatnonzero(whole)
    diff = np.empty((hb, wb), np.float32)
    blocks = np.empty((len(on_whole), n_ty + 1, n_tx + 1), np.float32)  # block means
    for j, i in enumerate(on_whole):
        y0, x0 = margin + int(shifts[i, 0]), margin + int(shifts[i, 1])
        cv2.absdiff(ref, cur[y0 : y0 + hb, x0 : x0 + wb], dst=diff)
        if not l1:
            cv2.multiply(diff, diff, dst=diff)
        cv2.resize(diff, (n_tx + 1, n_ty + 1), dst=blocks[j], interpolation=cv2.INTER_AREA)
    sums = blocks[:, :-1, :-1] + blocks[:, 1:, :-1] + blocks[:, :-1, 1:] + blocks[:, 1:, 1:]
    row = np.full(len(shifts), -1)
    row[on_whole] = np.arange(len(on_whole))
    k = np.flatnonzero(whole[trials.index])
    cost[k] = sums.reshape(len(on_whole), n_ty * n_tx)[row[trials.index[k]], trials.tile[k]]
    k = np.flatnonzero(~whole[trials.index])
    if len(k):  # the rest tile by tile, every (tile, shift) pair at once
        t, d = trials.tile[k], shifts[trials.index[k]]
        ty, tx = (t // n_tx) * step, (t % n_tx) * step
        tiles = np.lib.stride_tricks.sliding_window_view
        a = tiles(ref, (TILE, TILE))[ty, tx]
        b = tiles(cur, (TILE, TILE))[ty + margin + d[:, 0], tx + margin + d[:, 1]]
        diff = np.abs(a - b) if l1 else np.square(a - b)
        cost[k] = diff.sum(axis=(1, 2)) / np.float32(step * step)
    return cost
