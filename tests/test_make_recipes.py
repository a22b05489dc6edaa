"""make/vet.mk: pattern rules from a folder of captures to HDR EXRs and PNGs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from stages.formats import read_hdr, write_capture

from .conftest import ROOT

VET_MK = ROOT / "make" / "vet.mk"
SIZE = (96, 80)
STEMS = ["a", "day1/b", "day1/f"]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="GNU make is not installed")


@pytest.fixture
def project(tmp_path) -> Path:
    """A user's project: captures/ (a file, a nested .npz, a capture folder), a Makefile."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:chart", SIZE)
    rig = RigParams(sensor_size=SIZE)
    caps = tmp_path / "captures"
    for seed, rel in enumerate(["a.exr", "day1/b.npz", "day1/f/capture.exr"]):
        (caps / rel).parent.mkdir(parents=True, exist_ok=True)
        # Seeded: each capture differs and the test reproduces.
        write_capture(
            caps / rel, simulate(scene, parse_motion("none"), rig, seed=seed, measure_bins=2)["vet"]
        )
    shutil.copy(
        caps / "a.exr", caps / "day1/f/stream.exr"
    )  # inside a capture folder: not a capture
    vet = Path(sys.executable).parent / "vet"
    (tmp_path / "Makefile").write_text(
        f"all: vet-all\n\nVET = {vet}\nCAPTURES = captures\nOUT = out\ninclude {VET_MK}\n"
    )
    return tmp_path


def make(project: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        ["make", "--no-print-directory", *args],
        cwd=project,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def test_stems_cover_files_and_capture_folders(project):
    r = make(project, "vet-list")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == STEMS


def test_make_j2_builds_everything_and_touch_rebuilds_only_that_capture(project):
    r = make(project, "-j2")
    assert r.returncode == 0, r.stdout + r.stderr
    out = project / "out"
    for stem in STEMS:
        img = read_hdr(out / f"{stem}.hdr.exr")
        assert img.radiance.shape[:2] == (SIZE[1], SIZE[0])
        png = cv2.imread(str(out / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert png is not None and png.shape[:2] == (SIZE[1], SIZE[0])
    assert not (out / "day1/f").exists()
    assert "Nothing to be done" in make(project).stdout

    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    future = time.time() + 5  # later than every output, whatever the clock granularity
    os.utime(project / "captures/day1/b.npz", (future, future))
    plan = make(project, "-n").stdout
    assert "captures/day1/b.npz -o out/day1/b.hdr.exr" in plan
    assert "out/day1/b.hdr.exr -o out/day1/b.png" in plan
    assert len([line for line in plan.splitlines() if " -o " in line]) == 2
    r = make(project, "-j2")
    assert r.returncode == 0, r.stdout + r.stderr
    changed = {p.relative_to(out).as_posix() for p in before if p.stat().st_mtime_ns != before[p]}
    assert changed == {"day1/b.hdr.exr", "day1/b.png"}


def test_variables_with_trailing_comments_build(project):
    """``CAPTURES = captures   # comment`` keeps the spaces before the comment in Make;
    vet.mk strips its variables, so the style users write works."""
    vet = Path(sys.executable).parent / "vet"
    (project / "Makefile").write_text(
        f"all: vet-all\n\nVET = {vet}   # the command\nCAPTURES = captures   # searched\n"
        f"OUT = out      # mirrors CAPTURES\ninclude {VET_MK}\n"
    )
    r = make(project, "vet-hdr")
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in (project / "out").rglob("*.hdr.exr")) == [
        "a.hdr.exr",
        "b.hdr.exr",
        "f.hdr.exr",
    ]
