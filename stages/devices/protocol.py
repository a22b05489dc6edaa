"""The LCoS link protocol: frames, payloads, closure encodings and a streaming parser.

Pure functions on bytes and arrays, no I/O; the host driver (:mod:`stages.devices.lcos`)
and the emulated controller (:mod:`stages.devices.lcos_emulator`) both speak it. The
normative description, with byte tables, a worked example and the bandwidth arithmetic,
is ``docs/lcos-protocol.md``.

Frame layout (all integers little-endian)::

    offset  size  field
    0       2     SYNC = A5 5A
    2       1     protocol version (1)
    3       2     seq, uint16 (host frames: host counter; device frames: device counter)
    5       1     command, uint8 (:class:`Command`)
    6       4     payload length N, uint32
    10      N     payload
    10+N    4     CRC-32 (zlib.crc32) over bytes 2 .. 10+N-1 (version .. payload)

Cells are numbered row-major: cell ``(x, y)`` of a ``W x H`` grid is ``y * W + x``.
Masks are bitmaps with bit ``i % 8`` (least significant first) of byte ``i // 8`` set
when cell ``i`` is closed; bits past the last cell are zero.
"""

from __future__ import annotations

import enum
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "ACK_PAYLOAD_BYTES",
    "FRAME_OVERHEAD",
    "HEADER_BYTES",
    "INFO_REPLY_MAX_BYTES",
    "MAX_CELLS",
    "NAK_PAYLOAD_BYTES",
    "PROTOCOL_VERSION",
    "SYNC",
    "Ack",
    "Command",
    "DeviceInfo",
    "Encoding",
    "Frame",
    "FrameParser",
    "Nak",
    "NakReason",
    "ProtocolError",
    "bitmap_bytes",
    "closure_sizes",
    "decode_ack",
    "decode_closures",
    "decode_info_reply",
    "decode_nak",
    "decode_open_all",
    "encode_ack",
    "encode_closures",
    "encode_frame",
    "encode_info_reply",
    "encode_nak",
    "encode_open_all",
    "mask_crc",
    "max_payload_bytes",
    "pack_mask",
    "unpack_mask",
    "varint_sizes",
]

SYNC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
HEADER_BYTES = 10  # SYNC(2) version(1) seq(2) command(1) length(4)
CRC_BYTES = 4
FRAME_OVERHEAD = HEADER_BYTES + CRC_BYTES
ACK_PAYLOAD_BYTES = 10  # seq u16, applied subframe u32, mask CRC u32
NAK_PAYLOAD_BYTES = 3  # expected seq u16, reason u8
OPEN_ALL_PAYLOAD_BYTES = 4  # frame index u32
INFO_REPLY_FIXED_BYTES = 22
INFO_REPLY_MAX_BYTES = INFO_REPLY_FIXED_BYTES + 255
MAX_CELLS = 1 << 26  # 8 MiB bitmap: far above any LCoS, low enough to bound buffers
MAX_VARINT_BYTES = 5  # a uint32 needs at most 5 LEB128 bytes

_HEADER = struct.Struct("<2sBHBI")
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


# --- frames -------------------------------------------------------------------------


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
    header = _HEADER.pack(SYNC, version, seq & 0xFFFF, int(command), len(payload))
    crc = zlib.crc32(payload, zlib.crc32(header[2:])) & 0xFFFFFFFF
    return b"".join((header, payload, _U32.pack(crc)))


def bitmap_bytes(n_cells: int) -> int:
    """Bytes of a packed bitmap over ``n_cells`` cells, ``ceil(n_cells / 8)``."""
    return (int(n_cells) + 7) // 8


def max_payload_bytes(n_cells: int) -> int:
    """Largest payload a device with ``n_cells`` cells accepts (a tagged bitmap delta)."""
    return 1 + bitmap_bytes(n_cells)


def _length_ok(command: int, length: int, max_payload: int) -> bool:
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


class FrameParser:
    """Streaming frame parser that resynchronises on garbage.

    Feed it bytes as they arrive; it yields every complete frame whose header is
    plausible and whose CRC matches. A header is plausible when it starts with SYNC,
    carries :data:`PROTOCOL_VERSION`, a known command and a payload length allowed for
    that command and at most ``max_payload`` (so a corrupted length never makes the
    parser wait for more than one maximal frame). After a CRC failure or an implausible
    header the parser drops the first byte and scans for the next SYNC, so frames
    following a damaged one are still found.

    Parameters
    ----------
    max_payload : int
        Largest payload accepted, bytes. Hosts use :data:`INFO_REPLY_MAX_BYTES`; a
        device with ``n`` cells uses :func:`max_payload_bytes` ``(n)``.
    commands : iterable of Command, optional
        Commands accepted (default: all).

    Attributes
    ----------
    frames : int
        Valid frames yielded so far.
    bad_frames : int
        Frames with a plausible header but a wrong CRC, plus partial frames abandoned
        by :meth:`expire`.
    skipped_bytes : int
        Bytes discarded while hunting for SYNC (garbage and the remains of bad frames).
    """

    def __init__(
        self, max_payload: int = INFO_REPLY_MAX_BYTES, commands: frozenset[Command] | None = None
    ):
        if max_payload < 0:
            raise ValueError(f"max_payload must be non-negative, got {max_payload}.")
        self.max_payload = int(max_payload)
        self.commands = frozenset(Command) if commands is None else frozenset(commands)
        self._buf = bytearray()
        self.frames = 0
        self.bad_frames = 0
        self.skipped_bytes = 0

    @property
    def pending(self) -> int:
        """Bytes buffered but not yet resolved into frames or garbage."""
        return len(self._buf)

    def feed(self, data: bytes) -> Iterator[Frame]:
        """Add received bytes and yield the frames they complete.

        Parameters
        ----------
        data : bytes
            Bytes in arrival order.

        Yields
        ------
        Frame
            Each complete, CRC-valid frame, in order.
        """
        for kind, item in self.feed_events(data):
            if kind == "frame":
                yield item  # type: ignore[misc]

    def feed_events(self, data: bytes) -> Iterator[tuple[str, Frame | bytes]]:
        """Like :meth:`feed` but also yield discarded bytes.

        Yields ``("frame", Frame)`` and ``("garbage", bytes)`` in stream order; every
        byte fed comes out exactly once, either inside a frame or as garbage (a
        wire tap uses this to pass a stream through unchanged).
        """
        self._buf += data
        yield from self._parse()

    def expire(self) -> bytes:
        """Abandon a partial frame that stopped arriving (the link went idle).

        A byte corrupted inside the length field can announce a payload that never
        comes; after an idle gap the owner calls this: the partial frame counts as bad,
        its first byte is dropped and the rest is rescanned (call :meth:`feed` with
        ``b""`` to collect frames found in it).

        Returns
        -------
        bytes
            The dropped byte (empty if nothing was pending).
        """
        if not self._buf:
            return b""
        if len(self._buf) >= 2 and self._buf[:2] == SYNC:
            self.bad_frames += 1
        dropped = bytes(self._buf[:1])
        del self._buf[:1]
        self.skipped_bytes += 1
        return dropped

    def take_pending(self) -> bytes:
        """Remove and return the buffered bytes unparsed (a pass-through tap going idle)."""
        data = bytes(self._buf)
        self._buf.clear()
        return data

    def reset(self) -> None:
        """Forget buffered bytes (counters are kept)."""
        self.skipped_bytes += len(self._buf)
        self._buf.clear()

    def _skip(self, n: int) -> bytes:
        dropped = bytes(self._buf[:n])
        del self._buf[:n]
        self.skipped_bytes += n
        return dropped

    def _parse(self) -> Iterator[tuple[str, Frame | bytes]]:
        buf = self._buf
        while buf:
            start = buf.find(SYNC)
            if start < 0:
                # keep a trailing A5: it may be the first half of SYNC
                keep = 1 if buf[-1] == SYNC[0] else 0
                if len(buf) > keep:
                    yield "garbage", self._skip(len(buf) - keep)
                return
            if start > 0:
                yield "garbage", self._skip(start)
            if len(buf) < HEADER_BYTES:
                return
            _, version, seq, command, length = _HEADER.unpack_from(buf, 0)
            if (
                version != PROTOCOL_VERSION
                or command not in self.commands
                or not _length_ok(command, length, self.max_payload)
            ):
                yield "garbage", self._skip(1)
                continue
            total = HEADER_BYTES + length + CRC_BYTES
            if len(buf) < total:
                return
            body = bytes(buf[HEADER_BYTES : HEADER_BYTES + length])
            (crc,) = _U32.unpack_from(buf, HEADER_BYTES + length)
            if zlib.crc32(body, zlib.crc32(bytes(buf[2:HEADER_BYTES]))) & 0xFFFFFFFF != crc:
                self.bad_frames += 1
                yield "garbage", self._skip(1)
                continue
            del buf[:total]
            self.frames += 1
            yield "frame", Frame(seq=seq, command=Command(command), payload=body, version=version)


# --- small payloads -----------------------------------------------------------------


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


# --- masks --------------------------------------------------------------------------


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


# --- closure encodings --------------------------------------------------------------


def varint_sizes(values: np.ndarray) -> np.ndarray:
    """LEB128 length in bytes of each non-negative value (1 byte per 7 bits, min 1)."""
    v = np.asarray(values, dtype=np.uint64)
    sizes = np.ones(v.shape, dtype=np.int64)
    for k in range(1, MAX_VARINT_BYTES):
        sizes += v >= np.uint64(1 << (7 * k))
    return sizes


def _varint_encode(values: np.ndarray) -> bytes:
    v = np.asarray(values, dtype=np.uint64)
    if v.size == 0:
        return b""
    if int(v.max()) >= 1 << 35:
        raise ValueError("varint value out of range")
    sizes = varint_sizes(v)
    offsets = np.cumsum(sizes) - sizes
    out = np.empty(int(sizes.sum()), dtype=np.uint8)
    for k in range(int(sizes.max())):
        sel = sizes > k
        chunk = (v[sel] >> np.uint64(7 * k)) & np.uint64(0x7F)
        more = (sizes[sel] > k + 1).astype(np.uint64) << np.uint64(7)
        out[offsets[sel] + k] = (chunk | more).astype(np.uint8)
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


def _as_sorted_indices(cell_indices: ArrayLike, n_cells: int) -> np.ndarray:
    idx = np.asarray(cell_indices)
    if idx.dtype == bool:
        if idx.size != n_cells:
            raise ValueError(
                f"a boolean closure mask must have {n_cells} elements, got {idx.size}."
            )
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
    idx = _as_sorted_indices(cell_indices, n_cells)
    return _sizes(idx, n_cells)


def _sizes(idx: np.ndarray, n_cells: int) -> dict[Encoding, int]:
    starts, lengths = _runs(idx)
    return {
        Encoding.INDICES: 1 + int(varint_sizes(_index_values(idx)).sum()),
        Encoding.RUNS: 1 + int(varint_sizes(_run_values(starts, lengths)).sum()),
        Encoding.BITMAP: 1 + bitmap_bytes(n_cells),
    }


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
    idx = _as_sorted_indices(cell_indices, n_cells)
    if encoding is None:
        sizes = _sizes(idx, n_cells)
        best = min(sizes, key=lambda enc: (sizes[enc], int(enc)))
    else:
        best = Encoding(encoding)
    if best == Encoding.INDICES:
        body = _varint_encode(_index_values(idx))
    elif best == Encoding.RUNS:
        body = _varint_encode(_run_values(*_runs(idx)))
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
