"""Tables stage: candidate selection and the data term."""
import numpy as np
import pytest

from stex.camera import Calibration, Intrinsics
from stex.io import create_store, open_store

from stex.similarity import face_strain, local_similarity_faces, strain_similarity
from stex.data_term import (block_candidates, finish_candidates, prefilter_candidates, select_candidates,
                            unary_terms)
from stex.stages.data_term import write_data_term


def test_select_candidates_lowest_ascending_padded():
    s = np.array([[5.0, 1.0, np.inf, 0.5, 3.0],
                  [np.inf, np.inf, 2.0, np.inf, np.inf]])
    c = select_candidates(s, 3)
    assert c.tolist() == [[1, 3, 4], [2, -1, -1]]
    assert select_candidates(s, 9)[0].tolist() == [0, 1, 3, 4, -1, -1, -1, -1, -1]


def test_select_candidates_match_a_full_sort():
    """Against a stable full sort of every row: the k smallest finite scores (distinct here), as
    ascending column indices, -1 padding; also for k equal to and above the row length."""
    rng = np.random.default_rng(12)
    s = rng.random((40, 30))
    s[rng.random(s.shape) < 0.3] = np.inf
    for k in (1, 2, 5, 9, 30, 33):
        want = np.full((40, k), -1)
        for r, row in enumerate(s):
            best = [c for c in np.argsort(row, kind="stable")[:k] if np.isfinite(row[c])]
            want[r, :len(best)] = sorted(best)
        assert np.array_equal(select_candidates(s, k), want), k


def _random_case(rng, T=12, F=30, V=25, D=8):
    faces = np.array([rng.choice(V, 3, replace=False) for _ in range(F)])
    vis = rng.random((T, F)) < 0.7
    qual = rng.integers(0, 3, (T, F)).astype(np.float32)
    desc = rng.random((T, V, D)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=2, keepdims=True)
    glo = rng.random(T).astype(np.float32)
    return faces, vis, qual, desc, glo


@pytest.mark.parametrize("omega_str", [0.0, 0.7])
@pytest.mark.parametrize("similarity", ["both", "global", "local"])
def test_pruned_candidates_equal_full_ranking_where_exact(similarity, omega_str):
    """Where the stage claims its prefilter is exact, the K best by the full data term (computed
    over every visible frame) are exactly the candidates it kept, with or without E_str."""
    rng = np.random.default_rng(1)
    faces, vis, qual, desc, _ = _random_case(rng)
    strain = rng.normal(0, 0.05, (12, len(faces), 3)).astype(np.float32)
    K, t = 3, 5
    glo_rows = rng.random((2, 12)).astype(np.float32)
    res = block_candidates([t, 7], glo_rows, vis, qual, desc, faces, 0.9, similarity, K,
                           prefilter=5, median_hops=1, strain=strain, omega_str=omega_str,
                           str_clip=0.1)[0]
    glo = glo_rows[0]
    loc = local_similarity_faces(desc, faces, [(t, l) for l in range(12)], median_hops=1).T
    e_str = strain_similarity(strain, t, 0.1).T
    u = unary_terms(qual.T, glo[None, :], loc, 0.9, similarity, e_str, omega_str)
    if omega_str and similarity != "global":
        assert (res["e_str"] > 0).any()
    best = select_candidates(np.where(vis.T, u, np.inf), K)
    ex = res["exact"]
    assert ex.any()
    assert (res["candidates"][ex] == best[ex]).all()
    # the stored terms are those of the kept frames
    f = int(np.flatnonzero(ex & (res["candidates"][:, 0] >= 0))[0])
    l = int(res["candidates"][f, 0])
    assert res["e_qual"][f, 0] == qual[l, f] and res["e_glo"][f, 0] == pytest.approx(glo[l])


def test_target_groups_do_not_change_the_candidates():
    """E_loc computed for a few targets at a time (memory bound) equals all targets at once."""
    rng = np.random.default_rng(2)
    faces, vis, qual, desc, _ = _random_case(rng)
    glo_rows = rng.random((3, 12)).astype(np.float32)
    args = ([2, 5, 9], glo_rows, vis, qual, desc, faces, 0.9, "both", 3)
    one = block_candidates(*args, prefilter=6, median_hops=1, target_group=1)
    together = block_candidates(*args, prefilter=6, median_hops=1, target_group=3)
    assert any((r["e_loc"] != 0).any() for r in one)
    for a, b in zip(one, together):
        for name in ("candidates", "e_loc", "e_glo", "e_qual"):
            assert np.array_equal(a[name], b[name])


@pytest.mark.parametrize("similarity, str_row, want", [
    # U = E_qual + 0.9 E_glo + 0.1 E_loc: frame 0 scores 0.9 - 0.1, frame 1 0.97 - 0.1 (E_loc -1 both)
    ("both", None, 0),
    # U = E_qual + E_glo: 1.0 against 0.97 (0.9 against 0.97 were E_glo weighted by ω_g)
    ("global", None, 1),
    # U = E_qual + (1 + E_loc) + 0.5 E_str: 0 + 0 + 0.5 against 0.97 (1.0 were E_str unweighted)
    ("local", np.array([[1.0], [0.0]]), 0),
])
def test_prefilter_weights_the_terms_as_the_data_term(similarity, str_row, want):
    """With room for one frame, the prefilter must keep the frame the full data term ranks first
    (E_loc = -1 for both frames, so it cannot change their order): it weights E_glo and E_str as
    U does. Frame 0: E_qual 0, E_glo 1 (E_str 1); frame 1: E_qual 0.97, E_glo 0 (E_str 0)."""
    vis = np.ones((2, 1), bool)
    qual = np.array([[0.0], [0.97]], np.float32)
    glo = np.array([1.0, 0.0], np.float32)
    pre_c, pre = prefilter_candidates(glo, vis, qual, 0.9, similarity, 1, str_row, 0.5)
    assert pre_c.tolist() == [[want]]
    res = finish_candidates(pre_c, pre, glo, vis, qual, np.full((1, 1), -1.0), 0.9, similarity, 1,
                            str_row, 0.5)
    assert res["candidates"].tolist() == [[want]]
    assert res["e_qual"][0, 0] == qual[want, 0] and res["e_glo"][0, 0] == glo[want]


def test_prefilter_exact_flag_is_the_pruning_bound():
    """``exact`` holds where no frame left out by the prefilter could beat the K-th kept one:
    its pre-score is at least the worst kept one, P, and E_loc lowers it by at most 1 - ω_g = 0.1
    (E_glo = 0 here, so pre-score = E_qual). Prefilter 2 of 3 frames, K = 1, E_loc of the first
    kept frame as given, 0 for the second.
    Face 0: kept 0.2 and 0.9 (E_loc 0): 0.2 <= 0.9 - 0.1, exact (not with the best kept, 0.2).
    Face 1: kept 0.5 (E_loc -0.5: U = 0.45) and 0.52; the frame left out (0.53) could reach 0.43.
    Face 2: seen in 2 frames only, both kept: nothing left out, exact although 0.45 > 0.42.
    'global' has no E_loc (U = pre-score): with K < prefilter the bound always holds."""
    qual = np.array([[0.2, 0.5, 0.5], [0.9, 0.52, 0.52], [1.0, 0.53, 0.0]], np.float32)
    vis = np.ones((3, 3), bool)
    vis[2, 2] = False
    glo = np.zeros(3, np.float32)
    loc = np.array([[0.0, 0.0], [-0.5, 0.0], [-0.5, 0.0]])
    for similarity, want in (("both", [True, False, True]), ("global", [True, True, True])):
        pre_c, pre = prefilter_candidates(glo, vis, qual, 0.9, similarity, 2)
        assert pre_c.tolist() == [[0, 1]] * 3
        res = finish_candidates(pre_c, pre, glo, vis, qual, loc, 0.9, similarity, 1)
        assert res["candidates"].tolist() == [[0]] * 3
        assert res["exact"].tolist() == want, similarity


def test_faces_seen_in_few_frames_keep_only_those():
    """A face seen in fewer frames than the prefilter keeps exactly those, even when an unseen
    frame (here frame 0, of E_qual 0) would score best: the prefilter's padding is no candidate."""
    vis = np.array([[False], [True], [True]])
    qual = np.array([[0.0], [0.5], [0.7]], np.float32)
    res = block_candidates([0], np.zeros((1, 3), np.float32), vis, qual, None, np.array([[0, 1, 2]]),
                           0.9, "global", 2, prefilter=3)[0]
    assert res["candidates"].tolist() == [[1, 2]]
    assert np.array_equal(res["e_qual"], qual[1:].T)


def test_unary_modes():
    q, g, l = np.float32(1), np.float32(0.5), np.float32(-0.8)
    assert unary_terms(q, g, l, 0.9, "both") == pytest.approx(1 + 0.45 - 0.08)
    assert unary_terms(q, g, l, 0.9, "global") == pytest.approx(1.5)
    assert unary_terms(q, g, l, 0.9, "local") == pytest.approx(1.2)
    with pytest.raises(ValueError):
        unary_terms(q, g, l, 0.9, "neither")


def test_unary_strain_term():
    q, g, l, st = np.float32(1), np.float32(0.5), np.float32(-0.8), np.float32(0.5)
    assert unary_terms(q, g, l, 0.9, "both", st, 0.4) == pytest.approx(1 + 0.45 - 0.08 + 0.2)
    assert unary_terms(q, g, l, 0.9, "local", st, 0.4) == pytest.approx(1.2 + 0.2)
    assert unary_terms(q, g, l, 0.9, "global", st, 0.4) == pytest.approx(1.5)  # a local term
    assert unary_terms(q, g, l, 0.9, "both", None, 0.4) == pytest.approx(1 + 0.45 - 0.08)


def _strip(n=6):
    """A flat strip of 2 (n - 1) triangles along x (unit squares), z = 0."""
    x = np.arange(n, dtype=np.float64)
    V = np.concatenate([np.stack([x, np.zeros(n), np.zeros(n)], 1),
                        np.stack([x, np.ones(n), np.zeros(n)], 1)])
    F = [[i, i + 1, n + i] for i in range(n - 1)] + [[i + 1, n + i + 1, n + i] for i in range(n - 1)]
    return V, np.array(F)


def test_face_strain_measures_stretch_not_rigid_motion():
    V, F = _strip()
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    squeezed = V * [0.8, 1.0, 1.0]
    frames = np.stack([V @ R.T + [0.3, -2, 5], squeezed])
    S = face_strain(frames, V, F, rings=0)
    assert np.abs(S[0]).max() < 1e-6                       # rigid: no strain
    # edge v0 -> v1 of the first triangles runs along x: ln 0.8; v2 -> v0 runs along y: 0
    assert S[1, :5, 0] == pytest.approx(np.log(0.8), abs=1e-6)
    assert S[1, :5, 2] == pytest.approx(0.0, abs=1e-6)
    smooth = face_strain(frames, V, F, rings=2)
    assert np.abs(smooth[0]).max() < 1e-6
    # E_str: the squeezed frame differs from the rigid one by |ln 0.8| + the diagonal's change
    E = strain_similarity(S, 0, clip=1.0)
    assert E[0].max() == 0 and (E[1] > 0.2).all()
    assert strain_similarity(S, 0, clip=0.1)[1].max() == 1.0  # clipped
    with pytest.raises(ValueError, match="zero-length edge"):
        face_strain(frames, V * [0, 1, 1], F)
    collapsed = face_strain(np.stack([V, V * [0, 1, 1]]), V, F, rings=0)
    assert np.isfinite(collapsed).all()
    assert strain_similarity(collapsed, 0)[1].min() == 1.0


def test_strain_term_prefers_the_source_with_the_targets_compression():
    """Two sources equal in every paper term; the one whose surface is compressed like the
    target's ranks first once E_str has weight, and E_str is stored with the candidates."""
    V, F = _strip()
    T = 3
    frames = np.stack([V * [0.85, 1, 1], V, V * [0.86, 1, 1]])  # target 0 compressed like 2
    strain = face_strain(frames, V, F, rings=1)
    vis = np.ones((T, len(F)), bool)
    vis[0] = False                                                # the target does not see them
    qual = np.zeros((T, len(F)), np.float32)
    glo = np.zeros((1, T), np.float32)
    desc = np.ones((T, len(V), 4), np.float32) / 2.0
    paper = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2,
                             median_hops=0)[0]
    ours = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2,
                            median_hops=0, strain=strain, omega_str=1.0, str_clip=0.1)[0]
    assert (paper["candidates"][:, 0] == 1).all()                 # ties go to the lower index
    assert (ours["candidates"][:, 0] == 2).all()
    assert (ours["e_str"][:, 0] < 0.2).all()


def test_strain_tolerance_applies_to_faces_the_target_does_not_see():
    """A strain difference within the tolerance (drift of a surface that does not deform) does not
    rank the sources of a face the target does not see: the tie goes back to the other terms. On
    a face the target sees every difference counts."""
    V, F = _strip()
    T = 3
    frames = np.stack([V * [0.98, 1, 1], V, V * [0.985, 1, 1]])  # differences of a drift's size
    strain = face_strain(frames, V, F, rings=1)
    vis = np.ones((T, len(F)), bool)
    unseen = np.arange(len(F)) % 2 == 0
    vis[0, unseen] = False                                        # the target sees the odd faces only
    qual = np.zeros((T, len(F)), np.float32)
    glo = np.zeros((1, 2), np.float32)
    desc = np.ones((T, len(V), 4), np.float32) / 2.0
    # the target is compared with frames 1 and 2 only (candidate pruning's sources), so a face it
    # sees does not simply take its own frame
    kw = dict(median_hops=0, strain=strain, omega_str=1.0, str_clip=0.1, sources=np.array([[1, 2]]))
    exact = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2, **kw)[0]
    tolerant = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2,
                                str_tolerance=0.1, **kw)[0]
    assert (exact["candidates"][:, 0] == 2).all()                 # the nearer strain wins
    assert (tolerant["candidates"][unseen, 0] == 1).all()         # within the tolerance: a tie
    assert (tolerant["e_str"][unseen, 0] == 0).all()
    assert (tolerant["candidates"][~unseen, 0] == 2).all()        # seen at t: unchanged
    np.testing.assert_array_equal(tolerant["e_str"][~unseen], exact["e_str"][~unseen])


def test_borrowed_quality_weight_lets_shape_rank_the_faces_the_target_does_not_see():
    """On a face the target does not see, the texture is borrowed: with the quality weighted
    down, a blurry frame (E_qual 1) of the target's shape beats a sharp frame of another shape
    (E_glo 0.5). On a face the target sees, the sharp frame still wins."""
    V, F = _strip()
    T = 3
    vis = np.ones((T, len(F)), bool)
    unseen = np.arange(len(F)) % 2 == 0
    vis[0, unseen] = False
    qual = np.zeros((T, len(F)), np.float32)
    qual[1] = 1.0                                                 # frame 1 is blurry, frame 2 sharp
    glo = np.array([[0.0, 0.5]], np.float32)                      # frame 1 has the target's shape
    desc = np.ones((T, len(V), 4), np.float32) / 2.0
    kw = dict(median_hops=0, sources=np.array([[1, 2]]))
    same = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2, **kw)[0]
    shape_first = block_candidates([0], glo, vis, qual, desc, F, 0.9, "both", 1, prefilter=2,
                                   borrowed_qual_weight=0.2, **kw)[0]
    assert (same["candidates"][:, 0] == 2).all()                  # 1.0 + 0 > 0 + 0.45
    assert (shape_first["candidates"][unseen, 0] == 1).all()      # 0.2 + 0 < 0 + 0.45
    np.testing.assert_allclose(shape_first["e_qual"][unseen, 0], 0.2)   # as the labeling weighs it
    assert (shape_first["candidates"][~unseen, 0] == 2).all()


def _stores(d, blur, slanted, vis):
    """The input stores of :func:`write_data_term` for a static square (2 faces) seen from 1 m, with
    identity poses (E_glo = 0) and the given blur_cost, slanted and face_visible (T, 2)."""
    T = len(blur)
    ids = list(range(10, 10 + T))
    V = np.array([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.1, 0.1, 1.0], [-0.1, 0.1, 1.0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    cam = Intrinsics.from_focal(40.0, 40.0, 15.5, 15.5, 32, 32)
    with create_store(d / "scene.zarr", "scene", attrs={
            "calibration": Calibration(cam, cam, np.eye(4)).to_dict(), "frame_ids": ids,
            "frame_blocks": [[0, T]], "has_template": False}):
        pass
    with create_store(d / "template.zarr", "template", attrs={"atlas_size": 4}) as s:
        for name, a in (("vertices", V), ("faces", F), ("texcoords", V[:, :2]), ("texcoord_faces", F),
                        ("face_chart", np.zeros(2)), ("adjacency/pairs", [[0, 1]]),
                        ("adjacency/edges", [[0, 2]]), ("texel/face_id", -np.ones((4, 4))),
                        ("texel/bary", np.zeros((4, 4, 3))), ("embedding/face", np.zeros(4)),
                        ("embedding/bary", np.zeros((4, 3)))):
            s.write(name, np.asarray(a))
    with create_store(d / "tracking.zarr", "tracking", attrs={"frame_ids": ids, "mode": "given"}) as s:
        s.write("vertices", np.repeat(V[None], T, axis=0))
        for name in ("residual_m", "n_correspondences", "seconds", "silhouette_iou", "depth_fit_m"):
            s.write(name, np.zeros(T))
    with create_store(d / "poses.zarr", "poses", attrs={"frame_ids": ids}) as s:
        i, j = np.triu_indices(T, 1)
        s.write("pairs", np.stack([i, j], axis=1))
        s.write("poses", np.broadcast_to(np.eye(4), (i.size, 4, 4)).copy())
        s.write("inlier_ratio", np.ones(i.size))
        s.write("neighbours", np.broadcast_to(np.arange(T), (T, T)).copy())
        s.write("descriptors", np.zeros((T, 1)))
    with create_store(d / "observations.zarr", "observations", attrs={"frame_ids": ids}) as s:
        s.write("face_samples", np.zeros((T, 2, 15)))
        s.write("edge_samples", np.zeros((T, 1, 9)))
        s.write("face_visible", np.asarray(vis, bool))
        s.write("motion", np.zeros((T, 2)))
        s.write("blur_cost", np.asarray(blur, np.float32))
        s.write("slanted", np.asarray(slanted, bool))
    return [d / f"{n}.zarr" for n in ("scene", "template", "tracking", "poses", "observations")]


def test_write_tables_quality_term_and_source_stride(tmp_path):
    """The stage ranks by E_qual = blur_cost + slanted ('global' similarity, E_glo = 0 for the
    static mesh), among the visible frames at the source positions 0, k, 2k, ... only; prefilter
    may equal candidates.
    Face 0: E_qual 0.5, 0, 0.1 + 1, 0.9, 0.3, 0.2 -> best two [1, 5]; sources 0, 2, 4: [0, 4].
    Face 1: E_qual 0.4, 0.3, 0.2, 0.1, (unseen), 0.6 -> [2, 3]; sources 0, 2: [0, 2]."""
    blur = np.array([[0.5, 0.4], [0.0, 0.3], [0.1, 0.2], [0.9, 0.1], [0.3, 0.0], [0.2, 0.6]])
    slanted = np.zeros((6, 2), bool)
    slanted[2, 0] = True
    vis = np.ones((6, 2), bool)
    vis[4, 1] = False
    paths = _stores(tmp_path, blur, slanted, vis)
    for stride, want in ((1, [[1, 5], [2, 3]]), (2, [[0, 4], [0, 2]])):
        out = tmp_path / f"tables_{stride}.zarr"
        write_data_term(*paths, [0, 6], {"similarity": "global", "candidates": 2, "prefilter": 2,
                                      "omega_str": 0.0, "source_stride": stride}, out)
        tab = open_store(out, "data_term")
        assert tab.attrs["source_frames"] == [10, 11, 12, 13, 14, 15][::stride]
        assert (tab["glo"][...] == 0).all()
        for t in range(6):                      # E_glo = 0: the same candidates for every target
            assert tab["candidates"][t].tolist() == want, (stride, t)
        e_qual = blur + slanted
        np.testing.assert_allclose(tab["e_qual"][0], [e_qual[want[0], 0], e_qual[want[1], 1]], rtol=1e-6)
