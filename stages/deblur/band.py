"""The weighted normal product of many small shifted convolutions as one banded operator.

A shifted convolution's rows (:class:`~stages.deblur.convolution._Kernel`: row ``r``
reads ``f[r + s] = sum_u k[u] x[r + s + u]``), weighted by ``wt``, have the normal
product ``K.T diag(wt) K``. With ``m`` the weights put at the rows' pixels moved by the
shift (what :meth:`~stages.deblur.convolution.ConvolutionSplit.weights` makes), it is
the banded operator

    (K.T diag(wt) K x)[p] = sum_d c_d[p] x[p + d],   c_d[p] = sum_u k[u] k[u + d] m[p - u],

whose offsets ``d`` are the differences of the kernel's taps. Many kernels of the same
small extent (the measuring bins' short blurs, one or a few per bin, at shifts of their
own) share those offsets: their sum is one band, ``sum_d c_d x(. + d)`` over the union,
made once for a set of weights (:func:`make_band`), and each product of a solve is then
a multiply-add per offset where the kernels took two correlations, a product and a sum
each. The band is symmetric, ``c_{-d}[p + d] = c_d[p]``, so only the offsets ``d >= 0``
(row-major order) are held, each applied both ways.

The product is exact, in float32 (the sums in another order). Every coefficient ``c_d[p]``
is non-zero only where some kernel's row reads both ``p`` and ``p + d``, inside the image
(a kernel takes only rows whose stencil lies inside, :mod:`stages.deblur.convolution`).

Shapes: images (H, W) float32; offsets (dy, dx) in pixels.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from .convolution import PASS_COST, _span, kernel_cost

#: Cost of one offset's multiply-add over the image, in the units of
#: :data:`~stages.deblur.convolution.PASS_COST` (``make bench``'s ``bench_products``
#: measures both sides).
OFFSET_COST = 5 * PASS_COST


def _taps(small: np.ndarray) -> list[tuple[int, int, float]]:
    """The non-zero taps ``(uy, ux, value)`` of a kernel."""
    uy, ux = np.nonzero(small)
    return [(int(a), int(b), float(small[a, b])) for a, b in zip(uy, ux, strict=True)]


def _half(dy: int, dx: int) -> bool:
    """Whether offset (dy, dx) is zero or after it in row-major order (the half held)."""
    return dy > 0 or (dy == 0 and dx >= 0)


def offsets(kernels: Iterable) -> list[tuple[int, int]]:
    """The offsets ``d >= 0`` of the band of ``kernels`` (the differences of each one's
    taps), sorted; a one-tap kernel (``tap`` set) adds the zero offset alone."""
    out = {(0, 0)}
    for k in kernels:
        taps = _taps(k.small)
        for ay, ax, _ in taps:
            for by, bx, _ in taps:
                if _half(by - ay, bx - ax):
                    out.add((by - ay, bx - ax))
    return sorted(out)


def band_worth(kernels: list) -> bool:
    """Whether the band of ``kernels`` costs less per product than their convolutions
    (:func:`~stages.deblur.convolution.kernel_cost`)."""
    conv = sum(kernel_cost(k.small) for k in kernels)
    n = len(offsets(kernels))
    return (2 * n - 1) * OFFSET_COST < conv


@dataclass
class Band:
    """``sum_d c_d[p] x[p + d]`` over the offsets ``d`` and their opposites: ``offsets``
    (the half held, ``d >= 0``), ``coeffs`` (len(offsets), H, W) float32."""

    offsets: list[tuple[int, int]]
    coeffs: np.ndarray

    def plus(self, other: Band) -> Band:
        """The band of both products' sum (on the union of their offsets)."""
        offs = sorted(set(self.offsets) | set(other.offsets))
        at = {d: i for i, d in enumerate(offs)}
        coeffs = np.zeros((len(offs), *self.coeffs.shape[1:]), np.float32)
        for band in (self, other):
            for d, c in zip(band.offsets, band.coeffs, strict=True):
                coeffs[at[d]] += c
        return Band(offs, coeffs)

    def normal(self, x: np.ndarray, out: np.ndarray) -> None:
        """Add the band's product with ``x`` to ``out``, both (H, W) float32 (each term a
        fused multiply-add over the image: OpenCV's ``accumulateProduct``, in place on
        the views)."""
        h, w = x.shape
        for (dy, dx), c in zip(self.offsets, self.coeffs, strict=True):
            if dy == 0 and dx == 0:
                cv2.accumulateProduct(c, x, out)
                continue
            (py, qy), (px, qx) = _span(dy, h), _span(dx, w)
            if py.stop == py.start or px.stop == px.start:
                continue  # (the offset is the whole image or more: no pixel reads it)
            cv2.accumulateProduct(c[py, px], x[qy, qx], out[py, px])  # p reads p + d
            cv2.accumulateProduct(c[py, px], x[py, px], out[qy, qx])  # p + d reads p


def make_band(pairs: Iterable, offs: list[tuple[int, int]], shape: tuple[int, int]) -> Band:
    """The band of kernels and their weights, ``pairs`` of (kernel, ``m``: the weights at
    its rows' pixels moved by its shift, times the tap squared for a one-tap kernel, as
    :meth:`~stages.deblur.convolution.ConvolutionSplit.weights` makes them), on the
    offsets ``offs`` (:func:`offsets` of the kernels). ``pairs`` may be a generator: each
    ``m`` is read once, as it comes."""
    h, w = shape
    at = {d: i for i, d in enumerate(offs)}
    coeffs = np.zeros((len(offs), h, w), np.float32)
    for k, m in pairs:
        if k.tap is not None:  # (m holds the tap squared)
            coeffs[at[(0, 0)]] += m
            continue
        # c_d[p] += sum_u g[u] m[p - u], g[u] = k[u] k[u + d]: the correlation of m with
        # g flipped, anchored at its far corner (zero outside the image).
        ky, kx = k.small.shape
        big = np.zeros((3 * ky - 2, 3 * kx - 2), np.float32)  # (k[u + d] at u + d + k - 1)
        big[ky - 1 : 2 * ky - 1, kx - 1 : 2 * kx - 1] = k.small
        for (dy, dx), i in at.items():
            if dy >= ky or abs(dx) >= kx:
                continue
            g = k.small * big[ky - 1 + dy : 2 * ky - 1 + dy, kx - 1 + dx : 2 * kx - 1 + dx]
            if g.any():
                coeffs[i] += cv2.filter2D(
                    m, -1, g[::-1, ::-1], anchor=(kx - 1, ky - 1), borderType=cv2.BORDER_CONSTANT
                )
    return Band(offs, coeffs)
