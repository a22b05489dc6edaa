"""Captures with many measuring bins: every writer's layout reads back, hdr-static accepts it."""

from __future__ import annotations

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
