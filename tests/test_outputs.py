"""Outputs under adversity (issue 22 item 5): a full disk, a read-only folder, an output
that is a symbolic link, a closed standard output. Each gives one clean line and exit 1,
leaves no partial file and no temporaries, and keeps an existing file intact."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import tempfile

import pytest
from click.testing import CliRunner

from stages.formats import layered
from tests.conftest import ROOT
from vet_cli.main import cli


@pytest.fixture(scope="module")
def capture_file(tmp_path_factory):
    """A 320x240 capture (its HDR EXR is about 650 KB)."""
    path = tmp_path_factory.mktemp("outputs") / "cap.npz"
    result = CliRunner().invoke(
        cli, ["simulate", "builtin:interior", "--size", "320x240", "-o", str(path)]
    )
    assert result.exit_code == 0, result.stderr
    return path


def _mount_tmpfs(where, options: str) -> bool:
    if shutil.which("mount") is None or os.geteuid() != 0:
        return False
    where.mkdir(exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True
    )
    return done.returncode == 0


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 KiB tmpfs (root only; skipped where it cannot be mounted)."""
    where = tmp_path / "tiny"
    if not _mount_tmpfs(where, "size=64k"):
        pytest.skip("cannot mount a tmpfs here (not root, or no mount permission)")
    yield where
    subprocess.run(["umount", str(where)], check=False)


def _run(*args):
    result = CliRunner().invoke(cli, list(map(str, args)))
    return result.exit_code, result.stderr.strip().splitlines(), result.stdout


def _assert_refused(code, err, out, command, words):
    """Exit 1, nothing on stdout, one error line (last, after any warning of the work)."""
    assert code == 1 and out == ""
    assert err[-1].startswith(f"vet {command}: error: "), err
    assert all(line.startswith("vet: ") for line in err[:-1]), err
    assert words in err[-1], err[-1]


@pytest.mark.parametrize("name", ["h.exr", "h.npz"])
def test_full_disk_leaves_the_existing_file_and_no_temporaries(tiny_disk, capture_file, name):
    (tiny_disk / name).write_bytes(b"precious")
    # --force: replacing is asked for, and the full disk must still keep the old file
    code, err, out = _run("hdr-static", capture_file, "-o", tiny_disk / name, "--force")
    _assert_refused(code, err, out, "hdr-static", f"{name}: cannot write: no space left on device")
    assert sorted(os.listdir(tiny_disk)) == [name]
    assert (tiny_disk / name).read_bytes() == b"precious"


def test_full_disk_png(tiny_disk, capture_file):
    (tiny_disk / "fill").write_bytes(b"\0" * 60_000)
    code, err, out = _run("tonemap", capture_file, "--exposure-time-map", "-o", tiny_disk / "t.png")
    _assert_refused(code, err, out, "tonemap", "t.png: cannot write: no space left on device")
    assert sorted(os.listdir(tiny_disk)) == ["fill"]


def test_no_space_left_simulated(tmp_path, capture_file, monkeypatch):
    """ENOSPC mid-write, wherever a tmpfs cannot be mounted."""

    def half_then_full(path, data):
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 half a file")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(layered, "write_npz", half_then_full)
    (tmp_path / "h.npz").write_bytes(b"precious")
    code, err, out = _run("hdr-static", capture_file, "-o", tmp_path / "h.npz", "--force")
    _assert_refused(code, err, out, "hdr-static", "h.npz: cannot write: no space left on device")
    assert sorted(os.listdir(tmp_path)) == ["h.npz"]
    assert (tmp_path / "h.npz").read_bytes() == b"precious"


def test_read_only_folder(tmp_path, capture_file, monkeypatch):
    ro = tmp_path / "ro"
    if not _mount_tmpfs(ro, "ro,size=64k"):
        # Not root (or no mount): a folder without write permission does it, unless root.
        ro.mkdir(exist_ok=True)
        ro.chmod(0o555)

        def refuse(*args, **kwargs):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))

        monkeypatch.setattr(tempfile, "mkstemp", refuse)
    try:
        code, err, out = _run("hdr-static", capture_file, "-o", ro / "h.exr")
        _assert_refused(code, err, out, "hdr-static", f"h.exr: cannot create a file in {ro} (")
        assert os.listdir(ro) == []
    finally:
        subprocess.run(["umount", str(ro)], check=False, capture_output=True)


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_output_that_is_a_symlink_is_refused_before_any_work(tmp_path, capture_file, force):
    (tmp_path / "keep.exr").write_bytes(b"precious")
    (tmp_path / "link.exr").symlink_to(tmp_path / "keep.exr")
    code, err, out = _run("hdr-static", capture_file, "-o", tmp_path / "link.exr", *force)
    _assert_refused(code, err, out, "hdr-static", "link.exr: is a symbolic link (to ")
    assert (tmp_path / "keep.exr").read_bytes() == b"precious"
    assert (tmp_path / "link.exr").is_symlink()
    assert sorted(os.listdir(tmp_path)) == ["keep.exr", "link.exr"]


def test_closed_stdout_pipe(tmp_path):
    """``vet simulate ... -o - | head -c 10``: one line, exit 1, no temporary left."""
    private_tmp = tmp_path / "tmp"
    private_tmp.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(private_tmp))
    args = ["simulate", "builtin:interior", "--size", "128x96", "-o", "-"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "vet_cli", "-q", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    assert len(proc.stdout.read(10)) == 10
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1
    assert err.strip().splitlines() == [
        "vet simulate: error: standard output was closed before the output was written "
        "(broken pipe)"
    ]
    assert os.listdir(private_tmp) == []
