"""Rectangles along paths (accel, path, spin, several joined by +): their specs, their
rendering against the truth they store, and the CLI's answer to a bad SPEC."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from stages.errors import InputError
from stages.motion import Sprites, parse_motion

H, W = 72, 96


def _smooth_scene() -> np.ndarray:
    """A smooth radiance (H, W, 1): bilinear resampling errs by under 0.003 on it, while
    a position off by one pixel changes it by about 0.05."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return (1.0 + 0.3 * np.sin(0.21 * xx + 0.4) * np.cos(0.17 * yy) + 0.002 * xx)[..., None]


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    a, b = img[y0, x0], img[y0, x0 + 1]
    c, d = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


SPECS = {
    "accel": "accel:10,12,24,20:30,5:-40,10",
    "path": "path:14,10,20,24:0.3,6,-4;0.7,12,3;1.0,8,8",
    "spin": "spin:40,20,30,30:40",
    "two": "oscillate:6,8,22,18:0,9,1.5+accel:56,40,26,20:-20,0:10,-5",
}


def test_specs_parse_and_round_trip():
    for spec in SPECS.values():
        m = parse_motion(spec)
        assert isinstance(m, Sprites) and not m.is_still
        assert parse_motion(m.spec).spec == m.spec
    assert len(parse_motion(SPECS["two"]).sprites) == 2
    assert parse_motion("translate:1e+1,0").spec == "translate:10,0"  # (+ in a number)
    bad = (
        "accel:1,2,3,4:5,6",  # no acceleration
        "accel:1,2,0,4:5,6:1,1",  # no width
        "path:1,2,3,4:0.5,1,1;0.4,2,2",  # keyframe times must increase
        "path:1,2,3,4:0,1,1",  # (nor start at 0)
        "spin:1,2,3,4",
        "spin:1,2,3,4:x",
        "object:1,2,3,4:5,6+shake:2",  # only rectangles join
        "translate:1,2+object:1,2,3,4:5,6",
    )
    for spec in bad:
        with pytest.raises(InputError):
            parse_motion(spec)


def _expected(sprite, t: float, x0: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """Where the spec says the pixels (x0, y0) of a rectangle are at ``t``, written out
    here apart from stages.motion: (..., 2) px."""
    import cv2

    kind = sprite.spec.partition(":")[0]
    if kind == "spin":  # clockwise-positive in the y-down image, as rotate: renders it
        m = cv2.getRotationMatrix2D(sprite.centre, -sprite.deg_per_s * t, 1.0)
        return np.stack(
            [m[0, 0] * x0 + m[0, 1] * y0 + m[0, 2], m[1, 0] * x0 + m[1, 1] * y0 + m[1, 2]], -1
        )
    if kind == "accel":
        d = (sprite.vx * t + sprite.ax * t * t / 2, sprite.vy * t + sprite.ay * t * t / 2)
    elif kind == "oscillate":
        s = np.sin(2 * np.pi * sprite.hz * t)
        d = (sprite.ax * s, sprite.ay * s)
    else:  # path: checked at its keyframes below; between them the spline's own
        d = sprite.offsets(np.array([t]))[0]
    return np.stack([x0 + d[0], y0 + d[1]], -1)


def test_a_path_goes_through_its_keyframes_and_holds_after_the_last():
    s = parse_motion(SPECS["path"]).sprites[0]
    got = s.offsets(np.array([0.0, 0.3, 0.7, 1.0, 1.4]))
    np.testing.assert_allclose(got, [[0, 0], [6, -4], [12, 3], [8, 8], [8, 8]], atol=1e-12)


@pytest.mark.parametrize("name", sorted(SPECS))
def test_stored_truth_moves_the_scene_onto_the_rendered_frame(tmp_path, name):
    """Simulate, write and read the capture; the truth it stores (TruthPaths) puts each
    inner pixel of a moving rectangle, at a subframe's time, where the renderer (the one
    simulate uses) shows that pixel's t = 0 value; pixels no rectangle ever covers stay
    the scene's, and a pixel a rectangle has left shows the still scene beneath."""
    from stages.formats.capture import read_capture, write_capture
    from stages.rig import RigParams
    from stages.scenes import Scene
    from stages.simulate import simulate

    motion = parse_motion(SPECS[name])
    scene = Scene(_smooth_scene().astype(np.float32), ["Y"], "test:smooth")
    cap = simulate(scene, motion, RigParams(sensor_size=(W, H)), seed=0, measure_bins=2)["vet"]
    path = tmp_path / "c.npz"
    write_capture(path, cap)
    paths = read_capture(path).truth_paths()
    assert paths is not None and paths.front == list(range(len(motion.sprites), 0, -1))
    np.testing.assert_array_equal(paths.labels, motion.labels((H, W)))
    base = scene.radiance[..., 0].astype(np.float64)
    for m in (20, 70, 131):
        t = paths.times[m]
        frame = motion.render(scene.radiance, float(t))[..., 0].astype(np.float64)
        pos = paths.positions(m)
        for k, s in enumerate(motion.sprites, 1):
            inner = np.zeros((H, W), bool)
            inner[s.y + 3 : s.y + s.h - 3, s.x + 3 : s.x + s.w - 3] = True
            if name == "spin":  # (the disc the turning corners never leave)
                yy, xx = np.mgrid[0:H, 0:W]
                cx, cy = s.centre
                inner &= np.hypot(xx - cx, yy - cy) < min(s.w, s.h) / 2 - 2
            yy, xx = np.nonzero(inner)
            want = _expected(s, float(t), xx.astype(float), yy.astype(float))
            np.testing.assert_allclose(pos[inner], want, atol=1e-6)
            got = _bilinear(frame, want[:, 0], want[:, 1])
            assert np.abs(got - base[inner]).max() < 0.01, (name, k, m)
        # Where no rectangle is at t = 0 or at t, the still scene.
        covered = np.zeros((H, W), bool)
        for s in motion.sprites:
            corners = pos[s.y : s.y + s.h, s.x : s.x + s.w].reshape(-1, 2)
            lo, hi = np.floor(corners.min(axis=0)) - 1, np.ceil(corners.max(axis=0)) + 2
            covered[max(int(lo[1]), 0) : int(hi[1]), max(int(lo[0]), 0) : int(hi[0])] = True
            covered[s.y : s.y + s.h, s.x : s.x + s.w] = True
        np.testing.assert_array_equal(frame[~covered], base[~covered])
    if name == "accel":  # the rectangle has left its t = 0 place: the scene beneath shows
        s = motion.sprites[0]
        left = pos[s.y : s.y + s.h, s.x : s.x + 3]  # (its first columns moved right by ~12)
        assert left[..., 0].min() > s.x + 10
        np.testing.assert_array_equal(
            frame[s.y + 2 : s.y + s.h - 2, s.x : s.x + 3],
            base[s.y + 2 : s.y + s.h - 2, s.x : s.x + 3],
        )


def test_true_velocity_at_the_start():
    """truth_motion (the velocity at t = 0): an accelerating rectangle's start velocity,
    a spinning one's omega x (x - centre), zero elsewhere."""
    v = parse_motion(SPECS["accel"]).velocity((H, W))
    np.testing.assert_allclose(v[20, 20], [30, 5], atol=1e-3)
    assert np.all(v[60, 80] == 0)
    spin = parse_motion(SPECS["spin"])
    v = spin.velocity((H, W))
    cx, cy = spin.sprites[0].centre
    w = np.radians(40)
    np.testing.assert_allclose(v[30, 50], [-w * (30 - cy), w * (50 - cx)], rtol=1e-3, atol=1e-4)


def test_a_turning_layer_s_truth_round_trips_and_is_checked():
    """A spin's truth carries anchor and linear (a rotation per time); metadata that
    contradicts itself (linear without anchor, a front that is not the layers) is refused."""
    from stages.formats.schema import TruthTrajectory

    paths = parse_motion(SPECS["spin"]).truth((H, W), np.array([0.0, 0.5, 1.0]))
    meta = paths.meta()
    a = np.radians(40 * 0.5)
    np.testing.assert_allclose(
        meta["linear"][1][1], [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    )
    TruthTrajectory.model_validate(meta)
    for bad in (
        {k: v for k, v in meta.items() if k != "anchor"},
        dict(meta, front=[2]),
        dict(meta, linear=meta["linear"][:1]),
    ):
        with pytest.raises(ValueError):
            TruthTrajectory.model_validate(bad)


@pytest.mark.parametrize(
    "spec, form",
    [
        ("accel:1,2,3,4:5,6", "accel:X,Y,W,H:VX,VY:AX,AY"),
        ("path:1,2,3,4:0.5,1", "path:X,Y,W,H:T1,DX1,DY1"),
        ("spin:1,2,3,4", "spin:X,Y,W,H:DEG_PER_S"),
    ],
)
def test_cli_refuses_a_bad_spec_with_one_line(tmp_path, spec, form):
    r = subprocess.run(
        [sys.executable, "-m", "vet_cli", "simulate", "builtin:chart", "--size", "32x24"]
        + ["--motion", spec, "-o", str(tmp_path / "x.exr")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and form in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("Error: Invalid value for '--motion'")
