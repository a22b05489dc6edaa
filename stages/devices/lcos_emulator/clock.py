"""Subframe clocks of the emulated controller.

On a real rig the controller's clock counts the measurement camera's subframe trigger
pulses. Here it is either external (:class:`SubframeClock`, advanced by the camera side,
or a shared ``multiprocessing.Value`` across processes) or free-running
(:class:`FreeRunningClock`, derived from wall time).
"""

from __future__ import annotations

import time

from ...errors import DeviceError

__all__ = ["FreeRunningClock", "SubframeClock"]


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
