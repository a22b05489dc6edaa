"""CRC-32 of the LCoS protocol: over a frame's bytes, and over a mask state.

Both are ``zlib.crc32`` (the IEEE 802.3 polynomial, as in PNG and gzip), unsigned.
"""

from __future__ import annotations

import zlib

from numpy.typing import ArrayLike

from .masks import pack_mask

__all__ = ["CRC_BYTES", "frame_crc", "mask_crc"]

CRC_BYTES = 4


def frame_crc(header_tail: bytes, payload: bytes) -> int:
    """CRC-32 a frame carries: over version, seq, command, length (``header_tail``,
    the header without SYNC) and then the payload.

    Returns
    -------
    int
        Unsigned 32-bit CRC.
    """
    return zlib.crc32(payload, zlib.crc32(header_tail)) & 0xFFFFFFFF


def mask_crc(closed: ArrayLike) -> int:
    """CRC-32 of a mask state: ``zlib.crc32(pack_mask(closed))``.

    Parameters
    ----------
    closed : array_like of bool
        Closed cells, shape (H, W) or (H * W,), row-major.

    Returns
    -------
    int
        Unsigned 32-bit CRC, as carried by ACK and INFO_REPLY.
    """
    return zlib.crc32(pack_mask(closed)) & 0xFFFFFFFF
