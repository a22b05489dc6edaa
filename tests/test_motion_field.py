"""Dense motion fields from a file (``--motion field:PATH``) against known answers."""

from __future__ import annotations

import numpy as np
import pytest

from stages.errors import InputError
from stages.flow import write_motion
from stages.motion import DenseField, Translate, parse_motion
from stages.rig import RigParams
from stages.scenes import Scene
from stages.simulate import simulate
from tests.conftest import run_vet


def _constant_field(path, u: float, v: float, w: int = 40, h: int = 32) -> str:
    field = np.empty((h, w, 2), np.float32)
    field[..., 0], field[..., 1] = u, v
    write_motion(str(path), field)
    return str(path)


def test_constant_field_renders_like_translate(tmp_path, rng):
    motion = parse_motion("field:" + _constant_field(tmp_path / "m.exr", 12.0, -5.0))
    assert isinstance(motion, DenseField) and not motion.is_still
    scene = rng.random((32, 40, 3)).astype(np.float32)
    for t in (0.0, 0.4, 0.9):
        np.testing.assert_allclose(
            motion.render(scene, t), Translate(12.0, -5.0).render(scene, t), atol=2e-3
        )


def test_each_pixel_moves_along_its_own_velocity(tmp_path):
    field = np.zeros((20, 40, 2), np.float32)
    field[:, :20, 0] = 20.0  # the left half moves right at 20 px/s, the right half is still
    write_motion(str(tmp_path / "m.exr"), field)
    motion = parse_motion(f"field:{tmp_path / 'm.exr'}")
    img = np.zeros((20, 40, 1), np.float32)
    img[10, 5] = 1.0
    img[10, 30] = 1.0
    out = motion.render(img, 0.25)  # 5 px right on the left, nothing on the right
    assert out[10, 10, 0] == pytest.approx(1.0)
    assert out[10, 5, 0] == pytest.approx(0.0)
    assert out[10, 30, 0] == pytest.approx(1.0)
    np.testing.assert_array_equal(motion.velocity((20, 40)), field)


def test_field_is_resampled_to_the_scene_with_its_velocities(tmp_path):
    motion = parse_motion("field:" + _constant_field(tmp_path / "m.npz", 10.0, 4.0))
    vel = motion.velocity((64, 80))  # twice the field's size: twice the speed in pixels
    assert vel.shape == (64, 80, 2)
    np.testing.assert_allclose(vel[..., 0], 20.0, rtol=1e-6)
    np.testing.assert_allclose(vel[..., 1], 8.0, rtol=1e-6)
    with pytest.raises(InputError, match="does not fit a 80x40 scene"):
        motion.velocity((40, 80))


def test_a_still_field_simulates_exactly_like_no_motion(tmp_path):
    still = parse_motion("field:" + _constant_field(tmp_path / "m.exr", 0.0, 0.0))
    assert still.is_still
    rig = RigParams(sensor_size=(40, 32))
    scene = Scene(np.random.default_rng(3).random((32, 40, 1)).astype(np.float32), ["Y"], "r")
    a = simulate(scene, still, rig, seed=5)["vet"]
    b = simulate(scene, parse_motion("none"), rig, seed=5)["vet"]
    np.testing.assert_array_equal(a.I, b.I)
    np.testing.assert_array_equal(a.T, b.T)
    assert a.meta["motion"] == f"field:{tmp_path / 'm.exr'}"


def test_simulate_refuses_a_field_that_does_not_fit_before_rendering(tmp_path):
    motion = parse_motion("field:" + _constant_field(tmp_path / "m.exr", 1.0, 0.0))
    rig = RigParams(sensor_size=(40, 40))
    scene = Scene(np.ones((40, 40, 1), np.float32), ["Y"], "flat")
    calls = []
    with pytest.raises(InputError, match="another aspect ratio"):
        simulate(scene, motion, rig, progress=lambda done, total: calls.append(done))
    assert calls == []


def test_field_errors_are_one_line_exit_1(tmp_path):
    from stages.formats.layered import Layered, write_layered
    from tests.hostile import write_unchecked

    bad = Layered(meta={"kind": "motion", "units": "px/s"})
    bad.add("motion", np.zeros((8, 8, 2), np.float32), ["u", "v"])
    bad.layers["motion"][3, 3, 0] = np.nan
    write_unchecked(tmp_path / "nan.exr", bad)  # (write_motion refuses to write it)
    other = Layered(meta={"kind": "hdr"})
    other.add("", np.ones((8, 8, 1), np.float32), ["Y"])
    write_layered(tmp_path / "hdr.exr", other)
    cases = {
        "field:" + str(tmp_path / "nan.exr"): "non-finite velocities",
        "field:" + str(tmp_path / "hdr.exr"): "not a motion field (kind 'hdr'",
        "field:" + str(tmp_path / "missing.exr"): "no such file",
    }
    for spec, message in cases.items():
        res = run_vet(
            "simulate",
            "builtin:chart",
            "--size",
            "32x32",
            "--motion",
            spec,
            "-o",
            str(tmp_path / "out.exr"),
        )
        err = res.stderr.decode()
        assert res.returncode == 1, (spec, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("vet simulate: error: "), err
        assert message in lines[0], (spec, lines[0])
        assert not (tmp_path / "out.exr").exists()
    # A malformed SPEC is a bad option value: a usage error.
    res = run_vet("simulate", "builtin:chart", "--motion", "field:", "-o", tmp_path / "out.exr")
    assert res.returncode == 2 and b"field:PATH needs the path of a motion file" in res.stderr


def test_deblur_motion_out_drives_simulate(tmp_path):
    """The motion deblur writes is a motion simulate reads: the loop closes on files."""
    from stages.formats import read_capture, read_layered

    cap, motion = tmp_path / "cap.exr", tmp_path / "m.exr"
    simulate_args = "-q simulate builtin:chart --size 48x40 --motion translate:20,0 -o".split()
    assert run_vet(*simulate_args, str(cap)).returncode == 0
    res = run_vet(
        "-q", "deblur", str(cap), "-o", str(tmp_path / "d.exr"), "--motion-out", str(motion)
    )
    assert res.returncode == 0, res.stderr
    again = tmp_path / "again.exr"
    res = run_vet(
        "-q",
        "simulate",
        "builtin:chart",
        "--size",
        "96x80",
        "--motion",
        f"field:{motion}",
        "-o",
        str(again),
    )
    assert res.returncode == 0, res.stderr
    estimated = read_layered(motion).layers["motion"]
    truth = read_capture(again).truth_motion
    assert truth.shape == (80, 96, 2)
    # twice the size, twice the speed in pixels: the mean velocity scales exactly
    np.testing.assert_allclose(
        truth.mean(axis=(0, 1)), 2 * estimated.mean(axis=(0, 1)), rtol=1e-3, atol=1e-3
    )
    assert read_capture(again).meta["motion"] == f"field:{motion}"
