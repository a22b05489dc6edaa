"""A sparse image operator split into small shifted convolutions and the rows they miss.

A measuring bin's blur operator (:func:`stages.deblur.operator.blur_matrix` over a time
window shared by every pixel) is, row by row, one of a few stencils: a layer's motion
over the bin is the same for all its pixels, so the rows of the pixels inside a layer and
away from the image border hold the same weights at the same offsets. Those rows are a
shifted convolution: a small kernel (the stencil's bounding box) correlated by OpenCV's
``filter2D`` and read at the row's pixel moved by the stencil's first offsets (an
integer shift), passes of contiguous loads, where a sparse product gathers every
non-zero through its column index. The other rows
(the image border, where coordinates are reflected, and where layers meet) stay sparse.

The split is exact: a row is taken by a kernel only where every one of its entries is
that kernel's, at the same offset, and lies inside the image, so the convolution sums
that row's terms (in float32, in another order). The adjoint puts the rows' values back
at their shifted pixels and correlates them with the flipped kernel, plus the other rows'
transpose.

Shapes: the operator ``M`` is (N, N) CSR for an image of (H, W) = N pixels (rows: observed
pixels, columns: unknown pixels, both row-major); images are (H, W) float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp

#: At most this many kernels per operator (layers, or exposure times of the VET image).
MAX_KERNELS = 8
#: Costs in a sparse product's visits of one stored entry (``make bench``'s
#: ``bench_products`` measures both sides), for a kernel to be worth its passes: a pass
#: over the image (per pixel), and each of a kernel's taps in ``filter2D`` (per pixel).
PASS_COST = 0.5
TAP_COST = 0.07
#: Rows whose stencils are tried as a kernel's, spread over the rows not yet taken.
SEEDS = 8
GOLDEN = (5**0.5 - 1) / 2
#: Rows checked first for a seed's stencil (a rare one is not checked on every row).
PROBE_ROWS = 512
#: Largest kernel (rows x columns): OpenCV's ``filter2D`` goes through the DFT for larger
#: ones, slower than the sparse rows (a long diagonal path stays sparse).
MAX_KERNEL_AREA = 100
#: The other rows are kept on the columns they read where those are under this share of
#: the image (else on all: gathering most columns through an index costs more).
COMPRESS_BELOW = 0.5
#: An operator is split only where its kernels take at least this share of the rows
#: that have entries: the rest is a copy of its rows, beside the operator.
MIN_SPLIT_SHARE = 0.5


def kernel_cost(small: np.ndarray) -> float:
    """A kernel's cost in a normal product, per pixel, in sparse entry visits: a one-tap
    kernel is one fused pass, another two correlations, a product and a sum
    (:meth:`ConvolutionSplit.normal`)."""
    if small.size == 1:
        return PASS_COST
    return 4 * PASS_COST + 2 * TAP_COST * int(np.count_nonzero(small))


def _worth(rows: int, entries: int, small: np.ndarray, n: int) -> bool:
    """Whether a kernel taking ``rows`` rows of ``entries`` entries each saves more than
    its passes cost on an image of ``n`` pixels (the normal product visits each entry
    twice; :func:`kernel_cost`)."""
    return 2.0 * rows * entries > kernel_cost(small) * n


def _span(shift: int, n: int) -> tuple[slice, slice]:
    """(rows whose ``i + shift`` is inside ``n``, those positions) along one axis; empty
    where the shift is the whole axis or more."""
    lo = min(n, max(0, -shift))
    hi = max(lo, n - max(0, shift))
    return slice(lo, hi), slice(lo + shift, hi + shift)


@dataclass
class _Kernel:
    """One stencil, ``out[i, j] = sum small[u, v] x[i + sy + u, j + sx + v]``: the
    correlation of ``small`` (anchored at its corner) evaluated at the row's pixel moved
    by ``shift``."""

    small: np.ndarray  # (ky, kx) float32
    shift: tuple[int, int]  # (sy, sx): the stencil's first row and column offsets
    mask: np.ndarray  # (H, W) bool: the rows this kernel takes

    def __post_init__(self) -> None:
        ky, kx = self.small.shape
        self.flipped = np.ascontiguousarray(self.small[::-1, ::-1])
        self.anchor_flipped = (kx - 1, ky - 1)  # (OpenCV's (x, y))
        #: The one weight of a one-tap stencil (a whole-pixel shift), else None.
        self.tap = float(self.small[0, 0]) if self.small.size == 1 else None

    def slices(self, h: int, w: int):
        """((rows, columns) whose ``pixel + shift`` is inside, (those positions))."""
        (ry, cy), (rx, cx) = _span(self.shift[0], h), _span(self.shift[1], w)
        return (ry, rx), (cy, cx)

    def correlate(self, x: np.ndarray) -> np.ndarray:
        """``f[q] = sum small[u, v] x[q + (u, v)]`` (zero outside the image), (H, W)."""
        return cv2.filter2D(x, -1, self.small, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)

    def spread(self, c: np.ndarray) -> np.ndarray:
        """The adjoint of :meth:`correlate`: ``z[p] = sum small[d] c[p - d]``, (H, W)."""
        return cv2.filter2D(
            c, -1, self.flipped, anchor=self.anchor_flipped, borderType=cv2.BORDER_CONSTANT
        )


def _kernel_of(off: np.ndarray, val: np.ndarray, w: int):
    """The stencil of flat column offsets ``off`` with values ``val`` on an image ``w``
    pixels wide: (kernel, shift, dy, dx), or None where an offset is half the width or
    more sideways (its 2-D reading would be ambiguous) or the kernel's area is over
    :data:`MAX_KERNEL_AREA`."""
    dy = np.round(off / w).astype(np.int64)
    dx = off - dy * w
    if np.abs(dx).max() * 2 >= w:
        return None
    sy, sx = int(dy.min()), int(dx.min())
    ky, kx = int(dy.max()) - sy + 1, int(dx.max()) - sx + 1
    if ky * kx > MAX_KERNEL_AREA:
        return None
    small = np.zeros((ky, kx), np.float32)
    np.add.at(small, (dy - sy, dx - sx), val.astype(np.float32))
    return small, (sy, sx), dy, dx


def _taken(M: sp.csr_matrix, rows: np.ndarray, off: np.ndarray, val: np.ndarray) -> np.ndarray:
    """Which of ``rows`` (each with ``len(off)`` entries) hold exactly ``val`` at column
    offsets ``off`` from their own index, bool (len(rows),)."""
    at = M.indptr[rows]
    ok = np.ones(rows.size, bool)
    for e in range(off.size):
        ent = at + e if e else at
        ok &= M.indices[ent] == rows + M.indices.dtype.type(off[e])
        ok &= M.data[ent] == val[e]
    return ok


def _inside(dy: np.ndarray, dx: np.ndarray, rows: np.ndarray, h: int, w: int) -> np.ndarray:
    """Which of ``rows`` keep every offset (dy, dx) inside the (h, w) image, bool."""
    inside = np.zeros((h, w), bool)
    inside[max(0, -dy.min()) : h - max(0, dy.max()), max(0, -dx.min()) : w - max(0, dx.max())] = (
        True
    )
    return inside.reshape(-1)[rows]


def _best_seed(M: sp.csr_matrix, open_rows: np.ndarray, nnz: np.ndarray, h: int, w: int):
    """Of :data:`SEEDS` rows spread over ``open_rows``, the one whose stencil the most
    of :data:`PROBE_ROWS` open rows, evenly spread, share: ((small kernel, shift, offsets,
    values, dy, dx), the open rows it would take at that share), or None."""
    best = None
    probe = open_rows[:: max(1, open_rows.size // PROBE_ROWS)]
    # (Spread by the golden ratio, not evenly: even steps fall on one image column.)
    picks = np.unique((np.arange(1, SEEDS + 1) * GOLDEN % 1.0 * open_rows.size).astype(int))
    for seed in open_rows[picks]:
        s0, s1 = M.indptr[seed], M.indptr[seed + 1]
        off, val = M.indices[s0:s1].astype(np.int64) - int(seed), M.data[s0:s1]
        found = _kernel_of(off, val, w)
        if found is None:
            continue
        small, shift, dy, dx = found
        cand = probe[(nnz[probe] == off.size) & _inside(dy, dx, probe, h, w)]
        count = np.count_nonzero(_taken(M, cand, off, val)) * open_rows.size / probe.size
        if best is None or count > best[1]:
            best = ((small, shift, off, val, dy, dx), count)
    return best


class ConvolutionSplit:
    """``M`` as ``sum_k diag(m_k) K_k + R``: shifted convolutions ``K_k`` on the rows of
    masks ``m_k`` and ``R``, the rows no kernel takes (CSR). Build it with :meth:`of`."""

    def __init__(
        self, shape: tuple[int, int], kernels: list[_Kernel], rest: np.ndarray, R: sp.csr_matrix
    ):
        """``R``: the operator's rows ``rest``, (len(rest), N) CSR."""
        self.shape = shape
        self.kernels = kernels
        #: The rows no kernel takes (rows with no entries left out), and their matrix,
        #: on the columns they read (``cols``; None: on all of them).
        self.rest = rest
        n = R.shape[1]
        used = np.zeros(n, bool)
        used[R.indices] = True
        self.cols = None  # (all of them: no gather and scatter through an index)
        if np.count_nonzero(used) < COMPRESS_BELOW * n:
            self.cols = np.flatnonzero(used)
            place = np.zeros(n, R.indices.dtype)  # (each column's place among them)
            place[self.cols] = np.arange(self.cols.size, dtype=place.dtype)
            R = sp.csr_matrix(
                (R.data, place[R.indices], R.indptr), shape=(rest.size, self.cols.size)
            )
        self.R, self.RT = R, R.T

    @classmethod
    def of(
        cls, M: sp.csr_matrix, shape: tuple[int, int], detect: bool = True
    ) -> ConvolutionSplit | None:
        """The split of ``M`` (N, N) CSR, canonical (sorted indices, no duplicates), for
        an image of ``shape`` (H, W); None where no kernel is worth its passes
        (:func:`_worth`) or the kernels take under :data:`MIN_SPLIT_SHARE` of its rows.

        The kernels are the stencil groups of its assembly where it has them
        (``M.stencils``, :class:`~stages.deblur.operator.Stencils`), else, with
        ``detect``, stencils found among its rows (each checked on every row it takes)."""
        h, w = shape
        n = h * w
        if M.shape != (n, n) or n == 0:
            return None
        stencils = getattr(M, "stencils", None)
        if stencils is not None:
            return cls._of_stencils(M, stencils, shape)
        if not detect or not M.has_canonical_format:
            return None
        nnz = np.diff(M.indptr)
        label = np.where(nnz > 0, -1, -2).astype(np.int8)  # -1: not taken (yet)
        kernels: list[_Kernel] = []
        while len(kernels) < MAX_KERNELS:
            open_rows = np.flatnonzero(label == -1).astype(np.int32)
            found = _best_seed(M, open_rows, nnz, h, w) if open_rows.size else None
            if found is None:
                break
            (small, shift, off, val, dy, dx), count = found
            if not _worth(count, off.size, small, n):
                break  # (no stencil common enough: the rest stays sparse)
            rows = open_rows[(nnz[open_rows] == off.size) & _inside(dy, dx, open_rows, h, w)]
            rows = rows[_taken(M, rows, off, val)]
            if not _worth(rows.size, off.size, small, n):
                break
            label[rows] = len(kernels)
            kernels.append(_Kernel(small, shift, (label == len(kernels)).reshape(h, w)))
        if not kernels or np.count_nonzero(label >= 0) < MIN_SPLIT_SHARE * np.count_nonzero(nnz):
            return None
        rest = np.flatnonzero(label == -1)
        return cls(shape, kernels, rest, M[rest])

    @classmethod
    def _of_stencils(cls, M: sp.csr_matrix, st, shape: tuple[int, int]) -> ConvolutionSplit | None:
        """The split of a matrix whose rows' stencils its assembly knows
        (:class:`~stages.deblur.operator.Stencils`): the largest groups, each where it
        is worth its passes (:func:`_worth`), are the kernels."""
        return cls.of_plan(np.diff(M.indptr), st, shape, lambda _left, rest: M[rest])

    @classmethod
    def of_plan(
        cls, nnz: np.ndarray, st, shape: tuple[int, int], rest_rows
    ) -> ConvolutionSplit | None:
        """The split of an operator from its assembly's plan alone, its matrix never made:
        ``nnz`` (N,) its entries per row, ``st`` its :class:`~stages.deblur.operator.Stencils`,
        ``rest_rows(left, rest)`` the operator's rows ``rest`` (sorted: the generic rows
        with entries and the stencil rows ``st.rows[left]``, bool, that no kernel takes),
        (len(rest), N) CSR. None as :meth:`of`."""
        h, w = shape
        n = h * w
        label = np.full(n, -1, np.int8)
        label[nnz == 0] = -2
        sizes = (
            np.array([st.group.size])
            if len(st.reps) == 1
            else np.bincount(st.group, minlength=len(st.reps))
        )
        starts = np.cumsum(st.counts) - st.counts
        kernels: list[_Kernel] = []
        for g in np.argsort(-sizes, kind="stable")[:MAX_KERNELS]:
            rep = int(st.reps[g])
            sl = slice(int(starts[g]), int(starts[g] + st.counts[g]))
            off = st.cols[sl].astype(np.int64) - rep
            found = _kernel_of(off, st.vals[sl], w) if off.size else None
            if found is None:
                continue
            small, shift, dy, dx = found
            if not _worth(int(sizes[g]), off.size, small, n):
                continue
            rows = st.rows if len(st.reps) == 1 else st.rows[st.group == g]
            rows = rows[_inside(dy, dx, rows, h, w)]  # (so all along the assembly's plan)
            label[rows] = len(kernels)
            kernels.append(_Kernel(small, shift, (label == len(kernels)).reshape(h, w)))
        if not kernels or np.count_nonzero(label >= 0) < MIN_SPLIT_SHARE * np.count_nonzero(nnz):
            return None
        rest = np.flatnonzero(label == -1)
        return cls(shape, kernels, rest, rest_rows(label[st.rows] == -1, rest))

    def _cols(self, x: np.ndarray) -> np.ndarray:
        """The columns of ``x`` (N,) the other rows read."""
        return x if self.cols is None else x[self.cols]

    def _add_cols(self, out: np.ndarray, z: np.ndarray) -> None:
        """Add ``z`` (the other rows' adjoint, on their columns) to ``out`` (N,)."""
        if self.cols is None:
            out += z
        else:
            out[self.cols] += z

    def weights(self, wt: np.ndarray) -> list[np.ndarray]:
        """The row weights ``wt`` (N,) as :meth:`normal` takes them: each kernel's
        (H, W) float32 at its rows' pixels moved by its shift, zero elsewhere (times
        its tap squared for a one-tap stencil), then the other rows' (len(rest),)."""
        h, w = self.shape
        img = np.asarray(wt, np.float32).reshape(h, w)
        out = []
        for k in self.kernels:
            (ry, rx), (cy, cx) = k.slices(h, w)
            mw = np.zeros((h, w), np.float32)
            np.multiply(img[ry, rx], k.mask[ry, rx], out=mw[cy, cx])  # (0 off the mask)
            if k.tap is not None:
                mw *= np.float32(k.tap * k.tap)
            out.append(mw)
        out.append(np.asarray(wt, np.float32)[self.rest])
        return out

    def normal(self, x: np.ndarray, weights: list[np.ndarray], out: np.ndarray) -> None:
        """Add ``M.T @ (wt * (M @ x))`` to ``out``: ``x``, ``out`` (H, W) float32,
        ``weights`` from :meth:`weights`.

        With ``f`` the small kernel's correlation of ``x``, row ``r``'s value is
        ``f[r + shift]``; weighted and put back at ``r + shift``, the
        flipped kernel's correlation spreads it over the row's columns (inside the image
        for every row a kernel takes)."""
        for k, mw in zip(self.kernels, weights, strict=False):
            if k.tap is not None:  # a whole-pixel shift: one fused multiply-add
                cv2.accumulateProduct(x, mw, out)
                continue
            f = k.correlate(x)
            f *= mw
            out += k.spread(f)
        if self.rest.size:
            v = self.R @ self._cols(x.reshape(-1))
            v *= weights[-1]
            self._add_cols(out.reshape(-1), self.RT @ v)

    def diag_normal(self, wt: np.ndarray) -> np.ndarray:
        """The diagonal of ``M.T diag(wt) M``, ``sum_r wt_r M_rc^2``, for ``wt`` (N,);
        (N,) float64. A kernel's rows spread their weights, put at their pixels moved by
        its shift, over its squared taps."""
        h, w = self.shape
        out = np.zeros((h, w), np.float32)
        img = np.asarray(wt, np.float32).reshape(h, w)
        for k in self.kernels:
            (ry, rx), (cy, cx) = k.slices(h, w)
            mw = np.zeros((h, w), np.float32)
            np.multiply(img[ry, rx], k.mask[ry, rx], out=mw[cy, cx])  # (0 off the mask)
            sq = _Kernel(np.square(k.small), k.shift, k.mask)
            out += mw * np.float32(k.tap * k.tap) if k.tap is not None else sq.spread(mw)
        diag = out.reshape(-1).astype(np.float64)
        if self.rest.size:
            R2 = sp.csr_matrix(
                (np.square(self.R.data), self.R.indices, self.R.indptr), self.R.shape
            )
            self._add_cols(diag, R2.T @ np.asarray(wt, np.float32)[self.rest])
        return diag

    def moving_reach(self) -> np.ndarray:
        """The pixels that a row reading more than its own pixel reads, bool (N,) (what
        :func:`~stages.deblur.operator.static_rows` leaves, as
        :func:`~stages.deblur.still_pixels.moving_support` takes it)."""
        h, w = self.shape
        moving = np.zeros(h * w, np.float32)
        for k in self.kernels:
            if not (k.tap is not None and k.shift == (0, 0)):
                moving[k.mask.reshape(-1)] = 1.0
        if self.rest.size and self.R.nnz:
            R = self.R
            cnt = np.diff(R.indptr)
            col = R.indices[np.minimum(R.indptr[:-1], R.nnz - 1)]  # (a row's first entry)
            col = col if self.cols is None else self.cols[col]
            moving[self.rest] = (cnt > 1) | ((cnt == 1) & (col != self.rest))
        return self.adjoint(moving).reshape(-1) != 0

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``M @ x`` for ``x`` (H, W) float32; (H W,) float32."""
        h, w = self.shape
        y = np.zeros((h, w), np.float32)
        for k in self.kernels:
            (ry, rx), (cy, cx) = k.slices(h, w)
            f = k.correlate(x)
            fk = f[cy, cx]
            fk *= k.mask[ry, rx]  # (0 off the mask)
            y[ry, rx] += fk
        y = y.reshape(-1)
        if self.rest.size:
            y[self.rest] = self.R @ self._cols(x.reshape(-1))
        return y

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        """``M.T @ y`` for ``y`` (H W,) float32; (H, W) float32."""
        h, w = self.shape
        img = np.asarray(y, np.float32).reshape(h, w)
        out = np.zeros((h, w), np.float32)
        for k in self.kernels:
            (ry, rx), (cy, cx) = k.slices(h, w)
            at_shifted = np.zeros((h, w), np.float32)
            np.multiply(img[ry, rx], k.mask[ry, rx], out=at_shifted[cy, cx])
            out += k.spread(at_shifted)
        if self.rest.size:
            self._add_cols(out.reshape(-1), self.RT @ np.asarray(y, np.float32)[self.rest])
        return out


class SplitOperator:
    """An (N, N) operator held as its split alone (:class:`ConvolutionSplit`, no matrix),
    with what a solve takes of a sparse matrix: ``M @ x`` and ``M.T @ y`` for ``x``, ``y``
    (N,) or (N, C) (float32 results of the same shape), ``M.shape``, ``M.convolution``
    (the split), the normal diagonal (:meth:`diag_normal`) and the moving rows' reach
    (:meth:`moving_reach`)."""

    def __init__(self, split: ConvolutionSplit):
        self.convolution = split
        n = split.shape[0] * split.shape[1]
        self.shape = (n, n)

    @property
    def T(self) -> _SplitAdjoint:
        return _SplitAdjoint(self.convolution, self.shape)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        split = self.convolution
        return _by_column(lambda v: split.apply(v.reshape(split.shape)), x)

    def diag_normal(self, w: np.ndarray) -> np.ndarray:
        """The diagonal of ``M.T diag(w) M`` for ``w`` (N, C), float64 (N, C)."""
        return np.stack([self.convolution.diag_normal(w[:, c]) for c in range(w.shape[1])], axis=1)

    def moving_reach(self) -> np.ndarray:
        return self.convolution.moving_reach()


class _SplitAdjoint:
    """``M.T`` of a :class:`SplitOperator`: its products."""

    def __init__(self, split: ConvolutionSplit, shape: tuple[int, int]):
        self.convolution, self.shape = split, shape

    def __matmul__(self, y: np.ndarray) -> np.ndarray:
        return _by_column(lambda v: self.convolution.adjoint(v).reshape(-1), y)


def _by_column(fn, x: np.ndarray) -> np.ndarray:
    """``fn`` (of a contiguous float32 (N,) column, to (N,)) of ``x`` (N,) or (N, C)."""
    x = np.asarray(x, np.float32)
    if x.ndim == 1:
        return fn(np.ascontiguousarray(x))
    return np.stack([fn(np.ascontiguousarray(x[:, c])) for c in range(x.shape[1])], axis=1)
