"""A capture's measuring stream summed into time bins, which still gives every coarser
time bin made of whole bins of it, as the stream would to the bit.

A stream of integer DN (int16, uint16) summed in float32 is exact while every sum stays
below 2**24 in magnitude: a bin made of whole bins of those sums is then the same float32
image as the bin summed from the stream's frames, in any order. So once a stream is
binned for the misfit (in its own memory, :meth:`~stages.formats.capture.Capture.time_bins`
with ``consume``), the motion estimate can still read its coarser bins
(:meth:`StreamSums.time_bin`) without the stream being held.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from .capture import Capture, bin_span, bin_times, measure_bin_edges

#: Float32 holds every integer of at most this magnitude exactly.
EXACT_FLOAT32 = 1 << 24


class StreamSums:
    """What the motion estimate reads of a stream capture (:attr:`shape`, :attr:`rig`,
    :attr:`keeps_stream`, :attr:`measure_shape`, :meth:`bin_times`, :meth:`time_bin`),
    served from ``bins``: the stream's time bins (:meth:`Capture.time_bins`) over its
    subframes ``edges`` (S + 1,), with the stream's ``times`` (F, 2) s and subframe
    ``counts`` (F,). A bin whose subframes are not whole bins of these raises
    ValueError (:func:`serves` says beforehand)."""

    keeps_stream = True

    def __init__(self, bins: Capture, stream_shape: tuple[int, ...], times, counts, edges):
        self.bins = bins
        self.measure_shape = tuple(stream_shape)
        self.measure_times = np.asarray(times, np.float64)
        self.counts = np.asarray(counts, int)
        self.edges = np.asarray(edges, int)

    @property
    def shape(self) -> tuple[int, int]:
        return self.bins.shape

    @property
    def rig(self):
        return self.bins.rig

    def bin_times(self, n_bins: int) -> np.ndarray:
        """As :meth:`Capture.bin_times` of the stream."""
        return bin_times(self.measure_times, n_bins)

    def time_bin(self, n_bins: int, k: int) -> Capture:
        """As :meth:`Capture.time_bin` of the stream: bin ``k`` of ``n_bins``, summed
        from the whole bins it spans (float32 (1, H, W, C))."""
        a, b = bin_span(self.measure_shape[0], n_bins, k)
        i, j = np.searchsorted(self.edges, [a, b])
        if i >= len(self.edges) or j >= len(self.edges) or self.edges[i] != a or self.edges[j] != b:
            raise ValueError(f"subframes {a}:{b} are not whole bins of the stream's sums")
        total = np.sum(self.bins.measure[i:j], axis=0, dtype=np.float32)[None]
        meta = {**self.bins.meta, "measure_subframes": [int(self.counts[a:b].sum())]}
        times = np.array([[self.measure_times[a, 0], self.measure_times[b - 1, 1]]])
        return replace(self.bins, measure=total, measure_times=times, meta=meta)

    def time_bins(self, n_bins: int) -> Capture:
        """As :meth:`Capture.time_bins` of the stream (a stream has more subframes than
        bins), each bin by :meth:`time_bin`."""
        parts = [self.time_bin(n_bins, k) for k in range(n_bins)]
        meta = {
            **self.bins.meta,
            "measure_subframes": [p.meta["measure_subframes"][0] for p in parts],
        }
        return replace(
            self.bins,
            measure=np.concatenate([p.measure for p in parts]),
            measure_times=self.bin_times(n_bins),
            meta=meta,
        )


def serves(cap: Capture, n_bins: int, wanted: Iterable[int]) -> bool:
    """Whether ``cap``'s stream summed into ``n_bins`` time bins gives each binning of
    ``wanted`` (counts of bins) exactly: integer DN whose sums stay exact in float32, and
    every edge of those binnings an edge of its ``n_bins``."""
    stream = cap.measure
    if stream is None or not np.issubdtype(stream.dtype, np.integer):
        return False
    info = np.iinfo(stream.dtype)
    n = stream.shape[0]
    if n * max(abs(int(info.min)), int(info.max)) >= EXACT_FLOAT32:
        return False
    have = set(measure_bin_edges(n, n_bins).tolist())
    return all(set(measure_bin_edges(n, m).tolist()) <= have for m in wanted)


def summed_stream(cap: Capture, n_bins: int) -> tuple[Capture, StreamSums]:
    """``cap``'s stream summed into ``n_bins`` time bins in its own memory (``cap`` lets
    it go: :meth:`Capture.time_bins` with ``consume``), and those sums as the stream's
    :class:`StreamSums`. Check :func:`serves` first."""
    shape, times, counts = cap.measure.shape, cap.measure_times, cap.measure_counts()
    edges = measure_bin_edges(shape[0], n_bins)
    bins = cap.time_bins(n_bins, consume=True)
    return bins, StreamSums(bins, shape, times, counts, edges)
