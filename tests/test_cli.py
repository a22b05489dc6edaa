"""The command-line contract: exit codes, one-line errors, no partial outputs, pipes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from stages.formats import write_capture
from tests.conftest import run_vet
from vet_cli.main import cli


def invoke(*args: str):
    return CliRunner().invoke(cli, list(map(str, args)))


def stderr_of(result) -> str:
    return result.stderr if hasattr(result, "stderr") else result.output


# --- bad inputs: each must give exit 1, one line, no traceback, no output -------------


def _random_exr(p):
    p.write_bytes(np.random.default_rng(0).bytes(5000))


def _truncated_exr(p, cap):
    write_capture(p.with_suffix(".full.exr"), cap)
    data = p.with_suffix(".full.exr").read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _pickled_npz(p):
    np.savez(
        p,
        **{"layer:I": np.array([{"evil": 1}], dtype=object)},
        __meta__=np.array('{"kind": "capture"}'),
        __channels__=np.array('{"I": ["Y"]}'),
    )


def _shape_mismatch_npz(p, cap):
    data = cap.to_layered()
    arrays = {"layer:I": data.layers["I"], "layer:T": data.layers["T"][:-3, :-2]}
    np.savez(
        p,
        **arrays,
        __meta__=np.array(json.dumps(data.meta)),
        __channels__=np.array(json.dumps({"I": data.channels["I"], "T": ["Y"]})),
    )


def _nan_in_t(p, cap):
    from tests.hostile import write_unchecked

    data = cap.to_layered()
    data.layers["T"][3, 4, 0] = np.nan
    write_unchecked(p, data)  # (write_layered refuses to write it)


BAD_INPUTS = {
    "missing file": (lambda p, cap: None, "no such file"),
    "random bytes named .exr": (lambda p, cap: _random_exr(p), "not an OpenEXR"),
    "truncated EXR": (_truncated_exr, "EXR"),
    "npz holding a pickled object": (lambda p, cap: _pickled_npz(p), "pickle"),
    "I and T shapes differ": (_shape_mismatch_npz, "must match"),
    "NaN in T": (_nan_in_t, "NaN"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
@pytest.mark.parametrize("existing", [False, True])
def test_bad_input_exit_1_one_line_no_output(tmp_path, small_capture, case, existing):
    make, expect = BAD_INPUTS[case]
    suffix = ".npz" if case in ("npz holding a pickled object", "I and T shapes differ") else ".exr"
    bad = tmp_path / f"bad{suffix}"
    make(bad, small_capture)
    out = tmp_path / "out.exr"
    if existing:  # --force: the existing output may be replaced, but only by a result
        out.write_bytes(b"previous result")
    res = run_vet("hdr-static", bad, "-o", out, *(["--force"] if existing else []))
    err = res.stderr.decode()
    assert res.returncode == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("vet hdr-static: error: ")
    assert expect.lower() in lines[0].lower()
    assert "Traceback" not in err
    if existing:
        assert out.read_bytes() == b"previous result"
    else:
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".vet-tmp")) == []


def test_verbose_shows_traceback(tmp_path):
    _random_exr(tmp_path / "bad.exr")
    res = run_vet("-v", "hdr-static", tmp_path / "bad.exr", "-o", tmp_path / "o.exr")
    assert res.returncode == 1 and b"Traceback" in res.stderr


def test_usage_errors_exit_2():
    assert invoke("hdr-static").exit_code == 2  # missing argument
    assert invoke("simulate", "builtin:chart", "-o", "x.exr", "--method", "bogus").exit_code == 2
    both = invoke(
        "simulate",
        "builtin:chart",
        "-o",
        "x.exr",
        "--radiance-scale",
        "9",
        "--reach-subframes",
        "2",
    )
    assert both.exit_code == 2 and "not both" in both.output
    assert invoke("no-such-command").exit_code == 2
    paper = invoke("deblur", "c.exr", "-o", "o.exr", "--method", "paper", "--fuse-still")
    assert paper.exit_code == 2 and "--method vet only" in paper.output
    paper = invoke("deblur", "c.exr", "-o", "o.exr", "--method", "paper", "--keep-still")
    assert paper.exit_code == 2 and "--keep-still applies to --method vet only" in paper.output


def test_runtime_errors_in_arguments_exit_1(tmp_path):
    res = invoke("simulate", "builtin:nope", "-o", tmp_path / "c.exr")
    assert res.exit_code == 1 and "unknown builtin scene" in stderr_of(res)
    assert not (tmp_path / "c.exr").exists()


# --- bad output names: refused before any work, exit 1, one line ---------------------

#: The function each command's work starts with; a bad output must stop it earlier.
WORK = {
    "simulate": "stages.simulate.simulate",
    "evaluate": "stages.evaluate.run_evaluation",
    "calibrate": "stages.calibrate.run_calibration",
    "capture": "stages.devices.rigs.open_rig",
}

BAD_OUTPUTS = {
    "deblur, image extension": (["deblur", "{cap}", "-o", "{d}/o.png"], "unsupported output"),
    "deblur, missing folder": (["deblur", "{cap}", "-o", "{d}/no/o.exr"], "does not exist"),
    "deblur, name is a folder": (["deblur", "{cap}", "-o", "{d}/dir.exr"], "is a folder"),
    "deblur, motion in missing folder": (
        ["deblur", "{cap}", "-o", "{d}/o.exr", "--motion-out", "{d}/no/m.exr"],
        "does not exist",
    ),
    "deblur, motion picture as EXR": (
        ["deblur", "{cap}", "-o", "{d}/o.exr", "--motion-picture", "{d}/m.exr"],
        "unsupported image extension",
    ),
    "hdr-static, missing folder": (["hdr-static", "{cap}", "-o", "{d}/no/o.exr"], "does not exist"),
    "tonemap, data extension": (["tonemap", "{cap}", "-o", "{d}/o.exr"], "unsupported image"),
    "simulate, no extension": (
        ["simulate", "builtin:chart", "-o", "{d}/cap"],
        "unsupported output",
    ),
    "calibrate, missing folder": (
        ["calibrate", "--rig", "sim", "-o", "{d}/no/cal.exr"],
        "does not exist",
    ),
    "evaluate, a file in the way": (
        ["evaluate", "builtin:chart", "-o", "{d}/file/report"],
        "is a file, not a folder",
    ),
    "capture, a file in the way": (["capture", "--rig", "sim", "-o", "{d}/file"], "is a file"),
    "capture, missing parent": (["capture", "--rig", "sim", "-o", "{d}/no/cap"], "does not exist"),
}


@pytest.mark.parametrize("case", list(BAD_OUTPUTS))
def test_bad_output_is_refused_before_any_work(tmp_path, monkeypatch, case):
    import importlib

    argv, expect = BAD_OUTPUTS[case]
    (tmp_path / "dir.exr").mkdir()
    (tmp_path / "file").write_text("not a folder")

    def started(*args, **kwargs):
        raise AssertionError("the command's work started")

    command = argv[0]
    if command in WORK:
        module, name = WORK[command].rsplit(".", 1)
        monkeypatch.setattr(importlib.import_module(module), name, started)
    # The capture does not exist: reading it first would fail on the input instead.
    args = [a.format(d=tmp_path, cap=tmp_path / "missing.exr") for a in argv]
    res = invoke(*args)
    err = stderr_of(res).strip()
    assert res.exit_code == 1, err
    assert len(err.splitlines()) == 1 and err.startswith(f"vet {command}: error: "), err
    assert expect in err and "no such file" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.exr", "file"]


def test_simulate_help_names_the_builtin_scenes():
    res = invoke("simulate", "--help")
    assert res.exit_code == 0
    assert "interior" in res.output and "chart" in res.output


def test_top_level_help_lists_every_command():
    res = invoke("--help")
    for name in (
        "simulate",
        "hdr-static",
        "deblur",
        "tonemap",
        "calibrate",
        "capture",
        "evaluate",
        "batch",
        "info",
    ):
        assert name in res.output


def test_simulate_then_hdr_static_files_and_info(tmp_path):
    cap, hdr = tmp_path / "c.npz", tmp_path / "h.exr"
    assert (
        invoke("simulate", "builtin:chart", "--size", "64x48", "--seed", "2", "-o", cap).exit_code
        == 0
    )
    assert invoke("hdr-static", cap, "-o", hdr).exit_code == 0
    res = invoke("info", hdr)
    info = json.loads(res.output)
    assert info["metadata"]["kind"] == "hdr"
    assert [p["step"] for p in info["metadata"]["provenance"]] == ["simulate", "hdr-static"]
    assert info["size"] == {"width": 64, "height": 48}


def test_info_summarises_the_measuring_images_unless_full(tmp_path):
    # A capture keeps all 131 measuring subframes: by default one entry for them all (and
    # the per-image metadata lists summarised), --full each, in time order (M2 < M10).
    from stages.formats import read_capture

    cap = tmp_path / "c.exr"
    assert invoke("simulate", "builtin:chart", "--size", "32x24", "-o", cap).exit_code == 0
    res = invoke("info", cap)
    assert res.exit_code == 0, stderr_of(res)
    info = json.loads(res.stdout)
    assert len(res.stdout) < 6000, len(res.stdout)  # was 40 KB
    assert list(info["layers"]) == ["I", "M00..M130", "T", "truth", "truth_motion"]
    measure = read_capture(cap).measure
    m = info["layers"]["M00..M130"]
    assert m["count"] == 131 and m["times_s"] == pytest.approx([0.0, 131 * 0.00758])
    assert (m["min"], m["max"]) == (float(measure.min()), float(measure.max()))
    assert m["mean"] == pytest.approx(float(measure.mean(dtype=np.float64)))
    meta = info["metadata"]
    assert meta["measure_times"] == {"count": 131, "span_s": m["times_s"]}
    assert meta["measure_subframes"] == {"count": 131, "total": 131, "min": 1, "max": 1}
    assert list(meta["channel_order"]) == ["I", "M00..M130", "T", "truth", "truth_motion"]
    assert "vet info --full" in info["summarised"]

    full = invoke("info", cap, "--full")
    assert full.exit_code == 0, stderr_of(full)
    info = json.loads(full.stdout)
    names = [f"M{i:02d}" for i in range(131)]
    assert list(info["layers"]) == ["I", *names, "T", "truth", "truth_motion"]
    assert list(info["metadata"]["channel_order"]) == ["I", *names, "T", "truth", "truth_motion"]
    assert len(info["metadata"]["measure_times"]) == 131 and "summarised" not in info


def test_deblur_fuse_still_is_recorded_in_the_file(tmp_path):
    # A still capture: by default (and with --keep-still) deblur returns hdr-static's
    # still pixels; --fuse-still gives them the value of all their data.
    cap, plain, fused = tmp_path / "c.npz", tmp_path / "p.exr", tmp_path / "f.exr"
    kept = tmp_path / "k.exr"
    assert invoke("simulate", "builtin:interior", "--size", "64x48", "-o", cap).exit_code == 0
    assert invoke("deblur", cap, "-o", plain).exit_code == 0
    assert invoke("deblur", cap, "-o", fused, "--fuse-still").exit_code == 0
    assert invoke("deblur", cap, "-o", kept, "--keep-still").exit_code == 0
    meta = {p: json.loads(invoke("info", p).output)["metadata"] for p in (plain, fused, kept)}
    assert meta[fused]["still_pixels"] == "fused" and meta[fused]["provenance"][-1]["params"] == {
        "method": "vet",
        "motion_init": "layers",
        "fuse_still": True,
    }
    assert meta[plain]["still_pixels"] == meta[kept]["still_pixels"] == "hdr-static"
    assert meta[plain]["provenance"][-1]["params"]["fuse_still"] == "auto"
    assert meta[kept]["provenance"][-1]["params"]["fuse_still"] is False
    from stages.formats import read_hdr

    a, b, k = (read_hdr(p).radiance for p in (plain, fused, kept))
    assert a.shape == b.shape and not np.array_equal(a, b)  # the still pixels moved
    assert np.array_equal(a, k)


def test_pipe_through_stdin_and_stdout(tmp_path):
    sim = run_vet("simulate", "builtin:chart", "--size", "64x48", "-o", "-")
    assert sim.returncode == 0 and sim.stdout[:4] == b"\x76\x2f\x31\x01"
    assert b"\n" not in sim.stderr or b"vet:" in sim.stderr  # logs only on stderr
    hdr = run_vet("hdr-static", "-", "-o", "-", input=sim.stdout)
    assert hdr.returncode == 0, hdr.stderr
    info = run_vet("info", "-", input=hdr.stdout)
    assert json.loads(info.stdout)["metadata"]["kind"] == "hdr"


def test_empty_stdin_is_a_clear_error():
    res = run_vet("hdr-static", "-", "-o", "-", input=b"")
    assert res.returncode == 1 and b"standard input is empty" in res.stderr
    assert res.stdout == b""


def test_three_stage_pipe_to_png(tmp_path):
    """The README's first pipeline: simulate | hdr-static | tonemap."""
    sim = run_vet("simulate", "builtin:interior", "--size", "96x80", "-o", "-")
    hdr = run_vet("hdr-static", "-", "-o", "-", input=sim.stdout)
    png = run_vet("tonemap", "-", "-o", tmp_path / "out.png", input=hdr.stdout)
    assert png.returncode == 0, png.stderr
    import cv2

    img = cv2.imread(str(tmp_path / "out.png"))
    assert img.shape == (80, 96, 3) and img.std() > 5


def test_tonemap_refuses_a_capture_without_exposure_time_flag(tmp_path, small_capture):
    write_capture(tmp_path / "c.exr", small_capture)
    res = invoke("tonemap", tmp_path / "c.exr", "-o", tmp_path / "x.png")
    assert res.exit_code == 1 and "run hdr-static" in stderr_of(res)
    res = invoke("tonemap", tmp_path / "c.exr", "--exposure-time-map", "-o", tmp_path / "T.png")
    assert res.exit_code == 0 and (tmp_path / "T.png").stat().st_size > 1000


def test_sample_data_is_what_the_generator_makes(tmp_path):
    from pathlib import Path

    from stages.formats import read_capture
    from stages.sample_data import generate

    committed = Path(__file__).parent.parent / "sample_data" / "captures" / "interior_pan.exr"
    if not committed.exists():
        pytest.skip("sample_data not present")
    generate(tmp_path)
    a, b = read_capture(committed), read_capture(tmp_path / "captures" / "interior_pan.exr")
    np.testing.assert_array_equal(a.I, b.I)
    np.testing.assert_array_equal(a.T, b.T)
