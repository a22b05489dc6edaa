"""The blur operator's assembly against a plain reference assembly of the same model.

``_reference_blur_matrix`` builds the operator of :mod:`stages.deblur.operator` the
simplest way: every sample's bilinear corners as one coordinate list, summed into a CSR
matrix by scipy in float64 and rounded once to float32. :func:`stages.deblur.operator.
blur_matrix` assembles it in chunks and sums each row's duplicates on its own; the two
must give the same matrix: the same non-zeros in the same (sorted) order, values equal
up to the order of the float64 sums (at most 1 float32 ulp).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from stages.deblur.assembly import POSITION_STEPS
from stages.deblur.assembly import reflect as _reflect
from stages.deblur.operator import (
    Layers,
    Window,
    _layered_positions,
    blur_matrix,
    motion_layers,
    vet_windows,
)
from stages.deblur.pyramid import block_windows

TF, TAU, K, EPS = 0.99975, 0.00758, 131, 0.002


def _reference_blur_matrix(
    velocity, windows, step_px=1.0, max_samples=64, min_dt=None, layers=None
):
    h, w = velocity.shape[:2]
    n = h * w
    vel = velocity.reshape(n, 2).astype(np.float64)
    by_layer = layers is not None and (len(layers.velocity) > 1 or layers.trajectory is not None)
    speed = np.full(n, layers.max_speed()) if by_layer else np.hypot(vel[:, 0], vel[:, 1])
    rows_l, cols_l, vals_l = [], [], []
    for win in windows:
        a = np.broadcast_to(np.asarray(win.start, np.float64), (h, w)).reshape(-1)
        b = np.broadcast_to(np.asarray(win.end, np.float64), (h, w)).reshape(-1)
        wt = np.broadcast_to(np.asarray(win.weight, np.float64), (h, w)).reshape(-1)
        dur = np.maximum(b - a, 0.0)
        ns = np.ceil(speed * dur / step_px).astype(np.int64)
        if min_dt:
            ns = np.minimum(ns, np.maximum(np.floor(dur / min_dt), 1).astype(np.int64))
        ns = np.clip(ns, 1, max_samples)
        ns[(dur <= 0) | (wt == 0)] = 0
        pix = np.repeat(np.arange(n), ns)
        k = np.arange(len(pix)) - np.repeat(np.cumsum(ns) - ns, ns)
        dt = dur[pix] / ns[pix]
        t = a[pix] + (k + 0.5) * dt
        weight = wt[pix] * dt
        py, px = np.divmod(pix, w)
        if by_layer:
            x, y = _layered_positions(layers, px, py, t, h, w)
        else:
            x = px - vel[pix, 0] * t
            y = py - vel[pix, 1] * t
        x = np.rint(x * POSITION_STEPS) / POSITION_STEPS
        y = np.rint(y * POSITION_STEPS) / POSITION_STEPS
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        for yy, xx, ww in [
            (y0, x0, (1 - fx) * (1 - fy)),
            (y0, x0 + 1, fx * (1 - fy)),
            (y0 + 1, x0, (1 - fx) * fy),
            (y0 + 1, x0 + 1, fx * fy),
        ]:
            ww = ww * weight
            keep = ww > 0
            rows_l.append(pix[keep])
            cols_l.append((_reflect(yy, h) * w + _reflect(xx, w))[keep])
            vals_l.append(ww[keep])
    rows, cols, vals = (np.concatenate(v) for v in (rows_l, cols_l, vals_l))
    A = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    A.sum_duplicates()  # (in float64: the sums rounded once to float32)
    return sp.csr_matrix((A.data.astype(np.float32), A.indices, A.indptr), shape=(n, n))


def _assert_same(A, R):
    assert A.shape == R.shape and A.dtype == np.float32
    np.testing.assert_array_equal(A.indptr, R.indptr)
    np.testing.assert_array_equal(A.indices, R.indices)
    np.testing.assert_allclose(A.data, R.data, rtol=1.2e-7, atol=0)  # (1 ulp)
    assert np.all(A.data > 0)


def _T(rng, h, w):
    return rng.choice([0.004, 0.03, 0.5, 0.99298, TF], (h, w)).astype(np.float32)


def _uniform(h, w, vx, vy):
    v = np.zeros((h, w, 2), np.float32)
    v[..., 0], v[..., 1] = vx, vy
    return v


def _object(h, w):
    v = _uniform(h, w, 0.0, 0.0)
    v[h // 4 : h // 2, w // 4 : w // 2] = (40.0, 10.0)
    return v


CASES = {
    "translate": lambda rng, h, w: _uniform(h, w, 30.0, 0.0),
    "translate-drift": lambda rng, h, w: _uniform(h, w, 30.085, -0.0132),
    "diagonal": lambda rng, h, w: _uniform(h, w, -12.0, 5.0),
    "still": lambda rng, h, w: _uniform(h, w, 0.0, 0.0),
    "dense": lambda rng, h, w: rng.normal(0, 20, (h, w, 2)).astype(np.float32),
    "far": lambda rng, h, w: _uniform(h, w, 130.0, -70.0),  # paths beyond one reflection
    "object": lambda rng, h, w: _object(h, w),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("kind", ["vet", "bins", "blocks"])
def test_operator_equals_the_reference_assembly(case, kind):
    rng = np.random.default_rng(7)
    h, w = 37, 53
    vel = CASES[case](rng, h, w)
    T = _T(rng, h, w)
    if kind == "vet":
        wins, step = vet_windows(T, TF, TAU, K, EPS), 1.0
    elif kind == "bins":
        wins, step = [Window(0.0625 * b, 0.0625 * (b + 1), 0.5) for b in (0, 7, 15)], 1.5
    else:
        wins, step = block_windows(T, TF, EPS), 1.0
        h, w = h // 2, w // 2
        vel = np.ascontiguousarray(vel[: 2 * h : 2, : 2 * w : 2] / 2)
    layers = motion_layers(vel)
    A = blur_matrix(vel, wins, step_px=step, min_dt=TAU, layers=layers)
    _assert_same(A, _reference_blur_matrix(vel, wins, step, min_dt=TAU, layers=layers))
    B = blur_matrix(vel, wins, step_px=step, min_dt=TAU, layers=None)  # per-pixel reading
    _assert_same(B, _reference_blur_matrix(vel, wins, step, min_dt=TAU, layers=None))


def test_operator_along_trajectories_equals_the_reference_assembly():
    rng = np.random.default_rng(8)
    h, w = 41, 47
    label = np.zeros((h, w), np.int32)
    label[10:25, 12:30] = 1
    times = np.linspace(0.0, TF, 9)
    disp = np.zeros((2, 9, 2))
    disp[0, :, 0] = 3.0 * np.sin(7 * times)
    disp[0, :, 1] = 2.5 * np.cos(5 * times) - 2.5
    disp[1, :, 0] = 25.0 * times
    layers = Layers(label, disp[:, -1] / TF, [1], 0, trajectory=(times, disp))
    vel = layers.velocity[label].astype(np.float32)
    for wins in (vet_windows(_T(rng, h, w), TF, TAU, K, EPS), [Window(0.3, 0.36, 0.5)]):
        A = blur_matrix(vel, wins, step_px=0.5, min_dt=TAU, layers=layers)
        _assert_same(A, _reference_blur_matrix(vel, wins, 0.5, min_dt=TAU, layers=layers))


def test_operator_in_many_chunks_equals_the_reference_assembly(monkeypatch):
    import stages.deblur.assembly as asm

    monkeypatch.setattr(asm, "CHUNK_SAMPLES", 97)  # chunks of a few pixels, some of one
    rng = np.random.default_rng(9)
    h, w = 23, 31
    for vel in (_uniform(h, w, 30.0, 0.0), rng.normal(0, 20, (h, w, 2)).astype(np.float32)):
        wins = vet_windows(_T(rng, h, w), TF, TAU, K, EPS)
        A = blur_matrix(vel, wins, min_dt=TAU)
        _assert_same(A, _reference_blur_matrix(vel, wins, min_dt=TAU, layers=motion_layers(vel)))


def _count_stencil_expansions(monkeypatch):
    import stages.deblur.operator as op

    calls = []
    real = op.expand_stencils

    def counted(*args):
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(op, "expand_stencils", counted)
    return calls


@pytest.mark.parametrize("case", ["translate", "translate-drift", "diagonal", "still"])
def test_rows_expanded_from_stencils_equal_the_reference_assembly(case, monkeypatch):
    # A uniform velocity on a frame wide enough that most rows are away from the border:
    # those rows are expanded from one row per exposure pattern.
    calls = _count_stencil_expansions(monkeypatch)
    rng = np.random.default_rng(10)
    h, w = 61, 150
    vel = CASES[case](rng, h, w)
    windows = [
        (vet_windows(_T(rng, h, w), TF, TAU, K, EPS), 1.0),
        ([Window(0.0625 * b, 0.0625 * (b + 1), 0.5) for b in (0, 9)], 1.5),
    ]
    for wins, step in windows:
        A = blur_matrix(vel, wins, step_px=step, min_dt=TAU)
        ref = _reference_blur_matrix(vel, wins, step, min_dt=TAU, layers=motion_layers(vel))
        _assert_same(A, ref)
    assert len(calls) == len(windows)


def test_a_path_on_a_rounding_tie_is_assembled_row_by_row(monkeypatch):
    # 1/32 px/s sampled once at t = 0.5 s: the path ends half a grid step away, where
    # the rounding could go either way with the pixel's coordinate; no stencil is used.
    calls = _count_stencil_expansions(monkeypatch)
    h, w = 12, 20
    vel = _uniform(h, w, 1.0 / 32, 0.0)
    wins = [Window(0.0, 1.0, 1.0)]
    A = blur_matrix(vel, wins)
    _assert_same(A, _reference_blur_matrix(vel, wins, layers=motion_layers(vel)))
    assert not calls


def test_a_fit_bin_sampled_per_subframe_is_the_sum_of_the_simulators_subframes():
    """A measuring bin sums its subframes, each the scene where it was at the
    subframe's mid-time (the simulator's render). Sampled as finely as
    :func:`stages.deblur.problem.bin_step` allows a small frame (one sample per
    subframe), the bin's operator applied to the scene is that sum; one sample at the
    bin's mean position (the spacing large frames keep) is another blur where the
    subframes' positions straddle a pixel edge, off by percent at the texture's edges."""
    from stages.deblur.problem import BIN_STEP_COARSE, bin_step
    from stages.motion import parse_motion
    from stages.scenes import load_scene

    h, w, tau = 48, 64, 0.00758
    scene = load_scene("builtin:chart", (w, h)).radiance[..., :1].astype(np.float32)
    motion = parse_motion("translate:30,0")
    vel = motion.velocity((h, w))
    j0, j1 = 42, 45  # three subframes whose positions straddle a pixel edge (x + 10)
    want = sum(motion.render(scene, (j + 0.5) * tau) for j in range(j0, j1)) * np.float32(tau)
    step = bin_step(30.0, 131 * tau, 60, h * w)
    assert step < 0.25 and bin_step(30.0, 131 * tau, 16, 1280 * 1024) == BIN_STEP_COARSE
    win = [Window(j0 * tau, j1 * tau, 1.0)]
    inner = (slice(None), slice(4, -4))

    def error(spacing: float) -> float:
        A = blur_matrix(vel, win, step_px=spacing, min_dt=tau)
        got = (A @ scene.reshape(-1)).reshape(h, w)
        return float(np.abs(got - want[..., 0])[inner].max() / want.max())

    assert error(step) < 5e-3  # (0.2%: OpenCV's fixed-point warps against float64 weights)
    assert error(BIN_STEP_COARSE) > 3e-2  # (7.8%)


def test_deblur_samples_its_fit_bins_as_finely_as_the_frame_allows(monkeypatch):
    """deblur builds the bins' operators at the spacing bin_step gives its frame (a small
    frame: finer than a quarter pixel), and a tile at its frame's, not its own; the VET
    image's at vet_step's (finely along a camera path only)."""
    import stages.deblur.joint as joint
    from stages.deblur import deblur
    from stages.deblur.problem import VET_STEP_COARSE
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    seen: list[float] = []
    seen_vet: list[float] = []
    build = joint.build_operators

    def spy(*args, **kwargs):
        seen.append(kwargs["step_px_bins"])
        seen_vet.append(kwargs["step_px"])
        return build(*args, **kwargs)

    monkeypatch.setattr(joint, "build_operators", spy)
    scene = load_scene("builtin:chart", (160, 48))
    rig = RigParams(sensor_size=(160, 48))
    cap = simulate(scene, parse_motion("translate:30,0"), rig, seed=0)
    deblur(cap["vet"], motion_init="truth")
    assert seen and max(seen) < 0.25
    assert seen_vet and set(seen_vet) == {VET_STEP_COARSE}  # (no camera path: vet_step)
    seen.clear()
    deblur(cap["vet"], motion_init="truth", tile=64)
    assert seen and max(seen) < 0.25
    # Along a camera path the VET image's operator is sampled finely too.
    seen_vet.clear()
    shaken = simulate(scene, parse_motion("shake:4"), rig, seed=0, methods=["vet"])["vet"]
    deblur(shaken, motion_init="truth")
    assert seen_vet and max(seen_vet) < 0.25


def test_vet_step_is_fine_on_small_frames_and_coarse_on_large_ones():
    """vet_step along a camera path: 30 px of travel samples a 320x240 frame's VET image
    at the fit bins' finest spacing, keeps 1 px on a 1280x1024 frame (the sample budget),
    and a still frame at the finest (no samples to spend); off a path, 1 px."""
    from stages.deblur.problem import BIN_STEP_FINE, VET_STEP_COARSE, vet_step

    assert vet_step(30.0, 1.0, 320 * 240, True) == BIN_STEP_FINE
    assert vet_step(30.0, 1.0, 1280 * 1024, True) == VET_STEP_COARSE
    assert vet_step(0.0, 1.0, 1280 * 1024, True) == BIN_STEP_FINE
    assert BIN_STEP_FINE < vet_step(30.0, 1.0, 640 * 512, True) < VET_STEP_COARSE
    # Not along a camera path: the coarse spacing whatever the frame.
    assert vet_step(30.0, 1.0, 320 * 240, False) == VET_STEP_COARSE


def test_trajectory_sum_is_the_weighted_bilinear_gather_of_every_channel():
    """Five channels (a group of four and one, each remapped exactly): each pixel's
    weighted sum of its channel values at ``x - u t_s``, against scipy's interpolation
    with the same border (half-sample reflection)."""
    from scipy.ndimage import map_coordinates

    from stages.deblur.operator import trajectory_sum

    rng = np.random.default_rng(5)
    h, w, k = 20, 24, 5
    images = rng.random((h, w, k)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    velocity = np.stack([40 + 30 * np.sin(yy / 5), -25 + 20 * np.cos(xx / 7)], axis=-1)
    times = np.array([0.01, 0.04, 0.09])
    weights = rng.random((3, h, w))
    got = trajectory_sum(images, velocity.astype(np.float32), times, weights)
    want = np.zeros((h, w, k))
    for s, t in enumerate(times):
        coords = [yy - velocity[..., 1] * t, xx - velocity[..., 0] * t]
        for ch in range(k):
            want[..., ch] += weights[s] * map_coordinates(
                images[..., ch].astype(np.float64), coords, order=1, mode="reflect"
            )
    assert got.shape == (h, w, k) and got.dtype == np.float32
    assert np.abs(got - want).max() < 1e-4


def test_stencil_rows_expanded_for_some_rows_are_those_rows_of_the_matrix():
    # expand_stencils(rows=...) makes the rows asked for alone: the same entries as
    # those rows of the whole matrix (generic rows without entries may be left out).
    from stages.deblur.assembly import expand_stencils

    n = 12
    generic = (
        np.array([0, 3, 7]),  # rows (row 3 has no entries)
        np.array([2, 0, 1]),
        np.array([1, 5, 7], np.int32),
        np.array([0.5, 0.25, 1.0], np.float32),
    )
    stencil = (
        np.array([4, 5, 9, 10]),  # rows, in two groups
        np.array([0, 1, 0, 1]),
        np.array([4, 5]),  # each group's representative
        np.array([2, 1]),
        np.array([3, 5, 6], np.int32),  # the representatives' columns: 4 - 1, 4 + 1, 5 + 1
        np.array([0.125, 0.375, 2.0], np.float32),
    )
    full = expand_stencils(n, generic, stencil)
    rows = np.array([0, 4, 5, 7, 9, 10])
    part = expand_stencils(n, generic, stencil, rows=rows)
    assert part.shape == (rows.size, n)
    assert (part != full[rows]).nnz == 0
    np.testing.assert_array_equal(part.indptr, full[rows].indptr)
    np.testing.assert_array_equal(full[9].indices, [8, 10])  # (row 9 reads 4's, moved by 5)
