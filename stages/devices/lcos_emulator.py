"""Emulated LCoS controller speaking the vet LCoS protocol.

The device logic lives in :class:`LCoSEmulatorCore`, a state machine fed with the bytes
the host writes and asked for the bytes it sends back. It owns the authoritative mask,
the subframe at which it applied each cell's closure, a link model (a wire of
``link_bps`` bit/s in each direction) and seeded fault injection. Two wrappers put it
behind a transport:

* :class:`LCoSEmulator` runs it in **its own process** (``multiprocessing``, spawn start)
  behind a pseudo-terminal; :attr:`LCoSEmulator.port` is the pty path the host opens
  with pyserial, like ``/dev/ttyACM0``. ``python -m stages.devices.lcos_emulator`` does
  the same from a shell with a free-running clock.
* :class:`InProcessLCoS` puts it behind :class:`EmulatedSerial`, a pyserial-like object
  (a mocked transport) for fast tests of the host driver without a pty.

The subframe clock
------------------
The device applies a mask-changing frame at ``max(clock + latency_subframes, last
applied)``, where ``clock`` is its subframe index when the frame has fully arrived (after
the throttled wire has carried its last byte). On a real rig the clock counts the
measurement camera's subframe trigger pulses. Here it is either

* **external** (default): an integer the camera side advances once per subframe --
  :meth:`LCoSEmulator.tick` increments a shared ``multiprocessing.Value('q')``
  (:attr:`LCoSEmulator.clock`) that the emulator process reads; emulated cameras in
  another process can be handed that Value and increment it themselves; or
* **free-running** (``subframe_s`` given): ``floor((now - start) / subframe_s)``, which
  the emulator also writes into the shared Value so the host can read it.

Applied subframes are absolute clock values; the ACK of OPEN_ALL gives the frame's
start ``s0`` and a cell applied at ``a`` was open for ``a - s0`` subframes.
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing
import os
import select
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DeviceError, InputError
from .protocol import (
    HOST_COMMANDS,
    PROTOCOL_VERSION,
    Command,
    DeviceInfo,
    Frame,
    FrameParser,
    NakReason,
    ProtocolError,
    decode_closures,
    decode_open_all,
    encode_ack,
    encode_frame,
    encode_info_reply,
    encode_nak,
    mask_crc,
    max_payload_bytes,
    unpack_mask,
)

__all__ = [
    "EmulatedSerial",
    "EmulatorConfig",
    "EmulatorRecord",
    "FreeRunningClock",
    "InProcessLCoS",
    "LCoSEmulator",
    "LCoSEmulatorCore",
    "SubframeClock",
    "main",
]

_WIRE_PIECE = 256  # wire model granularity: bytes delivered together


@dataclass
class EmulatorConfig:
    """How the emulated controller behaves.

    Attributes
    ----------
    cells : (int, int)
        Grid (width, height) in cells.
    latency_subframes : int
        Subframes between a frame's arrival and the subframe it is applied at.
    leakage : float
        Transmittance of a closed cell, reported in INFO.
    link_bps : float or None
        Link rate in bit/s, each direction; None = unthrottled.
    bits_per_byte : int
        Bits each byte costs on the wire (10 = 8N1 UART framing).
    link_fault_rate : float
        Probability per frame, in each direction, of a fault: one byte corrupted, the
        frame dropped, or the frame delayed (each a third of the time).
    fault_delay_s : float
        Longest extra delay of a delayed frame, seconds (uniform in [0.1, 1] of it).
    disconnect_at_subframe : int or None
        Once the clock reaches this subframe, the next reply is cut in half and the
        link is closed.
    seed : int
        Seed of the fault-injection random generator.
    firmware : str
        Firmware string reported in INFO.
    subframe_s : float or None
        Free-running clock period, seconds; None = clock advanced externally.
    idle_expire_s : float
        Idle gap after which a partial frame is abandoned (corrupted length field).
    reply_cache : int
        Replies remembered for answering retransmitted frames.
    connect_timeout_s : float
        The emulator process exits if no host writes within this time.
    """

    cells: tuple[int, int] = (1024, 600)
    latency_subframes: int = 1
    leakage: float = 0.002
    link_bps: float | None = None
    bits_per_byte: int = 10
    link_fault_rate: float = 0.0
    fault_delay_s: float = 0.02
    disconnect_at_subframe: int | None = None
    seed: int = 0
    firmware: str = "vet-lcos-emulator 1"
    subframe_s: float | None = None
    idle_expire_s: float = 0.05
    reply_cache: int = 1024
    connect_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        self.cells = (int(self.cells[0]), int(self.cells[1]))
        checks = [
            (
                0 < self.cells[0] < 65536 and 0 < self.cells[1] < 65536,
                "cells must be 1..65535 each way",
            ),
            (self.latency_subframes >= 0, "latency must be a non-negative number of subframes"),
            (0 <= self.leakage < 1, "leakage must be in [0, 1)"),
            (self.link_bps is None or self.link_bps > 0, "link rate must be positive"),
            (self.bits_per_byte >= 8, "a byte costs at least 8 bits"),
            (0 <= self.link_fault_rate <= 1, "fault rate must be a probability"),
            (self.fault_delay_s >= 0, "fault delay must be non-negative"),
            (self.subframe_s is None or self.subframe_s > 0, "subframe length must be positive"),
            (self.idle_expire_s > 0, "idle expiry must be positive"),
            (self.reply_cache >= 256, "reply cache must hold at least 256 replies"),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f"invalid LCoS emulator setting: {message}")

    @classmethod
    def from_rig(cls, rig: Any, **overrides: Any) -> EmulatorConfig:
        """Grid, latency and leakage from a :class:`~stages.rig.RigParams`."""
        base = {
            "cells": rig.lcos_cells,
            "latency_subframes": rig.latency_subframes,
            "leakage": rig.leakage,
        }
        base.update(overrides)
        return cls(**base)


@dataclass
class EmulatorRecord:
    """The emulated device's authoritative state.

    Attributes
    ----------
    cells : (int, int)
        Grid (width, height).
    applied_subframe : ndarray of int32, shape (W * H,)
        Subframe at which the device applied each cell's current closure, -1 = open.
    closed : ndarray of bool, shape (W * H,)
        The device's mask.
    frame_index : int
        Index carried by the last OPEN_ALL (-1 before any).
    frame_start_subframe : int
        Subframe at which the last OPEN_ALL was applied (-1 before any).
    subframe : int
        Clock value when the record was taken.
    counters : dict
        Frames received, applied, duplicates, ACKs, NAKs, injected faults, ...
    exit_reason : str
        Why the emulator stopped (empty while running).
    """

    cells: tuple[int, int]
    applied_subframe: np.ndarray
    closed: np.ndarray
    frame_index: int = -1
    frame_start_subframe: int = -1
    subframe: int = 0
    counters: dict[str, int] = field(default_factory=dict)
    exit_reason: str = ""

    def save_npz(self, path: str | os.PathLike[str]) -> None:
        """Write the record atomically to an ``.npz`` file."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        meta = {k: v for k, v in asdict(self).items() if k not in ("applied_subframe", "closed")}
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                applied_subframe=self.applied_subframe,
                closed=self.closed,
                meta=np.array(json.dumps(meta)),
            )
        os.replace(tmp, path)

    @classmethod
    def load_npz(cls, path: str | os.PathLike[str]) -> EmulatorRecord:
        """Read a record written by :meth:`save_npz`."""
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return cls(
                cells=tuple(meta.pop("cells")),
                applied_subframe=z["applied_subframe"],
                closed=z["closed"],
                **meta,
            )


class SubframeClock:
    """In-process subframe clock, advanced by the camera side with :meth:`tick`."""

    def __init__(self, start: int = 0) -> None:
        self.value = int(start)

    def tick(self, n: int = 1) -> int:
        """Advance by ``n`` subframes; returns the new value."""
        self.value += int(n)
        return self.value


class FreeRunningClock:
    """Subframe clock derived from wall time: ``start + floor((now - t0) / subframe_s)``."""

    def __init__(self, subframe_s: float, start: int = 0) -> None:
        self.subframe_s = float(subframe_s)
        self.start = int(start)
        self._t0 = time.monotonic()

    @property
    def value(self) -> int:
        """Current subframe index."""
        return self.start + int((time.monotonic() - self._t0) / self.subframe_s)

    def tick(self, n: int = 1) -> int:
        raise DeviceError("a free-running subframe clock cannot be ticked")


class LCoSEmulatorCore:
    """The emulated controller: protocol state machine, mask, link model, faults.

    Bytes from the host enter with :meth:`receive` (at the current time); the wire
    model delivers them ``len * bits_per_byte / link_bps`` seconds later; a wire tap
    splits them into frames and injects faults; the device parser and logic process
    them; replies go through faults and the outgoing wire and come out of
    :meth:`pop_output` when they have fully arrived. Call :meth:`poll` to let time pass.

    Parameters
    ----------
    config : EmulatorConfig
    clock : callable returning int
        The subframe clock (see the module docstring).
    now : callable returning float
        Monotonic time in seconds.
    """

    def __init__(
        self,
        config: EmulatorConfig,
        clock: Callable[[], int],
        now: Callable[[], float] = time.monotonic,
    ):
        self.config = config
        self._clock = clock
        self._now = now
        w, h = config.cells
        self.n_cells = w * h
        self.closed = np.zeros(self.n_cells, dtype=bool)
        self.applied = np.full(self.n_cells, -1, dtype=np.int32)
        self.frame_index = -1
        self.frame_start = -1
        self.expected_seq = 0
        self._last_applied = 0
        self._rng = np.random.default_rng(config.seed)
        limit = max_payload_bytes(self.n_cells)
        self._tap = FrameParser(limit)
        self._parser = FrameParser(limit)
        self._bad_seen = 0
        self._wire_in: collections.deque[tuple[float, bytes]] = collections.deque()
        # tapped bytes waiting for the device parser: (due, bytes, fresh from the wire)
        self._held: collections.deque[tuple[float, bytes, bool]] = collections.deque()
        self._tx: collections.deque[tuple[float, bytes]] = collections.deque()
        self._rx_free = 0.0
        self._rx_hold = 0.0
        self._tx_free = 0.0
        self._last_input = 0.0  # when bytes last came off the wire (idle detection)
        self._cache: collections.OrderedDict[int, bytes] = collections.OrderedDict()
        self._nak_pending_for: int | None = None
        self._dev_seq = 0
        self._cut = False
        self.disconnected = False
        self.counters: dict[str, int] = collections.defaultdict(int)

    # -- transport side --------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes the host has just written (they reach the device after the wire delay)."""
        t = self._now()
        bps = self.config.link_bps
        for start in range(0, len(data), _WIRE_PIECE):
            piece = bytes(data[start : start + _WIRE_PIECE])
            if bps:
                self._rx_free = max(t, self._rx_free) + len(piece) * self.config.bits_per_byte / bps
                due = self._rx_free
            else:
                due = t
            self._wire_in.append((due, piece))

    def input_backlog_s(self) -> float:
        """Seconds until the incoming wire has carried everything received so far."""
        return max(0.0, self._rx_free - self._now())

    def pop_output(self) -> bytes:
        """Reply bytes that have fully crossed the outgoing wire by now."""
        t = self._now()
        out = bytearray()
        while self._tx and self._tx[0][0] <= t:
            out += self._tx.popleft()[1]
        if self._cut and not self._tx:
            self.disconnected = True
        return bytes(out)

    def next_deadline(self) -> float | None:
        """Earliest time at which :meth:`poll` or :meth:`pop_output` has work."""
        times = [q[0][0] for q in (self._wire_in, self._held, self._tx) if q]
        if self._tap.pending or self._parser.pending:
            times.append(self._last_input + self.config.idle_expire_s)
        return min(times) if times else None

    def poll(self) -> None:
        """Deliver what the wire has carried by now and process complete frames."""
        t = self._now()
        expire = self.config.idle_expire_s
        while self._wire_in and self._wire_in[0][0] <= t:
            self._last_input = t
            self._tap_pass(self._tap.feed_events(self._wire_in.popleft()[1]), t)
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

    # -- state -------------------------------------------------------------------------
    def record(self, exit_reason: str = "") -> EmulatorRecord:
        """A copy of the authoritative state."""
        counters = dict(self.counters)
        counters["bad_frames"] = self._parser.bad_frames
        counters["skipped_bytes"] = self._parser.skipped_bytes
        return EmulatorRecord(
            cells=self.config.cells,
            applied_subframe=self.applied.copy(),
            closed=self.closed.copy(),
            frame_index=self.frame_index,
            frame_start_subframe=self.frame_start,
            subframe=int(self._clock()),
            counters=counters,
            exit_reason=exit_reason,
        )

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open cells (a cell driver glitch) so the host sees a CRC mismatch."""
        idx = np.asarray(cells, dtype=np.int64).ravel()
        self.closed[idx] = False
        self.applied[idx] = -1
        self.counters["mask_faults"] += int(idx.size)

    # -- internals ---------------------------------------------------------------------
    def _fault(self) -> str | None:
        p = self.config.link_fault_rate
        if p <= 0 or self._rng.random() >= p:
            return None
        return ("corrupt", "drop", "delay")[int(self._rng.integers(3))]

    def _corrupt(self, raw: bytes) -> bytes:
        b = bytearray(raw)
        pos = int(self._rng.integers(len(b)))
        b[pos] ^= int(self._rng.integers(1, 256))
        return bytes(b)

    def _delay(self) -> float:
        return float(self._rng.uniform(0.1, 1.0)) * self.config.fault_delay_s

    def _tap_pass(self, events: Iterable[tuple[str, Frame | bytes]], t: float) -> None:
        """Incoming faults: act on whole frames as the host sent them."""
        for kind, item in events:
            if kind == "garbage":
                raw = item  # type: ignore[assignment]
            else:
                raw = item.encode()  # type: ignore[union-attr]
                fault = self._fault()
                if fault == "drop":
                    self.counters["rx_dropped"] += 1
                    continue
                if fault == "corrupt":
                    self.counters["rx_corrupted"] += 1
                    raw = self._corrupt(raw)
                elif fault == "delay":
                    self.counters["rx_delayed"] += 1
                    self._rx_hold = max(t, self._rx_hold) + self._delay()
            self._held.append((max(t, self._rx_hold), raw, True))

    def _device_input(self, data: bytes) -> None:
        for frame in self._parser.feed(data):
            self._handle(frame)
        if self._parser.bad_frames > self._bad_seen:
            self._bad_seen = self._parser.bad_frames
            self._nak(NakReason.BAD_CRC)

    def _nak(self, reason: NakReason) -> None:
        if reason in (NakReason.BAD_CRC, NakReason.OUT_OF_ORDER):
            if self._nak_pending_for == self.expected_seq:
                return  # one NAK per gap; the host's timeout covers a lost NAK
            self._nak_pending_for = self.expected_seq
        self.counters["naks_sent"] += 1
        self._reply(Command.NAK, encode_nak(self.expected_seq, reason))

    def _reply(self, command: Command, payload: bytes, cache_seq: int | None = None) -> None:
        raw = encode_frame(command, self._dev_seq, payload)
        self._dev_seq = (self._dev_seq + 1) & 0xFFFF
        if cache_seq is not None:
            self._cache[cache_seq] = raw
            while len(self._cache) > self.config.reply_cache:
                self._cache.popitem(last=False)
        self._transmit(raw)

    def _transmit(self, raw: bytes) -> None:
        if self._cut:
            return
        t = self._now()
        extra = 0.0
        cut_at = self.config.disconnect_at_subframe
        if cut_at is not None and self._clock() >= cut_at:
            raw = raw[: len(raw) // 2]
            self._cut = True
            self.counters["disconnects"] += 1
        else:
            fault = self._fault()
            if fault == "drop":
                self.counters["tx_dropped"] += 1
                return
            if fault == "corrupt":
                self.counters["tx_corrupted"] += 1
                raw = self._corrupt(raw)
            elif fault == "delay":
                self.counters["tx_delayed"] += 1
                extra = self._delay()
        bps = self.config.link_bps
        duration = len(raw) * self.config.bits_per_byte / bps if bps else 0.0
        self._tx_free = max(t, self._tx_free) + extra + duration
        self._tx.append((self._tx_free, raw))

    def _handle(self, frame: Frame) -> None:
        self.counters["frames_received"] += 1
        if frame.command not in HOST_COMMANDS:
            self._nak(NakReason.UNKNOWN_COMMAND)
            return
        if frame.command == Command.INFO:
            # INFO opens a session: accepted at any seq, it resets the expected seq.
            self.expected_seq = (frame.seq + 1) & 0xFFFF
            self._cache.clear()
            self._nak_pending_for = None
            info = DeviceInfo(
                cells=self.config.cells,
                protocol_version=PROTOCOL_VERSION,
                latency_subframes=self.config.latency_subframes,
                leakage=self.config.leakage,
                subframe=int(self._clock()),
                mask_crc=mask_crc(self.closed),
                firmware=self.config.firmware,
                seq=frame.seq,
            )
            self._reply(Command.INFO_REPLY, encode_info_reply(info), cache_seq=frame.seq)
            return
        ahead = (frame.seq - self.expected_seq) & 0xFFFF
        if ahead >= 0x8000:  # behind: a retransmission of a frame already applied
            self.counters["duplicates"] += 1
            cached = self._cache.get(frame.seq)
            if cached is not None:
                self._transmit(cached)
            return
        if ahead:
            self.counters["out_of_order"] += 1
            self._nak(NakReason.OUT_OF_ORDER)
            return
        try:
            index = decode_open_all(frame.payload) if frame.command == Command.OPEN_ALL else -1
            mask = (
                unpack_mask(frame.payload, self.n_cells)
                if frame.command == Command.FULL_MASK
                else None
            )
            idx = (
                decode_closures(frame.payload, self.n_cells)
                if frame.command == Command.CLOSE_DELTA
                else None
            )
        except ProtocolError:
            self._nak(NakReason.BAD_PAYLOAD)
            return
        applied = max(int(self._clock()) + self.config.latency_subframes, self._last_applied)
        self._last_applied = applied
        if mask is not None:
            self._full_mask(mask, applied)
        elif idx is not None:
            self._close(idx, applied)
        else:
            self._open_all(index, applied)
        self.counters["frames_applied"] += 1
        self.expected_seq = (self.expected_seq + 1) & 0xFFFF
        self._nak_pending_for = None
        self.counters["acks_sent"] += 1
        self._reply(
            Command.ACK, encode_ack(frame.seq, applied, mask_crc(self.closed)), cache_seq=frame.seq
        )

    def _open_all(self, frame_index: int, at: int) -> None:
        self.closed[:] = False
        self.applied[:] = -1
        self.frame_index = frame_index
        self.frame_start = at

    def _full_mask(self, mask: np.ndarray, at: int) -> None:
        self.applied[mask & ~self.closed] = at
        self.applied[~mask] = -1
        self.closed = mask

    def _close(self, idx: np.ndarray, at: int) -> None:
        newly = idx[~self.closed[idx]]
        self.closed[newly] = True
        self.applied[newly] = at


# --- in-process transport -------------------------------------------------------------


class EmulatedSerial:
    """A pyserial-like port wired straight to an :class:`LCoSEmulatorCore`.

    Implements the subset the host driver uses: ``write``, ``read`` (blocking up to
    ``timeout``), ``in_waiting``, ``timeout``, ``close``, ``reset_input_buffer``.
    When the core disconnects, reads and writes raise :class:`serial.SerialException`
    as a vanished USB device would.
    """

    def __init__(
        self, core: LCoSEmulatorCore, timeout: float | None = 0.01, name: str = "emulated-lcos"
    ):
        self.core = core
        self.timeout = timeout
        self.name = name
        self.port = name
        self.is_open = True
        self._rx = bytearray()

    def _pump(self) -> None:
        self.core.poll()
        self._rx += self.core.pop_output()

    def _check(self) -> None:
        import serial

        if not self.is_open:
            raise serial.PortNotOpenError()

    def write(self, data: bytes) -> int:
        """Hand bytes to the emulated device."""
        import serial

        self._check()
        if self.core.disconnected:
            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        self.core.receive(bytes(data))
        self._pump()
        return len(data)

    @property
    def in_waiting(self) -> int:
        """Bytes readable without waiting."""
        self._check()
        self._pump()
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        """Read up to ``size`` bytes, waiting at most ``timeout`` seconds for them."""
        import serial

        self._check()
        deadline = time.monotonic() + (self.timeout or 0.0)
        while True:
            self._pump()
            if len(self._rx) >= size:
                break
            if self.core.disconnected:
                if self._rx:
                    break
                raise serial.SerialException(
                    "device reports readiness to read but returned no data (device disconnected?)"
                )
            now = time.monotonic()
            if now >= deadline:
                break
            nxt = self.core.next_deadline()
            wait = deadline - now if nxt is None else min(deadline - now, max(nxt - now, 0.0))
            time.sleep(min(max(wait, 5e-5), 0.001))
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def reset_input_buffer(self) -> None:
        """Drop unread bytes."""
        self._rx.clear()

    def flush(self) -> None:
        """Nothing to flush: writes are delivered immediately."""

    def close(self) -> None:
        """Close the port (the host side)."""
        self.is_open = False


class InProcessLCoS:
    """An emulated controller in this process behind an :class:`EmulatedSerial`.

    Same interface as :class:`LCoSEmulator` (``port``, ``clock``, ``tick``,
    ``subframe``, ``snapshot``, ``inject_mask_fault``, ``stop``), so one behavioural
    test suite runs against both.

    Parameters
    ----------
    cells : (int, int)
        Grid (width, height).
    **settings
        Further :class:`EmulatorConfig` fields.
    """

    def __init__(self, cells: tuple[int, int] = (1024, 600), **settings: Any) -> None:
        self.config = EmulatorConfig(cells=cells, **settings)
        self.clock: SubframeClock | FreeRunningClock = (
            FreeRunningClock(self.config.subframe_s) if self.config.subframe_s else SubframeClock()
        )
        self.core = LCoSEmulatorCore(self.config, clock=lambda: self.clock.value)
        self.port = EmulatedSerial(self.core)

    def start(self) -> EmulatedSerial:
        """Nothing to start; returns :attr:`port` (for symmetry with the process)."""
        return self.port

    @property
    def subframe(self) -> int:
        """The device's subframe clock."""
        return int(self.clock.value)

    def tick(self, n: int = 1) -> int:
        """Advance the external clock by ``n`` subframes (camera side)."""
        return self.clock.tick(n)

    def snapshot(self) -> EmulatorRecord:
        """The device's authoritative record now."""
        return self.core.record()

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open closed cells (see :meth:`LCoSEmulatorCore.inject_mask_fault`)."""
        self.core.inject_mask_fault(cells)

    def stop(self, timeout_s: float = 5.0) -> EmulatorRecord:
        """Final record (the core keeps no resources)."""
        reason = "disconnect injected" if self.core.disconnected else "stop requested"
        return self.core.record(reason)

    def __enter__(self) -> InProcessLCoS:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# --- the emulator process -------------------------------------------------------------


def _serve(
    config: EmulatorConfig,
    clock_value: Any,
    conn: Any,
    record_path: str | None,
    announce: Callable[[str], None],
) -> EmulatorRecord:
    """Run the controller behind a fresh pty until the host closes it (or told to stop)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    path = os.ttyname(slave)
    if config.subframe_s:
        free = FreeRunningClock(
            config.subframe_s, start=int(clock_value.value) if clock_value is not None else 0
        )

        def clock() -> int:
            v = free.value
            if clock_value is not None:
                clock_value.value = v
            return v

    elif clock_value is not None:

        def clock() -> int:
            return int(clock_value.value)

    else:
        raise InputError("an emulator without a shared clock needs a free-running subframe_s")

    core = LCoSEmulatorCore(config, clock)
    bps = config.link_bps
    chunk = max(64, int(bps / config.bits_per_byte * 0.002)) if bps else 65536
    out = bytearray()
    host_seen = False
    started = time.monotonic()
    reason = ""
    announce(path)
    try:
        while not reason:
            core.poll()
            out += core.pop_output()
            if out:
                try:
                    del out[: os.write(master, out)]
                except BlockingIOError:
                    pass
                except OSError:
                    reason = "host closed the port"
                    break
            if core.disconnected and not out:
                reason = "disconnect injected"
                break
            now = time.monotonic()
            if not host_seen and now - started > config.connect_timeout_s:
                reason = "no host connected"
                break
            rlist: list[Any] = [conn] if conn is not None else []
            if core.input_backlog_s() < 0.002:
                rlist.append(master)
            nxt = core.next_deadline()
            timeout = 0.05 if nxt is None else min(0.05, max(0.0, nxt - now))
            if config.subframe_s:
                timeout = min(timeout, config.subframe_s)
            readable, _, _ = select.select(rlist, [master] if out else [], [], timeout)
            if conn is not None and conn in readable:
                try:
                    msg = conn.recv()
                except (EOFError, OSError):
                    reason = "parent went away"
                    break
                if msg[0] == "snapshot":
                    conn.send(("record", core.record()))
                elif msg[0] == "fault_mask":
                    core.inject_mask_fault(msg[1])
                    conn.send(("ok", None))
                elif msg[0] == "stop":
                    reason = "stop requested"
            if master in readable:
                try:
                    data = os.read(master, chunk)
                except BlockingIOError:
                    data = None
                except OSError:
                    reason = "host closed the port"
                    break
                if data:
                    core.receive(data)
                    if not host_seen:
                        host_seen = True
                        os.close(slave)  # from now on the host closing its end reads as EIO
                elif data is not None:
                    reason = "host closed the port"
    finally:
        for fd in (master,) if host_seen else (master, slave):
            try:
                os.close(fd)
            except OSError:
                pass
        record = core.record(reason or "error")
        if conn is not None:
            try:
                conn.send(("final", record))
            except (OSError, ValueError):
                pass
        if record_path:
            record.save_npz(record_path)
    return record


def _process_main(
    config: EmulatorConfig, clock_value: Any, conn: Any, record_path: str | None
) -> None:
    _serve(config, clock_value, conn, record_path, lambda path: conn.send(("ready", path)))


class LCoSEmulator:
    """An emulated LCoS controller in its own process, behind a pseudo-terminal.

    Parameters
    ----------
    cells : (int, int)
        Grid (width, height).
    record_path : str, optional
        Also write the final :class:`EmulatorRecord` to this ``.npz`` file.
    start_timeout_s : float
        Longest wait for the process to come up (and to answer requests).
    **settings
        Further :class:`EmulatorConfig` fields (``link_bps``, ``latency_subframes``,
        ``leakage``, ``link_fault_rate``, ``disconnect_at_subframe``, ``seed``,
        ``subframe_s``, ...).

    Examples
    --------
    >>> with LCoSEmulator((64, 48), link_bps=3e6) as emu:      # doctest: +SKIP
    ...     lcos = SerialLCoS(emu.port)
    ...     s0 = lcos.open_all(0); emu.tick(); lcos.close_cells([5, 6], wait=True)
    ...     lcos.close()
    ...     record = emu.stop()
    """

    def __init__(
        self,
        cells: tuple[int, int] = (1024, 600),
        *,
        record_path: str | None = None,
        start_timeout_s: float = 20.0,
        **settings: Any,
    ) -> None:
        self.config = EmulatorConfig(cells=cells, **settings)
        self.record_path = record_path
        self.start_timeout_s = float(start_timeout_s)
        self._ctx = multiprocessing.get_context("spawn")
        self.clock = self._ctx.Value("q", 0)
        self._conn: Any = None
        self._proc: Any = None
        self._port: str | None = None
        self._final: EmulatorRecord | None = None
        self._lock = threading.Lock()

    @classmethod
    def from_rig(cls, rig: Any, **settings: Any) -> LCoSEmulator:
        """Emulator with the grid, latency and leakage of a :class:`~stages.rig.RigParams`."""
        cfg = EmulatorConfig.from_rig(rig, **settings)
        settings = {k: v for k, v in asdict(cfg).items() if k != "cells"}
        return cls(cfg.cells, **settings)

    def start(self) -> str:
        """Start the process; returns the pty path for the host to open."""
        if self._proc is not None:
            assert self._port is not None
            return self._port
        parent, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(
            target=_process_main,
            args=(self.config, self.clock, child, self.record_path),
            name="vet-lcos-emulator",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            if not parent.poll(self.start_timeout_s):
                raise DeviceError(
                    f"the LCoS emulator did not start within {self.start_timeout_s:g} s"
                )
            kind, path = parent.recv()
        except (EOFError, OSError):
            self._kill()
            raise DeviceError(
                "the LCoS emulator process died while starting (a script that starts it must "
                "guard its main code with `if __name__ == '__main__':`, see multiprocessing's spawn rules)"
            ) from None
        except DeviceError:
            self._kill()
            raise
        if kind != "ready":
            self._kill()
            raise DeviceError(f"the LCoS emulator failed to start ({kind})")
        self._port = path
        return path

    @property
    def port(self) -> str:
        """The pty path (starts the process if needed)."""
        return self._port if self._port is not None else self.start()

    @property
    def subframe(self) -> int:
        """The device's subframe clock."""
        return int(self.clock.value)

    def tick(self, n: int = 1) -> int:
        """Advance the shared clock by ``n`` subframes (the camera side's job)."""
        if self.config.subframe_s:
            raise DeviceError("a free-running subframe clock cannot be ticked")
        with self.clock.get_lock():
            self.clock.value += int(n)
            return int(self.clock.value)

    @property
    def running(self) -> bool:
        """Whether the emulator process is alive."""
        return self._proc is not None and self._proc.is_alive()

    def _request(self, msg: tuple[Any, ...], expect: str) -> Any:
        with self._lock:
            if self._final is None and self._conn is not None:
                try:
                    self._conn.send(msg)
                except (OSError, ValueError):
                    pass
                deadline = time.monotonic() + self.start_timeout_s
                while self._final is None:
                    remaining = deadline - time.monotonic()
                    try:
                        if remaining <= 0 or not self._conn.poll(remaining):
                            raise DeviceError(f"the LCoS emulator did not answer {msg[0]!r}")
                        kind, payload = self._conn.recv()
                    except (EOFError, OSError):
                        raise DeviceError(
                            "the LCoS emulator died without reporting its state"
                        ) from None
                    if kind == "final":
                        self._final = payload
                    elif kind == expect:
                        return payload
            if expect == "record" and self._final is not None:
                return self._final
            raise DeviceError("the LCoS emulator has exited")

    def snapshot(self) -> EmulatorRecord:
        """The device's authoritative record now (the final one if it has exited)."""
        return self._request(("snapshot",), "record")

    def inject_mask_fault(self, cells: ArrayLike) -> None:
        """Silently open cells in the device's mask (see the core's method)."""
        self._request(("fault_mask", np.asarray(cells, dtype=np.int64)), "ok")

    def stop(self, timeout_s: float = 5.0) -> EmulatorRecord:
        """Stop the process (if still running) and return its final record."""
        if self._proc is None:
            raise DeviceError("the LCoS emulator was never started")
        if self._final is None:
            try:
                self._request(("stop",), "final")
            except DeviceError:
                pass
        self._proc.join(timeout_s)
        self._kill()
        if self._final is None:
            raise DeviceError("the LCoS emulator exited without reporting its state")
        return self._final

    def _kill(self) -> None:
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.terminate()
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(2.0)
        if self._conn is not None and (proc is None or not proc.is_alive()):
            if self._final is None:
                try:  # the final record may still sit in the pipe
                    while self._conn.poll(0):
                        kind, payload = self._conn.recv()
                        if kind == "final":
                            self._final = payload
                except (EOFError, OSError):
                    pass
            self._conn.close()
            self._conn = None

    def __enter__(self) -> LCoSEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._proc is not None:
            try:
                self.stop()
            except DeviceError:
                pass


# --- command line ----------------------------------------------------------------------


def _parse_cells(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"cells must look like 1024x600, got {text!r}") from None
    return w, h


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.devices.lcos_emulator``: serve one host session on a new pty.

    Prints the pty path on standard output, then runs with a free-running clock until
    the host closes the port; the final record goes to ``--record`` if given.
    """
    ap = argparse.ArgumentParser(
        prog="python -m stages.devices.lcos_emulator", description=main.__doc__
    )
    ap.add_argument(
        "--cells", type=_parse_cells, default=(1024, 600), help="grid WxH (default 1024x600)"
    )
    ap.add_argument(
        "--subframe-s", type=float, default=0.00758, help="free-running subframe length, s"
    )
    ap.add_argument("--latency", type=int, default=1, help="latency, subframes")
    ap.add_argument("--leakage", type=float, default=0.002)
    ap.add_argument(
        "--link-bps", type=float, default=None, help="link rate, bit/s (default unthrottled)"
    )
    ap.add_argument("--link-fault-rate", type=float, default=0.0)
    ap.add_argument("--disconnect-at-subframe", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--record", default=None, help="write the final record to this .npz")
    ap.add_argument("--connect-timeout-s", type=float, default=60.0)
    args = ap.parse_args(argv)
    try:
        config = EmulatorConfig(
            cells=args.cells,
            subframe_s=args.subframe_s,
            latency_subframes=args.latency,
            leakage=args.leakage,
            link_bps=args.link_bps,
            link_fault_rate=args.link_fault_rate,
            disconnect_at_subframe=args.disconnect_at_subframe,
            seed=args.seed,
            connect_timeout_s=args.connect_timeout_s,
        )
    except InputError as exc:
        print(f"lcos_emulator: error: {exc}", file=sys.stderr)
        return 2

    def announce(path: str) -> None:
        print(path, flush=True)

    record = _serve(config, multiprocessing.Value("q", 0, lock=False), None, args.record, announce)
    print(
        f"lcos_emulator: {record.exit_reason}; counters {json.dumps(record.counters)}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
