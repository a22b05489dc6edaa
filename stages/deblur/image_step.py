"""One image step of the default deblur: the weighted least-squares image for fixed
weights and motion, by preconditioned conjugate gradients (:func:`solve_image`).

The normal product applies the VET image's operator, the measuring bins' and the
stream's, each weighted, and the edge-preserving relative smoothness
(:func:`smooth_weights`): the bins' (and the VET image's, where its rows are one stencil
per exposure time) as shifted convolutions (:mod:`stages.deblur.convolution`), the bins'
short ones with the smoothness as one band where that costs less
(:mod:`stages.deblur.band`), the rest as sparse products, in float32 pieces on the
process's threads. Shapes: images (H W, C) float64 (the conjugate gradients' vectors
(C, H W), a channel contiguous), weights of the shape of what they weigh.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..cluster import opencv_single_threaded, solve_threads
from .band import Band
from .joint_options import EDGE_REL_MIN, JointOptions
from .problem import Observations, pcg
from .stacked import SplitWeights, StackedOperator, diag_normal, product, row_blocks

#: Blocks of rows the VET image's normal product is made in (:func:`solve_image`).
VET_ROW_BLOCKS = 2
#: The smoothness's band (:class:`~stages.deblur.band.Band`): a pixel, its right and its
#: lower neighbour.
SMOOTH_OFFSETS = [(0, 0), (0, 1), (1, 0)]


def smooth_weights(
    L: np.ndarray,
    ref: np.ndarray,
    prec: np.ndarray,
    lam: float,
    edge_rel: float,
    edge_snr: float = 0.0,
):
    """Edge weights of the relative smoothness for the x and y differences.

    The Charbonnier scale is ``edge_rel`` (relative); with ``edge_snr`` > 0 it falls to
    ``edge_snr`` times the pixel's relative noise where that is smaller (a well-exposed
    pixel's low-contrast texture is kept), never below :data:`EDGE_REL_MIN`.

    ``L`` (the image), ``ref`` (its reference levels) and ``prec`` (precisions) are
    (H, W, C); returns ``sx``, ``sy`` (H, W, C) float64, zero on the last column and the
    last row respectively.
    """
    edge = None
    if edge_snr > 0:
        electrons = np.maximum(prec * ref * ref, 1.0)
        edge = np.clip(edge_snr / np.sqrt(electrons), EDGE_REL_MIN, edge_rel)
    out = []
    # The x and y differences' weights on the pixels that have a right (lower) neighbour
    # (zero on the last column (row)), each in a few passes in place: the larger of the
    # two pixels' reference levels and edge scales, the smaller of their precisions.
    for here, there in (
        ((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
        ((slice(0, -1),), (slice(1, None),)),
    ):
        scale = np.maximum(ref[here], ref[there], dtype=np.float64)
        scale *= edge_rel if edge is None else np.maximum(edge[here], edge[there])
        t = np.true_divide(L[there] - L[here], scale, out=scale)
        t *= t
        t += 1.0
        np.sqrt(t, out=t)
        np.true_divide(1.0, t, out=t)  # (the Charbonnier factor)
        sm = np.minimum(prec[here], prec[there])
        sm *= lam
        sm *= t
        full = np.zeros(np.broadcast_shapes(L.shape, ref.shape, prec.shape), sm.dtype)
        full[here] = sm
        out.append(full)
    return out[0], out[1]


def smooth_bands(sx: np.ndarray, sy: np.ndarray) -> tuple[list[Band], np.ndarray]:
    """The smoothness's normal product, ``grad_adjoint(sx * gx, sy * gy)`` of an image's
    ``gx, gy = grad(img)``, as a band per channel (:class:`~stages.deblur.band.Band`,
    float32: its diagonal, and minus the weights of the x and y differences), and its
    diagonal (H, W, C) float64, for edge weights ``sx``, ``sy`` (H, W, C) whose last
    column and row are zero (:func:`smooth_weights`)."""
    dsm = np.zeros(sx.shape)
    dsm += sx
    dsm[:, 1:] += sx[:, :-1]
    dsm += sy
    dsm[1:] += sy[:-1]
    bands = [
        Band(SMOOTH_OFFSETS, np.stack([dsm[..., k], -sx[..., k], -sy[..., k]]).astype(np.float32))
        for k in range(sx.shape[2])
    ]
    return bands, dsm


@dataclass
class BinWeights:
    """The measuring bins' weights ``wb`` (B N, C) as one image step takes them
    (:func:`bin_weights`; the step adds its smoothness to their band, where they have
    one): ``split``, as the split groups take them (:meth:`StackedOperator.split_weights`);
    ``rhs``, the bins' share of the right-hand side ``Ab.T (wb yb)`` (N, C) float64; ``w``,
    ``wb`` itself where some group is not split (its products read it), else None: the
    caller then holds no (B N, C) weights through the solve."""

    split: SplitWeights
    rhs: np.ndarray
    w: np.ndarray | None


def bin_weights(Ab: StackedOperator, wb: np.ndarray, yb: np.ndarray) -> BinWeights:
    """``wb`` as :func:`solve_image` takes it, for the bins' data ``yb`` (B N, C)."""
    return BinWeights(Ab.split_weights(wb), Ab.mvt_weighted(wb, yb), None if Ab.all_split else wb)


def solve_image(
    obs: Observations,
    A: sp.csr_matrix,
    Ab: StackedOperator | None,
    w: np.ndarray,
    wb: np.ndarray | BinWeights | None,
    L: np.ndarray,
    ref: np.ndarray,
    anchor: np.ndarray,
    anchor_w: np.ndarray,
    opts: JointOptions,
    iters: int,
    expo: np.ndarray,
    callback: Callable[[int, np.ndarray], None] | None = None,
    free: np.ndarray | None = None,
    data_diag: np.ndarray | None = None,
    ws: np.ndarray | None = None,
    still: np.ndarray | None = None,
) -> np.ndarray:
    """One weighted least-squares image step (PCG), ``L`` of shape (H W, C).

    ``wb``: the bins' weights, or them as :func:`bin_weights` makes them (then with
    ``data_diag``).
    ``free`` (H W,) bool: the pixels re-estimated; the others keep their value in ``L``.
    ``data_diag``: the diagonal of the data terms' normal matrix for the preconditioner
    (computed from ``w``, ``wb`` when not given; any positive approximation will do).
    ``ws``: the weights of the measuring stream's term ``obs.stream`` (when it has one).
    ``still`` (H W,) bool: free pixels that no moving path touches, re-estimated from
    their data alone (no smoothness between two of them), as
    :func:`~stages.deblur.still_pixels.fuse_still` would where their columns do not
    overlap.
    """
    h, wd, c = obs.shape
    n = h * wd
    AT = A.T  # one transposed view for all the products below
    S = obs.stream
    prepared = wb if isinstance(wb, BinWeights) else None
    if prepared is not None:
        if data_diag is None:
            raise ValueError("bins' weights given as bin_weights makes them need data_diag")
        wb = prepared.w
    if data_diag is None:
        data_diag = diag_normal(A, w)
        if Ab is not None:
            data_diag = data_diag + Ab.diag_normal(wb)
        if S is not None:
            data_diag = data_diag + S.diag_normal(ws)
    rhs = product(AT, (w * obs.y).astype(np.float32)).astype(np.float64)
    if Ab is not None:
        rhs += prepared.rhs if prepared is not None else Ab.mvt_weighted(wb, obs.yb)
    if S is not None:
        rhs += S.adjoint(ws * S.y)
    rhs += anchor_w * anchor
    # Precision a pixel at the reference level would have from its own exposure alone
    # (electrons / rate^2): the prior's weight does not shrink where the data are
    # contaminated by bright light passing by, so the prior decides there.
    prec = (expo / ref.reshape(n, c)).reshape(h, wd, c)
    sx, sy = smooth_weights(L.reshape(h, wd, c), ref, prec, opts.lam, opts.edge_rel, opts.edge_snr)
    del prec
    if still is not None:
        st = still.reshape(h, wd, 1)
        sx[:, :-1] *= ~(st[:, :-1] & st[:, 1:])
        sy[:-1] *= ~(st[:-1] & st[1:])
    smooth, dsm = smooth_bands(sx, sy)
    del sx, sy
    diag = data_diag + dsm.reshape(n, c)
    del dsm
    diag += anchor_w
    anchored = np.flatnonzero(np.any(anchor_w != 0, axis=1))  # (few: pixels only bounded)

    threads = solve_threads()
    split = getattr(A, "convolution", None)
    if split is not None:
        # The VET image's operator as convolutions (stages.deblur.convolution), with
        # each channel's weights as they take them, for the whole solve.
        blocks = [None]
        split_w = [split.weights(w[:, k]) for k in range(c)]
    else:
        # The VET image's rows in blocks (views of A's arrays), so that its normal
        # product, the largest, is shared between threads like the bins' groups (as many
        # blocks whatever the threads: the pieces sum in one order, to the same image).
        blocks = row_blocks(A, VET_ROW_BLOCKS)
    # The bins' weights as their convolutions take them, for the whole solve.
    bins_w = None if Ab is None else prepared.split if prepared else Ab.split_weights(wb)
    if bins_w is not None and bins_w.bands is not None:
        # The smoothness's product in the bins' band (this solve's): one pass per offset
        # for both where they share one.
        bins_w.bands = [b.plus(sm) for b, sm in zip(bins_w.bands, smooth, strict=True)]
        smooth = None

    def vet_column(xc: np.ndarray, k: int, b: int) -> np.ndarray:
        # (The smoothness's product with the first block's, unless in the bins' band.)
        if split is not None:
            out = np.zeros((h, wd), np.float32)
            split.normal(xc.reshape(h, wd), split_w[k], out)
        else:
            Mb, MbT, r0, r1 = blocks[b]
            y = Mb @ xc
            y *= w[r0:r1, k]
            out = (MbT @ y).reshape(h, wd)
        if b == 0 and smooth is not None:
            smooth[k].normal(xc.reshape(h, wd), out)
        return out.reshape(-1)

    def apply_h(x: np.ndarray) -> np.ndarray:
        # ``x`` and the product (C, N), a channel's unknowns contiguous. The terms'
        # products in pieces (the VET image's with the smoothness's and each group of
        # bins', channel by channel) on the process's threads (scipy's sparse products
        # and numpy's and OpenCV's passes release the GIL); inline in a worker limited
        # to one.
        xs = [x[k].astype(np.float32) for k in range(c)]
        jobs = [
            (k, pool.submit(vet_column, xs[k], k, b)) for k in range(c) for b in range(len(blocks))
        ]
        if Ab is not None:
            jobs += [
                (k, pool.submit(Ab.normal_column, g, xs[k], wb, k, bins_w))
                for k in range(c)
                for g in range(len(Ab.groups))
            ]
        out = np.zeros((c, n))
        if S is not None:
            out += S.adjoint(ws * S.apply(np.ascontiguousarray(x.T))).T
        if anchored.size:
            out[:, anchored] += (anchor_w[anchored] * x[:, anchored].T).T
        for k, job in jobs:
            out[k] += job.result()
        return out

    cb = None if callback is None else (lambda k, x: callback(k, x.T))
    rhs, diag = np.ascontiguousarray(rhs.T), np.ascontiguousarray(diag.T)  # (C, N)
    # (OpenCV's convolutions on the pool's threads, not each on threads of its own.)
    with (
        ThreadPoolExecutor(threads) if threads > 1 else nullcontext(_Inline()) as pool,
        opencv_single_threaded(),
    ):
        x = pcg(apply_h, rhs, np.ascontiguousarray(L.T), diag, iters, callback=cb, free=free)
    return np.ascontiguousarray(x.T)


class _Inline:
    """A stand-in for an executor on one thread: ``submit`` defers the call to its
    ``result()``, so that the pieces are made one at a time as they are summed, not all
    held at once."""

    class _Deferred:
        def __init__(self, fn, args):
            self.fn, self.args = fn, args

        def result(self):
            return self.fn(*self.args)

    def submit(self, fn, *args):
        return self._Deferred(fn, args)
