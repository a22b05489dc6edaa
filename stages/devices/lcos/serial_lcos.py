"""The LCoS controller on a serial link: :class:`SerialLCoS`.

It keeps a *mirror* of the mask the host intends and a *committed* copy that follows
the device's acknowledgements frame by frame. The exposure-time record
(:attr:`~stages.devices.lcos.device.LCoSDevice.applied_subframe`) is written only from
acknowledgements, so T always comes from when the device says it applied a closure,
never from when the host asked. Delivery (window, retries, timeouts, serial I/O) is
:class:`~stages.devices.lcos.link.FrameLink`'s job.
"""

from __future__ import annotations

import time

import numpy as np

from ...errors import DeviceError
from ..protocol import (
    PROTOCOL_VERSION,
    Command,
    DeviceInfo,
    encode_closures,
    encode_open_all,
    mask_crc,
    pack_mask,
)
from .device import LCoSDevice
from .link import FrameLink, LinkStats, Outstanding, SerialLike

__all__ = ["CLOCK_SLACK_SUBFRAMES", "CLOCK_TOLERANCE", "MAX_APPLIED_SUBFRAME", "SerialLCoS"]

MAX_APPLIED_SUBFRAME = 2**31 - 1  #: the T record holds int32 subframe indices
CLOCK_TOLERANCE = 0.1  #: relative rate error allowed between the device clock and subframe_s
CLOCK_SLACK_SUBFRAMES = 4  #: subframes of slack on top (trigger jitter, INFO read time)


class SerialLCoS(LCoSDevice):
    """LCoS controller on a serial-like link, speaking the vet LCoS protocol.

    Frames are delivered by a :class:`~stages.devices.lcos.link.FrameLink` (go-back-N
    with a window of ``window`` frames, bounded retries and timeouts); the capture loop
    never waits for a closure to be acknowledged unless it asks.

    Acknowledgements are committed in sequence order; each commit updates the
    committed mask and :attr:`applied_subframe` and compares the ACK's mask CRC with
    the committed mask. On disagreement the driver sends a FULL_MASK of its mirror
    (once; if that FULL_MASK's own ACK still disagrees it raises).

    An acknowledgement is committed only if its applied subframe can be true: the
    device applies frames in order, so applied subframes never decrease; they fit the
    31-bit record; and, when ``subframe_s`` is given, none lies beyond what the
    device's clock can have reached (its INFO reading plus the time since, at
    ``subframe_s`` per subframe with :data:`CLOCK_TOLERANCE`, plus its latency and
    :data:`CLOCK_SLACK_SUBFRAMES`). Otherwise :class:`~stages.errors.DeviceError` is
    raised and nothing of that acknowledgement enters the T record.

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
    cells : (int, int), optional
        The grid (width, height) the rig expects: an INFO reporting another grid is
        refused before any per-cell state is allocated.
    subframe_s : float, optional
        Subframe length of the device's clock, seconds, when it runs in real time (the
        camera's trigger): enables the check that applied subframes are not in the
        future. Leave unset when the clock is advanced by other means (emulators
        ticked by tests).

    Raises
    ------
    DeviceError
        If the port cannot be opened or (with ``connect``) the device does not answer.
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
        cells: tuple[int, int] | None = None,
        subframe_s: float | None = None,
    ) -> None:
        super().__init__()
        if subframe_s is not None and not subframe_s > 0:
            raise ValueError(f"subframe_s must be positive, got {subframe_s}.")
        self.expected_cells = None if cells is None else (int(cells[0]), int(cells[1]))
        self.subframe_s = subframe_s
        self._link = FrameLink(
            port,
            commit=self._commit,
            after_rx=self._after_rx,
            baudrate=baudrate,
            link_bps=link_bps,
            bits_per_byte=bits_per_byte,
            ack_timeout_s=ack_timeout_s,
            max_retries=max_retries,
            window=window,
            poll_s=poll_s,
            write_timeout_s=write_timeout_s,
            flush_timeout_s=flush_timeout_s,
        )
        self._resync_needed = False
        self._n = 0
        self._mirror = np.zeros(0, dtype=bool)
        self._committed = np.zeros(0, dtype=bool)
        self._applied = np.zeros(0, dtype=np.int32)
        self._frame_start = -1
        self._frame_index = -1
        self._last_applied = -1  # highest applied subframe committed (INFO aside)
        self._clock_ref: tuple[int, float] | None = None  # (INFO subframe, host time)
        if connect:
            try:
                self.info()
            except BaseException:
                self.close()
                raise

    # -- state -------------------------------------------------------------------------
    @property
    def link(self) -> FrameLink:
        """The frame link (settings, outstanding frames)."""
        return self._link

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
        return self._link.stats

    @property
    def outstanding(self) -> int:
        """Frames sent and not yet committed."""
        return len(self._link.pending)

    @property
    def port_name(self) -> str:
        """The transport's name, as used in error messages."""
        return self._link.name

    # -- hooks -------------------------------------------------------------------------
    def _do_info(self) -> DeviceInfo:
        self._do_flush(None)
        rec = self._link.send(Command.INFO, b"")
        self._link.wait_acked(rec)
        assert rec.info is not None
        info = rec.info
        if info.protocol_version != PROTOCOL_VERSION:
            raise DeviceError(
                f"LCoS on {self.port_name} speaks protocol version {info.protocol_version}, "
                f"this driver speaks {PROTOCOL_VERSION}"
            )
        if self.expected_cells is not None and info.cells != self.expected_cells:
            raise DeviceError(
                f"the LCoS on {self.port_name} reports {info.cells[0]}x{info.cells[1]} cells "
                f"but the rig says {self.expected_cells[0]}x{self.expected_cells[1]}"
            )
        self._clock_ref = (info.subframe, rec.first_sent)
        if info.n_cells != self._n:
            self._n = info.n_cells
            self._mirror = np.zeros(self._n, dtype=bool)
            self._committed = np.zeros(self._n, dtype=bool)
            self._applied = np.full(self._n, -1, dtype=np.int32)
        return info

    def _do_open_all(self, frame_index: int, wait: bool) -> int | None:
        self._require_info()
        self._mirror[:] = False
        rec = self._link.send(
            Command.OPEN_ALL, encode_open_all(frame_index), frame_index=frame_index
        )
        return self._wait_applied(rec) if wait else None

    def _do_send_full_mask(self, mask: np.ndarray, wait: bool) -> int | None:
        self._require_info()
        self._mirror = mask.copy()
        rec = self._link.send(Command.FULL_MASK, pack_mask(mask), mask=mask.copy())
        return self._wait_applied(rec) if wait else None

    def _do_close_cells(self, cells: np.ndarray, wait: bool) -> int | None:
        self._require_info()
        new = cells[~self._mirror[cells]]
        if new.size == 0:
            self._link.service(block=False)
            return None
        self._mirror[new] = True
        rec = self._link.send(Command.CLOSE_DELTA, encode_closures(new, self._n), cells=new)
        return self._wait_applied(rec) if wait else None

    def _do_flush(self, timeout_s: float | None) -> None:
        self._link.wait(
            lambda: not self._link.pending and not self._resync_needed,
            timeout_s,
            "acknowledgements",
        )

    def _do_close(self) -> None:
        self._link.close()

    def _require_info(self) -> None:
        if self._info is None:
            self.info()

    def _wait_applied(self, rec: Outstanding) -> int:
        return int(self._link.wait_acked(rec).applied_subframe)

    # -- committing acknowledgements ---------------------------------------------------
    def _commit(self, rec: Outstanding) -> None:
        """Apply one acknowledged frame to the committed mask and the T record."""
        ack = rec.ack
        assert ack is not None
        if rec.command == Command.INFO:
            self._info = rec.info
            return
        self._check_applied(rec, int(ack.applied_subframe))
        self._last_applied = int(ack.applied_subframe)
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
                    f"the LCoS on {self.port_name} still reports a different mask after a "
                    "full-mask resynchronisation; the device is not applying masks"
                )
            if not any(r.resync for r in self._link.pending):
                self._resync_needed = True

    def _check_applied(self, rec: Outstanding, a: int) -> None:
        """Refuse an applied subframe the device cannot have reached (see the class)."""
        what = (
            f"the LCoS on {self.port_name} reported applying frame {rec.seq} ({rec.command.name})"
        )
        if a > MAX_APPLIED_SUBFRAME:
            raise DeviceError(f"{what} at subframe {a}, beyond any plausible clock value")
        if a < self._last_applied:
            raise DeviceError(
                f"{what} at subframe {a}, before the previous frame's {self._last_applied}: "
                "its applied subframes went backwards"
            )
        if self.subframe_s and self._clock_ref is not None and self._info is not None:
            c0, t0 = self._clock_ref
            elapsed = max(0.0, time.monotonic() - t0) / self.subframe_s
            limit = (
                c0
                + int(elapsed * (1 + CLOCK_TOLERANCE))
                + self._info.latency_subframes
                + CLOCK_SLACK_SUBFRAMES
            )
            if a > limit:
                raise DeviceError(
                    f"{what} at subframe {a}, a subframe that has not happened yet (its clock "
                    f"can have reached at most {limit} at {self.subframe_s:g} s per subframe)"
                )

    def _after_rx(self) -> None:
        if self._resync_needed:
            self._resync_needed = False
            self._link.stats.resyncs += 1
            self._link.send(
                Command.FULL_MASK, pack_mask(self._mirror), mask=self._mirror.copy(), resync=True
            )

    def __repr__(self) -> str:
        cells = self._info.cells if self._info else None
        return f"SerialLCoS({self.port_name!r}, cells={cells})"
