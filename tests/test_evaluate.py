"""Tests of vet evaluate and the deblur command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from vet_cli.main import cli

HDR_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdr"


def test_evaluate_writes_all_files(tmp_path):
    out = tmp_path / "report"
    res = CliRunner().invoke(
        cli,
        [
            "evaluate",
            "builtin:chart",
            "--size",
            "64x48",
            "--motion",
            "translate:30,0",
            "-o",
            str(out),
            "-q",
        ],
    )
    assert res.exit_code == 0, res.output
    for name in (
        "results.csv",
        "results.md",
        "errors.png",
        "contact_sheet.png",
        "exposure_time.png",
        "motion.png",
    ):
        assert (out / name).is_file(), name
    text = (out / "results.md").read_text()
    for row in (
        "vet-deblur",
        "vet-deblur-paper",
        "vet-static",
        "burst-merge",
        "adaptive-attenuation",
        "long",
        "short",
        "vet-deblur-oracle",
    ):
        assert f"| {row} |" in text
    header = (out / "results.csv").read_text().splitlines()[0]
    assert "dark_rms" in header and "runtime_s" in header
    assert not list(out.glob(".vet-tmp-*"))


def test_evaluate_runs_a_subset_on_a_dimmer_scene_and_says_so(tmp_path):
    """--methods runs only those rows; --reach-subframes dims the scene (the short
    exposure gets noisier, the scale drops by that factor) and the report states the rig."""
    import csv

    rms, scale = {}, {}
    for n in (1, 8):
        out = tmp_path / f"r{n}"
        args = ["evaluate", "builtin:interior", "--size", "96x80", "--motion", "translate:30,0"]
        args += ["--methods", "short,vet-static", "--reach-subframes", str(n)]
        args += ["--leakage", "0.01", "-o", str(out), "-q"]
        res = CliRunner().invoke(cli, args)
        assert res.exit_code == 0, res.output
        with open(out / "results.csv") as fh:
            rows = {r["method"]: r for r in csv.DictReader(fh)}
        assert list(rows) == ["vet-static", "short"]  # table order, not argument order
        rms[n] = float(rows["short"]["all_rms"])
        text = (out / "results.md").read_text()
        assert (
            "vet's default rig (the values `vet simulate --help` lists) except leakage = 0.01"
            in text
        )
        assert "DESIGN.md" not in text  # not a file of this project
        assert f"threshold in {n} subframe" in text
        scale[n] = float(text.split("Radiance scale ")[1].split()[0])
        assert (out / "motion.png").is_file() and (out / "contact_sheet.png").is_file()
    assert scale[8] == pytest.approx(scale[1] / 8, rel=1e-5)
    assert rms[8] > 1.5 * rms[1]


def test_measurable_floor_is_where_signal_equals_noise():
    from stages.metrics import measurable_floor
    from stages.rig import RigParams

    rig = RigParams()
    scale = 670.0
    floor = measurable_floor(rig, scale)
    s = floor * scale * rig.frame_s  # electrons of a whole-frame exposure
    noise = np.sqrt(s + rig.read_noise_e**2 + rig.dark_current_e_s * rig.frame_s)
    assert s == pytest.approx(noise, rel=1e-12)
    assert s == pytest.approx(6.44, abs=0.01)  # DESIGN.md's read noise and dark current
    assert measurable_floor(rig, 2 * scale) == pytest.approx(floor / 2)


def test_evaluate_scores_every_pixel_the_rig_can_measure():
    """The interior's wall is 13+ stops below its lamp: a floor relative to the scene's
    brightest pixels left most of it out; the rig's measurable floor keeps it."""
    from stages.evaluate import results_markdown, run_evaluation
    from stages.metrics import measurable_floor
    from stages.rig import RigParams
    from stages.scenes import luminance

    ev = run_evaluation("builtin:interior", "translate:30,0", (96, 80), rows=("vet-static",))
    lt = luminance(ev.truth)[8:-8, 8:-8]
    rig = RigParams(sensor_size=(96, 80))
    assert ev.floor == pytest.approx(measurable_floor(rig, ev.radiance_scale))
    scored = ev.scores["vet-static"]["all"]["n"]
    assert scored == int((lt > ev.floor).sum())
    assert scored > 1.5 * int((lt > 1e-4 * np.percentile(luminance(ev.truth), 99.9)).sum())
    assert f"{ev.floor_e:.1f} e-" in results_markdown(ev)


def test_evaluate_with_a_given_radiance_scale_reports_it(tmp_path):
    out = tmp_path / "r"
    args = ["evaluate", "builtin:chart", "--size", "64x48", "--methods", "long"]
    res = CliRunner().invoke(cli, [*args, "--radiance-scale", "50", "-o", str(out), "-q"])
    assert res.exit_code == 0, res.output
    text = (out / "results.md").read_text()
    assert (
        "Rig: vet's default rig (the values `vet simulate --help` lists). Radiance scale 50 e-/s per scene unit (as given)."
        in text
    )


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--methods", "vet-static,bogus"], "unknown method bogus"),
        (["--methods", ","], "unknown method (none)"),
        (["--radiance-scale", "10", "--reach-subframes", "2"], "not both"),
        (["--reach-subframes", "0"], "--reach-subframes"),
    ],
)
def test_evaluate_usage_errors_exit_2(tmp_path, extra, message):
    out = tmp_path / "report"
    res = CliRunner().invoke(cli, ["evaluate", "builtin:chart", "-o", str(out), *extra])
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not out.exists()


def test_deblur_cli_bad_capture_exits_1(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all")
    res = CliRunner().invoke(cli, ["deblur", str(bad), "-o", str(tmp_path / "o.exr")])
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("vet deblur: error:")
    assert not (tmp_path / "o.exr").exists()


def test_deblur_cli_usage_error_exits_2(tmp_path):
    res = CliRunner().invoke(
        cli, ["deblur", "x.exr", "-o", str(tmp_path / "o.exr"), "--method", "magic"]
    )
    assert res.exit_code == 2


def test_deblur_cli_writes_image_and_motion(tmp_path):
    from stages.formats.hdr import read_hdr

    cap = tmp_path / "cap.exr"
    r = CliRunner().invoke(
        cli,
        [
            "simulate",
            "builtin:chart",
            "--size",
            "48x40",
            "--motion",
            "translate:20,0",
            "-o",
            str(cap),
            "-q",
        ],
    )
    assert r.exit_code == 0, r.output
    res = CliRunner().invoke(
        cli,
        [
            "deblur",
            str(cap),
            "-o",
            str(tmp_path / "d.exr"),
            "--motion-out",
            str(tmp_path / "m.exr"),
            "--motion-picture",
            str(tmp_path / "m.png"),
            "-q",
        ],
    )
    assert res.exit_code == 0, res.output
    img = read_hdr(tmp_path / "d.exr")
    assert img.meta["method"] == "vet-deblur" and np.all(np.isfinite(img.radiance))
    assert (tmp_path / "m.exr").is_file() and (tmp_path / "m.png").is_file()


def _scores(all_rms: float, dark_n: int) -> dict:
    nan = float("nan")
    dark = {"median": nan, "p99": nan, "rms": nan, "n": 0} if dark_n == 0 else None
    return {
        "all": {"median": 0.1, "p99": 1.0, "rms": all_rms, "n": 100},
        "dark": dark or {"median": 0.2, "p99": 2.0, "rms": 0.3, "n": dark_n},
        "bright": {"median": 0.1, "p99": 1.0, "rms": 0.4, "n": 100 - dark_n},
    }


def test_report_marks_empty_regions_and_infinite_errors():
    """A capture with no dark pixel gets '-' cells and no dark bars; an infinitely wrong
    method (a zero estimate) is 'inf' in the table and a marked full-height bar, never 0."""
    from stages.evaluate import Evaluation, chart_bars, errors_chart, results_markdown

    ev = Evaluation(scene="s.exr", motion="translate:30,0", size=(10, 10), seed=0)
    ev.scores = {"vet-deblur": _scores(0.5, 0), "short": _scores(float("inf"), 0)}
    ev.runtime_s = {"vet-deblur": 1.0, "short": 0.0}
    md = results_markdown(ev)
    assert "| vet-deblur | 0.100 | 1.000 | 0.500 | - | - | - | 0.100 | 1.000 | 0.400 |" in md
    assert "| short | 0.100 | 1.000 | inf | - |" in md
    assert "No pixel is dark in this capture" in md and "'inf'" in md
    heights, infinite, top = chart_bars(ev)
    assert top == pytest.approx(0.55)  # 10% above the largest finite bar
    assert heights["all"].tolist() == [0.5, pytest.approx(0.55)]
    assert infinite["all"].tolist() == [False, True]
    assert np.all(np.isnan(heights["dark"]))
    assert errors_chart(ev)[:8] == b"\x89PNG\r\n\x1a\n"
    # With dark pixels and finite errors the table carries neither note.
    ev.scores = {"vet-deblur": _scores(0.5, 40)}
    md = results_markdown(ev)
    assert "No pixel" not in md and "'inf'" not in md and "| 0.300 |" in md


def test_motion_picture_shows_no_estimate_when_deblur_did_not_run():
    """Without vet-deblur there is no estimated motion: one panel (the truth), not a blank
    'estimated' panel beside it."""
    from stages.evaluate import Evaluation, motion_picture

    ev = Evaluation(scene="s.exr", motion="translate:30,0", size=(40, 30), seed=0)
    ev.truth = np.ones((30, 40, 1), np.float32)
    ev.truth_motion = np.tile(np.float32([30.0, 0.0]), (30, 40, 1))
    alone = motion_picture(ev)
    ev.velocity = ev.truth_motion.copy()
    both = motion_picture(ev)
    assert alone.shape[0] == both.shape[0]
    assert both.shape[1] - alone.shape[1] >= 40  # the estimated panel's width and more


def test_stops_error_scores_only_the_mask():
    # Known answer: the estimate is twice the truth (1 stop) on the left half, exact on
    # the right; scoring the left half alone gives exactly 1 stop and its pixel count.
    from stages.metrics import stops_error

    truth = np.full((40, 60, 1), 3.0, np.float32)
    est = truth.copy()
    est[:, :30] *= 2.0
    left = np.zeros((40, 60), bool)
    left[:, :30] = True
    whole = stops_error(est, truth, border=0, floor=0.0)
    part = stops_error(est, truth, border=0, floor=0.0, mask=left)
    assert whole["all"]["n"] == 2400 and abs(whole["all"]["rms"] - np.sqrt(0.5)) < 1e-6
    assert part["all"]["n"] == 1200 and part["all"]["rms"] == 1.0 and part["scale"] == 2.0
    with pytest.raises(ValueError, match="mask"):
        stops_error(est, truth, mask=left[:10])
