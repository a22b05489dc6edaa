"""LCoS protocol message types: commands, reasons, encodings and the small payloads.

Every payload here has a fixed layout (little-endian); ``docs/lcos-protocol.md`` §3
gives the byte tables. Decoders raise :class:`ProtocolError` on anything that does not
match, never another exception, and never allocate more than the payload they are given.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

__all__ = [
    "ACK_PAYLOAD_BYTES",
    "DEVICE_COMMANDS",
    "HOST_COMMANDS",
    "INFO_REPLY_FIXED_BYTES",
    "INFO_REPLY_MAX_BYTES",
    "MAX_CELLS",
    "NAK_PAYLOAD_BYTES",
    "OPEN_ALL_PAYLOAD_BYTES",
    "Ack",
    "Command",
    "DeviceInfo",
    "Encoding",
    "Nak",
    "NakReason",
    "ProtocolError",
    "decode_ack",
    "decode_info_reply",
    "decode_nak",
    "decode_open_all",
    "encode_ack",
    "encode_info_reply",
    "encode_nak",
    "encode_open_all",
]

ACK_PAYLOAD_BYTES = 10  # seq u16, applied subframe u32, mask CRC u32
NAK_PAYLOAD_BYTES = 3  # expected seq u16, reason u8
OPEN_ALL_PAYLOAD_BYTES = 4  # frame index u32
INFO_REPLY_FIXED_BYTES = 22
INFO_REPLY_MAX_BYTES = INFO_REPLY_FIXED_BYTES + 255
MAX_CELLS = 1 << 26  # 8 MiB bitmap: far above any LCoS, low enough to bound buffers

_ACK = struct.Struct("<HII")
_NAK = struct.Struct("<HB")
_INFO = struct.Struct("<HBHHHfIIB")
_U32 = struct.Struct("<I")


class ProtocolError(ValueError):
    """A payload that does not decode (malformed, truncated or out of range)."""


class Command(enum.IntEnum):
    """Frame commands. Host to device: the first four; device to host: the rest."""

    INFO = 0x01  #: request device information; answered by INFO_REPLY
    OPEN_ALL = 0x02  #: open every cell and start frame ``frame_index``
    FULL_MASK = 0x03  #: set the whole mask (calibration patterns, resynchronisation)
    CLOSE_DELTA = 0x04  #: close the listed cells (tagged :class:`Encoding`)
    ACK = 0x06  #: frame applied: seq, applied subframe, mask CRC
    NAK = 0x15  #: frame rejected: next expected seq, reason
    INFO_REPLY = 0x81  #: answer to INFO (also acknowledges it)


HOST_COMMANDS = frozenset({Command.INFO, Command.OPEN_ALL, Command.FULL_MASK, Command.CLOSE_DELTA})
DEVICE_COMMANDS = frozenset({Command.ACK, Command.NAK, Command.INFO_REPLY})


class NakReason(enum.IntEnum):
    """Why the device rejected a frame (NAK payload byte 2)."""

    BAD_CRC = 1  #: a frame arrived damaged (CRC mismatch or truncated)
    OUT_OF_ORDER = 2  #: a frame arrived after a gap in the sequence numbers
    BAD_PAYLOAD = 3  #: intact frame whose payload does not decode for its command
    UNKNOWN_COMMAND = 4  #: intact frame with a command the device does not accept


class Encoding(enum.IntEnum):
    """Tag byte (payload byte 0) of a CLOSE_DELTA."""

    INDICES = 0x01  #: LEB128 varints: first index, then (gap - 1) between indices
    RUNS = 0x02  #: LEB128 varint pairs: (start - previous run end - 1, length - 1)
    BITMAP = 0x03  #: packed bitmap of the whole grid


@dataclass(frozen=True)
class Ack:
    """ACK payload: the device applied frame ``seq`` at subframe ``applied_subframe``."""

    seq: int
    applied_subframe: int
    mask_crc: int


@dataclass(frozen=True)
class Nak:
    """NAK payload: the device wants frame ``expected_seq`` next, for ``reason``."""

    expected_seq: int
    reason: NakReason


@dataclass(frozen=True)
class DeviceInfo:
    """What an LCoS controller reports about itself (INFO_REPLY).

    Attributes
    ----------
    cells : (int, int)
        Grid size (width, height) in cells.
    protocol_version : int
        Protocol version the device speaks.
    latency_subframes : int
        Subframes between a frame's arrival and the subframe it is applied at.
    leakage : float
        Transmittance of a closed cell (0 = perfect shutter).
    subframe : int
        The device's subframe clock when it answered.
    mask_crc : int
        CRC-32 of the device's packed mask when it answered.
    firmware : str
        Free-form firmware identification (at most 255 UTF-8 bytes).
    seq : int
        Sequence number of the INFO request this answers.
    """

    cells: tuple[int, int]
    protocol_version: int
    latency_subframes: int
    leakage: float
    subframe: int
    mask_crc: int
    firmware: str
    seq: int = 0

    @property
    def n_cells(self) -> int:
        """Number of cells, ``W * H``."""
        return self.cells[0] * self.cells[1]


def encode_open_all(frame_index: int) -> bytes:
    """OPEN_ALL payload: the frame index, uint32."""
    return _U32.pack(int(frame_index) & 0xFFFFFFFF)


def decode_open_all(payload: bytes) -> int:
    """Frame index from an OPEN_ALL payload."""
    if len(payload) != OPEN_ALL_PAYLOAD_BYTES:
        raise ProtocolError(f"OPEN_ALL payload must be 4 bytes, got {len(payload)}.")
    return _U32.unpack(payload)[0]


def encode_ack(seq: int, applied_subframe: int, mask_crc_value: int) -> bytes:
    """ACK payload: acknowledged seq (u16), applied subframe (u32), mask CRC-32 (u32)."""
    return _ACK.pack(
        seq & 0xFFFF, int(applied_subframe) & 0xFFFFFFFF, int(mask_crc_value) & 0xFFFFFFFF
    )


def decode_ack(payload: bytes) -> Ack:
    """Decode an ACK payload."""
    if len(payload) != ACK_PAYLOAD_BYTES:
        raise ProtocolError(f"ACK payload must be {ACK_PAYLOAD_BYTES} bytes, got {len(payload)}.")
    return Ack(*_ACK.unpack(payload))


def encode_nak(expected_seq: int, reason: NakReason) -> bytes:
    """NAK payload: the seq the device expects next (u16) and a :class:`NakReason` (u8)."""
    return _NAK.pack(expected_seq & 0xFFFF, int(reason))


def decode_nak(payload: bytes) -> Nak:
    """Decode a NAK payload (unknown reason codes raise :class:`ProtocolError`)."""
    if len(payload) != NAK_PAYLOAD_BYTES:
        raise ProtocolError(f"NAK payload must be {NAK_PAYLOAD_BYTES} bytes, got {len(payload)}.")
    seq, reason = _NAK.unpack(payload)
    try:
        return Nak(seq, NakReason(reason))
    except ValueError:
        raise ProtocolError(f"NAK carries unknown reason code {reason}.") from None


def encode_info_reply(info: DeviceInfo) -> bytes:
    """INFO_REPLY payload (see ``docs/lcos-protocol.md`` for the layout)."""
    fw = info.firmware.encode("utf-8")[:255]
    return (
        _INFO.pack(
            info.seq & 0xFFFF,
            info.protocol_version,
            info.cells[0],
            info.cells[1],
            info.latency_subframes,
            info.leakage,
            info.subframe & 0xFFFFFFFF,
            info.mask_crc & 0xFFFFFFFF,
            len(fw),
        )
        + fw
    )


def decode_info_reply(payload: bytes) -> DeviceInfo:
    """Decode an INFO_REPLY payload, checking the grid size is sane."""
    if len(payload) < INFO_REPLY_FIXED_BYTES:
        raise ProtocolError(f"INFO_REPLY payload too short ({len(payload)} bytes).")
    seq, version, w, h, latency, leakage, subframe, crc, fw_len = _INFO.unpack_from(payload)
    if len(payload) != INFO_REPLY_FIXED_BYTES + fw_len:
        raise ProtocolError("INFO_REPLY firmware string length does not match the payload.")
    if w == 0 or h == 0 or w * h > MAX_CELLS:
        raise ProtocolError(f"INFO_REPLY reports an implausible grid of {w}x{h} cells.")
    firmware = payload[INFO_REPLY_FIXED_BYTES:].decode("utf-8", errors="replace")
    return DeviceInfo(
        cells=(w, h),
        protocol_version=version,
        latency_subframes=latency,
        leakage=float(f"{leakage:.7g}"),  # float32 on the wire: drop the binary noise
        subframe=subframe,
        mask_crc=crc,
        firmware=firmware,
        seq=seq,
    )
