"""The minimum-cut labelling of undecided points (stages.deblur.layers.potts), against
brute force and known answers, and what it does for the layers' labels."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from stages.deblur.layers import labels as labels_mod
from stages.deblur.layers.potts import CAPACITY_SCALE, binary_cut, complete_labels


def _energy(lab: np.ndarray, cost: np.ndarray, beta: float) -> float:
    """E(l) = sum cost[l_p, p] + beta * (4-neighbour pairs with different layers)."""
    h, w = lab.shape
    e = float(cost[lab, np.arange(h)[:, None], np.arange(w)[None, :]].sum())
    cuts = (lab[:, 1:] != lab[:, :-1]).sum() + (lab[1:] != lab[:-1]).sum()
    return e + beta * float(cuts)


def _brute_force(label: np.ndarray, cost: np.ndarray, beta: float) -> float:
    free = np.argwhere(label < 0)
    best = np.inf
    for combo in itertools.product(range(cost.shape[0]), repeat=len(free)):
        lab = label.copy()
        lab[free[:, 0], free[:, 1]] = combo
        best = min(best, _energy(lab, cost, beta))
    return best


@pytest.mark.parametrize("trial", range(12))
def test_two_layers_take_the_labelling_of_least_energy(trial):
    rng = np.random.default_rng(trial)
    h, w = 3, 4
    cost = np.concatenate([np.zeros((1, h, w)), rng.normal(0, 1, (1, h, w))]).astype(np.float32)
    label = np.full((h, w), -1, np.int32)
    fixed = rng.random((h, w)) < 0.3
    label[fixed] = rng.integers(0, 2, int(fixed.sum()))
    beta = float(rng.uniform(0.2, 2.0))
    out = complete_labels(label, cost, beta)
    assert np.array_equal(out[fixed], label[fixed])  # the decided points keep their layer
    assert set(np.unique(out)) <= {0, 1}
    # Exact up to the capacities' rounding (half a unit per term).
    slack = (h * w + 2 * h * w) / CAPACITY_SCALE
    assert _energy(out, cost, beta) <= _brute_force(label, cost, beta) + slack


@pytest.mark.parametrize("trial", range(6))
def test_more_layers_come_within_twice_the_least_energy(trial):
    """Alpha-expansion's bound for the Potts model (Boykov, Veksler & Zabih 2001)."""
    rng = np.random.default_rng(100 + trial)
    h, w = 3, 3
    cost = rng.uniform(0, 2, (3, h, w)).astype(np.float32)
    label = np.full((h, w), -1, np.int32)
    label[0, 0] = 2
    beta = 1.0
    out = complete_labels(label, cost, beta)
    assert out[0, 0] == 2
    best = _brute_force(label, cost, beta)
    assert _energy(out, cost, beta) <= 2 * best + 0.1
    start = label.copy()
    start[label < 0] = int(np.argmin(cost.reshape(3, -1).sum(axis=1)))
    assert _energy(out, cost, beta) <= _energy(start, cost, beta) + 1e-6


@pytest.mark.parametrize("evidence, expect", [(0.3, 1), (-0.3, 0)])
def test_an_undecided_strip_takes_the_layer_its_evidence_favours_in_sum(evidence, expect):
    """20 x 30: the left ten columns decided moving (1), the right ten still (0); the
    middle ten hold ``evidence`` nats each for moving. Moving costs the 20 pairs on its
    right (40 nats at 2 each) and gains 200 x 0.3 = 60; still costs the 20 on its left."""
    label = np.full((20, 30), -1, np.int32)
    label[:, :10], label[:, 20:] = 1, 0
    cost = np.zeros((2, 20, 30), np.float32)
    cost[1] = -evidence
    out = complete_labels(label, cost, 2.0)
    assert np.all(out[:, 10:20] == expect)
    assert np.all(out[:, :10] == 1) and np.all(out[:, 20:] == 0)


def test_an_undecided_pocket_with_no_evidence_takes_the_layer_about_it():
    label = np.zeros((30, 30), np.int32)
    label[5:25, 5:25] = 1
    label[12:18, 12:18] = -1
    out = complete_labels(label, np.zeros((2, 30, 30), np.float32), 2.0)
    assert np.all(out[5:25, 5:25] == 1)


def test_a_cut_reads_the_right_side_of_each_edge():
    """Two nodes joined by an edge that charges (x_0, x_1) = (0, 1) only."""
    u0 = np.array([0.0, 5.0])  # node 1 would rather be 1 ...
    u1 = np.array([1.0, 0.0])  # ... node 0 rather 0
    x = binary_cut(u0, u1, np.array([0]), np.array([1]), np.array([10.0]))
    assert x.tolist() == [True, True]  # 0 -> 1 costs 10: node 0 pays 1 to follow node 1
    x = binary_cut(u0, u1, np.array([1]), np.array([0]), np.array([10.0]))
    assert x.tolist() == [False, True]  # (1, 0) then costs nothing


def test_a_weakly_evidenced_corner_of_an_object_is_labelled_with_it(monkeypatch):
    """The layers' assignment: an object (left half) with strong evidence for its motion,
    a still background (right) with strong evidence against, and a corner of the object
    whose content (flat, or textured along the motion) gives each point only about 0.5
    nats for it, too little at any pooling scale: the corner is the object's, but for the
    few columns beside the background that its pooled evidence reaches (the full-resolution
    boundary step decides those). Each point chose its layer alone before (the default:
    still)."""
    h, w = 60, 80
    rng = np.random.default_rng(3)
    evidence = np.where(np.arange(w)[None, :] < 40, 20.0, -40.0) * np.ones((h, 1))
    corner = (slice(40, 60), slice(22, 40))
    evidence[corner] = rng.normal(0.5, 1.0, (20, 18))
    evidence = evidence.astype(np.float32)
    monkeypatch.setattr(labels_mod, "track_score", lambda lv, slv, v, c: evidence)
    lv = np.zeros((4, h, w), np.float32)
    label = labels_mod.assign_labels(lv, lv, [np.zeros(2), np.array([40.0, 10.0])], np.arange(4.0))
    assert (label[40:60, 22:35] == 1).mean() > 0.95
    assert np.all(label[:, 45:] == 0) and np.all(label[:, :18] == 1)


def test_a_region_an_object_sweeps_over_stays_still(monkeypatch):
    """Background points the object covers during the frame: both hypotheses misfit once
    they are covered, so most points score a little for the motion (+2 nats) and some
    far against it (-10): in sum, still. Evidence clipped at +-2 would call the region
    moving (1.4 - 0.6 nats a point on average)."""
    h, w = 60, 80
    rng = np.random.default_rng(4)
    evidence = np.where(np.arange(w)[None, :] < 40, 20.0, -40.0) * np.ones((h, 1))
    swept = (slice(20, 40), slice(40, 60))
    evidence[swept] = np.where(rng.random((20, 20)) < 0.3, -10.0, 2.0)
    evidence = evidence.astype(np.float32)
    monkeypatch.setattr(labels_mod, "track_score", lambda lv, slv, v, c: evidence)
    lv = np.zeros((4, h, w), np.float32)
    label = labels_mod.assign_labels(lv, lv, [np.zeros(2), np.array([40.0, 10.0])], np.arange(4.0))
    assert np.all(label[22:38, 50:60] == 0)  # (nearer the object, its pooled evidence)


def test_costs_past_int32_capacities_are_scaled_and_the_cut_still_right():
    """scipy's capacities are int32: a point that must not leave its layer at any price
    (2^32 + 10 units at full scale, which int32 would wrap to 10) beside points that weigh
    a few nats."""
    u0 = np.array([0.0, 3.0, 3.0, 0.0])
    u1 = np.array([((1 << 32) + 10) / CAPACITY_SCALE, 0.0, 0.0, 5.0])
    p = np.array([0, 1, 2])
    x = binary_cut(u0, u1, p, p + 1, np.full(3, 1.0))
    assert x.tolist() == [False, True, True, False]


def test_a_tie_keeps_the_current_layer():
    """With nothing to choose between the layers, no point changes (two layers start at
    0; more at the least costly, here the first)."""
    for k in (2, 3):
        out = complete_labels(np.full((4, 5), -1, np.int32), np.zeros((k, 4, 5), np.float32), 2.0)
        assert np.all(out == 0)
