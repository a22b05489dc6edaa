"""The measuring bins' kernels as one band (stages.deblur.band) and their other rows as
one stack (stages.deblur.stacked.RestRows): the same normal product as the bins'
matrices, a symmetric band holding half its offsets, and made only where it costs less
than the kernels' convolutions."""

from __future__ import annotations

import numpy as np
import pytest

from stages.deblur.band import band_worth, make_band, offsets
from stages.deblur.convolution import ConvolutionSplit, _Kernel
from stages.deblur.operator import Window, blur_matrix
from stages.deblur.stacked import BIN_GROUPS, StackedOperator

H, W = 48, 64
EDGES = np.linspace(0.0, 1.0, 17)  # (16 bins over a 1 s frame)


def _bins(v, split: bool):
    """The 16 bins' operators of a translation ``v`` px/s: matrices, or their splits."""
    vel = np.zeros((H, W, 2), np.float32)
    vel[...] = v
    out = []
    for a, b in zip(EDGES[:-1], EDGES[1:], strict=True):
        M = blur_matrix(
            vel,
            [Window(a, b, 1.0)],
            step_px=1.5,
            min_dt=1 / 131,
            split_shape=(H, W) if split else None,
        )
        out.append(
            M if not split or isinstance(M, ConvolutionSplit) else ConvolutionSplit.of(M, (H, W))
        )
    return out


@pytest.mark.parametrize("v", [(30.0, 0.0), (-17.0, 9.5)])
def test_banded_bins_give_the_stacked_matrices_normal_product(v):
    lean, plain = StackedOperator(_bins(v, True)), StackedOperator(_bins(v, False))
    assert lean.banded is not None and len(lean.groups) == 1
    offs, rest = lean.banded
    assert rest.R.nnz > 0  # (the border's rows: the stack of other rows is exercised)
    n = H * W
    rng = np.random.default_rng(3)
    x = rng.random((n, 2))
    for _ in range(2):  # (then other weights: the band made anew)
        w = rng.random((16 * n, 2))
        sw = lean.split_weights(w)
        # Held per channel: the band's coefficients and the other rows' weights, no
        # kernel's weights image.
        assert sw.groups is None
        assert [b.coeffs.shape for b in sw.bands] == [(len(offs), H, W)] * 2
        assert [r.size for r in sw.rests] == [rest.R.shape[0]] * 2
        want = plain.normal(x, w)
        np.testing.assert_allclose(lean.normal(x, w), want, rtol=1e-5, atol=1e-6)
        for c in range(2):
            xc = np.ascontiguousarray(x[:, c], np.float32)
            got = lean.normal_column(0, xc, w, c, sw)
            np.testing.assert_allclose(got, want[:, c], rtol=1e-5, atol=1e-6)
        # The other products do not go through the band.
        np.testing.assert_allclose(lean.diag_normal(w), plain.diag_normal(w), rtol=1e-5)


def test_bins_whose_band_would_cost_more_keep_their_convolutions():
    # A translation with a vertical part: 2 x 3 kernels, eight offsets held, fifteen
    # multiply-adds per product against sixteen kernels' convolutions.
    lean, plain = (
        StackedOperator(_bins((24.0, 5.0), True)),
        StackedOperator(_bins((24.0, 5.0), False)),
    )
    assert lean.parts is not None and lean.banded is None
    assert len(lean.groups) == BIN_GROUPS
    n = H * W
    rng = np.random.default_rng(4)
    x, w = rng.random((n, 1)), rng.random((16 * n, 1))
    assert lean.split_weights(w).bands is None
    np.testing.assert_allclose(lean.normal(x, w), plain.normal(x, w), rtol=1e-5, atol=1e-6)


def _kernel(rng, shape, shift):
    small = rng.random(shape).astype(np.float32)
    mask = np.zeros((H, W), bool)
    mask[3 : H - 4, 4 : W - 5] = rng.random((H - 7, W - 9)) > 0.3
    return _Kernel(small, shift, mask)


def test_a_band_is_symmetric_holds_half_its_offsets_and_matches_the_convolutions():
    rng = np.random.default_rng(5)
    ks = [
        _kernel(rng, (2, 3), (1, -2)),
        _kernel(rng, (1, 2), (0, 2)),
        _kernel(rng, (3, 1), (-2, 0)),
        _kernel(rng, (1, 1), (1, 1)),  # (a whole-pixel shift: weights hold the tap squared)
    ]
    offs = offsets(ks)
    assert (0, 0) in offs and all(d[0] > 0 or (d[0] == 0 and d[1] >= 0) for d in offs)
    # 2 x 3: (0,0..2), (1,-2..2); 1 x 2: (0,1); 3 x 1: (1,0), (2,0).
    assert len(offs) == 9
    mws = []
    for k in ks:
        (ry, rx), (cy, cx) = k.slices(H, W)
        mw = np.zeros((H, W), np.float32)
        mw[cy, cx] = np.where(k.mask[ry, rx], rng.random((H, W)).astype(np.float32)[ry, rx], 0)
        mws.append(mw * np.float32(k.tap**2) if k.tap is not None else mw)
    band = make_band(zip(ks, mws, strict=True), offs, (H, W))
    x, y = rng.random((H, W)).astype(np.float32), rng.random((H, W)).astype(np.float32)
    want = np.zeros((H, W), np.float32)
    for k, mw in zip(ks, mws, strict=True):
        if k.tap is not None:
            want += x * mw
        else:
            want += k.spread(k.correlate(x) * mw)
    got, hy = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    band.normal(x, got)
    band.normal(y, hy)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert abs(float((y * got).sum()) - float((hy * x).sum())) < 1e-5 * float((y * got).sum())


def test_a_band_is_made_only_where_it_costs_less_than_the_convolutions():
    rng = np.random.default_rng(6)
    short = [_kernel(rng, (1, 3), (0, i)) for i in range(16)]
    assert band_worth(short)  # 3 offsets, 5 multiply-adds, against 16 kernels
    assert not band_worth(short[:4])
    assert not band_worth([_kernel(rng, (1, 31), (0, 0))])  # (31 offsets for one kernel)


def test_the_sum_of_two_bands_is_one_band_on_their_offsets():
    rng = np.random.default_rng(7)
    ka, kb = _kernel(rng, (1, 3), (0, 1)), _kernel(rng, (2, 1), (1, 0))
    a, b = (
        make_band([(k, rng.random((H, W)).astype(np.float32))], offsets([k]), (H, W))
        for k in (ka, kb)
    )
    both = a.plus(b)
    assert both.offsets == [(0, 0), (0, 1), (0, 2), (1, 0)]
    x = rng.random((H, W)).astype(np.float32)
    want = np.zeros((H, W), np.float32)
    a.normal(x, want)
    b.normal(x, want)
    got = np.zeros((H, W), np.float32)
    both.normal(x, got)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_a_deblur_through_the_band_is_the_one_through_the_convolutions(monkeypatch):
    # The whole solve, the bins' band holding the smoothness too, against the same solve
    # with the bins' convolutions and the smoothness's own band: the same image up to
    # float32 sums in another order.
    import stages.deblur.stacked as stacked
    from stages.deblur import deblur
    from tests.test_deblur import _capture

    cap = _capture("translate:30,0", 96, 80)
    made = []
    make = stacked.make_band
    monkeypatch.setattr(stacked, "make_band", lambda *a: made.append(1) or make(*a))
    banded, _ = deblur(cap, "vet", motion_init="truth")
    assert made  # (the bins were banded)
    monkeypatch.setattr(stacked, "band_worth", lambda kernels: False)
    made.clear()
    plain, _ = deblur(cap, "vet", motion_init="truth")
    assert not made
    rel = np.abs(banded.radiance - plain.radiance) / np.abs(plain.radiance).max()
    assert rel.max() < 1e-5


@pytest.mark.parametrize("shape", [(1, 1), (2, 1), (1, 2), (2, 2), (2, 3), (3, 2), (4, 5)])
def test_a_band_on_an_image_narrower_than_its_offsets_is_the_dense_product(shape):
    # Offsets as long as the image or longer read nothing; the others as on a large one.
    from stages.deblur.band import Band

    h, w = shape
    rng = np.random.default_rng(3)
    offs = [(0, 0), (0, 1), (0, 2), (0, 3), (1, -1), (1, 0), (2, 1), (3, 0)]
    coeffs = rng.random((len(offs), h, w)).astype(np.float32)
    x = rng.random((h, w)).astype(np.float32)
    want = np.zeros((h, w))
    for (dy, dx), c in zip(offs, coeffs, strict=True):
        for py in range(h):
            for px in range(w):
                qy, qx = py + dy, px + dx
                if 0 <= qy < h and 0 <= qx < w:
                    want[py, px] += c[py, px] * x[qy, qx]
                    if (dy, dx) != (0, 0):
                        want[qy, qx] += c[py, px] * x[py, px]
    out = np.zeros((h, w), np.float32)
    Band(offs, coeffs).normal(x, out)
    np.testing.assert_allclose(out, want, rtol=1e-5)
