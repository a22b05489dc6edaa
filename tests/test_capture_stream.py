"""Captures with many measuring bins: every writer's layout reads back, hdr-static accepts it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.formats import read_capture, write_capture
from stages.motion import parse_motion
from stages.rig import RigParams
from stages.simulate import simulate
from tests.conftest import run_vet


@pytest.fixture(scope="module")
def many_bins_capture(small_scene_module):
    rig = RigParams(sensor_size=(48, 40))
    return simulate(small_scene_module, parse_motion("none"), rig, seed=5, measure_bins=101)["vet"]


@pytest.fixture(scope="module")
def small_scene_module():
    from stages.scenes import load_scene

    return load_scene("builtin:interior", size=(48, 40))


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_over_100_bins_round_trip_in_time_order(tmp_path, many_bins_capture, ext):
    cap = many_bins_capture
    assert cap.measure.shape[0] == 101
    write_capture(tmp_path / f"c.{ext}", cap)
    back = read_capture(tmp_path / f"c.{ext}")
    assert back.measure.shape == cap.measure.shape
    np.testing.assert_array_equal(back.measure, cap.measure)
    np.testing.assert_allclose(back.measure_times, cap.measure_times)
    # bins come back in time order: M100 follows M99, not M10
    assert np.all(np.diff(back.measure_times[:, 0]) > 0)


def test_simulate_101_bins_then_hdr_static(tmp_path):
    cap = tmp_path / "c.exr"
    res = run_vet(
        "simulate", "builtin:interior", "--size", "48x40", "--measure-bins", "101", "-o", cap
    )
    assert res.returncode == 0, res.stderr
    res = run_vet("hdr-static", cap, "-o", tmp_path / "h.exr")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "h.exr").is_file()


@pytest.mark.parametrize("n_bins", [7, 101, 200])
def test_one_time_bin_is_that_bin_of_all_of_them(many_bins_capture, n_bins):
    cap = many_bins_capture
    cap.meta["measure_subframes"] = [1 + (k % 3 == 0) for k in range(cap.measure.shape[0])]
    try:
        every = cap.time_bins(n_bins)
        for k in range(every.measure.shape[0]):
            one = cap.time_bin(n_bins, k)
            assert one.measure.shape == (1, *cap.measure.shape[1:])
            np.testing.assert_array_equal(one.measure[0], every.measure[k])
            np.testing.assert_array_equal(one.measure_times[0], every.measure_times[k])
            assert one.measure_counts()[0] == every.measure_counts()[k]
    finally:
        del cap.meta["measure_subframes"]


def _stream_capture(nb, dtype, h=6, w=5, ch=3, seed=0, values=(0, 4000)):
    """A capture of a stream of ``nb`` frames, int16 DN drawn from ``values`` [low, high)
    (then as ``dtype``), some frames two subframes long (their time bins as long, on the
    rig's subframe clock, as the schema's relations ask)."""
    from stages.formats.capture import Capture

    rng = np.random.default_rng(seed)
    measure = rng.integers(*values, (nb, h, w, ch), dtype=np.int16).astype(dtype, copy=False)
    lengths = [1 + (k % 3 == 0) for k in range(nb)]
    edges = np.concatenate([[0], np.cumsum(lengths)])
    rig = RigParams(sensor_size=(w, h), frame_s=0.00758 * max(131, int(edges[-1])))
    times = np.stack([edges[:-1], edges[1:]], 1) * rig.subframe_s
    return Capture(
        I=np.ones((h, w, ch), np.float32),
        T=np.full((h, w), 0.5, np.float32),
        channels=["R", "G", "B"][:ch],
        rig=rig,
        measure=measure,
        measure_times=times,
        meta={"measure_subframes": lengths},
    )


_READ_PEAK = """
import sys
from stages.formats import read_capture


def peak():  # (the process's own high-water mark: ru_maxrss carries the parent's over)
    with open("/proc/self/status") as f:
        return next(int(v.split()[1]) for v in f if v.startswith("VmHWM:")) * 1024


before = peak()
cap = read_capture(sys.argv[1])
print(cap.measure.nbytes, peak() - before)
"""


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux's /proc")
@pytest.mark.parametrize("ext", ["npz", "exr"])
def test_reading_a_stream_holds_its_frames_once(tmp_path, ext):
    # The measuring images are stacked as they are read out, not copied beside all of
    # them (and an EXR's channels are decoded a block of rows at a time, not all into one
    # array first): reading a stream costs about its own size, not twice it. (One malloc
    # arena: the figure is what vet holds, not what OpenEXR's decoding threads' arenas
    # keep of freed blocks. An EXR's layers are stacked from the heap, which keeps the
    # freed ones while the stack fills: about 1.66x here, 2.38x before.)
    import os
    import subprocess
    import sys

    cap = _stream_capture(96, np.int16, 384, 512)
    measure = cap.measure
    write_capture(tmp_path / f"s.{ext}", cap)
    out = subprocess.run(
        [sys.executable, "-c", _READ_PEAK, str(tmp_path / f"s.{ext}")],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "MALLOC_ARENA_MAX": "1"},
    )
    nbytes, grew = (int(v) for v in out.stdout.split())
    assert nbytes == measure.nbytes
    assert grew < {"npz": 1.4, "exr": 1.9}[ext] * nbytes


def test_measuring_images_of_two_sizes_are_refused_in_one_line():
    from stages.errors import FormatError
    from stages.formats.capture import Capture

    cap = Capture(
        I=np.ones((6, 8, 1), np.float32),
        T=np.full((6, 8), 0.5, np.float32),
        channels=["Y"],
        rig=RigParams(sensor_size=(8, 6)),
        measure=np.ones((2, 6, 8, 1), np.float32),
        measure_times=np.array([[0.0, 0.1], [0.1, 0.2]]),
    )
    data = cap.to_layered()
    data.layers["M01"] = np.ones((6, 7, 1), np.float32)  # (a container made in memory)
    with pytest.raises(FormatError, match=r"^mem: measuring image M01 is not the size of M00$"):
        Capture.from_layered(data, "mem")


@pytest.mark.parametrize(
    ("nb", "n_bins", "dtype"),
    [(131, 16, np.int16), (131, 16, np.float32), (33, 16, np.int16), (97, 5, np.uint16)],
)
def test_time_bins_made_in_the_streams_memory_equal_the_others(nb, n_bins, dtype):
    # Consumed, the stream's own memory holds the bins (shrunk to them): the same sums,
    # times and counts as bins made beside the stream, which the capture no longer holds.
    cap = _stream_capture(nb, dtype)
    want = cap.time_bins(n_bins)
    got = cap.time_bins(n_bins, consume=True)
    assert cap.measure is None
    assert got.measure.dtype == np.float32 and got.measure.shape == want.measure.shape
    np.testing.assert_array_equal(got.measure, want.measure)
    np.testing.assert_array_equal(got.measure_times, want.measure_times)
    np.testing.assert_array_equal(got.measure_counts(), want.measure_counts())
    base = got.measure.base
    assert isinstance(base, np.ndarray) and base.dtype == np.dtype(dtype)
    assert base.nbytes == got.measure.nbytes  # (the stream's block, shrunk to the bins)


def test_a_stream_held_elsewhere_is_never_written_over():
    # Another capture holding the same stream, or a view of it, keeps it as it was: the
    # bins are then made beside it.
    from dataclasses import replace

    cap = _stream_capture(131, np.int16)
    want = cap.time_bins(16).measure
    other = replace(cap)
    copy = cap.measure.copy()
    got = cap.time_bins(16, consume=True)
    assert cap.measure is None
    np.testing.assert_array_equal(other.measure, copy)
    np.testing.assert_array_equal(got.measure, want)
    view = other.measure[3:]
    other.measure = view.base
    view_copy = view.copy()
    got = other.time_bins(16, consume=True)
    np.testing.assert_array_equal(view, view_copy)
    np.testing.assert_array_equal(got.measure, want)


def test_too_few_frames_per_bin_are_binned_beside_the_stream():
    # 20 int16 frames in 16 float32 bins: a bin would overwrite frames not yet read.
    from stages.formats.capture import measure_bin_edges, sum_bins_in_place

    cap = _stream_capture(20, np.int16)
    stream = cap.measure
    copy = stream.copy()
    box = [stream]
    del stream
    cap.measure = None
    assert sum_bins_in_place(box, measure_bin_edges(20, 16)) is None
    np.testing.assert_array_equal(box[0], copy)


_BIN_PEAK = """
import numpy as np
from tests.test_capture_stream import _stream_capture


def status(key):
    with open("/proc/self/status") as f:
        return next(int(v.split()[1]) for v in f if v.startswith(key + ":")) * 1024


cap = _stream_capture(96, np.int16, 384, 512)
before, held = status("VmHWM"), status("VmRSS")
bins = cap.time_bins(16, consume=True)
print(cap.measure is None, bins.measure.nbytes, status("VmHWM") - before, held - status("VmRSS"))
"""


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux's /proc")
def test_consumed_stream_and_its_bins_are_never_held_side_by_side():
    # A 113 MB stream binned into 38 MB: the peak grows by a few bins' temporaries, not by
    # the bins, and the process then holds the bins, not the stream.
    import os
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _BIN_PEAK],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "MALLOC_ARENA_MAX": "1"},
    )
    dropped, nbytes, grew, freed = out.stdout.split()
    stream_bytes = 96 * 384 * 512 * 3 * 2
    assert dropped == "True" and int(nbytes) == 16 * 384 * 512 * 3 * 4
    assert int(grew) < 0.5 * int(nbytes)
    assert int(freed) > 0.9 * (stream_bytes - int(nbytes))
