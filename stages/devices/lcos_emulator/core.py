"""The emulated controller as one state machine on bytes: :class:`LCoSEmulatorCore`.

Bytes from the host enter with :meth:`LCoSEmulatorCore.receive` (at the current time);
the incoming :class:`~.wire.Wire` delivers them ``len * bits_per_byte / link_bps``
seconds later; a wire tap splits them into frames and lets the
:class:`~.faults.FaultInjector` damage, drop or delay whole frames; the device parser
and the :class:`~.controller.Controller` process them; replies go through faults and
the outgoing wire and come out of :meth:`LCoSEmulatorCore.pop_output` when they have
fully arrived. Call :meth:`LCoSEmulatorCore.poll` to let time pass.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import ArrayLike

from ..protocol import Frame, FrameParser, NakReason, max_payload_bytes
from .config import EmulatorConfig, EmulatorRecord
from .controller import Controller
from .faults import FaultInjector
from .hostile import HostileController
from .wire import Wire

__all__ = ["LCoSEmulatorCore"]

_WIRE_PIECE = 256  # wire model granularity: bytes delivered together


class LCoSEmulatorCore:
    """The emulated controller: link model, faults and device state, driven by time.

    Parameters
    ----------
    config : EmulatorConfig
    clock : callable returning int
        The subframe clock (see :mod:`~stages.devices.lcos_emulator.clock`).
    now : callable returning float
        Monotonic time in seconds.
    controller : type, optional
        The device state machine (default: :class:`~.controller.Controller`, or
        :class:`~.hostile.HostileController` when ``config.hostile`` is set).
    """

    def __init__(
        self,
        config: EmulatorConfig,
        clock: Callable[[], int],
        now: Callable[[], float] = time.monotonic,
        controller: type[Controller] | None = None,
    ):
        self.config = config
        self._clock = clock
        self._now = now
        self.counters: dict[str, int] = collections.defaultdict(int)
        if controller is None:
            controller = HostileController if config.hostile else Controller
        self.device = controller(config, clock, self._transmit, self.counters)
        self.n_cells = self.device.n_cells
        self._faults = FaultInjector(config.link_fault_rate, config.fault_delay_s, config.seed)
        limit = max_payload_bytes(self.n_cells)
        self._tap = FrameParser(limit)
        self._parser = FrameParser(limit)
        self._bad_seen = 0
        self._wire_in = Wire(config.link_bps, config.bits_per_byte)
        # tapped bytes waiting for the device parser: (due, bytes, fresh from the wire)
        self._held: collections.deque[tuple[float, bytes, bool]] = collections.deque()
        self._wire_out = Wire(config.link_bps, config.bits_per_byte)
        self._rx_hold = 0.0
        self._last_input = 0.0  # when bytes last came off the wire (idle detection)
        self._cut = False
        self.disconnected = False

    # -- device state, read through --------------------------------------------------
    @property
    def closed(self) -> np.ndarray:
        """The device's mask, shape (W * H,)."""
        return self.device.closed

    @property
    def applied(self) -> np.ndarray:
        """Applied subframe per cell, shape (W * H,), -1 = open."""
        return self.device.applied

    @property
    def frame_index(self) -> int:
        return self.device.frame_index

    @property
    def frame_start(self) -> int:
        return self.device.frame_start

    @property
    def expected_seq(self) -> int:
        return self.device.expected_seq

    # -- transport side --------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes the host has just written (they reach the device after the wire delay)."""
        t = self._now()
        for start in range(0, len(data), _WIRE_PIECE):
            self._wire_in.send(t, bytes(data[start : start + _WIRE_PIECE]))

    def input_backlog_s(self) -> float:
        """Seconds until the incoming wire has carried everything received so far."""
        return self._wire_in.backlog_s(self._now())

    def pop_output(self) -> bytes:
        """Reply bytes that have fully crossed the outgoing wire by now."""
        out = b"".join(self._wire_out.arrived(self._now()))
        if self._cut and not self._wire_out:
            self.disconnected = True
        return out

    def next_deadline(self) -> float | None:
        """Earliest time at which :meth:`poll` or :meth:`pop_output` has work."""
        times = [w.next_arrival for w in (self._wire_in, self._wire_out) if w]
        if self._held:
            times.append(self._held[0][0])
        if self._tap.pending or self._parser.pending:
            times.append(self._last_input + self.config.idle_expire_s)
        return min(times) if times else None  # type: ignore[type-var]

    def poll(self) -> None:
        """Deliver what the wire has carried by now and process complete frames."""
        t = self._now()
        expire = self.config.idle_expire_s
        for piece in self._wire_in.arrived(t):
            self._last_input = t
            self._tap_pass(self._tap.feed_events(piece), t)
        idle = not self._wire_in and t - self._last_input > expire
        if self._tap.pending and idle:
            # the tap never drops bytes: an unfinished "frame" goes on to the device as is
            self._held.append((max(t, self._rx_hold), self._tap.take_pending(), False))
        while self._held and self._held[0][0] <= t:
            _, data, fresh = self._held.popleft()
            if fresh:
                self._last_input = t
            self._device_input(data)
        idle = not self._wire_in and t - self._last_input > expire
        if self._parser.pending and not self._held and idle:
            # e.g. a corrupted length field announced bytes that will never come
            self._parser.expire()
            self._device_input(b"")
        self.device.on_poll(t)

    # -- state -------------------------------------------------------------------------
    def record(self, exit_reason: str = "") -> EmulatorRecord:
        """A copy of the authoritative state."""
        counters = dict(self.counters)
        counters["bad_frames"] = self._parser.bad_frames
        counters["skipped_bytes"] = self._parser.skipped_bytes
        return EmulatorRecord(
            cells=self.config.cells,
            applied_subframe=self.device.applied.copy(),
            closed=self.device.closed.copy(),
            frame_index=self.device.frame_index,
            frame_start_subframe=self.device.frame_start,
            subframe=int(self._clock()),
            counters=counters,
            exit_reason=exit_reason,
        )

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open cells (a cell driver glitch) so the host sees a CRC mismatch."""
        self.device.inject_mask_fault(cells)

    # -- internals ---------------------------------------------------------------------
    def _tap_pass(self, events: Iterable[tuple[str, Frame | bytes]], t: float) -> None:
        """Incoming faults: act on whole frames as the host sent them."""
        for kind, item in events:
            if kind == "garbage":
                raw = item  # type: ignore[assignment]
            else:
                raw = item.encode()  # type: ignore[union-attr]
                fault = self._faults.draw()
                if fault == "drop":
                    self.counters["rx_dropped"] += 1
                    continue
                if fault == "corrupt":
                    self.counters["rx_corrupted"] += 1
                    raw = self._faults.corrupt(raw)
                elif fault == "delay":
                    self.counters["rx_delayed"] += 1
                    self._rx_hold = max(t, self._rx_hold) + self._faults.delay()
            self._held.append((max(t, self._rx_hold), raw, True))

    def _device_input(self, data: bytes) -> None:
        for frame in self._parser.feed(data):
            self.device.handle(frame)
        if self._parser.bad_frames > self._bad_seen:
            self._bad_seen = self._parser.bad_frames
            self.device.nak(NakReason.BAD_CRC)

    def _transmit(self, raw: bytes) -> None:
        """Outgoing faults and the injected disconnect, then the outgoing wire."""
        if self._cut:
            return
        extra = 0.0
        cut_at = self.config.disconnect_at_subframe
        if cut_at is not None and self._clock() >= cut_at:
            raw = raw[: len(raw) // 2]
            self._cut = True
            self.counters["disconnects"] += 1
        else:
            fault = self._faults.draw()
            if fault == "drop":
                self.counters["tx_dropped"] += 1
                return
            if fault == "corrupt":
                self.counters["tx_corrupted"] += 1
                raw = self._faults.corrupt(raw)
            elif fault == "delay":
                self.counters["tx_delayed"] += 1
                extra = self._faults.delay()
        self._wire_out.send(self._now(), raw, extra)
