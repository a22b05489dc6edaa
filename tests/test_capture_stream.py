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

    from stages.formats.capture import Capture

    rng = np.random.default_rng(0)
    h, w, nb = 384, 512, 96
    measure = rng.integers(0, 4000, (nb, h, w, 3), dtype=np.int16)
    times = np.stack([np.arange(nb), np.arange(1, nb + 1)], 1) * 0.0075
    cap = Capture(
        I=np.ones((h, w, 3), np.float32),
        T=np.full((h, w), 0.5, np.float32),
        channels=["R", "G", "B"],
        rig=RigParams(sensor_size=(w, h)),
        measure=measure,
        measure_times=times,
    )
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
