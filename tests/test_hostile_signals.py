"""Signals, standard input and a closed standard output (issue 52): real signals sent to
a ``vet`` process at several moments; what it leaves behind is checked on disk.

Every signal ends the command with one line, ``vet <command>: interrupted``, and status
128 + its number, from the moment vet's own code runs (before that, a few tens of
milliseconds of the interpreter's start, Python's default applies), and every temporary
file it made is gone.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from .conftest import ROOT, VET

ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def _caught(pid: int) -> int:
    """The signals process ``pid`` has handlers for (a bit mask; all when it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return -1  # (gone already, or no /proc: send the signal now)
    return int(status.split("SigCgt:")[1].split()[0], 16)


def _wait_for_vet(pid: int, most_s: float = 0.5) -> None:
    """Until vet's own handlers are in (SIGHUP caught: Python leaves it alone), or
    ``most_s`` after Python's (SIGINT caught): whichever comes first. A vet without
    handlers of its own is then in the middle of its imports."""
    t0 = time.monotonic()
    python_up = None
    while time.monotonic() - t0 < 60:
        caught = _caught(pid)
        if caught & (1 << (signal.SIGHUP - 1)):
            return
        if caught & (1 << (signal.SIGINT - 1)):
            python_up = python_up or time.monotonic()
            if time.monotonic() - python_up >= most_s:
                return
        time.sleep(0.002)


def _signal_at(argv, signum: int, delay: float, **popen):
    """Run ``argv``, send ``signum`` ``delay`` s after vet's code runs; (rc, stderr)."""
    p = subprocess.Popen(argv, stderr=subprocess.PIPE, env=ENV, **popen)
    _wait_for_vet(p.pid)
    time.sleep(delay)
    p.send_signal(signum)
    _, err = p.communicate(timeout=120)
    return p.returncode, err.decode()


@pytest.mark.parametrize(
    "signum, delay",
    [
        (signal.SIGINT, 0.0),  # (click and the stages still importing)
        (signal.SIGINT, 0.05),
        (signal.SIGINT, 0.15),
        (signal.SIGINT, 0.6),
        (signal.SIGTERM, 0.1),
        (signal.SIGTERM, 0.8),
        (signal.SIGHUP, 0.4),
    ],
)
def test_a_signal_ends_a_command_with_one_line(tmp_path, signum, delay):
    out = tmp_path / "cap.exr"
    argv = [*VET, "simulate", "builtin:interior", "--size", "320x256", "-o", out]
    rc, err = _signal_at(argv, signum, delay, stdout=subprocess.DEVNULL)
    if rc == 0:  # (finished first: then the output is whole)
        assert out.stat().st_size > 0
        return
    assert rc == 128 + signum, err
    assert err == "vet simulate: interrupted\n", err
    assert sorted(os.listdir(tmp_path)) == []  # no output, no temporary file


# A vet whose EXR writer stalls once its temporary file holds the image: a signal then
# finds an atomic output half done.
_STALLED_WRITER = """
import sys, time
from vet_cli import signals
signals.install(["vet", "hdr-static"])
from stages.formats import layered
write = layered.write_exr
def stalled(*args, **kwargs):
    write(*args, **kwargs)
    time.sleep(60)
layered.write_exr = stalled
from vet_cli.main import cli
cli(sys.argv[1:], prog_name="vet")
"""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_during_an_atomic_write_removes_the_temporary_file(tmp_path, signum):
    from stages.formats import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = RigParams(sensor_size=(48, 40))
    cap = simulate(load_scene("builtin:chart", (48, 40)), parse_motion("none"), rig, measure_bins=2)
    write_capture(tmp_path / "cap.exr", cap["vet"])
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "h.exr").write_bytes(b"precious")
    argv = [sys.executable, "-c", _STALLED_WRITER, "hdr-static", tmp_path / "cap.exr"]
    p = subprocess.Popen(
        [*argv, "-o", tmp_path / "out" / "h.exr", "--force"], stderr=subprocess.PIPE, env=ENV
    )
    t0 = time.monotonic()
    while not any(n.startswith(".vet-tmp-") for n in os.listdir(tmp_path / "out")):
        assert time.monotonic() - t0 < 120 and p.poll() is None, p.stderr.read()
        time.sleep(0.01)
    time.sleep(0.2)  # (in the stall)
    p.send_signal(signum)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 128 + signum and err.decode() == "vet hdr-static: interrupted\n", err
    assert os.listdir(tmp_path / "out") == ["h.exr"]
    assert (tmp_path / "out" / "h.exr").read_bytes() == b"precious"


# ------------------------------------------------------------------ standard input


def test_stdin_that_is_no_vet_file_is_refused_before_it_is_read(tmp_path):
    # `yes` never ends: a reader that spooled before looking would never answer.
    done = subprocess.run(
        f"yes | {' '.join(map(str, VET))} hdr-static - -o {tmp_path / 'h.exr'}",
        shell=True,
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert done.returncode == 1
    assert done.stderr == (
        "vet hdr-static: error: standard input: not an OpenEXR or NumPy .npz file "
        "(unrecognised magic bytes)\n"
    )


def test_stdin_past_the_size_limit_is_refused(tmp_path):
    done = subprocess.run(
        f"(printf 'v/1\\001'; yes) | {' '.join(map(str, VET))} hdr-static - -o {tmp_path / 'h.exr'}",
        shell=True,
        capture_output=True,
        text=True,
        env=dict(ENV, VET_MAX_DENSE_INPUT_BYTES="3000000", TMPDIR=str(tmp_path)),
        timeout=120,
    )
    assert done.returncode == 1
    assert done.stderr == (
        "vet hdr-static: error: standard input is over the limit of 3000000 bytes "
        "(set VET_MAX_DENSE_INPUT_BYTES to raise it)\n"
    )
    assert os.listdir(tmp_path) == []


def _feed_slowly(pipe) -> None:
    """An EXR's magic, then a trickle that never ends (until the pipe breaks)."""
    try:
        pipe.write(b"v/1\x01" + b"\0" * 65536)
        while True:
            pipe.write(b"\0" * 4096)
            pipe.flush()
            time.sleep(0.01)
    except (BrokenPipeError, OSError, ValueError):
        pass


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL])
def test_a_signal_while_spooling_stdin_leaves_no_file(tmp_path, signum):
    spool = tmp_path / "tmp"
    spool.mkdir()
    argv = [*VET, "hdr-static", "-", "-o", tmp_path / "h.exr"]
    p = subprocess.Popen(
        argv, stdin=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(ENV, TMPDIR=str(spool))
    )
    threading.Thread(target=_feed_slowly, args=(p.stdin,), daemon=True).start()
    _wait_for_vet(p.pid)
    time.sleep(2.0)  # (spooling by now)
    p.send_signal(signum)
    _, err = p.communicate(timeout=60)
    assert p.returncode == (-signal.SIGKILL if signum == signal.SIGKILL else 143)
    if signum == signal.SIGTERM:
        assert err.decode() == "vet hdr-static: interrupted\n"
    assert os.listdir(spool) == [] and not (tmp_path / "h.exr").exists()


# ------------------------------------------------------------------ standard output


def test_a_reader_that_leaves_early_is_an_error_not_a_success():
    p = subprocess.Popen(
        [*VET, "simulate", "builtin:chart", "--size", "64x48", "-o", "-"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    head = p.stdout.read(10)  # as `| head -c 10`: ten bytes, then the pipe is closed
    p.stdout.close()
    err = p.stderr.read().decode()
    p.wait(timeout=120)
    assert head == b"v/1\x01" + head[4:] and len(head) == 10
    assert p.returncode == 1
    assert err.strip().splitlines()[-1] == (
        "vet simulate: error: standard output was closed before the output was written "
        "(broken pipe)"
    )
