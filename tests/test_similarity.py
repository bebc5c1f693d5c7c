"""stex.similarity: E_glo from depth renders, geodesic neighbourhoods, SHOT, E_loc."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from stex import shot
from stex import similarity as S
from stex.camera import transform_points
from stex.render import rasterize
from stex.synth.shapes import bumpy_sphere

K = np.array([[80.0, 0.0, 49.5], [0.0, 80.0, 44.5], [0.0, 0.0, 1.0]])
W, H = 100, 90


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@pytest.fixture(scope="module")
def blob():
    """A small self-occluding bumpy sphere (642 vertices, 1280 faces) 1.2 m from the camera."""
    return bumpy_sphere(subdivisions=3, radius=0.3, distance=1.2)


def _bend(V, centre, amount):
    """Push the vertices above the centre (image up = -y) towards the camera, smoothly."""
    h = np.clip((centre[1] - V[:, 1]) / 0.3, 0.0, None)
    out = V.copy()
    out[:, 2] -= amount * h ** 2
    return out


@pytest.fixture(scope="module")
def sequence(blob):
    """4 frames: frames 0-2 the blob moved rigidly, frame 3 moved and bent; exact poses."""
    V, F = blob
    c = V.mean(axis=0)
    X, M = [], []
    for t in range(4):
        Mt = np.eye(4)
        Mt[:3, :3] = _rot_y(0.2 * t)
        Mt[:3, 3] = c - Mt[:3, :3] @ c + [0.02 * t, -0.01 * t, 0.0]
        M.append(Mt)
        X.append(transform_points(Mt, V))
    # the bend is applied in the object frame, then moved like frame 3
    X[3] = transform_points(M[3], _bend(V, c, 0.06))
    X = np.stack(X)
    P = np.stack([[M[l] @ np.linalg.inv(M[t]) for l in range(4)] for t in range(4)])
    return X, F, P


def _brute_glo(X, F, P, t, l, clip):
    a = rasterize(transform_points(P[t, l], X[t]), F, K, W, H).depth.astype(np.float64)
    b = rasterize(X[l], F, K, W, H).depth.astype(np.float64)
    union = (a > 0) | (b > 0)
    d = np.where((a > 0) & (b > 0), np.minimum(clip, np.abs(a - b)), clip)
    return d[union].sum() / union.sum() / clip


# --------------------------------------------------------------------------------------------
# E_glo
# --------------------------------------------------------------------------------------------

def test_global_similarity_rigid_zero_bend_positive_and_bounded(sequence):
    X, F, P = sequence
    G = S.global_similarity(X, F, P, K, W, H)
    assert G.shape == (4, 4) and G.dtype == np.float32
    assert np.all(np.diag(G) == 0.0)
    rigid = G[:3, :3]
    assert np.abs(rigid).max() < 1e-6            # exact pose, rigid motion: identical renders
    assert G[:3, 3].min() > 0.02 and G[3, :3].min() > 0.02   # the bend shows
    assert G.min() >= 0.0 and G.max() <= 1.0


def test_global_similarity_grows_with_the_bend(blob):
    V, F = blob
    c = V.mean(axis=0)
    X = np.stack([V] + [_bend(V, c, a) for a in (0.01, 0.03, 0.08)])
    P = np.broadcast_to(np.eye(4), (4, 4, 4, 4)).copy()
    row = S.global_similarity(X, F, P, K, W, H, targets=[0])[0]
    assert row[0] == 0.0
    assert 0.0 < row[1] < row[2] < row[3] <= 1.0


def test_global_similarity_matches_brute_force(sequence):
    X, F, P = sequence
    for clip in (0.1, 0.01):
        G = S.global_similarity(X, F, P, K, W, H, clip_m=clip)
        B = np.array([[0.0 if t == l else _brute_glo(X, F, P, t, l, clip) for l in range(4)]
                      for t in range(4)])
        np.testing.assert_allclose(G, B, atol=1e-6)
    # a tighter clip saturates more pixels: the normalised values grow
    assert S.global_similarity(X, F, P, K, W, H, clip_m=0.01)[3, 0] > \
        S.global_similarity(X, F, P, K, W, H, clip_m=0.1)[3, 0]


def test_global_similarity_targets_threads_and_scale(sequence):
    X, F, P = sequence
    full = S.global_similarity(X, F, P, K, W, H)
    sub = S.global_similarity(X, F, P, K, W, H, targets=[3, 1], threads=2)
    np.testing.assert_array_equal(sub, full[[3, 1]])
    half = S.global_similarity(X, F, P, K, W, H, scale=0.5)
    assert np.all(np.diag(half) == 0.0) and np.abs(half[:3, :3]).max() < 1e-6
    np.testing.assert_allclose(half[3, :3], full[3, :3], atol=0.05)  # same quantity, coarser
    assert S.global_similarity(X, F, P, K, W, H, targets=[]).shape == (0, 4)


def test_global_similarity_bad_input(sequence):
    X, F, P = sequence
    with pytest.raises(ValueError, match="poses must have shape"):
        S.global_similarity(X, F, P[:3, :3], K, W, H)
    Pn = P.copy()
    Pn[1, 2, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"poses\[1, 2\]"):
        S.global_similarity(X, F, Pn, K, W, H)
    with pytest.raises(ValueError, match="targets"):
        S.global_similarity(X, F, P, K, W, H, targets=[4])
    with pytest.raises(ValueError, match="clip_m"):
        S.global_similarity(X, F, P, K, W, H, clip_m=0.0)
    with pytest.raises(ValueError, match="scale"):
        S.global_similarity(X, F, P, K, W, H, scale=-1)
    Xn = X.copy()
    Xn[2, 5, 1] = np.inf
    with pytest.raises(ValueError, match="frame 2, vertex 5"):
        S.global_similarity(Xn, F, P, K, W, H)
    with pytest.raises(ValueError, match="faces index out of range"):
        S.global_similarity(X, F + X.shape[1], P, K, W, H)


# --------------------------------------------------------------------------------------------
# neighbourhoods
# --------------------------------------------------------------------------------------------

def test_geodesic_neighbourhoods_match_scipy_and_exceed_euclidean(blob):
    V, F = blob
    R = 4.0 * shot.mesh_resolution(V, F)
    ptr, idx, dist = shot.geodesic_neighbourhoods(V, F, R)
    assert ptr.dtype == np.int64 and idx.dtype == np.int32 and dist.dtype == np.float32
    assert ptr.shape == (V.shape[0] + 1,)
    rows = np.repeat(np.arange(V.shape[0]), np.diff(ptr))
    # each list starts with the vertex itself and is sorted by distance
    assert np.all(idx[ptr[:-1]] == np.arange(V.shape[0])) and np.all(dist[ptr[:-1]] == 0)
    assert np.all(np.diff(dist)[np.diff(rows) == 0] >= 0)
    # scipy on the same edge graph
    e = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    G = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(V), len(V))).tocsr()
    D = dijkstra(G, directed=False, limit=R)
    within = np.isfinite(D) & (D <= R)
    assert within.sum() == idx.size
    assert within[rows, idx].all()
    np.testing.assert_allclose(dist, D[rows, idx], rtol=1e-6, atol=1e-7)
    # path lengths are never shorter than the straight line
    eu = np.linalg.norm(V[rows] - V[idx], axis=1)
    assert np.all(dist >= eu * (1 - 1e-6))


def test_vertex_rings_are_k_hop_sets():
    # a strip of 4 triangles: 0-1-2 / 1-3-2 / 2-3-4 / 3-5-4 (a path-like graph)
    F = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    ptr, idx = S.vertex_rings(F, 6, 1)
    assert idx[ptr[0]:ptr[1]].tolist() == [0, 1, 2]
    ptr, idx = S.vertex_rings(F, 6, 2)
    assert idx[ptr[0]:ptr[1]].tolist() == [0, 1, 2, 3, 4]
    ptr, idx = S.vertex_rings(F, 6, 0)
    assert idx.tolist() == list(range(6))


# --------------------------------------------------------------------------------------------
# SHOT
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def shot_setup(blob):
    V, F = blob
    R = 5.0 * shot.mesh_resolution(V, F)
    nbh = shot.geodesic_neighbourhoods(V, F, R)
    return V, F, R, nbh, shot.shot_descriptors(V, F, nbh, radius_m=R)


def test_shot_unit_and_rigid_invariant(shot_setup):
    V, F, R, nbh, d = shot_setup
    assert d.shape == (V.shape[0], shot.SHOT_DIM) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert d.min() >= 0.0
    M = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    M[:3, :3] = _rot_y(1.1) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    M[:3, 3] = [0.3, -0.2, 0.5]
    d2 = shot.shot_descriptors(transform_points(M, V), F, nbh, radius_m=R)
    diff = np.linalg.norm(d - d2, axis=1)
    assert np.median(diff) < 1e-5
    assert np.mean(diff > 1e-3) < 0.02   # only sign-tie vertices may flip
    # descriptors distinguish places: a vertex is most similar to itself
    sims = d[:50] @ d.T
    assert np.all(np.argmax(sims, axis=1) == np.arange(50))


def test_shot_changes_near_a_local_bend_only(shot_setup):
    V, F, R, nbh, d = shot_setup
    # dent: push the vertices within 0.1 m of one vertex inwards
    c = V[0]
    r = np.linalg.norm(V - c, axis=1)
    moved = r < 0.1
    n = V[0] - V.mean(axis=0)
    n /= np.linalg.norm(n)
    Vb = V - (0.05 * np.clip(1 - r / 0.1, 0, None) ** 2)[:, None] * n
    d2 = shot.shot_descriptors(Vb, F, nbh, radius_m=R)
    diff = np.linalg.norm(d - d2, axis=1)
    edge = np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).max()
    far = r > 0.1 + R + 2 * edge         # no moved vertex in the support nor in a neighbour's 1-ring
    assert far.sum() > 100 and moved.sum() > 10
    assert diff[far].max() < 1e-6
    assert np.median(diff[moved]) > 0.05


def test_shot_radius_float_and_bad_input(shot_setup):
    V, F, R, nbh, d = shot_setup
    np.testing.assert_array_equal(shot.shot_descriptors(V, F, R), shot.shot_descriptors(V, F, nbh, radius_m=R))
    with pytest.raises(ValueError, match="neighbourhoods ptr"):
        shot.shot_descriptors(V[:-1], F[np.all(F < len(V) - 1, axis=1)], nbh, radius_m=R)
    with pytest.raises(ValueError, match="radius_m is required"):
        shot.shot_descriptors(V, F, nbh)
    with pytest.raises(ValueError, match="radius_m"):
        shot.geodesic_neighbourhoods(V, F, 0.0)
    with pytest.raises(ValueError, match="vertices"):
        shot.shot_descriptors(V[:, :2], F, nbh, radius_m=R)


# --------------------------------------------------------------------------------------------
# E_loc
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def desc_seq(blob):
    V, F = blob
    R = 5.0 * shot.mesh_resolution(V, F)
    nbh = shot.geodesic_neighbourhoods(V, F, R)
    c = V.mean(axis=0)
    X = [V, _bend(V, c, 0.02), _bend(V, c, 0.06), transform_points(np.diag([1, 1, 1, 1.0]), V) + 0.1]
    return F, np.stack([shot.shot_descriptors(x, F, nbh, radius_m=R) for x in X])


def _brute_loc(D, F, rings, t, l):
    rp, ri = rings
    s = (D[t].astype(np.float64) * D[l]).sum(axis=1)
    med = np.array([np.median(s[ri[rp[v]:rp[v + 1]]]) for v in range(D.shape[1])])
    return -med[F].mean(axis=1)


def test_median_filter_matches_numpy(blob):
    V, F = blob
    rings = S.vertex_rings(F, len(V), 2)
    vals = np.random.default_rng(1).random((3, len(V)))
    got = S.median_filter_vertices(vals, rings)
    rp, ri = rings
    ref = np.array([[np.median(r[ri[rp[v]:rp[v + 1]]]) for v in range(len(V))] for r in vals])
    np.testing.assert_allclose(got, ref, rtol=1e-6)
    np.testing.assert_allclose(S.median_filter_vertices(vals[0], rings), ref[0], rtol=1e-6)


def test_local_similarity_faces_matches_brute_force(desc_seq):
    F, D = desc_seq
    pairs = np.array([[0, 1], [2, 0], [1, 1], [3, 0], [0, 2]])
    rings = S.vertex_rings(F, D.shape[1], 2)
    E = S.local_similarity_faces(D, F, pairs, target_chunk=2)
    assert E.shape == (5, F.shape[0]) and E.dtype == np.float32
    for k, (t, l) in enumerate(pairs):
        np.testing.assert_allclose(E[k], _brute_loc(D, F, rings, t, l), atol=1e-5)
    assert np.allclose(E[2], -1.0, atol=1e-5)     # a frame against itself
    assert np.allclose(E[3], -1.0, atol=1e-5)     # a translated copy
    assert E.min() >= -1.0 - 1e-5 and E.max() <= 0.0
    assert E[4].mean() > E[0].mean()              # the stronger bend is less similar
    # no filtering: the plain face mean of per-vertex dot products
    E0 = S.local_similarity_faces(D, F, pairs[:2], median_hops=0)
    np.testing.assert_allclose(E0[0], -S.vertex_similarity(D[0], D[1])[F].mean(axis=1), atol=1e-6)


def test_local_similarity_triples_equal_faces(desc_seq):
    F, D = desc_seq
    rng = np.random.default_rng(0)
    n = 400
    t, f, l = rng.integers(0, 4, n), rng.integers(0, F.shape[0], n), rng.integers(0, 4, n)
    got = S.local_similarity_triples(D, F, t, f, l, target_chunk=3)
    full = S.local_similarity_faces(D, F, np.stack([t, l], axis=1))
    np.testing.assert_array_equal(got, full[np.arange(n), f])


def test_local_similarity_float16_storage(desc_seq):
    F, D = desc_seq
    pairs = np.array([[0, 2], [1, 2]])
    E32 = S.local_similarity_faces(D, F, pairs)
    E16 = S.local_similarity_faces(D.astype(np.float16), F, pairs)
    assert np.abs(E16 - E32).max() < 1e-3


def test_local_similarity_bad_input(desc_seq):
    F, D = desc_seq
    with pytest.raises(ValueError, match="pairs"):
        S.local_similarity_faces(D, F, [0, 1])
    with pytest.raises(ValueError, match="sources"):
        S.local_similarity_faces(D, F, [[0, 9]])
    with pytest.raises(ValueError, match="descriptors must have shape"):
        S.local_similarity_faces(D[0], F, [[0, 1]])
    with pytest.raises(ValueError, match="face_ids"):
        S.local_similarity_triples(D, F, [0], [F.shape[0]], [1])
    with pytest.raises(ValueError, match="one length"):
        S.local_similarity_triples(D, F, [0, 1], [0], [1])
    Dn = D.copy()
    Dn[2, 7, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        S.local_similarity_faces(Dn, F, [[0, 2]])
    Dh = D.astype(np.float16)
    Dh[2, 7, 3] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        S.local_similarity_triples(Dh, F, [0], [int(np.flatnonzero((F == 7).any(axis=1))[0])], [2])


def test_global_similarity_is_zero_for_an_empty_union(blob):
    """Both meshes outside the image (empty union of the silhouettes) give 0, as the authors'
    code (module docstring), not the clip."""
    V, F = blob
    X = np.stack([V, V + [100.0, 0.0, 0.0]])               # frame 1 far to the side of the view
    P = np.broadcast_to(np.eye(4), (2, 2, 4, 4)).copy()
    P[0, 1, 0, 3], P[1, 0, 0, 3] = 100.0, -100.0          # exact poses
    G = S.global_similarity(X, F, P, K, W, H)
    assert G[0, 1] == 0.0                                  # K(M_0) = M_1: both off the image
    assert G[1, 0] == 0.0                                  # both in view and identical


def _grid(n=3, step=1.0):
    """n x n vertex grid in the plane z = 1 with spacing ``step`` (vertex r * n + c at
    (c, r) * step), two triangles per cell split along the (r, c) -> (r+1, c+1) diagonal."""
    r, c = np.divmod(np.arange(n * n), n)
    V = np.stack([c * step, r * step, np.ones(n * n)], 1).astype(float)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return V, np.array(F)


def test_geodesic_neighbourhood_includes_the_radius():
    """"Within radius_m" includes a neighbour at exactly the radius: on the unit grid the corner
    reaches its two edge neighbours (1), the diagonal (√2) and the vertices two edges away (2)
    with R = 2, but nothing further (1 + √2)."""
    V, F = _grid(3)
    ptr, idx, dist = shot.geodesic_neighbourhoods(V, F, 2.0)
    got = dict(zip(idx[ptr[0]:ptr[1]].tolist(), dist[ptr[0]:ptr[1]].tolist()))
    assert got == pytest.approx({0: 0.0, 1: 1.0, 3: 1.0, 4: np.sqrt(2), 2: 2.0, 6: 2.0})


def test_shot_needs_three_neighbours_in_the_support():
    """A vertex with fewer than 3 neighbours within R gets an all-zero descriptor. On a square
    of two triangles split along the diagonal 0-3 with R = 1.5 edges, vertices 0 and 3 have the
    other three within R (at 1, 1 and √2), vertices 1 and 2 only two (the opposite corner is
    2 edges away)."""
    V, F = _grid(2, 0.01)                                   # 0 (0,0), 1 (1,0), 2 (0,1), 3 (1,1)
    d = shot.shot_descriptors(V, F, 0.015)
    np.testing.assert_allclose(np.linalg.norm(d[[0, 3]], axis=1), 1.0, atol=1e-6)
    assert not d[[1, 2]].any()


def test_shot_flat_patch_fills_the_cos_one_bin_only():
    """SHOT's 11 bins per volume hold cos(neighbour normal, z) from -1 (bin 0) to 1 (bin 10):
    on a flat patch every normal is z, so all the mass is in bin 10 of the volumes."""
    V, F = _grid(7, 0.01)
    d = shot.shot_descriptors(V, F, 0.035)
    centre = 3 * 7 + 3
    h = d[centre].reshape(32, 11)
    assert h.sum() > 0 and not h[:, :10].any()


def test_face_strain_smoothing_averages():
    """The smoothing passes average the faces sharing a vertex: a uniform scale s stretches
    every edge by ln s, and an average of equal values leaves them unchanged at any ring count."""
    V, F = _grid(4, 0.01)
    X = np.stack([V * 1.1, V])
    for rings in (0, 1, 3):
        st = S.face_strain(X, V, F, rings=rings)
        np.testing.assert_allclose(st[0], np.log(1.1), atol=1e-6)
        np.testing.assert_allclose(st[1], 0.0, atol=1e-7)


def test_strain_similarity_is_the_clipped_l1_difference():
    """E_str = min(1, Σ_k |s_k(t) − s_k(l)| / clip), worked by hand."""
    st = np.zeros((3, 2, 3), np.float32)
    st[1, 0] = [0.01, -0.02, 0.03]                           # L1 distance 0.06 from frame 0
    st[1, 1] = [0.2, 0.0, 0.0]                              # 0.2: clipped
    st[2, 0] = [0.01, -0.02, 0.03]
    st[2, 1] = [0.0, 0.04, 0.0]
    E = S.strain_similarity(st, 0, clip=0.1)
    np.testing.assert_allclose(E, [[0, 0], [0.6, 1.0], [0.6, 0.4]], atol=1e-6)
    np.testing.assert_allclose(S.strain_similarity(st, 1, clip=0.1)[2], [0.0, 1.0], atol=1e-6)


def test_strain_similarity_tolerance_ignores_small_differences():
    """With a tolerance the difference is reduced by it before the clip, worked by hand: a drift
    of a surface that does not deform (small differences) no longer ranks frames."""
    st = np.zeros((3, 2, 3), np.float32)
    st[1, 0] = [0.01, -0.02, 0.03]                           # L1 distance 0.06: within the tolerance
    st[1, 1] = [0.2, 0.0, 0.0]                              # 0.2 - 0.08 = 0.12: clipped
    st[2, 1] = [0.0, 0.13, 0.0]                             # 0.13 - 0.08 = 0.05 -> 0.5
    E = S.strain_similarity(st, 0, clip=0.1, tolerance=0.08)
    np.testing.assert_allclose(E, [[0, 0], [0.0, 1.0], [0.0, 0.5]], atol=1e-6)
    # with sources (padding -1 stays fully dissimilar)
    Es = S.strain_similarity(st, 0, clip=0.1, sources=np.array([2, -1]), tolerance=0.08)
    np.testing.assert_allclose(Es, [[0.0, 0.5], [1.0, 1.0]], atol=1e-6)
    # one tolerance per face: face 0 without, face 1 with
    Ef = S.strain_similarity(st, 0, clip=0.1, tolerance=np.array([0.0, 0.08]))
    np.testing.assert_allclose(Ef, [[0, 0], [0.6, 1.0], [0.0, 0.5]], atol=1e-6)
    for bad in (-0.1, np.array([0.1, 0.1, 0.1])):
        with pytest.raises(ValueError, match="tolerance"):
            S.strain_similarity(st, 0, tolerance=bad)


def test_strain_noise_measures_the_still_faces_and_scales_with_the_drift():
    """The strain noise is the typical change of the stillest faces: a surface three quarters
    still (strain moved only by a drift) and a quarter deforming strongly gives about the drift's
    size, twice the drift gives twice the noise, and the deforming quarter does not raise it.
    A frame the caller leaves out (a lost track's garbage) does not count."""
    rng = np.random.default_rng(0)
    T, F = 20, 400
    drift = rng.standard_normal((T, F, 3)) * 0.01
    deform = np.zeros((T, F, 3))
    deform[:, :100] = np.sin(np.linspace(0, 6, T))[:, None, None] * 0.3   # a quarter folds
    a = S.strain_noise(drift + deform)
    b = S.strain_noise(2 * drift + deform)
    assert b == pytest.approx(2 * a, rel=0.1)
    assert a == pytest.approx(S.strain_noise(drift), rel=0.2)            # the folds do not count
    # three edges, each |N(0, 0.01²)| off its median: about 3 × 0.0067 at the median frame
    assert 0.01 < a < 0.03
    bad = drift + deform
    bad[5] = 5.0
    keep = np.ones(T, bool)
    keep[5] = False
    assert S.strain_noise(bad, keep) == pytest.approx(S.strain_noise(np.delete(bad, 5, 0)))
    assert S.strain_noise(bad[:1]) == 0.0
    with pytest.raises(ValueError, match="strain"):
        S.strain_noise(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="frames"):
        S.strain_noise(bad, keep[:-1])


@pytest.mark.parametrize("d_over_r, outer_share", [(0.1, 0.0), (0.35, 0.05), (0.6, 0.925), (0.9, 1.0)])
def test_shot_splits_a_neighbour_between_the_radial_shells(d_over_r, outer_share):
    """SHOT's two radial shells meet at R/2, and a neighbour's vote is shared with the other
    shell by linear interpolation between the shells' middles (R/4, 3R/4; Tombari et al. and
    PCL): each neighbour casts 4 units (cosine, radial, elevation and azimuth interpolation,
    one each), of which only the radial unit can cross shells: rd = (d − R/4)/(R/2) of it goes
    out from the inner shell beyond R/4, |d − 3R/4|/(R/2) in from the outer shell below 3R/4.
    Eight neighbours in a ring at distance d in the tangent plane: the outer shell's share of the
    descriptor's sum is 0 (d = 0.1 R: inner, below R/4), 0.2/4 (0.35 R), 1 − 0.3/4 (0.6 R) and 1
    (0.9 R: outer, beyond 3R/4)."""
    R = 0.02
    ring = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    V = np.concatenate([[[0.0, 0.0, 0.0]],
                        np.stack([np.cos(ring), np.sin(ring), np.zeros(8)], 1) * d_over_r * R])
    F = np.array([[0, 1 + k, 1 + (k + 1) % 8] for k in range(8)])      # a fan facing +z
    nbh = (np.array([0, 8] + [8] * 8), np.arange(1, 9))                  # vertex 0's neighbours only
    desc = shot.shot_descriptors(V, F, nbh, radius_m=R)[0].astype(np.float64)
    assert desc.sum() > 0
    volume = np.arange(desc.size) // 11                                   # 32 volumes x 11 cosine bins
    outer = (volume // 2) % 2 == 1                                        # volume = sector·4 + shell·2 + up
    assert desc[outer].sum() / desc.sum() == pytest.approx(outer_share, abs=1e-5)
