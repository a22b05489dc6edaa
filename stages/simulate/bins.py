"""The measuring images a simulated VET capture keeps: every subframe, or time bins of
them, and what the rig's dropped frames take out (:func:`stages.simulate.simulate`)."""

from __future__ import annotations

import numpy as np

from ..formats.capture import measure_bin_edges


def measure_store(
    n_subframes: int, measure_bins: int | None, shape: tuple[int, ...]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Bin edges and the zeroed array the measuring images gather in (None, None for
    ``measure_bins`` 0): ``measure_bins`` None keeps every subframe, (K, *shape) int16
    (a subframe's whole DN, ``-black_level_dn .. max_dn``, fit exactly); N bins sum
    subframes in float32."""
    if measure_bins == 0:
        return None, None
    if measure_bins is None:
        measure_bins = n_subframes
    edges = measure_bin_edges(n_subframes, measure_bins)
    one_each = bool(np.all(np.diff(edges) == 1))
    dtype = np.int16 if one_each else np.float32
    return edges, np.zeros((len(edges) - 1, *shape), dtype)


def add_subframe(measure: np.ndarray, b: int, frame_dn: np.ndarray) -> None:
    """Gather one subframe (whole DN, float) into measuring image ``b``."""
    if measure.dtype == np.int16:
        np.rint(frame_dn, out=measure[b], casting="unsafe")
    else:
        measure[b] += frame_dn


class MeasureBins:
    """The measuring images of one simulated frame as they gather: ``n_subframes``
    subframes of ``shape`` (Hm, Wm, C) into ``measure_bins`` time bins
    (:func:`measure_store`; None keeps every subframe, 0 none)."""

    def __init__(self, n_subframes: int, measure_bins: int | None, shape: tuple[int, ...]):
        self.edges, self.measure = measure_store(n_subframes, measure_bins, shape)
        self.bin_of = (
            np.searchsorted(self.edges, np.arange(n_subframes), side="right") - 1
            if self.edges is not None
            else None
        )

    def add(self, j: int, frame_dn: np.ndarray) -> None:
        """Subframe ``j`` (DN, float) into its bin (none kept: nothing)."""
        if self.measure is not None:
            add_subframe(self.measure, self.bin_of[j], frame_dn)

    def images(
        self, subframe_s: float, offset_s: float, dropped: np.ndarray | None
    ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """``(measure, measure_times, counts)``: the bins, their ``[start, end)`` times on
        the rig's trigger clock (s, the nominal one shifted by ``offset_s``) and the
        subframes each holds, less the ``dropped`` subframes' (indices; a bin left empty
        goes); (None, None, None) when none are kept."""
        if self.measure is None:
            return None, None, None
        edges = self.edges
        times = np.stack([edges[:-1] * subframe_s, edges[1:] * subframe_s], axis=1) + offset_s
        counts = np.diff(edges)
        measure = self.measure
        if dropped is not None and len(dropped):
            lost = np.bincount(self.bin_of[dropped], minlength=len(counts))
            keep = counts > lost
            counts = (counts - lost)[keep]
            measure, times = measure[keep], times[keep]
        return measure, times, counts
