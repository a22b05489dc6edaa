"""CLOSE_DELTA closure encodings: LEB128 index gaps, runs, or a bitmap, smallest wins.

See :class:`~stages.devices.protocol.messages.Encoding` for the three layouts and
``docs/lcos-protocol.md`` §4 for the size arithmetic. Decoders bound every count by the
grid size before allocating.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .masks import bitmap_bytes, pack_mask, unpack_mask
from .messages import MAX_CELLS, Encoding, ProtocolError

__all__ = [
    "closure_sizes",
    "decode_closures",
    "encode_closures",
    "sorted_cell_indices",
    "varint_sizes",
]

MAX_VARINT_BYTES = 5  # a uint32 needs at most 5 LEB128 bytes


_VARINT_STEPS = tuple(1 << (7 * k) for k in range(1, MAX_VARINT_BYTES))


def varint_sizes(values: np.ndarray) -> np.ndarray:
    """LEB128 length in bytes of each non-negative value (1 byte per 7 bits, min 1)."""
    v = np.asarray(values)
    if v.dtype != np.int64:
        v = v.astype(np.uint64)
    sizes = np.ones(v.shape, dtype=np.int64)
    for step in _VARINT_STEPS:
        sizes += v >= step
    return sizes


def _varint_encode(values: np.ndarray) -> bytes:
    v = np.asarray(values)
    if v.size == 0:
        return b""
    if int(v.max()) >= 1 << 35:
        raise ValueError("varint value out of range")
    v = v.astype(np.int64, copy=False)
    sizes = varint_sizes(v)
    ends = np.cumsum(sizes)
    starts = ends - sizes
    out = np.empty(int(ends[-1]), dtype=np.uint8)
    # Byte k of every value that has one: its k-th 7-bit group, the top bit set when
    # more follow (all values have byte 0; few have the later ones).
    out[starts] = (v & 0x7F) | ((sizes > 1) << 7)
    sel = np.flatnonzero(sizes > 1)
    k = 1
    while sel.size:
        more = sizes[sel] > k + 1
        out[starts[sel] + k] = ((v[sel] >> (7 * k)) & 0x7F) | (more << 7)
        sel = sel[more]
        k += 1
    return out.tobytes()


def _varint_decode(data: bytes) -> np.ndarray:
    b = np.frombuffer(data, dtype=np.uint8)
    if b.size == 0:
        return np.zeros(0, dtype=np.uint64)
    last = (b & 0x80) == 0
    if not last[-1]:
        raise ProtocolError("varint stream is truncated (last byte has the continuation bit).")
    ends = np.flatnonzero(last)
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts + 1
    if lengths.max() > MAX_VARINT_BYTES:
        raise ProtocolError("varint longer than 5 bytes.")
    pos = np.arange(b.size) - np.repeat(starts, lengths)
    parts = (b & 0x7F).astype(np.uint64) << (np.uint64(7) * pos.astype(np.uint64))
    return np.add.reduceat(parts, starts)


def sorted_cell_indices(cell_indices: ArrayLike, n_cells: int) -> np.ndarray:
    """Sorted unique row-major cell indices from indices (any order, duplicates allowed)
    or from a boolean mask of ``n_cells`` elements.

    Returns
    -------
    ndarray of int64, shape (n,)

    Raises
    ------
    ValueError
        If a mask has the wrong size, indices are not integers or lie outside
        ``[0, n_cells)``.
    """
    idx = np.asarray(cell_indices)
    if idx.dtype == bool:
        if idx.size != n_cells:
            raise ValueError(f"a boolean cell mask must have {n_cells} elements, got {idx.size}.")
        return np.flatnonzero(idx.ravel())
    if idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"cell indices must be integers, got dtype {idx.dtype}.")
    idx = idx.ravel().astype(np.int64, copy=False)
    if idx.size > 1 and bool(np.all(idx[1:] > idx[:-1])):
        lo, hi = int(idx[0]), int(idx[-1])
    else:
        lo, hi = int(idx.min()), int(idx.max())
        if lo >= 0 and hi < n_cells:
            if n_cells <= 16 * idx.size:  # scatter into a mask: O(n_cells), no sort
                mask = np.zeros(n_cells, dtype=bool)
                mask[idx] = True
                idx = np.flatnonzero(mask)
            else:
                idx = np.unique(idx)
    if lo < 0 or hi >= n_cells:
        raise ValueError(f"cell indices must lie in [0, {n_cells}); got {lo} .. {hi}.")
    return idx


def _runs(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximal runs (start, length) of a sorted unique index array."""
    if idx.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    breaks = np.flatnonzero(np.diff(idx) != 1)
    first = np.concatenate(([0], breaks + 1))
    last = np.concatenate((breaks, [idx.size - 1]))
    return idx[first], last - first + 1


def _run_values(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    prev_end = np.zeros_like(starts)
    prev_end[1:] = starts[:-1] + lengths[:-1] + 1
    values = np.empty(2 * starts.size, dtype=np.int64)
    values[0::2] = starts - prev_end
    values[1::2] = lengths - 1
    return values


def _index_values(idx: np.ndarray) -> np.ndarray:
    values = np.empty_like(idx)
    if idx.size:
        values[0] = idx[0]
        values[1:] = np.diff(idx) - 1
    return values


def closure_sizes(cell_indices: ArrayLike, n_cells: int) -> dict[Encoding, int]:
    """Payload size in bytes (tag included) of each encoding of a closure set.

    Parameters
    ----------
    cell_indices : array_like of int, or bool mask of n_cells elements
        Cells to close (row-major indices; duplicates and order do not matter).
    n_cells : int
        Cells in the grid.

    Returns
    -------
    dict
        ``{Encoding.INDICES: 1 + sum L(d_k), Encoding.RUNS: 1 + sum L(g_j) + L(len_j - 1),
        Encoding.BITMAP: 1 + ceil(n_cells / 8)}`` with ``L`` the LEB128 length.
    """
    idx = sorted_cell_indices(cell_indices, n_cells)
    return _sizes(idx, n_cells)


def _sizes(idx: np.ndarray, n_cells: int) -> dict[Encoding, int]:
    starts, lengths = _runs(idx)
    return {
        Encoding.INDICES: 1 + int(varint_sizes(_index_values(idx)).sum()),
        Encoding.RUNS: 1 + int(varint_sizes(_run_values(starts, lengths)).sum()),
        Encoding.BITMAP: 1 + bitmap_bytes(n_cells),
    }


def _list_values(idx: np.ndarray, enc: Encoding) -> np.ndarray:
    """The varint values of the INDICES or RUNS encoding of ``idx``."""
    return _index_values(idx) if enc == Encoding.INDICES else _run_values(*_runs(idx))


def _smallest(idx: np.ndarray, n_cells: int) -> tuple[Encoding, np.ndarray | None]:
    """The encoding :func:`_sizes` makes smallest (ties to the lower tag), with its varint
    values when it is a list; a list is sized only when its lower bound (a byte per value)
    does not settle the choice."""
    n_runs = 1 + int(np.count_nonzero(np.diff(idx) != 1)) if idx.size else 0
    low = {Encoding.INDICES: 1 + idx.size, Encoding.RUNS: 1 + 2 * n_runs}
    exact = {Encoding.BITMAP: 1 + bitmap_bytes(n_cells)}
    values: dict[Encoding, np.ndarray] = {}
    # Size the list with the lower bound first: often that alone beats the other's bound.
    for enc in sorted(low, key=lambda e: (low[e], int(e))):
        if min(exact.values()) < low[enc] or (
            min(exact.values()) == low[enc] and min(exact, key=int) < enc
        ):
            continue  # cannot win
        values[enc] = _list_values(idx, enc)
        exact[enc] = 1 + int(varint_sizes(values[enc]).sum())
    best = min(exact, key=lambda e: (exact[e], int(e)))
    return best, values.get(best)


def encode_closures(
    cell_indices: ArrayLike, n_cells: int, encoding: Encoding | None = None
) -> bytes:
    """Encode a set of newly closed cells as a CLOSE_DELTA payload, smallest encoding wins.

    The three encodings (see :class:`Encoding`) are sized first with vectorised varint
    arithmetic, and only the smallest is built; ties go to INDICES, then RUNS, then
    BITMAP. An empty set encodes as the single tag byte of INDICES.

    Parameters
    ----------
    cell_indices : array_like of int, or bool mask of n_cells elements
        Row-major indices of the cells to close, in ``[0, n_cells)``; duplicates and
        order do not matter.
    n_cells : int
        Cells in the grid (``W * H``).
    encoding : Encoding, optional
        Force one encoding instead of the smallest (for tests and measurements).

    Returns
    -------
    bytes
        Tag byte followed by the encoded set.

    Raises
    ------
    ValueError
        If an index is out of range or the input is not integer/boolean.
    """
    if not 0 < n_cells <= MAX_CELLS:
        raise ValueError(f"n_cells must be in (0, {MAX_CELLS}], got {n_cells}.")
    idx = sorted_cell_indices(cell_indices, n_cells)
    if encoding is None:
        best, values = _smallest(idx, n_cells)
    else:
        best, values = Encoding(encoding), None
    if best != Encoding.BITMAP:
        body = _varint_encode(_list_values(idx, best) if values is None else values)
    else:
        mask = np.zeros(n_cells, dtype=bool)
        mask[idx] = True
        body = pack_mask(mask)
    return bytes((int(best),)) + body


def decode_closures(payload: bytes, n_cells: int) -> np.ndarray:
    """Decode a CLOSE_DELTA payload.

    Parameters
    ----------
    payload : bytes
        Tag byte and encoded set, as made by :func:`encode_closures`.
    n_cells : int
        Cells in the grid.

    Returns
    -------
    ndarray of int64, shape (n,)
        Sorted, unique row-major cell indices in ``[0, n_cells)``.

    Raises
    ------
    ProtocolError
        On an unknown tag, a malformed body or an index outside the grid.
    """
    if not payload:
        raise ProtocolError("CLOSE_DELTA payload is empty (no encoding tag).")
    tag, body = payload[0], payload[1:]
    if tag == Encoding.BITMAP:
        return np.flatnonzero(unpack_mask(body, n_cells)).astype(np.int64)
    if tag == Encoding.INDICES:
        values = _varint_decode(body)
        if values.size == 0:
            return np.zeros(0, dtype=np.int64)
        if values.size > n_cells:
            raise ProtocolError("index list is longer than the grid.")
        idx = np.cumsum(values + np.uint64(1)) - np.uint64(1)
        if int(idx[-1]) >= n_cells:
            raise ProtocolError(
                f"index list reaches cell {int(idx[-1])}, outside a {n_cells}-cell grid."
            )
        return idx.astype(np.int64)
    if tag == Encoding.RUNS:
        values = _varint_decode(body)
        if values.size % 2:
            raise ProtocolError("run list has an odd number of values.")
        if values.size == 0:
            return np.zeros(0, dtype=np.int64)
        if values.size // 2 > n_cells:
            raise ProtocolError("run list is longer than the grid.")
        gaps = values[0::2].astype(np.int64)
        lengths = values[1::2].astype(np.int64) + 1
        step = lengths + 1
        starts = np.cumsum(gaps) + np.cumsum(step) - step
        if int(starts[-1] + lengths[-1]) > n_cells:
            raise ProtocolError(f"run list reaches past the end of a {n_cells}-cell grid.")
        offsets = np.cumsum(lengths) - lengths
        total = int(lengths.sum())
        return np.repeat(starts - offsets, lengths) + np.arange(total, dtype=np.int64)
    raise ProtocolError(f"unknown CLOSE_DELTA encoding tag 0x{tag:02x}.")
