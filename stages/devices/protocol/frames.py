"""LCoS protocol frame codec: the frame header, :class:`Frame` and :func:`encode_frame`.

Frame layout (all integers little-endian)::

    offset  size  field
    0       2     SYNC = A5 5A
    2       1     protocol version (1)
    3       2     seq, uint16 (host frames: host counter; device frames: device counter)
    5       1     command, uint8 (:class:`~stages.devices.protocol.messages.Command`)
    6       4     payload length N, uint32
    10      N     payload
    10+N    4     CRC-32 (zlib.crc32) over bytes 2 .. 10+N-1 (version .. payload)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .crc import CRC_BYTES, frame_crc
from .messages import (
    ACK_PAYLOAD_BYTES,
    INFO_REPLY_FIXED_BYTES,
    INFO_REPLY_MAX_BYTES,
    NAK_PAYLOAD_BYTES,
    OPEN_ALL_PAYLOAD_BYTES,
    Command,
)

__all__ = [
    "FRAME_OVERHEAD",
    "HEADER",
    "HEADER_BYTES",
    "PROTOCOL_VERSION",
    "SYNC",
    "Frame",
    "encode_frame",
    "length_ok",
]

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
HEADER_BYTES = 10  # SYNC(2) version(1) seq(2) command(1) length(4)
FRAME_OVERHEAD = HEADER_BYTES + CRC_BYTES

HEADER = struct.Struct("<2sBHBI")
_U32 = struct.Struct("<I")


@dataclass(frozen=True)
class Frame:
    """One decoded frame.

    Attributes
    ----------
    seq : int
        Sequence number, 0 .. 65535.
    command : Command
        What the frame asks or reports.
    payload : bytes
        Command-specific payload.
    version : int
        Protocol version byte.
    """

    seq: int
    command: Command
    payload: bytes
    version: int = PROTOCOL_VERSION

    def encode(self) -> bytes:
        """The frame's bytes on the wire."""
        return encode_frame(self.command, self.seq, self.payload, version=self.version)

    @property
    def wire_bytes(self) -> int:
        """Length of the frame on the wire, bytes."""
        return FRAME_OVERHEAD + len(self.payload)


def encode_frame(
    command: int, seq: int, payload: bytes = b"", *, version: int = PROTOCOL_VERSION
) -> bytes:
    """Build one frame.

    Parameters
    ----------
    command : int
        A :class:`Command` value.
    seq : int
        Sequence number, taken modulo 65536.
    payload : bytes
        Command payload.
    version : int
        Protocol version byte.

    Returns
    -------
    bytes
        ``SYNC | version | seq | command | len | payload | CRC-32``.
    """
    header = HEADER.pack(SYNC, version, seq & 0xFFFF, int(command), len(payload))
    return b"".join((header, payload, _U32.pack(frame_crc(header[2:], payload))))


def length_ok(command: int, length: int, max_payload: int) -> bool:
    """Whether a header's payload length is allowed for its command.

    Fixed-size payloads must match exactly; INFO_REPLY carries 0 .. 255 firmware bytes;
    FULL_MASK and CLOSE_DELTA carry 1 .. ``max_payload`` bytes. A parser checks this
    before waiting for the payload, so a corrupted or hostile length (up to 2**32 - 1)
    never makes it buffer more than one maximal frame.
    """
    if command == Command.INFO:
        return length == 0
    if command == Command.OPEN_ALL:
        return length == OPEN_ALL_PAYLOAD_BYTES
    if command == Command.ACK:
        return length == ACK_PAYLOAD_BYTES
    if command == Command.NAK:
        return length == NAK_PAYLOAD_BYTES
    if command == Command.INFO_REPLY:
        return INFO_REPLY_FIXED_BYTES <= length <= INFO_REPLY_MAX_BYTES
    if command in (Command.FULL_MASK, Command.CLOSE_DELTA):
        return 1 <= length <= max_payload
    return False
