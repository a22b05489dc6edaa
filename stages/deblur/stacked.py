"""Sparse products of the deblur's operators: one matrix with several image columns
(:func:`product`), the measuring bins' operators stacked in groups
(:class:`StackedOperator`) and the diagonal of a weighted normal matrix
(:func:`diag_normal`), each with bounded temporaries. Shapes: an image is (N, C) for N
pixels and C channels; products are float32 unless stated."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .band import Band, band_worth, make_band, offsets
from .convolution import ConvolutionSplit, SplitOperator, _SplitAdjoint

#: Mean non-zeros per row above which a product with several columns goes one column at
#: a time (:func:`product`).
LONG_ROWS_NNZ = 8


def product(M: sp.spmatrix, x: np.ndarray) -> np.ndarray:
    """``M @ x`` for ``x`` of shape (N, C), float32 (rows, C); ``M`` CSR or CSC (a
    transposed view).

    A float32 ``x`` keeps the product in the matrix's precision with no upcast copy of
    ``M``. Several columns go through scipy's multi-vector kernel, which reads the matrix
    once for all of them, where rows are short (a measuring bin's operator); where they
    are long (over :data:`LONG_ROWS_NNZ` non-zeros on average: the VET image's), one
    column at a time through the single-vector kernel, which is faster there.
    """
    if isinstance(M, (SplitOperator, _SplitAdjoint)):  # (no matrix: its convolutions)
        return M @ x
    if x.shape[1] == 1:
        return (M @ np.ascontiguousarray(x[:, 0], np.float32)).reshape(-1, 1)
    if M.nnz > LONG_ROWS_NNZ * M.shape[0]:
        out = np.empty((M.shape[0], x.shape[1]), np.float32)
        for c in range(x.shape[1]):
            out[:, c] = M @ np.ascontiguousarray(x[:, c], np.float32)
        return out
    return np.asarray(M @ np.ascontiguousarray(x, np.float32), np.float32)


class RestRows:
    """The rows no kernel takes of several splits (:class:`ConvolutionSplit`, each's
    ``R``) stacked as one CSR matrix on the columns they read, so that their weighted
    normal product is two sparse products, not two per split."""

    def __init__(self, parts: list[ConvolutionSplit]):
        blocks = []
        for part in parts:
            R = part.R
            cols = R.indices if part.cols is None else part.cols[R.indices]
            n = part.shape[0] * part.shape[1]
            blocks.append(sp.csr_matrix((R.data, cols, R.indptr), (R.shape[0], n)))
        R = sp.vstack(blocks, format="csr")
        used = np.bincount(R.indices, minlength=R.shape[1]) > 0
        #: The columns read (ascending), and the stack on them.
        self.cols = np.flatnonzero(used)
        at = np.cumsum(used, dtype=np.int64) - 1
        self.R = sp.csr_matrix((R.data, at[R.indices], R.indptr), (R.shape[0], self.cols.size))
        self.RT = self.R.T

    def normal(self, x: np.ndarray, wt: np.ndarray, out: np.ndarray) -> None:
        """Add ``R.T diag(wt) R x`` to ``out``: ``x``, ``out`` (N,) float32, ``wt`` the
        rows' weights, the parts' one after the other."""
        v = self.R @ x[self.cols]
        v *= wt
        out[self.cols] += self.RT @ v


@dataclass
class SplitWeights:
    """The bins' row weights as their split groups take them
    (:meth:`StackedOperator.split_weights`): ``groups``, per group (None where not
    split), per channel, each part's (:meth:`ConvolutionSplit.weights`); or, where the
    parts are banded (``StackedOperator.banded``), ``groups`` None, ``bands`` the band
    of every part's kernels per channel (:mod:`stages.deblur.band`) and ``rests`` the
    weights of the stacked other rows per channel (:class:`RestRows`)."""

    groups: list | None
    bands: list[Band] | None = None
    rests: list[np.ndarray] | None = None


#: Groups the measuring bins' operators are stacked into (:class:`StackedOperator`):
#: enough pieces of work, with the VET image's, to keep a few threads busy
#: (:func:`stages.cluster.solve_threads`).
BIN_GROUPS = 4


class StackedOperator:
    """Operators of several images sharing the unknown (the measuring bins).

    Behaves as their vertical stack for the few products the solvers need. The parts are
    stacked into at most :data:`BIN_GROUPS` consecutive groups (one CSR matrix each,
    with its transposed view, or, for parts given as splits alone, the group's splits),
    so that a product is a few calls of scipy's kernels, not one per bin, and the normal
    product splits into independent pieces, one per group and channel
    (:meth:`normal_column`), that threads can share. Products go in the parts' float32;
    no (B N, C) float64 array is ever made.
    """

    def __init__(
        self,
        parts: list[sp.csr_matrix] | list[ConvolutionSplit],
        blurs: list[sp.csr_matrix] | None = None,
        image_shape: tuple[int, int] | None = None,
        splits: list[ConvolutionSplit | None] | None = None,
        release: bool = False,
    ):
        """``parts``: the bins' (N, N) operators, or their splits alone
        (:class:`ConvolutionSplit`, every one: no matrix is then held, and the products
        all go through them); ``image_shape`` (H, W): split the matrices into
        convolutions (``splits``: their splits, when the caller has them);
        ``release``: set each of ``parts`` to None once stacked (the caller holds no
        other reference), so that a part and its group's stack are not both held."""
        #: The bins' operators as their splits alone (no group holds a matrix), or None.
        self.parts = None
        if parts and all(isinstance(p, ConvolutionSplit) for p in parts):
            self.parts = list(parts)
            image_shape, splits = parts[0].shape, self.parts
        n, cols = (image_shape[0] * image_shape[1],) * 2 if self.parts else parts[0].shape
        self.rows = n
        self.image_shape = image_shape
        self.shape = (n * len(parts), cols)
        if image_shape is not None and splits is None:
            from ..cluster import in_order  # (numpy's passes release the GIL: on the threads)

            splits = list(
                in_order(lambda i: ConvolutionSplit.of(parts[i], image_shape), len(parts))
            )
        #: The parts' kernels as one band (:mod:`stages.deblur.band`) and their other rows
        #: as one stack (:class:`RestRows`), where the parts are splits alone and the band
        #: costs less than the kernels' convolutions: the parts are then one group.
        self.banded: tuple[list, RestRows] | None = None
        if self.parts is not None:
            kernels = [k for part in self.parts for k in part.kernels]
            if kernels and band_worth(kernels):
                self.banded = (offsets(kernels), RestRows(self.parts))
        groups = 1 if self.banded else min(BIN_GROUPS, len(parts))
        step = -(-len(parts) // groups)
        #: (stack, its transposed view, first row, end row) of each group (the stack
        #: and its view None where the parts are splits alone).
        self.groups = []
        #: Each group's parts as shifted convolutions (:mod:`stages.deblur.convolution`)
        #: where every part of the group splits (operators on an ``image_shape`` grid),
        #: else None: :meth:`normal_column` then goes through them.
        self.splits: list[list[ConvolutionSplit] | None] = []
        for b0 in range(0, len(parts), step):
            chunk = parts[b0 : b0 + step]
            r0, r1 = b0 * n, (b0 + len(chunk)) * n
            if self.parts is not None:
                self.groups.append((None, None, r0, r1))
                self.splits.append(chunk)
                continue
            M = chunk[0].tocsr() if len(chunk) == 1 else sp.vstack(chunk, format="csr")
            self.groups.append((M, M.T, r0, r1))
            split = None if image_shape is None else splits[b0 : b0 + len(chunk)]
            self.splits.append(None if split is None or None in split else split)
            if release:
                parts[b0 : b0 + len(chunk)] = [None] * len(chunk)
            del chunk
        #: The bins' blurs on the VET grid (the groups' stacks, or what a camera's
        #: sampling multiplies): where the motion moves an integration path.
        self.blurs = [g[0] for g in self.groups if g[0] is not None] if blurs is None else blurs

    @property
    def all_split(self) -> bool:
        """Whether every group goes through its convolutions (:meth:`normal_column` then
        reads the weights only as :meth:`split_weights` makes them)."""
        return all(s is not None for s in self.splits)

    def moving_reach(self) -> np.ndarray:
        """The pixels some bin's moving integration path reads, bool (N,) (see
        :func:`~stages.deblur.still_pixels.moving_support`)."""
        from .operator import moving_reach

        out = np.zeros(self.shape[1], bool)
        for part in self.parts or []:
            out |= part.moving_reach()
        for M in self.blurs:  # (none where the parts are splits alone)
            out |= moving_reach(M)
        return out

    def mv(self, x: np.ndarray) -> np.ndarray:
        """``stack @ x`` for ``x`` of shape (N, C), float32 result (B N, C)."""
        x32 = np.asarray(x, np.float32)
        out = np.empty((self.shape[0], x.shape[1]), np.float32)
        if self.parts is not None:
            n = self.rows
            xs = [
                np.ascontiguousarray(x32[:, c]).reshape(self.image_shape) for c in range(x.shape[1])
            ]
            for i, part in enumerate(self.parts):
                for c, xc in enumerate(xs):
                    out[i * n : (i + 1) * n, c] = part.apply(xc)
            return out
        for M, _, r0, r1 in self.groups:
            out[r0:r1] = product(M, x32)
        return out

    def mvt(self, r: np.ndarray) -> np.ndarray:
        """``stack.T @ r`` for ``r`` of shape (B N, C), float64 result (N, C)."""
        if self.parts is not None:
            return self._adjoint(r)
        out = np.zeros((self.shape[1], r.shape[1]))
        for _, MT, r0, r1 in self.groups:
            out += MT @ np.asarray(r[r0:r1], np.float32)
        return out

    def mvt_weighted(self, w: np.ndarray, r: np.ndarray) -> np.ndarray:
        """``stack.T @ (w * r)`` (both (B N, C)) group by group, float64 (N, C)."""
        if self.parts is not None:
            return self._adjoint(r, w)
        out = np.zeros((self.shape[1], r.shape[1]))
        for _, MT, r0, r1 in self.groups:
            out += MT @ (w[r0:r1] * r[r0:r1]).astype(np.float32, copy=False)
        return out

    def _adjoint(self, r: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """``stack.T @ (w * r)`` through the parts' splits, a part and channel at a time:
        (N, C) float64, the transpose of a (C, N) array (a channel contiguous)."""
        n = self.rows
        out = np.zeros((r.shape[1], n))  # (a channel contiguous; returned as (N, C))
        for i, part in enumerate(self.parts):
            y = r[i * n : (i + 1) * n]
            y = y if w is None else w[i * n : (i + 1) * n] * y
            y = np.ascontiguousarray(np.asarray(y, np.float32).T)  # (C, N)
            for c in range(r.shape[1]):
                out[c] += part.adjoint(y[c]).reshape(-1)
        return out.T

    def split_weights(self, w: np.ndarray) -> SplitWeights:
        """The row weights ``w`` (B N, C) as the split groups take them
        (:class:`SplitWeights`), made once for the products of one ``w``
        (:meth:`normal_column`). Where the parts are banded, each part's weights go into
        the channel's band and other rows' weights as they are made."""
        if self.banded is not None:
            bands, rests = [], []
            for c in range(w.shape[1]):
                rw = []

                def pairs(c=c, rw=rw):
                    for _, part, pw in self._part_weights(w, c):
                        yield from zip(part.kernels, pw[:-1], strict=True)
                        rw.append(pw[-1])  # (the other rows')

                bands.append(make_band(pairs(), self.banded[0], self.image_shape))
                rests.append(np.concatenate(rw))
            return SplitWeights(None, bands, rests)
        groups = [
            None if split is None else [[] for _ in range(w.shape[1])] for split in self.splits
        ]
        for c in range(w.shape[1]):
            for g, _, pw in self._part_weights(w, c):
                groups[g][c].append(pw)
        return SplitWeights(groups)

    def _part_weights(self, w: np.ndarray, c: int):
        """``(group, part, its weights)`` of every split part for channel ``c`` of ``w``
        (:meth:`ConvolutionSplit.weights`), made one at a time."""
        n = self.shape[1]
        for g, (split, (_, _, r0, _)) in enumerate(zip(self.splits, self.groups, strict=True)):
            for i, part in enumerate(split or []):
                yield g, part, part.weights(w[r0 + i * n : r0 + (i + 1) * n, c])

    def normal_column(
        self, g: int, xc: np.ndarray, w: np.ndarray, c: int, split_w: SplitWeights | None = None
    ) -> np.ndarray:
        """Group ``g``'s share of ``stack.T diag(w) stack @ x`` for channel ``c``:
        ``xc`` that channel of ``x`` (N,) contiguous float32, ``w`` (B N, C); (N,)
        float32. The pieces of all groups sum to :meth:`normal`'s column ``c``.
        ``split_w``: :meth:`split_weights` of ``w`` (made here for a split group if
        not given)."""
        M, MT, r0, r1 = self.groups[g]
        split = self.splits[g]
        if split is not None:
            sw = split_w or self.split_weights(w)
            out = np.zeros(self.image_shape, np.float32)
            x = xc.reshape(self.image_shape)
            if sw.bands is not None:  # (the one group)
                sw.bands[c].normal(x, out)
                self.banded[1].normal(xc, sw.rests[c], out.reshape(-1))
                return out.reshape(-1)
            for part, pw in zip(split, sw.groups[g][c], strict=True):
                part.normal(x, pw, out)
            return out.reshape(-1)
        y = M @ xc
        y *= w[r0:r1, c]
        return MT @ y

    def normal(self, x: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``stack.T diag(w) stack @ x`` (``w`` of shape (B N, C)), float64 (N, C).

        Group by group and channel by channel: the transient is one group's (rows,)
        float32 product.
        """
        out = np.zeros((self.shape[1], x.shape[1]))
        split_w = self.split_weights(w)
        for c in range(x.shape[1]):
            xc = np.ascontiguousarray(x[:, c], np.float32)
            for g in range(len(self.groups)):
                out[:, c] += self.normal_column(g, xc, w, c, split_w)
        return out

    def diag_normal(self, w: np.ndarray) -> np.ndarray:
        """Diagonal of ``stack.T diag(w) stack`` (w of shape (B N, C))."""
        if self.parts is not None:
            n = self.rows
            out = np.zeros((n, w.shape[1]))
            for i, part in enumerate(self.parts):
                for c in range(w.shape[1]):
                    out[:, c] += part.diag_normal(w[i * n : (i + 1) * n, c])
            return out
        out = None
        for M, _, r0, r1 in self.groups:
            part = diag_normal(M, w[r0:r1])
            out = part if out is None else out + part
        return out


def _rows(A: sp.csr_matrix, r0: int, r1: int, data: np.ndarray | None = None) -> sp.csr_matrix:
    """Rows ``r0:r1`` of ``A`` (CSR) sharing its index arrays, with its values or
    ``data`` (the block's, one per stored entry)."""
    p0, p1 = int(A.indptr[r0]), int(A.indptr[r1])
    # (Set on an empty matrix: the constructor copies a view of a much larger array.)
    B = sp.csr_matrix((int(r1 - r0), A.shape[1]), dtype=A.dtype)
    B.data = A.data[p0:p1] if data is None else data
    B.indices = A.indices[p0:p1]
    B.indptr = (A.indptr[r0 : r1 + 1] - p0).astype(A.indptr.dtype)
    return B


def row_blocks(A: sp.csr_matrix, n: int) -> list[tuple[sp.csr_matrix, sp.spmatrix, int, int]]:
    """``A`` (CSR) in ``n`` blocks of consecutive rows, each ``(block, its transposed
    view, first row, end row)``; the blocks share ``A``'s value and index arrays."""
    bounds = np.linspace(0, A.shape[0], max(1, n) + 1).round().astype(int)
    out = []
    for r0, r1 in zip(bounds[:-1], bounds[1:], strict=True):
        B = _rows(A, int(r0), int(r1))
        out.append((B, B.T, int(r0), int(r1)))
    return out


#: Rows per block of :func:`diag_normal` (bounds its copy of the squared values).
DIAG_BLOCK_ROWS = 1 << 16


def diag_normal(A: sp.csr_matrix, w: np.ndarray) -> np.ndarray:
    """Diagonal of ``A.T diag(w) A``, ``w`` of shape (N, C): ``sum_r w_r A_rc^2``.

    Squares the stored values a block of :data:`DIAG_BLOCK_ROWS` rows at a time into a
    matrix that shares ``A``'s index arrays (no index matching, unlike
    ``A.multiply(A)``, and no squared copy of the whole matrix).
    """
    if isinstance(A, SplitOperator):
        return A.diag_normal(w)
    n_rows, n_cols = A.shape
    out = np.zeros((n_cols, w.shape[1]))
    for r0 in range(0, n_rows, DIAG_BLOCK_ROWS):
        r1 = min(n_rows, r0 + DIAG_BLOCK_ROWS)
        blk = _rows(A, r0, r1, np.square(A.data[int(A.indptr[r0]) : int(A.indptr[r1])]))
        out += blk.T @ np.asarray(w[r0:r1], np.float32)
    return out
