"""vet calibrate: Gray-code decoding, homography fit, dark/leakage/gain, folders, CLI."""

from __future__ import annotations

import json
from pathlib import Path

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


# --- recorded frames ----------------------------------------------------------------------

GAIN = RigParams().gain_dn_per_e  # DN per electron of the default 12-bit sensor


def _write_folder(root: Path, with_gray: bool = True) -> dict:
    """Synthesise a recorded calibration (16-bit PNG and TIFF, raw pedestal 64 DN)."""
    import cv2

    cells, size = (40, 24), (64, 48)
    w, h = size
    truth = {
        "cells": cells,
        "size": size,
        "hom": c.example_homography(cells, size),
        "bias": 64.0,
        "dark": 20.0,
        "leak": 0.004,
        "rate": 2.0e5,
        "meas": 0.5,
    }
    root.mkdir(exist_ok=True)
    (root / "rig.toml").write_text(f"[params]\nlcos_cells = [{cells[0]}, {cells[1]}]\n")
    rng = np.random.default_rng(3)  # seeded: small fixed-pattern variation in the bias
    bias = truth["bias"] + rng.normal(0, 1.0, (h, w))
    cm = CellMap(truth["hom"], cells, (h, w))

    def save(name: str, img: np.ndarray) -> None:
        cv2.imwrite(str(root / name), np.clip(np.rint(img), 0, 65535).astype(np.uint16))

    def dark(t: float) -> np.ndarray:
        return bias + GAIN * truth["dark"] * t

    for t in (0.5, 10.0):
        for n in range(2):
            save(f"dark_{t:g}s_{n:02d}.tif", dark(t))
    t_o, t_c, t_m = 0.01, 2.0, 0.005
    save("open_0.01s_00.png", dark(t_o) + truth["rate"] * t_o)
    leak_px = cm.to_pixels(np.append(np.full(cm.n_cells, truth["leak"]), 1.0))
    save("closed_2s_00.png", dark(t_c) + truth["rate"] * t_c * leak_px)
    save("meas_flat_0.005s_00.png", dark(t_m) + truth["meas"] * truth["rate"] * t_m)
    if with_gray:
        for k, pat in enumerate(c.gray_code_patterns(cells)):
            per_cell = np.append(np.where(pat.ravel(), 1.0, truth["leak"]), 1.0)
            save(f"gray_{k:02d}.png", dark(t_o) + truth["rate"] * t_o * cm.to_pixels(per_cell))
    (root / "notes.txt").write_text("ignored\n")
    return truth


def test_calibrate_from_folder(tmp_path):
    truth = _write_folder(tmp_path / "rec")
    cal = c.calibrate_from_folder(tmp_path / "rec")
    assert cal.sensor_size == truth["size"] and cal.lcos_cells == truth["cells"]
    mx, _ = c.homography_error_px(cal.homography, truth["hom"], truth["cells"], truth["size"])
    assert mx <= 0.5
    assert cal.summary["bias_median_dn"] == pytest.approx(truth["bias"], abs=0.5)
    assert cal.summary["dark_current_median_e_s"] == pytest.approx(truth["dark"], rel=0.1)
    assert cal.summary["leakage_median"] == pytest.approx(truth["leak"], rel=0.1)
    assert cal.summary["gain_ratio_median"] == pytest.approx(truth["meas"], rel=0.05)
    assert cal.provenance["skipped"] == []


def test_calibrate_from_folder_skips_missing_parts(tmp_path, caplog):
    _write_folder(tmp_path / "rec", with_gray=False)
    (tmp_path / "rec" / "gray_00.png").write_bytes(
        (tmp_path / "rec" / "open_0.01s_00.png").read_bytes()
    )
    cal = c.calibrate_from_folder(tmp_path / "rec")
    assert cal.homography is None and cal.cell_x is None
    assert "leakage_median" in cal.summary
    assert any("gray_00" in r.getMessage() for r in caplog.records)  # incomplete Gray set named
    assert any("homography" in s for s in cal.provenance["skipped"])


def test_calibrate_from_folder_without_frames(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    (tmp_path / "empty" / "photo.png").write_bytes(b"not even a png")
    with pytest.raises(InputError, match="no calibration frames"):
        c.calibrate_from_folder(tmp_path / "empty")
    with pytest.raises(InputError, match="no such folder"):
        c.calibrate_from_folder(tmp_path / "missing")


def test_calibrate_from_folder_refuses_bad_frames(tmp_path):
    import cv2

    truth = _write_folder(tmp_path / "rec", with_gray=False)
    (tmp_path / "rec" / "dark_0.5s_01.tif").write_bytes(b"garbage")
    with pytest.raises(FormatError, match="not a readable image"):
        c.calibrate_from_folder(tmp_path / "rec")
    w, h = truth["size"]
    cv2.imwrite(str(tmp_path / "rec" / "dark_0.5s_01.tif"), np.zeros((h, w + 1), np.uint16))
    with pytest.raises(InputError, match="others are"):
        c.calibrate_from_folder(tmp_path / "rec")


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


def test_read_frame_raw_and_images(tmp_path):
    import cv2

    (tmp_path / "dark_1s_00.dng").write_bytes(b"garbage" * 10)
    with pytest.raises(FormatError, match="raw"):
        c.read_frame(tmp_path / "dark_1s_00.dng")
    rgb = np.zeros((4, 6, 3), np.uint16)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 30, 60, 90
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb)
    img = c.read_frame(tmp_path / "rgb.png")
    assert img.shape == (4, 6) and img.dtype == np.float32
    np.testing.assert_allclose(img, 60.0)  # 16-bit values kept, channels averaged


def test_cli_from_folder(tmp_path):
    truth = _write_folder(tmp_path / "rec")
    out = tmp_path / "cal.exr"
    r = run_vet("calibrate", "--frames", tmp_path / "rec", "-o", out)
    assert r.returncode == 0, r.stderr.decode()
    cal = c.read_calibration(out)
    mx, _ = c.homography_error_px(cal.homography, truth["hom"], truth["cells"], truth["size"])
    assert mx <= 0.5
    assert cal.provenance["source"].startswith("folder:")
    # the command line's --lcos overrides the folder's rig.toml: a wrong grid is refused
    # as an incomplete Gray set plus the other parts, not silently misdecoded
    r = run_vet("calibrate", "--frames", tmp_path / "rec", "--lcos", "80x24", "-o", out, "--force")
    assert r.returncode == 0 and b"missing" in r.stderr
    assert c.read_calibration(out).homography is None


def test_undecodable_gray_frames_are_skipped_not_fatal(tmp_path):
    """Gray frames that show no LCoS modulation (LCoS not in the path): warn, keep the rest."""
    _write_folder(tmp_path / "rec", with_gray=False)
    src = (tmp_path / "rec" / "open_0.01s_00.png").read_bytes()
    for k in range(2 * sum(c.gray_bit_counts((40, 24)))):
        (tmp_path / "rec" / f"gray_{k:02d}.png").write_bytes(src)
    cal = c.calibrate_from_folder(tmp_path / "rec")
    assert cal.homography is None and cal.cell_x is not None and (cal.cell_x < 0).all()
    assert any("decoded" in s for s in cal.provenance["skipped"])
    assert "leakage_median" in cal.summary
