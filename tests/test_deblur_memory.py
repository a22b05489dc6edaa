"""The deblur's operators and data: products against dense known answers, and memory
bounded by the work in flight (no float64 copy of all the measuring bins)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import scipy.sparse as sp

from stages.deblur import stacked
from stages.deblur.problem import observations
from stages.deblur.stacked import StackedOperator, diag_normal, product
from stages.motion import parse_motion
from stages.rig import RigParams
from stages.scenes import builtin_interior
from stages.simulate import simulate


def _parts(rng: np.random.Generator, n: int = 60, nb: int = 3) -> list[sp.csr_matrix]:
    return [
        sp.random(n, n, density=0.1, format="csr", dtype=np.float32, random_state=rng)
        for _ in range(nb)
    ]


def test_stacked_operator_products_equal_the_dense_stack():
    rng = np.random.default_rng(0)
    parts = _parts(rng)
    S = np.vstack([M.toarray().astype(np.float64) for M in parts])
    op = StackedOperator(parts)
    x = rng.random((60, 2))
    r = rng.random((180, 2))
    w = rng.random((180, 2))
    np.testing.assert_allclose(op.mv(x), S @ x, rtol=1e-5)
    np.testing.assert_allclose(product(parts[1], x), S[60:120] @ x, rtol=1e-5)
    np.testing.assert_allclose(op.mvt(r), S.T @ r, rtol=1e-5)
    np.testing.assert_allclose(op.mvt_weighted(w, r), S.T @ (w * r), rtol=1e-5)
    np.testing.assert_allclose(op.normal(x, w), S.T @ (w * (S @ x)), rtol=1e-5)
    np.testing.assert_allclose(op.diag_normal(w), (S * S).T @ w, rtol=1e-5)
    # dot-product (adjoint) test of the stack
    lhs = float(np.sum(op.mv(x) * r))
    rhs = float(np.sum(x * op.mvt(r)))
    assert abs(lhs - rhs) <= 1e-5 * abs(lhs)


def test_stacked_groups_and_their_pieces_make_the_whole_stack():
    # Seven parts go into BIN_GROUPS groups; the normal product's pieces (group and
    # channel, as threads share them) sum to the whole stack's.
    rng = np.random.default_rng(4)
    parts = _parts(rng, n=50, nb=7)
    S = np.vstack([M.toarray().astype(np.float64) for M in parts])
    op = StackedOperator(parts)
    assert 1 < len(op.groups) <= stacked.BIN_GROUPS
    assert [g[2] for g in op.groups][0] == 0 and op.groups[-1][3] == 350
    x = rng.random((50, 3))
    w = rng.random((350, 3)).astype(np.float32)
    whole = S.T @ (w * (S @ x))
    pieces = np.zeros_like(whole)
    for c in range(3):
        xc = np.ascontiguousarray(x[:, c], np.float32)
        for g in range(len(op.groups)):
            pieces[:, c] += op.normal_column(g, xc, w, c)
    np.testing.assert_allclose(pieces, whole, rtol=1e-5)
    np.testing.assert_allclose(op.normal(x, w), whole, rtol=1e-5)
    np.testing.assert_allclose(op.mv(x), S @ x, rtol=1e-5)
    np.testing.assert_allclose(op.diag_normal(w), (S * S).T @ w, rtol=1e-5)
    # one part alone is one group
    assert len(StackedOperator(parts[:1]).groups) == 1


def test_products_with_long_and_short_rows_equal_the_dense_ones():
    # Long rows (the VET image's operator) go one column at a time, short rows (a
    # bin's) all at once; a transposed (CSC) view alike.
    rng = np.random.default_rng(6)
    for density in (0.05, 0.5):
        M = sp.random(70, 60, density=density, format="csr", dtype=np.float32, random_state=rng)
        D = M.toarray().astype(np.float64)
        x, y = rng.random((60, 3)), rng.random((70, 3))
        np.testing.assert_allclose(product(M, x), D @ x, rtol=1e-5)
        np.testing.assert_allclose(product(M.T, y), D.T @ y, rtol=1e-5)
        np.testing.assert_allclose(product(M, x[:, :1]), D @ x[:, :1], rtol=1e-5)
        assert product(M, x).dtype == np.float32


def test_diag_normal_in_row_blocks_equals_the_whole(monkeypatch):
    rng = np.random.default_rng(1)
    (A,) = _parts(rng, n=50, nb=1)
    w = rng.random((50, 3))
    whole = (A.toarray().astype(np.float64) ** 2).T @ w
    monkeypatch.setattr(stacked, "DIAG_BLOCK_ROWS", 7)  # several blocks, a short last one
    np.testing.assert_allclose(diag_normal(A, w), whole, rtol=1e-5)


def _traced_peak(fn):
    tracemalloc.start()
    tracemalloc.reset_peak()
    try:
        out = fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return out, peak


def test_observations_hold_the_bins_once_in_float32():
    # Before, the bins went through float64 copies of all of them at once (electrons,
    # variance, weights, data): a peak of 12x the capture's own float32 bins here.
    rig = RigParams(sensor_size=(64, 48))
    cap = simulate(
        builtin_interior(64, 48),
        parse_motion("translate:30,0"),
        rig,
        methods=["vet"],
        measure_bins=8,
    )["vet"]
    obs, peak = _traced_peak(lambda: observations(cap))
    assert obs.yb.dtype == np.float32 and obs.wb.dtype == np.float32
    assert obs.yb.shape == (cap.measure.shape[0] * 48 * 64, 3)
    assert peak < 4 * cap.measure.nbytes
    # the same electrons and weights as computed in float64
    g = rig.gain_dn_per_e
    b = 2
    dur = float(np.diff(cap.measure_times[b])[0])
    expect = cap.measure[b].astype(np.float64) / g - rig.dark_current_e_s * dur
    np.testing.assert_allclose(obs.yb[b * 48 * 64 : (b + 1) * 48 * 64], expect.reshape(-1, 3), 1e-6)


def test_bins_normal_product_holds_one_part_at_a_time():
    rng = np.random.default_rng(2)
    n, c, nb = 4000, 3, 8
    parts = [sp.identity(n, np.float32, format="csr") for _ in range(nb)]
    op = StackedOperator(parts)
    x = rng.random((n, c))
    w = rng.random((nb * n, c)).astype(np.float32)
    out, peak = _traced_peak(lambda: op.normal(x, w))
    np.testing.assert_allclose(out, w.reshape(nb, n, c).sum(axis=0)[:, :] * x, rtol=1e-5)
    # The (B N, C) float64 product of the whole stack alone would be nb * n * c * 8 bytes.
    assert peak < 4 * n * c * 8  # (half that of the stack)


def test_growing_assembly_buffer_keeps_every_part_in_order():
    from stages.deblur.assembly import Growing as _Growing

    rng = np.random.default_rng(3)
    parts = [rng.integers(0, 1000, rng.integers(0, 50)).astype(np.int32) for _ in range(30)]
    buf = _Growing(1)  # grows many times
    for p in parts:
        buf.append(p, p.astype(np.float32) / 2)
    idx, dat = buf.finish()
    np.testing.assert_array_equal(idx, np.concatenate(parts))
    np.testing.assert_array_equal(dat, np.concatenate(parts) / 2)


def test_a_vanishing_cross_component_keeps_one_row_of_weights():
    # A layered estimate of translate:30,0 carries a few thousandths of a px/s along y;
    # on OpenCV's 1/32 px grid the path stays on its row, so the operator is no larger
    # than that of the exact motion (before, every sample kept two rows: twice the
    # non-zeros, memory and product time).
    from stages.deblur.operator import Window, blur_matrix, vet_windows

    h, w = 24, 40
    T = np.full((h, w), 0.99975, np.float32)
    wins = vet_windows(T, 0.99975, 0.00758, 131, 0.002) + [Window(0.1, 0.21, 1.0)]
    exact = np.zeros((h, w, 2), np.float32)
    exact[..., 0] = 30.0
    drift = exact.copy()
    drift[..., 1] = 0.003
    A = blur_matrix(exact, wins)
    B = blur_matrix(drift, wins)
    assert B.nnz == A.nnz
    x = np.random.default_rng(4).random(h * w)
    np.testing.assert_allclose(B @ x, A @ x, rtol=1e-6)


def test_a_stream_is_fitted_through_unbiased_time_bins():
    """A stream capture is observed through FIT_BINS time bins whose inverse-variance
    weights do not favour the low counts: on a flat, still, dark scene (about 60 e- a
    bin) the weighted mean of the bins is the plain mean to 0.5% (0.997 here; weights from
    each bin's own count gave 0.990)."""
    from stages.deblur.problem import FIT_BINS
    from tests.test_deblur import flat_dark_capture

    w, h, signal = 96, 80, 2000.0
    cap = flat_dark_capture(w, h, signal)
    assert cap.keeps_stream
    obs = observations(cap)
    assert obs.yb.shape == (FIT_BINS * h * w, 1)
    yb = obs.yb.reshape(FIT_BINS, h, w)[:, 4:-4, 4:-4]
    wb = obs.wb.reshape(FIT_BINS, h, w)[:, 4:-4, 4:-4]
    weighted = (wb * yb).sum(axis=0) / wb.sum(axis=0)
    assert abs(float(weighted.mean() / yb.mean()) - 1.0) < 0.005


@pytest.mark.parametrize(("size", "tile"), [((96, 64), None), ((128, 80), 64)])
def test_release_stream_drops_the_stream_and_changes_nothing(monkeypatch, size, tile):
    """deblur(..., release_stream=True), as vet deblur calls it, lets go of the capture's
    measuring stream once it has made the time bins it fits, in the stream's own memory
    (the stream and the bins are never both held), in one piece or for tiles, and gives
    the same image."""
    import stages.formats.capture as capture_module
    from stages.deblur import deblur

    rig = RigParams(sensor_size=size)
    cap = simulate(builtin_interior(*size), parse_motion("translate:20,0"), rig, seed=1)["vet"]
    assert cap.keeps_stream
    kept, _ = deblur(cap, "vet", tile=tile)
    assert cap.measure is not None
    made = []
    in_place = capture_module.sum_bins_in_place
    monkeypatch.setattr(
        capture_module,
        "sum_bins_in_place",
        lambda box, e: made.append(in_place(box, e)) or made[-1],
    )
    released, _ = deblur(cap, "vet", tile=tile, release_stream=True)
    assert cap.measure is None
    assert len(made) == 1 and made[0] is not None
    np.testing.assert_array_equal(released.radiance, kept.radiance)


def test_smoothness_band_is_the_adjoint_of_the_weighted_gradient():
    from stages.deblur.image_step import smooth_bands
    from stages.deblur.problem import grad, grad_adjoint

    rng = np.random.default_rng(5)
    img = rng.random((9, 11, 3))
    sx, sy = rng.random((9, 11, 3)), rng.random((9, 11, 3))
    sx[:, -1] = 0
    sy[-1] = 0
    gx, gy = grad(img)
    want = grad_adjoint(sx * gx, sy * gy)
    bands, dsm = smooth_bands(sx, sy)
    other = rng.random((9, 11, 3))
    for k, band in enumerate(bands):
        got = np.zeros((9, 11), np.float32)
        band.normal(img[..., k].astype(np.float32), got)
        np.testing.assert_allclose(got, want[..., k], rtol=1e-5, atol=1e-6)
        # symmetric: <a, S b> = <S a, b>
        back = np.zeros((9, 11), np.float32)
        band.normal(other[..., k].astype(np.float32), back)
        lhs, rhs = float(np.sum(other[..., k] * got)), float(np.sum(back * img[..., k]))
        assert abs(lhs - rhs) <= 1e-5 * abs(lhs)
    # The diagonal: the product's with a unit image.
    unit = np.zeros((9, 11, 3))
    unit[4, 5] = 1.0
    gx, gy = grad(unit)
    np.testing.assert_allclose(dsm[4, 5], grad_adjoint(sx * gx, sy * gy)[4, 5])


def _panning_capture(w: int, h: int):
    """A w x h RGB capture of the built-in scene panning at 30 px/s, with 8 time bins."""
    return simulate(
        builtin_interior(w, h),
        parse_motion("translate:30,0"),
        RigParams(sensor_size=(w, h)),
        seed=2,
        methods=["vet"],
        measure_bins=8,
    )["vet"]


def test_the_solve_gives_the_same_image_on_one_thread_and_on_several(monkeypatch):
    # The products' pieces are summed in the same order however many threads make
    # them: a worker limited to one thread (Dask) gets the same image to the bit.
    from stages import cluster
    from stages.deblur import deblur, image_step

    cap = _panning_capture(64, 48)
    got = {}
    for threads in (1, 3):
        monkeypatch.setattr(image_step, "solve_threads", lambda t=threads: t)
        got[threads] = deblur(cap)[0].radiance
    np.testing.assert_array_equal(got[1], got[3])
    monkeypatch.setattr(cluster, "_started_one_thread", True)  # (OMP_NUM_THREADS=1 at start)
    assert cluster.solve_threads() == 1
    monkeypatch.setattr(cluster, "_started_one_thread", False)
    assert 1 <= cluster.solve_threads() <= cluster.MAX_SOLVE_THREADS


def test_bins_some_of_which_have_no_convolutions_are_all_matrices(monkeypatch):
    # The bins are held as splits alone only where every one has them; where one comes
    # as a matrix (no plan), all are made as matrices (with their splits beside), and
    # the products are the same.
    from stages.deblur import problem
    from stages.deblur.problem import build_operators

    rig = RigParams(sensor_size=(64, 48))
    cap = simulate(builtin_interior(64, 48), parse_motion("translate:20,0"), rig, seed=1)["vet"]
    obs = observations(cap)
    vel = np.zeros((48, 64, 2), np.float32)
    vel[..., 0] = 20.0
    _, lean = build_operators(obs, vel, step_px_bins=0.5)
    assert lean.parts is not None
    first = obs.windows_b[0]
    make = problem.blur_matrix

    def no_plan_for_the_first(vel, wins, **kw):
        if wins is first:
            kw["split_shape"] = None
        return make(vel, wins, **kw)

    monkeypatch.setattr(problem, "blur_matrix", no_plan_for_the_first)
    _, mixed = build_operators(obs, vel, step_px_bins=0.5)
    assert mixed.parts is None
    assert all(g[0] is not None for g in mixed.groups)
    assert all(s is not None for s in mixed.splits)
    rng = np.random.default_rng(4)
    x = rng.random((48 * 64, 1))
    w = rng.random((mixed.shape[0], 1))
    np.testing.assert_allclose(mixed.mv(x), lean.mv(x), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(mixed.normal(x, w), lean.normal(x, w), rtol=1e-5, atol=1e-6)


def test_an_image_step_holds_one_copy_of_the_bins_weights_and_one_piece(monkeypatch):
    # After the first step the joint solve hands each image step its bins' robust
    # weights only as the step takes them (bin_weights: the convolutions' weights and
    # the right-hand side), keeping no (B N, C) weights of its own through the solve;
    # on one thread the normal product's pieces are made as they are summed, not all
    # held at once. The image is the same to the bit as the other way round.
    from stages.deblur import deblur, image_step, joint

    cap = _panning_capture(96, 64)
    bins_bytes = observations(cap).yb.nbytes
    monkeypatch.setattr(image_step, "solve_threads", lambda: 1)
    handed, held_at, peaks, last = [], [], [], []
    solve, pcg = joint.solve_image, image_step.pcg

    def recorded(obs, A, Ab, w, wb, *args, **kw):
        bw = isinstance(wb, image_step.BinWeights)
        handed.append("noise" if wb is obs.wb else "prepared" if bw and wb.w is None else "other")
        last[:] = [(obs, A, Ab, w, wb, *args), kw]
        return solve(obs, A, Ab, w, wb, *args, **kw)

    def traced_pcg(*args, **kw):  # (what is held through the iterations; their peak)
        held_at.append(tracemalloc.get_traced_memory()[0])
        tracemalloc.reset_peak()
        out = pcg(*args, **kw)
        peaks.append(tracemalloc.get_traced_memory()[1] - held_at[-1])
        return out

    monkeypatch.setattr(joint, "solve_image", recorded)
    monkeypatch.setattr(image_step, "pcg", traced_pcg)

    def run() -> tuple[np.ndarray, list[int], list[int]]:
        for seen in (handed, held_at, peaks):
            seen.clear()
        tracemalloc.start()
        try:
            return deblur(cap)[0].radiance, list(held_at), list(peaks)
        finally:
            tracemalloc.stop()

    run()  # (what a first run leaves behind: caches)
    lean, held, peak = run()
    assert handed[0] == "noise" and set(handed[1:]) == {"prepared"} and len(handed) > 2
    monkeypatch.setattr(joint, "bin_weights", lambda Ab, wb, yb: wb)  # (kept by the caller)
    kept, held_kept, _ = run()
    monkeypatch.setattr(image_step, "_Inline", _Eager)
    eager, _, peak_eager = run()
    np.testing.assert_array_equal(lean, kept)
    np.testing.assert_array_equal(lean, eager)
    # (The first step fits the noise weights themselves: nothing to hand over.)
    assert abs(held[0] - held_kept[0]) < 0.1 * bins_bytes
    assert all(a < b - 0.5 * bins_bytes for a, b in zip(held[1:], held_kept[1:], strict=True))
    pieces = 3 * 5 * 96 * 64 * 4  # (channels x (bins' groups + the VET image's) x (N,) float32)
    assert all(a < b - 0.5 * pieces for a, b in zip(peak, peak_eager, strict=True))
    # Weights so given carry no diagonal for the preconditioner: the caller passes it.
    args, kw = last
    prepared = image_step.bin_weights(args[2], args[0].wb, args[0].yb)
    with pytest.raises(ValueError, match="data_diag"):
        solve(*args[:4], prepared, *args[5:], **dict(kw, data_diag=None))


class _Done:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


class _Eager:
    """An executor on one thread that makes each piece as it is submitted."""

    def submit(self, fn, *args):
        return _Done(fn(*args))
