"""LCoS protocol streaming parser: frames out of a byte stream, resynchronising on garbage."""

from __future__ import annotations

import struct
from collections.abc import Iterator

from .crc import CRC_BYTES, frame_crc
from .frames import HEADER, HEADER_BYTES, PROTOCOL_VERSION, SYNC, Frame, length_ok
from .messages import INFO_REPLY_MAX_BYTES, Command

__all__ = ["FrameParser"]

_U32 = struct.Struct("<I")


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
    truncated : int
        Partial frames abandoned by :meth:`expire` (also counted in ``bad_frames``).
    bad_headers : int
        Headers starting with SYNC whose version, command or length is impossible
        (their bytes are counted in ``skipped_bytes``).
    last_bad_header : str
        What the last impossible header said, in words (empty before any).
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
        self.truncated = 0
        self.bad_headers = 0
        self.last_bad_header = ""

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
            self.truncated += 1
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
            _, version, seq, command, length = HEADER.unpack_from(buf, 0)
            if (
                version != PROTOCOL_VERSION
                or command not in self.commands
                or not length_ok(command, length, self.max_payload)
            ):
                self.bad_headers += 1
                self.last_bad_header = _describe_header(version, command, length, self.commands)
                yield "garbage", self._skip(1)
                continue
            total = HEADER_BYTES + length + CRC_BYTES
            if len(buf) < total:
                return
            body = bytes(buf[HEADER_BYTES : HEADER_BYTES + length])
            (crc,) = _U32.unpack_from(buf, HEADER_BYTES + length)
            if frame_crc(bytes(buf[2:HEADER_BYTES]), body) != crc:
                self.bad_frames += 1
                yield "garbage", self._skip(1)
                continue
            del buf[:total]
            self.frames += 1
            yield "frame", Frame(seq=seq, command=Command(command), payload=body, version=version)


def _describe_header(version: int, command: int, length: int, accepted: frozenset) -> str:
    """An impossible header in words (for error messages)."""
    if version != PROTOCOL_VERSION:
        return f"a header of protocol version {version}"
    if command not in accepted:
        known = command in Command._value2member_map_
        return f"a {Command(command).name} frame" if known else f"unknown command 0x{command:02x}"
    return f"{Command(command).name} header announcing {length} payload bytes"
