"""The relations a capture's metadata holds between its fields, beyond each field's type.

:func:`check_capture` runs inside :class:`stages.formats.schema.CaptureMeta`'s validation
(each field already of its type and range) and raises ``ValueError("field: ...")``, which
the schema reports as one line naming the file and the field:

- ``measure_times``: each bin ``[start, end)`` inside the frame, the bins in order and
  disjoint, each made of whole subframes on the rig's clock (``trigger_offset_s + j
  subframe_s``);
- ``measure_subframes``: one count per bin, each at most its bin's subframes and at least
  those less the dropped subframes that fall in it;
- ``measure_dropped``: subframe indices of the frame, in increasing order, each once;
- ``integration_s``: within the frame.

Tolerances are for rounding alone (times are stored as decimal JSON numbers).
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Subframes by which a bin's edge may miss the rig's clock (rounding of stored times).
CLOCK_TOLERANCE = 1e-4


def check_capture(meta: Any) -> None:
    """Raise ValueError naming the first field of ``meta`` (a validated capture's
    metadata model) that contradicts another."""
    rig = meta.rig
    frame = rig.frame_s
    if meta.integration_s is not None and meta.integration_s > frame * (1 + 1e-6):
        raise ValueError(
            f"integration_s: {meta.integration_s} s; allowed at most the frame "
            f"(frame_s = {frame} s)"
        )
    n_sub = int(np.floor(frame / rig.subframe_s + 1e-9))
    dropped = _dropped(meta.measure_dropped, n_sub)
    times = meta.measure_times or []
    spans = _bin_spans(times, rig)
    counts = meta.measure_subframes
    if counts is not None and meta.measure_times is not None:
        if len(counts) != len(times):
            raise ValueError(
                f"measure_subframes: {len(counts)} counts for {len(times)} time bins "
                "(measure_times); allowed one count per bin"
            )
        _check_counts(spans, counts, dropped)


def _dropped(indices: list[int] | None, n_sub: int) -> np.ndarray:
    """The dropped subframes, checked: increasing, each once, within the frame."""
    if not indices:
        return np.zeros(0, int)
    d = np.asarray(indices, np.int64)
    if len(d) > n_sub or int(d.max()) >= n_sub:
        raise ValueError(
            f"measure_dropped: {len(d)} indices up to {int(d.max())}; allowed indices of the "
            f"frame's {n_sub} subframes (0 to {n_sub - 1}), each once"
        )
    bad = np.flatnonzero(np.diff(d) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise ValueError(
            f"measure_dropped.{k}: {int(d[k])} after {int(d[k - 1])}; allowed increasing "
            "subframe indices, each once"
        )
    return d


def _bin_spans(times: list[list[float]], rig: Any) -> np.ndarray:
    """Each bin's first subframe and its subframes, (B, 2) int, from its ``[start, end)``
    (checked: inside the frame, in order, disjoint, on the rig's subframe clock)."""
    t = np.asarray(times, np.float64).reshape(-1, 2)
    frame, tau, off = rig.frame_s, rig.subframe_s, rig.trigger_offset_s
    top = frame * (1 + 1e-6)
    for b, (start, end) in enumerate(t):
        if not 0 <= start < end <= top:
            raise ValueError(
                f"measure_times.{b}: [{start}, {end}] s; allowed 0 <= start < end <= "
                f"frame_s ({frame} s)"
            )
        if b and start < t[b - 1, 1] - CLOCK_TOLERANCE * tau:
            raise ValueError(
                f"measure_times.{b}: [{start}, {end}] s begins before bin {b - 1} ends "
                f"({t[b - 1, 1]} s); allowed bins in order of time, disjoint"
            )
    edges = (t - off) / tau
    whole = np.rint(edges)
    miss = np.abs(edges - whole) > CLOCK_TOLERANCE * np.maximum(1.0, np.abs(whole))
    if miss.any():
        b = int(np.flatnonzero(miss.any(axis=1))[0])
        raise ValueError(
            f"measure_times.{b}: [{t[b, 0]}, {t[b, 1]}] s is not whole subframes on the rig's "
            f"clock (trigger_offset_s + j * subframe_s = {off:g} + j * {tau:g} s)"
        )
    return np.stack([whole[:, 0], whole[:, 1] - whole[:, 0]], axis=1).astype(np.int64)


def _check_counts(spans: np.ndarray, counts: list[int], dropped: np.ndarray) -> None:
    """Each bin sums its subframes, less at most those dropped within it."""
    for b, ((first, n), count) in enumerate(zip(spans, counts, strict=True)):
        lost = int(np.count_nonzero((dropped >= first) & (dropped < first + n)))
        if not n - lost <= count <= n:
            also = f", {lost} of them dropped" if lost else ""
            raise ValueError(
                f"measure_subframes.{b}: {count} subframes in a bin of {n} (measure_times.{b}"
                f"{also}); allowed {n - lost} to {n}"
            )
