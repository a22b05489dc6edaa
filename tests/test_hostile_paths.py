"""Where an output may go (issue 52): by identity, not by name; batch names injective.

Every case is a clean refusal before any work (exit 1, one line naming both paths, no
traceback) that leaves every existing file byte for byte, or a correct result.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import struct
from pathlib import Path

import pytest
from click.testing import CliRunner

import stages
from stages.formats import write_capture
from vet_cli.main import cli

SAMPLE_SCENE = Path(stages.__file__).resolve().parents[1] / "sample_data/scenes/interior.exr"


def vet(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


@pytest.fixture(scope="module")
def capture_bytes(tmp_path_factory) -> bytes:
    """A small capture (48x40, two bins), as bytes."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = RigParams(sensor_size=(48, 40))
    cap = simulate(load_scene("builtin:chart", (48, 40)), parse_motion("none"), rig, measure_bins=2)
    path = tmp_path_factory.mktemp("cap") / "cap.exr"
    write_capture(path, cap["vet"])
    return path.read_bytes()


@pytest.fixture(scope="module")
def npz_bytes(tmp_path_factory, capture_bytes) -> bytes:
    from stages.formats import read_capture

    src = tmp_path_factory.mktemp("npz") / "cap.exr"
    src.write_bytes(capture_bytes)
    out = src.with_suffix(".npz")
    write_capture(out, read_capture(src))
    return out.read_bytes()


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (links not followed) and the SHA-256 of its bytes."""
    out = {}
    for dirpath, _dirs, files in os.walk(folder):
        for name in files:
            p = Path(dirpath) / name
            out[p.relative_to(folder).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def refused(result, command: str, *words: str) -> str:
    """Exit 1 and one line ``vet COMMAND: error: ...`` holding ``words``; that line."""
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert lines[-1].startswith(f"vet {command}: error: "), lines
    assert all(line.startswith("vet: ") for line in lines[:-1]), lines
    for w in words:
        assert w in lines[-1], lines[-1]
    return lines[-1]


@pytest.fixture
def d(tmp_path, capture_bytes) -> Path:
    """A capture folder tree: d/x.exr, a capture named d/x.hdr.exr (what x.exr's output
    would be called) and d/sub/y.exr."""
    root = tmp_path / "d"
    (root / "sub").mkdir(parents=True)
    for rel in ("x.exr", "x.hdr.exr", "sub/y.exr"):
        (root / rel).write_bytes(capture_bytes)
    return root


# ------------------------------------------------------------- vet batch: OUT vs ROOT


def test_batch_into_a_link_to_root_is_refused(d, tmp_path):
    (tmp_path / "dl").symlink_to(d)
    before = snapshot(d)
    line = refused(vet("batch", d, "-o", tmp_path / "dl", "-j", "1"), "batch", "is the input")
    assert "ROOT" in line and "through a link" in line
    assert snapshot(d) == before


@pytest.mark.parametrize("spelling", ["d/./sub/..", "d/sub/../", "d/sub/../../d"])
def test_batch_into_root_spelt_otherwise_is_refused(d, tmp_path, spelling, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = snapshot(d)
    refused(vet("batch", "d", "-o", spelling, "-j", "1"), "batch", "is the input ROOT d")
    assert snapshot(d) == before


def test_batch_from_root_spelt_otherwise_is_refused(d, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = snapshot(d)
    refused(vet("batch", "d/sub/..", "-o", "d", "-j", "1"), "batch", "is the input ROOT")
    assert snapshot(d) == before


def test_batch_into_a_folder_inside_root_is_refused(d, tmp_path):
    before = snapshot(d)
    refused(vet("batch", d, "-o", d / "results", "-j", "1"), "batch", "lies inside the input ROOT")
    assert snapshot(d) == before and not (d / "results").exists()


def test_batch_into_a_folder_holding_root_is_refused(d, tmp_path):
    before = snapshot(d)
    refused(vet("batch", d / "sub", "-o", d, "-j", "1"), "batch", "contains the input ROOT")
    assert snapshot(d) == before


def test_batch_with_a_capture_linked_from_the_output_folder_is_refused(d, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "z.exr").write_bytes((d / "x.exr").read_bytes())
    (d / "z.exr").symlink_to(out / "z.exr")  # a capture in ROOT that lives in OUT
    before_d, before_out = snapshot(d), snapshot(out)
    refused(vet("batch", d, "-o", out, "-j", "1"), "batch", "contains the input")
    assert snapshot(d) == before_d and snapshot(out) == before_out


def test_batch_output_that_is_a_hard_link_of_a_capture_is_refused(d, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    os.link(d / "x.exr", out / "x.hdr.exr")  # where x.exr's output would go
    before = snapshot(d)
    refused(vet("batch", d, "-o", out, "-j", "1"), "batch", "is the input")
    assert snapshot(d) == before and (out / "x.hdr.exr").read_bytes() == (d / "x.exr").read_bytes()


# ---------------------------------------------------------- vet batch: injective names


def test_batch_output_names_that_collide_are_refused_naming_both(
    tmp_path, capture_bytes, npz_bytes
):
    root = tmp_path / "c"
    root.mkdir()
    (root / "a.exr").write_bytes(capture_bytes)
    (root / "a.npz").write_bytes(npz_bytes)
    (root / "a.exr.exr").write_bytes(capture_bytes)
    line = refused(vet("batch", root, "-o", tmp_path / "out", "-j", "1"), "batch", "a.exr.hdr.exr")
    assert f"{root}/a.exr and {root}/a.exr.exr would both write" in line
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").rglob("*.exr"))


def test_batch_output_that_another_needs_as_a_folder_is_refused(tmp_path, capture_bytes):
    root = tmp_path / "c"
    (root / "a.hdr.exr").mkdir(parents=True)  # a folder whose captures go to OUT/a.hdr.exr/
    (root / "a.exr").write_bytes(capture_bytes)  # whose output is the file OUT/a.hdr.exr
    (root / "a.hdr.exr" / "b.exr").write_bytes(capture_bytes)
    line = refused(vet("batch", root, "-o", tmp_path / "out", "-j", "1"), "batch", "a.hdr.exr")
    assert f"{root}/a.exr" in line and f"{root}/a.hdr.exr/b.exr" in line
    assert not list((tmp_path / "out").rglob("*.exr"))


def test_batch_names_kept_apart_by_extension_still_run(tmp_path, capture_bytes, npz_bytes):
    root = tmp_path / "c"
    root.mkdir()
    (root / "a.exr").write_bytes(capture_bytes)
    (root / "a.npz").write_bytes(npz_bytes)
    r = vet("batch", root, "-o", tmp_path / "out", "-j", "1", "--steps", "hdr-static")
    assert r.exit_code == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "out").glob("*.exr")) == [
        "a.exr.hdr.exr",
        "a.npz.hdr.exr",
    ]


def _encrypt_member(data: bytes, member: bytes) -> bytes:
    """The zip with ``member``'s encryption flag set (local header and directory)."""
    out = bytearray(data)
    for magic, flag_at, name_len_at, name_at in (
        (b"PK\x03\x04", 6, 26, 30),
        (b"PK\x01\x02", 8, 28, 46),
    ):
        i = out.find(magic)
        while i >= 0:
            (n,) = struct.unpack_from("<H", out, i + name_len_at)
            if bytes(out[i + name_at : i + name_at + n]) == member:
                (flags,) = struct.unpack_from("<H", out, i + flag_at)
                struct.pack_into("<H", out, i + flag_at, flags | 1)
            i = out.find(magic, i + 4)
    return bytes(out)


def test_an_encrypted_npz_member_fails_its_capture_alone(tmp_path, capture_bytes, npz_bytes):
    root = tmp_path / "c"
    (root / "deep").mkdir(parents=True)
    (root / "good.exr").write_bytes(capture_bytes)
    (root / "deep" / "bad.npz").write_bytes(_encrypt_member(npz_bytes, b"__meta__.npy"))
    r = vet("batch", root, "-o", tmp_path / "out", "-j", "1", "--steps", "hdr-static")
    assert r.exit_code == 3, r.stderr
    assert "Traceback" not in r.stderr and "deep/bad.npz" in r.stderr
    assert (tmp_path / "out" / "good.hdr.exr").is_file()


# --------------------------------------------------------------- single commands


def test_hdr_static_onto_its_own_input_is_refused_with_force(tmp_path, capture_bytes):
    (tmp_path / "same.exr").write_bytes(capture_bytes)
    r = vet("hdr-static", tmp_path / "same.exr", "-o", tmp_path / "same.exr", "--force")
    refused(r, "hdr-static", "is the input CAPTURE")
    assert (tmp_path / "same.exr").read_bytes() == capture_bytes


def test_hdr_static_into_its_capture_folder_is_refused_with_force(tmp_path, capture_bytes):
    folder = tmp_path / "capfolder"
    folder.mkdir()
    (folder / "capture.exr").write_bytes(capture_bytes)
    for target in ("capture.exr", "hdr.exr"):
        r = vet("hdr-static", folder, "-o", folder / target, "--force")
        refused(r, "hdr-static", "lies inside the input CAPTURE")
    assert snapshot(folder) == {"capture.exr": hashlib.sha256(capture_bytes).hexdigest()}


def test_output_that_is_a_hard_link_of_the_input_is_refused(tmp_path, capture_bytes):
    (tmp_path / "a.exr").write_bytes(capture_bytes)
    os.link(tmp_path / "a.exr", tmp_path / "b.exr")
    r = vet("hdr-static", tmp_path / "a.exr", "-o", tmp_path / "b.exr", "--force")
    refused(r, "hdr-static", "is the input CAPTURE", "through a link")
    assert (tmp_path / "a.exr").read_bytes() == capture_bytes


def test_output_through_a_linked_folder_onto_the_input_is_refused(tmp_path, capture_bytes):
    (tmp_path / "real").mkdir()
    (tmp_path / "real" / "a.exr").write_bytes(capture_bytes)
    (tmp_path / "alias").symlink_to(tmp_path / "real")
    r = vet("deblur", tmp_path / "real/a.exr", "-o", tmp_path / "alias/a.exr", "--force")
    refused(r, "deblur", "is the input CAPTURE")
    r = vet(
        "deblur",
        tmp_path / "real/a.exr",
        "-o",
        tmp_path / "out.exr",
        "--motion-out",
        tmp_path / "alias/../real/a.exr",
        "--force",
    )
    refused(r, "deblur", "--motion-out")
    assert (tmp_path / "real" / "a.exr").read_bytes() == capture_bytes


def test_simulate_onto_its_scene_is_refused(tmp_path):
    scene = tmp_path / "scene.exr"
    shutil.copy(SAMPLE_SCENE, scene)
    before = scene.read_bytes()
    refused(vet("simulate", scene, "-o", scene, "--force"), "simulate", "is the input SCENE")
    assert scene.read_bytes() == before


def test_evaluate_report_folder_holding_its_scene_is_refused(tmp_path):
    scene = tmp_path / "scenes" / "scene.exr"
    scene.parent.mkdir()
    shutil.copy(SAMPLE_SCENE, scene)
    r = vet("evaluate", scene, "--methods", "long", "-o", tmp_path / "scenes", "--force")
    refused(r, "evaluate", "contains the input SCENE")
    assert sorted(os.listdir(scene.parent)) == ["scene.exr"]


def test_tonemap_onto_a_hard_link_of_its_input_is_refused(tmp_path, capture_bytes):
    (tmp_path / "a.exr").write_bytes(capture_bytes)
    os.link(tmp_path / "a.exr", tmp_path / "t.png")
    r = vet("tonemap", tmp_path / "a.exr", "--exposure-time-map", "-o", tmp_path / "t.png", "-f")
    refused(r, "tonemap", "is the input INPUT")
    assert (tmp_path / "a.exr").read_bytes() == capture_bytes
