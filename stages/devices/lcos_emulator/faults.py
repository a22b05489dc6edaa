"""Seeded fault injection of the emulated link: corrupted, dropped and delayed frames."""

from __future__ import annotations

import numpy as np

__all__ = ["FaultInjector"]


class FaultInjector:
    """Decides, frame by frame, whether and how the link damages it.

    Parameters
    ----------
    rate : float
        Probability per frame of a fault; a fault is a corrupted byte, a dropped frame
        or a delayed frame, each a third of the time.
    delay_s : float
        Longest extra delay of a delayed frame, seconds (uniform in [0.1, 1] of it).
    seed : int
        Seed of the random generator (one stream for both directions, in call order).
    """

    def __init__(self, rate: float, delay_s: float, seed: int) -> None:
        self.rate = float(rate)
        self.delay_s = float(delay_s)
        self._rng = np.random.default_rng(seed)

    def draw(self) -> str | None:
        """``"corrupt"``, ``"drop"``, ``"delay"`` or None (no fault) for the next frame."""
        p = self.rate
        if p <= 0 or self._rng.random() >= p:
            return None
        return ("corrupt", "drop", "delay")[int(self._rng.integers(3))]

    def corrupt(self, raw: bytes) -> bytes:
        """``raw`` with one byte XORed with a random non-zero value."""
        b = bytearray(raw)
        pos = int(self._rng.integers(len(b)))
        b[pos] ^= int(self._rng.integers(1, 256))
        return bytes(b)

    def delay(self) -> float:
        """Extra delay of a delayed frame, seconds."""
        return float(self._rng.uniform(0.1, 1.0)) * self.delay_s
