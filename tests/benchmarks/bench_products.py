"""Benchmark: the solve's normal products as sparse matrices against their split into
shifted convolutions (stages.deblur.convolution).

For a tile-sized frame (default 474 x 559, a 1280 x 1024 frame's tile with its halo) and
a few motions over a 1 s frame of 131 subframes, it assembles the VET image's operator
(exposure times from a smooth map with 40% or 80% of the pixels open all frame: a
kernel per exposure time, the VET rows split where those open all frame are most) and 16 measuring
bins' operators as the default deblur does (VET samples 1 px apart, bins' 1.5 px), then
times ``M.T diag(w) M x`` both ways (split as the deblur splits them: the VET image's
along its assembly's stencil groups only, the bins' also by a search of their rows) (the median of several, one thread) and checks that
they agree. Prints per motion and operator: non-zeros per row, the share of rows the
kernels take, milliseconds for the sparse product and the split, their ratio, and the
largest difference relative to the largest value. Then, per motion, the 16 bins'
normal product through their splits one by one against their band and stacked other rows
(stages.deblur.band, where made): the offsets the band holds, the time to make it for one
set of weights against the splits' weights alone, both products' milliseconds and their ratio.

Run: ``.venv/bin/python -m tests.benchmarks.bench_products [WxH]``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from stages.deblur.convolution import ConvolutionSplit
from stages.deblur.operator import Window, blur_matrix, vet_windows

FRAME_S, SUBFRAMES, LEAKAGE, BINS = 1.0, 131, 0.01, 16
#: Shares of the pixels open all frame in the VET image's exposure maps.
OPEN_SHARES = (0.4, 0.8)
MOTIONS = {
    "translate 30,0": ((30.0, 0.0), None),
    "translate 21,21": ((21.0, 21.0), None),
    "object 24,-6 on a still background": ((24.0, -6.0), "object"),
}


def _velocity(shape, v, kind) -> np.ndarray:
    h, w = shape
    vel = np.zeros((h, w, 2), np.float32)
    if kind == "object":
        vel[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4] = v
    else:
        vel[...] = v
    return vel


def _exposure(shape, open_share: float, seed: int = 0) -> np.ndarray:
    """Closure times (s) on the subframe grid: a smooth random map, ``open_share`` of the
    pixels open all frame (dark), the others closed at times spread over the frame."""
    import cv2

    rng = np.random.default_rng(seed)
    field = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 12)
    q = np.quantile(field, 1.0 - open_share)
    frac = np.clip((field - field.min()) / max(q - field.min(), 1e-9), 0.02, 1.0)
    sub = FRAME_S / SUBFRAMES
    return np.maximum(np.round(frac * SUBFRAMES), 1) * sub


def _median_ms(fn, reps: int = 7) -> float:
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def _compare(M, shape, seed: int, detect: bool):
    rng = np.random.default_rng(seed)
    n = shape[0] * shape[1]
    x, wt = rng.random(n).astype(np.float32), rng.random(n).astype(np.float32)
    S = ConvolutionSplit.of(M, shape, detect=detect)
    MT = M.T
    csr = _median_ms(lambda: MT @ (wt * (M @ x)))
    if S is None:
        return M.nnz / n, 0.0, csr, None, None
    weights = S.weights(wt)
    out = np.zeros(shape, np.float32)

    def split():
        out[...] = 0
        S.normal(x.reshape(shape), weights, out)

    ms = _median_ms(split)
    want = MT @ (wt * (M @ x))
    err = float(np.abs(out.ravel() - want).max() / np.abs(want).max())
    taken = float(sum(k.mask.sum() for k in S.kernels)) / n
    return M.nnz / n, taken, csr, ms, err


def main(size: str = "474x559") -> list[dict]:
    from stages.cluster import opencv_single_threaded

    w, h = (int(v) for v in size.split("x"))
    shape = (h, w)
    edges = np.linspace(0.0, SUBFRAMES, BINS + 1).round() * (FRAME_S / SUBFRAMES)
    rows = []
    print(f"frame {w} x {h}, {BINS} bins, one thread (cv2 threads: 1)")
    print(
        f"{'motion':36s} {'operator':8s} {'nnz/row':>7s} {'taken':>6s} {'sparse ms':>9s}"
        f" {'split ms':>8s} {'ratio':>6s} {'max diff':>9s}"
    )
    with opencv_single_threaded():
        for name, (v, kind) in MOTIONS.items():
            vel = _velocity(shape, v, kind)
            parts = {}
            for share in OPEN_SHARES:
                T = _exposure(shape, share)
                wins = vet_windows(T, FRAME_S, FRAME_S / SUBFRAMES, SUBFRAMES, LEAKAGE)
                A = blur_matrix(vel, wins, step_px=1.0, min_dt=FRAME_S / SUBFRAMES)
                parts[f"VET {share:.0%}"] = [A]
            parts["bins"] = [
                blur_matrix(vel, [Window(a, b, 1.0)], step_px=1.5, min_dt=FRAME_S / SUBFRAMES)
                for a, b in zip(edges[:-1], edges[1:], strict=True)
            ]
            band = _band_row(parts["bins"], shape)
            for op, mats in parts.items():
                res = [_compare(M, shape, seed, op == "bins") for seed, M in enumerate(mats)]
                nnz = sum(r[0] for r in res)
                taken = float(np.mean([r[1] for r in res]))
                csr = sum(r[2] for r in res)
                split = None if any(r[3] is None for r in res) else sum(r[3] for r in res)
                err = None if split is None else max(r[4] for r in res)
                rows.append(
                    dict(motion=name, operator=op, nnz=nnz, taken=taken, csr=csr, split=split)
                )
                split_s = "-" if split is None else f"{split:8.2f}"
                ratio_s = "-" if split is None else f"{csr / split:6.2f}"
                err_s = "-" if err is None else f"{err:9.1e}"
                print(
                    f"{name:36s} {op:8s} {nnz:7.1f} {taken:6.1%} {csr:9.2f} {split_s:>8s}"
                    f" {ratio_s:>6s} {err_s:>9s}",
                    flush=True,
                )
            if band is not None:
                conv, ms, build, offs, err = band
                rows.append(dict(motion=name, operator="band", offsets=offs, conv=conv, band=ms))
                print(
                    f"{name:36s} {'band':8s} {offs:2d} offsets, weights {build[0]:.1f} ms"
                    f" (without it {build[1]:.1f} ms)"
                    f" {conv:9.2f} {ms:8.2f} {conv / ms:6.2f} {err:9.1e}",
                    flush=True,
                )
    return rows


def _band_row(mats, shape):
    """The bins' normal product through their splits one by one against their band and
    stacked other rows (:attr:`StackedOperator.banded`), one set of weights: (splits' ms,
    band's ms, (ms to make the weights with the band, without it), offsets held, largest difference relative to the largest
    value), or None where some bin does not split or the band would cost more."""
    from stages.deblur.stacked import StackedOperator

    splits = [ConvolutionSplit.of(M, shape) for M in mats]
    if any(s is None for s in splits):
        return None
    S = StackedOperator(splits)
    if S.banded is None:
        return None
    n = shape[0] * shape[1]
    rng = np.random.default_rng(0)
    x = rng.random(n).astype(np.float32)
    w = rng.random((len(splits) * n, 1)).astype(np.float32)
    each = [s.weights(w[i * n : (i + 1) * n, 0]) for i, s in enumerate(splits)]
    out = np.zeros(shape, np.float32)

    def conv():
        out[...] = 0
        for s, pw in zip(splits, each, strict=True):
            s.normal(x.reshape(shape), pw, out)

    ms_conv = _median_ms(conv)
    want = out.ravel().copy()
    build = (
        _median_ms(lambda: S.split_weights(w)),
        _median_ms(lambda: [s.weights(w[i * n : (i + 1) * n, 0]) for i, s in enumerate(splits)]),
    )
    sw = S.split_weights(w)
    got = S.normal_column(0, x, w, 0, sw)
    ms = _median_ms(lambda: S.normal_column(0, x, w, 0, sw))
    err = float(np.abs(got - want).max() / np.abs(want).max())
    return ms_conv, ms, build, len(S.banded[0]), err


if __name__ == "__main__":
    main(*sys.argv[1:])
