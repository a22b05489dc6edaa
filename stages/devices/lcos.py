"""Host-side LCoS shutter drivers.

:class:`LCoSDevice` is the abstract device the capture loop talks to: public methods
validate their arguments and call ``_do_*`` hooks that a concrete driver implements
(the python-microscope pattern). :class:`SerialLCoS` drives a controller that speaks the
framed protocol of :mod:`stages.devices.protocol` over any pyserial transport
(``/dev/ttyACM0``, ``socket://host:port``, ``loop://``, a pty path) or over any object
with pyserial's ``read``/``write``/``in_waiting`` interface (the in-process emulator).

The driver keeps a *mirror* of the mask the host intends and a *committed* copy that
follows the device's acknowledgements frame by frame. The exposure-time record
(:attr:`LCoSDevice.applied_subframe`) is written only from acknowledgements, so T always
comes from when the device says it applied a closure, never from when the host asked.
"""

from __future__ import annotations

import abc
import collections
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DeviceError
from .protocol import (
    DEVICE_COMMANDS,
    INFO_REPLY_MAX_BYTES,
    PROTOCOL_VERSION,
    Ack,
    Command,
    DeviceInfo,
    Frame,
    FrameParser,
    ProtocolError,
    decode_ack,
    decode_info_reply,
    decode_nak,
    encode_closures,
    encode_frame,
    encode_open_all,
    mask_crc,
    pack_mask,
)

__all__ = ["LCoSDevice", "LinkStats", "SerialLCoS", "SerialLike"]


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


class LCoSDevice(abc.ABC):
    """An LCoS shutter array as the capture loop sees it.

    Cells are addressed by row-major index ``y * W + x`` on the device grid of
    ``cells = (W, H)``. Public methods check their arguments and delegate to ``_do_*``
    hooks. A concrete device keeps :attr:`applied_subframe`, the subframe index at
    which the device reported applying each cell's closure (-1 while open), and
    :attr:`frame_start_subframe`, the subframe at which the last OPEN_ALL was applied.
    """

    def __init__(self) -> None:
        self._info: DeviceInfo | None = None

    # -- public API -------------------------------------------------------------------
    def info(self) -> DeviceInfo:
        """Ask the device for its description (grid, latency, leakage, clock, firmware).

        Returns
        -------
        DeviceInfo
        """
        self._info = self._do_info()
        return self._info

    @property
    def device_info(self) -> DeviceInfo:
        """The last :class:`DeviceInfo` received (asks the device if there is none)."""
        return self._info if self._info is not None else self.info()

    @property
    def cells(self) -> tuple[int, int]:
        """Device grid (width, height) in cells."""
        return self.device_info.cells

    @property
    def n_cells(self) -> int:
        """Number of cells, ``W * H``."""
        return self.device_info.n_cells

    def open_all(self, frame_index: int, *, wait: bool = True) -> int | None:
        """Open every cell and start frame ``frame_index``.

        Parameters
        ----------
        frame_index : int
            Frame counter, 0 .. 2**32 - 1 (reported back by the device's record).
        wait : bool
            Wait for the acknowledgement (default) and return the frame's start.

        Returns
        -------
        int or None
            Subframe index at which the device opened the cells (the frame's t = 0),
            or None when ``wait`` is false.
        """
        frame_index = int(frame_index)
        if not 0 <= frame_index < 2**32:
            raise ValueError(f"frame_index must be in [0, 2**32), got {frame_index}.")
        return self._do_open_all(frame_index, wait)

    def send_full_mask(self, mask: ArrayLike, *, wait: bool = True) -> int | None:
        """Set the whole mask (calibration patterns, resynchronisation).

        Parameters
        ----------
        mask : array_like of bool, shape (H, W) or (H * W,)
            True where the cell must be closed.
        wait : bool
            Wait for the acknowledgement (default).

        Returns
        -------
        int or None
            Subframe index at which the device applied the mask, or None when ``wait``
            is false.
        """
        m = np.asarray(mask)
        w, h = self.cells
        if m.shape not in ((h, w), (w * h,)):
            raise ValueError(f"mask must have shape ({h}, {w}) or ({w * h},), got {m.shape}.")
        return self._do_send_full_mask(m.astype(bool).ravel(), wait)

    def close_cells(self, cells: ArrayLike, *, wait: bool = False) -> int | None:
        """Close cells (only those not already closed are sent).

        Parameters
        ----------
        cells : array_like of int, or array_like of bool with H * W elements
            Row-major indices of the cells to close, or a mask of them.
        wait : bool
            Wait for the acknowledgement (default: return as soon as the frame is
            written; :meth:`flush` waits for everything outstanding).

        Returns
        -------
        int or None
            With ``wait``, the subframe index at which the device applied the closure;
            otherwise (or when no cell was newly closed) None.
        """
        idx = _normalise_cells(cells, self.n_cells)
        return self._do_close_cells(idx, wait)

    def flush(self, timeout_s: float | None = None) -> None:
        """Wait until the device has acknowledged every frame sent so far.

        Raises
        ------
        DeviceError
            If the link fails or ``timeout_s`` passes first.
        """
        self._do_flush(timeout_s)

    def close(self) -> None:
        """Release the device (does not wait for outstanding frames)."""
        self._do_close()

    def exposure_time_s(self, subframe_s: float, frame_s: float) -> np.ndarray:
        """Exposure time per cell from the device-reported closure subframes.

        A cell applied at subframe ``a`` in a frame that started at subframe ``s0`` was
        open during subframes ``s0 .. a - 1``: ``T = (a - s0) * subframe_s``, clipped
        to ``[0, frame_s]``; a cell that never closed has ``T = frame_s``.

        Parameters
        ----------
        subframe_s : float
            Subframe length, seconds.
        frame_s : float
            Frame length, seconds.

        Returns
        -------
        ndarray of float64, shape (H, W)

        Raises
        ------
        DeviceError
            If no frame has been started.
        """
        if self.frame_start_subframe < 0:
            raise DeviceError("no frame has been started on the LCoS (call open_all first)")
        applied = self.applied_subframe.astype(np.float64)
        t = np.where(applied >= 0, (applied - self.frame_start_subframe) * subframe_s, frame_s)
        w, h = self.cells
        return np.clip(t, 0.0, frame_s).reshape(h, w)

    def __enter__(self) -> LCoSDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state every device reports ----------------------------------------------------
    @property
    @abc.abstractmethod
    def applied_subframe(self) -> np.ndarray:
        """ndarray of int32, shape (H * W,): device-reported closure subframe, -1 = open."""

    @property
    @abc.abstractmethod
    def frame_start_subframe(self) -> int:
        """Subframe at which the device applied the last OPEN_ALL (-1 before any)."""

    @property
    @abc.abstractmethod
    def mask(self) -> np.ndarray:
        """ndarray of bool, shape (H, W): the mask the host has asked for so far."""

    @property
    @abc.abstractmethod
    def stats(self) -> LinkStats:
        """Link counters."""

    # -- hooks -------------------------------------------------------------------------
    @abc.abstractmethod
    def _do_info(self) -> DeviceInfo: ...

    @abc.abstractmethod
    def _do_open_all(self, frame_index: int, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_send_full_mask(self, mask: np.ndarray, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_close_cells(self, cells: np.ndarray, wait: bool) -> int | None: ...

    @abc.abstractmethod
    def _do_flush(self, timeout_s: float | None) -> None: ...

    @abc.abstractmethod
    def _do_close(self) -> None: ...


def _normalise_cells(cells: ArrayLike, n_cells: int) -> np.ndarray:
    arr = np.asarray(cells)
    if arr.dtype == bool:
        if arr.size != n_cells:
            raise ValueError(f"a boolean cell mask must have {n_cells} elements, got {arr.size}.")
        return np.flatnonzero(arr.ravel())
    if arr.size == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"cell indices must be integers, got dtype {arr.dtype}.")
    idx = arr.ravel().astype(np.int64, copy=False)
    lo, hi = int(idx.min()), int(idx.max())
    if lo < 0 or hi >= n_cells:
        raise ValueError(f"cell indices must lie in [0, {n_cells}); got {lo} .. {hi}.")
    if idx.size > 1 and not bool(np.all(idx[1:] > idx[:-1])):
        idx = np.unique(idx)
    return idx


@dataclass
class _Outstanding:
    """A frame sent and not yet committed."""

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


class SerialLCoS(LCoSDevice):
    """LCoS controller on a serial-like link, speaking the vet LCoS protocol.

    Frames go out with increasing sequence numbers; up to ``window`` may be
    unacknowledged at once (the capture loop never waits for a closure to be
    acknowledged unless it asks). The device processes frames strictly in order, so:

    * a NAK names the next frame it expects: the driver resends every unacknowledged
      frame from there on (go-back-N);
    * an ACK for a frame sent after an unacknowledged one means the earlier ACK was
      lost: the earlier frame is resent and the device answers from its reply cache;
    * if nothing arrives for ``ack_timeout_s`` (plus the frame's own transmission time
      when ``link_bps`` is known), the oldest unacknowledged frame and those after it
      are resent;
    * a frame transmitted ``1 + max_retries`` times without acknowledgement raises
      :class:`~stages.errors.DeviceError`.

    Acknowledgements are committed in sequence order; each commit updates the
    committed mask and :attr:`applied_subframe` and compares the ACK's mask CRC with
    the committed mask. On disagreement the driver sends a FULL_MASK of its mirror
    (once; if that FULL_MASK's own ACK still disagrees it raises).

    Parameters
    ----------
    port : str or serial-like object
        A pyserial URL or device path (opened with :func:`serial.serial_for_url`), or
        an already open object with ``read``/``write``/``in_waiting``/``timeout``
        (its ``timeout`` is set to ``poll_s``).
    baudrate : int, optional
        UART rate for real serial ports (ignored by USB CDC, sockets and ptys).
    link_bps : float, optional
        Link rate in bit/s used to stretch ACK timeouts for long frames (default:
        ``baudrate`` when given, else unknown).
    bits_per_byte : int
        Bits each byte costs on the wire (10 for an 8N1 UART).
    ack_timeout_s : float
        Silence after which the oldest unacknowledged frame is resent, seconds.
    max_retries : int
        Retransmissions allowed per frame before giving up.
    window : int
        Frames that may be unacknowledged at once (1 = stop-and-wait).
    poll_s : float
        Read timeout of one poll of the port, seconds.
    write_timeout_s : float
        Longest a write may block (a stalled link), seconds.
    flush_timeout_s : float
        Default limit for :meth:`flush` and blocking calls, seconds.
    connect : bool
        Ask the device for INFO now (default) so the grid size is known.
    """

    def __init__(
        self,
        port: str | SerialLike,
        *,
        baudrate: int | None = None,
        link_bps: float | None = None,
        bits_per_byte: int = 10,
        ack_timeout_s: float = 0.5,
        max_retries: int = 8,
        window: int = 8,
        poll_s: float = 0.002,
        write_timeout_s: float = 10.0,
        flush_timeout_s: float = 30.0,
        connect: bool = True,
    ) -> None:
        super().__init__()
        if not 1 <= window <= 256:
            raise ValueError(f"window must be 1 to 256 frames, got {window}.")
        if ack_timeout_s <= 0 or poll_s <= 0:
            raise ValueError("ack_timeout_s and poll_s must be positive.")
        if max_retries < 0:
            raise ValueError(f"max_retries must be non-negative, got {max_retries}.")
        if isinstance(port, str):
            self._name = port
            self._port = self._open_url(port, baudrate, poll_s, write_timeout_s)
        else:
            self._name = str(
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
        self._parser = FrameParser(INFO_REPLY_MAX_BYTES, DEVICE_COMMANDS)
        self._stats = LinkStats()
        self._seq = 0
        self._tx_order = 0
        self._pending: collections.deque[_Outstanding] = collections.deque()
        self._by_seq: dict[int, _Outstanding] = {}
        self._rx: collections.deque[Frame] = collections.deque()
        self._last_rx = time.monotonic()
        self._resync_needed = False
        self._closed = False
        self._n = 0
        self._mirror = np.zeros(0, dtype=bool)
        self._committed = np.zeros(0, dtype=bool)
        self._applied = np.zeros(0, dtype=np.int32)
        self._frame_start = -1
        self._frame_index = -1
        if connect:
            try:
                self.info()
            except BaseException:
                self.close()
                raise

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

    # -- state -------------------------------------------------------------------------
    @property
    def applied_subframe(self) -> np.ndarray:
        return self._applied.copy()

    @property
    def frame_start_subframe(self) -> int:
        return self._frame_start

    @property
    def frame_index(self) -> int:
        """Index of the frame started by the last committed OPEN_ALL (-1 before any)."""
        return self._frame_index

    @property
    def mask(self) -> np.ndarray:
        w, h = self.cells
        return self._mirror.reshape(h, w).copy()

    @property
    def committed_mask(self) -> np.ndarray:
        """ndarray of bool, shape (H, W): the mask as acknowledged by the device so far."""
        w, h = self.cells
        return self._committed.reshape(h, w).copy()

    @property
    def stats(self) -> LinkStats:
        self._stats.bad_frames = self._parser.bad_frames
        self._stats.skipped_bytes = self._parser.skipped_bytes
        return self._stats

    @property
    def outstanding(self) -> int:
        """Frames sent and not yet committed."""
        return len(self._pending)

    @property
    def port_name(self) -> str:
        """The transport's name, as used in error messages."""
        return self._name

    # -- hooks -------------------------------------------------------------------------
    def _do_info(self) -> DeviceInfo:
        self._do_flush(None)
        rec = self._send(Command.INFO, b"")
        self._wait(lambda: rec.seq not in self._by_seq, None, f"INFO reply from {self._name}")
        assert rec.info is not None
        info = rec.info
        if info.protocol_version != PROTOCOL_VERSION:
            raise DeviceError(
                f"LCoS on {self._name} speaks protocol version {info.protocol_version}, "
                f"this driver speaks {PROTOCOL_VERSION}"
            )
        if info.n_cells != self._n:
            self._n = info.n_cells
            self._mirror = np.zeros(self._n, dtype=bool)
            self._committed = np.zeros(self._n, dtype=bool)
            self._applied = np.full(self._n, -1, dtype=np.int32)
        return info

    def _do_open_all(self, frame_index: int, wait: bool) -> int | None:
        self._require_info()
        self._mirror[:] = False
        rec = self._send(Command.OPEN_ALL, encode_open_all(frame_index), frame_index=frame_index)
        return self._wait_applied(rec) if wait else None

    def _do_send_full_mask(self, mask: np.ndarray, wait: bool) -> int | None:
        self._require_info()
        self._mirror = mask.copy()
        rec = self._send(Command.FULL_MASK, pack_mask(mask), mask=mask.copy())
        return self._wait_applied(rec) if wait else None

    def _do_close_cells(self, cells: np.ndarray, wait: bool) -> int | None:
        self._require_info()
        new = cells[~self._mirror[cells]]
        if new.size == 0:
            self._service(block=False)
            return None
        self._mirror[new] = True
        rec = self._send(Command.CLOSE_DELTA, encode_closures(new, self._n), cells=new)
        return self._wait_applied(rec) if wait else None

    def _do_flush(self, timeout_s: float | None) -> None:
        self._wait(
            lambda: not self._pending and not self._resync_needed, timeout_s, "acknowledgements"
        )

    def _do_close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._port.close()
            except Exception:  # closing a dead port must not mask the real error
                pass

    def _require_info(self) -> None:
        if self._info is None:
            self.info()

    # -- sending -----------------------------------------------------------------------
    def _send(self, command: Command, payload: bytes, **meta: Any) -> _Outstanding:
        if self._closed:
            raise DeviceError(f"the LCoS link {self._name} is closed")
        resync = bool(meta.get("resync", False))
        if not resync:
            self._wait(
                lambda: len(self._pending) < self.window, None, "a free slot in the send window"
            )
        seq = self._seq
        self._seq = (seq + 1) & 0xFFFF
        rec = _Outstanding(
            seq=seq, command=command, wire=encode_frame(command, seq, payload), **meta
        )
        self._pending.append(rec)
        self._by_seq[seq] = rec
        self._stats.frames_sent += 1
        self._transmit(rec)
        self._process_rx()
        return rec

    def _transmit(self, rec: _Outstanding) -> None:
        if rec.transmissions > self.max_retries:
            problem = rec.last_problem or f"no reply within {self.ack_timeout_s:g} s"
            raise DeviceError(
                f"the LCoS on {self._name} did not acknowledge frame {rec.seq} ({rec.command.name}) "
                f"after {rec.transmissions} transmissions (last problem: {problem}); "
                "the link is too noisy or the device stopped responding"
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

    def _resend_from(self, first: _Outstanding, problem: str) -> None:
        """Go back: resend ``first`` and every later unacknowledged frame, in order."""
        started = False
        for rec in list(self._pending):
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
                f"writing to the LCoS link {self._name} timed out after {self.write_timeout_s:g} s: "
                "the link is stalled (device not reading?)"
            )
        return DeviceError(f"lost the LCoS link {self._name}: {exc}")

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

    def _service(self, block: bool) -> None:
        """One turn of the link: read, handle replies, commit, resend on timeout."""
        if block and not self._rx:
            self._read_blocking()
        else:
            self._read_available()
        self._process_rx()
        self._check_timeout()

    def _process_rx(self) -> None:
        while self._rx:
            self._handle(self._rx.popleft())
        self._commit()
        if self._resync_needed:
            self._resync_needed = False
            self._stats.resyncs += 1
            self._send(
                Command.FULL_MASK, pack_mask(self._mirror), mask=self._mirror.copy(), resync=True
            )

    def _handle(self, frame: Frame) -> None:
        self._last_rx = time.monotonic()
        try:
            if frame.command == Command.NAK:
                nak = decode_nak(frame.payload)
                self._stats.naks += 1
                rec = self._by_seq.get(nak.expected_seq)
                if rec is not None and rec.ack is None:
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
                f"the LCoS on {self._name} sent a malformed {frame.command.name}: {exc}"
            ) from exc
        rec = self._by_seq.get(ack.seq)
        if rec is None or rec.ack is not None:
            self._stats.duplicate_acks += 1
            return
        if (rec.command == Command.INFO) != (info is not None):
            raise DeviceError(
                f"the LCoS on {self._name} answered frame {rec.seq} ({rec.command.name}) with {frame.command.name}"
            )
        rec.ack, rec.info = ack, info
        delay = self._last_rx - rec.first_sent
        self._stats.acks += 1
        self._stats.total_ack_delay_s += delay
        self._stats.max_ack_delay_s = max(self._stats.max_ack_delay_s, delay)
        # The device works in order: an earlier frame last sent before this one and
        # still unacknowledged had its ACK lost on the way back.
        for older in list(self._pending):
            if older is rec:
                break
            if older.ack is None and older.tx_order < rec.tx_order:
                older.last_problem = "acknowledgement lost"
                self._transmit(older)

    def _commit(self) -> None:
        while self._pending and self._pending[0].ack is not None:
            rec = self._pending.popleft()
            del self._by_seq[rec.seq]
            ack = rec.ack
            assert ack is not None
            if rec.command == Command.INFO:
                self._info = rec.info
                continue
            applied = np.int32(ack.applied_subframe)
            if rec.command == Command.OPEN_ALL:
                self._committed[:] = False
                self._applied[:] = -1
                self._frame_start = int(ack.applied_subframe)
                self._frame_index = rec.frame_index
            elif rec.command == Command.FULL_MASK:
                assert rec.mask is not None
                newly = rec.mask & ~self._committed
                self._applied[newly] = applied
                self._applied[~rec.mask] = -1
                self._committed = rec.mask
            else:
                assert rec.cells is not None
                newly = rec.cells[~self._committed[rec.cells]]
                self._committed[newly] = True
                self._applied[newly] = applied
            if ack.mask_crc != mask_crc(self._committed):
                if rec.resync:
                    raise DeviceError(
                        f"the LCoS on {self._name} still reports a different mask after a full-mask "
                        "resynchronisation; the device is not applying masks"
                    )
                if not any(r.resync for r in self._pending):
                    self._resync_needed = True

    def _check_timeout(self) -> None:
        oldest = next((r for r in self._pending if r.ack is None), None)
        if oldest is None:
            return
        limit = self.ack_timeout_s
        if self.link_bps:
            limit += len(oldest.wire) * self.bits_per_byte / self.link_bps
        if time.monotonic() - max(oldest.last_sent, self._last_rx) > limit:
            self._stats.timeouts += 1
            self._parser.expire()
            self._rx.extend(self._parser.feed(b""))
            self._process_rx()
            if oldest.ack is None and oldest.seq in self._by_seq:
                self._resend_from(oldest, f"no reply within {limit:g} s")

    def _wait(self, done: Callable[[], bool], timeout_s: float | None, what: str) -> None:
        limit = self.flush_timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + limit
        while not done():
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"gave up after {limit:g} s waiting for {what} on the LCoS link {self._name} "
                    f"({len(self._pending)} frames unacknowledged)"
                )
            self._service(block=True)

    def _wait_applied(self, rec: _Outstanding) -> int:
        self._wait(
            lambda: self._by_seq.get(rec.seq) is not rec,
            None,
            f"the acknowledgement of frame {rec.seq}",
        )
        assert rec.ack is not None
        return int(rec.ack.applied_subframe)

    def __repr__(self) -> str:
        return f"SerialLCoS({self._name!r}, cells={self._info.cells if self._info else None})"
