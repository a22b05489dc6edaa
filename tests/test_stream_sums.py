"""A stream summed into the misfit's bins still gives the motion estimate's bins to the
bit (stages.formats.stream_sums), and the deblur that bins first makes the same image."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from stages.formats.capture import MOTION_BINS, Capture, measure_bin_edges
from stages.formats.stream_sums import StreamSums, serves, summed_stream
from stages.rig import RigParams
from tests.test_capture_stream import _stream_capture


def _stream(nb: int = 131) -> Capture:
    # int16 DN over the whole range (negative ones too): every sum stays exact.
    cap = _stream_capture(nb, np.int16, h=5, w=4, seed=3, values=(-32768, 32767))
    cap.meta["note"] = "kept"  # (the rest of the metadata goes with every bin)
    return cap


def _same(a: Capture, b: Capture) -> None:
    assert a.measure.dtype == b.measure.dtype == np.float32
    np.testing.assert_array_equal(a.measure, b.measure)
    np.testing.assert_array_equal(a.measure_times, b.measure_times)
    assert a.meta == b.meta


def test_the_sums_give_each_bin_of_the_stream_to_the_bit():
    cap = _stream()
    kept = copy.deepcopy(cap)
    assert serves(cap, 16, (MOTION_BINS, 16))
    bins, sums = summed_stream(cap, 16)
    assert cap.measure is None and bins.measure.shape == (16, 5, 4, 3)
    _same(bins, kept.time_bins(16))
    assert sums.keeps_stream and sums.measure_shape == kept.measure.shape
    assert sums.shape == kept.shape
    for n in (MOTION_BINS, 16, 4, 2, 1):
        np.testing.assert_array_equal(sums.bin_times(n), kept.bin_times(n))
        for k in range(n):
            _same(sums.time_bin(n, k), kept.time_bin(n, k))
    _same(sums.time_bins(MOTION_BINS), kept.time_bins(MOTION_BINS))


def test_a_bin_not_made_of_whole_sums_is_refused():
    cap = _stream()
    assert not serves(cap, 12, (MOTION_BINS,))  # (an edge of 8 bins is none of 12's)
    _bins, sums = summed_stream(cap, 12)
    with pytest.raises(ValueError, match="not whole bins"):
        sums.time_bin(MOTION_BINS, 1)


@pytest.mark.parametrize(
    "dtype, frames, ok",
    [
        (np.int16, 131, True),
        (np.uint16, 131, True),
        (np.uint16, 512, False),  # (512 x 65535 over 2**24: a float32 sum rounds)
        (np.float32, 131, False),  # (float sums depend on their order)
    ],
)
def test_sums_serve_only_where_they_are_exact(dtype, frames, ok):
    cap = _stream(nb=frames)
    cap.measure = cap.measure.astype(dtype)
    assert measure_bin_edges(frames, 16)[-1] == frames
    assert serves(cap, 16, (MOTION_BINS, 16)) is ok


def test_stream_sums_are_not_a_capture():
    # What the motion estimate reads alone: anything else fails loudly, never reads sums
    # as if they were the stream.
    _bins, sums = summed_stream(_stream(), 16)
    assert isinstance(sums, StreamSums) and not hasattr(sums, "measure")


def test_a_deblur_that_bins_first_makes_the_image_of_one_that_bins_after(monkeypatch):
    # A frame where the compute budget sets the misfit's bins (FIT_BIN_PIXELS lowered to
    # make this small frame one): with its stream let go, the deblur bins first and the
    # motion estimate reads the sums; kept, it reads the stream. The same image, to the
    # bit, in one piece and in tiles.
    from stages.deblur import deblur, problem
    from stages.formats import stream_sums
    from stages.motion import parse_motion
    from stages.scenes import builtin_interior
    from stages.simulate import simulate

    w, h = 96, 64
    cap = simulate(
        builtin_interior(w, h),
        parse_motion("translate:20,0"),
        RigParams(sensor_size=(w, h)),
        seed=1,
    )["vet"]
    assert cap.keeps_stream
    monkeypatch.setattr(problem, "FIT_BIN_PIXELS", w * h * problem.FIT_BINS)
    made = []
    real = stream_sums.summed_stream
    monkeypatch.setattr(stream_sums, "summed_stream", lambda *a: made.append(1) or real(*a))
    for tile in (None, 64):
        kept = deblur(copy.deepcopy(cap), tile=tile)[0]
        assert not made
        first = copy.deepcopy(cap)
        released = deblur(first, tile=tile, release_stream=True)[0]
        assert made and first.measure is None
        made.clear()
        np.testing.assert_array_equal(released.radiance, kept.radiance)
        assert released.meta["fit_bins"] == kept.meta["fit_bins"] == problem.FIT_BINS
