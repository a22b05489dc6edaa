"""Calibration from recorded frames: folders of images and camera raws (stages.calibrate.recorded)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages import calibrate as c
from stages.errors import FormatError, InputError
from stages.physics import CellMap
from stages.rig import RigParams

from .conftest import run_vet

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
    # Every flat-field part measured; only the parts of a real rig (no target or
    # switching frames in this folder) are skipped.
    assert [s.split(" (")[0] for s in cal.provenance["skipped"]] == [
        "measurement -> VET mapping",
        "trigger offset and switching time",
        "per-cell leakage",
        "trigger jitter and drop rate",
    ]
    # The Gray-code edges of this folder are sharp: no relay blur. Its measurement flat
    # field is flat: no vignetting, and the gain ratio (one grid assumed, no chessboard)
    # goes into the gain with the configured light share of 1.
    assert cal.parts["relay_blur_px"] < 0.2
    assert cal.parts["measure_vignetting"] == pytest.approx(0, abs=1e-3)
    assert cal.parts["measure_gain"] == pytest.approx(truth["meas"], rel=0.05)
    assert cal.parts["measure_fraction"] == 1.0
    assert cal.provenance["parts_fit"]["measure_flat"]["mapping"] == "identity"


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


def test_a_measurement_flat_field_of_its_own_size_without_its_dark_frames(tmp_path):
    """The measurement camera may have its own size; without its own dark frames its flat
    field borrows the VET sensor's dark model (its medians, the grids differing): the
    folder calibrates, and only the per-pixel gain ratio is skipped, naming why."""
    import cv2

    _write_folder(tmp_path / "rec")
    (tmp_path / "rec" / "meas_flat_0.005s_00.png").unlink()
    flat = np.full((40, 56), 64.0 + 0.5 * 2.0e5 * 0.005)
    cv2.imwrite(str(tmp_path / "rec" / "meas_flat_0.005s_00.png"), flat.astype(np.uint16))
    out = tmp_path / "cal.npz"
    r = run_vet("calibrate", "--frames", tmp_path / "rec", "-o", out)
    assert r.returncode == 0, r.stderr.decode()
    assert b"Traceback" not in r.stderr
    cal = c.read_calibration(out)
    assert cal.gain_ratio is None and cal.homography is not None
    assert any(
        "gain ratio (measurement and VET frames differ" in s for s in cal.provenance["skipped"]
    )


def test_per_cell_leakage_takes_equal_halves_of_the_flat_fields(tmp_path, monkeypatch):
    """Three open and three closed frames at the longest exposure: the per-cell leakage
    gets the first and the second frame as its two halves (the third left out, so that
    the halves' difference measures the noise of equal halves), a layer of the sensor's
    size, and the frames it used in the provenance."""
    import cv2

    import stages.calibrate.cell_leakage as cl

    root = tmp_path / "rec"
    _write_folder(root)
    for kind in ("open_0.01s", "closed_2s"):
        first = cv2.imread(str(root / f"{kind}_00.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        for n, extra in ((1, 4.0), (2, 40.0)):
            cv2.imwrite(str(root / f"{kind}_{n:02d}.png"), (first + extra).astype(np.uint16))
    seen = {}
    real = cl.leakage_from_halves

    def spy(closed, opened):
        seen["closed"], seen["opened"] = closed, opened
        return real(closed, opened)

    monkeypatch.setattr(cl, "leakage_from_halves", spy)
    cal = c.calibrate_from_folder(root)
    dark = cal.bias_dn + cal.dark_current_e_s * GAIN * 2.0
    first = cv2.imread(str(root / "closed_2s_00.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(seen["closed"][0] * 2.0, first - dark, rtol=1e-5, atol=1e-2)
    np.testing.assert_allclose(seen["closed"][1] * 2.0, first + 4.0 - dark, rtol=1e-5, atol=1e-2)
    assert cal.cell_leakage.shape == (48, 64)
    assert cal.provenance["parts_fit"]["cell_leakage"]["frames"] == 3
