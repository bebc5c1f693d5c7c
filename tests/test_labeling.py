"""Labeling: the spatiotemporal MRF (Eq. 2) by per-frame α-expansion and even/odd BCD."""
import numpy as np
import pytest

from stex.labeling import (EdgeFeatures, frame_problem, glimpse_sources, label_sequence,
                           spatial_features, temporal_cost, total_energy)


def _grid_pairs(n):
    """Faces on an n x n grid, 4-neighbour adjacency."""
    idx = np.arange(n * n).reshape(n, n)
    return np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                           np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1)])


def _problem(seed=0, T=8, n=6, K=4, S=15, n_s=9):
    rng = np.random.default_rng(seed)
    F = n * n
    pairs = _grid_pairs(n)
    vis = rng.random((T, F)) < 0.6
    vis[:, 0] = False                                         # one face never seen
    cand = np.full((T, F, K), -1, np.int16)
    unary = np.zeros((T, F, K), np.float32)
    for t in range(T):
        for f in range(F):
            frames = np.flatnonzero(vis[:, f])
            if frames.size:
                pick = np.sort(rng.choice(frames, min(K, frames.size), replace=False))
                cand[t, f, :pick.size] = pick
                unary[t, f, :pick.size] = rng.random(pick.size) + 0.3 * np.abs(pick - t) / T
    base = rng.integers(0, 255, (1, F, S))
    face_samples = np.clip(base + rng.normal(0, 20, (T, F, S)), 0, 255).astype(np.uint8)
    edge_samples = np.clip(rng.integers(0, 255, (1, len(pairs), n_s)) + rng.normal(0, 30, (T, len(pairs), n_s)), 0, 255).astype(np.uint8)
    return dict(cand=cand, unary=unary, pairs=pairs, pair_weight=np.full(len(pairs), 10.0),
                edge_samples=edge_samples, face_samples=face_samples)


def test_spatial_features_l1_is_the_edge_cost():
    rng = np.random.default_rng(3)
    a, b = rng.integers(0, 255, (2, 9)).astype(np.uint8)
    want = 0.5 * np.abs(a / 255 - b / 255).mean() + 0.5 * np.abs(np.diff(a / 255) - np.diff(b / 255)).mean()
    got = np.abs(spatial_features(a) - spatial_features(b)).sum()
    assert got == pytest.approx(want, rel=1e-5)


def test_temporal_cost_and_gates():
    fs = np.zeros((3, 2, 4), np.uint8)
    fs[1, 0] = 51
    fs[2, 0] = 255
    c = temporal_cost(fs, np.array([[1, 2], [0, -1]]), np.array([0, 1]), np.array([0, 0]))
    assert c[0].tolist() == pytest.approx([0.2, 1.0]) and c[1].tolist() == [0.0, 0.0]
    gates = np.ones((3, 2), np.float32)
    gates[2, 0] = 0.0                                      # frame 2 dynamic at face 0
    c = temporal_cost(fs, np.array([[1, 2]]), np.array([0]), np.array([0]), gates)
    assert c[0].tolist() == pytest.approx([0.2, 0.0])
    assert temporal_cost(fs, np.array([[1]]), np.array([0]), np.array([-1]))[0, 0] == 0


def test_frame_problem_nodes_edges_and_features():
    P = _problem()
    t = 3
    pr = frame_problem(P["cand"][t], P["unary"][t], P["pairs"], P["pair_weight"], EdgeFeatures(P["edge_samples"]))
    assert 0 not in pr.faces                               # never-seen face is not a node
    assert len(pr.cand_ptr) == len(pr.faces) + 1
    # every candidate of both ends of an edge has a feature row
    for e, (i, j) in enumerate(pr.edges):
        labs = set(pr.feat_label[pr.feat_ptr[e]:pr.feat_ptr[e + 1]])
        for node in (i, j):
            assert set(pr.cand_label[pr.cand_ptr[node]:pr.cand_ptr[node + 1]]) <= labs


def test_bcd_energy_never_rises_and_matches_eq2():
    P = _problem(seed=1)
    res = label_sequence(**P, omega_t=2.0, max_rounds=4, rel_tol=0.0, threads=2)
    e = res["energy"]
    assert len(e) >= 2 and np.all(np.diff(e) <= 1e-9)
    assert e[-1] < e[0]                                    # the temporal rounds did something
    assert total_energy(res["labels"], omega_t=2.0, **P) == pytest.approx(e[-1], rel=1e-9)
    L = res["labels"]
    assert (L[:, 0] == -1).all()                           # never seen: no label
    has = P["cand"][:, :, 0] >= 0
    assert (L[has] >= 0).all()                             # every face with candidates is labelled
    for t in range(L.shape[0]):                            # labels come from the candidate sets
        for f in np.flatnonzero(has[t]):
            assert L[t, f] in P["cand"][t, f]


def test_deterministic_and_threads_do_not_matter():
    P = _problem(seed=2)
    a = label_sequence(**P, omega_t=2.0, seed=5, threads=1)
    b = label_sequence(**P, omega_t=2.0, seed=5, threads=2)
    assert (a["labels"] == b["labels"]).all() and np.array_equal(a["energy"], b["energy"])


def test_alpha_expansion_not_worse_than_icm_per_frame():
    P = _problem(seed=4, n=8, K=6)
    for t in range(P["cand"].shape[0]):
        pr = frame_problem(P["cand"][t], P["unary"][t], P["pairs"], P["pair_weight"], EdgeFeatures(P["edge_samples"]))
        lab, _ = pr.solve()
        assert pr.energy(lab) <= pr.energy(pr.icm()) + 1e-9


def test_temporal_term_makes_labels_steadier():
    P = _problem(seed=6)
    off = label_sequence(**P, omega_t=0.0)
    on = label_sequence(**P, omega_t=20.0, max_rounds=6)
    switches = lambda L: int(((L[1:] != L[:-1]) & (L[1:] >= 0)).sum())
    assert switches(on["labels"]) < switches(off["labels"])


def test_glimpse_sources_pick_the_best_glimpse_of_a_source_frame():
    T, F = 5, 4
    glimpsed = np.zeros((T, F), bool)
    cos = np.zeros((T, F), np.float32)
    glimpsed[[1, 2, 3], 0] = True                 # face 0: glimpsed thrice, best at frame 3 ...
    cos[[1, 2, 3], 0] = [0.2, 0.5, 0.9]
    glimpsed[[0, 4], 1] = True                    # face 1: only by frame 4 among the sources
    cos[[0, 4], 1] = [0.9, 0.1]
    glimpsed[:, 2] = True                         # face 2: seen somewhere (not never_seen)
    cos[:, 2] = 0.7
    never = np.array([True, True, False, True])   # face 3: never seen, never glimpsed
    is_source = np.array([False, True, True, False, True])
    got = glimpse_sources(glimpsed, cos, never, is_source)
    assert got.dtype == np.int32
    assert got.tolist() == [2, 4, -1, -1]         # ... but frame 3 is not a source
    assert glimpse_sources(glimpsed, cos, never, np.ones(T, bool)).tolist() == [3, 0, -1, -1]


def test_gate_is_the_smaller_of_both_frames():
    """The selective gate multiplies E_temp by min(gate[a, f], gate[b, f]): a link is switched
    off when either end is dynamic, the neighbouring frame's label as well as the candidate."""
    fs = np.zeros((3, 1, 4), np.uint8)
    fs[2, 0] = 255
    gates = np.ones((3, 1), np.float32)
    gates[2, 0] = 0.0                                      # frame 2 dynamic at face 0
    c = temporal_cost(fs, np.array([[0, 1]]), np.array([0]), np.array([2]), gates)
    assert c[0].tolist() == [0.0, 0.0]
    assert temporal_cost(fs, np.array([[0, 1]]), np.array([0]), np.array([2]))[0].tolist() == [1.0, 1.0]


@pytest.mark.parametrize("flip", [False, True])
def test_bcd_couples_a_frame_to_both_neighbours(flip):
    """Eq. 2's temporal term links t with t - 1 and t + 1: the end frame (0, or 1 with
    ``flip``), whose only neighbour is the other frame, gives up its slightly cheaper own label
    to agree with the other frame's (whose unary strongly prefers it), as the total energy
    wants (0.1 instead of >= 1)."""
    cand = np.array([[[0, 1]], [[0, 1]]], np.int16)           # (T=2, F=1, K=2)
    unary = np.array([[[0.0, 0.1]], [[1.0, 0.0]]], np.float32)
    face_samples = np.array([[[0] * 4], [[255] * 4]], np.uint8)   # E_temp(0, 1) = 1
    if flip:
        unary, face_samples = unary[::-1].copy(), face_samples[::-1].copy()
    P = dict(cand=cand, unary=unary, pairs=np.zeros((0, 2), np.int64), pair_weight=np.zeros(0),
             edge_samples=np.zeros((2, 0, 3), np.uint8), face_samples=face_samples)
    res = label_sequence(**P, omega_t=1.0, max_rounds=4, rel_tol=0.0, threads=1)
    assert res["labels"][:, 0].tolist() == [1, 1]
    assert res["energy"][-1] == pytest.approx(0.1, rel=1e-6)
    assert total_energy(res["labels"], omega_t=1.0, **P) == pytest.approx(0.1, rel=1e-6)


def test_bcd_rounds_go_on_until_a_change_has_reached_the_end_of_the_chain():
    """One face, five frames, candidates the source frames 0, 1, 2 (E_temp 0.4 between 0 and 1,
    0.6 between either and 2). Alone, the frames pick [0, 1, 2, 2, 1]. Round 1: frame 4 takes 2
    (its neighbour's) in the even sweep, then frame 1, between 0 and 2, takes 2 in the odd one
    (1.2 against 1.3 for 0 and 1.5 for 1); frame 0, an even frame, can follow only in round 2
    (0.4 against 0.6 for keeping 0). The result is the brute-force optimum of Eq. 2 over all
    3^5 sequences (energy 2.0), which one round does not reach (2.2)."""
    import itertools

    unary = np.array([[0.0, 0.9, 0.4], [0.7, 0.5, 0.6], [0.8, 0.5, 0.3], [0.7, 0.9, 0.2], [0.4, 0.1, 0.5]],
                     np.float32)[:, None]                              # (T=5, F=1, K=3)
    face_samples = np.array([[204, 153], [102, 51], [0, 255], [153, 102], [0, 204]], np.uint8)[:, None]
    T = 5
    P = dict(cand=np.array([[[0, 1, 2]]] * T, np.int16), unary=unary, pairs=np.zeros((0, 2), np.int64),
             pair_weight=np.zeros(0), edge_samples=np.zeros((T, 0, 3), np.uint8), face_samples=face_samples)

    def eq2(L):                                    # written out: Σ unary + ω_t Σ mean|I_a − I_b| / 255
        temporal = sum(np.abs(face_samples[a, 0].astype(int) - face_samples[b, 0]).mean() / 255
                       for a, b in zip(L[:-1], L[1:]))
        return sum(float(unary[t, 0, L[t]]) for t in range(T)) + temporal

    best = min(itertools.product(range(3), repeat=T), key=eq2)
    assert best == (2, 2, 2, 2, 2) and eq2(best) == pytest.approx(2.0)
    res = label_sequence(**P, omega_t=1.0, max_rounds=4, rel_tol=1e-3, threads=1)
    assert res["labels"][:, 0].tolist() == list(best)
    assert res["energy"].tolist() == pytest.approx([2.7, 2.2, 2.0, 2.0], abs=1e-6)
    assert [r["changed"] for r in res["rounds"][1:]] == [2, 1, 0]
