"""What a new user meets (issue 21): the output rule, input kinds, standard output once,
usage errors with the valid form, capture folders, progress, provenance, completion."""

from __future__ import annotations

import hashlib
import io
import json

import numpy as np
import pytest
from click.testing import CliRunner

from stages.formats import read_layered, write_capture
from tests.conftest import run_vet
from vet_cli.main import cli


def invoke(*args, **kwargs):
    return CliRunner().invoke(cli, [str(a) for a in args], **kwargs)


def err_of(result) -> str:
    return result.stderr if hasattr(result, "stderr") else result.output


@pytest.fixture
def cap_file(tmp_path, small_capture):
    path = tmp_path / "cap.exr"
    write_capture(path, small_capture)
    return path


# --- 2. nothing is overwritten by surprise --------------------------------------------

#: The function each command's work starts with; an existing output must stop it earlier.
WORK = {
    "simulate": "stages.simulate.simulate",
    "evaluate": "stages.evaluate.run_evaluation",
    "calibrate": "stages.calibrate.run_calibration",
    "capture": "stages.devices.rigs.open_rig",
    "hdr-static": "stages.formats.read_capture",
    "deblur": "stages.formats.read_capture",
    "tonemap": "stages.formats.layered.read_layered",
}

EXISTING = {
    "simulate": (["simulate", "builtin:chart", "-o", "{d}/old.exr"], "old.exr"),
    "hdr-static": (["hdr-static", "{d}/in.exr", "-o", "{d}/old.exr"], "old.exr"),
    "deblur": (["deblur", "{d}/in.exr", "-o", "{d}/new.exr", "--motion-out", "{d}/old.exr"], ""),
    "tonemap": (["tonemap", "{d}/in.exr", "-o", "{d}/old.png"], "old.png"),
    "calibrate": (["calibrate", "--rig", "sim", "-o", "{d}/old.exr"], "old.exr"),
    "capture": (["capture", "--rig", "sim", "-o", "{d}/capdir"], "capdir: already holds"),
    "evaluate": (["evaluate", "builtin:chart", "-o", "{d}/report"], "report: already holds"),
}


@pytest.mark.parametrize("command", list(EXISTING))
def test_an_existing_output_is_refused_before_any_work(tmp_path, monkeypatch, command):
    import importlib

    argv, expect = EXISTING[command]
    for name in ("old.exr", "old.png"):
        (tmp_path / name).write_bytes(b"a result that cannot be remade")
    (tmp_path / "capdir").mkdir()
    (tmp_path / "capdir" / "capture.exr").write_bytes(b"a real capture")
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "results.csv").write_text("method\nall seven\n")
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}

    def started(*args, **kwargs):
        raise AssertionError("the command's work started")

    module, name = WORK[command].rsplit(".", 1)
    monkeypatch.setattr(importlib.import_module(module), name, started)
    res = invoke(*[a.format(d=tmp_path) for a in argv])
    err = err_of(res).strip()
    assert res.exit_code == 1, err
    assert len(err.splitlines()) == 1 and err.startswith(f"vet {command}: error: "), err
    assert "--force" in err and (expect or "already exists") in err, err
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_force_replaces_a_file_and_a_capture_folder(tmp_path):
    out = tmp_path / "c.exr"
    out.write_bytes(b"old")
    assert invoke("-q", "simulate", "builtin:chart", "--size", "32x32", "-o", out).exit_code == 1
    res = invoke("-q", "simulate", "builtin:chart", "--size", "32x32", "-o", out, "--force")
    assert res.exit_code == 0, err_of(res)
    assert read_layered(out).meta["kind"] == "capture"
    # A capture folder retaken with --force in the other format keeps no stale capture.
    folder = tmp_path / "cap"
    args = ["-q", "capture", "--rig", "sim", "--size", "32x32", "--measure-bins", "2"]
    assert invoke(*args, "-o", folder).exit_code == 0
    assert (folder / "capture.exr").is_file() and (folder / "measure_raw.npy").is_file()
    again = invoke(*args, "-o", folder, "--format", "npz", "--no-raw-stream", "-f")
    assert again.exit_code == 0, err_of(again)
    names = sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
    assert names == ["capture.json", "capture.log", "capture.npz"]


def test_make_recipes_and_demo_replace_what_make_rebuilds():
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    mk = (root / "make" / "vet.mk").read_text()
    recipes = [ln for ln in mk.splitlines() if ln.startswith("\t$(VET) ")]
    assert recipes and all("--force" in ln for ln in recipes), recipes
    demo = (root / "Makefile").read_text().split("\ndemo:")[1].split("\n\n")[0]
    assert "rm -rf $(DEMO_DIR)" in demo


# --- 3. inputs are what they claim ----------------------------------------------------


def _motion_file(path):
    from stages.flow import write_motion

    write_motion(str(path), np.zeros((32, 32, 2), np.float32))


@pytest.mark.parametrize("kind", ["capture", "motion"])
@pytest.mark.parametrize("command", ["simulate", "evaluate"])
def test_a_vet_file_of_another_kind_is_not_a_scene(tmp_path, cap_file, kind, command):
    scene = cap_file
    if kind == "motion":
        scene = tmp_path / "m.exr"
        _motion_file(scene)
    out = tmp_path / ("c.exr" if command == "simulate" else "report")
    res = invoke(command, scene, "-o", out)
    err = err_of(res).strip()
    assert res.exit_code == 1, err
    assert len(err.splitlines()) == 1, err
    assert f"is a vet {kind} file" in err and "linear radiance" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "ext,bits,what",
    [
        (".png", 8, "an 8-bit, sRGB-encoded"),
        (".jpg", 8, "an 8-bit, sRGB-encoded"),
        (".png", 16, "an sRGB-encoded"),
    ],
)
def test_a_display_referred_picture_as_scene_is_warned_about(tmp_path, ext, bits, what):
    from stages.formats.images import write_display_image

    pic = tmp_path / f"photo{ext}"
    rng = np.random.default_rng(0)
    write_display_image(pic, rng.uniform(0.1, 1, (32, 40, 3)).astype(np.float32), bits=bits)
    res = invoke("simulate", pic, "-o", tmp_path / "c.exr")
    assert res.exit_code == 0, err_of(res)
    assert f"{what} image is display-referred, not linear radiance" in err_of(res)


def test_a_linear_hdr_image_is_a_scene_without_warning(tmp_path, cap_file):
    hdr = tmp_path / "h.exr"
    assert invoke("-q", "hdr-static", cap_file, "-o", hdr).exit_code == 0
    res = invoke("simulate", hdr, "-o", tmp_path / "c.exr")
    assert res.exit_code == 0, err_of(res)
    assert "display-referred" not in err_of(res)


def test_each_command_refuses_files_of_the_wrong_kind(tmp_path, cap_file):
    hdr, motion = tmp_path / "h.exr", tmp_path / "m.exr"
    assert invoke("-q", "hdr-static", cap_file, "-o", hdr).exit_code == 0
    _motion_file(motion)
    cases = [
        (["hdr-static", hdr, "-o", tmp_path / "o.exr"], "not a capture (kind: hdr)"),
        (["deblur", motion, "-o", tmp_path / "o.exr"], "not a capture (kind: motion)"),
        (["tonemap", cap_file, "-o", tmp_path / "o.png"], "is a capture, not an HDR image"),
        (["tonemap", motion, "-o", tmp_path / "o.png"], "is a motion file, not an HDR image"),
        (
            ["capture", "--rig", "sim", "--calibration", cap_file, "-o", tmp_path / "k"],
            "not a calibration (kind: capture)",
        ),
        (
            ["simulate", "builtin:chart", "--motion", f"field:{hdr}", "-o", tmp_path / "o.exr"],
            "not a motion field (kind 'hdr'",
        ),
    ]
    for argv, expect in cases:
        res = invoke(*argv)
        err = err_of(res).strip()
        assert res.exit_code == 1 and expect in err and len(err.splitlines()) == 1, (argv, err)


# --- 4. standard output once, never a terminal ----------------------------------------


@pytest.mark.parametrize(
    "extra", [["--motion-out", "-"], ["--motion-picture", "-"]], ids=["motion", "picture"]
)
def test_standard_output_for_one_output_only(cap_file, extra):
    res = invoke("deblur", cap_file, "-o", "-", *extra)
    assert res.exit_code == 2, err_of(res)
    assert "only one output may go to standard output" in err_of(res)
    assert res.stdout_bytes == b""


def test_two_outputs_may_not_name_one_file(tmp_path, cap_file):
    res = invoke("deblur", cap_file, "-o", tmp_path / "x.exr", "--motion-out", tmp_path / "x.exr")
    assert res.exit_code == 2 and "-o and --motion-out both name" in err_of(res), err_of(res)
    assert not (tmp_path / "x.exr").exists()


def test_binary_output_to_a_terminal_is_refused(monkeypatch, cap_file):
    import vet_cli.outputs

    monkeypatch.setattr(vet_cli.outputs, "_stdout_is_terminal", lambda: True)
    for argv in (["hdr-static", cap_file], ["simulate", "builtin:chart"]):
        res = invoke(*argv, "-o", "-")
        assert res.exit_code == 2, err_of(res)
        assert "standard output is a terminal" in err_of(res)
        assert res.stdout_bytes == b""


def test_binary_output_to_a_real_terminal_is_refused():
    import os
    import subprocess

    from tests.conftest import ROOT, VET

    master, slave = os.openpty()
    try:
        res = subprocess.run(
            [*VET, "simulate", "builtin:chart", "--size", "32x32", "-o", "-"],
            stdout=slave,
            stderr=subprocess.PIPE,
            env=dict(os.environ, PYTHONPATH=str(ROOT)),
            timeout=60,
        )
    finally:
        os.close(slave)
        os.close(master)
    assert res.returncode == 2 and b"standard output is a terminal" in res.stderr, res.stderr


@pytest.mark.parametrize(
    "argv",
    [
        ["hdr-static", "-", "-o", "{d}/h.exr"],
        ["deblur", "-", "-o", "{d}/h.exr"],
        ["tonemap", "-", "-o", "{d}/t.png"],
        ["info", "-"],
        ["simulate", "builtin:chart", "--motion", "field:-", "-o", "{d}/s.exr"],
    ],
    ids=lambda a: a[0],
)
def test_reading_a_terminal_as_standard_input_is_refused(monkeypatch, tmp_path, argv):
    # Nothing piped in: a usage error at once rather than a silent wait for an image.
    import stages.formats.io

    monkeypatch.setattr(stages.formats.io, "stdin_is_terminal", lambda: True)
    res = invoke(*[a.format(d=tmp_path) for a in argv])
    err = err_of(res)
    assert res.exit_code == 2, err
    assert "Error: -: standard input is a terminal; redirect a file into it" in err, err
    assert list(tmp_path.iterdir()) == [] and res.stdout_bytes == b""


def test_reading_a_real_terminal_as_standard_input_is_refused(tmp_path):
    import os
    import subprocess

    from tests.conftest import ROOT, VET

    master, slave = os.openpty()
    try:
        res = subprocess.run(
            [*VET, "hdr-static", "-", "-o", tmp_path / "x.exr"],
            stdin=slave,
            capture_output=True,
            env=dict(os.environ, PYTHONPATH=str(ROOT)),
            timeout=60,  # without the check it waits for input until killed here
        )
    finally:
        os.close(slave)
        os.close(master)
    assert res.returncode == 2 and b"standard input is a terminal" in res.stderr, res.stderr
    assert not (tmp_path / "x.exr").exists()


# --- 5. every invalid option value is a usage error naming the valid form --------------

BAD_VALUES = {
    "motion kind": (["simulate", "builtin:chart", "--motion", "warp:9"], "translate:VX,VY"),
    "motion no velocity": (
        ["simulate", "builtin:chart", "--motion", "object:80,64,160,128"],
        "the velocity part is missing; use object:X,Y,W,H:VX,VY",
    ),
    "motion numbers": (
        ["evaluate", "builtin:chart", "--motion", "translate:1"],
        "use translate:VX,VY",
    ),
    "size": (["simulate", "builtin:chart", "--size", "10by10"], "expected WIDTHxHEIGHT"),
    "size range": (["calibrate", "--rig", "sim", "--size", "4x4"], "8 to 16384"),
    "lcos": (["simulate", "builtin:chart", "--lcos", "12"], "expected WIDTHxHEIGHT"),
    "threshold": (["simulate", "builtin:chart", "--threshold", "2"], "0<x<=1"),
    "leakage": (["capture", "--rig", "sim", "--leakage", "1"], "0<=x<1"),
    "adc bits": (["simulate", "builtin:chart", "--adc-bits", "99"], "4<=x<=24"),
    "nan": (["simulate", "builtin:chart", "--frame-s", "nan"], "not a finite number"),
    "gamma": (["tonemap", "x.exr", "--gamma", "0"], "x>0"),
    "method": (["simulate", "builtin:chart", "--method", "bogus"], "'vet', 'long'"),
    "seed": (["simulate", "builtin:chart", "--seed", "one"], "not a valid integer"),
    "negative seed": (["capture", "--rig", "sim", "--seed", "-5"], "x>=0"),
    "exposure": (["tonemap", "x.exr", "--exposure", "nan"], "not a finite number"),
    "rig together": (
        ["evaluate", "builtin:chart", "--subframe-s", "2"],
        "subframe length must be in (0, frame length]",
    ),
    "link": (["capture", "--rig", "sim", "--link-bps", "-3"], "x>0"),
    "map and mask": (["tonemap", "x.exr", "--exposure-time-map", "--mask"], "not both"),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_invalid_option_values_are_usage_errors(tmp_path, case):
    argv, expect = BAD_VALUES[case]
    out = (
        "o.png" if argv[0] == "tonemap" else "o" if argv[0] in ("capture", "evaluate") else "o.exr"
    )
    res = invoke(*argv, "-o", tmp_path / out)
    err = err_of(res)
    assert res.exit_code == 2, err
    assert expect in err and "Traceback" not in err and "internal error" not in err, err
    assert list(tmp_path.iterdir()) == []


#: A rectangle wholly outside the frame at the size used: nothing would move.
SMALL = ["builtin:chart", "--size", "64x48"]
OUTSIDE = {
    "simulate": ["simulate", *SMALL, "-o", "{d}/o.exr"],
    "evaluate": ["evaluate", *SMALL, "--methods", "long", "-o", "{d}/r"],
    "capture": ["capture", "--rig", "sim", "--size", "64x48", "-o", "{d}/c"],
}


@pytest.mark.parametrize("command", list(OUTSIDE))
@pytest.mark.parametrize(
    "motion",
    ["object:80,64,160,128:40,10", "oscillate:-60,10,50,20:4,0", "object:10,48,8,8:1,0"],
    ids=["object", "oscillate", "edge"],
)
def test_a_motion_rectangle_wholly_outside_the_scene_is_a_usage_error(
    tmp_path, monkeypatch, command, motion
):
    # The README's object at 640x512 given for a 64x48 scene: known only once the
    # scene's size is, still a usage error naming the rectangle and the frame, no work.
    import stages.simulate

    def started(*args, **kwargs):
        raise AssertionError("the simulation started")

    monkeypatch.setattr(stages.simulate, "simulate", started)
    argv = [a.format(d=tmp_path) for a in OUTSIDE[command]]
    res = invoke(*argv, "--motion", motion)
    err = err_of(res)
    assert res.exit_code == 2, err
    assert "Invalid value for '--motion'" in err and "lies wholly outside the 64x48 frame" in err
    rect = motion.split(":")[1]
    assert f"X,Y,W,H = {rect}" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", ["simulate", "evaluate"])
def test_a_motion_rectangle_partly_outside_the_scene_is_warned_about(tmp_path, command):
    argv = [a.format(d=tmp_path) for a in OUTSIDE[command]]
    res = invoke(*argv, "--motion", "object:40,30,40,30:10,0")
    err = err_of(res)
    assert res.exit_code == 0, err
    warned = [line for line in err.splitlines() if "outside" in line]
    assert warned == [
        "vet: motion object:40,30,40,30:10,0: its rectangle (X,Y,W,H = 40,30,40,30) lies "
        "partly outside the 64x48 frame; only the part inside moves (rectangles are in "
        "pixels at the size used)"
    ], err
    inside = invoke(*argv, "--motion", "object:24,18,40,30:10,0", "--force")
    assert inside.exit_code == 0 and "outside" not in err_of(inside), err_of(inside)


@pytest.mark.parametrize(
    "param,expect",
    [
        ("deblur.foo=1", "step 'deblur' has no parameter 'foo'"),
        ("deblur.method=fast", "deblur method must be one of vet, paper, not 'fast'"),
        ("deblur.fuse_still=maybe", "fuse_still must be one of true, false, auto"),
        ("tonemap.exposure=nan", "tonemap exposure must be a number of stops within +/-64"),
        ("deblur.tile=8", "deblur tile must be one of auto, none, null, an integer >= 64"),
    ],
)
@pytest.mark.parametrize("dry", [False, True], ids=["run", "dry-run"])
def test_batch_params_are_checked_before_any_capture_runs(tmp_path, cap_file, param, expect, dry):
    root, out = tmp_path / "root", tmp_path / "out"
    root.mkdir()
    cap_file.rename(root / "a.exr")
    argv = ["batch", root, "-o", out, "-j", "1", "--steps", "hdr-static,deblur,tonemap"]
    res = invoke(*argv, "--param", param, *(["-n"] if dry else []))
    err = err_of(res)
    assert res.exit_code == 2, err
    assert expect in err and "internal error" not in err, err
    assert not out.exists() or not any(out.iterdir())


def test_garbage_on_stdin_is_named_standard_input():
    res = run_vet("hdr-static", "-", "-o", "-", input=b"this is not an image at all")
    err = res.stderr.decode()
    assert res.returncode == 1, err
    assert err.startswith("vet hdr-static: error: standard input: not an OpenEXR"), err
    assert "vet-stdin" not in err and "/tmp" not in err and res.stdout == b""


# --- 6. a capture folder wherever a capture is taken ----------------------------------


def test_every_command_takes_a_capture_folder(tmp_path, small_capture):
    folder = tmp_path / "cap1"
    folder.mkdir()
    write_capture(folder / "capture.exr", small_capture)
    res = invoke("tonemap", folder, "--exposure-time-map", "-o", tmp_path / "T.png")
    assert res.exit_code == 0, err_of(res)
    assert (tmp_path / "T.png").stat().st_size > 0
    res = invoke("tonemap", folder, "-o", tmp_path / "x.png")
    assert res.exit_code == 1 and "is a capture, not an HDR image" in err_of(res)
    assert invoke("-q", "hdr-static", folder, "-o", tmp_path / "h.exr").exit_code == 0
    res = invoke("info", folder, "--no-layers")
    assert res.exit_code == 0 and json.loads(res.stdout)["metadata"]["kind"] == "capture"


# --- 7. progress ------------------------------------------------------------------------


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_on_a_pipe_is_sparse_and_ends_at_100():
    from vet_cli._common import Progress

    stream = io.StringIO()
    with Progress("deblur vet", delay_s=0.0, every_s=3600.0, stream=stream) as p:
        for i in range(1, 201):
            p(i, 200)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2, lines
    assert lines[0].startswith("vet: deblur vet: 1/200 (0%)")
    assert lines[1].startswith("vet: deblur vet: 200/200 (100%)")


def test_progress_on_a_terminal_is_one_updating_bar():
    from vet_cli._common import Progress

    stream = _Tty()
    with Progress("simulate vet", delay_s=0.0, stream=stream) as p:
        for i in range(1, 51):
            p(i, 50)
    text = stream.getvalue()
    assert "\r" in text and "vet: simulate vet" in text and "50/50" in text and "100%" in text
    assert text.count("\n") == 1, repr(text)


def test_progress_shows_a_long_first_step_without_further_reports():
    """A stage reports (0, N) and then works for long: the display must not stay blank."""
    import time

    from vet_cli._common import Progress

    pipe, tty = io.StringIO(), _Tty()
    with Progress("deblur vet", delay_s=0.05, every_s=0.05, stream=pipe, tick_s=0.01) as p:
        p(0, 9)
        time.sleep(0.4)
    lines = pipe.getvalue().splitlines()
    assert len(lines) >= 2 and all(ln.startswith("vet: deblur vet: 0/9 (0%)") for ln in lines)
    with Progress("deblur vet", delay_s=0.05, stream=tty, tick_s=0.01) as p:
        p(0, 9)
        time.sleep(0.3)
    assert "vet: deblur vet:   0%|" in tty.getvalue() and "0/9" in tty.getvalue()


def test_progress_is_silent_when_quiet_and_for_short_steps(monkeypatch):
    from vet_cli._common import Progress, State

    stream = io.StringIO()
    with Progress("x", delay_s=3600.0, stream=stream) as p:
        p(1, 2)
        p(2, 2)
    monkeypatch.setattr(State, "verbosity", -1)
    with Progress("x", delay_s=0.0, stream=stream) as p:
        p(2, 2)
    assert stream.getvalue() == ""


@pytest.fixture(scope="module")
def moving_capture():
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:chart", (128, 96))  # the smallest the pyramid coarsens
    rig = RigParams(sensor_size=(128, 96))
    return simulate(scene, parse_motion("translate:20,0"), rig, seed=1, measure_bins=4)["vet"]


@pytest.mark.parametrize(
    "method,motion,moving",
    [("vet", "zero", False), ("vet", "truth", True), ("paper", "zero", False)],
    ids=["vet-still", "vet-coarse-to-fine", "paper"],
)
def test_deblur_progress_reaches_its_total(small_capture, moving_capture, method, motion, moving):
    from stages.deblur import deblur
    from stages.deblur.paper import PaperOptions

    cap = moving_capture if moving else small_capture
    options = PaperOptions(sd_iters=5) if method == "paper" else None  # (fast; same loop)
    calls = []
    deblur(
        cap, method, motion_init=motion, options=options, progress=lambda d, t: calls.append((d, t))
    )
    assert calls and calls[-1][0] == calls[-1][1], calls
    assert all(d <= t for d, t in calls)
    # Reported from the start (the motion estimate is the first step), never backwards.
    assert calls[0] == (0, 1) and calls[1][0] == 1, calls
    done = [d for d, _t in calls]
    assert done == sorted(done), calls
    if method == "paper":  # more than the two outer passes: the bar moves within them
        assert calls[-1][1] > 3
    if moving:  # the coarse start's steps count: the bar moves before the fine solve
        assert len({d for d, _t in calls}) > 6, calls


def test_evaluate_counts_its_parts():
    from stages.evaluate import run_evaluation

    steps, notes = [], []
    run_evaluation(
        "builtin:chart",
        "translate:10,0",
        (32, 32),
        rows=("vet-static", "long"),
        progress=notes.append,
        on_step=lambda d, t: steps.append((d, t)),
    )
    assert steps[0] == (0, 300) and steps[-1] == (300, 300)
    assert {t for _d, t in steps} == {300}
    done = [d for d, _t in steps]
    assert done == sorted(done) and 100 in done and 200 in done
    assert len(set(done)) > 10  # the simulation moves the bar within its part
    assert notes[0].startswith("simulating") and notes[-1] == "reconstructing long"


# --- 8. provenance inputs ---------------------------------------------------------------


@pytest.mark.parametrize("command", ["hdr-static", "deblur"])
def test_provenance_records_the_input_file(tmp_path, cap_file, command):
    out = tmp_path / "o.exr"
    extra = ["--motion-init", "zero"] if command == "deblur" else []
    res = invoke("-q", command, cap_file, "-o", out, *extra)
    assert res.exit_code == 0, err_of(res)
    last = read_layered(out).meta["provenance"][-1]
    assert last["step"] == command
    data = cap_file.read_bytes()
    assert last["inputs"] == [
        {"path": str(cap_file), "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    ]


# --- 11. version and shell completion ---------------------------------------------------


def test_short_version_flag():
    for flag in ("-V", "--version"):
        res = invoke(flag)
        assert res.exit_code == 0 and res.output.startswith("vet, version "), res.output


def test_shell_completion_through_vet_complete():
    import os
    import subprocess

    from tests.conftest import ROOT, VET

    def complete(**env):
        env = dict(os.environ, PYTHONPATH=str(ROOT), **env)
        return subprocess.run(VET, capture_output=True, env=env, timeout=60)

    res = complete(COMP_WORDS="vet hdr", COMP_CWORD="1", _VET_COMPLETE="bash_complete")
    assert res.returncode == 0 and b"plain,hdr-static" in res.stdout, res
    res = complete(_VET_COMPLETE="bash_source")
    assert res.returncode == 0 and b"_vet_completion" in res.stdout, res
