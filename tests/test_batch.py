"""vet batch: discovery, manifest-driven reruns, failure isolation, kill -9, Dask."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from stages.batch import (
    EXIT_SOME_FAILED,
    MANIFEST_NAME,
    STEPS,
    SUMMARY_NAME,
    BatchOptions,
    CaptureUnit,
    Step,
    StepSpecError,
    discover_captures,
    output_stems,
    probe_kind,
    register_step,
    run_batch,
)
from stages.batch.discover import UNREADABLE
from stages.batch.manifest import output_lock
from stages.batch.steps import PIPELINE_ORDER, parse_steps, resolve_params
from stages.errors import VetError
from stages.formats import read_hdr, write_capture, write_hdr
from vet_cli.main import cli

from .conftest import ROOT

SIZE = (96, 80)
GOOD = ["a.exr", "b.npz", "day1/c.exr", "day1/d.exr", "day1/sub/e.exr", "f/capture.exr"]
BAD = ["bad.exr", "day1/trunc.exr"]


def _simulate(seed: int):
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:chart", SIZE)
    rig = RigParams(sensor_size=SIZE)
    return simulate(scene, parse_motion("none"), rig, seed=seed, measure_bins=2)["vet"]


@pytest.fixture(scope="module")
def capture_tree(tmp_path_factory) -> Path:
    """6 good captures (files, nested, a capture folder), 2 corrupt ones, 1 non-capture."""
    root = tmp_path_factory.mktemp("captures")
    for seed, rel in enumerate(GOOD):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        write_capture(root / rel, _simulate(seed))  # seeded: distinct, reproducible captures
    (root / "bad.exr").write_bytes(b"this is not an EXR file\n" * 4)
    data = (root / "a.exr").read_bytes()
    (root / "day1/trunc.exr").write_bytes(data[: len(data) // 2])  # header intact, pixels cut
    # Not captures: an HDR image, and a stream file inside the capture folder.
    from stages.hdr_static import hdr_static

    write_hdr(root / "day1/already.hdr.exr", hdr_static(_simulate(0)))
    shutil.copy(root / "a.exr", root / "f" / "stream.exr")
    return root


@pytest.fixture
def tree(capture_tree, tmp_path) -> Path:
    root = tmp_path / "captures"
    shutil.copytree(capture_tree, root)
    return root


def vet(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


def outputs_of(rel: str) -> list[str]:
    stem = rel[: -len("/capture.exr")] if rel.endswith("/capture.exr") else rel.rsplit(".", 1)[0]
    return [stem + ".hdr.exr", stem + ".png"]


def mtimes(out: Path) -> dict[str, int]:
    return {
        p.relative_to(out).as_posix(): p.stat().st_mtime_ns
        for p in out.rglob("*")
        if p.is_file() and p.suffix in (".exr", ".png")
    }


def assert_readable(path: Path) -> None:
    if path.suffix == ".png":
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape[:2] == (SIZE[1], SIZE[0]), path
    else:
        img = read_hdr(path)
        assert img.radiance.shape[:2] == (SIZE[1], SIZE[0]) and np.isfinite(img.radiance).all(), (
            path
        )


def summary(out: Path) -> dict:
    return json.loads((out / SUMMARY_NAME).read_text())


# ------------------------------------------------------------------ discovery


def test_discovery_finds_files_and_folders_and_keeps_corrupt_ones(tree):
    units, ignored = discover_captures(tree)
    assert [u.rel for u in units] == sorted(GOOD[:-1] + ["f"] + BAD)
    folder = next(u for u in units if u.rel == "f")
    assert folder.is_folder and folder.path.name == "capture.exr"
    assert [i.rel for i in ignored] == ["day1/already.hdr.exr"]
    assert "kind: hdr" in ignored[0].reason


def test_discovery_skips_the_output_folder_and_hidden_files(tree):
    (tree / "results").mkdir()
    shutil.copy(tree / "a.exr", tree / "results" / "x.exr")
    shutil.copy(tree / "a.exr", tree / ".hidden.exr")
    units, _ = discover_captures(tree, exclude=[tree / "results"])
    assert "results/x.exr" not in [u.rel for u in units]
    assert ".hidden.exr" not in [u.rel for u in units]


def test_probe_kind_reads_headers_only(tree):
    assert probe_kind(tree / "a.exr") == "capture"
    assert probe_kind(tree / "b.npz") == "capture"
    assert probe_kind(tree / "day1/trunc.exr") == "capture"
    assert probe_kind(tree / "day1/already.hdr.exr") == "hdr"
    assert probe_kind(tree / "bad.exr") == UNREADABLE
    header_cut = tree / "cut.exr"
    header_cut.write_bytes((tree / "a.exr").read_bytes()[:40])
    assert probe_kind(header_cut) == UNREADABLE
    # metadata whose header declares a terabyte: unreadable, nothing allocated for it
    import io
    import zipfile

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {"descr": "|u1", "fortran_order": False, "shape": (1 << 40,)}
    )
    with zipfile.ZipFile(tree / "huge.npz", "w") as zf:
        zf.writestr("__meta__.npy", head.getvalue() + b"x" * 16)
    assert probe_kind(tree / "huge.npz") == UNREADABLE


def test_output_stems_mirror_layout_and_resolve_collisions(tmp_path):
    units = [
        CaptureUnit("d/a.exr", tmp_path / "d/a.exr", False),
        CaptureUnit("d/a.npz", tmp_path / "d/a.npz", False),
        CaptureUnit("x", tmp_path / "x/capture.exr", True),
        CaptureUnit("x.exr", tmp_path / "x.exr", False),
        CaptureUnit("y.exr", tmp_path / "y.exr", False),
    ]
    assert output_stems(units, "root") == {
        "d/a.exr": "d/a.exr",
        "d/a.npz": "d/a.npz",
        "x": "x",
        "x.exr": "x.exr",
        "y.exr": "y",
    }
    assert output_stems([CaptureUnit(".", tmp_path / "capture.exr", True)], "root") == {".": "root"}


# ------------------------------------------------------------------ steps


def test_steps_parse_in_pipeline_order_and_refuse_nonsense():
    assert parse_steps("tonemap,hdr-static") == ["hdr-static", "tonemap"]
    assert parse_steps(None) == ["hdr-static", "tonemap"]
    with pytest.raises(StepSpecError, match="unknown step"):
        parse_steps("hdr-static,sharpen")
    with pytest.raises(StepSpecError, match="needs an HDR step"):
        parse_steps("tonemap")
    with pytest.raises(StepSpecError, match="no parameter 'gain'"):
        resolve_params(["hdr-static", "tonemap"], {"tonemap": {"gain": 2}})
    with pytest.raises(StepSpecError, match="operator"):
        resolve_params(["hdr-static", "tonemap"], {"tonemap": {"operator": "magic"}})
    with pytest.raises(StepSpecError, match="not in --steps"):
        resolve_params(["hdr-static"], {"tonemap": {"exposure": 1}})


def test_unavailable_step_stops_the_run_with_a_clear_error(tree, tmp_path):
    register_step(
        Step(
            "fake",
            ".fake.exr",
            "capture",
            "hdr",
            "stages.no_such_module_for_tests",
            lambda i, o, p: None,
        )
    )
    try:
        with pytest.raises(VetError, match="'fake' is not available"):
            run_batch(tree, tmp_path / "out", BatchOptions(steps="fake"))
        assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.exr"))
    finally:
        STEPS.pop("fake")
        PIPELINE_ORDER.remove("fake")


# ------------------------------------------------------------------ runs (in-process)


def test_batch_results_summary_and_exit_status(tree, tmp_path):
    out = tmp_path / "out"
    r = vet("batch", tree, "-o", out, "-j", "1")
    assert r.exit_code == EXIT_SOME_FAILED, r.output
    for rel in GOOD:
        for o in outputs_of(rel):
            assert_readable(out / o)
    assert (out / "f.hdr.exr").is_file() and not (out / "f").exists()
    s = summary(out)
    assert s["counts"] == {
        "captures": 8,
        "done": 6,
        "up_to_date": 0,
        "failed": 2,
        "would_run": 0,
        "ignored_files": 1,
    }
    reasons = {f["capture"]: f["reason"] for f in s["failures"]}
    assert set(reasons) == set(BAD)
    assert "not an OpenEXR" in reasons["bad.exr"]
    assert "unreadable" in reasons["day1/trunc.exr"]
    # The readable table on stderr names both, and the last line is vet's one-line error.
    assert "bad.exr" in r.stderr and "day1/trunc.exr" in r.stderr and "not an OpenEXR" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("vet batch: error: 2 of 8 captures failed")
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    rec = manifest["captures"]["a.exr"]
    assert rec["status"] == "ok" and len(rec["input"]["sha256"]) == 64
    assert rec["steps"]["tonemap"]["params"] == {"operator": "log", "exposure": 0.0, "bits": 8}
    assert manifest["vet_version"]


def test_deblur_parameters_reach_the_stage(tree, tmp_path):
    # Batch passes deblur.NAME=VALUE to stages.deblur.deblur(): --fuse-still as a parameter.
    for rel in BAD:
        (tree / rel).unlink()
    out = tmp_path / "out"
    r = vet(
        "batch",
        tree,
        "-o",
        out,
        "-j",
        "1",
        "--steps",
        "deblur",
        "--param",
        "deblur.fuse_still=true",
    )
    assert r.exit_code == 0, r.output
    img = read_hdr(out / "a.deblur.exr")
    assert img.meta["still_pixels"] == "fused"
    assert img.meta["provenance"][-1]["params"]["fuse_still"] is True


def test_all_good_exits_zero(tree, tmp_path):
    for rel in BAD:
        (tree / rel).unlink()
    r = vet("batch", tree, "-o", tmp_path / "out", "-j", "1")
    assert r.exit_code == 0, r.output


def test_rerun_does_no_work(tree, tmp_path):
    out = tmp_path / "out"
    run_batch(tree, out)
    before = mtimes(out)
    report = run_batch(tree, out)
    assert report.summary["counts"]["done"] == 0
    assert report.summary["counts"]["up_to_date"] == 6
    assert [f["cached"] for f in report.failures] == [True, True]
    assert report.exit_status == EXIT_SOME_FAILED
    assert mtimes(out) == before
    # A touched but unchanged input is recognised by its hash and not rerun.
    os.utime(tree / "b.npz", ns=(time.time_ns(), time.time_ns()))
    assert run_batch(tree, out).summary["counts"]["done"] == 0
    # --retry-failed tries the failed ones again, and only those.
    report = run_batch(tree, out, BatchOptions(retry_failed=True))
    assert report.summary["counts"]["done"] == 0 and report.summary["counts"]["failed"] == 2
    assert [f["cached"] for f in report.failures] == [False, False]


def test_changed_parameter_reruns_only_the_affected_step(tree, tmp_path):
    out = tmp_path / "out"
    run_batch(tree, out)
    before = mtimes(out)
    png_before = (out / "a.png").read_bytes()
    r = vet("batch", tree, "-o", out, "-j", "1", "--exposure", "2")
    assert r.exit_code == EXIT_SOME_FAILED
    after = mtimes(out)
    for rel in GOOD:
        hdr, png = outputs_of(rel)
        assert after[hdr] == before[hdr], hdr
        assert after[png] != before[png], png
    assert (out / "a.png").read_bytes() != png_before
    assert summary(out)["params"]["tonemap"]["exposure"] == 2.0
    # The same parameters again: nothing to do.
    assert (
        run_batch(tree, out, BatchOptions(params={"tonemap": {"exposure": 2}})).summary["counts"][
            "done"
        ]
        == 0
    )


def test_changed_input_and_damaged_outputs_rerun(tree, tmp_path):
    out = tmp_path / "out"
    run_batch(tree, out)
    before = mtimes(out)
    write_capture(tree / "a.exr", _simulate(99))  # new content
    (out / "day1/c.png").unlink()  # deleted output
    (out / "day1/d.hdr.exr").write_bytes(b"garbage")  # corrupted output
    report = run_batch(tree, out)
    done = {o["capture"] for o in report.summary["captures"] if o["status"] == "done"}
    assert done == {"a.exr", "day1/c.exr", "day1/d.exr"}
    after = mtimes(out)
    assert after["day1/c.hdr.exr"] == before["day1/c.hdr.exr"]  # only the PNG was missing
    for rel in ("a.exr", "day1/c.exr", "day1/d.exr"):
        for o in outputs_of(rel):
            assert_readable(out / o)
    # A repaired bad capture is retried without --retry-failed (its input changed).
    shutil.copy(tree / "b.npz", tree / "day1/trunc.exr")
    report = run_batch(tree, out)
    assert [f["capture"] for f in report.failures] == ["bad.exr"]
    assert_readable(out / "day1/trunc.png")


def test_dry_run_writes_nothing(tree, tmp_path):
    out = tmp_path / "out"
    r = vet("batch", tree, "-o", out, "-n")
    assert r.exit_code == 0, r.output
    assert not out.exists()
    assert "a.exr: hdr-static, tonemap" in r.stderr


def test_usage_errors_exit_2(tree, tmp_path):
    out = tmp_path / "out"
    for args in (
        ["--steps", "tonemap"],
        ["--steps", "blur"],
        ["--param", "tonemap.gain=2"],
        ["--param", "nonsense"],
        ["--operator", "magic"],
        ["-j", "0"],
    ):
        r = vet("batch", tree, "-o", out, *args)
        assert r.exit_code == 2, (args, r.output)
    assert vet("batch", tmp_path / "missing", "-o", out).exit_code == 2


def test_locked_output_folder_is_a_runtime_error(tree, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with output_lock(out):
        r = vet("batch", tree, "-o", out, "-j", "1")
    assert r.exit_code == 1
    assert "another vet batch is writing" in r.stderr


@pytest.mark.skipif(sys.platform == "win32", reason="kill -9 is POSIX")
def test_kill_9_midway_then_rerun_completes_with_no_corrupt_output(capture_tree, tmp_path):
    root = tmp_path / "captures"
    root.mkdir()
    for i in range(40):  # copies of one capture: enough work to be killed midway
        shutil.copy(capture_tree / "a.exr", root / f"cap{i:02d}.exr")
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "vet_cli", "batch", str(root), "-o", str(out), "-j", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    try:
        # Kill as soon as the first capture is recorded in the manifest, mid-way through.
        deadline = time.monotonic() + 60
        while not (out / MANIFEST_NAME).exists():
            assert proc.poll() is None, "batch finished before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    for p in [*out.glob("*.exr"), *out.glob("*.png")]:
        if not p.name.startswith(".vet-tmp-"):  # unfinished temporaries are not outputs
            assert_readable(p)
    if (out / MANIFEST_NAME).exists():
        json.loads((out / MANIFEST_NAME).read_text())  # never torn
    report = run_batch(root, out)
    assert report.exit_status == 0
    c = report.summary["counts"]
    assert c["done"] + c["up_to_date"] == 40 and c["up_to_date"] >= 1
    assert not list(out.rglob(".vet-tmp-*"))
    for i in range(40):
        assert_readable(out / f"cap{i:02d}.hdr.exr")
        assert_readable(out / f"cap{i:02d}.png")


# ------------------------------------------------------------------ Dask


def test_local_cluster_two_workers(tree, tmp_path):
    out = tmp_path / "out"
    report = run_batch(tree, out, BatchOptions(jobs=2))
    assert "LocalCluster, 2 worker" in report.summary["executor"]
    assert report.summary["counts"]["done"] == 6
    assert {f["capture"] for f in report.failures} == set(BAD)
    assert report.summary["workers"] == 2
    for rel in GOOD:
        for o in outputs_of(rel):
            assert_readable(out / o)


@pytest.fixture
def dask_cluster(tmp_path):
    """A Dask scheduler and two single-thread workers, started as separate processes on
    loopback; yields the scheduler address; everything is stopped at the end."""
    from tests.dask_local import separate_dask_cluster

    with separate_dask_cluster(tmp_path, workers=2) as address:
        yield address


def test_separately_started_scheduler_and_two_workers(tree, tmp_path, dask_cluster):
    out = tmp_path / "out"
    r = vet("batch", tree, "-o", out, "--scheduler", dask_cluster)
    assert r.exit_code == EXIT_SOME_FAILED, r.output
    s = summary(out)
    assert s["executor"] == f"dask scheduler {dask_cluster}"
    assert s["counts"]["done"] == 6 and {f["capture"] for f in s["failures"]} == set(BAD)
    for rel in GOOD:
        for o in outputs_of(rel):
            assert_readable(out / o)
    # The rerun against the cluster has nothing to do.
    r = vet("batch", tree, "-o", out, "--scheduler", dask_cluster)
    assert summary(out)["counts"]["done"] == 0


def test_unreachable_scheduler_is_a_runtime_error(tree, tmp_path, monkeypatch):
    import stages.batch.run as run_mod

    monkeypatch.setattr(run_mod, "CONNECT_TIMEOUT_S", 2.0)
    r = vet("batch", tree, "-o", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:9")
    assert r.exit_code == 1
    assert "cannot reach the Dask scheduler" in r.stderr


def test_workers_limit_openimageio_to_one_thread():
    """N workers must mean N cores: OpenImageIO/OpenEXR would otherwise spread each
    worker's compression over every core (measured 1.4 cores for one worker)."""
    import OpenImageIO as oiio

    from stages import cluster

    before = oiio.get_int_attribute("threads")
    try:
        cluster._threads_limited = False
        cluster.limit_threads()
        assert oiio.get_int_attribute("threads") == 1
        assert oiio.get_int_attribute("exr_threads") == 1
    finally:
        oiio.attribute("threads", before)
