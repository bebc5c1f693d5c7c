"""Texture dynamism (SSIM between consecutive partial textures) and the selective weights."""
import cv2
import numpy as np
import pytest

from stex.dynamism import (authors_dynamic_faces, dynamism_rows, dynamism_table, face_ssim, label_set_min,
                           partial_texture, spatial_edge_weight, spatial_face_weight, ssim_map_image,
                           temporal_gate, temporal_pair_weight)
from conftest import grid_atlas
from stex.atlas import texel_map
from stex.sampling import TexelSampler

W = 64  # atlas side, texels
N = 9   # grid vertices per side: 2 * 8 * 8 = 128 faces


@pytest.fixture(scope="module")
def atlas():
    tc, faces = grid_atlas(N)
    tf, bary = texel_map(tc, faces, W)
    # ξ maps texel (r, c)'s centre onto image pixel (c, r): the partial texture is the image itself
    xi = (tc * W - 0.5).astype(np.float32)
    return {"faces": faces, "tf": tf, "bary": bary, "xi": xi, "F": len(faces),
            "sampler": TexelSampler(tf, bary, faces)}


def _texture(seed, size=W):
    """Smooth random RGB texture (blurred noise, full 0..255 contrast)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (size, size, 3)).astype(np.float32), (0, 0), 1.2)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return (img + 0.5).astype(np.uint8)


def _patch_faces(atlas):
    """Faces whose texels lie in the block rows/cols 20..44 (4 x 4 grid cells in the middle)."""
    tf = atlas["tf"]
    inside = np.zeros((W, W), bool)
    inside[20:44, 20:44] = True
    faces_in = np.unique(tf[inside & (tf >= 0)])
    # faces entirely inside the block
    full = np.array([np.all(inside[tf == f]) for f in faces_in])
    return faces_in[full], inside


def test_partial_texture_copies_visible_faces(atlas):
    img = _texture(0)
    vis = np.zeros(atlas["F"], bool)
    vis[::3] = True
    tex, cov = partial_texture(atlas["sampler"], atlas["xi"], vis, img)
    assert tex.dtype == np.uint8 and tex.shape == (W, W, 3) and cov.shape == (W, W)
    expect = (atlas["tf"] >= 0) & vis[np.maximum(atlas["tf"], 0)]
    np.testing.assert_array_equal(cov, expect)
    np.testing.assert_array_equal(tex[cov], img[cov])   # ξ puts texel (r, c) on pixel (c, r)
    assert not tex[~cov].any()
    # the (texel_face, bary, faces) tuple works the same
    tex2, cov2 = partial_texture((atlas["tf"], atlas["bary"], atlas["faces"]), atlas["xi"], vis, img)
    np.testing.assert_array_equal(tex2, tex)
    np.testing.assert_array_equal(cov2, cov)


def test_identical_textures_give_one_and_nan_where_not_seen_in_both(atlas):
    img = _texture(1)
    F = atlas["F"]
    va = np.ones(F, bool)
    va[:40] = False
    vb = np.ones(F, bool)
    vb[100:] = False
    ta, ca = partial_texture(atlas["sampler"], atlas["xi"], va, img)
    tb, cb = partial_texture(atlas["sampler"], atlas["xi"], vb, img)
    both = va & vb
    for erode in (None, 0):
        S = face_ssim(ta, ca, tb, cb, atlas["tf"], F, erode_px=erode)
        assert S.shape == (F,) and S.dtype == np.float32
        finite = np.isfinite(S)
        assert not (finite & ~both).any()                    # NaN on faces not seen in both
        if erode is None:
            np.testing.assert_allclose(S[finite], 1.0, atol=1e-6)
            assert 10 <= finite.sum() < both.sum()           # erosion drops the border faces
        else:
            np.testing.assert_array_equal(finite, both)      # every common face scored, but
            assert np.nanmin(S) < 0.9                        # windows reaching black texels lie


def test_changed_face_below_theta_unchanged_faces_above(atlas):
    F = atlas["F"]
    a = _texture(2)
    b = a.astype(np.float32) + np.random.default_rng(3).normal(0, 2.0, a.shape)   # sensor noise
    patch_faces, inside = _patch_faces(atlas)
    b[inside] = _texture(4)[inside]                          # new appearance in the block
    b = np.clip(b + 0.5, 0, 255).astype(np.uint8)
    vis = np.ones(F, bool)
    ta, ca = partial_texture(atlas["sampler"], atlas["xi"], vis, a)
    tb, cb = partial_texture(atlas["sampler"], atlas["xi"], vis, b)
    S, smap, valid = face_ssim(ta, ca, tb, cb, atlas["tf"], F, return_map=True)
    assert len(patch_faces) >= 8
    assert np.all(S[patch_faces] < 0.95)
    # faces whose texels are all farther than the window radius (5) + 1 from the block
    far_zone = cv2.dilate(inside.astype(np.uint8), np.ones((13, 13), np.uint8)) == 0
    far = np.array([f for f in range(F) if np.all(far_zone[atlas["tf"] == f])])
    far = far[np.isfinite(S[far])]
    assert len(far) >= 5
    assert np.all(S[far] >= 0.95) and np.all(S[far] < 1.0)   # noise lowers SSIM a little
    assert smap.shape == (W, W) and np.isnan(smap[~valid]).all() and np.isfinite(smap[valid]).all()


def test_data_range_is_honoured(atlas):
    F = atlas["F"]
    a = _texture(5)
    b = np.clip(a.astype(int) + np.random.default_rng(6).integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    cov = atlas["tf"] >= 0
    s_u8 = face_ssim(a, cov, b, cov, atlas["tf"], F)                                    # 255 implied
    s_u8_explicit = face_ssim(a, cov, b, cov, atlas["tf"], F, data_range=255)
    s_f = face_ssim(a / 255.0, cov, b / 255.0, cov, atlas["tf"], F, data_range=1.0)
    s_2 = face_ssim(a / 255.0, cov, b / 255.0, cov, atlas["tf"], F, data_range=2.0)    # the authors' accident
    ok = np.isfinite(s_u8)
    assert ok.sum() > 10
    np.testing.assert_array_equal(s_u8, s_u8_explicit)
    np.testing.assert_allclose(s_f[ok], s_u8[ok], rtol=1e-5, atol=1e-6)
    assert np.all(s_2[ok] > s_f[ok])   # larger constants pull SSIM towards 1
    with pytest.raises(ValueError, match="data_range"):
        face_ssim(a / 255.0, cov, b / 255.0, cov, atlas["tf"], F)


def test_dynamism_table_streams_and_fills_row_zero(atlas):
    F = atlas["F"]
    patch_faces, inside = _patch_faces(atlas)
    base = _texture(7)
    frames = [base.copy() for _ in range(4)]
    frames[2][inside] = _texture(8)[inside]     # change between frames 1 and 2 (and back at 3)
    vis = np.ones((4, F), bool)
    vis[3, :50] = False
    calls = []

    def load(t):
        calls.append(t)
        return frames[t], atlas["xi"], vis[t]

    S, mmap = dynamism_table(load, 4, atlas["sampler"], return_min_map=True)
    assert calls == [0, 1, 2, 3]                                # each frame once, in order
    assert S.shape == (4, F) and S.dtype == np.float32
    np.testing.assert_array_equal(S[0], S[1])                   # row 0 copies pair (0, 1)
    assert np.all(S[1][np.isfinite(S[1])] > 0.999)              # frames 0 and 1 identical
    assert np.all(S[2, patch_faces] < 0.95) and np.all(S[3, patch_faces] < 0.95)
    assert np.isnan(S[3, :50]).all()                            # not seen at frame 3
    assert mmap.shape == (W, W) and mmap.dtype == np.float32
    assert np.median(mmap[28:36, 28:36]) < 0.95 and mmap[0, 0] == 1.0
    # a frame block: rows 2..3 alone are the same rows
    calls.clear()
    rows = dynamism_rows(load, [2, 3], atlas["sampler"])
    assert calls == [1, 2, 3]
    np.testing.assert_array_equal(rows, S[2:])
    # a single frame: one NaN row
    S1 = dynamism_table(lambda t: (base, atlas["xi"], vis[0]), 1, atlas["sampler"])
    assert S1.shape == (1, F) and np.isnan(S1).all()


def test_authors_statistic_any_texel_rule(atlas):
    F = atlas["F"]
    patch_faces, inside = _patch_faces(atlas)
    a = _texture(9)
    b = a.copy()
    b[inside] = _texture(10)[inside]
    cov = atlas["tf"] >= 0
    S_paper = face_ssim(a, cov, b, cov, atlas["tf"], F, mode="paper")
    S_auth = face_ssim(a, cov, b, cov, atlas["tf"], F, mode="authors")
    assert np.all(S_auth >= np.nan_to_num(S_paper, nan=-1))     # max >= mean
    assert np.isfinite(S_auth).all()                            # uncovered texels count as 1
    border = ~np.isfinite(S_paper)
    assert border.any() and np.all(S_auth[border] == 1.0)       # faces at the chart border: static
    assert np.all(S_auth[patch_faces] < 0.98)                   # fully changed faces: dynamic


def test_temporal_gate_and_pair_weight():
    S = np.array([[0.99, 0.5, np.nan, 0.95],
                  [0.20, 0.97, 0.96, 0.9499]], np.float32)
    g = temporal_gate(S, 0.95)
    np.testing.assert_array_equal(g, [[1, 0, 1, 1], [0, 1, 1, 0]])
    assert g.dtype == np.float32
    np.testing.assert_array_equal(temporal_gate(S, 0.95, nan_static=False)[0, 2], 0)
    w = temporal_pair_weight(g, faces=[0, 1, 2, 3, 0], label_a=[0, 0, 0, 0, 0], label_b=[1, 1, 1, 1, 0])
    np.testing.assert_array_equal(w, [0, 0, 1, 0, 1])
    with pytest.raises(ValueError, match="label_b"):
        temporal_pair_weight(g, [0], [0], [2])


def test_spatial_weights_take_the_formula_values():
    # 3 source frames, 4 faces
    S = np.array([[0.99, 0.99, 0.50, np.nan],
                  [0.98, 0.80, 0.99, np.nan],
                  [0.10, 0.99, 0.99, 0.97]], np.float32)
    sets = np.array([[1, 1, 1, 1],
                     [1, 0, 0, 1],
                     [0, 1, 0, 0]], bool)               # L_f: f0 {0,1}, f1 {0,2}, f2 {0}, f3 {0,1}
    np.testing.assert_allclose(label_set_min(S, sets), [0.98, 0.99, 0.50, np.nan])
    w = spatial_face_weight(S, sets, 0.95)
    np.testing.assert_array_equal(w, [1, 1, 0, 1])       # f3: no evidence -> static
    # the same sets as a candidate array [T, F, K] (union over target frames, -1 padding)
    cand = np.full((2, 4, 2), -1, np.int64)
    cand[0, 0] = [0, 1]
    cand[1, 1] = [2, 0]
    cand[0, 2] = [0, -1]
    cand[1, 3] = [1, 0]
    np.testing.assert_array_equal(label_set_min(S, cand), label_set_min(S, sets))
    pairs = np.array([[0, 1], [1, 2], [2, 2], [0, 3]])
    e = spatial_edge_weight(w, pairs)
    np.testing.assert_array_equal(e, [1.0, 1.5, 2.0, 1.0])
    assert set(np.unique(e)) <= {1.0, 1.5, 2.0}
    np.testing.assert_array_equal(spatial_edge_weight(w, pairs, mode="authors"), 1.0)   # the ×10 no-op
    np.testing.assert_array_equal(spatial_edge_weight(w, pairs, mode="authors_intended"), [1.0, 5.5, 10.0, 1.0])


def test_authors_dynamic_faces(atlas):
    F = atlas["F"]
    mm = np.ones((W, W), np.float32)
    mm[30, 30] = 0.5                       # one low texel
    f0 = atlas["tf"][30, 30]
    dyn0 = authors_dynamic_faces(mm, atlas["tf"], F, dilate_px=0)
    np.testing.assert_array_equal(np.flatnonzero(dyn0), [f0])
    dyn = authors_dynamic_faces(mm, atlas["tf"], F, dilate_px=5)
    near = np.unique(atlas["tf"][28:33, 28:33])
    np.testing.assert_array_equal(np.flatnonzero(dyn), np.sort(near[near >= 0]))


def test_ssim_map_image(atlas):
    F = atlas["F"]
    vals = np.linspace(0.5, 1.0, F).astype(np.float32)
    vals[3] = np.nan
    img = ssim_map_image(vals, atlas["tf"], theta=0.95)
    assert img.dtype == np.uint8 and img.shape == (W, W, 3)
    tf = atlas["tf"]
    np.testing.assert_array_equal(img[tf < 0][0], (20, 20, 60))        # empty
    np.testing.assert_array_equal(img[tf == 3][0], (20, 20, 60))       # NaN face
    top = img[tf == F - 1][0]
    np.testing.assert_array_equal(top, (255, 255, 255))               # S = 1: white
    low = img[tf == 0][0]
    assert low[0] == 255 and low[1] < 50                               # below theta: red
    grey_img = ssim_map_image(np.full((W, W), 0.75, np.float32))
    np.testing.assert_array_equal(grey_img[0, 0], (128, 128, 128))


def test_bad_inputs_raise(atlas):
    F = atlas["F"]
    img = _texture(11)
    cov = atlas["tf"] >= 0
    with pytest.raises(ValueError, match="face_visible_t"):
        partial_texture(atlas["sampler"], atlas["xi"], np.ones(F - 1, bool), img)
    with pytest.raises(ValueError, match="image_t"):
        partial_texture(atlas["sampler"], atlas["xi"], np.ones(F, bool), img.astype(np.float32))
    with pytest.raises(ValueError, match="xi_t"):
        partial_texture(atlas["sampler"], atlas["xi"][:10], np.ones(F, bool), img)
    with pytest.raises(ValueError, match="sampler_or_maps"):
        partial_texture("atlas", atlas["xi"], np.ones(F, bool), img)
    with pytest.raises(ValueError, match="differ in shape"):
        face_ssim(img, cov, img[:32, :32], cov, atlas["tf"], F)
    with pytest.raises(ValueError, match="covered_b"):
        face_ssim(img, cov, img, cov[:10], atlas["tf"], F)
    with pytest.raises(ValueError, match="n_faces"):
        face_ssim(img, cov, img, cov, atlas["tf"], 5)
    with pytest.raises(ValueError, match="mode"):
        face_ssim(img, cov, img, cov, atlas["tf"], F, mode="fancy")
    with pytest.raises(ValueError, match="data_range"):
        face_ssim(img, cov, img, cov, atlas["tf"], F, data_range=0)
    with pytest.raises(ValueError, match=r"\(T, F\)"):
        temporal_gate(np.ones(5))
    with pytest.raises(ValueError, match="float"):
        temporal_gate(np.ones((2, 2), int))
    with pytest.raises(ValueError, match="label_sets"):
        label_set_min(np.ones((2, 3), np.float32), np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="label_sets holds frame"):
        label_set_min(np.ones((2, 3), np.float32), np.full((3, 1), 5))
    with pytest.raises(ValueError, match="pairs"):
        spatial_edge_weight(np.ones(3, np.float32), np.array([[0, 3]]))
    with pytest.raises(ValueError, match="NaN"):
        spatial_edge_weight(np.array([1, np.nan], np.float32), np.array([[0, 1]]))
    with pytest.raises(ValueError, match="mode"):
        spatial_edge_weight(np.ones(3, np.float32), np.array([[0, 1]]), mode="x")
    with pytest.raises(ValueError, match="frame 1: face_visible_t"):
        dynamism_table(lambda t: (img, atlas["xi"], np.ones(F if t == 0 else 3, bool)), 2, atlas["sampler"])
    with pytest.raises(ValueError, match="consecutive"):
        dynamism_rows(lambda t: (img, atlas["xi"], np.ones(F, bool)), [1, 3], atlas["sampler"])


def test_dynamism_on_the_tiny_pipeline(tiny_config, tmp_path):
    """The real stores (ingest -> projection, Φ as ξ): S is NaN wherever a face is not seen in
    both frames, most faces seen in both are scored at 256², and consecutive frames of the
    slowly deforming object agree (median S >= 0.95; with u and v swapped it is ~0.8)."""
    from conftest import run_stages
    from stex.io import open_store

    paths = run_stages(tiny_config, tmp_path)
    tm = open_store(paths["template"], "template")
    pr = open_store(paths["projection"], "projection")
    color = np.concatenate([open_store(f, "frames")["color"][...] for f in paths["frames"]])
    phi, vis = pr["phi"][...], pr["face_visible"][...]
    tf, bary = texel_map(tm["texcoords"][...], tm["texcoord_faces"][...], 256)
    sampler = TexelSampler(tf, bary, tm["faces"][...])
    S = dynamism_table(lambda t: (color[t], phi[t], vis[t]), len(color), sampler)
    both = vis[1:] & vis[:-1]
    scored = np.isfinite(S[1:])
    assert not (scored & ~both).any()
    assert scored.sum() >= 0.4 * both.sum()
    assert np.nanmedian(S) >= 0.95
    assert np.nanmax(S) <= 1.0 + 1e-6


def test_non_finite_texels_and_float_indices_are_refused():
    """One NaN texel made its face's S NaN, which the gate reads as static; float indices were
    a bincount TypeError or an IndexError."""
    W = 16
    rng = np.random.default_rng(1)
    a = rng.random((W, W, 3))
    cov = np.ones((W, W), bool)
    tf = np.zeros((W, W), np.int32)
    assert np.isfinite(face_ssim(a, cov, a, cov, tf, 1, data_range=1.0, erode_px=0)).all()
    b = a.copy()
    b[3, 3] = np.nan
    cov_b = cov.copy()
    cov_b[3, 3] = False            # outside the coverage too: the SSIM windows read it
    for c in (cov, cov_b):
        with pytest.raises(ValueError, match="tex_b holds 3 non-finite"):
            face_ssim(a, cov, b, c, tf, 1, data_range=1.0, erode_px=0)
    with pytest.raises(ValueError, match="texel_face must be integer"):
        face_ssim(a, cov, a, cov, tf.astype(float), 1, data_range=1.0)
    g = temporal_gate(np.ones((3, 2), np.float32), 0.95)
    with pytest.raises(ValueError, match="label_a must be integer"):
        temporal_pair_weight(g, [0, 1], [0.0, 1.0], [1, 2])


def test_grey_is_bt601():
    """SSIM is computed on 0.299 R + 0.587 G + 0.114 B (module docstring); a swapped R and B
    (BGR order) changed no other test."""
    from stex.image import grey

    img = np.zeros((1, 3, 3), np.uint8)
    img[0, 0, 0] = img[0, 1, 1] = img[0, 2, 2] = 200
    np.testing.assert_allclose(grey(img)[0], [59.8, 117.4, 22.8], atol=1e-9)


def test_common_coverage_is_eroded_by_the_window_radius_on_every_side():
    """Only texels whose whole (2r+1)² window (r = 5 at σ 1.5) is covered in both frames count,
    and outside the atlas counts as uncovered: a covered square [4, 28)² shrinks to exactly
    [9, 23)², a fully covered atlas to [5, W-5)²."""
    W = 32
    tex = np.random.default_rng(0).random((W, W))
    tf = np.zeros((W, W), np.int32)
    full = np.ones((W, W), bool)
    block = np.zeros((W, W), bool)
    block[4:28, 4:28] = True
    _, _, valid = face_ssim(tex, block, tex, full, tf, 1, data_range=1.0, return_map=True)
    want = np.zeros((W, W), bool)
    want[9:23, 9:23] = True
    np.testing.assert_array_equal(valid, want)
    _, _, valid = face_ssim(tex, full, tex, full, tf, 1, data_range=1.0, return_map=True)
    want = np.zeros((W, W), bool)
    want[5:W - 5, 5:W - 5] = True
    np.testing.assert_array_equal(valid, want)


def test_ssim_map_equals_the_whole_image_ssim_on_the_valid_texels():
    """face_ssim computes SSIM on the bounding box of the valid texels plus a margin ("same
    values, less work"): on the valid texels the map must equal scikit-image's SSIM of the whole
    textures (the valid texels' windows lie inside the coverage, away from the image border)."""
    from skimage.metrics import structural_similarity

    W = 48
    rng = np.random.default_rng(1)
    a = rng.random((W, W))
    b = np.clip(a + rng.normal(0, 0.1, (W, W)), 0, 1)
    tf = np.zeros((W, W), np.int32)
    cov = np.zeros((W, W), bool)
    cov[14:34, 14:34] = True
    S, smap, valid = face_ssim(a, cov, b, cov, tf, 1, data_range=1.0, return_map=True)
    _, ref = structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                   use_sample_covariance=False, full=True)
    assert valid.sum() == 100                                  # [19, 29)²
    np.testing.assert_allclose(smap[valid], ref[valid], atol=1e-6)
    assert S[0] == pytest.approx(ref[valid].mean(), abs=1e-6)


def test_ssim_map_is_scikit_images_bit_for_bit():
    """The map of the default window comes from stex.ssim's kernels: on the bounding box face_ssim
    scores it must be scikit-image's SSIM of the same crop exactly (float32 as stored), uint8
    RGB textures and the default data range."""
    from skimage.metrics import structural_similarity

    from stex.image import grey

    W = 64
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (W, W, 3)).astype(np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-30, 30, a.shape), 0, 255).astype(np.uint8)
    tf = rng.integers(0, 4, (W, W)).astype(np.int32)
    cov = np.zeros((W, W), bool)
    cov[10:50, 12:60] = True
    _, smap, valid = face_ssim(a, cov, b, cov, tf, 4, data_range=255.0, return_map=True)
    r0, r1, c0, c1 = 8, 52, 10, 62    # the valid box [15, 45) x [17, 55) plus the margin of 7
    assert valid[15:45, 17:55].all() and valid.sum() == 30 * 38
    _, ref = structural_similarity(grey(a[r0:r1, c0:c1]), grey(b[r0:r1, c0:c1]), data_range=255.0,
                                   gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                   full=True)
    np.testing.assert_array_equal(smap[valid], ref.astype(np.float32)[valid[r0:r1, c0:c1]])


def test_label_set_min_skips_nan_entries():
    """S_m(f) is the minimum over the face's labels with NaN entries skipped (docstring): a
    label never compared does not hide another label's dynamism."""
    S = np.array([[np.nan, 0.5, np.nan],
                  [0.9, np.nan, np.nan]], np.float32)
    got = label_set_min(S, np.ones((2, 3), bool))
    np.testing.assert_array_equal(got[:2], np.float32([0.9, 0.5]))
    assert np.isnan(got[2])
    np.testing.assert_array_equal(spatial_face_weight(S, np.ones((2, 3), bool), 0.95), [0, 0, 1])


def test_authors_dilation_defaults_to_ten_texels_per_thousand():
    """The authors dilate the low-SSIM texels by 10 x 10 at 1000²; by default the side scales
    with the atlas: 5 texels at W = 500, i.e. two texels either side of a low one."""
    W = 500
    tf = np.tile(np.arange(W, dtype=np.int32), (W, 1))    # face = column
    mm = np.ones((W, W), np.float32)
    mm[250, 250] = 0.5
    np.testing.assert_array_equal(np.flatnonzero(authors_dynamic_faces(mm, tf, W)),
                                  [248, 249, 250, 251, 252])
