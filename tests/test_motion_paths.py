"""Motions whose velocity changes within the frame (shake, oscillate): their rendering,
their stored truth, the deblur's oracle along them and the paths it measures."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from stages.errors import InputError
from stages.motion import Oscillate, Shake, parse_motion, trajectory_times


@pytest.fixture
def sixteen_fit_bins(monkeypatch):
    """The deblur fits 16 time bins whatever the motion: these tests are about the paths
    (measured, refined, in tiles), their figures were taken with 16, and a shake's speed
    would otherwise take 64 at four times the cost (the bins a motion needs are tested in
    tests/test_deblur_stream.py)."""
    import stages.deblur.problem as problem

    monkeypatch.setattr(problem, "FIT_BINS_MAX", problem.FIT_BINS)


def _shaken(scene: str = "builtin:interior", size: tuple[int, int] = (256, 192)):
    """``scene`` at ``size`` under shake:4 (seed 0, the default rig), keeping its stream,
    and a function giving an image's all-pixel RMS error in stops against its truth."""
    from stages.metrics import measurable_floor, stops_error
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    rig = RigParams(sensor_size=size)
    cap = simulate(load_scene(scene, size), parse_motion("shake:4"), rig, seed=0)["vet"]
    floor = measurable_floor(rig, cap.radiance_scale)

    def rms(img):
        return stops_error(img, cap.truth, cap.T, rig.frame_s, floor=floor)["all"]["rms"]

    return cap, rms


def test_specs_parse_and_round_trip():
    assert parse_motion("shake:3").spec == "shake:3,0"
    assert parse_motion("shake:3,7") == Shake(3.0, 7)
    assert parse_motion("oscillate:1,2,30,40:5,-2") == Oscillate(1, 2, 30, 40, 5.0, -2.0, 1.0)
    assert parse_motion("oscillate:1,2,30,40:5,-2,2.5").spec == "oscillate:1,2,30,40:5,-2,2.5"
    for bad in ("shake:-1", "shake:1,0.5", "oscillate:1,2,0,4:5,0", "oscillate:1,2,3,4", "shake:x"):
        with pytest.raises(InputError):
            parse_motion(bad)


def test_shake_path_starts_at_zero_with_the_stated_rms():
    m = Shake(4.0, 1)
    t = np.linspace(0, 1, 201)
    d = m.offsets(t)[0]
    assert np.allclose(d[0], 0)
    assert abs(np.sqrt(np.mean(np.sum(d**2, axis=1))) - 4.0) < 1e-9
    # The velocity changes within the frame: no constant velocity explains the path.
    v = (d * t[:, None]).sum(axis=0) / (t * t).sum()
    assert np.abs(d - v * t[:, None]).max() > 2.0


def test_oscillate_renders_the_object_at_its_displacement():
    rng = np.random.default_rng(0)
    scene = rng.random((40, 60, 1)).astype(np.float32)
    m = Oscillate(10, 10, 20, 15, 4.0, 0.0, 1.0)
    out = m.render(scene, 0.25)  # sin(pi/2) = 1: the object 4 px to the right
    np.testing.assert_allclose(out[12:20, 16:30, 0], scene[12:20, 12:26, 0], atol=1e-5)
    np.testing.assert_allclose(out[30:, :, 0], scene[30:, :, 0])  # the rest stays
    v = m.velocity((40, 60))
    assert np.allclose(v[12, 12], [2 * np.pi * 4.0, 0.0], rtol=1e-3)
    assert np.allclose(v[0, 0], 0)


def test_simulated_truth_trajectory_round_trips_through_files(tmp_path):
    from stages.deblur import truth_layers
    from stages.formats.capture import read_capture, write_capture
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (80, 64))
    rig = RigParams(sensor_size=(80, 64))
    m = Oscillate(20, 16, 30, 20, 6.0, 2.0)
    cap = simulate(scene, m, rig, seed=0, measure_bins=4)["vet"]
    for ext in ("exr", "npz"):
        path = tmp_path / f"c.{ext}"
        write_capture(path, cap)
        back = read_capture(path)
        np.testing.assert_array_equal(back.truth_layers, m.labels((64, 80)))
        layers = truth_layers(back)
        times = trajectory_times(rig.frame_s, rig.subframe_s, rig.n_subframes)
        np.testing.assert_allclose(layers.displacement(times[5])[1], m.offsets(times[5:6])[1, 0])
        assert layers.front == [1] and layers.background == 0


def test_deblur_oracle_follows_the_path():
    """The oracle along the true path beats hdr-static on an oscillating object, and
    fitting a constant velocity instead (the path's mean) does worse than the path."""
    from stages.deblur import deblur
    from stages.hdr_static import hdr_static
    from stages.metrics import measurable_floor, stops_error
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (160, 128))
    rig = RigParams(sensor_size=(160, 128))
    m = parse_motion("oscillate:40,30,80,60:12,0")
    cap = simulate(scene, m, rig, seed=0, measure_bins=rig.n_subframes)["vet"]
    floor = measurable_floor(rig, cap.radiance_scale)

    def rms(img):
        return stops_error(img, cap.truth, cap.T, rig.frame_s, floor=floor)["all"]["rms"]

    oracle, _ = deblur(cap, motion_init="truth")
    assert rms(oracle.radiance) < rms(hdr_static(cap).radiance)


def test_paths_are_measured_on_a_shaken_capture():
    """The tile registration of the stream finds the shake's path (to a pixel) and says
    the motion changes; a constant translation is left to the layered estimate."""
    from stages.deblur.layers.paths import tile_paths
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (256, 192))
    rig = RigParams(sensor_size=(256, 192))
    for spec, changing in (("shake:4", True), ("translate:20,0", False)):
        m = parse_motion(spec)
        cap = simulate(scene, m, rig, seed=0, measure_bins=rig.n_subframes)["vet"]
        tp = tile_paths(cap.measure, cap.measure_times, rig)
        assert tp.changing is changing, spec
        if changing:
            truth = m.offsets(tp.mids)[0]
            got = tp.layer_paths[0] + truth[0]  # (paths are measured from group 0)
            assert np.sqrt(np.mean(np.sum((got - truth) ** 2, axis=1))) < 1.0


def test_cli_simulates_a_shake(tmp_path):
    out = tmp_path / "s.exr"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "vet_cli",
            "simulate",
            "builtin:interior",
            "--size",
            "64x48",
            "--motion",
            "shake:2",
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "vet_cli",
            "simulate",
            "builtin:interior",
            "--size",
            "64x48",
            "--motion",
            "oscillate:1,2",
            "-o",
            str(tmp_path / "x.exr"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "oscillate:X,Y,W,H:AX,AY[,HZ]" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("Error: Invalid value for '--motion'")


@pytest.mark.usefixtures("sixteen_fit_bins")
def test_default_deblur_follows_a_camera_shake():
    """A shaken capture that keeps its stream: the default deblur measures the path most
    of the frame follows and deblurs along it (model ``layer-paths``), closer to the truth
    than hdr-static and than the constant-velocity layers of the same data in time bins;
    a constant-velocity object (whose edge tiles once set the path detector off) is left
    to the layered estimate."""
    from stages.deblur import deblur
    from stages.deblur.layers.paths import tile_paths
    from stages.hdr_static import hdr_static
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    cap, rms = _shaken()
    img, _ = deblur(cap)
    assert img.meta["motion_model"] == "layer-paths"
    # The path sampled finely (48 groups of 2-3 subframes) comes within 7% of the oracle
    # along the true path (1.05x; 16 groups of 8 subframes gave 1.10x).
    oracle, _ = deblur(cap, motion_init="truth")
    assert rms(img.radiance) < 1.07 * rms(oracle.radiance)
    binned, _ = deblur(cap.time_bins(8))
    assert binned.meta["motion_model"] != "layer-paths"
    assert rms(img.radiance) < 0.8 * rms(binned.radiance)
    assert rms(img.radiance) < 0.8 * rms(hdr_static(cap).radiance)

    chart = load_scene("builtin:chart", (160, 128))
    rig = RigParams(sensor_size=(160, 128))
    obj = simulate(chart, parse_motion("object:40,32,80,64:40,10"), rig, seed=0)["vet"]
    tp = tile_paths(obj.measure, obj.measure_times, rig)
    assert not tp.main_changing
    assert deblur(obj)[0].meta["motion_model"] == "layers"


@pytest.mark.usefixtures("sixteen_fit_bins")
def test_the_measured_camera_path_is_refined_on_the_misfit(shared_hdr):
    """The path registered from the stream carries each group's noise and an offset of
    its anchor D(0) (the extrapolation to t = 0); Gauss-Newton steps on its knots, D(0)
    included, between image steps bring the deblur closer to the oracle's: Cannon
    shake:4 at 240x180, the refined path's all-pixel RMS under 0.75x the measured one's."""
    from stages.deblur import deblur
    from stages.deblur.joint import JointOptions

    cap, rms = _shaken(str(shared_hdr / "Cannon.exr"), (240, 180))
    refined, _ = deblur(cap)
    measured, _ = deblur(cap, options=JointOptions(path_motion=False))
    assert refined.meta["motion_model"] == measured.meta["motion_model"] == "layer-paths"
    assert rms(refined.radiance) < 0.75 * rms(measured.radiance)


@pytest.mark.slow
def test_the_camera_path_s_anchor_follows_the_early_samples(shared_hdr):
    """The anchor D(0) is fitted to the early samples under a prior as wide as the start's
    extrapolation errs (ANCHOR_PX): Cannon shake:4 at 320x240 comes within 1.2x of the
    oracle's all-pixel RMS (a prior of 0.05 px held it at 1.37x)."""
    from stages.deblur import deblur

    cap, rms = _shaken(str(shared_hdr / "Cannon.exr"), (320, 240))
    got, _ = deblur(cap)
    oracle, _ = deblur(cap, motion_init="truth")
    assert got.meta["motion_model"] == "layer-paths"
    assert rms(got.radiance) < 1.2 * rms(oracle.radiance)


def test_paths_are_measured_without_holding_every_group():
    """The stream's groups are made one at a time as they are registered, and the
    layers' spread of the pulled-back groups comes from running sums: neither the tile
    registration nor the layers hold GROUPS frames beside the stream (each held all 48,
    and the layers 48 more per path)."""
    import tracemalloc

    from stages.deblur.layers.paths import GROUPS, path_layers, tile_paths

    cap, _ = _shaken()
    frame = cap.shape[0] * cap.shape[1] * 4  # (one float32 frame)

    def added(fn):
        tracemalloc.start()
        try:
            out = fn()
            return out, tracemalloc.get_traced_memory()[1] / frame
        finally:
            tracemalloc.stop()

    tp, reg = added(lambda: tile_paths(cap.measure, cap.measure_times, cap.rig))
    layers, lay = added(lambda: path_layers(tp, cap.rig.frame_s))
    assert layers is not None and len(tp.groups) == GROUPS
    assert reg < GROUPS and lay < GROUPS / 2, (reg, lay)


def test_path_search_keeps_the_best_state_and_shortens_after_a_worse_one():
    """PathSearch: a state is kept while its misfit is the lowest so far; a worse one
    brings back the best (image, path, residuals) and halves the next path step."""
    from stages.deblur.path_steps import REJECT_SHRINK, PathSearch, robust_misfit

    search = PathSearch()
    a = search.keep_best(10.0, "L1", "P1", "r1", "b1")
    assert a == ("L1", "P1", "r1", "b1", True) and search.gain == 1.0
    b = search.keep_best(8.0, "L2", "P2", "r2", "b2")
    assert b[-1] and search.gain == 1.0
    c = search.keep_best(9.0, "L3", "P3", "r3", "b3")
    assert c == ("L2", "P2", "r2", "b2", False) and search.gain == REJECT_SHRINK
    d = search.keep_best(8.5, "L4", "P4", "r4", "b4")
    assert d[:2] == ("L2", "P2") and search.gain == REJECT_SHRINK**2
    # The Cauchy misfit: k^2 log(1 + w r^2 / k^2), VET and bins summed.
    r, w = np.array([[2.0]]), np.array([[1.0]])
    want = 4.0 * np.log(2.0)
    assert robust_misfit(r, w, None, None, 2.0) == pytest.approx(want)
    assert robust_misfit(r, w, r.astype(np.float32), w, 2.0) == pytest.approx(2 * want)


def test_anchor_image_moves_the_image_by_the_anchor():
    """anchor_image(L, d0) is L(y - d0): a smooth pattern moved by a known subpixel shift
    matches the pattern evaluated at the shifted coordinates (a cubic spline: within
    1e-4 of 2, away from the border)."""
    from stages.deblur.path_steps import anchor_image

    h, w = 40, 48
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def pattern(x, y):
        return 2.0 + np.sin(0.3 * x) * np.cos(0.25 * y)

    d0 = np.array([0.3, -0.2])
    L = np.stack([pattern(xx, yy), 3 * pattern(xx, yy)], -1).reshape(h * w, 2)
    moved = anchor_image(L, (h, w, 2), d0).reshape(h, w, 2)
    want = pattern(xx - d0[0], yy - d0[1])
    inner = (slice(10, -10), slice(10, -10))
    assert np.abs(moved[..., 0][inner] - want[inner]).max() < 1e-4
    assert np.abs(moved[..., 1][inner] - 3 * want[inner]).max() < 3e-4


@pytest.mark.slow
@pytest.mark.usefixtures("sixteen_fit_bins")
def test_tiles_follow_the_measured_camera_path():
    """A shaken capture solved in tiles: each tile deblurs along its crop of the frame's
    measured path (model ``layer-paths``, halo covering the path's farthest excursion),
    close to the one-piece solve and far from hdr-static; the stream is let go of once
    the tiles' bins are made, and the bins made once for all tiles give what each tile
    would bin from its own crop of the stream."""
    from stages.deblur import deblur
    from stages.hdr_static import hdr_static

    cap, rms = _shaken()
    whole, _ = deblur(cap)
    kept, _ = deblur(cap, tile=96)
    assert kept.meta["motion_model"] == "layer-paths"
    assert kept.meta["tiles"]["count"] == 6
    assert rms(kept.radiance) < 1.15 * rms(whole.radiance)
    assert rms(kept.radiance) < 0.8 * rms(hdr_static(cap).radiance)
    released, _ = deblur(cap, tile=96, release_stream=True)
    assert cap.measure is None
    np.testing.assert_array_equal(released.radiance, kept.radiance)


def test_tile_paths_group_into_the_layers_paths_largest_first():
    """``_cluster``: tiles' paths scattered 0.3 px about three paths (600, 300, 150 tiles)
    among 200 wanderers come back as those three paths, largest first, each within
    0.15 px; a group under MIN_PATH_SHARE of the tiles (30 of 1280) is no layer."""
    from stages.deblur.layers.paths import _cluster

    rng = np.random.default_rng(4)
    g = 48
    truth = [np.cumsum(rng.normal(size=(g, 2)), axis=0) for _ in range(4)]
    sizes = [600, 300, 150, 30]
    parts = [
        p[None] + rng.normal(scale=0.3, size=(n, g, 2)) for p, n in zip(truth, sizes, strict=True)
    ]
    parts.append(rng.normal(scale=6.0, size=(200, g, 2)))
    tiles = np.concatenate(parts)[rng.permutation(sum(sizes) + 200)]
    found = _cluster(tiles)
    assert len(found) == 3
    for path, want in zip(found, truth[:3], strict=True):
        assert np.abs(path - want).max() < 0.15
