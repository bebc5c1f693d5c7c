"""Tables stage: candidate selection and the data term."""
import numpy as np
import pytest

from stex.similarity import local_similarity_faces
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


@pytest.mark.parametrize("similarity", ["both", "global", "local"])
def test_pruned_candidates_equal_full_ranking_where_exact(similarity):
    """Where the stage claims its prefilter is exact, the K best by the full data term (computed
    over every visible frame) are exactly the candidates it kept."""
    rng = np.random.default_rng(1)
    faces, vis, qual, desc, _ = _random_case(rng)
    K, t = 3, 5
    glo_rows = rng.random((2, 12)).astype(np.float32)
    res = block_candidates([t, 7], glo_rows, vis, qual, desc, faces, 0.9, similarity, K,
                           prefilter=5, median_hops=1)[0]
    glo = glo_rows[0]
    loc = local_similarity_faces(desc, faces, [(t, l) for l in range(12)], median_hops=1).T
    u = unary_terms(qual.T, glo[None, :], loc, 0.9, similarity)
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
