"""stex.resample: exact closest points on a mesh, and textures carried between UV layouts."""

import numpy as np
import pytest
import trimesh

from stex.resample import atlas_transfer, closest_surface_points
from stex.atlas import build_atlas, texel_map


def _brute_force(points, V, F):
    """Closest distance of each point to each triangle, by trimesh's exact per-triangle routine."""
    tri = V[F]
    best = np.full(len(points), np.inf)
    for j in range(len(F)):
        q = trimesh.triangles.closest_point(np.repeat(tri[j:j + 1], len(points), 0), points)
        best = np.minimum(best, np.linalg.norm(q - points, axis=1))
    return best


@pytest.fixture(scope="module")
def blob():
    """A lumpy closed mesh (0.1 m), triangles of uneven size."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    V = m.vertices * (1.0 + 0.3 * np.sin(9.0 * m.vertices[:, [1]]) * np.array([[1.0, 0.4, 1.0]]))
    return V, np.asarray(m.faces)


def test_closest_points_are_exact_on_and_off_the_surface(blob):
    """Equal to a brute-force search over every triangle: points on the surface (how texels are
    queried), near it, and far from it (the latter answered by the fallback)."""
    V, F = blob
    rng = np.random.default_rng(0)
    f = rng.integers(0, len(F), 300)
    b = rng.dirichlet(np.ones(3), 300)
    on = np.einsum("nk,nkd->nd", b, V[F[f]])
    near = on + rng.normal(0, 0.003, on.shape)
    far = rng.normal(0, 0.3, (100, 3))
    P = np.concatenate([on, near, far])
    face, bary, dist = closest_surface_points(P, V, F)
    np.testing.assert_allclose(dist, _brute_force(P, V, F), atol=1e-7)
    assert dist[:300].max() < 1e-9
    # the returned face and barycentrics give the closest point
    q = np.einsum("nk,nkd->nd", bary, V[F[face]])
    np.testing.assert_allclose(np.linalg.norm(q - P, axis=1), dist, atol=1e-9)
    np.testing.assert_allclose(bary.sum(1), 1.0)
    assert (bary >= -1e-12).all()


def test_closest_points_by_hand_on_an_open_mesh():
    """One triangle A (0, 0, 0), B (1, 0, 0), C (0, 1, 0): a point over its inside, beyond each
    edge and beyond each corner, worked by hand. On a boundary no neighbour answers for an edge
    (on a closed mesh the face across it does). A zero-area face comes first: it is skipped, and
    the face index still counts it."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    F = np.array([[0, 0, 1], [0, 1, 2]])
    cases = [  # point, weights of (A, B, C) at its closest point
        ((0.2, 0.3, 0.1), (0.5, 0.2, 0.3)),       # inside: the foot (0.2, 0.3, 0)
        ((0.3, -0.2, 0.1), (0.7, 0.3, 0.0)),      # beyond AB: (0.3, 0, 0)
        ((0.7, 0.5, 0.1), (0.0, 0.6, 0.4)),       # beyond BC (x + y = 1): (0.6, 0.4, 0)
        ((-0.2, 0.6, 0.1), (0.4, 0.0, 0.6)),      # beyond CA: (0, 0.6, 0)
        ((-0.1, -0.2, 0.1), (1.0, 0.0, 0.0)),     # beyond A
        ((1.2, -0.1, 0.0), (0.0, 1.0, 0.0)),      # beyond B
        ((-0.1, 1.2, 0.1), (0.0, 0.0, 1.0)),      # beyond C
    ]
    P = np.array([p for p, _ in cases])
    want = np.array([w for _, w in cases])
    foot = want @ V
    face, bary, dist = closest_surface_points(P, V, F)
    assert face.tolist() == [1] * len(cases)
    np.testing.assert_allclose(bary, want, atol=1e-12)
    np.testing.assert_allclose(dist, np.linalg.norm(P - foot, axis=1), atol=1e-12)


def _paint(texel_face, texel_bary, V, F):
    """A smooth colour field of the 3-D position, painted into an atlas (0 outside charts)."""
    W = texel_face.shape[0]
    img = np.zeros((W, W, 3), np.uint8)
    hit = texel_face >= 0
    P = np.einsum("nk,nkd->nd", texel_bary[hit].astype(np.float64), V[F[texel_face[hit]]])
    img[hit] = np.clip(128 + 100 * np.sin(P * np.array([25.0, 31.0, 19.0])), 0, 255).astype(np.uint8)
    return img


def test_a_texture_carried_into_another_layout_reads_the_same_surface(blob, caplog):
    """A colour field of the 3-D position painted in one UV layout, carried into another layout
    of the same surface, equals the field painted there directly (to the bilinear read), and the
    new layout's gutter is filled."""
    V, F = blob
    uv_a, tf_a = build_atlas(V, F, 256, 2)
    uv_b, tf_b = build_atlas(V, F, 192, 2)
    face_a, bary_a = texel_map(uv_a, tf_a, 256)
    face_b, bary_b = texel_map(uv_b, tf_b, 192)
    assert (face_b >= 0).any() and not np.array_equal(uv_a, uv_b)
    tr = atlas_transfer(face_b, bary_b, V, F, V, F, uv_a, tf_a, gutter_px=2)
    assert tr.reads.sum() == (face_b >= 0).sum()
    got = tr.apply(_paint(face_a, bary_a, V, F))
    want = _paint(face_b, bary_b, V, F)
    hit = face_b >= 0
    diff = np.abs(got[hit].astype(int) - want[hit])
    assert diff.mean() < 1.5 and np.percentile(diff, 99) < 8
    assert got.shape == (192, 192, 3) and got.dtype == np.uint8
    ring = ~hit & (np.abs(np.diff(hit.astype(int), axis=1, prepend=0)) > 0)   # texels just outside
    assert got[ring].any(axis=1).mean() > 0.9
    # a mesh moved 5 cm, or in millimetres, is refused; so is one without texture coordinates
    with pytest.raises(ValueError, match="median texel"):
        atlas_transfer(face_b, bary_b, V, F, V + [0.05, 0, 0], F, uv_a, tf_a, where="moved.obj")
    with pytest.raises(ValueError, match="moved.obj"):
        atlas_transfer(face_b, bary_b, V, F, V * 1000, F, uv_a, tf_a, where="moved.obj")
    with pytest.raises(ValueError, match="no texture coordinates"):
        atlas_transfer(face_b, bary_b, V, F, V, F, None, None)
    # texels farther than max_distance_m read nothing: black
    half = V.copy()
    half[V[:, 0] > 0.03] *= 1.2
    tr2 = atlas_transfer(face_b, bary_b, V, F, half, F, uv_a, tf_a, max_distance_m=0.002)
    far = hit & ~tr2.reads
    assert far.any() and not tr2.apply(_paint(face_a, bary_a, V, F))[far].any()
    with pytest.raises(ValueError, match="square"):
        tr.apply(np.zeros((16, 32, 3), np.uint8))
    # a tiling layout is refused (it scored 4 dB, silently); a mesh with holes warns
    with pytest.raises(ValueError, match=r"tiled\.obj: \d+ of its \d+ texture coordinates lie outside \[0, 1\]"):
        atlas_transfer(face_b, bary_b, V, F, V, F, uv_a * 3, tf_a, where="tiled.obj")
    import logging

    with caplog.at_level(logging.WARNING, logger="stex.resample"):
        atlas_transfer(face_b, bary_b, V, F, V, F[::2], uv_a, tf_a[::2], where="half.obj")
    assert "half.obj" in caplog.text and "boundary edges" in caplog.text


def test_a_transposed_layout_gives_the_transposed_texture_exactly():
    """A 10 cm square in two UV layouts, the run's (u, v) = (x, y) / 0.1 and the other's (y, x) /
    0.1: the centre of the run's texel (r, c) is the other layout's texel centre (c, r), so the
    transfer is the texture transposed, to the grey level. At 30^2 the texel centres are not
    representable in float32: the reads land a hair off them and must round, not truncate."""
    S = 30
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]) * 0.1
    F = np.array([[0, 1, 2], [0, 2, 3]])
    face, bary = texel_map(V[:, :2] / 0.1, F, S)
    assert (face >= 0).all()
    tr = atlas_transfer(face, bary, V, F, V, F, V[:, 1::-1] / 0.1, F)
    tex = np.random.default_rng(0).integers(0, 256, (S, S, 3), dtype=np.uint8)
    np.testing.assert_array_equal(tr.apply(tex), tex.transpose(1, 0, 2))


def test_texels_beyond_max_distance_read_nothing():
    """The other mesh is the square tilted to z = 0.04 x: the run's texel at x (column c, x = (c +
    0.5) / 300 m) is 0.04 x / sqrt(1 + 0.04^2) from it (its foot is inside), so with
    max_distance_m = 3 mm columns 0..22 read (x <= 75.06 mm) and 23..29 read nothing (black)."""
    S, k = 30, 0.04
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]) * 0.1
    F = np.array([[0, 1, 2], [0, 2, 3]])
    tilted = V + np.c_[np.zeros((4, 2)), k * V[:, 0]]
    face, bary = texel_map(V[:, :2] / 0.1, F, S)
    tr = atlas_transfer(face, bary, V, F, tilted, F, V[:, :2] / 0.1, F, max_distance_m=0.003)
    x = (np.arange(S) + 0.5) / S * 0.1
    np.testing.assert_allclose(tr.distance_m, np.broadcast_to(k * x / np.hypot(1, k), (S, S)), atol=1e-7)
    assert np.array_equal(tr.reads, np.broadcast_to(np.arange(S) <= 22, (S, S)))
    out = tr.apply(np.full((S, S, 3), 200, np.uint8))
    assert (out[:, :23] == 200).all() and (out[:, 23:] == 0).all()


def test_closest_surface_points_checks_its_arguments():
    """(3, 2) points were reshaped to (2, 3), face -1 wrapped to the last vertex."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    F = np.array([[0, 1, 2], [1, 3, 2]])
    for points, faces, msg in ((np.zeros((3, 2)), F, r"points must be \(n, 3\)"),
                               (np.array([[0, 0, np.nan]]), F, "non-finite"),
                               (np.zeros((1, 3)), [[0, 1, -1]], "index out of range"),
                               (np.zeros((1, 3)), [[0, 1, 7]], "index out of range"),
                               (np.zeros((1, 3)), [[0, 1, 2, 3]], r"must have shape \(F, 3\)")):
        with pytest.raises(ValueError, match=msg):
            closest_surface_points(points, V, faces)
    face, bary, dist = closest_surface_points(np.array([[0.2, 0.2, 0.1]]), V, F)
    assert face.tolist() == [0] and dist[0] == pytest.approx(0.1)
