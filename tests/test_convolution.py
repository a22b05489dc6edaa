"""Measuring bins' operators as shifted convolutions (stages.deblur.convolution): the
split reproduces the sparse operator exactly, its adjoint passes the dot-product test,
and the deblur's stacked bins and the VET image's row blocks give the same products."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from stages.deblur.convolution import ConvolutionSplit
from stages.deblur.operator import Window, blur_matrix
from stages.deblur.stacked import StackedOperator, row_blocks

H, W = 40, 56


def _translate(v=(30.0, 4.0)) -> np.ndarray:
    vel = np.zeros((H, W, 2), np.float32)
    vel[...] = v
    return vel


def _object(v=(12.0, -5.0)) -> np.ndarray:
    """A still background with a moving rectangle (two layers, half the pixels each)."""
    vel = np.zeros((H, W, 2), np.float32)
    vel[6:34, 8:48] = v
    return vel


def _bin(vel: np.ndarray, t0: float = 0.3, t1: float = 0.4, step: float = 0.5):
    return blur_matrix(vel, [Window(t0, t1, 1.0)], step_px=step)


def _rand(seed: int, n: int = H * W) -> np.ndarray:
    return np.random.default_rng(seed).random(n).astype(np.float32)


@pytest.mark.parametrize("compress", [0.5, 0.0])
@pytest.mark.parametrize("vel", [_translate(), _translate((-17.0, 9.5)), _object()])
def test_split_reproduces_the_operator_and_its_adjoint(vel, compress, monkeypatch):
    # (compress 0: the other rows kept on all the columns, as where they read most.)
    from stages.deblur import convolution

    monkeypatch.setattr(convolution, "COMPRESS_BELOW", compress)
    M = _bin(vel)
    S = ConvolutionSplit.of(M, (H, W))
    assert S is not None and S.rest.size
    assert (S.cols is None) == (compress == 0.0)
    x, y, wt = _rand(0), _rand(1), _rand(2)
    np.testing.assert_allclose(S.apply(x.reshape(H, W)), M @ x, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(S.adjoint(y).ravel(), M.T @ y, rtol=1e-5, atol=1e-7)
    out = np.zeros((H, W), np.float32)
    S.normal(x.reshape(H, W), S.weights(wt), out)
    np.testing.assert_allclose(out.ravel(), M.T @ (wt * (M @ x)), rtol=1e-5, atol=1e-7)
    # Dot-product test of the split's own pair.
    lhs = float(np.dot(S.apply(x.reshape(H, W)).astype(np.float64), y))
    rhs = float(np.dot(x.astype(np.float64), S.adjoint(y).ravel()))
    assert abs(lhs - rhs) <= 1e-6 * abs(lhs)


def test_kernels_take_the_layers_inside_and_leave_the_border_and_boundaries():
    M = _bin(_object())
    S = ConvolutionSplit.of(M, (H, W))
    # The still background (a one-tap stencil) and the moving rectangle.
    assert len(S.kernels) == 2
    taps = [k for k in S.kernels if k.tap is not None]
    assert len(taps) == 1 and taps[0].shift == (0, 0)
    moving = next(k for k in S.kernels if k.tap is None)
    assert moving.mask[12:28, 16:40].all()  # the rectangle's inside
    # Rows near its edges (where the layers meet) are the sparse rest.
    rest = np.zeros(H * W, bool)
    rest[S.rest] = True
    assert rest.reshape(H, W)[6:34, 8:48].any()
    assert not rest.reshape(H, W)[:3].any()  # the still background far from it


def test_rows_whose_stencil_leaves_the_image_stay_sparse():
    # The scene moves 8 px to the left over the bin, so a pixel sees the scene up to 8 px
    # to its right: the last columns' samples are reflected at the border, so their rows
    # are not the kernel's.
    M = _bin(_translate((-80.0, 0.0)), 0.0, 0.1)
    S = ConvolutionSplit.of(M, (H, W))
    rest = np.zeros(H * W, bool)
    rest[S.rest] = True
    assert rest.reshape(H, W)[:, -8:].all()
    assert not rest.reshape(H, W)[:, 2:-10].any()


def test_a_whole_pixel_shift_is_one_tap():
    M = _bin(_translate((20.0, -10.0)), 0.2, 0.2 + 1e-4, step=1.0)  # (4, -2) px
    S = ConvolutionSplit.of(M, (H, W))
    assert [k.tap is not None for k in S.kernels] == [True]
    x, wt = _rand(3), _rand(4)
    out = np.zeros((H, W), np.float32)
    S.normal(x.reshape(H, W), S.weights(wt), out)
    np.testing.assert_allclose(out.ravel(), M.T @ (wt * (M @ x)), rtol=1e-5, atol=1e-7)


def test_an_operator_without_a_common_stencil_is_not_split():
    rng = np.random.default_rng(5)
    M = sp.random(H * W, H * W, density=3 / (H * W), format="csr", random_state=rng)
    M.sum_duplicates()
    assert ConvolutionSplit.of(M.astype(np.float32), (H, W)) is None
    # Nor one whose shape is not the image's.
    assert ConvolutionSplit.of(_bin(_translate()), (W, H + 1)) is None


def test_stacked_bins_normal_product_matches_the_sparse_one():
    vel = _object()
    parts = [_bin(vel, t, t + 0.06) for t in np.arange(0.0, 0.6, 0.06)]
    split = StackedOperator(parts, image_shape=(H, W))
    plain = StackedOperator(parts)
    assert all(g is not None for g in split.splits)
    assert all(g is None for g in plain.splits)
    n = H * W
    x = np.stack([_rand(6), _rand(7)], 1)
    w = np.random.default_rng(8).random((len(parts) * n, 2))
    for _ in range(2):  # (then the same array's values changed: weights made anew)
        split_w = split.split_weights(w)
        assert plain.split_weights(w).groups == [None] * len(plain.groups)
        for c in range(2):
            xc = np.ascontiguousarray(x[:, c])
            want = sum(plain.normal_column(g, xc, w, c) for g in range(len(plain.groups)))
            for given in (split_w, None):
                got = sum(split.normal_column(g, xc, w, c, given) for g in range(len(split.groups)))
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
        w *= np.random.default_rng(9).random(w.shape)


def test_row_blocks_share_the_matrix_and_sum_to_its_normal_product():
    A = blur_matrix(_translate(), [Window(0.0, 1.0, 1.0)], step_px=1.0)
    x, w = _rand(10), _rand(11, A.shape[0])
    blocks = row_blocks(A, 3)
    assert [b[2] for b in blocks][0] == 0 and blocks[-1][3] == A.shape[0]
    assert all(np.shares_memory(B.data, A.data) for B, *_ in blocks)
    got = sum(BT @ (w[r0:r1] * (B @ x)) for B, BT, r0, r1 in blocks)
    np.testing.assert_allclose(got, A.T @ (w * (A @ x)), rtol=1e-5, atol=1e-6)


def test_vet_image_operator_splits_along_its_assembly_stencils():
    # Exposure times in three groups: the assembly's stencil groups become the kernels
    # (one per exposure time), with or without its plan (read from the rows then).
    from stages.deblur.operator import vet_windows

    h, w = 48, 80
    vel = np.zeros((h, w, 2), np.float32)
    vel[...] = (12.0, 3.0)
    T = np.full((h, w), 0.8)
    T[:, :10] = 0.2
    T[30:] = 1.0
    A = blur_matrix(vel, vet_windows(T, 1.0, 1 / 131, 131, 0.01), step_px=1.0, min_dt=1 / 131)
    assert hasattr(A, "stencils")
    x, wt = _rand(12, h * w), _rand(13, h * w)
    want = A.T @ (wt * (A @ x))
    for M in (A, sp.csr_matrix(A)):  # (a copy has no plan)
        S = ConvolutionSplit.of(M, (h, w))
        assert len(S.kernels) == 2  # (the 0.2 s group is under a kernel's share)
        # 12 x 3 px of travel over the frame: 13 columns and 4 rows of bilinear taps.
        assert all(k.small.shape == (4, 13) and k.shift == (-3, -12) for k in S.kernels)
        out = np.zeros((h, w), np.float32)
        S.normal(x.reshape(h, w), S.weights(wt), out)
        np.testing.assert_allclose(out.ravel(), want, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(S.apply(x.reshape(h, w)), A @ x, rtol=1e-5, atol=1e-7)
    # Without its assembly's plan and not asked to search the rows: not split.
    assert ConvolutionSplit.of(sp.csr_matrix(A), (h, w), detect=False) is None
    assert ConvolutionSplit.of(A, (h, w), detect=False) is not None


def test_a_kernel_too_large_for_a_direct_filter_leaves_its_rows_sparse():
    # A long diagonal path: a kernel of over MAX_KERNEL_AREA taps' extent.
    from stages.deblur.convolution import MAX_KERNEL_AREA

    M = _bin(_translate((60.0, 60.0)), 0.0, 0.2)  # 12 x 12 px
    assert ConvolutionSplit.of(M, (H, W)) is None
    assert 13 * 13 > MAX_KERNEL_AREA


def test_a_kernel_is_taken_only_where_it_saves_more_than_its_passes_cost():
    from stages.deblur.convolution import _worth

    n = 10_000
    one_tap, three = np.ones((1, 1), np.float32), np.ones((1, 3), np.float32)
    # A one-tap stencil costs one pass: worth it over a quarter of the rows.
    assert _worth(3000, 1, one_tap, n) and not _worth(2000, 1, one_tap, n)
    # A three-tap stencil of three entries costs four passes and its taps: worth it
    # over two fifths of the rows.
    assert _worth(4500, 3, three, n) and not _worth(3500, 3, three, n)
    # The VET image's long rows pay for their 32 taps over a tenth of them.
    long = np.ones((1, 32), np.float32)
    assert _worth(1100, 32, long, n) and not _worth(900, 32, long, n)


def test_stacked_bins_release_their_parts_once_stacked():
    parts = [_bin(_translate(), t, t + 0.05) for t in (0.0, 0.05, 0.1)]
    want = [P.copy() for P in parts]
    S = StackedOperator(parts, image_shape=(H, W), release=True)
    assert parts == [None, None, None]  # (each part's stack holds its rows)
    x = _rand(14)
    np.testing.assert_allclose(S.mv(x[:, None])[:, 0], np.concatenate([P @ x for P in want]))


def test_opencv_single_threaded_restores_the_thread_count():
    import cv2

    from stages.cluster import opencv_single_threaded

    before = cv2.getNumThreads()
    with opencv_single_threaded():
        assert cv2.getNumThreads() == 1
    assert cv2.getNumThreads() == before


@pytest.mark.parametrize("vel", [_translate(), _translate((-17.0, 9.5)), _translate((0.0, 0.0))])
def test_a_bins_split_made_from_its_plan_is_the_matrix_split(vel):
    # With the image's shape, a bin's operator comes as its split, the matrix never made:
    # the same kernels, the same other rows, the same products as the split of the matrix.
    M = _bin(vel)
    want = ConvolutionSplit.of(M, (H, W))
    got = blur_matrix(vel, [Window(0.3, 0.4, 1.0)], step_px=0.5, split_shape=(H, W))
    assert isinstance(got, ConvolutionSplit) and want is not None
    np.testing.assert_array_equal(got.rest, want.rest)
    assert (got.R != want.R).nnz == 0
    assert [k.shift for k in got.kernels] == [k.shift for k in want.kernels]
    x, y = _rand(10), _rand(11)
    np.testing.assert_array_equal(got.apply(x.reshape(H, W)), want.apply(x.reshape(H, W)))
    np.testing.assert_array_equal(got.adjoint(y), want.adjoint(y))


def test_layers_without_a_plan_still_come_as_a_matrix():
    M = blur_matrix(_object(), [Window(0.3, 0.4, 1.0)], step_px=0.5, split_shape=(H, W))
    assert sp.issparse(M)


@pytest.mark.parametrize("vel", [_translate(), _object(), _translate((20.0, -10.0))])
def test_the_splits_normal_diagonal_and_moving_reach_are_the_matrix_ones(vel):
    from stages.deblur.operator import moving_reach
    from stages.deblur.stacked import diag_normal

    M = _bin(vel, 0.2, 0.26)
    S = ConvolutionSplit.of(M, (H, W))
    assert S is not None
    wt = _rand(12)
    want = diag_normal(M, wt.reshape(-1, 1))[:, 0]
    np.testing.assert_allclose(S.diag_normal(wt), want, rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(S.moving_reach(), moving_reach(M))


def test_a_stack_of_splits_alone_gives_the_stacked_matrices_products():
    # The bins held as splits alone (no matrix) give every product the solve takes.
    vel = _translate((-17.0, 9.5))
    wins = [(t, t + 0.06) for t in np.arange(0.0, 0.6, 0.06)]
    mats = [_bin(vel, a, b) for a, b in wins]
    splits = [
        blur_matrix(vel, [Window(a, b, 1.0)], step_px=0.5, split_shape=(H, W)) for a, b in wins
    ]
    lean, plain = StackedOperator(splits), StackedOperator(mats)
    assert lean.parts is not None and all(g[0] is None for g in lean.groups)
    assert lean.shape == plain.shape and len(lean.groups) == len(plain.groups)
    n = H * W
    rng = np.random.default_rng(13)
    x = rng.random((n, 2))
    r = rng.random((len(wins) * n, 2))
    w = rng.random((len(wins) * n, 2))
    close = dict(rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(lean.mv(x), plain.mv(x), **close)
    np.testing.assert_allclose(lean.mvt(r), plain.mvt(r), **close)
    np.testing.assert_allclose(lean.mvt_weighted(w, r), plain.mvt_weighted(w, r), **close)
    np.testing.assert_allclose(lean.diag_normal(w), plain.diag_normal(w), **close)
    np.testing.assert_allclose(lean.normal(x, w), plain.normal(x, w), **close)
    np.testing.assert_array_equal(lean.moving_reach(), plain.moving_reach())


def test_the_vet_image_made_as_its_split_alone_gives_the_matrix_products():
    # The VET image's rows, an exposure time per group (here two), made as convolutions
    # and the rows they miss: products, transposed products, the normal diagonal and the
    # moving rows' reach are the matrix's.
    from stages.deblur.convolution import SplitOperator
    from stages.deblur.operator import moving_reach
    from stages.deblur.stacked import diag_normal, product

    vel = _translate((-6.0, 2.5))
    T = np.where(np.arange(W)[None, :] < W // 3, 0.45, 1.0).repeat(H, 0).astype(np.float32)
    wins = [Window(0.0, T, 1.0), Window(T, 1.0, 0.01)]
    M = blur_matrix(vel, wins, step_px=0.5)
    made = blur_matrix(vel, wins, step_px=0.5, split_shape=(H, W))
    assert isinstance(made, ConvolutionSplit) and len(made.kernels) == 2
    A = SplitOperator(made)
    assert A.shape == M.shape and A.convolution is made
    rng = np.random.default_rng(14)
    x, w = rng.random((H * W, 3)), rng.random((H * W, 3))
    close = dict(rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(A @ x[:, 0], M @ x[:, 0].astype(np.float32), **close)
    np.testing.assert_allclose(product(A, x), product(M, x), **close)
    np.testing.assert_allclose(product(A.T, x), product(M.T, x), **close)
    np.testing.assert_allclose(diag_normal(A, w), diag_normal(M, w), **close)
    np.testing.assert_array_equal(moving_reach(A), moving_reach(M))
