"""The deblur's conjugate gradients (stages.deblur.problem.pcg): each row of a (C, N)
array an independent system, solved to the exact answer; fixed unknowns keep their
value."""

from __future__ import annotations

import numpy as np

from stages.deblur.problem import pcg


def _spd(rng, n):
    m = rng.random((n, n))
    return m @ m.T + n * np.eye(n)


def test_each_row_is_its_own_system_solved_exactly():
    rng = np.random.default_rng(0)
    n = 12
    H = [_spd(rng, n), _spd(rng, n)]  # (a channel's operator each)
    b = rng.random((2, n))
    seen = []
    x = pcg(
        lambda x: np.stack([H[k] @ x[k] for k in range(2)]),
        b,
        np.zeros((2, n)),
        np.stack([np.diag(h) for h in H]),
        3 * n,
        tol=0,
        callback=lambda k, x: seen.append(x.shape),
    )
    for k in range(2):
        np.testing.assert_allclose(x[k], np.linalg.solve(H[k], b[k]), rtol=1e-8)
    assert seen and seen[0] == (2, n)


def test_fixed_unknowns_keep_their_start():
    rng = np.random.default_rng(1)
    n = 10
    H = _spd(rng, n)
    b = rng.random((1, n))
    x0 = rng.random((1, n))
    free = np.ones(n, bool)
    free[[2, 7]] = False
    x = pcg(lambda x: (H @ x[0])[None], b, x0, np.diag(H)[None], 3 * n, tol=0, free=free)
    np.testing.assert_array_equal(x[0, ~free], x0[0, ~free])
    # The free ones solve H restricted to them, the fixed ones' part moved to the right.
    f = np.flatnonzero(free)
    want = np.linalg.solve(H[np.ix_(f, f)], b[0, f] - H[np.ix_(f, ~free)] @ x0[0, ~free])
    np.testing.assert_allclose(x[0, f], want, rtol=1e-8)


def test_it_stops_once_every_row_is_solved():
    # A diagonal system: the Jacobi step solves it in one iteration, then nothing is left.
    rng = np.random.default_rng(2)
    d = rng.random((2, 50)) + 1
    b = rng.random((2, 50))
    seen = []
    x = pcg(lambda x: d * x, b, np.zeros((2, 50)), d, 20, callback=lambda k, x: seen.append(k))
    np.testing.assert_allclose(x, b / d)
    assert seen == [0]
