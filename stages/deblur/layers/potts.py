"""Labels of the points the evidence leaves undecided, by a minimum cut (Potts model).

A labelling ``l`` of an (H, W) grid over K layers is scored by

    E(l) = sum_p cost[l_p, p]  +  beta * #{4-neighbour pairs (p, q): l_p != l_q}

where ``cost[k, p]`` is the negative evidence (nats) that point ``p`` belongs to layer
``k``. The points already decided keep their layer; the others take the labelling of least
energy. With two layers that is one s-t minimum cut, exact (Greig, Porteous & Seheult,
"Exact maximum a posteriori estimation for binary images", J. R. Stat. Soc. B 51, 1989);
with more, alpha-expansion moves, each a minimum cut (Boykov, Veksler & Zabih, "Fast
approximate energy minimization via graph cuts", IEEE TPAMI 23(11), 2001), with the
pairwise terms of each move built as Kolmogorov & Zabih's ("What energy functions can be
minimized via graph cuts?", IEEE TPAMI 26(2), 2004). The cuts are scipy's
:func:`scipy.sparse.csgraph.maximum_flow` (Dinic's algorithm) on integer capacities of
1/:data:`CAPACITY_SCALE` nat.

What this does for the layers: a region whose points each hold only weak evidence, too
little for any one of them (or for a neighbourhood pooled across a boundary) to decide,
takes the layer its evidence favours in sum, unless that would cost more boundary than
the evidence is worth; a small undecided pocket takes the layer around it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

#: Capacities are integers: this many per nat.
CAPACITY_SCALE = 64
#: Expansion sweeps over all layers, at most (more than two layers).
SWEEPS = 3
#: Largest flow a cut may carry (scipy's flows are int32).
FLOW_LIMIT = (1 << 31) - 1


def _neighbour_pairs(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (p, q) of every 4-neighbour pair of an (h, w) grid."""
    flat = np.arange(h * w).reshape(h, w)
    p = np.concatenate([flat[:, :-1].ravel(), flat[:-1, :].ravel()])
    q = np.concatenate([flat[:, 1:].ravel(), flat[1:, :].ravel()])
    return p, q


def binary_cut(
    u0: np.ndarray, u1: np.ndarray, p: np.ndarray, q: np.ndarray, w: np.ndarray
) -> np.ndarray:
    """The x in {0, 1}^n that minimises ``sum u0[x == 0] + sum u1[x == 1] + sum_e w_e
    [x_p[e] == 0 and x_q[e] == 1]`` (``u0, u1`` (n,), ``w`` (m,) >= 0 for the pairs
    ``p, q`` (m,) of node indices); returns x as (n,) bool, 0 wherever a tie allows."""
    n = len(u0)
    s, t = n, n + 1
    m = np.minimum(u0, u1)
    to_one = np.rint((u1 - m) * CAPACITY_SCALE).astype(np.int64)  # s -> i: cut if x_i = 1
    to_zero = np.rint((u0 - m) * CAPACITY_SCALE).astype(np.int64)  # i -> t: cut if x_i = 0
    cw = np.rint(np.asarray(w, np.float64) * CAPACITY_SCALE).astype(np.int64)
    # scipy's capacities and flows are int32: all are scaled down where their sum (which
    # bounds every capacity and flow) would pass that.
    total = int(to_one.sum()) + int(to_zero.sum()) + int(cw.sum())
    if total > FLOW_LIMIT:
        to_one, to_zero, cw = (
            np.floor(c * (FLOW_LIMIT / total)).astype(np.int64) for c in (to_one, to_zero, cw)
        )
    nodes = np.arange(n)
    rows = np.concatenate([np.full(n, s), nodes, p])
    cols = np.concatenate([nodes, np.full(n, t), q])
    caps = np.concatenate([to_one, to_zero, cw])
    keep = caps > 0
    graph = sp.csr_matrix(
        (caps[keep].astype(np.int32), (rows[keep], cols[keep])), shape=(n + 2, n + 2)
    )
    flow = maximum_flow(graph, s, t, method="dinic").flow
    # (the flow is antisymmetric: its reverse entries give the reverse residuals)
    residual = (graph - flow).tocsr()
    residual.data = np.maximum(residual.data, 0)
    residual.eliminate_zeros()
    # The sink's side: the nodes that still reach it. (Of the minimum cuts, the one with
    # the fewest nodes at 1: a tie keeps 0.)
    reaching = breadth_first_order(residual.T.tocsr(), t, directed=True, return_predecessors=False)
    x = np.zeros(n, bool)
    x[reaching[reaching < n]] = True
    return x


def complete_labels(label: np.ndarray, cost: np.ndarray, beta: float) -> np.ndarray:
    """Labels of the points of ``label`` (H, W) int that are -1, given the others'.

    ``cost`` (K, H, W): the cost (nats) of each layer at each point; ``beta`` (nats) the
    cost of each 4-neighbour pair whose layers differ. The undecided points start at
    the layer of least total cost over them (K > 2) and take the labelling of least
    energy (see the module docstring; exact for K = 2). Returns a new (H, W) int32 array.
    """
    h, w = label.shape
    k_layers = cost.shape[0]
    free = (label < 0).ravel()
    out = label.astype(np.int32).ravel().copy()
    if not free.any():
        return out.reshape(h, w)
    cf = cost.reshape(k_layers, -1).astype(np.float64)
    free_idx = np.flatnonzero(free)
    node = np.full(h * w, -1, np.int64)
    node[free_idx] = np.arange(len(free_idx))
    p, q = _neighbour_pairs(h, w)
    touch = free[p] | free[q]
    p, q = p[touch], q[touch]
    both = free[p] & free[q]
    pb, qb = p[both], q[both]
    # Pairs with one decided point: a cost on the undecided one.
    one_p = np.concatenate([p[free[p] & ~free[q]], q[free[q] & ~free[p]]])
    one_fixed = np.concatenate([q[free[p] & ~free[q]], p[free[q] & ~free[p]]])
    if k_layers == 2:  # (one cut, 0 against 1, is exact)
        out[free_idx], alphas, sweeps = 0, [1], 1
    else:
        out[free_idx] = int(np.argmin(cf[:, free_idx].sum(axis=1)))
        alphas, sweeps = list(range(k_layers)), SWEEPS
    for _sweep in range(sweeps):
        changed = False
        for alpha in alphas:
            cur = out
            u0 = cf[cur[free_idx], free_idx].copy()  # keep the current layer
            u1 = cf[alpha, free_idx].copy()  # take alpha
            np.add.at(u0, node[one_p], beta * (cur[one_p] != cur[one_fixed]))
            np.add.at(u1, node[one_p], beta * (cur[one_fixed] != alpha))
            # E(x_p, x_q) with A = E(0,0), B = E(0,1), C = E(1,0), D = E(1,1) = 0, as
            # A + (C - A) x_p + (D - C) x_q + (B + C - A - D) (1 - x_p) x_q.
            a = beta * (cur[pb] != cur[qb])
            b = beta * (cur[pb] != alpha)
            c = beta * (cur[qb] != alpha)
            np.add.at(u1, node[pb], c - a)
            np.add.at(u1, node[qb], -c)
            x = binary_cut(u0, u1, node[pb], node[qb], b + c - a)
            take = free_idx[x & (cur[free_idx] != alpha)]
            if len(take):
                out[take] = alpha
                changed = True
        if not changed:
            break
    return out.reshape(h, w)
