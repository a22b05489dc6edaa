"""The host end of the LCoS link: serial I/O, send window, retries and timeouts.

:class:`FrameLink` delivers host frames to the controller reliably and in order over any
pyserial transport, and hands each acknowledged frame, in sequence order, to its owner's
``commit`` callback. It knows nothing about masks or exposure times (that is
:class:`~stages.devices.lcos.serial_lcos.SerialLCoS`).

Every wait is bounded: a poll of the port waits ``poll_s``; a frame is resent after
``ack_timeout_s`` of silence (plus its own transmission time when the link rate is
known) and given up after ``1 + max_retries`` transmissions; a blocking call gives up
after ``flush_timeout_s``; a write may block ``write_timeout_s``. Received bytes go
through :class:`~stages.devices.protocol.FrameParser`, which never buffers more than
one maximal device frame whatever a length field claims.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np

from ...errors import DeviceError
from ..protocol import (
    DEVICE_COMMANDS,
    INFO_REPLY_MAX_BYTES,
    Ack,
    Command,
    DeviceInfo,
    Frame,
    FrameParser,
    ProtocolError,
    decode_ack,
    decode_info_reply,
    decode_nak,
    encode_frame,
)

__all__ = ["FrameLink", "LinkStats", "Outstanding", "SerialLike"]


class SerialLike(Protocol):
    """The part of :class:`serial.SerialBase` the driver uses."""

    timeout: float | None

    def write(self, data: bytes) -> int | None: ...

    def read(self, size: int = 1) -> bytes: ...

    @property
    def in_waiting(self) -> int: ...

    def close(self) -> None: ...


@dataclass
class LinkStats:
    """Counters of one link session.

    Attributes
    ----------
    frames_sent : int
        Distinct frames sent (first transmissions).
    retransmits : int
        Extra transmissions (after a NAK, a timeout or a lost acknowledgement).
    naks : int
        NAK frames received.
    timeouts : int
        Times the oldest unacknowledged frame waited longer than the ACK timeout.
    acks : int
        Acknowledgements (ACK or INFO_REPLY) that completed a frame.
    duplicate_acks : int
        Acknowledgements for frames already acknowledged (after retransmissions).
    resyncs : int
        FULL_MASK frames sent because an ACK's mask CRC disagreed with the host.
    bytes_sent, bytes_received : int
        Bytes written to and read from the transport.
    bad_frames : int
        Received frames with a CRC error (or abandoned partial frames).
    skipped_bytes : int
        Received bytes discarded while resynchronising.
    max_ack_delay_s : float
        Longest time from a frame's first transmission to its acknowledgement.
    total_ack_delay_s : float
        Sum of those delays (see :attr:`mean_ack_delay_s`).
    """

    frames_sent: int = 0
    retransmits: int = 0
    naks: int = 0
    timeouts: int = 0
    acks: int = 0
    duplicate_acks: int = 0
    resyncs: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    bad_frames: int = 0
    skipped_bytes: int = 0
    max_ack_delay_s: float = 0.0
    total_ack_delay_s: float = 0.0

    @property
    def mean_ack_delay_s(self) -> float:
        """Mean time from first transmission to acknowledgement, seconds."""
        return self.total_ack_delay_s / self.acks if self.acks else 0.0

    def as_dict(self) -> dict[str, Any]:
        """All counters plus ``mean_ack_delay_s``, for logs and capture metadata."""
        d = asdict(self)
        d["mean_ack_delay_s"] = self.mean_ack_delay_s
        return d


@dataclass
class Outstanding:
    """A frame sent and not yet committed (with what its owner needs to commit it)."""

    seq: int
    command: Command
    wire: bytes
    cells: np.ndarray | None = None  # CLOSE_DELTA: the cells it newly closes
    mask: np.ndarray | None = None  # FULL_MASK: the state it sets
    frame_index: int = -1  # OPEN_ALL
    resync: bool = False
    first_sent: float = 0.0
    last_sent: float = 0.0
    tx_order: int = 0
    transmissions: int = 0
    last_problem: str = ""
    ack: Ack | None = None
    info: DeviceInfo | None = None


class FrameLink:
    """Reliable, ordered delivery of host frames over a serial-like port.

    Frames go out with increasing sequence numbers; up to ``window`` may be
    unacknowledged at once. The device processes frames strictly in order, so:

    * a NAK names the next frame it expects: every unacknowledged frame from there on
      is resent (go-back-N);
    * an ACK for a frame sent after an unacknowledged one means the earlier ACK was
      lost: the earlier frame is resent and the device answers from its reply cache;
    * if nothing arrives for ``ack_timeout_s`` (plus the frame's own transmission time
      when ``link_bps`` is known), the oldest unacknowledged frame and those after it
      are resent;
    * a frame transmitted ``1 + max_retries`` times without acknowledgement raises
      :class:`~stages.errors.DeviceError` saying what the device sent since its last
      useful reply (:meth:`device_behaviour`);
    * only replies that move the session on (an ACK of an outstanding frame, a NAK
      naming one) restart the silence timer: replayed ACKs cannot keep it alive;
    * an ACK naming a frame not yet sent raises :class:`~stages.errors.DeviceError` at
      once (the device is lying or confused).

    Acknowledged frames are passed to ``commit`` in sequence order; after each batch of
    received frames ``after_rx`` runs (the owner may send from it).

    Parameters
    ----------
    port : str or serial-like object
        A pyserial URL or device path (opened with :func:`serial.serial_for_url`), or an
        already open object with ``read``/``write``/``in_waiting``/``timeout`` (its
        ``timeout`` is set to ``poll_s``).
    commit : callable(Outstanding)
        Called with each acknowledged frame, in sequence order.
    after_rx : callable()
        Called after received frames have been handled and committed.
    baudrate, link_bps, bits_per_byte, ack_timeout_s, max_retries, window, poll_s,
    write_timeout_s, flush_timeout_s
        As for :class:`~stages.devices.lcos.serial_lcos.SerialLCoS`.

    Raises
    ------
    ValueError
        On an out-of-range setting.
    DeviceError
        If the port cannot be opened.
    """

    def __init__(
        self,
        port: str | SerialLike,
        *,
        commit: Callable[[Outstanding], None],
        after_rx: Callable[[], None],
        baudrate: int | None = None,
        link_bps: float | None = None,
        bits_per_byte: int = 10,
        ack_timeout_s: float = 0.5,
        max_retries: int = 8,
        window: int = 8,
        poll_s: float = 0.002,
        write_timeout_s: float = 10.0,
        flush_timeout_s: float = 30.0,
    ) -> None:
        if not 1 <= window <= 256:
            raise ValueError(f"window must be 1 to 256 frames, got {window}.")
        if ack_timeout_s <= 0 or poll_s <= 0:
            raise ValueError("ack_timeout_s and poll_s must be positive.")
        if max_retries < 0:
            raise ValueError(f"max_retries must be non-negative, got {max_retries}.")
        if isinstance(port, str):
            self.name = port
            self._port = self._open_url(port, baudrate, poll_s, write_timeout_s)
        else:
            self.name = str(
                getattr(port, "name", None) or getattr(port, "port", None) or type(port).__name__
            )
            self._port = port
            self._port.timeout = poll_s
        self.link_bps = float(link_bps) if link_bps else (float(baudrate) if baudrate else None)
        self.bits_per_byte = int(bits_per_byte)
        self.ack_timeout_s = float(ack_timeout_s)
        self.max_retries = int(max_retries)
        self.window = int(window)
        self.write_timeout_s = float(write_timeout_s)
        self.flush_timeout_s = float(flush_timeout_s)
        self._commit_cb = commit
        self._after_rx = after_rx
        self._parser = FrameParser(INFO_REPLY_MAX_BYTES, DEVICE_COMMANDS)
        self._stats = LinkStats()
        self._seq = 0
        self._tx_order = 0
        self.pending: collections.deque[Outstanding] = collections.deque()
        self._by_seq: dict[int, Outstanding] = {}
        self._rx: collections.deque[Frame] = collections.deque()
        self._last_rx = time.monotonic()
        self._baseline = self._counts()
        self.closed = False

    @staticmethod
    def _open_url(
        url: str, baudrate: int | None, poll_s: float, write_timeout_s: float
    ) -> SerialLike:
        import serial  # pyserial

        kwargs: dict[str, Any] = {"timeout": poll_s, "write_timeout": write_timeout_s}
        if baudrate:
            kwargs["baudrate"] = int(baudrate)
        try:
            return serial.serial_for_url(url, **kwargs)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open the LCoS link {url!r}: {exc}") from exc

    @property
    def stats(self) -> LinkStats:
        """Link counters (parser counters folded in)."""
        self._stats.bad_frames = self._parser.bad_frames
        self._stats.skipped_bytes = self._parser.skipped_bytes
        return self._stats

    def is_pending(self, rec: Outstanding) -> bool:
        """Whether ``rec`` is still waiting to be committed."""
        return self._by_seq.get(rec.seq) is rec

    def close(self) -> None:
        """Close the port (does not wait for outstanding frames)."""
        if not self.closed:
            self.closed = True
            try:
                self._port.close()
            except Exception:  # closing a dead port must not mask the real error
                pass

    # -- sending -----------------------------------------------------------------------
    def send(self, command: Command, payload: bytes, **meta: Any) -> Outstanding:
        """Send one frame (waiting for a free slot in the window unless ``resync``).

        ``meta`` fills the :class:`Outstanding` fields the owner commits from.
        """
        if self.closed:
            raise DeviceError(f"the LCoS link {self.name} is closed")
        resync = bool(meta.get("resync", False))
        if not resync:
            self.wait(
                lambda: len(self.pending) < self.window, None, "a free slot in the send window"
            )
        seq = self._seq
        self._seq = (seq + 1) & 0xFFFF
        rec = Outstanding(
            seq=seq, command=command, wire=encode_frame(command, seq, payload), **meta
        )
        self.pending.append(rec)
        self._by_seq[seq] = rec
        self._stats.frames_sent += 1
        self._transmit(rec)
        self.process_rx()
        return rec

    def _transmit(self, rec: Outstanding) -> None:
        if rec.transmissions > self.max_retries:
            problem = rec.last_problem or f"no valid reply within {self.ack_timeout_s:g} s"
            raise DeviceError(
                f"the LCoS on {self.name} did not acknowledge frame {rec.seq} ({rec.command.name}) "
                f"after {rec.transmissions} transmissions (last problem: {problem}); since its "
                f"last useful reply the device sent {self.device_behaviour()}"
            )
        if rec.transmissions:
            self._stats.retransmits += 1
        chunk = 16384
        data = rec.wire
        if not rec.transmissions:
            rec.first_sent = time.monotonic()
        try:
            for start in range(0, len(data), chunk):
                self._port.write(data[start : start + chunk])
                self._read_available()
        except OSError as exc:  # serial.SerialException is an OSError
            raise self._link_error(exc) from exc
        rec.last_sent = time.monotonic()
        rec.transmissions += 1
        self._tx_order += 1
        rec.tx_order = self._tx_order
        self._stats.bytes_sent += len(data)

    def _resend_from(self, first: Outstanding, problem: str) -> None:
        """Go back: resend ``first`` and every later unacknowledged frame, in order."""
        started = False
        for rec in list(self.pending):
            started = started or rec is first
            if started and rec.ack is None and rec.seq in self._by_seq:
                rec.last_problem = problem
                self._transmit(rec)

    # -- receiving ---------------------------------------------------------------------
    def _link_error(self, exc: BaseException) -> DeviceError:
        import serial

        if isinstance(exc, DeviceError):
            return exc
        if isinstance(exc, serial.SerialTimeoutException):
            return DeviceError(
                f"writing to the LCoS link {self.name} timed out after {self.write_timeout_s:g} s: "
                "the link is stalled (device not reading?)"
            )
        return DeviceError(f"lost the LCoS link {self.name}: {exc}")

    def _feed(self, data: bytes) -> None:
        if data:
            self._stats.bytes_received += len(data)
            self._rx.extend(self._parser.feed(data))

    def _read_available(self) -> None:
        """Read whatever has arrived without blocking (frames are queued, not handled)."""
        try:
            n = self._port.in_waiting
            if n:
                self._feed(self._port.read(n))
        except OSError as exc:  # serial.SerialException is an OSError
            raise self._link_error(exc) from exc

    def _read_blocking(self) -> None:
        """Wait up to ``poll_s`` for bytes, then take everything available."""
        try:
            data = self._port.read(1)
            if data:
                n = self._port.in_waiting
                if n:
                    data += self._port.read(n)
            self._feed(data)
        except OSError as exc:  # serial.SerialException is an OSError
            raise self._link_error(exc) from exc

    def service(self, block: bool) -> None:
        """One turn of the link: read, handle replies, commit, resend on timeout."""
        if block and not self._rx:
            self._read_blocking()
        else:
            self._read_available()
        self.process_rx()
        self._check_timeout()

    def process_rx(self) -> None:
        """Handle the frames received so far, commit in order, then run ``after_rx``."""
        while self._rx:
            self._handle(self._rx.popleft())
        while self.pending and self.pending[0].ack is not None:
            rec = self.pending.popleft()
            del self._by_seq[rec.seq]
            self._commit_cb(rec)
        self._after_rx()

    def _counts(self) -> dict[str, int]:
        p, s = self._parser, self._stats
        return {
            "bytes": s.bytes_received,
            "skipped": p.skipped_bytes,
            "bad_crc": p.bad_frames - p.truncated,
            "truncated": p.truncated,
            "bad_headers": p.bad_headers,
            "replays": s.duplicate_acks,
            "naks": s.naks,
        }

    def _progress(self) -> None:
        """A reply that moved the session on: restart the silence timer and the tally."""
        self._last_rx = time.monotonic()
        self._baseline = self._counts()

    def device_behaviour(self) -> str:
        """What the device sent since its last useful reply, in words."""
        now, base = self._counts(), self._baseline
        d = {k: now[k] - base[k] for k in now}
        if not d["bytes"]:
            return "nothing at all"
        parts = []
        if d["bad_headers"]:
            parts.append(
                f"{d['bad_headers']} impossible frame header(s) "
                f"(last: {self._parser.last_bad_header})"
            )
        if d["bad_crc"]:
            parts.append(f"{d['bad_crc']} frame(s) with a bad CRC")
        if d["truncated"]:
            parts.append(f"{d['truncated']} truncated frame(s)")
        if d["replays"]:
            parts.append(
                f"{d['replays']} replayed acknowledgement(s) of frames already acknowledged"
            )
        if d["naks"]:
            parts.append(f"{d['naks']} NAK(s)")
        if d["skipped"] and not (d["bad_headers"] or d["bad_crc"] or d["truncated"]):
            parts.append(f"{d['skipped']} bytes of garbage")
        elif d["skipped"]:
            parts.append(f"{d['skipped']} bytes that were not frames in all")
        return ", ".join(parts) if parts else f"{d['bytes']} bytes that completed no frame"

    def _handle(self, frame: Frame) -> None:
        try:
            if frame.command == Command.NAK:
                nak = decode_nak(frame.payload)
                self._stats.naks += 1
                rec = self._by_seq.get(nak.expected_seq)
                if rec is not None and rec.ack is None:
                    self._last_rx = time.monotonic()
                    self._resend_from(rec, f"NAK {nak.reason.name}")
                return
            if frame.command == Command.INFO_REPLY:
                info = decode_info_reply(frame.payload)
                ack = Ack(info.seq, info.subframe, info.mask_crc)
            else:
                info = None
                ack = decode_ack(frame.payload)
        except ProtocolError as exc:
            raise DeviceError(
                f"the LCoS on {self.name} sent a malformed {frame.command.name}: {exc}"
            ) from exc
        if (ack.seq - self._seq) & 0xFFFF < 0x8000:
            raise DeviceError(
                f"the LCoS on {self.name} acknowledged frame {ack.seq}, which was never sent "
                f"(the last frame sent was {(self._seq - 1) & 0xFFFF})"
            )
        rec = self._by_seq.get(ack.seq)
        if rec is None or rec.ack is not None:
            self._stats.duplicate_acks += 1  # a replay: no progress, the timer runs on
            return
        if (rec.command == Command.INFO) != (info is not None):
            raise DeviceError(
                f"the LCoS on {self.name} answered frame {rec.seq} ({rec.command.name}) with {frame.command.name}"
            )
        rec.ack, rec.info = ack, info
        self._progress()
        delay = self._last_rx - rec.first_sent
        self._stats.acks += 1
        self._stats.total_ack_delay_s += delay
        self._stats.max_ack_delay_s = max(self._stats.max_ack_delay_s, delay)
        # The device works in order: an earlier frame last sent before this one and
        # still unacknowledged had its ACK lost on the way back.
        for older in list(self.pending):
            if older is rec:
                break
            if older.ack is None and older.tx_order < rec.tx_order:
                older.last_problem = "acknowledgement lost"
                self._transmit(older)

    def _check_timeout(self) -> None:
        oldest = next((r for r in self.pending if r.ack is None), None)
        if oldest is None:
            return
        limit = self.ack_timeout_s
        if self.link_bps:
            limit += len(oldest.wire) * self.bits_per_byte / self.link_bps
        if time.monotonic() - max(oldest.last_sent, self._last_rx) > limit:
            self._stats.timeouts += 1
            self._parser.expire()
            self._rx.extend(self._parser.feed(b""))
            self.process_rx()
            if oldest.ack is None and oldest.seq in self._by_seq:
                self._resend_from(oldest, f"no valid reply within {limit:g} s")

    def wait(self, done: Callable[[], bool], timeout_s: float | None, what: str) -> None:
        """Service the link until ``done()`` holds.

        Raises
        ------
        DeviceError
            After ``timeout_s`` (default ``flush_timeout_s``), naming ``what``.
        """
        limit = self.flush_timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + limit
        while not done():
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"gave up after {limit:g} s waiting for {what} on the LCoS link {self.name} "
                    f"({len(self.pending)} frames unacknowledged)"
                )
            self.service(block=True)

    def wait_acked(self, rec: Outstanding) -> Ack:
        """Wait until ``rec`` is committed; returns its acknowledgement."""
        self.wait(lambda: not self.is_pending(rec), None, f"the acknowledgement of frame {rec.seq}")
        assert rec.ack is not None
        return rec.ack
