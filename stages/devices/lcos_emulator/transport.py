"""The emulated controller in this process behind a pyserial-like port (no pty).

:class:`EmulatedSerial` is a mocked transport wired straight to an
:class:`~stages.devices.lcos_emulator.core.LCoSEmulatorCore`; :class:`InProcessLCoS`
has the same interface as the process-backed
:class:`~stages.devices.lcos_emulator.process.LCoSEmulator`, so one behavioural test
suite runs against both.
"""

from __future__ import annotations

import time
from typing import Any

from numpy.typing import ArrayLike

from .clock import FreeRunningClock, SubframeClock
from .config import EmulatorConfig, EmulatorRecord
from .core import LCoSEmulatorCore

__all__ = ["EmulatedSerial", "InProcessLCoS"]


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
