"""The host's per-subframe scan: subtract a frame from each pixel's remaining budget and
find the pixels whose budget reached zero.

The scan is three passes over memory (subtract, compare, find) and is bound by memory
bandwidth, so a large frame is cut into bands scanned on two threads, the caller's and a
pool's (numpy releases the GIL inside each pass); the hits are found a 64-bit word at a time, skipping the words with
none, which is cheaper than ``np.flatnonzero`` over every byte while hits are sparse.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: Below this many pixels one thread is faster than handing out bands.
BANDED_FROM_PIXELS = 1 << 19
#: Threads for the banded scan (the passes are memory bound: two saturate a socket).
SCAN_THREADS = min(2, os.cpu_count() or 1)

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max(1, SCAN_THREADS - 1), thread_name_prefix="vet-scan")
        return _POOL


def _forget_pool() -> None:  # a forked child has none of its parent's threads
    global _POOL, _POOL_LOCK
    _POOL, _POOL_LOCK = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def set_bits(mask: np.ndarray) -> np.ndarray:
    """Indices (int64, ascending) of the True elements of a 1-D bool array whose length
    is a multiple of 8: ``np.flatnonzero(mask)``, found word by word while sparse."""
    words = mask.view(np.uint64)
    hit = np.flatnonzero(words != 0)
    if hit.size > words.size // 4:  # dense: the plain scan is faster
        return np.flatnonzero(mask)
    within = np.flatnonzero(mask.reshape(-1, 8)[hit])
    return hit[within >> 3] * 8 + (within & 7)


class CrossingScan:
    """Subtract frames from ``remaining`` (float32, 1-D, contiguous, updated in place)
    and return where it is at or below zero.

    Elements set to a huge value (for example 3e38) never cross again: that is how the
    caller retires pixels. ``banded`` forces (True) or forbids (False) the threaded
    bands; by default they are used from :data:`BANDED_FROM_PIXELS` pixels on.
    """

    def __init__(self, remaining: np.ndarray, banded: bool | None = None):
        if remaining.ndim != 1 or remaining.dtype != np.float32:
            raise ValueError("remaining must be a 1-D float32 array")
        n = remaining.size
        self.remaining = remaining
        # The compare's output, padded to whole 64-bit words (the padding stays False).
        self._hits = np.zeros(-(-n // 8) * 8, bool)
        if banded is None:
            banded = n >= BANDED_FROM_PIXELS and SCAN_THREADS > 1
        parts = SCAN_THREADS if banded else 1
        edges = [min(n, (n * i // parts) // 64 * 64) for i in range(parts)] + [n]
        self._bands = [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]

    def _band(self, frame: np.ndarray, a: int, b: int) -> np.ndarray:
        rem = self.remaining[a:b]
        np.subtract(rem, frame[a:b], out=rem, casting="unsafe")
        hits = self._hits[a:b]
        np.less_equal(rem, 0, out=hits)
        padded = self._hits[a : -(-b // 8) * 8] if b == self.remaining.size else hits
        return set_bits(padded) + a

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """Subtract ``frame`` (any real dtype, ``remaining.size`` elements); return the
        indices (int64, ascending) where ``remaining <= 0``."""
        flat = np.ascontiguousarray(frame).reshape(-1)
        if flat.size != self.remaining.size:
            raise ValueError(f"frame has {flat.size} pixels, expected {self.remaining.size}")
        if len(self._bands) == 1:
            return self._band(flat, *self._bands[0])
        # The calling thread scans the first band itself (no hand-off to wait for).
        rest = [_pool().submit(self._band, flat, *ab) for ab in self._bands[1:]]
        first = self._band(flat, *self._bands[0])
        return np.concatenate([first] + [job.result() for job in rest])
