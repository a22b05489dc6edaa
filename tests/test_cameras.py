"""Cameras: OpenCV replay of recorded measuring streams and the emulated sensors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stages.devices.cameras import OpenCVCamera
from stages.devices.emulated_cameras import EmulatedMeasurementCamera, EmulatedVETCamera
from stages.errors import DeviceError, InputError
from stages.motion import parse_motion
from stages.rig import RigParams


def _write_frames(folder, n, rng, ext=".png"):
    folder.mkdir()
    frames = [rng.integers(0, 4096, (12, 16), dtype=np.uint16) for _ in range(n)]
    for i, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"sub_{i:04d}{ext}"), f)
    return frames


@pytest.mark.parametrize("ext", [".png", ".tif"])
def test_replay_folder_keeps_16_bit_values_and_order(tmp_path, rng, ext):
    frames = _write_frames(tmp_path / "stream", 5, rng, ext)
    with OpenCVCamera(str(tmp_path / "stream"), frame_period_s=0.01) as cam:
        got = [cam.grab() for _ in range(5)]
        with pytest.raises(DeviceError, match="ended after 5 frames"):
            cam.grab()
    for i, (g, f) in enumerate(zip(got, frames, strict=True)):
        assert g.index == i and g.timestamp_s == pytest.approx(0.01 * i)
        np.testing.assert_array_equal(g.data[:, :, 0], f.astype(np.float32))


def test_replay_printf_pattern(tmp_path, rng):
    frames = _write_frames(tmp_path / "seq", 3, rng)
    with OpenCVCamera(str(tmp_path / "seq" / "sub_%04d.png")) as cam:
        first = cam.grab()
    np.testing.assert_array_equal(first.data[:, :, 0], frames[0])


def test_missing_sources_are_clear_errors(tmp_path):
    with pytest.raises(InputError, match="no such video"):
        OpenCVCamera(str(tmp_path / "nope.avi")).open()
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no PNG or TIFF"):
        OpenCVCamera(str(tmp_path / "empty")).open()


def test_emulated_cameras_match_simulate(small_scene):
    """With the device applying closures as simulate does, the emulated rig records
    exactly what `vet simulate` renders (same physics, same seeds)."""
    from stages.simulate import simulate

    rig = RigParams(sensor_size=(96, 80))
    motion = parse_motion("translate:30,0")
    cap = simulate(small_scene, motion, rig, seed=5, measure_bins=0)["vet"]
    scale = cap.radiance_scale
    meas = EmulatedMeasurementCamera(small_scene.radiance, motion, rig, scale, seed=5)
    from stages.physics import CellMap, ClosureController

    ctrl = ClosureController(rig, CellMap.for_rig(rig, (80, 96)))
    with meas:
        for k in range(rig.n_subframes):
            ctrl.step(meas.grab().data, k)
    vet = EmulatedVETCamera(small_scene.radiance, motion, rig, scale, seed=5)
    close = np.where(ctrl.close_subframe[:-1] == ctrl.NEVER, -1, ctrl.close_subframe[:-1])
    frame = vet.expose_frame(close)
    np.testing.assert_array_equal(ctrl.exposure_time(), cap.T)
    np.testing.assert_array_equal(frame.data, cap.I)


def test_dropped_frames_show_as_index_gaps(small_scene):
    rig = RigParams(sensor_size=(96, 80))
    cam = EmulatedMeasurementCamera(
        small_scene.radiance, parse_motion("none"), rig, 1.0, drop=(1, 2)
    )
    with cam:
        assert [cam.grab().index for _ in range(3)] == [0, 3, 4]
