"""The coarse level of the deblur's coarse-to-fine solve (stages.deblur.pyramid)."""

from __future__ import annotations

import numpy as np

from stages.deblur.operator import apply, blur_matrix, vet_windows
from stages.deblur.problem import observations
from stages.deblur.pyramid import block_sum, block_windows, coarsen, restrict_mean
from tests.test_deblur import _capture

TF, TAU, K, EPS = 0.99975, 0.00758, 131, 0.002


def _fine_then_sum(vel, T, x_coarse):
    """Block sums of the fine operator applied to the piecewise-constant prolongation."""
    fine = np.repeat(np.repeat(x_coarse, 2, axis=0), 2, axis=1)
    A = blur_matrix(vel, vet_windows(T, TF, TAU, K, EPS))
    return block_sum(apply(A, fine))


def test_block_row_is_the_sum_of_its_children_rows_when_still():
    rng = np.random.default_rng(0)
    h, w = 24, 32
    T = rng.choice([0.03, 0.2, 0.5, TF], (h, w)).astype(np.float32)
    x = rng.random((h // 2, w // 2, 2))
    Ac = blur_matrix(np.zeros((h // 2, w // 2, 2), np.float32), block_windows(T, TF, EPS))
    fine = _fine_then_sum(np.zeros((h, w, 2), np.float32), T, x)
    np.testing.assert_allclose(apply(Ac, x), fine, rtol=1e-5)


def test_block_row_matches_its_children_under_motion_up_to_sub_block_offsets():
    rng = np.random.default_rng(1)
    h, w = 48, 64
    T = rng.choice([0.03, 0.2, 0.5, TF], (h, w)).astype(np.float32)
    x = np.repeat(np.repeat(rng.random((h // 4, w // 4, 1)), 2, 0), 2, 1)  # smooth-ish
    vel = np.zeros((h, w, 2), np.float32)
    vel[..., 0] = 12.0
    Ac = blur_matrix(vel[::2, ::2] / 2, block_windows(T, TF, EPS))
    coarse = apply(Ac, x)
    fine = _fine_then_sum(vel, T, x)
    inner = (slice(2, -2), slice(4, -4))
    rel = np.abs(coarse - fine)[inner] / fine[inner]
    assert np.median(rel) < 0.05


def test_coarsened_data_add_and_their_variances_add():
    w, h = 40, 32
    cap = _capture("translate:30,0", w, h, seed=0)
    obs = observations(cap)
    cobs, t_c = coarsen(obs, cap.T, cap.rig.frame_s, cap.rig.leakage)
    assert cobs.shape == (h // 2, w // 2, 3)
    y = obs.y.reshape(h, w, 3)
    np.testing.assert_allclose(cobs.y.reshape(h // 2, w // 2, 3), block_sum(y), rtol=1e-6)
    with np.errstate(divide="ignore"):
        var = 1 / obs.w.reshape(h, w, 3)  # inf where saturated: the block has no weight
    ok = cobs.w.reshape(h // 2, w // 2, 3) > 0
    np.testing.assert_allclose(
        1 / cobs.w.reshape(h // 2, w // 2, 3)[ok], block_sum(var)[ok], rtol=1e-6
    )
    np.testing.assert_allclose(t_c, restrict_mean(cap.T), rtol=1e-6)
    assert len(cobs.windows_b) == len(obs.windows_b)


def test_coarse_level_gives_the_fine_solve_a_better_start():
    # Five fine CG iterations from the coarse level's start beat five from hdr-static.
    from stages.deblur import deblur
    from stages.deblur.joint import JointOptions
    from stages.metrics import stops_error

    cap = _capture("translate:30,0", 128, 96, seed=0)

    def dark_rms(levels: int) -> float:
        opts = JointOptions(outer=0, final_cg_iters=5, levels=levels)
        img, _ = deblur(cap, "vet", motion_init="truth", options=opts)
        return stops_error(img.radiance, cap.truth, cap.T, cap.rig.frame_s)["dark"]["rms"]

    assert dark_rms(1) < 0.9 * dark_rms(0)


def test_block_sum_adds_each_blocks_children_in_row_major_order():
    rng = np.random.default_rng(2)
    a = rng.random((7, 9, 3)) * 1e6  # (odd: the last row and column are dropped)
    want = np.empty((3, 4, 3))
    for i in range(3):
        for j in range(4):
            b = a[2 * i : 2 * i + 2, 2 * j : 2 * j + 2]
            want[i, j] = ((b[0, 0] + b[0, 1]) + b[1, 0]) + b[1, 1]
    got = block_sum(a)
    assert got.dtype == np.float64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    # Booleans are counted, not or-ed.
    mask = np.array([[True, True, False], [True, False, False]])
    np.testing.assert_array_equal(block_sum(mask), [[3]])
    assert block_sum(np.ones((4, 4), np.float32)).dtype == np.float32
