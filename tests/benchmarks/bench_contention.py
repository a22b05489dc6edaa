"""Benchmark: how much faster two processes finish a tile solve's sparse products than
one, on this machine.

A tile's image solve is mostly sparse matrix-vector products (the deblur's profile),
bound by memory bandwidth. Two Dask workers each solve their own tiles: their speedup
over one worker is at most what two processes running such products side by side give
over one running them alone. This runs a fixed amount of work (``ROUNDS`` products of a
banded CSR matrix shaped like a 512 px tile's blur operator: rows of ``NNZ_PER_ROW``
non-zeros, float32) once in one process, then the same work split over two processes
started together, each single-threaded, and prints the times and their ratio (2.0 would
be perfect scaling; what the cores share, memory bandwidth above all, takes it lower).
``bench_tiles`` times a whole tile solve alone and beside another: where the products
scale here and the solves do not, what contends is the rest of the solve (its
element-wise passes over the images and their temporaries), not the products.

Run: ``.venv/bin/python -m tests.benchmarks.bench_contention``.
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor

#: Rows of the operator (a 512 px tile with a 64 px halo) and non-zeros per row.
ROWS = 640 * 640
NNZ_PER_ROW = 120
#: Products in all (split evenly over the processes).
ROUNDS = 240


def _products(rounds: int) -> float:
    """Seconds for ``rounds`` products ``A @ x`` (scipy's CSR kernel: one thread)."""
    import numpy as np
    import scipy.sparse as sp

    rng = np.random.default_rng(0)
    offsets = np.sort(rng.choice(np.arange(-6000, 6000), NNZ_PER_ROW, replace=False))
    rows = np.repeat(np.arange(ROWS), NNZ_PER_ROW)
    cols = np.clip(rows + np.tile(offsets, ROWS), 0, ROWS - 1)
    data = rng.random(rows.size, dtype=np.float32)
    a = sp.csr_matrix((data, (rows, cols)), shape=(ROWS, ROWS))
    x = rng.random(ROWS, dtype=np.float32)
    t0 = time.perf_counter()
    for _ in range(rounds):
        x = a @ x
        x /= np.float32(np.abs(x).max() + 1e-30)
    return time.perf_counter() - t0


def main() -> None:
    with ProcessPoolExecutor(1) as one:
        alone = one.submit(_products, ROUNDS).result()
    with ProcessPoolExecutor(2) as two:
        halves = [j.result() for j in [two.submit(_products, ROUNDS // 2) for _ in range(2)]]
    both = max(halves)
    print(
        f"{ROUNDS} sparse products ({ROWS} rows x {NNZ_PER_ROW} non-zeros, float32): "
        f"one process {alone:.2f} s; two processes, half each, side by side "
        f"{halves[0]:.2f} s and {halves[1]:.2f} s"
    )
    print(
        f"two processes against one: {alone / both:.2f}x (each product "
        f"{(both / (ROUNDS // 2)) / (alone / ROUNDS):.2f}x slower beside the other)"
    )


if __name__ == "__main__":
    main()
