"""Every shell example in README.md and docs/*.md runs, as pasted, with small sizes.

Each fenced ``sh``/``bash``/``console`` block is one test; the blocks of a document run
in order in one folder, as a reader following it would, with ``vet`` and ``make`` on the
PATH. Untyped blocks are synopses, diagrams or byte dumps, not examples.

What a reader would have beside the document (the *fixture*):
``sample_data/scenes/interior.exr`` (the shipped linear HDR scene, here at 96x80),
``captures/`` (three captures, one a capture folder), ``recorded/`` (recorded
calibration frames), ``real.exr`` (a capture standing for one from a rig) and, where the
document shows a Make snippet, a Makefile holding it (its ``VET_HOME`` the checkout's
absolute path, as from a project elsewhere). What the test changes in a command
(:data:`SUBSTITUTIONS`, each with its reason): sizes shrink (every example runs at
96x80, objects and LCoS grids scaled with it), a real rig (``--rig rig.toml``) becomes the
emulated one, an example cluster address becomes a scheduler started on loopback for the
test, the virtual environment activated is the one running the tests, and ``make test``
(this suite itself) is not run from within it.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SIZE = "96x80"

#: (pattern, replacement, why). Applied in order to each example.
SUBSTITUTIONS = [
    (r"--size \d+x\d+", f"--size {SIZE}", "every example runs at 96x80"),
    (r"object:40,32,80,64:20,5", "object:12,10,24,20:20,5", "the object scaled to 96x80"),
    (r"--lcos 256x150", "--lcos 64x40", "an LCoS grid scaled to 96x80"),
    (r"--lcos 1024x600", "--lcos 40x24", "the recorded/ fixture's LCoS grid"),
    (r"--rig rig\.toml", f"--rig sim --size {SIZE}", "no real rig here: the emulated one"),
    (
        r"(vet (?:simulate|evaluate) builtin:\w+)(?![^\n]*--size)",
        rf"\1 --size {SIZE}",
        "builtin scenes render at 640x512 unless told",
    ),
    (
        r"(vet capture --rig sim)(?![^\n]*(?:--size|--calibration))",
        rf"\1 --size {SIZE}",
        "the emulated rig at 96x80 (with a calibration it takes the calibrated size)",
    ),
    (r"^make test\b.*$", "true  # make test: this suite itself", "no recursion"),
    (
        r"^\. \.venv/bin/activate\b",
        f". {Path(sys.executable).parent / 'activate'}",
        "the virtual environment running the tests, not one in the fixture's folder",
    ),
    (r"path/to/vet/make/vet\.mk", str(ROOT / "make" / "vet.mk"), "where vet.mk is here"),
]


def shell_blocks(path: Path) -> list[tuple[int, str]]:
    """``(line, text)`` of each fenced sh/bash/console block of a Markdown file."""
    text = path.read_text(encoding="utf-8")
    out = []
    for m in re.finditer(r"^```(sh|bash|console|shell)\n(.*?)^```", text, re.S | re.M):
        out.append((text[: m.start()].count("\n") + 1, m.group(2)))
    return out


def make_blocks(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    return [m.group(1) for m in re.finditer(r"^```make\n(.*?)^```", text, re.S | re.M)]


def substitute(script: str, scheduler: str | None) -> str:
    for pattern, repl, _why in SUBSTITUTIONS:
        script = re.sub(pattern, repl, script, flags=re.M)
    if scheduler:
        script = script.replace("tcp://10.0.0.5:8786", scheduler)
    return script


def _write_fixture(folder: Path, doc: Path) -> None:
    from stages.formats import write_capture
    from stages.formats.layered import _oiio
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import builtin_interior
    from stages.simulate import simulate
    from tests.test_calibrate_recorded import _write_folder

    w, h = (int(v) for v in SIZE.split("x"))
    scene = builtin_interior(w, h)
    oiio = _oiio()
    spec = oiio.ImageSpec(w, h, 3, "float")
    scene_path = folder / "sample_data" / "scenes" / "interior.exr"
    scene_path.parent.mkdir(parents=True)
    out = oiio.ImageOutput.create(str(scene_path))
    out.open(str(scene_path), spec)
    out.write_image(np.ascontiguousarray(scene.radiance, np.float32))
    out.close()
    rig = RigParams(sensor_size=(w, h))
    for seed, rel in enumerate(["a.exr", "day1/b.npz", "day1/c/capture.exr"]):
        path = folder / "captures" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        motion = parse_motion("translate:20,0" if seed == 1 else "none")
        write_capture(path, simulate(scene, motion, rig, seed=seed, measure_bins=4)["vet"])
    shutil.copy(folder / "captures" / "day1" / "b.npz", folder / "real.npz")
    cap = simulate(scene, parse_motion("translate:20,0"), rig, seed=7)["vet"]
    write_capture(folder / "real.exr", cap)
    _write_folder(folder / "recorded")
    snippets = make_blocks(doc)
    if snippets:
        body = substitute(snippets[0], None)
        body = re.sub(
            r"^VET\s*=.*$", f"VET = {Path(sys.executable).parent / 'vet'}", body, flags=re.M
        )
        body = re.sub(r"^VET_HOME\s*=.*$", f"VET_HOME = {ROOT}", body, flags=re.M)
        body = body.replace("include make/vet.mk", f"include {ROOT / 'make' / 'vet.mk'}")
        (folder / "Makefile").write_text(body)


_folders: dict[Path, Path] = {}


def _folder(doc: Path, tmp_path_factory) -> Path:
    if doc not in _folders:
        folder = tmp_path_factory.mktemp(doc.stem)
        _write_fixture(folder, doc)
        _folders[doc] = folder
    return _folders[doc]


#: Examples that take minutes even at 96x80, run by ``make test-slow``: make demo (its
#: own 640x512 demo), and those that start a Dask cluster or run the paper's deblur.
SLOW_KEYS = ("make demo", "--scheduler", "deblur.method=paper")


def _is_slow(text: str) -> bool:
    return any(key in text for key in SLOW_KEYS)


CASES = [
    pytest.param(
        doc,
        line,
        text,
        id=f"{doc.name}:{line}",
        # A document's blocks run in order in one folder: on one pytest-xdist worker.
        marks=[pytest.mark.xdist_group(doc.name), *([pytest.mark.slow] if _is_slow(text) else [])],
    )
    for doc in DOCS
    for line, text in shell_blocks(doc)
]


@pytest.mark.parametrize("doc, line, text", CASES)
def test_example_runs_as_pasted(doc, line, text, tmp_path_factory):
    scheduler = None
    cluster = None
    if "tcp://10.0.0.5:8786" in text:
        from tests.dask_local import separate_dask_cluster

        cluster = separate_dask_cluster(tmp_path_factory.mktemp("dask"), workers=1)
        scheduler = cluster.__enter__()
    try:
        script = substitute(text, scheduler)
        script = script.replace("make demo", f"make -C {ROOT} demo")
        env = dict(
            os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
        )
        env["PYTHONPATH"] = str(ROOT)
        res = subprocess.run(
            ["bash", "-c", "set -euo pipefail\n" + script],
            cwd=_folder(doc, tmp_path_factory),
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
    finally:
        if cluster is not None:
            cluster.__exit__(None, None, None)
    assert res.returncode == 0, f"{doc.name}:{line}\n{script}\n--- stderr:\n{res.stderr[-3000:]}"
    # No traceback out of vet's own code (Dask's worker heartbeats may log one of theirs
    # on a loaded machine while the command succeeds).
    assert not re.search(r'File "[^"]*/(stages|vet_cli)/', res.stderr), res.stderr[-3000:]


def test_every_document_with_examples_is_covered():
    """The README and the docs that show commands all have runnable blocks here."""
    names = {c.values[0].name for c in CASES}
    assert {"README.md", "batch.md", "calibration.md"} <= names


@pytest.mark.parametrize("doc", [d for d in DOCS if make_blocks(d)], ids=lambda d: d.name)
def test_make_snippet_builds(doc, tmp_path):
    """The document's Make snippet, pasted into a Makefile beside captures/, builds every
    capture's HDR image and picture."""
    _write_fixture(tmp_path, doc)
    res = subprocess.run(
        ["make", "-j2", "vet-all"], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stdout + res.stderr
    out = re.search(r"^OUT\s*=\s*(\S+)", (tmp_path / "Makefile").read_text(), re.M).group(1)
    built = sorted(
        p.relative_to(tmp_path / out).as_posix() for p in (tmp_path / out).rglob("*.png")
    )
    assert built == ["a.png", "day1/b.png", "day1/c.png"], built
