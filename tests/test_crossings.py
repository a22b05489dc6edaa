"""The host's per-subframe crossing scan: same answer banded or not, at any size."""

from __future__ import annotations

import numpy as np
import pytest

from stages.crossings import CrossingScan, set_bits


@pytest.mark.parametrize("density", [0.0, 1e-4, 0.01, 0.3, 1.0])
def test_set_bits_is_flatnonzero(density):
    rng = np.random.default_rng(3)
    mask = rng.random(8 * 5003) < density
    assert np.array_equal(set_bits(mask), np.flatnonzero(mask))


@pytest.mark.parametrize("n", [1, 7, 64, 1001, 4099])
@pytest.mark.parametrize("banded", [False, True])
def test_scan_finds_what_a_running_sum_crosses(n, banded):
    rng = np.random.default_rng(n)
    budget = rng.uniform(5, 50, n).astype(np.float32)
    budget[rng.random(n) < 0.1] = 3.0e38  # retired: never crosses
    remaining = budget.copy()
    scan = CrossingScan(remaining, banded=banded)
    total = np.zeros(n, np.float64)
    for _ in range(12):
        frame = rng.poisson(4.0, n).astype(np.float32)
        total += frame
        found = scan(frame)
        want = np.flatnonzero(budget.astype(np.float64) - total <= 0)
        assert np.array_equal(found, want)
        assert found.dtype == np.int64
    assert np.allclose(remaining[budget < 1e30], (budget - total)[budget < 1e30])


def test_scan_takes_integer_frames_and_refuses_a_wrong_size():
    remaining = np.full(100, 10, np.float32)
    scan = CrossingScan(remaining)
    assert scan(np.full((10, 10), 4, np.uint16)).size == 0
    assert scan(np.full((10, 10), 4, np.uint16)).size == 0
    assert scan(np.full((10, 10), 4, np.uint16)).size == 100
    with pytest.raises(ValueError, match="99 pixels, expected 100"):
        scan(np.zeros(99, np.float32))
    with pytest.raises(ValueError, match="1-D float32"):
        CrossingScan(np.zeros((2, 2), np.float32))


def _scan_in_child(queue):
    remaining = np.full(1024, 1, np.float32)
    queue.put(CrossingScan(remaining, banded=True)(np.ones(1024, np.float32)).size)


def test_a_forked_child_scans_in_bands_with_a_pool_of_its_own():
    """A child forked after the parent's scan pool started has none of its threads: it
    starts its own instead of waiting forever on the parent's."""
    import multiprocessing

    remaining = np.full(1024, 5, np.float32)
    assert CrossingScan(remaining, banded=True)(np.ones(1024, np.float32)).size == 0
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_scan_in_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=30) == 1024
    finally:
        child.join(5)
        if child.is_alive():
            child.kill()
