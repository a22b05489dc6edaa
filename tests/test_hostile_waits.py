"""Bounded waits (issue 52, issue 54 point 1): a scheduler address checked before any
work, a connection that fails within seconds, a batch's per-capture time limit."""

from __future__ import annotations

import dataclasses
import http.server
import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from stages.batch import STEPS, BatchOptions, run_batch
from stages.batch import child as child_mod
from stages.batch.steps import run_hdr_static
from stages.formats import write_capture
from vet_cli.main import cli

from .conftest import ROOT, VET


def vet(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


@pytest.fixture(scope="module")
def capture_file(tmp_path_factory) -> Path:
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = RigParams(sensor_size=(48, 40))
    cap = simulate(load_scene("builtin:chart", (48, 40)), parse_motion("none"), rig, measure_bins=2)
    path = tmp_path_factory.mktemp("cap") / "cap.exr"
    write_capture(path, cap["vet"])
    return path


@pytest.fixture
def root(tmp_path, capture_file) -> Path:
    """ok1.exr, wedged.exr, ok2.exr."""
    folder = tmp_path / "root"
    folder.mkdir()
    for name in ("ok1.exr", "wedged.exr", "ok2.exr"):
        (folder / name).write_bytes(capture_file.read_bytes())
    return folder


# ----------------------------------------------------------------- scheduler address


@pytest.mark.parametrize(
    "address, words",
    [
        ("bogus", "no port given"),
        ("inproc://x", "scheme inproc:// is not supported"),
        ("tcp://127.0.0.1", "no port given"),
        ("tcp://127.0.0.1:0", "not in 1..65535"),
        ("tcp://127.0.0.1:99999", "not in 1..65535"),
        ("tcp://:8786", "no host given"),
    ],
)
@pytest.mark.parametrize("command", ["batch", "deblur"])
def test_a_malformed_scheduler_address_is_a_usage_error(root, tmp_path, command, address, words):
    target = (
        ["batch", root, "-o", tmp_path / "out"]
        if command == "batch"
        else ["deblur", root / "ok1.exr", "-o", tmp_path / "out.exr"]
    )
    r = vet(*target, "--scheduler", address)
    assert r.exit_code == 2, r.output
    assert "'--scheduler'" in r.stderr and words in r.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.exr").exists()


def _silent_listener():
    """A TCP port that accepts connections and never says a word."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held = []

    def accept():
        while True:
            try:
                held.append(server.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    return server, server.getsockname()[1]


def _http_server():
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, httpd.server_address[1]


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_port_where_no_scheduler_answers_fails_in_seconds(root, tmp_path, kind):
    server, port = _silent_listener() if kind == "silent" else _http_server()
    try:
        # (a subprocess: that Client.__del__ does not wait at exit is part of the test;
        # the timeout bounds the whole command, which waited 90-120 s before)
        done = subprocess.run(
            [*VET, "batch", root, "-o", tmp_path / "out", "--scheduler", f"127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=60,
            env=dict(os.environ, PYTHONPATH=str(ROOT)),
        )
    finally:
        server.shutdown() if kind == "http" else server.close()
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[-1] == (
        f"vet batch: error: cannot reach the Dask scheduler at tcp://127.0.0.1:{port} "
        "(no Dask scheduler answered within 5 s)"
    ), lines
    assert "Traceback" not in done.stderr and len(lines) == 2  # (the plan's line, then this)


def test_deblur_says_when_the_scheduler_goes_unused(capture_file, tmp_path):
    # 48x40 is solved in one piece: nothing to send to a cluster, and vet says so
    # instead of exiting 0 as though the cluster had done the work.
    r = vet("deblur", capture_file, "-o", tmp_path / "o.exr", "--scheduler", "tcp://127.0.0.1:9")
    assert r.exit_code == 0, r.stderr
    assert (
        "vet: deblur: --scheduler tcp://127.0.0.1:9 not used: the 48x40 frame is solved in one "
        "piece (too small for tiles)"
    ) in r.stderr


# ---------------------------------------------------------------- per-capture limit


def _wedged_in_python(input_path, output_path, params):
    if Path(input_path).name == "wedged.exr":
        while True:
            time.sleep(0.01)
    run_hdr_static(input_path, output_path, params)


def _wedged_deaf(input_path, output_path, params):
    if (
        Path(input_path).name == "wedged.exr"
    ):  # as a native call that never returns: SIGTERM is not heard
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
        time.sleep(3600)
    run_hdr_static(input_path, output_path, params)


@pytest.mark.parametrize("wedge", [_wedged_in_python, _wedged_deaf])
def test_a_wedged_capture_fails_alone_at_its_time_limit(root, tmp_path, monkeypatch, wedge):
    monkeypatch.setitem(STEPS, "hdr-static", dataclasses.replace(STEPS["hdr-static"], run=wedge))
    monkeypatch.setattr(child_mod, "GRACE_S", 0.5)
    out = tmp_path / "out"
    report = run_batch(root, out, BatchOptions(steps="hdr-static", timeout=3))
    assert report.exit_status == 3
    assert report.failures == [
        {
            "capture": "wedged.exr",
            "step": "hdr-static",
            "reason": "timed out after 3 s (the batch's --timeout)",
            "cached": False,
        }
    ]
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".vet-batch")) == [
        "batch-summary.json",
        "ok1.hdr.exr",
        "ok2.hdr.exr",
    ]


def test_a_wedged_capture_fails_alone_on_dask_workers(root, tmp_path, monkeypatch):
    # (the job carries its steps: the workers run the test's wedge, by reference)
    wedged = dataclasses.replace(STEPS["hdr-static"], run=_wedged_in_python)
    monkeypatch.setitem(STEPS, "hdr-static", wedged)
    out = tmp_path / "out"
    report = run_batch(root, out, BatchOptions(steps="hdr-static", timeout=3, jobs=2))
    assert "LocalCluster" in report.summary["executor"]
    assert [f["capture"] for f in report.failures] == ["wedged.exr"]
    assert "timed out after 3 s" in report.failures[0]["reason"]
    assert report.summary["counts"]["done"] == 2
    assert not list(out.rglob(".vet-tmp-*"))


@pytest.mark.parametrize("value", ["0", "-1", "nan", "soon"])
def test_a_bad_timeout_is_a_usage_error(root, tmp_path, value):
    r = vet("batch", root, "-o", tmp_path / "out", "--timeout", value)
    assert r.exit_code == 2 and "'--timeout'" in r.stderr, r.output


def test_the_default_time_limit_grows_with_the_capture(tmp_path):
    from stages.batch.plan import AUTO_TIMEOUT_BASE_S, AUTO_TIMEOUT_S_PER_MB, capture_timeout

    small, large = tmp_path / "s.exr", tmp_path / "l.exr"
    small.write_bytes(b"x" * 1000)
    large.write_bytes(b"x" * 4_000_000)
    assert capture_timeout("auto", small) == AUTO_TIMEOUT_BASE_S + AUTO_TIMEOUT_S_PER_MB * 0.001
    assert capture_timeout("auto", large) == AUTO_TIMEOUT_BASE_S + 4 * AUTO_TIMEOUT_S_PER_MB
    assert capture_timeout(None, large) is None and capture_timeout(7.5, large) == 7.5


# ------------------------------------------------------------------ Ctrl-C on a batch


def _group(pgid: int) -> list[str]:
    return subprocess.run(["pgrep", "-g", str(pgid)], capture_output=True, text=True).stdout.split()


@pytest.mark.slow
def test_ctrl_c_on_a_batch_with_workers_is_one_line_and_the_rerun_resumes(root, tmp_path):
    out = tmp_path / "out"
    argv = [*VET, "batch", root, "-o", out, "-j", "2", "--steps", "hdr-static,deblur,tonemap"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    t0 = time.monotonic()
    while len(_group(p.pid)) < 4 and time.monotonic() - t0 < 120:  # vet, tracker, 2 workers
        time.sleep(0.2)
    time.sleep(2.0)  # (the workers at their captures)
    os.killpg(p.pid, signal.SIGINT)  # what a terminal does on Ctrl-C: the whole group
    _, err = p.communicate(timeout=120)
    if p.returncode == 0:
        pytest.skip("the batch finished before the signal")
    assert p.returncode == 130, err
    lines = err.strip().splitlines()
    assert lines[-1] == "vet batch: interrupted" and len(lines) <= 2, err
    time.sleep(2.0)  # (the captures' processes end themselves once their worker is gone)
    assert not list(out.rglob(".vet-tmp-*"))
    rerun = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    for name in ("ok1", "wedged", "ok2"):
        for suffix in (".hdr.exr", ".deblur.exr", ".png"):
            assert (out / (name + suffix)).is_file()
    assert not list(out.rglob(".vet-tmp-*"))
