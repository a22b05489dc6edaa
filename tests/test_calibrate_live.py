"""vet calibrate recording a rig live through its devices (stages.calibrate.live): the
emulated realistic rig (seeded, 160x120) recorded into the --frames layout and calibrated
from it against its truth; the frame clock's file; the chessboard poses' terminal; a
camera whose exposure cannot be set."""

from __future__ import annotations

import io
import json
import logging
import tempfile
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from stages import calibrate as c
from stages.calibrate.frame_clock import emulated_timestamps, read_timestamps
from stages.calibrate.live import (
    LiveSettings,
    check_live,
    record_clock,
    record_switching,
    terminal_prompt,
)
from stages.devices.cameras import OpenCVCamera
from stages.devices.genicam import GenICamCamera
from stages.errors import InputError, UsageError
from stages.rig import RigParams

SIZE = (160, 120)


def run_cli(*args):
    from click.testing import CliRunner

    from vet_cli.main import cli

    return CliRunner().invoke(cli, list(map(str, args)))


def test_live_recording_of_the_emulated_rig_calibrates_to_its_parts(tmp_path):
    """--rig sim --save-frames records live (the board shown to the cameras, closures on
    the subframe clock, the camera's free run) and calibrates from the folder: the mapping
    within 0.1 px RMS, the trigger offset and switching time within 10%, and the frames
    of the layout in the folder."""
    d = tmp_path / "frames"
    out = tmp_path / "cal.npz"
    r = run_cli(
        "calibrate", "--rig", "sim", "--size", "160x120", "--seed", "3",
        "--clock-frames", 3000, "--save-frames", d, "-o", out,
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    names = {p.name for p in d.iterdir()}
    assert sum(n.startswith("target_vet_01_") for n in names) == 4
    assert sum(n.startswith("target_meas_00_") for n in names) == 4
    assert sum(n.startswith("switch_20_") for n in names) == 29 * 4
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    cal = c.read_calibration(out)
    err = cal.provenance["errors_vs_truth"]
    truth = cal.provenance["emulated_truth"]
    assert err["mapping_rms_px"] <= 0.1
    assert abs(err["trigger_offset_err_s"]) <= 0.1 * truth["trigger_offset_s"]
    assert abs(err["switch_rel_err"]) <= 0.1
    assert abs(err["trigger_jitter_rel_err"]) <= 0.2  # 3000 frames: a 1.3% sigma
    live = cal.provenance["live"]
    assert live["rig"] == "sim" and live["closures"] == [20] and live["poses"] == 2
    assert cal.provenance["source"] == f"folder:{d}"
    info = run_cli("info", out)
    meta = json.loads(info.stdout)["metadata"]
    assert meta["parts"]["switch_s"] == pytest.approx(cal.parts["switch_s"])


def test_live_calibration_into_a_temporary_folder(tmp_path, monkeypatch, caplog):
    """Without --save-frames a rig is recorded into a temporary folder that is removed;
    with no board poses the mapping is skipped with a warning."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    live = LiveSettings(clock_frames=0, board_poses=0, switch_subframe=-1)
    with caplog.at_level(logging.WARNING, logger="vet.calibrate"):
        with c.open_sim_calibration_rig(SIZE, seed=1, profile="realistic") as rig:
            cal = c.calibrate_live(rig, None, live=live)
    assert list(tmp_path.iterdir()) == []
    assert cal.provenance["source"] == "rig:sim"
    assert cal.homography is not None and "relay_blur_px" in cal.parts
    assert "measure_homography" not in cal.parts and "switch_s" not in cal.parts
    assert "measurement -> VET mapping is not found" in caplog.text


def test_timestamps_file_holds_the_frames_the_camera_gave(tmp_path):
    """The emulated measurement camera's free run: every frame it delivered within the
    run, its own id and timestamp (its clock's jitter, its drops); a replayed camera's
    frames likewise."""
    with c.open_sim_calibration_rig(SIZE, seed=2, profile="realistic") as rig:
        n = record_clock(rig, tmp_path / "a.csv", 3000)
        truth = rig.params
    ids, t = read_timestamps(tmp_path / "a.csv")
    want_ids, want_t = emulated_timestamps(truth, 3000, seed=2)
    assert n == ids.size and np.array_equal(ids, want_ids)
    assert np.allclose(t, want_t, atol=1e-9)
    assert 0 < 3000 - ids.size < 30  # drop rate 0.002
    resid = t - (truth.trigger_offset_s + ids * truth.subframe_s)
    assert 0.5 < np.std(resid) / truth.trigger_jitter_s < 1.5

    folder = tmp_path / "replay"
    folder.mkdir()
    for i in range(8):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((4, 6), i, np.uint16))
    cam = OpenCVCamera(str(folder), frame_period_s=0.01)
    assert record_clock(SimpleNamespace(measurement=cam), tmp_path / "b.csv", 5) == 5
    ids, t = read_timestamps(tmp_path / "b.csv")
    assert ids.tolist() == [0, 1, 2, 3, 4] and np.allclose(t, 0.01 * ids)


def test_a_camera_whose_frame_ids_do_not_advance_ends_the_clock_run(tmp_path):
    """A driver that numbers every frame 0 cannot hang the recording: at most as many
    grabs as subframes asked for (the repeated ids are then refused by the fit's reader)."""
    grabs = []

    class Stuck:
        def start_exposure(self):
            pass

        def grab(self):
            grabs.append(1)
            return SimpleNamespace(index=0, timestamp_s=0.01 * len(grabs))

    record_clock(SimpleNamespace(measurement=Stuck()), tmp_path / "s.csv", 50)
    assert len(grabs) == 50


def test_board_poses_without_a_terminal_exit_2_before_any_device(tmp_path):
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(
        '[lcos]\nurl = "/dev/null"\n\n[measurement_camera]\nsource = "/dev/video98"\n\n'
        '[vet_camera]\nsource = "/dev/video99"\n'
    )
    r = run_cli("calibrate", "--rig", rig_file, "-o", tmp_path / "cal.npz")
    assert r.exit_code == 2
    assert "standard input is not a terminal" in r.output and "--frames" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "cal.npz").exists()
    with pytest.raises(UsageError, match="--board-poses 0"):
        check_live(SimpleNamespace(vet=object(), measurement=object()), LiveSettings())
    check_live(None, LiveSettings(board_poses=0))  # nothing to ask
    check_live(None, LiveSettings(), ask=lambda k, n: None)  # someone answers


def test_terminal_prompt_asks_on_stderr_and_stops_when_stdin_closes(monkeypatch, capsys):
    monkeypatch.setattr("sys.stdin", io.StringIO("\n"))
    terminal_prompt(2, 3)
    assert capsys.readouterr().err == "place the board for pose 2 of 3, press Enter\n"
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    with pytest.raises(InputError, match="closed while waiting for board pose 1 of 3"):
        terminal_prompt(1, 3)


class _NoExposureTime:
    """An Aravis camera without a settable ExposureTime."""

    def is_exposure_time_available(self) -> bool:
        return False


@pytest.mark.parametrize("backend", ["opencv", "genicam"])
def test_a_camera_whose_exposure_cannot_be_set_skips_the_switching_series(
    tmp_path, caplog, backend
):
    if backend == "opencv":  # a replayed source: no V4L2 exposure control
        (tmp_path / "000.png").write_bytes(cv2.imencode(".png", np.zeros((4, 4), np.uint16))[1])
        vet = OpenCVCamera(str(tmp_path))
    else:
        vet = GenICamCamera()
        vet._is_open, vet._cam = True, _NoExposureTime()
    saved = []
    rig = SimpleNamespace(params=RigParams(), vet=vet, measurement=object())
    with caplog.at_level(logging.WARNING, logger="vet.calibrate"):
        got = record_switching(rig, lambda name, img: saved.append(name), LiveSettings(), 1e4)
    assert got == [] and saved == []
    assert "cannot have its exposure set from the host" in caplog.text
    assert "switching series (trigger offset, switching time) is skipped" in caplog.text
    assert Path(tmp_path).exists()


def test_a_real_rig_is_asked_for_each_board_pose_and_its_clock_recorded(tmp_path, caplog):
    """The hardware path with fake devices (a V4L2-like VET camera whose exposure the
    host cannot set): the person asked for each pose, both cameras' frames saved per
    pose, the switching series skipped, the measurement camera's own frame ids written."""
    from tests.test_calibrate import _fake_hardware_rig

    rig, _ = _fake_hardware_rig()
    asked = []
    live = LiveSettings(clock_frames=30, board_poses=2, board_frames=2)
    with caplog.at_level(logging.WARNING, logger="vet.calibrate"):
        cal = c.calibrate_live(
            rig,
            tmp_path / "frames",
            c.AcquisitionSettings(frames_per_exposure=2),
            live,
            ask=lambda k, n: asked.append((k, n)),
        )
    assert asked == [(1, 2), (2, 2)]
    names = {p.name for p in (tmp_path / "frames").iterdir()}
    for stem in ("target_vet_00_01", "target_meas_01_00", "open_0.01s_01", "meas_flat_0.005s_00"):
        assert f"{stem}.png" in names, stem
    assert not any(n.startswith("switch_") for n in names)
    assert "switching series (trigger offset, switching time) is skipped" in caplog.text
    ids, _ = read_timestamps(tmp_path / "frames" / "meas_timestamps.csv")
    assert ids.size == 30 and np.array_equal(np.diff(ids), np.ones(29))
    assert cal.provenance["live"]["clock_frames"] == 30
    assert cal.homography is not None
