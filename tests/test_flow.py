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


def test_motion_picture_panels_share_one_scale_and_carry_the_key():
    from stages.flow import flow_key, motion_picture, picture_speed_scale

    est = np.zeros((60, 80, 2), np.float32)
    est[20:40, 20:50] = (40.0, 0.0)  # a small moving object on a still background
    true = est.copy()
    true[20:40, 20:50] = (20.0, 0.0)
    # The still background does not count towards the scale.
    assert picture_speed_scale(est, true) == pytest.approx(40.0, rel=0.01)
    assert picture_speed_scale(np.zeros_like(est)) == 1.0
    pic = motion_picture([("estimated", est), ("true", true)])
    key = flow_key(picture_speed_scale(est, true))
    assert pic.shape[1] == 2 * (80 + 8) + key.shape[1]
    assert pic.shape[0] == max(60 + 22, key.shape[0])
    # Below each 22-pixel caption bar: the same pixel of both panels, on one scale.
    left = pic[22 + 30, 35]
    right = pic[22 + 30, 88 + 35]
    assert tuple(left) == tuple(flow_to_color(est, 40.0)[30, 35])
    assert tuple(right) == tuple(flow_to_color(true, 40.0)[30, 35])
    assert left[1] < right[1]  # 40 px/s is more saturated (less white) than 20 px/s
    assert np.all(pic[22 + 5, 5] == 255)  # still is white
    # The key's rim, rightwards, is the colour of full speed to the right.
    k = flow_key(40.0, size=101)
    assert k.shape == (22 + 101, 101, 3)  # the speed caption above the wheel
    rim_right = k[22 + 50, 98]  # 48 of the 50 px radius (inside the outline): 96% of full speed
    assert np.abs(rim_right.astype(int) - flow_to_color(est, 40.0)[30, 35]).max() <= 12


@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_flow_started_from_a_prediction_finds_a_long_displacement(method):
    """25 px on a 128 px image is beyond what either pyramid finds on its own; started
    from a prediction 3 px off, both find it, and the warp residual says which is right."""
    import cv2

    from stages.flow import _flow_pair, warp_residual

    rng = np.random.default_rng(0)
    g = cv2.GaussianBlur(rng.random((96, 128)).astype(np.float32), (0, 0), 2)
    a = (255 * (g - g.min()) / (g.max() - g.min())).astype(np.uint8)
    b = cv2.warpAffine(
        a, np.float32([[1, 0, 25], [0, 1, 4]]), (128, 96), borderMode=cv2.BORDER_REFLECT
    )
    inner = (slice(20, 70), slice(30, 100))
    plain = _flow_pair(a, b, method)
    start = np.zeros((96, 128, 2), np.float32)
    start[...] = (23, 2)
    guided = _flow_pair(a, b, method, init=start)
    assert np.median(guided[inner], axis=(0, 1)) == pytest.approx([25, 4], abs=0.2)
    assert np.median(np.hypot(*(plain[inner] - (25, 4)).T)) > 5
    truth = np.zeros_like(start)
    truth[...] = (25, 4)
    residual = {
        k: np.median(warp_residual(a, b, f)[inner])
        for k, f in (("truth", truth), ("plain", plain), ("guided", guided))
    }
    assert residual["truth"] < 1.0 and residual["guided"] < 1.0
    assert residual["plain"] > 100 * max(residual["guided"], 0.01)
