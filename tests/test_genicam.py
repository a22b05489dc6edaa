"""The GenICam camera backend (stages.devices.genicam).

Rig-file parsing and errors run everywhere. The rest drives Aravis's own fake GigE Vision
camera (``arv-fake-gv-camera-0.8``, Debian's aravis-tools) on loopback: it needs Aravis's
GObject bindings in the venv, so it runs in ``make test-hardware`` (which installs them) and
skips cleanly elsewhere.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from stages.devices import genicam
from stages.devices.rigs import load_rig_file
from stages.errors import DeviceError, InputError
from vet_cli.main import cli

FAKE = shutil.which("arv-fake-gv-camera-0.8")


def _has_aravis() -> bool:
    try:
        genicam.aravis()
    except DeviceError:
        return False
    return True


#: ``make test-hardware`` sets this: there a missing facility is a failure, not a skip.
REQUIRED = os.environ.get("VET_REQUIRE_HARDWARE") == "1"
MISSING = "Aravis fake camera and PyGObject not installed (make test-hardware installs them)"
needs_fake = pytest.mark.skipif(
    (FAKE is None or not _has_aravis()) and not REQUIRED, reason=MISSING
)


# --- everywhere ---------------------------------------------------------------------------


def _rig_toml(tmp_path: Path, meas: str, vet: str, lcos_url: str = "/dev/null", params: str = ""):
    path = tmp_path / "rig.toml"
    path.write_text(
        f'[params]\n{params}\n[lcos]\nurl = "{lcos_url}"\n\n'
        f"[measurement_camera]\n{meas}\n\n[vet_camera]\n{vet}\n"
    )
    return path


def test_rig_file_selects_backend_and_checks_keys(tmp_path):
    rig = _rig_toml(tmp_path, 'backend = "genicam"\nexposure_us = 7000', 'source = "v.mp4"')
    data = load_rig_file(rig)
    assert data["measurement_camera"]["backend"] == "genicam"
    cam = genicam.camera_from_section(data["measurement_camera"], "rig.toml: [measurement_camera]")
    assert cam.exposure_us == 7000.0 and cam.pixel_format == "Mono16" and cam.trigger == "free"

    bad = _rig_toml(tmp_path, 'backend = "gige"', 'source = "v.mp4"')
    with pytest.raises(InputError, match=r"backend = 'gige'; known: opencv, genicam"):
        load_rig_file(bad)
    for line, message in (
        ('backend = "genicam"\nexposure = 3', "unknown key.*exposure"),
        ('backend = "genicam"\nexposure_us = "fast"', "exposure_us must be a number"),
        ('backend = "genicam"\npixel_format = "Bayer12"', "pixel_format 'Bayer12'"),
        ('backend = "genicam"\nregion = [640]', "region must be"),
        ('backend = "genicam"\nright_shift = 12', "right_shift must be 0-8"),
    ):
        rig = _rig_toml(tmp_path, line, 'source = "v.mp4"')
        with pytest.raises(InputError, match=message):
            genicam.camera_from_section(load_rig_file(rig)["measurement_camera"], "x")


def test_missing_aravis_is_a_clear_device_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "gi", None)  # import gi -> ImportError
    with pytest.raises(DeviceError, match="need Aravis 0.8 and PyGObject.*make test-hardware"):
        genicam.aravis()
    cam = genicam.GenICamCamera("Aravis-Fake-GV01")
    with pytest.raises(DeviceError, match="gir1.2-aravis-0.8"):
        cam.open()


def test_capture_without_aravis_exits_1_with_one_line(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "gi", None)
    emu, port = _lcos_emulator("32x24", 0.01)
    rig = _rig_toml(
        tmp_path,
        'backend = "genicam"',
        'backend = "genicam"',
        lcos_url=port,
        params="frame_s = 0.2\nsubframe_s = 0.01\nsensor_size = [64, 48]\nlcos_cells = [32, 24]",
    )
    try:
        res = CliRunner().invoke(cli, ["capture", "--rig", str(rig), "-o", str(tmp_path / "cap")])
    finally:
        emu.wait(20)
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output and "PyGObject" in res.output


# --- on Aravis's fake GigE Vision camera ---------------------------------------------------


def _start_fake(address: str, serial: str) -> subprocess.Popen | None:
    proc = subprocess.Popen(
        [FAKE, "-i", address, "-s", serial],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    arv = genicam.aravis()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return None  # e.g. no interface holds this address
        try:
            arv.Camera.new(address)
            return proc
        except Exception:  # noqa: BLE001 - not listening yet
            time.sleep(0.1)
    proc.kill()
    return None


@pytest.fixture(scope="module")
def fake_cameras():
    """One fake camera on 127.0.0.1 and, where loopback also holds 127.0.0.2 (``make
    test-hardware`` adds it as root), a second one there: addresses of those running."""
    if FAKE is None or not _has_aravis():
        (pytest.fail if REQUIRED else pytest.skip)(MISSING)
    procs, addresses = [], []
    for address, serial in (("127.0.0.1", "GV01"), ("127.0.0.2", "GV02")):
        proc = _start_fake(address, serial)
        if proc is not None:
            procs.append(proc)
            addresses.append(address)
    if not addresses:
        (pytest.fail if REQUIRED else pytest.skip)("the Aravis fake camera did not start")
    yield addresses
    for proc in procs:
        proc.terminate()
        proc.wait(5)


@needs_fake
def test_free_running_frames_settings_and_timestamps(fake_cameras):
    cam = genicam.GenICamCamera(
        fake_cameras[0],
        exposure_us=8000,
        frame_rate_hz=100,
        region=(64, 48),
        pixel_format="Mono16",
        right_shift=4,
    )
    with cam:
        frames = [cam.grab() for _ in range(10)]
    s = cam.describe()
    assert (s["vendor"], s["model"]) == ("Aravis", "Fake")
    assert s["exposure_us"] == 8000.0 and s["frame_rate_hz"] == pytest.approx(100.0)
    assert s["region"] == [0, 0, 64, 48] and s["pixel_format"] == "Mono16"
    assert s["trigger_mode"] == "Off"
    for f in frames:
        assert f.data.shape == (48, 64, 1) and f.data.dtype == np.float32
        assert 0 < f.data.max() <= 4095  # 16-bit container shifted to 12 bits
    assert [f.index for f in frames] == list(range(10))
    dt = np.diff([f.timestamp_s for f in frames])
    assert frames[0].timestamp_s == 0.0
    assert np.median(dt) == pytest.approx(0.01, rel=0.1)


@needs_fake
def test_software_trigger_exposes_one_frame_per_request(fake_cameras):
    cam = genicam.GenICamCamera(
        fake_cameras[0], exposure_us=5000, region=(32, 24), trigger="software", timeout_s=0.3
    )
    with cam:
        assert cam.describe()["trigger_mode"] == "On"
        with pytest.raises(DeviceError, match="delivered no frame within"):
            cam.grab()  # nothing was triggered
        cam.start_exposure()
        frame = cam.grab()
    assert frame.data.shape == (24, 32, 1) and frame.index == 0


@needs_fake
def test_settings_outside_the_camera_range_are_refused(fake_cameras):
    cam = genicam.GenICamCamera(fake_cameras[0], exposure_us=1e9)
    with pytest.raises(DeviceError, match=r"exposure_us 1000000000.0 is outside .*\[10, 1e\+07\]"):
        cam.open()
    with pytest.raises(DeviceError, match="does not fit the 2048x2048 sensor"):
        genicam.GenICamCamera(fake_cameras[0], region=(4096, 16)).open()


def _lcos_emulator(cells: str, subframe_s: float) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "stages.devices.lcos_emulator", "--cells", cells]
        + ["--subframe-s", str(subframe_s), "--connect-timeout-s", "20"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    port = proc.stdout.readline().strip()
    assert port.startswith("/dev/"), proc.stderr.read()
    return proc, port


@needs_fake
def test_vet_capture_on_fake_genicam_cameras(fake_cameras, tmp_path):
    """``vet capture`` on a rig file: the measurement camera is a fake GigE Vision camera
    streaming one frame per subframe, the VET camera a second fake camera exposing the
    whole frame on a software trigger (or, with one fake camera only, a recorded frame),
    the LCoS the emulated controller on a pty with a free-running clock."""
    w, h, sub, frame_s = 64, 48, 0.01, 0.2
    emu, port = _lcos_emulator("32x24", sub)
    if len(fake_cameras) > 1:
        vet = (
            f'backend = "genicam"\ndevice = "{fake_cameras[1]}"\nregion = [{w}, {h}]\n'
            f'exposure_us = {frame_s * 1e6:.0f}\ntrigger = "software"\nright_shift = 4'
        )
    else:
        import cv2

        (tmp_path / "vetframes").mkdir()
        cv2.imwrite(str(tmp_path / "vetframes" / "0.png"), np.full((h, w), 900, np.uint16))
        vet = f'source = "{tmp_path / "vetframes"}"'
    rig = _rig_toml(
        tmp_path,
        f'backend = "genicam"\ndevice = "{fake_cameras[0]}"\nregion = [{w}, {h}]\n'
        f"exposure_us = 8000\nframe_rate_hz = {1 / sub:g}\nright_shift = 4",
        vet,
        lcos_url=port,
        params=f"frame_s = {frame_s}\nsubframe_s = {sub}\nsensor_size = [{w}, {h}]\n"
        "lcos_cells = [32, 24]",
    )
    try:
        res = CliRunner().invoke(
            cli, ["capture", "--rig", str(rig), "-o", str(tmp_path / "cap"), "--format", "npz"]
        )
    finally:
        emu.wait(20)
    assert res.exit_code == 0, res.output
    from stages.formats.capture import read_capture

    cap = read_capture(tmp_path / "cap" / "capture.npz")
    k = round(frame_s / sub)
    stats = cap.meta["capture_stats"]
    assert cap.I.shape[:2] == (h, w) and cap.T.shape[:2] == (h, w)
    assert stats["subframes"] == k
    meas = stats["cameras"]["measurement"]
    assert meas["exposure_us"] == 8000.0 and meas["frame_rate_hz"] == pytest.approx(1 / sub)
    assert meas["region"] == [0, 0, w, h] and meas["pixel_format"] == "Mono16"
    stamps = np.array(stats["measure_timestamps_s"])
    assert len(stamps) == k and stamps[0] == 0.0 and np.all(np.diff(stamps) > 0)
    assert np.median(np.diff(stamps)) == pytest.approx(sub, rel=0.1)
    raw = json.loads((tmp_path / "cap" / "measure_raw.json").read_text())
    assert raw["timestamps_s"] == stats["measure_timestamps_s"]
    if len(fake_cameras) > 1:
        vet_s = stats["cameras"]["vet"]
        assert vet_s["exposure_us"] == frame_s * 1e6 and vet_s["trigger_mode"] == "On"
        assert cap.I.max() > 0
    # T is what the device applied: within the frame, and some cells of the bright ramp closed
    assert 0 < cap.T.min() <= cap.T.max() <= frame_s + 1e-6


def test_rig_file_builds_genicam_cameras(tmp_path):
    from stages.devices.rigs import _camera

    rig = _rig_toml(
        tmp_path,
        'backend = "genicam"\ndevice = "GV01"\nexposure_us = 7000',
        'backend = "genicam"\ntrigger = "software"',
    )
    data = load_rig_file(rig)
    meas = _camera(data["measurement_camera"], "m", 0.01)
    vet = _camera(data["vet_camera"], "v", 1.0)
    assert isinstance(meas, genicam.GenICamCamera) and isinstance(vet, genicam.GenICamCamera)
    assert meas.device == "GV01" and meas.exposure_us == 7000.0 and vet.trigger == "software"
