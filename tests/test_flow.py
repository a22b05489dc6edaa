"""Tests of motion initialisation from the measuring images."""

from __future__ import annotations

import numpy as np
import pytest

from stages.flow import estimate_velocity, flow_to_color, write_motion
from stages.formats.layered import read_layered
from stages.motion import parse_motion
from stages.rig import RigParams
from stages.scenes import builtin_chart
from stages.simulate import simulate


@pytest.fixture(scope="module")
def moving_chart():
    w, h = 128, 96
    rig = RigParams(sensor_size=(w, h))
    return simulate(
        builtin_chart(w, h), parse_motion("translate:30,-10"), rig, seed=3, methods=["vet"]
    )["vet"]


@pytest.mark.parametrize("method", ["farneback", "dis"])
def test_flow_recovers_translation(moving_chart, method):
    vel, conf = estimate_velocity(moving_chart, method)
    inner = vel[10:-10, 10:-10].reshape(-1, 2)
    med = np.median(inner, axis=0)
    assert med[0] == pytest.approx(30.0, abs=4.0)
    assert med[1] == pytest.approx(-10.0, abs=4.0)
    assert conf.shape == moving_chart.shape and conf.min() >= 0 and conf.max() <= 1


def test_motion_file_and_picture(tmp_path):
    vel = np.zeros((20, 30, 2), np.float32)
    vel[..., 0] = 5.0
    write_motion(str(tmp_path / "m.exr"), vel)
    data = read_layered(tmp_path / "m.exr")
    assert data.meta["kind"] == "motion" and data.meta["units"] == "px/s"
    assert np.allclose(data.layers["motion"][..., data.channels["motion"].index("u")], 5.0)
    pic = flow_to_color(vel)
    assert pic.shape == (20, 30, 3) and pic.dtype == np.uint8
    still = flow_to_color(np.zeros_like(vel))
    assert np.all(still == 255)
