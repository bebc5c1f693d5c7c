"""Fill of never-seen faces in texture space (stex.fill): harmonic, seam-continuous, seen kept."""
import numpy as np
import pytest

from stex.atlas import texel_map, uv_charts
from stex.fill import SeamFill
from stex.mesh import face_adjacency
from stex.texel_graph import texel_graph


def _system(F, tc, tf, face, never, **kw):
    pairs, edges = face_adjacency(F)
    return SeamFill(face, uv_charts(tf, len(tc)), tc, tf, F, pairs, edges, never, **kw)


@pytest.fixture(scope="module")
def grid():
    """One chart: a 6 x 6 vertex grid, its centre faces never seen."""
    n = 6
    ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    vid = ii * n + jj
    a, b, c, d = vid[:-1, :-1].ravel(), vid[:-1, 1:].ravel(), vid[1:, 1:].ravel(), vid[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)]).astype(np.int32)
    tc = (0.05 + 0.9 * np.stack([jj.ravel(), ii.ravel()], 1) / (n - 1)).astype(np.float32)
    face, _ = texel_map(tc, F, 64)
    centre = tc[F].mean(axis=1)
    never = (np.abs(centre - 0.5) < 0.25).all(axis=1)
    return F, tc, F.copy(), face, never


def test_fill_reproduces_a_harmonic_function_and_keeps_the_seen_texels(grid):
    F, tc, tf, face, never = grid
    W = face.shape[0]
    rr, cc = np.mgrid[0:W, 0:W]
    linear = 40.0 + 2.0 * cc + 0.8 * rr                  # harmonic: the discrete Laplacian is 0
    cov = face >= 0
    img = np.zeros((W, W, 3), np.uint8)
    img[cov] = np.clip(np.round(linear[cov]), 0, 255)[:, None]
    hole = cov & never[np.maximum(face, 0)]
    img[hole] = 0                                        # the fill starts from black
    before = img.copy()
    fs = _system(F, tc, tf, face, never, screen_length=1e3)   # λ ~ 0: the harmonic fill
    assert fs.n_filled == hole.sum() > 100
    fs.fill(img)
    err = np.abs(img[hole].astype(float) - linear[hole][:, None])
    assert err.max() <= 1.0, err.max()
    np.testing.assert_array_equal(img[~hole], before[~hole])


@pytest.fixture(scope="module")
def strip():
    """Two squares sharing the 3-D edge 1-4, unwrapped into two charts side by side (one seam)."""
    F = np.array([[0, 4, 1], [0, 3, 4], [1, 5, 2], [1, 4, 5]], np.int32)
    tc = np.array([[.05, .1], [.45, .1], [.45, .9], [.05, .9], [.55, .1], [.95, .1], [.95, .9], [.55, .9]], np.float32)
    tf = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]], np.int32)
    face, _ = texel_map(tc, tf, 128)
    return F, tc, tf, face


def test_fill_is_continuous_across_a_seam(strip):
    F, tc, tf, face = strip
    W = face.shape[0]
    never = np.array([False, False, True, True])         # the second chart: no frame saw it
    cov = face >= 0
    hole = cov & never[np.maximum(face, 0)]
    rr = np.mgrid[0:W, 0:W][0]
    img = np.zeros((W, W, 3), np.uint8)
    seen = cov & ~hole
    img[seen] = np.round(40 + 1.5 * rr[seen])[:, None]   # a ramp along the seam's direction
    img[hole] = 200                                      # the starting (nearest) fill
    before = img.copy()
    pairs, edges = face_adjacency(F)
    graph = texel_graph(face, uv_charts(tf, len(tc)), tc, tf, F, pairs, edges)

    def step(im):
        return float(np.abs(graph.S @ im.reshape(-1, 3)[graph.index].astype(float)).mean())

    fs = _system(F, tc, tf, face, never, screen_length=1e3)
    fs.fill(img)
    np.testing.assert_array_equal(img[seen], before[seen])
    assert step(before) > 50
    # less than the ramp's own step between two neighbouring texels (1.5 grey levels)
    assert step(img) < 1.5, step(img)
    # the hole's only boundary is the seam: its column along the seam carries the ramp on
    first = np.argmax(hole, axis=1)
    rows = np.flatnonzero(hole.any(axis=1))
    rows = rows[len(rows) // 5:-len(rows) // 5]           # away from the ends (Neumann corners)
    np.testing.assert_allclose(img[rows, first[rows], 0], 40 + 1.5 * rows, atol=2.0)
    # without the seam coupling the chart has no path to a seen texel: it keeps its start
    isolated = before.copy()
    _system(F, tc, tf, face, never, screen_length=1e3, seam_weight=0.0).fill(isolated)
    np.testing.assert_array_equal(isolated, before)


def test_bad_never_seen_shape_raises(strip):
    F, tc, tf, face = strip
    with pytest.raises(ValueError, match="never_seen"):
        _system(F, tc, tf, face, np.zeros(3, bool))


def test_a_slice_like_the_last_is_solved_in_fewer_cycles_to_the_same_texture(grid):
    """Each slice starts from the previous slice's solution: fewer V-cycles, same uint8 result
    as a fill that starts cold, within one grey level."""
    F, tc, tf, face, never = grid
    W = face.shape[0]
    rr, cc = np.mgrid[0:W, 0:W]
    cov = face >= 0
    hole = cov & never[np.maximum(face, 0)]

    def slice_(shift):
        img = np.zeros((W, W, 3), np.uint8)
        ramp = 60.0 + 1.7 * cc + 0.9 * rr + 20 * np.sin(rr / 9.0) + shift
        img[cov] = np.clip(np.round(ramp[cov]), 0, 255)[:, None]
        img[hole] = 0
        return img

    warm = _system(F, tc, tf, face, never, screen_length=0.05)
    warm.fill(slice_(0.0))
    first = list(warm.last_iterations)
    second = warm.fill(slice_(0.6))
    cold = _system(F, tc, tf, face, never, screen_length=0.05)
    reference = cold.fill(slice_(0.6))
    assert cold.last_iterations == first                  # a cold start costs the first slice's cycles
    assert sum(warm.last_iterations) < sum(first), (warm.last_iterations, first)
    assert np.abs(second.astype(int) - reference.astype(int)).max() <= 1
