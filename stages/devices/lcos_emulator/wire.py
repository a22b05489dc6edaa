"""The emulated link's throttling: one direction of a wire of ``link_bps`` bit/s.

Bytes handed to :meth:`Wire.send` at time ``t`` arrive when the wire has carried them:
``max(t, wire free) + extra delay + len * bits_per_byte / link_bps`` (no throttling when
``link_bps`` is None). Pieces arrive in order.
"""

from __future__ import annotations

import collections
from collections.abc import Iterator

__all__ = ["Wire"]


class Wire:
    """One direction of a throttled serial wire.

    Parameters
    ----------
    link_bps : float or None
        Rate in bit/s; None = unthrottled (bytes arrive when sent, plus any delay).
    bits_per_byte : int
        Bits each byte costs (10 = 8N1 UART framing).
    """

    def __init__(self, link_bps: float | None, bits_per_byte: int) -> None:
        self.link_bps = link_bps
        self.bits_per_byte = int(bits_per_byte)
        self._queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self._free = 0.0

    def send(self, t: float, data: bytes, extra_s: float = 0.0) -> float:
        """Put ``data`` on the wire at time ``t`` (seconds); returns its arrival time."""
        duration = len(data) * self.bits_per_byte / self.link_bps if self.link_bps else 0.0
        self._free = max(t, self._free) + extra_s + duration
        self._queue.append((self._free, data))
        return self._free

    def arrived(self, t: float) -> Iterator[bytes]:
        """Yield, in order, the pieces that have fully arrived by time ``t``."""
        while self._queue and self._queue[0][0] <= t:
            yield self._queue.popleft()[1]

    @property
    def next_arrival(self) -> float | None:
        """Arrival time of the next piece on the wire (None when empty)."""
        return self._queue[0][0] if self._queue else None

    def backlog_s(self, t: float) -> float:
        """Seconds from ``t`` until the wire has carried everything sent so far."""
        return max(0.0, self._free - t)

    def __bool__(self) -> bool:
        return bool(self._queue)
