"""vet calibrate: Gray-code decoding, homography fit, dark/leakage/gain, the file, CLI, rig path."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages import calibrate as c
from stages.errors import FormatError, InputError
from stages.physics import CellMap
from stages.rig import RigParams

from .conftest import run_vet


def _decode_maps(hom: np.ndarray, cells: tuple[int, int], size: tuple[int, int]):
    """Noise-free decoded maps for a homography: the cell containing each pixel centre."""
    w, h = size
    cm = CellMap(hom, cells, (h, w))
    idx = cm.pixel_cell
    valid = idx < cm.n_cells
    return np.where(valid, idx % cells[0], -1), np.where(valid, idx // cells[0], -1), valid


# --- Gray code --------------------------------------------------------------------------


@pytest.mark.parametrize("cells", [(37, 21), (64, 32), (1, 5), (2, 3)])
def test_gray_round_trip_identity(cells):
    """Patterns imaged 1:1 (pixel = cell), no noise: every cell decodes to itself."""
    pats = c.gray_code_patterns(cells)
    nx, ny = c.gray_bit_counts(cells)
    assert len(pats) == 2 * (nx + ny)
    assert all(p.shape == (cells[1], cells[0]) for p in pats)
    diffs = [
        pats[k].astype(np.float32) * 100 - pats[k + 1].astype(np.float32) * 100
        for k in range(0, len(pats), 2)
    ]
    cx, cy, valid = c.decode_gray(diffs, cells)
    yy, xx = np.mgrid[0 : cells[1], 0 : cells[0]]
    assert valid.all()
    np.testing.assert_array_equal(cx, xx)
    np.testing.assert_array_equal(cy, yy)


def test_gray_decode_rejects_unmodulated_and_ambiguous_pixels():
    cells = (16, 8)
    pats = c.gray_code_patterns(cells)
    diffs = [(pats[k].astype(np.float32) - pats[k + 1]) * 50 for k in range(0, len(pats), 2)]
    diffs = [d.copy() for d in diffs]
    for d in diffs:
        d[0, 0] = 0.5  # not modulated: outside the LCoS footprint
    diffs[-1][3, 3] = 2.0  # one weak bit: a pixel straddling a cell edge
    cx, cy, valid = c.decode_gray(diffs, cells, min_contrast_dn=4.0)
    assert not valid[0, 0] and cx[0, 0] == -1 and cy[0, 0] == -1
    assert not valid[3, 3]
    assert valid.sum() == valid.size - 2
    with pytest.raises(ValueError, match="differences"):
        c.decode_gray(diffs[:-1], cells)


def test_fit_homography_recovers_known_homography():
    cells, size = (96, 56), (160, 128)
    h_true = c.example_homography(cells, size)
    cx, cy, valid = _decode_maps(h_true, cells, size)
    fit = c.fit_homography(cx, cy, valid)
    mx, rms = c.homography_error_px(fit.homography, h_true, cells, size)
    assert mx < 0.05 and rms < 0.02
    assert fit.n_inliers == fit.n_points == valid.sum()
    assert fit.decode_agreement > 0.99
    # cell quantisation: about pitch / sqrt(6) px (pitch ~1.8 px here)
    assert 0.3 < fit.reprojection_rms_px < 1.2


def test_fit_homography_ignores_outliers():
    cells, size = (96, 56), (160, 128)
    h_true = c.example_homography(cells, size)
    cx, cy, valid = _decode_maps(h_true, cells, size)
    rng = np.random.default_rng(7)  # seeded: the same gross decode errors every run
    bad = rng.random(valid.shape) < 0.05
    cx = np.where(bad, rng.integers(0, cells[0], valid.shape), cx)
    fit = c.fit_homography(cx, cy, valid)
    mx, _ = c.homography_error_px(fit.homography, h_true, cells, size)
    assert mx < 0.2
    assert fit.n_inliers < fit.n_points


def test_fit_homography_needs_decoded_pixels():
    z = np.full((8, 8), -1)
    with pytest.raises(InputError, match="decoded"):
        c.fit_homography(z, z, z >= 0)


def test_example_homography_covers_sensor_and_refuses_gaps():
    c.example_homography((1024, 600), (1280, 1024))
    with pytest.raises(ValueError, match="zoom"):
        c.example_homography((100, 60), (200, 120), zoom=0.9)


def test_dark_model_recovers_bias_and_slope():
    gain = 0.4
    bias, d = 64.0, 12.0
    frames = {t: np.full((4, 5), bias + gain * d * t, np.float32) for t in (0.1, 1.0, 4.0)}
    b, dc = c.dark_model(frames, gain)
    np.testing.assert_allclose(b, bias, atol=1e-3)
    np.testing.assert_allclose(dc, d, rtol=1e-4)
    with pytest.raises(ValueError, match="two"):
        c.dark_model({1.0: frames[1.0]}, gain)


# --- acceptance on the emulated rig -------------------------------------------------------


def test_acceptance_emulated_rig_small():
    """DESIGN acceptance: known homography, leakage 0.003, dark current 15 e-/s."""
    fig = c.selftest(
        size=(320, 256), lcos_cells=(256, 150), leakage=0.003, dark_current_e_s=15.0, seed=1
    )
    assert fig["homography_max_px"] <= 0.5
    assert fig["homography_rms_px"] <= 0.5
    assert abs(fig["leakage_rel_err"]) <= 0.10
    assert abs(fig["dark_current_rel_err"]) <= 0.10
    assert abs(fig["gain_ratio_rel_err"]) <= 0.05
    assert fig["decoded_fraction"] > 0.95


@pytest.mark.slow
def test_acceptance_emulated_rig_full_size():
    fig = c.selftest(size=(1280, 1024), lcos_cells=(1024, 600))
    assert fig["homography_max_px"] <= 0.5
    assert abs(fig["leakage_rel_err"]) <= 0.10
    assert abs(fig["dark_current_rel_err"]) <= 0.10


# --- file round trip and use --------------------------------------------------------------


@pytest.fixture(scope="module")
def small_cal() -> c.Calibration:
    cells, size = (48, 30), (64, 48)
    return c.calibrate_sim(
        size,
        {"lcos_cells": cells, "leakage": 0.004, "dark_current_e_s": 20.0},
        c.example_homography(cells, size),
        seed=2,
    )


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_calibration_file_round_trip(small_cal, tmp_path, ext):
    path = tmp_path / f"cal.{ext}"
    c.write_calibration(path, small_cal)
    back = c.read_calibration(path)
    np.testing.assert_allclose(back.homography, small_cal.homography)
    assert back.summary == pytest.approx(small_cal.summary)
    for name in ("cell_x", "cell_y", "bias_dn", "dark_current_e_s", "leakage", "gain_ratio"):
        np.testing.assert_array_equal(getattr(back, name), getattr(small_cal, name))
    assert back.provenance["errors_vs_truth"]["homography_max_px"] <= 0.5


def test_apply_calibration(small_cal, tmp_path):
    params = RigParams(sensor_size=(64, 48), lcos_cells=(48, 30))
    applied = c.apply_calibration(params, small_cal)
    np.testing.assert_allclose(applied.homography, small_cal.homography)
    assert applied.leakage == pytest.approx(0.004, rel=0.1)
    assert applied.dark_current_e_s == pytest.approx(20.0, rel=0.1)
    assert applied.measure_fraction == pytest.approx(1.0, rel=0.05)
    with pytest.raises(InputError, match="LCoS"):
        c.apply_calibration(RigParams(sensor_size=(64, 48), lcos_cells=(40, 30)), small_cal)
    with pytest.raises(InputError, match="sensor"):
        c.apply_calibration(RigParams(sensor_size=(64, 40), lcos_cells=(48, 30)), small_cal)
    c.write_calibration(tmp_path / "cal.npz", small_cal)
    over = c.calibration_overrides(tmp_path / "cal.npz")
    assert RigParams(sensor_size=(64, 48), **over).homography == applied.homography


def test_read_calibration_refuses_other_kinds(tmp_path):
    from stages.formats.layered import Layered, write_layered

    data = Layered(meta={"kind": "hdr"})
    data.add("", np.zeros((4, 4, 1)), ["Y"])
    write_layered(tmp_path / "x.npz", data)
    with pytest.raises(FormatError, match="not a calibration"):
        c.read_calibration(tmp_path / "x.npz")


def test_parse_homography(tmp_path):
    h = c.parse_homography("2,0,1,0,3,0,0,0,1")
    np.testing.assert_allclose(h, [[2, 0, 1], [0, 3, 0], [0, 0, 1]])
    (tmp_path / "h.json").write_text(json.dumps({"homography": h.tolist()}))
    np.testing.assert_allclose(c.parse_homography(str(tmp_path / "h.json")), h)
    assert c.parse_homography("example", (100, 60), (120, 100)).shape == (3, 3)
    for bad in ("1,2,3", "a,b,c,d,e,f,g,h,i", "0,0,0,0,0,0,0,0,1"):
        with pytest.raises(InputError):
            c.parse_homography(bad)


# --- command line -------------------------------------------------------------------------


def test_cli_sim_writes_calibration_info_shows_it(tmp_path):
    out = tmp_path / "cal.npz"
    r = run_vet(
        "calibrate",
        "--rig",
        "sim",
        "--size",
        "64x48",
        "--lcos",
        "48x30",
        "--true-homography",
        "example",
        "--leakage",
        "0.003",
        "--dark-current",
        "15",
        "-o",
        out,
    )
    assert r.returncode == 0, r.stderr.decode()
    assert b"vs emulated truth" in r.stderr and r.stdout == b""
    info = run_vet("info", out)
    assert info.returncode == 0
    meta = json.loads(info.stdout)["metadata"]
    assert meta["kind"] == "calibration" and len(meta["homography"]) == 3
    assert meta["provenance"]["errors_vs_truth"]["homography_max_px"] <= 0.5


def test_cli_errors(tmp_path):
    r = run_vet("calibrate", "--rig", tmp_path / "nope.toml", "-o", tmp_path / "cal.exr")
    assert r.returncode == 1
    lines = r.stderr.decode().strip().splitlines()
    assert (
        len(lines) == 1 and lines[0].startswith("vet calibrate: error:") and "nope.toml" in lines[0]
    )
    assert not (tmp_path / "cal.exr").exists()

    r = run_vet("calibrate", "-o", tmp_path / "cal.exr")
    assert r.returncode == 2 and b"--frames" in r.stderr

    (tmp_path / "empty").mkdir()
    r = run_vet("calibrate", "--frames", tmp_path / "empty", "-o", tmp_path / "cal.exr")
    assert r.returncode == 1 and b"no calibration frames" in r.stderr

    r = run_vet("calibrate", "--rig", "sim", "--true-homography", "1,2", "-o", tmp_path / "cal.exr")
    assert r.returncode == 1 and b"homography" in r.stderr


# --- the hardware code path, against fake devices ------------------------------------------


class _FakeLCoS:
    """Records the masks sent; the fake camera renders through the last one."""

    def __init__(self, cells):
        self.cells = cells
        self.mask = np.zeros(cells[0] * cells[1], bool)
        self.sent = 0

    def send_full_mask(self, mask, *, wait=True):
        self.mask = np.asarray(mask, bool).ravel().copy()
        self.sent += 1
        return self.sent


def _fake_hardware_rig(cells=(40, 24), size=(64, 48), leak=0.004):
    from types import SimpleNamespace

    from stages.devices.cameras import Camera, Frame

    hom = c.example_homography(cells, size)
    lcos = _FakeLCoS(cells)
    cm = CellMap(hom, cells, (size[1], size[0]))

    class FakeCam(Camera):  # a V4L2-like camera: fixed exposure in 100 us units, 16-bit frames
        def __init__(self, exposure, behind_lcos, level):
            super().__init__()
            self.exposure, self.behind, self.level, self.n = exposure, behind_lcos, level, 0

        def _do_open(self):
            pass

        def _do_grab(self):
            img = np.full((size[1], size[0]), self.level)  # black-subtracted, no dark current
            if self.behind:
                per_cell = np.append(np.where(lcos.mask, leak, 1.0), 1.0)
                img = self.level * cm.to_pixels(per_cell)
            self.n += 1
            return Frame(img[:, :, None].astype(np.float32), self.n, 0.0)

    params = RigParams(sensor_size=size, lcos_cells=cells)
    rig = SimpleNamespace(
        params=params,
        lcos=lcos,
        name="fake",
        meta={},
        vet=FakeCam(100, True, 2000.0),
        measurement=FakeCam(50, False, 500.0),
    )
    return rig, hom


def test_calibrate_rig_hardware_path_with_fake_devices(caplog):
    rig, hom = _fake_hardware_rig()
    cal = c.calibrate_rig(rig, settings=c.AcquisitionSettings(frames_per_exposure=2))
    mx, _ = c.homography_error_px(cal.homography, hom, (40, 24), (64, 48))
    assert mx <= 0.5
    assert cal.summary["leakage_median"] == pytest.approx(0.004, rel=1e-3)
    # 500 DN in 5 ms (measurement) vs 2000 DN in 10 ms (VET): exposures from the driver units
    assert cal.summary["gain_ratio_median"] == pytest.approx(0.5, rel=1e-3)
    assert cal.dark_current_e_s is None  # a real camera cannot cap its own lens
    assert any("lens capped" in r.getMessage() for r in caplog.records)
    assert rig.lcos.sent == 2 + 2 * sum(c.gray_bit_counts((40, 24))) + 1
    assert not rig.lcos.mask.any()  # left all open


def test_calibrate_rig_with_software_triggered_genicam_style_cameras():
    """GenICam cameras state exposure_us (read back, maybe rounded, in describe()) and, with
    trigger = "software", deliver a frame only after start_exposure()."""
    from stages.devices.cameras import Camera
    from stages.errors import DeviceError

    rig, hom = _fake_hardware_rig()

    class SoftwareTriggered(Camera):
        def __init__(self, inner, exposure_us, read_back_us):
            super().__init__()
            self.inner, self.exposure_us, self.read_back_us = inner, exposure_us, read_back_us
            self.armed = False

        def _do_open(self):
            pass

        def describe(self):
            return {"backend": "genicam", "exposure_us": self.read_back_us}

        def start_exposure(self):
            self.armed = True

        def _do_grab(self):
            if not self.armed:
                raise DeviceError("no frame: the software trigger was not sent")
            self.armed = False
            return self.inner.grab()

    # the camera rounds 10 ms to 9.9 ms; the flat levels are per frame, so the exposures
    # read back (9.9 ms VET, 5 ms measurement) set the gain ratio: (500 / 5) / (2000 / 9.9)
    rig.vet = SoftwareTriggered(rig.vet, 10_000.0, 9_900.0)
    rig.measurement = SoftwareTriggered(rig.measurement, 5_000.0, 5_000.0)
    cal = c.calibrate_rig(rig, settings=c.AcquisitionSettings(frames_per_exposure=2))
    mx, _ = c.homography_error_px(cal.homography, hom, (40, 24), (64, 48))
    assert mx <= 0.5
    assert cal.summary["gain_ratio_median"] == pytest.approx(0.495, rel=1e-3)
    assert cal.provenance["exposures_s"]["open"] == [pytest.approx(9.9e-3)]
