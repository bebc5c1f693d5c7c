"""Tables stage: candidate selection and the data term."""
import numpy as np
import pytest

from stex.similarity import face_strain, local_similarity_faces, strain_similarity
from stex.tables import block_candidates, select_candidates, unary_terms


def test_select_candidates_lowest_ascending_padded():
    s = np.array([[5.0, 1.0, np.inf, 0.5, 3.0],
                  [np.inf, np.inf, 2.0, np.inf, np.inf]])
    c = select_candidates(s, 3)
    assert c.tolist() == [[1, 3, 4], [2, -1, -1]]
    assert select_candidates(s, 9)[0].tolist() == [0, 1, 3, 4, -1, -1, -1, -1, -1]


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
