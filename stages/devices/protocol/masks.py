"""LCoS protocol mask bitmaps: packing a boolean mask into the wire format and back.

Cells are numbered row-major: cell ``(x, y)`` of a ``W x H`` grid is ``y * W + x``.
A mask is a bitmap with bit ``i % 8`` (least significant first) of byte ``i // 8`` set
when cell ``i`` is closed; bits past the last cell are zero.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .messages import ProtocolError

__all__ = ["bitmap_bytes", "max_payload_bytes", "pack_mask", "unpack_mask"]


def bitmap_bytes(n_cells: int) -> int:
    """Bytes of a packed bitmap over ``n_cells`` cells, ``ceil(n_cells / 8)``."""
    return (int(n_cells) + 7) // 8


def max_payload_bytes(n_cells: int) -> int:
    """Largest payload a device with ``n_cells`` cells accepts (a tagged bitmap delta)."""
    return 1 + bitmap_bytes(n_cells)


def pack_mask(closed: ArrayLike) -> bytes:
    """Pack a boolean mask (any shape, row-major) into the wire bitmap (LSB first)."""
    flat = np.ascontiguousarray(closed, dtype=bool).ravel()
    return np.packbits(flat, bitorder="little").tobytes()


def unpack_mask(payload: bytes, n_cells: int) -> np.ndarray:
    """Unpack a wire bitmap into a boolean array of shape (n_cells,).

    Raises
    ------
    ProtocolError
        If the length is not ``ceil(n_cells / 8)`` or a padding bit is set.
    """
    if len(payload) != bitmap_bytes(n_cells):
        raise ProtocolError(
            f"bitmap must be {bitmap_bytes(n_cells)} bytes for {n_cells} cells, got {len(payload)}."
        )
    bits = np.unpackbits(np.frombuffer(payload, dtype=np.uint8), bitorder="little")
    if bits[n_cells:].any():
        raise ProtocolError("bitmap sets padding bits past the last cell.")
    return bits[:n_cells].astype(bool)
