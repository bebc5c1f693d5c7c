"""Texture-volume slices (stex.volume): sampling through ξ, grouping by label, gutter filling."""
import numpy as np
import pytest

from stex.render import sample_bilinear
from stex.atlas import build_atlas, texel_map
from stex.sampling import TexelSampler, fill_gutter, label_colors, nearest_seen_texels
from stex.volume import volume_slice

W = 128
GUTTER = 3
FX, CX, CY, HC, WC = 300.0, 159.5, 119.5, 240, 320


@pytest.fixture(scope="module")
def plane():
    """A 12 x 12 grid of quads on the plane z = 1 facing the camera, its atlas and texel map."""
    n = 12
    x, y = np.meshgrid(np.linspace(-0.45, 0.45, n + 1), np.linspace(-0.35, 0.35, n + 1))
    V = np.column_stack([x.ravel(), y.ravel(), np.ones(x.size)])
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    F = np.concatenate([np.stack([a, a + n + 1, a + 1], 1), np.stack([a + 1, a + n + 1, a + n + 2], 1)]).astype(np.int32)
    tc, tf = build_atlas(V, F, resolution=W, gutter_px=GUTTER)
    face, bary = texel_map(tc, tf, W)
    return V, F, tc, tf, face, bary


def _colour(P):
    """A smooth colour function of the 3-D surface point (the 'true texture')."""
    X, Y = P[..., 0], P[..., 1]
    return np.stack([128 + 90 * np.sin(4 * X) * np.cos(3 * Y), 120 + 80 * np.cos(5 * Y), 100 + 70 * np.sin(3 * X + 2 * Y)], -1)


def _perfect_render():
    """The camera image of the plane coloured by _colour (pixel centre back-projected to z = 1)."""
    yy, xx = np.mgrid[0:HC, 0:WC].astype(np.float64)
    P = np.stack([(xx - CX) / FX, (yy - CY) / FX, np.ones_like(xx)], -1)
    return np.clip(np.round(_colour(P)), 0, 255).astype(np.uint8)


def _project(V):
    return np.column_stack([FX * V[:, 0] / V[:, 2] + CX, FX * V[:, 1] / V[:, 2] + CY])


def test_slice_reproduces_the_known_texture(plane):
    V, F, tc, tf, face, bary = plane
    cov = face >= 0
    labels = np.full(len(F), 2, np.int32)  # every face from source frame 2
    coords = {2: _project(V)}
    images = {2: _perfect_render()}
    sl, lm = volume_slice(face, bary, F, labels, coords, images, GUTTER)
    assert sl.shape == (W, W, 3) and sl.dtype == np.uint8 and lm.dtype == np.int32
    assert (lm[cov] == 2).all() and (lm[~cov] == -1).all()
    P = np.einsum("rck,rckd->rcd", bary.astype(np.float64), V[F[np.maximum(face, 0)]])
    truth = np.clip(np.round(_colour(P)), 0, 255)
    err = np.abs(sl[cov].astype(float) - truth[cov])
    assert err.mean() < 0.7 and err.max() <= 3, (err.mean(), err.max())


def test_gutter_is_filled_and_keeps_no_label(plane):
    from scipy import ndimage

    V, F, tc, tf, face, bary = plane
    cov = face >= 0
    labels = np.zeros(len(F), np.int32)
    sl, lm = volume_slice(face, bary, F, labels, {0: _project(V)}, {0: _perfect_render()}, GUTTER)
    band = ndimage.binary_dilation(cov, np.ones((3, 3), bool), iterations=GUTTER)
    assert (sl[band].sum(1) > 0).all(), "black texels within the gutter"
    assert (lm[~cov] == -1).all()
    far = ~ndimage.binary_dilation(cov, np.ones((3, 3), bool), iterations=GUTTER + 1)
    assert (sl[far] == 0).all()


def test_unlabelled_faces_are_filled_inside_charts(plane):
    V, F, tc, tf, face, bary = plane
    cov = face >= 0
    labels = np.zeros(len(F), np.int32)
    labels[::7] = -1
    sl, lm = volume_slice(face, bary, F, labels, {0: _project(V)}, {0: _perfect_render()}, GUTTER)
    hole = cov & (labels[np.maximum(face, 0)] < 0)
    assert hole.any() and (lm[hole] == -1).all()
    assert (sl[cov].sum(1) > 0).all()


def _keys_cubic(img, x):
    """Reference bicubic lookup (Keys, a = -0.75 as OpenCV), clamp-to-edge, at x = (u, v)."""
    H, Wd = img.shape[:2]
    u, v = min(max(x[0], 0.0), Wd - 1.0), min(max(x[1], 0.0), H - 1.0)
    c0, r0 = int(np.floor(u)), int(np.floor(v))

    def w(d):
        a, d = -0.75, abs(d)
        return ((a + 2) * d - (a + 3)) * d * d + 1 if d <= 1 else ((a * d - 5 * a) * d + 8 * a) * d - 4 * a

    acc = np.zeros(img.shape[2])
    for i in range(-1, 3):
        for j in range(-1, 3):
            r, c = min(max(r0 + i, 0), H - 1), min(max(c0 + j, 0), Wd - 1)
            acc += w(v - (r0 + i)) * w(u - (c0 + j)) * img[r, c]
    return acc


@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
def test_grouping_by_label_equals_naive_reference(plane, interpolation):
    V, F, tc, tf, face, bary = plane
    rng = np.random.default_rng(3)
    T = 4
    images = rng.integers(0, 256, (T, 50, 70, 3), dtype=np.uint8)
    coords = np.stack([np.column_stack([rng.uniform(-3, 72, len(V)), rng.uniform(-3, 52, len(V))]) for _ in range(T)])
    coords[1, 5] = np.nan  # a vertex without a coordinate in frame 1
    labels = rng.integers(-1, T, len(F)).astype(np.int32)
    reads = []

    def image_of(s):
        reads.append(s)
        return images[s]

    sl, lm = volume_slice(face, bary, F, labels, coords, image_of, gutter_px=0, interpolation=interpolation)
    assert sorted(reads) == sorted(set(int(x) for x in labels if x >= 0)), "each source image read once"
    ref = np.zeros_like(sl)
    ref_lab = np.full((W, W), -1, np.int32)
    for r, c in zip(*np.nonzero(face >= 0)):
        f = face[r, c]
        l = labels[f]
        if l < 0:
            continue
        x = (bary[r, c, :, None].astype(np.float64) * coords[l][F[f]]).sum(0)
        if not np.isfinite(x).all():
            continue
        if interpolation == "bilinear":
            ref[r, c] = np.clip(np.floor(sample_bilinear(images[l], x) + np.float32(0.5)), 0, 255)
        else:
            ref[r, c] = np.clip(np.round(_keys_cubic(images[l].astype(np.float64), x)), 0, 255)
        ref_lab[r, c] = l
    np.testing.assert_array_equal(lm, ref_lab)
    m = ref_lab >= 0
    if interpolation == "bilinear":
        np.testing.assert_array_equal(sl[m], ref[m])
    else:  # OpenCV's fixed-point weights (1/32 px, 1/1024) round a little differently
        diff = np.abs(sl[m].astype(int) - ref[m].astype(int))
        assert diff.max() <= 1 and diff.mean() < 0.01, (diff.max(), diff.mean())
    assert (lm[face >= 0] == -1).sum() > (labels == -1).sum()  # NaN vertex faces dropped too


def test_sampler_reuse_matches_function(plane):
    V, F, tc, tf, face, bary = plane
    rng = np.random.default_rng(1)
    images = {s: rng.integers(0, 256, (40, 40, 3), dtype=np.uint8) for s in range(3)}
    coords = {s: rng.uniform(0, 39, (len(V), 2)) for s in range(3)}
    sampler = TexelSampler(face, bary, F)
    for _ in range(2):
        labels = rng.integers(0, 3, len(F)).astype(np.int32)
        a = sampler.slice(labels, coords, images, GUTTER)
        b = volume_slice(face, bary, F, labels, coords, images, GUTTER)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
def test_slices_of_a_pass_read_each_source_once_and_equal_single_slices(plane, interpolation):
    V, F, tc, tf, face, bary = plane
    rng = np.random.default_rng(7)
    T, S = 6, 5
    images = rng.integers(0, 256, (T, 50, 70, 3), dtype=np.uint8)
    coords = rng.uniform(-3, 72, (T, len(V), 2))
    coords[2] = np.nan            # a source frame without coordinates: nothing sampled from it
    coords[4, :9] = np.inf
    labels = rng.integers(-1, T, (S, len(F))).astype(np.int32)
    reads = []

    def image_of(s):
        reads.append(s)
        return images[s]

    sampler = TexelSampler(face, bary, F, interpolation)
    sampler.CHUNK_TEXELS = 97     # many lookups per source frame, some of them all NaN
    together = list(sampler.slices(labels, coords, image_of, GUTTER))
    assert sorted(reads) == sorted(set(labels[labels >= 0].tolist())), "each source read once per pass"
    assert len(together) == S
    single = TexelSampler(face, bary, F, interpolation)
    for k in range(S):
        sl, lm = single.slice(labels[k], coords, images, GUTTER)
        np.testing.assert_array_equal(together[k][0], sl)
        np.testing.assert_array_equal(together[k][1], lm)
        assert not (lm == 2).any() and (lm >= 0).any()
    with pytest.raises(ValueError, match="labels must have shape"):
        next(sampler.slices(labels[:, :-1], coords, images))


def test_never_seen_texels_blend_the_nearest_seen_vertices(plane):
    """Against brute force: every texel of a never-seen face blends the k nearest vertices of seen
    faces (inverse distance), each represented by the seen texel nearest to it in 3-D."""
    V, F, tc, tf, face, bary = plane
    centres = V[F].mean(1)
    never = centres[:, 0] > 0.2                       # a strip of faces no frame saw
    dst, src, w = nearest_seen_texels(face, bary, V, F, never, k=3)
    flat_face = face.ravel()
    P = np.einsum("nk,nkd->nd", bary.reshape(-1, 3).astype(np.float64), V[F[np.maximum(flat_face, 0)]])
    unseen = np.flatnonzero((flat_face >= 0) & never[np.maximum(flat_face, 0)])
    np.testing.assert_array_equal(dst, unseen)
    seen = np.flatnonzero((flat_face >= 0) & ~never[np.maximum(flat_face, 0)])
    anchors = np.unique(F[~never])
    rep = seen[np.argmin(((P[seen][None] - V[anchors][:, None]) ** 2).sum(-1), axis=1)]
    d = np.linalg.norm(P[dst][:, None] - V[anchors][None], axis=-1)
    near = np.argsort(d, axis=1)[:, :3]
    np.testing.assert_array_equal(np.sort(src, 1), np.sort(rep[near], 1))
    np.testing.assert_allclose(w.sum(1), 1, atol=1e-6)
    dn = np.take_along_axis(d, near, 1)
    np.testing.assert_allclose(np.sort(w, 1), np.sort((1 / dn) / (1 / dn).sum(1, keepdims=True), 1), rtol=1e-5)
    assert nearest_seen_texels(face, bary, V, F, np.zeros(len(F), bool))[0].size == 0
    assert nearest_seen_texels(face, bary, V, F, np.ones(len(F), bool))[0].size == 0


def test_fill_gutter_rings():
    img = np.zeros((9, 9, 3), np.uint8)
    img[4, 4] = 200
    valid = np.zeros((9, 9), bool)
    valid[4, 4] = True
    inside, gutter = fill_gutter(img, valid, valid.copy(), 2)
    assert inside == 0 and gutter == 24
    assert (img[2:7, 2:7] == 200).all() and img[1].sum() == 0


def test_fill_gutter_takes_the_rounded_mean_of_the_valid_neighbours():
    """A filled texel is the mean of its valid 8-neighbours per channel, rounded to the nearest
    grey level (not truncated: truncation darkens every ring by up to 1 level, and the rings
    compound it outwards)."""
    img = np.zeros((5, 5, 3), np.uint8)
    valid = np.zeros((5, 5), bool)
    img[1, 1:4] = [(100, 10, 0), (101, 12, 0), (101, 12, 2)]
    valid[1, 1:4] = True
    fill_gutter(img, valid, valid.copy(), 1)
    assert tuple(img[2, 2]) == (101, 11, 1)              # means 100.67, 11.33, 0.67
    assert tuple(img[0, 2]) == (101, 11, 1)
    assert tuple(img[2, 0]) == (100, 10, 0)              # (1, 1) alone


def test_label_colors():
    lm = np.array([[-1, 0, 1], [2, 0, 7]], np.int32)
    pic = label_colors(lm)
    assert pic.shape == (2, 3, 3) and pic.dtype == np.uint8
    assert (pic[0, 0] == 0).all()
    assert (pic[0, 1] == pic[1, 1]).all()
    cols = {tuple(pic[0, 1]), tuple(pic[0, 2]), tuple(pic[1, 0]), tuple(pic[1, 2])}
    assert len(cols) == 4 and all(max(c) > 0 for c in cols)


# -- a slice's own frame read at Φ (volume.own_frame_coordinates) -----------------------------

def _shifted_coordinates(P, out, shift_px):
    """A ``texcoords`` store whose ξ is the run's Φ moved by ``shift_px`` (x, y): a stand-in for
    the optimisation's correction that makes ξ and Φ read different colours."""
    from stex.io import create_store, open_store

    proj = open_store(P["projection"], "projection")
    phi = np.asarray(proj["phi"][...], np.float32)
    attrs = {"frame_ids": list(proj.attrs["frame_ids"]), "keyframes": [], "color_size": [0, 0],
             "energy_rows": [], "stages": [], "seconds": 0.0}
    with create_store(out, "texcoords", attrs=attrs) as store:
        store.write("xi", phi + np.float32(shift_px))
        store.write("valid", np.asarray(proj["vertex_visible"][...], bool))
        store.write("energy", np.zeros((1, 1)))
    return out


def test_own_frame_texels_are_read_at_phi_and_the_others_at_xi(tiny_pipeline, tmp_path):
    """With ``own_frame_coordinates: projected`` slice t's texels labelled t equal those of a
    volume read entirely at Φ, every other labelled texel equals the volume read at ξ, and the
    label maps are the ones the labels give (the stand-in label T + t never leaks out). ξ here is
    Φ moved by (0.7, -0.4) px, so ξ and Φ give different colours on the own frame's texels."""
    from stex.io import open_store
    from stex.stages.volume import write_volume

    P = tiny_pipeline
    xi = _shifted_coordinates(P, tmp_path / "xi.zarr", (0.7, -0.4))
    start, stop = open_store(P["scene"], "scene").attrs["frame_blocks"][0]
    out = {}
    for name, coords, own in (("xi", xi, "as_sources"), ("phi", P["projection"], "as_sources"),
                              ("own_phi", xi, "projected"),
                              ("projected_at_phi", P["projection"], "projected")):
        out[name] = tmp_path / f"volume_{name}.zarr"
        write_volume(P["template"], P["labels"], coords, P["frames"], [start, stop],
                     {"own_frame_coordinates": own}, out[name], projection_path=P["projection"])
    vol = {k: open_store(v, "volume") for k, v in out.items()}
    lm = np.asarray(vol["xi"]["label_map"][...])
    for k in vol:
        np.testing.assert_array_equal(np.asarray(vol[k]["label_map"][...]), lm)
    tex = {k: np.asarray(v["texture"][...]) for k, v in vol.items()}
    own = lm == (start + np.arange(stop - start))[:, None, None]
    other = (lm >= 0) & ~own
    assert own.sum() > 1000 and other.sum() > 1000
    np.testing.assert_array_equal(tex["own_phi"][own], tex["phi"][own])
    np.testing.assert_array_equal(tex["own_phi"][other], tex["xi"][other])
    assert (tex["xi"][own] != tex["phi"][own]).any(axis=-1).mean() > 0.3   # the shift shows
    np.testing.assert_array_equal(tex["projected_at_phi"], tex["phi"])   # Φ everywhere: no change
    with pytest.raises(ValueError, match=r"own_frame_coordinates 'projected' .*give the projection store"):
        write_volume(P["template"], P["labels"], xi, P["frames"], [start, stop],
                     {"own_frame_coordinates": "projected"}, tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


def test_harmonic_fill_changes_only_the_never_seen_texels(tiny_pipeline, tmp_path):
    """volume.fill harmonic against nearest: the same slices but on texels of never-seen faces,
    which the harmonic fill joins to the seen texels around them without a step."""
    from stex.io import open_store
    from stex.stages.volume import write_volume

    P = tiny_pipeline
    start, stop = open_store(P["scene"], "scene").attrs["frame_blocks"][0]
    never = np.asarray(open_store(P["labels"], "labels")["never_seen"][...], bool)
    face = np.asarray(open_store(P["template"], "template")["texel/face_id"][...])
    hole = (face >= 0) & never[np.maximum(face, 0)]
    assert hole.sum() > 100
    tex = {}
    for fill in ("nearest", "harmonic"):
        path = tmp_path / f"volume_{fill}.zarr"
        write_volume(P["template"], P["labels"], P["projection"], P["frames"], [start, stop],
                     {"fill": fill}, path)
        store = open_store(path, "volume")
        assert store.attrs["fill"] == fill
        tex[fill] = np.asarray(store["texture"][...], np.float64)
    inner = (face >= 0) & ~hole
    np.testing.assert_array_equal(tex["harmonic"][:, inner], tex["nearest"][:, inner])
    assert (tex["harmonic"][:, hole] != tex["nearest"][:, hole]).any(axis=-1).mean() > 0.5

    def edge_step(t):     # mean |Δ| between a hole texel and its seen left / right neighbour
        # (covered texels side by side lie in one chart: the gutter separates charts)
        a, b = hole[:, 1:] & inner[:, :-1], hole[:, :-1] & inner[:, 1:]
        right, left = t[:, :, 1:], t[:, :, :-1]
        return np.concatenate([np.abs(right[:, a] - left[:, a]), np.abs(left[:, b] - right[:, b])], axis=1).mean()

    assert edge_step(tex["harmonic"]) < 0.7 * edge_step(tex["nearest"])
