"""Candidate pruning (stex.pruning): the pair set, and that pruning nothing reproduces the full tables."""

import numpy as np
import pytest
from conftest import tiny_scene_config

from stex import poses as poses_mod
from stex.io import open_store
from stex.labeling import label_sequence
from stex.pruning import directed_poses, nearest_sources, pair_index, pose_pairs, shape_descriptors
from stex.stages.data_term import write_data_term
from stex.stages.labeling import labeling_inputs
from stex.stages.poses import read_pose_table, write_pose_table


def test_nearest_sources_hold_each_frames_k_nearest_and_each_faces():
    rng = np.random.default_rng(1)
    T, F, k = 30, 40, 4
    desc = rng.normal(size=(T, 3))
    vis = rng.random((T, F)) < 0.3
    vis[:, 0] = False
    vis[[3, 17], 0] = True                       # a face only two far frames see
    nb = nearest_sources(desc, vis, k)
    d = np.linalg.norm(desc[:, None] - desc[None], axis=2)
    for t in range(T):
        row = set(nb[t][nb[t] >= 0].tolist())
        seeing = np.flatnonzero(vis.any(axis=1))
        nearest = seeing[np.argsort(d[t, seeing], kind="stable")[:k]]
        assert set(nearest.tolist()) <= row, t
        assert t in row or not vis[t].any()
        for f in range(F):                       # every face keeps its k nearest frames that see it
            v = np.flatnonzero(vis[:, f])
            assert set(v[np.argsort(d[t, v], kind="stable")[:k]].tolist()) <= row, (t, f)
        assert {3, 17} <= row
    # with less coverage: still the k nearest, and every face seen by some frame keeps one
    nb1 = nearest_sources(desc, vis, k, coverage=1)
    assert (nb1 >= 0).sum() < (nb >= 0).sum()
    for t in range(T):
        row = nb1[t][nb1[t] >= 0]
        seeing = np.flatnonzero(vis.any(axis=1))
        assert set(seeing[np.argsort(d[t, seeing], kind="stable")[:k]].tolist()) <= set(row.tolist())
        assert (vis[row].any(axis=0) == vis.any(axis=0)).all(), t
    # only source frames are chosen
    src = np.arange(T) % 3 == 0
    nb3 = nearest_sources(desc, vis, k, src)
    assert src[nb3[nb3 >= 0]].all()
    # the pairs hold every (target, source) once, unordered
    pairs = pose_pairs(nb)
    assert (pairs[:, 0] < pairs[:, 1]).all() and len({tuple(p) for p in pairs}) == len(pairs)
    t, l = np.nonzero(nb >= 0)
    assert (pair_index(pairs, T, t, nb[t, l]) >= -1).all()
    with pytest.raises(ValueError, match="has no pose"):
        pair_index(pairs[1:], T, pairs[:1, 0], pairs[:1, 1])


def _turning_visibility(T=60, F=90, width=12):
    """A turning object: face f is seen by the frames of a window that moves with f."""
    t = np.arange(T)[:, None]
    f = np.arange(F)[None]
    return ((t - f * T / F) % T) < width


def test_set_cover_covers_every_owed_face_with_fewer_frames():
    rng = np.random.default_rng(2)
    T, k, c = 60, 3, 2
    vis = _turning_visibility(T)
    desc = np.cumsum(rng.normal(size=(T, 4)), axis=0)
    walk = nearest_sources(desc, vis, k, coverage=c)
    cover = nearest_sources(desc, vis, k, coverage=c, mode="cover")
    d = np.linalg.norm(desc[:, None] - desc[None], axis=2)
    need = np.minimum(c, vis.sum(axis=0))
    for t in range(T):
        row = cover[t][cover[t] >= 0]
        nearest = np.argsort(np.where(np.arange(T) == t, -1.0, d[t]), kind="stable")[:k]
        assert set(nearest.tolist()) <= set(row.tolist()), t
        assert (vis[row].sum(axis=0) >= need).all(), t       # every face keeps its owed frames
    assert (cover >= 0).sum() < (walk >= 0).sum()
    assert len(pose_pairs(cover)) < len(pose_pairs(walk))
    # ratio 1 is the plain greedy cover: here its first pick after t covers the most owed faces
    one = nearest_sources(desc, vis, 1, coverage=1, mode="cover", cover_ratio=1.0)
    for t in range(T):
        row = one[t][one[t] >= 0]
        assert (vis[row].sum(axis=0) >= 1).all()
        gain = (vis & ~vis[t][None]).sum(axis=1)              # owed faces each frame sees after t
        assert gain[row[row != t]].max() == gain.max(), t
    with pytest.raises(ValueError, match="coverage_mode"):
        nearest_sources(desc, vis, k, mode="cover2")
    with pytest.raises(ValueError, match="cover_ratio"):
        nearest_sources(desc, vis, k, mode="cover", cover_ratio=0.0)


def test_shape_descriptor_ignores_rigid_motion():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(1, 200, 3)).repeat(4, axis=0)
    X[2] += 0.05 * rng.normal(size=(200, 3))     # frame 2 deforms
    c, s = np.cos(0.7), np.sin(0.7)
    X[1] = X[1] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [0.3, -0.1, 1.0]
    D = shape_descriptors(X, n_vertices=100)
    dist = np.linalg.norm(D - D[0], axis=1)
    assert dist[1] < 1e-6 and dist[3] < 1e-6 and dist[2] > 0.1


def test_pruned_pose_pairs_equal_the_full_table():
    """A pair's pose does not depend on which other pairs are computed."""
    rng = np.random.default_rng(2)
    V = rng.normal(size=(60, 3)) * 0.1 + [0, 0, 1]
    X = np.stack([V + 0.002 * rng.normal(size=V.shape) for _ in range(5)])
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6]])
    full, ratio = poses_mod.pose_table(X, faces)
    pairs = np.array([[0, 3], [1, 4], [2, 3]])
    P, r = poses_mod.pair_poses(X, faces, pairs)
    np.testing.assert_array_equal(P, full[pairs[:, 0], pairs[:, 1]])
    np.testing.assert_array_equal(r, ratio[pairs[:, 0], pairs[:, 1]])
    D = directed_poses(pairs, P, 5, np.array([3, 0, 2]), np.array([0, 0, 3]))
    np.testing.assert_array_equal(D[0], full[3, 0])
    np.testing.assert_array_equal(D[1], np.eye(4))
    np.testing.assert_array_equal(D[2], full[2, 3])


def _tables(P, d, k, cfg):
    poses = d / f"poses_{k}.zarr"
    write_pose_table(P["tracking"], poses, dict(cfg["poses"], nearest_frames=k), faces=P["template"],
                     visibility=P["projection"])
    blocks = open_store(P["scene"], "scene").attrs["frame_blocks"]
    out = [d / f"data_term_{k}_{b}.zarr" for b in range(len(blocks))]
    for path, rng in zip(out, blocks):
        write_data_term(P["scene"], P["template"], P["tracking"], poses, P["observations"], rng,
                        cfg["data_term"], path)
    return poses, out


def test_pruning_with_k_of_all_frames_reproduces_the_full_tables(tiny_pipeline, tmp_path):
    cfg = tiny_scene_config(template={"atlas_size": 256})
    P = tiny_pipeline
    T = len(open_store(P["observations"], "observations").attrs["frame_ids"])
    full_poses, full = _tables(P, tmp_path, 0, cfg)
    all_poses, pruned = _tables(P, tmp_path, T - 1, cfg)
    a, b = read_pose_table(full_poses), read_pose_table(all_poses)
    np.testing.assert_array_equal(a["pairs"], b["pairs"])
    np.testing.assert_array_equal(a["poses"], b["poses"])
    for fa, fb in zip(full, pruned):
        ga, gb = open_store(fa, "data_term"), open_store(fb, "data_term")
        for name in ("candidates", "e_glo", "e_loc", "e_qual", "e_str"):
            np.testing.assert_array_equal(ga[name][...], gb[name][...], err_msg=name)
        # E_glo rows: the same values at the sources kept
        cols = gb["glo_sources"][...]
        rows = np.broadcast_to(np.arange(cols.shape[0])[:, None], cols.shape)
        ok = cols >= 0
        np.testing.assert_array_equal(ga["glo"][...][rows[ok], cols[ok]], gb["glo"][...][ok])
    la = label_sequence(**_solve_args(P, full, cfg))["labels"]
    lb = label_sequence(**_solve_args(P, pruned, cfg))["labels"]
    np.testing.assert_array_equal(la, lb)
    # pruning to 2 frames per face: fewer pairs, every candidate among the target's sources
    few_poses, few = _tables(P, tmp_path, 2, cfg)
    c = read_pose_table(few_poses)
    assert len(c["pairs"]) <= len(a["pairs"])
    for path in few:
        g = open_store(path, "data_term")
        cand, cols = g["candidates"][...], g["glo_sources"][...]
        for t in range(cand.shape[0]):
            got = cand[t][cand[t] >= 0]
            assert np.isin(got, cols[t]).all()


def _solve_args(P, blocks, cfg):
    args = labeling_inputs(P["observations"], blocks, P["template"], cfg["labeling"])
    args.pop("frame_ids")
    args.pop("never_seen")
    return dict(args, threads=1)


def test_sparse_e_glo_and_candidates_equal_the_dense_ones():
    """global_similarity and block_candidates over an explicit source list give the dense
    tables' values at those sources; a source list of every frame gives the dense tables."""
    import dataclasses

    from stex.data_term import block_candidates
    from stex.similarity import global_similarity
    from stex.synth.procedural import ProceduralBody

    b = ProceduralBody(dataclasses.replace(ProceduralBody().p, n_around=16, n_rings=8))
    T = 7
    X = np.stack([b.vertices(0.2 * t) + [0, 0, 1.2] for t in range(T)])
    F = b.faces
    Pd, _ = poses_mod.pose_table(X, F)
    K = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
    dense = global_similarity(X, F, Pd, K, 80, 60, targets=[1, 4])
    cols = np.array([[0, 1, 5, -1], [2, 3, 4, 6]])
    tt = np.array([[1], [4]]).repeat(4, axis=1)
    Ps = Pd[tt, np.where(cols >= 0, cols, tt)]
    sparse = global_similarity(X, F, Ps, K, 80, 60, targets=[1, 4], sources=cols)
    ok = cols >= 0
    np.testing.assert_array_equal(sparse[ok], dense[np.nonzero(ok)[0], cols[ok]])
    assert sparse[0, 3] == 1.0
    rng = np.random.default_rng(3)
    vis = rng.random((T, len(F))) < 0.6
    e_qual = rng.random((T, len(F))).astype(np.float32)
    desc = rng.random((T, len(X[0]), 8)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=2, keepdims=True)
    strain = rng.normal(scale=0.05, size=(T, len(F), 3)).astype(np.float32)
    args = (vis, e_qual, desc, F, 0.9, "both", 3, 4)
    kw = dict(strain=strain, omega_str=1.0)
    a = block_candidates([1, 4], dense, *args, **kw)
    every = np.broadcast_to(np.arange(T), (2, T))
    c = block_candidates([1, 4], dense, *args, sources=every, **kw)
    for x, y in zip(a, c):
        for name in ("candidates", "e_glo", "e_loc", "e_qual", "e_str"):
            np.testing.assert_array_equal(x[name], y[name], err_msg=name)
    # pruned: every candidate is one of the target's sources
    p = block_candidates([1, 4], sparse, *args, sources=cols, **kw)
    for k in range(2):
        got = p[k]["candidates"]
        assert np.isin(got[got >= 0], cols[k][cols[k] >= 0]).all()
