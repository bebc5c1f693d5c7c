"""stex.mrf: BK max-flow against scipy, α-expansion against brute force, ICM, input checks."""

import itertools

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_flow

from stex import maxflow, mrf

# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def make_problem(rng, n, n_labels, max_subset, p_edge=0.4, k=3, n_empty=0, potts=False,
                 subsets=None, unary=(0.0, 3.0)):
    """A random MRF in stex.mrf's representation (a tuple of the 8 arrays). ``potts`` uses
    one-hot features (every label pair of an edge costs w), so c = 1 in the 2c bound."""
    if subsets is None:
        subsets = []
        for i in range(n):
            if i < n_empty:
                subsets.append(np.zeros(0, np.int64))
            else:
                size = rng.integers(1, max_subset + 1)
                subsets.append(np.sort(rng.choice(n_labels, size, replace=False)))
    cand_ptr = np.r_[0, np.cumsum([len(s) for s in subsets])].astype(np.int64)
    cand_label = np.concatenate(subsets).astype(np.int32)
    cand_cost = rng.uniform(*unary, cand_label.size)
    edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < p_edge],
                     np.int32).reshape(-1, 2)
    labs = [np.union1d(subsets[i], subsets[j]) for i, j in edges]
    feat_ptr = np.r_[0, np.cumsum([len(s) for s in labs])].astype(np.int64)
    feat_label = (np.concatenate(labs) if labs else np.zeros(0)).astype(np.int32)
    if potts:
        feat = (0.5 * np.eye(n_labels)[feat_label]).astype(np.float32)
    else:
        feat = rng.normal(0.0, 1.0, (feat_label.size, k)).astype(np.float32)
    weight = rng.uniform(0.2, 1.0, len(edges))
    return cand_ptr, cand_label, cand_cost, edges, weight, feat_ptr, feat_label, feat


def grid_problem(rng, side, n_labels, subset, k=4):
    """A side x side 4-connected grid whose subsets are windows of labels around a smooth
    per-node centre (as for faces and frames)."""
    n = side * side
    yy, xx = np.divmod(np.arange(n), side)
    centre = np.round((n_labels - subset) * (0.5 + 0.4 * np.sin(xx / 3.0) * np.cos(yy / 4.0))).astype(int)
    subsets = [np.arange(c, c + subset) for c in centre]
    prob = make_problem(rng, n, n_labels, subset, p_edge=0.0, k=k, subsets=subsets)
    right = [(i, i + 1) for i in range(n) if xx[i] < side - 1]
    down = [(i, i + side) for i in range(n) if yy[i] < side - 1]
    edges = np.array(right + down, np.int32)
    labs = [np.union1d(subsets[i], subsets[j]) for i, j in edges]
    feat_ptr = np.r_[0, np.cumsum([len(s) for s in labs])].astype(np.int64)
    feat_label = np.concatenate(labs).astype(np.int32)
    # smooth in the label plus noise, so neighbouring frames look alike
    feat = (np.sin(0.3 * feat_label[:, None] + np.arange(k)) + rng.normal(0, 0.3, (feat_label.size, k)))
    return (prob[0], prob[1], prob[2], edges, np.ones(len(edges)), feat_ptr, feat_label,
            feat.astype(np.float32))


def choices(prob):
    cand_ptr, cand_label = prob[0], prob[1]
    out = []
    for i in range(cand_ptr.size - 1):
        s = cand_label[cand_ptr[i]:cand_ptr[i + 1]]
        out.append(s if s.size else np.array([-1]))
    return out


def energies_of(prob, labelings):
    """Energy of each row of ``labelings`` (C, N), computed directly in numpy."""
    cand_ptr, cand_label, cand_cost, edges, weight, feat_ptr, feat_label, feat = prob
    labelings = np.atleast_2d(labelings)
    tot = np.zeros(labelings.shape[0])
    for i in range(cand_ptr.size - 1):
        sub = cand_label[cand_ptr[i]:cand_ptr[i + 1]]
        if sub.size:
            tot += cand_cost[cand_ptr[i] + np.searchsorted(sub, labelings[:, i])]
    for e, (u, v) in enumerate(edges):
        fl = feat_label[feat_ptr[e]:feat_ptr[e + 1]]
        fe = feat[feat_ptr[e]:feat_ptr[e + 1]].astype(np.float64)
        a, b = labelings[:, u], labelings[:, v]
        ok = (a >= 0) & (b >= 0)
        d = np.abs(fe[np.searchsorted(fl, np.where(ok, a, fl[0]))]
                   - fe[np.searchsorted(fl, np.where(ok, b, fl[0]))]).sum(axis=1)
        tot += np.where(ok, weight[e] * d, 0.0)
    return tot


def brute_force(prob):
    combos = np.array(list(itertools.product(*choices(prob))))
    en = energies_of(prob, combos)
    return combos[np.argmin(en)], en.min()


def best_expansion(prob, labels, alpha):
    """Lowest energy over all α-expansion moves from ``labels`` (brute force)."""
    cand_ptr, cand_label = prob[0], prob[1]
    var = [i for i in range(labels.size)
           if alpha in cand_label[cand_ptr[i]:cand_ptr[i + 1]] and labels[i] != alpha]
    moves = np.repeat(labels[None, :], 2 ** len(var), axis=0)
    for b, i in enumerate(var):
        take = (np.arange(2 ** len(var)) >> b) & 1 == 1
        moves[take, i] = alpha
    return energies_of(prob, moves).min()


# --------------------------------------------------------------------------------------------
# max-flow / min-cut
# --------------------------------------------------------------------------------------------


def cut_cost(side, cs, ct, ei, ej, cij, cji):
    s = side == 0
    return (cs[~s].sum() + ct[s].sum() + cij[s[ei] & ~s[ej]].sum() + cji[s[ej] & ~s[ei]].sum())


def test_min_cut_matches_scipy_max_flow():
    rng = np.random.default_rng(0)
    for _ in range(60):
        n = int(rng.integers(1, 40))
        p = int(rng.integers(0, 120))
        ei, ej = rng.integers(0, n, p), rng.integers(0, n, p)
        keep = ei != ej
        ei, ej = ei[keep], ej[keep]
        cs = rng.integers(0, 20, n) * (rng.random(n) < 0.4)
        ct = rng.integers(0, 20, n) * (rng.random(n) < 0.4)
        cij, cji = rng.integers(0, 15, ei.size), rng.integers(0, 15, ei.size)
        flow, side = maxflow.min_cut(n, cs, ct, ei, ej, cij, cji)

        s, t = n, n + 1
        rows = np.r_[np.full(n, s), np.arange(n), ei, ej]
        cols = np.r_[np.arange(n), np.full(n, t), ej, ei]
        graph = csr_matrix((np.r_[cs, ct, cij, cji].astype(np.int32), (rows, cols)), shape=(n + 2, n + 2))
        graph.sum_duplicates()
        assert flow == maximum_flow(graph, s, t).flow_value
        assert side.shape == (n,) and set(np.unique(side)) <= {0, 1}
        assert cut_cost(side, cs, ct, ei, ej, cij, cji) == flow


def test_min_cut_float_capacities_cut_equals_flow():
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = 30
        ei, ej = rng.integers(0, n, 90), rng.integers(0, n, 90)
        keep = ei != ej
        ei, ej = ei[keep], ej[keep]
        cs, ct = rng.exponential(1.0, n), rng.exponential(1.0, n)
        cij, cji = rng.exponential(0.5, ei.size), rng.exponential(0.5, ei.size)
        flow, side = maxflow.min_cut(n, cs, ct, ei, ej, cij, cji)
        assert cut_cost(side, cs, ct, ei, ej, cij, cji) == pytest.approx(flow, rel=1e-12)
        # no other cut is cheaper
        for _ in range(50):
            other = rng.integers(0, 2, n)
            assert cut_cost(other, cs, ct, ei, ej, cij, cji) >= flow - 1e-9


def test_min_cut_small_cases():
    # no pairs: each node pays the smaller terminal capacity, and goes where that is cheaper
    flow, side = maxflow.min_cut(3, [5.0, 1.0, 2.0], [1.0, 4.0, 2.0], [], [], [], [])
    assert flow == 1.0 + 1.0 + 2.0
    assert side.tolist() == [0, 1, 1]   # ties (node 2) go to the sink side
    flow, side = maxflow.min_cut(0, [], [], [], [], [], [])
    assert flow == 0.0 and side.shape == (0,)
    # s -> 0 -> 1 -> t chain with a bottleneck in the middle
    flow, side = maxflow.min_cut(2, [3.0, 0.0], [0.0, 3.0], [0], [1], [1.0], [0.0])
    assert flow == 1.0 and side.tolist() == [0, 1]


@pytest.mark.parametrize("kwargs, match", [
    (dict(source_cap=[-1.0, 0.0]), "source_cap"),
    (dict(cap_ij=[-2.0]), "cap_ij"),
    (dict(edge_j=[0]), "self-loop"),
    (dict(edge_j=[5]), "outside"),
    (dict(sink_cap=[0.0]), "sink_cap"),
    (dict(cap_ji=[1.0, 2.0]), "cap_ji"),
    (dict(source_cap=[np.nan, 0.0]), "not finite"),
])
def test_min_cut_bad_input(kwargs, match):
    args = dict(n=2, source_cap=[1.0, 0.0], sink_cap=[0.0, 1.0], edge_i=[0], edge_j=[1], cap_ij=[1.0], cap_ji=[0.0])
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        maxflow.min_cut(**args)


# --------------------------------------------------------------------------------------------
# energy, ICM, α-expansion
# --------------------------------------------------------------------------------------------


def test_energy_matches_direct_sum():
    rng = np.random.default_rng(2)
    prob = make_problem(rng, 7, 6, 3, n_empty=2, k=5)
    combos = np.array(list(itertools.product(*choices(prob))))[::7]
    direct = energies_of(prob, combos)
    for lab, e in zip(combos, direct):
        assert mrf.energy(lab, *prob) == pytest.approx(e, rel=1e-12, abs=1e-12)


def test_alpha_expansion_within_factor_two_of_optimum_for_potts():
    # the α-expansion bound E <= 2c E* (c = 1 for Potts, unaries >= 0)
    rng = np.random.default_rng(3)
    for _ in range(25):
        prob = make_problem(rng, int(rng.integers(3, 9)), 4, 3, n_empty=1, potts=True)
        labels, en = mrf.alpha_expansion(*prob, tol=0.0)
        _, e_opt = brute_force(prob)
        assert en[-1] == pytest.approx(mrf.energy(labels, *prob), rel=1e-12)
        assert e_opt - 1e-9 <= en[-1] <= 2.0 * e_opt + 1e-9


def test_alpha_expansion_is_optimal_over_expansion_moves():
    # for L1-metric features: the result is within 2c of the optimum, and no α move improves it
    rng = np.random.default_rng(4)
    for _ in range(20):
        prob = make_problem(rng, int(rng.integers(3, 9)), 5, 3, n_empty=1, k=4)
        labels, en = mrf.alpha_expansion(*prob, tol=0.0, max_cycles=50)
        _, e_opt = brute_force(prob)
        pair = [abs(prob[7][a].astype(float) - prob[7][b].astype(float)).sum() * w
                for e, w in enumerate(prob[4])
                for a in range(prob[5][e], prob[5][e + 1]) for b in range(a + 1, prob[5][e + 1])]
        c = max(pair) / min(pair) if pair else 1.0
        assert e_opt - 1e-9 <= en[-1] <= 2.0 * c * e_opt + 1e-9
        for alpha in np.unique(prob[1]):
            assert best_expansion(prob, labels, alpha) >= en[-1] - 1e-9


def test_alpha_expansion_binary_problems_reach_the_optimum():
    rng = np.random.default_rng(5)
    for _ in range(20):
        n = int(rng.integers(2, 9))
        a, b = np.sort(rng.choice(10, 2, replace=False))
        prob = make_problem(rng, n, 10, 2, p_edge=0.5, subsets=[np.array([a, b])] * n,
                            k=int(rng.integers(1, 4)), unary=(0.0, 1.5))
        labels, en = mrf.alpha_expansion(*prob, tol=0.0)
        _, e_opt = brute_force(prob)
        assert en[-1] == pytest.approx(e_opt, rel=1e-9, abs=1e-12)


def test_alpha_expansion_energies_non_increasing_and_consistent():
    rng = np.random.default_rng(6)
    prob = grid_problem(rng, 16, 40, 8)
    labels0 = mrf.icm(*prob, max_sweeps=1)
    labels, en = mrf.alpha_expansion(*prob, labels0=labels0, tol=0.0, max_cycles=30)
    assert en.size >= 3
    assert np.all(np.diff(en) <= 0.0)
    assert en[0] == pytest.approx(mrf.energy(labels0, *prob), rel=1e-12)
    assert en[-1] == pytest.approx(mrf.energy(labels, *prob), rel=1e-12)
    assert en[-1] < en[0]
    # converged (tol=0 and the last cycle changed nothing): a restart changes nothing
    again, en2 = mrf.alpha_expansion(*prob, labels0=labels, tol=0.0, seed=9)
    assert np.array_equal(again, labels) and en2.size == 2 and en2[1] == en2[0]


def test_alpha_expansion_beats_icm():
    rng = np.random.default_rng(7)
    for _ in range(4):
        prob = grid_problem(rng, 14, 30, 6)
        lab_icm = mrf.icm(*prob)
        lab_ae, en = mrf.alpha_expansion(*prob)
        assert en[-1] <= mrf.energy(lab_icm, *prob)
        assert en[-1] < en[0]


def test_alpha_expansion_deterministic_and_valid():
    rng = np.random.default_rng(8)
    prob = make_problem(rng, 60, 12, 5, p_edge=0.08, n_empty=3, k=3)
    l1, e1 = mrf.alpha_expansion(*prob, seed=3)
    l2, e2 = mrf.alpha_expansion(*prob, seed=3)
    assert np.array_equal(l1, l2) and np.array_equal(e1, e2)
    assert l1.dtype == np.int32
    assert (l1[:3] == -1).all()
    cand_ptr, cand_label = prob[0], prob[1]
    for i in range(3, 60):
        assert l1[i] in cand_label[cand_ptr[i]:cand_ptr[i + 1]]
    # max_cycles=0 returns the initial labeling (the unary argmin, lowest label on ties)
    l0, e0 = mrf.alpha_expansion(*prob, max_cycles=0)
    argmin = [cand_label[cand_ptr[i] + np.argmin(prob[2][cand_ptr[i]:cand_ptr[i + 1]])] for i in range(3, 60)]
    assert l0[3:].tolist() == argmin and e0.size == 1


def test_icm_is_a_local_minimum():
    rng = np.random.default_rng(9)
    prob = make_problem(rng, 40, 10, 4, p_edge=0.1, n_empty=2, k=3)
    start = mrf.icm(*prob, max_sweeps=1)
    labels = mrf.icm(*prob)
    e = mrf.energy(labels, *prob)
    assert e <= mrf.energy(start, *prob)
    cand_ptr, cand_label = prob[0], prob[1]
    for i in range(40):
        for lab in cand_label[cand_ptr[i]:cand_ptr[i + 1]]:
            trial = labels.copy()
            trial[i] = lab
            assert mrf.energy(trial, *prob) >= e - 1e-9
    assert np.array_equal(mrf.icm(*prob), labels)


def test_nodes_with_empty_subsets_are_ignored():
    rng = np.random.default_rng(10)
    prob = make_problem(rng, 6, 4, 3, p_edge=1.0, n_empty=2, k=2)
    labels, en = mrf.alpha_expansion(*prob, tol=0.0)
    assert (labels[:2] == -1).all()
    # an edge to an empty node costs nothing: the energy equals the MRF without those nodes
    cand_ptr, cand_label, cand_cost, edges, w, feat_ptr, feat_label, feat = prob
    keep = (edges >= 2).all(axis=1)
    rows = np.concatenate([np.arange(feat_ptr[e], feat_ptr[e + 1]) for e in np.flatnonzero(keep)])
    sub = (cand_ptr[2:] - cand_ptr[2], cand_label[cand_ptr[2]:], cand_cost[cand_ptr[2]:], edges[keep] - 2,
           w[keep], np.r_[0, np.cumsum(np.diff(feat_ptr)[keep])], feat_label[rows], feat[rows])
    assert en[-1] == pytest.approx(mrf.energy(labels[2:], *sub), rel=1e-12)
    _, e_opt = brute_force(sub)
    assert en[-1] >= e_opt - 1e-9


def _chain(subsets, costs, edges=(), weights=(), feat=None):
    """A problem from per-node label lists and unary costs; every edge carries the 1-D feature
    ``feat[label]`` for every label of the problem."""
    labels = sorted({l for sub in subsets for l in sub})
    cand_ptr = np.r_[0, np.cumsum([len(x) for x in subsets])].astype(np.int64)
    edges = np.array(edges, np.int32).reshape(-1, 2)
    feat_label = np.tile(labels, len(edges)).astype(np.int32)
    feat_rows = (np.array([[feat[l]] for l in labels] * len(edges), np.float32) if len(edges)
                 else np.zeros((0, 1), np.float32))
    return (cand_ptr, np.concatenate(subsets).astype(np.int32), np.concatenate(costs).astype(float), edges,
            np.array(weights, float), np.arange(len(edges) + 1) * len(labels), feat_label, feat_rows)


def test_ties_keep_the_lowest_label_at_start_and_the_current_one_after():
    """No edges. Node 0: labels 2, 5, 7 at unary 1, 0.5, 0.5; node 1: labels 1, 3 at 0.2 both. The
    start is the unary argmin with the lowest label on ties, [5, 1]; from [7, 3] nothing moves
    (ICM changes only on a strict decrease, an expansion only when the energy drops)."""
    prob = _chain([[2, 5, 7], [1, 3]], [[1.0, 0.5, 0.5], [0.2, 0.2]])
    assert mrf.alpha_expansion(*prob, max_cycles=0)[0].tolist() == [5, 1]
    assert mrf.alpha_expansion(*prob)[0].tolist() == [5, 1]
    assert mrf.icm(*prob).tolist() == [5, 1]
    assert mrf.icm(*prob, labels0=[7, 3]).tolist() == [7, 3]
    labels, en = mrf.alpha_expansion(*prob, labels0=[7, 3], tol=0.0)
    assert labels.tolist() == [7, 3] and en.tolist() == [0.7, 0.7]


def test_icm_sweeps_until_a_sweep_changes_nothing():
    """A chain 0 - 1 - 2 (weights 1, 2), labels {0, 1} with features 0 and 1 (a change costs the
    weight), unaries node 0: 0, 0.5; node 1: 0, 0.2; node 2: 5, 0. From [0, 0, 0] each sweep (in
    node order) changes one node: node 2 takes 1 (2 < 5), then node 1 (1.2 < 2), then node 0
    (0.5 < 1); [1, 1, 1] (energy 0.7) is the brute-force optimum."""
    prob = _chain([[0, 1]] * 3, [[0.0, 0.5], [0.0, 0.2], [5.0, 0.0]], [(0, 1), (1, 2)], [1.0, 2.0],
                  feat={0: 0.0, 1: 1.0})
    best, e_best = brute_force(prob)
    assert best.tolist() == [1, 1, 1] and e_best == pytest.approx(0.7)
    assert mrf.icm(*prob, labels0=[0, 0, 0]).tolist() == [1, 1, 1]
    assert mrf.icm(*prob, labels0=[0, 0, 0], max_sweeps=1).tolist() == [0, 0, 1]


def test_expansion_label_order_cycles_and_stopping_rule():
    """Node 0 holds labels 0, 1 (unaries 0, 1), node 1 labels 2, 3 (unaries 3, 0); one edge,
    features 0, 2, 0, 2 (a mismatch costs 2). From [0, 2] (energy 3) expanding label 1 does not
    pay (6) until node 1 has taken label 3 (energy 2); then it does (energy 1, the optimum).
    A cycle tries the labels in a seeded random order: label 3 first gives energies 3 -> 1 in one
    cycle, label 1 first 3 -> 2 and label 1 must be tried again in the next cycle, as node 0's
    neighbour changed. Both orders occur over ten seeds. With tol = 0.4 the run stops after a
    cycle that lowers the energy by less than 0.4 x its energy before (1 < 1.2, not 2)."""
    prob = _chain([[0, 1], [2, 3]], [[0.0, 1.0], [3.0, 0.0]], [(0, 1)], [1.0],
                  feat={0: 0.0, 1: 2.0, 2: 0.0, 3: 2.0})
    assert brute_force(prob)[0].tolist() == [1, 3]
    firsts = set()
    for seed in range(10):
        one = mrf.alpha_expansion(*prob, labels0=[0, 2], max_cycles=1, tol=0.0, seed=seed)
        label1_first = one[1].tolist() == [3.0, 2.0]
        assert one[1].tolist() == ([3.0, 2.0] if label1_first else [3.0, 1.0])
        firsts.add(label1_first)
        labels, en = mrf.alpha_expansion(*prob, labels0=[0, 2], tol=0.0, seed=seed)
        assert labels.tolist() == [1, 3]
        assert en.tolist() == ([3.0, 2.0, 1.0, 1.0] if label1_first else [3.0, 1.0, 1.0])
        labels, en = mrf.alpha_expansion(*prob, labels0=[0, 2], tol=0.4, seed=seed)
        assert en.tolist() == ([3.0, 2.0] if label1_first else [3.0, 1.0, 1.0])
    assert firsts == {True, False}


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------


@pytest.fixture
def small():
    return list(make_problem(np.random.default_rng(11), 5, 6, 3, p_edge=1.0, k=2))


def test_bad_problem_arrays_raise(small):
    def bad(i, value, match):
        p = list(small)
        p[i] = value
        for fn in (lambda: mrf.alpha_expansion(*p), lambda: mrf.icm(*p)):
            with pytest.raises(ValueError, match=match):
                fn()

    cand_ptr, cand_label, cand_cost, edges, w, feat_ptr, feat_label, feat = small
    bad(2, cand_cost[:-1], "cand_cost")
    bad(1, cand_label[:-1], "cand_label")
    bad(0, cand_ptr[:-1] if cand_ptr.size > 2 else cand_ptr, "cand_label|cand_ptr|edges")
    unsorted = cand_label.copy()
    node = int(np.flatnonzero(np.diff(cand_ptr) >= 2)[0])
    unsorted[cand_ptr[node]:cand_ptr[node] + 2] = unsorted[cand_ptr[node]:cand_ptr[node] + 2][::-1]
    bad(1, unsorted, f"node {node} must be strictly increasing")
    bad(4, -w, "edge_weight.*negative")
    bad(4, w[:-1], "edge_weight")
    bad(3, np.r_[edges, [[0, 0]]], "edges|self-loop")
    loops = edges.copy()
    loops[0, 1] = loops[0, 0]
    bad(3, loops, "self-loop")
    out = edges.copy()
    out[0, 0] = 99
    bad(3, out, "outside")
    bad(7, feat[:-1], "feat")
    unsorted_f = feat_label.copy()
    unsorted_f[feat_ptr[0]:feat_ptr[0] + 2] = unsorted_f[feat_ptr[0]:feat_ptr[0] + 2][::-1]
    bad(6, unsorted_f, "feat_label of edge 0")
    nan = feat.copy()
    nan[0, 0] = np.nan
    bad(7, nan, "not finite")
    # a candidate label without a feature on an incident edge
    e = 0
    p = list(small)
    drop = feat_ptr[e]
    p[5] = np.r_[feat_ptr[:e + 1], feat_ptr[e + 1:] - 1]
    p[6] = np.delete(feat_label, drop)
    p[7] = np.delete(feat, drop, axis=0)
    with pytest.raises(ValueError, match=f"edge {e} .* no feature for label {feat_label[drop]}"):
        mrf.alpha_expansion(*p)


def test_bad_labels_raise(small):
    cand_ptr, cand_label = small[0], small[1]
    labels = mrf.icm(*small)
    outside = labels.copy()
    sub = cand_label[cand_ptr[2]:cand_ptr[3]]
    outside[2] = next(x for x in range(100) if x not in sub)
    with pytest.raises(ValueError, match=r"labels0\[2\].*not in node 2"):
        mrf.alpha_expansion(*small, labels0=outside)
    with pytest.raises(ValueError, match=r"labels0\[2\]"):
        mrf.icm(*small, labels0=outside)
    with pytest.raises(ValueError, match=r"labels\[2\]"):
        mrf.energy(outside, *small)
    missing = labels.copy()
    missing[1] = -1
    with pytest.raises(ValueError, match=r"labels0\[1\]"):
        mrf.alpha_expansion(*small, labels0=missing)
    with pytest.raises(ValueError, match="labels0 must have shape"):
        mrf.alpha_expansion(*small, labels0=labels[:-1])
    for tol in (-1.0, None, "0.1", float("nan")):
        with pytest.raises(ValueError, match="tol must be a finite number >= 0"):
            mrf.alpha_expansion(*small, tol=tol)
    # edges and pointers in any integer type or byte order give the same labels
    want = mrf.alpha_expansion(*small)[0]
    for i, dtype in ((3, ">i8"), (3, np.uint8), (0, ">i4"), (5, np.uint16)):
        p = list(small)
        p[i] = np.asarray(p[i]).astype(dtype)
        np.testing.assert_array_equal(mrf.alpha_expansion(*p)[0], want)
