"""vet calibrate --frames on a folder the emulated realistic rig recorded
(stages.calibrate.emulated_folder), against the emulated truth (seeded, 320x240)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from stages import calibrate as c
from stages.calibrate.parts import fit_switching_scaled, switching_exposure
from stages.rig import RigParams

SIZE = (320, 240)


def run_cli(*args):
    from click.testing import CliRunner

    from vet_cli.main import cli

    return CliRunner().invoke(cli, list(map(str, args)))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The emulated realistic rig's frames at 320x240 (seed 0), and its truth."""
    root = tmp_path_factory.mktemp("cal") / "frames"
    truth = c.write_emulated_folder(root, SIZE, seed=0)
    return root, truth


@pytest.fixture(scope="module")
def calibrated(recorded, tmp_path_factory):
    """``vet calibrate --frames`` on the recorded folder: (result, calibration, truth)."""
    root, truth = recorded
    out = tmp_path_factory.mktemp("out") / "cal.npz"
    r = run_cli("calibrate", "--frames", root, "-o", out)
    return r, out, truth


def _subset(src: Path, dst: Path, prefixes: tuple[str, ...], toml: str | None = None) -> Path:
    dst.mkdir()
    for p in src.iterdir():
        if p.name.startswith(prefixes):
            shutil.copy(p, dst / p.name)
    if toml is not None:
        (dst / "rig.toml").write_text(toml)
    return dst


def test_switching_fit_with_an_unknown_light_level_is_exact_without_noise():
    w = 0.15 + np.arange(-2e-3, 5e-3, 2.5e-4)
    y = 123.4 * switching_exposure(w, 0.1521, 0.0025, 0.0035)
    t, s, rate = fit_switching_scaled(w, y, 0.0035, 0.1516)
    assert (t, s, rate) == pytest.approx((0.1521, 0.0025, 123.4), rel=1e-6)


def test_folder_layout_written_by_the_emulated_rig(recorded):
    root, truth = recorded
    names = {p.name for p in root.iterdir()}
    assert "rig.toml" in names and "chessboard = [24, 18]" in (root / "rig.toml").read_text()
    for prefix in ("dark_", "open_", "closed_", "gray_", "meas_flat_"):
        assert any(n.startswith(prefix) for n in names), prefix
    assert sum(n.startswith("target_vet_00_") for n in names) == 4
    assert sum(n.startswith("target_meas_01_") for n in names) == 4
    assert sum(n.startswith("switch_20_") for n in names) == 29 * 4
    assert [p.name for p in root.parent.iterdir()] == ["frames"]  # no temporary left
    img = c.read_frame(root / "target_vet_00_00.png")
    assert img.shape == (240, 320) and img.min() >= 0  # black level added back


def test_folder_calibration_finds_the_parts_of_the_emulated_rig(calibrated):
    """The measurement -> VET mapping within 0.1 px RMS over the frame (0.019), the
    trigger offset within 0.1 ms (+0.012 ms), the switching time within 10% (-0.4%), the
    per-pixel leakage within 10% everywhere (5.0% max, 1.0% RMS), the relay blur within
    10% (-4.4%, from the first Gray-code bits' edges), the per-cell leakage layer."""
    r, out, truth = calibrated
    assert r.exit_code == 0, r.output
    cal = c.read_calibration(out)
    err = c.compare_parts_to_truth(cal, truth)
    assert err["mapping_rms_px"] <= 0.1
    assert abs(err["trigger_offset_err_s"]) <= 1e-4
    assert abs(err["switch_rel_err"]) <= 0.1
    assert err["leakage_px_max_rel_err"] <= 0.1
    assert abs(err["relay_blur_rel_err"]) <= 0.1
    assert set(cal.parts) == {
        "relay_blur_px",
        "measure_homography",
        "measure_k1",
        "measure_k2",
        "trigger_offset_s",
        "switch_s",
        "measure_vignetting",
        "measure_gain",
        "measure_fraction",
        "trigger_jitter_s",
        "drop_rate",
    }
    assert cal.provenance["skipped"] == []
    fit = cal.provenance["parts_fit"]
    assert fit["mapping"]["poses"] == ["pose 00", "pose 01"] and fit["mapping"]["corners"] == 864
    assert fit["switching"]["closures"] == [20] and fit["switching"]["windows"] == 29
    # The per-cell leakage from the 4 open and closed frames' halves: its median within
    # 10% (5.2%); so few frames leave single cells far off (docs/calibration.md: 16384).
    assert fit["cell_leakage"]["frames"] == 4 and cal.cell_leakage.shape == (240, 320)
    assert err["cell_leakage_px_median_rel_err"] <= 0.1
    # apply_calibration puts them in the rig, and vet info shows them.
    rig = c.apply_calibration(RigParams(sensor_size=SIZE, lcos_cells=truth.lcos_cells), cal)
    assert rig.switch_s == cal.parts["switch_s"] and rig.measure_k1 == cal.parts["measure_k1"]
    info = run_cli("info", out)
    assert info.exit_code == 0, info.output
    meta = json.loads(info.stdout)["metadata"]
    assert meta["parts"]["trigger_offset_s"] == pytest.approx(cal.parts["trigger_offset_s"])


def test_chessboard_pattern_found_without_the_rig_toml_table(recorded, tmp_path):
    root, truth = recorded
    sub = _subset(root, tmp_path / "f", ("target_", "open_", "closed_"))
    cal = c.calibrate_from_folder(sub)
    assert cal.provenance["parts_fit"]["mapping"]["pattern"] == [24, 18]
    assert c.compare_parts_to_truth(cal, truth)["mapping_rms_px"] <= 0.1


def test_folder_of_the_old_frame_kinds_calibrates_with_the_parts_skipped(recorded, tmp_path):
    root, _ = recorded
    sub = _subset(root, tmp_path / "f", ("dark_", "open_", "closed_", "rig.toml"))
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "cal.npz")
    assert r.exit_code == 0, r.output
    assert "skipped measurement -> VET mapping" in r.output
    assert "skipped trigger offset and switching time" in r.output
    assert "skipped trigger jitter and drop rate (no meas_timestamps.csv)" in r.output
    assert "skipped measurement gain and vignetting" in r.output
    cal = c.read_calibration(tmp_path / "cal.npz")
    assert cal.parts == {} and cal.leakage is not None


def test_malformed_target_frames_are_left_out_with_a_warning(recorded, tmp_path):
    import cv2

    root, truth = recorded
    sub = _subset(root, tmp_path / "f", ("target_", "open_", "closed_", "rig.toml"))
    flat = np.full((240, 320), 1000, np.uint16)
    for p in sub.glob("target_vet_01_*.png"):
        cv2.imwrite(str(p), flat)
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "one.npz")
    assert r.exit_code == 0, r.output
    assert "pose 01: chessboard not found in the VET camera's frame" in r.output
    cal = c.read_calibration(tmp_path / "one.npz")
    assert cal.provenance["parts_fit"]["mapping"]["poses"] == ["pose 00"]
    assert c.compare_parts_to_truth(cal, truth)["mapping_rms_px"] <= 0.1
    # No pose found: the mapping is skipped, never a traceback.
    for p in sub.glob("target_vet_00_*.png"):
        cv2.imwrite(str(p), flat)
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "none.npz")
    assert r.exit_code == 0, r.output
    assert "skipped measurement -> VET mapping (no chessboard pose found" in r.output
    assert "Traceback" not in r.output


def test_bad_chessboard_table_is_a_one_line_error(recorded, tmp_path):
    root, _ = recorded
    sub = _subset(root, tmp_path / "f", ("target_", "open_"))
    (sub / "rig.toml").write_text("[calibration]\nchessboard = [24]\n")
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "cal.npz")
    assert r.exit_code == 1
    assert "chessboard: [24]; expected [columns, rows]" in r.output
    assert "Traceback" not in r.output


def test_save_frames_refuses_a_used_folder_without_force(tmp_path):
    """--save-frames writes the folder and calibrates from it; a non-empty folder is
    refused (exit 1) unless --force, which replaces the layout's files and keeps others."""
    d = tmp_path / "frames"
    args = ("calibrate", "--rig", "sim", "--size", "160x120", "--save-frames", d)
    r = run_cli(*args, "-o", tmp_path / "a.npz")
    assert r.exit_code == 0, r.output
    cal = c.read_calibration(tmp_path / "a.npz")
    err = cal.provenance["errors_vs_truth"]
    assert err["mapping_rms_px"] <= 0.1 and abs(err["trigger_offset_err_s"]) <= 1e-4
    assert cal.provenance["source"] == f"folder:{d}"
    (d / "notes.txt").write_text("keep me\n")
    n = len(list(d.iterdir()))
    r = run_cli(*args, "-o", tmp_path / "b.npz")
    assert r.exit_code == 1 and "folder is not empty; give --force" in r.output
    assert not (tmp_path / "b.npz").exists()
    r = run_cli(*args, "--force", "-o", tmp_path / "b.npz")
    assert r.exit_code == 0, r.output
    assert len(list(d.iterdir())) == n and (d / "notes.txt").read_text() == "keep me\n"
    r = run_cli("calibrate", "--frames", d, "--save-frames", d, "-o", tmp_path / "c.npz")
    assert r.exit_code == 2


def test_measurement_gain_vignetting_and_frame_clock_against_the_truth(calibrated, capsys):
    """The realistic rig's measurement camera (vignetting 0.12, gain 0.96 with a light
    share of 1, trigger jitter 50 us, drop rate 0.002) from its flat field and its
    20000 frames' ids and timestamps: vignetting, gain product and jitter within 10%
    (+0.2%, +0.01%, -0.8% at 320x240, seed 0); the drop rate within three binomial
    sigmas of 20000 frames (3.2e-4 each), and exactly the ids the emulated camera
    dropped inside the recorded range."""
    from stages.calibrate.frame_clock import EMULATED_FRAMES, emulated_timestamps
    from stages.calibrate.meas_flat import MEASURE_ERRORS

    r, out, truth = calibrated
    assert r.exit_code == 0, r.output
    cal = c.read_calibration(out)
    err = c.compare_parts_to_truth(cal, truth)
    with capsys.disabled():
        print("\nerrors vs truth:", {k: round(err[k], 6) for k in MEASURE_ERRORS})
    assert truth.measure_vignetting == 0.12 and truth.measure_gain == 0.96
    assert abs(err["measure_vignetting_rel_err"]) <= 0.1
    assert abs(err["measure_gain_product_rel_err"]) <= 0.1
    assert abs(err["trigger_jitter_rel_err"]) <= 0.1
    p, n = truth.drop_rate, EMULATED_FRAMES
    assert abs(err["drop_rate_err"]) <= 3 * np.sqrt(p * (1 - p) / n)
    ids, _ = emulated_timestamps(truth, seed=0)
    fit = cal.provenance["parts_fit"]
    assert fit["frame_clock"]["missing"] == (ids[-1] - ids[0] + 1) - ids.size
    assert fit["frame_clock"]["period_rel_err"] == pytest.approx(0, abs=1e-5)
    assert fit["measure_flat"]["mapping"] == "chessboard"
    # The flat field gives the product; the configured light share stays.
    assert cal.parts["measure_fraction"] == 1.0
    rig = c.apply_calibration(RigParams(sensor_size=SIZE, lcos_cells=truth.lcos_cells), cal)
    assert rig.measure_gain == cal.parts["measure_gain"] and rig.measure_fraction == 1.0
    assert rig.trigger_jitter_s == cal.parts["trigger_jitter_s"]
    assert rig.drop_rate == cal.parts["drop_rate"]
    assert rig.measure_vignetting == cal.parts["measure_vignetting"]
    assert cal.provenance["frames_averaged"]["meas_timestamps"] == ids.size
    info = run_cli("info", out)
    meta = json.loads(info.stdout)["metadata"]
    assert meta["parts"]["drop_rate"] == pytest.approx(cal.parts["drop_rate"])
    assert meta["parts"]["measure_vignetting"] == pytest.approx(cal.parts["measure_vignetting"])


@pytest.mark.parametrize(
    "text, message",
    [
        ("frame_id,timestamp_s\n0,0.0\n1,abc\n", "meas_timestamps.csv:3: '1,abc' is not"),
        ("id,t\n0,0.0\n", "meas_timestamps.csv:1: header 'id,t'"),
        ("frame_id,timestamp_s\n0,0.0\n0,0.1\n", "frame id 0 appears more than once"),
        ("frame_id,timestamp_s\n0,1e999\n", "timestamp '1e999' is not finite"),
        ("frame_id,timestamp_s\n-1,0.5\n", "meas_timestamps.csv:2: '-1,0.5' is not"),
        ("", "empty; expected a header"),
    ],
)
def test_malformed_timestamps_file_is_a_one_line_error(recorded, tmp_path, text, message):
    root, _ = recorded
    sub = _subset(root, tmp_path / "f", ("open_", "closed_", "rig.toml"))
    (sub / "meas_timestamps.csv").write_text(text)
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "cal.npz")
    assert r.exit_code == 1, r.output
    errors = [ln for ln in r.output.splitlines() if "error" in ln]
    assert len(errors) == 1 and message in errors[0], r.output
    assert "Traceback" not in r.output and not (tmp_path / "cal.npz").exists()


def test_timestamps_alone_give_the_frame_clock(recorded, tmp_path):
    """A folder with the timestamps but no measurement flat field: jitter and drop rate
    found, the gain and vignetting skipped with a log line."""
    root, truth = recorded
    sub = _subset(root, tmp_path / "f", ("open_", "closed_", "rig.toml", "meas_timestamps"))
    r = run_cli("calibrate", "--frames", sub, "-o", tmp_path / "cal.npz")
    assert r.exit_code == 0, r.output
    assert "skipped measurement gain and vignetting" in r.output
    cal = c.read_calibration(tmp_path / "cal.npz")
    assert set(cal.parts) == {"trigger_jitter_s", "drop_rate"}
    assert cal.parts["trigger_jitter_s"] == pytest.approx(truth.trigger_jitter_s, rel=0.1)
