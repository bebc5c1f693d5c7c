"""Baselines: Kim et al. 2019's single global texture and the naive per-frame projection."""
import cv2
import numpy as np
import pytest

from stex.global_texture import global_texture, projection_texture
from stex.stages.global_texture import write_global_texture
from stex.data_term import source_mask
from conftest import grid_atlas, run_stages, tiny_scene_config
from stex.atlas import texel_map
from stex.sampling import TexelSampler

W = 64
N = 9
HC = 96  # colour image side, px


@pytest.fixture(scope="module")
def atlas():
    """A flat N x N vertex grid covering [0.05, 0.95]^2 of the atlas; texcoords = vertices."""
    tc, faces = grid_atlas(N)
    tf, bary = texel_map(tc, faces, W)
    return {"tc": tc, "faces": faces, "tf": tf, "F": len(faces), "sampler": TexelSampler(tf, bary, faces)}


def _truth():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (W, W, 3)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 235 + 10
    return (img + 0.5).astype(np.uint8)


def _frame(truth, offset, noise_seed=None):
    """The truth texture seen in a HC x HC image, translated by ``offset`` (px, fractional) and
    optionally with sensor noise (σ 4 grey levels); the atlas texel (r, c) lands on pixel
    (c + ox, r + oy)."""
    M = np.float32([[1, 0, offset[0]], [0, 1, offset[1]]])
    img = cv2.warpAffine(truth.astype(np.float32), M, (HC, HC), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    if noise_seed is not None:
        img = img + np.random.default_rng(noise_seed).normal(0, 4.0, img.shape)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def test_static_object_from_several_frames_recovers_the_truth(atlas):
    truth = _truth()
    offsets = [(0.0, 0.0), (10.5, 3.25), (4.75, 20.0), (25.0, 12.5), (17.25, 28.75)]
    F = atlas["F"]
    rng = np.random.default_rng(1)
    vis = rng.random((len(offsets), F)) < 0.6          # each frame sees a different subset
    vis[0, ~vis.any(0)] = True                         # every face seen at least once
    cos = rng.uniform(0.2, 1.0, (len(offsets), F)).astype(np.float32)
    calls = []

    def load(t):
        calls.append(t)
        xi = (atlas["tc"] * W - 0.5 + np.array(offsets[t])).astype(np.float32)
        return _frame(truth, offsets[t], noise_seed=10 + t), xi, vis[t]

    tex, wsum = global_texture(load, len(offsets), atlas["sampler"], face_weight=cos, gutter_px=2)
    assert calls == list(range(len(offsets)))          # streaming: each frame once, in order
    assert tex.dtype == np.uint8 and tex.shape == (W, W, 3) and wsum.dtype == np.float32
    cov = atlas["tf"] >= 0
    assert np.all(wsum[cov] > 0) and np.all(wsum[~cov] == 0)
    # Σ_t w_t(f) of the texel's face
    expect = (cos * vis).sum(0)[atlas["tf"][cov]]
    np.testing.assert_allclose(wsum[cov], expect, rtol=1e-5)
    err = np.abs(tex[cov].astype(int) - truth[cov].astype(int))
    assert err.mean() < 2.5 and np.percentile(err, 99) <= 8
    # the noise of a single frame is larger than that of the blend
    single = _frame(truth, (0, 0), noise_seed=10)
    err1 = np.abs(single[:W, :W][cov].astype(int) - truth[cov].astype(int))
    assert err.mean() < err1.mean()
    # gutter: 2 rings around the grid filled, beyond stays black
    ring = cv2.dilate(cov.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert tex[ring & ~cov].any(axis=-1).all() and not tex[~ring].any()


def test_weights_are_normalised(atlas):
    F = atlas["F"]
    xi = (atlas["tc"] * W - 0.5).astype(np.float32)
    vis = np.ones((3, F), bool)
    rng = np.random.default_rng(2)
    w = rng.uniform(0.1, 1.0, (3, F)).astype(np.float32)
    # a constant-colour scene stays that colour whatever the weights
    const = np.full((HC, HC, 3), (200, 100, 50), np.uint8)
    tex, _ = global_texture(lambda t: (const, xi, vis[t]), 3, atlas["sampler"], face_weight=w, gutter_px=0)
    cov = atlas["tf"] >= 0
    assert np.all(tex[cov] == (200, 100, 50))
    # two colours: frame 0 weight 3, frame 1 weight 1 -> (3 A + B) / 4 exactly
    A = np.full((HC, HC, 3), 40, np.uint8)
    B = np.full((HC, HC, 3), 200, np.uint8)
    w2 = np.stack([np.full(F, 3.0), np.full(F, 1.0)]).astype(np.float32)
    tex2, wsum2 = global_texture(lambda t: ((A, B)[t], xi, vis[t]), 2, atlas["sampler"],
                                 face_weight=lambda t: w2[t], gutter_px=0)
    assert np.all(tex2[cov] == 80) and np.all(wsum2[cov] == 4.0)
    # min_weight leaves out the light frame (weight 1 <= 2): only A remains
    tex3, _ = global_texture(lambda t: ((A, B)[t], xi, vis[t]), 2, atlas["sampler"], face_weight=w2,
                             min_weight=2.0, gutter_px=0)
    assert np.all(tex3[cov] == 40)
    # no weights: plain average over the frames where the face is visible
    vis4 = vis[:2].copy()
    vis4[1, :10] = False
    tex4, wsum4 = global_texture(lambda t: ((A, B)[t], xi, vis4[t]), 2, atlas["sampler"], gutter_px=0)
    only_a = np.isin(atlas["tf"], np.arange(10))
    assert np.all(tex4[only_a] == 40) and np.all(tex4[cov & ~only_a] == 120)
    assert np.all(wsum4[only_a] == 1) and np.all(wsum4[cov & ~only_a] == 2)


def test_min_weight_drops_pairs_at_or_below_it_per_face(atlas):
    """min_weight acts per (frame, face) pair, and a weight equal to it is left out (``<=``):
    frame 0 (colour 40, weight 3 everywhere) is always kept; frame 1 (colour 200) is kept only on
    the faces where its weight 3 is above min_weight 2, not where it is 1 or exactly 2. The
    dropped faces take frame 0 alone (40, weight sum 3), not a blend with frame 1's black
    uncovered texels; the others (3·40 + 3·200) / 6 = 120, weight sum 6."""
    F = atlas["F"]
    xi = (atlas["tc"] * W - 0.5).astype(np.float32)
    vis = np.ones(F, bool)
    A = np.full((HC, HC, 3), 40, np.uint8)
    B = np.full((HC, HC, 3), 200, np.uint8)
    w = np.full((2, F), 3.0, np.float32)
    w[1, :10] = 1.0                                    # below min_weight
    w[1, 10:20] = 2.0                                  # exactly min_weight
    tex, wsum = global_texture(lambda t: ((A, B)[t], xi, vis), 2, atlas["sampler"], face_weight=w,
                               min_weight=2.0, gutter_px=0)
    cov = atlas["tf"] >= 0
    dropped = np.isin(atlas["tf"], np.arange(20))
    assert np.all(tex[dropped] == 40) and np.all(wsum[dropped] == 3.0)
    assert np.all(tex[cov & ~dropped] == 120) and np.all(wsum[cov & ~dropped] == 6.0)


def test_unseen_faces_are_filled_and_marked(atlas):
    F = atlas["F"]
    xi = (atlas["tc"] * W - 0.5).astype(np.float32)
    vis = np.ones(F, bool)
    vis[:16] = False                                   # the first grid row of cells never seen
    img = np.full((HC, HC, 3), 90, np.uint8)
    tex, wsum = global_texture(lambda t: (img, xi, vis), 1, atlas["sampler"], gutter_px=0)
    unseen = np.isin(atlas["tf"], np.arange(16))
    assert np.all(wsum[unseen] == 0) and np.all(tex[unseen] == 90)   # filled from neighbours


def test_projection_texture_only_what_the_frame_sees(atlas):
    F = atlas["F"]
    truth = _truth()
    xi = (atlas["tc"] * W - 0.5 + np.array([10.5, 3.25])).astype(np.float32)
    vis = np.zeros(F, bool)
    vis[40:90] = True
    tex, cov = projection_texture(atlas["sampler"], xi, vis, _frame(truth, (10.5, 3.25)))
    np.testing.assert_array_equal(cov, np.isin(atlas["tf"], np.arange(40, 90)))
    assert not tex[~cov].any()
    err = np.abs(tex[cov].astype(int) - truth[cov].astype(int))
    assert err.mean() < 2.0


def test_bad_inputs_raise(atlas):
    F = atlas["F"]
    xi = (atlas["tc"] * W - 0.5).astype(np.float32)
    img = np.zeros((HC, HC, 3), np.uint8)
    vis = np.ones(F, bool)
    with pytest.raises(ValueError, match="n_frames"):
        global_texture(lambda t: (img, xi, vis), 0, atlas["sampler"])
    with pytest.raises(ValueError, match="face_weight row 0"):
        global_texture(lambda t: (img, xi, vis), 1, atlas["sampler"], face_weight=np.ones((1, F - 1)))
    with pytest.raises(ValueError, match=">= 0"):
        global_texture(lambda t: (img, xi, vis), 1, atlas["sampler"], face_weight=-np.ones((1, F)))
    with pytest.raises(ValueError, match="load"):
        global_texture(lambda t: (img, xi), 1, atlas["sampler"])
    with pytest.raises(ValueError, match="image_t"):
        projection_texture(atlas["sampler"], xi, vis, img[..., 0])


# --------------------------------------------------------------------------------------------
# the global_texture stage on the tiny synthetic scene
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    """ingest .. projection of the tiny synthetic scene (6 frames, blocks [0, 4) and [4, 6))."""
    cfg = tiny_scene_config(template={"atlas_size": 128})
    return run_stages(cfg, tmp_path_factory.mktemp("tiny"))


def _direct(P, positions, min_weight, frames=None):
    """global_texture called directly on the given sequence positions of the tiny scene."""
    from stex.io import FrameSequence, open_store

    template = open_store(P["template"], "template")
    proj = open_store(P["projection"], "projection")
    photos = FrameSequence(frames or P["frames"], "frames")
    faces = template["faces"][...]
    sampler = TexelSampler(template["texel/face_id"][...], template["texel/bary"][...], faces)
    vis, cos, phi = proj["face_visible"][...], proj["face_cos"][...], proj["phi"][...]
    pos = list(positions)
    tex, wsum = global_texture(lambda k: (photos.read("color", photos.frame_ids[pos[k]]),
                                          phi[pos[k]].astype(np.float64), vis[pos[k]]),
                               len(pos), sampler, face_weight=cos[pos], min_weight=min_weight,
                               gutter_px=int(template.attrs["gutter_px"]))
    return tex, wsum, (vis[pos] & (cos[pos] > min_weight)).any(0)


def _write(P, out, params, frames=None):
    write_global_texture(P["scene"], frames or P["frames"], P["template"], P["projection"],
                         P["projection"], out, params)
    from stex.io import open_store
    return open_store(out, "global_texture")


def test_source_mask():
    assert source_mask(7, 3).tolist() == [True, False, False, True, False, False, True]
    assert source_mask(4, 1).all()
    with pytest.raises(ValueError, match="source_stride"):
        source_mask(4, 0)


def test_write_global_texture_is_the_direct_blend(stages, tmp_path):
    P = stages
    g = _write(P, tmp_path / "g.zarr", {"min_weight": 0.3})
    tex, wsum, textured = _direct(P, range(6), 0.3)
    assert g["texture"].dtype == np.uint8 and g["texture"].shape == (128, 128, 3)
    np.testing.assert_array_equal(g["texture"][...], tex)
    np.testing.assert_array_equal(g["weight_sum"][...], wsum)
    np.testing.assert_array_equal(g["face_textured"][...], textured)
    assert g.attrs["source_frames"] == list(range(6)) and g.attrs["seconds"] > 0
    assert g.attrs["params"] == {"min_weight": 0.3, "source_stride": 1}
    # min_weight matters: some faces are only seen at grazing angles
    assert 0 < textured.sum() < _write(P, tmp_path / "g0.zarr", {})["face_textured"][...].sum()


def test_source_stride_uses_only_the_source_frames(stages, tmp_path):
    """With source_stride 2 only positions 0, 2, 4 are read: painting the odd frames red changes
    nothing, while the stride-1 texture does change."""
    import shutil

    import zarr

    P = stages
    red_frames = []
    for b, path in enumerate(P["frames"]):
        q = tmp_path / f"frames_{b}.zarr"
        shutil.copytree(path, q)
        g = zarr.open_group(str(q), mode="r+")
        for i, fid in enumerate(g.attrs["frame_ids"]):
            if fid % 2 == 1:
                img = g["color"][i]
                img[...] = (255, 0, 0)
                g["color"][i] = img
        red_frames.append(q)
    g2 = _write(P, tmp_path / "g2.zarr", {"source_stride": 2})
    assert g2.attrs["source_frames"] == [0, 2, 4]
    tex, wsum, textured = _direct(P, [0, 2, 4], 0.0)
    np.testing.assert_array_equal(g2["texture"][...], tex)
    np.testing.assert_array_equal(g2["weight_sum"][...], wsum)
    np.testing.assert_array_equal(g2["face_textured"][...], textured)
    g2_red = _write(P, tmp_path / "g2red.zarr", {"source_stride": 2}, frames=red_frames)
    np.testing.assert_array_equal(g2_red["texture"][...], g2["texture"][...])
    g1, g1_red = (_write(P, tmp_path / "g1.zarr", {}),
                  _write(P, tmp_path / "g1red.zarr", {}, frames=red_frames))
    assert (g1_red["texture"][...] != g1["texture"][...]).any()
    # the odd frames add weight where they see faces
    assert (g1["weight_sum"][...] > g2["weight_sum"][...]).any()


def test_write_global_texture_bad_inputs_name_the_store(stages, tmp_path):
    import shutil

    import zarr

    from stex.io import StoreError

    P = stages
    short = tmp_path / "projection_5.zarr"
    shutil.copytree(P["projection"], short)
    g = zarr.open_group(str(short), mode="r+")
    g.attrs["frame_ids"] = g.attrs["frame_ids"][:5]
    for name in ("phi", "vertex_visible", "vertex_cos", "face_visible", "face_cos"):
        g[name].resize((5,) + g[name].shape[1:])
    with pytest.raises(ValueError, match="projection_5.zarr"):
        write_global_texture(P["scene"], P["frames"], P["template"], short, P["projection"],
                             tmp_path / "a.zarr", {})
    with pytest.raises(ValueError, match="projection_5.zarr"):   # as texture coordinates
        write_global_texture(P["scene"], P["frames"], P["template"], P["projection"], short,
                             tmp_path / "b.zarr", {})
    with pytest.raises(ValueError, match="frames"):              # a frame block missing
        write_global_texture(P["scene"], P["frames"][:1], P["template"], P["projection"],
                             P["projection"], tmp_path / "c.zarr", {})
    with pytest.raises(StoreError, match="nothing.zarr"):
        write_global_texture(P["scene"], P["frames"], tmp_path / "nothing.zarr", P["projection"],
                             P["projection"], tmp_path / "d.zarr", {})
    with pytest.raises(ValueError, match="min_weights"):
        write_global_texture(P["scene"], P["frames"], P["template"], P["projection"],
                             P["projection"], tmp_path / "e.zarr", {"min_weights": 0.1})
    assert not any((tmp_path / n).exists() for n in ("a.zarr", "b.zarr", "c.zarr", "d.zarr", "e.zarr"))


def test_face_textured_leaves_out_weights_at_min_weight(stages, tmp_path):
    """A face whose weight (face_cos) is exactly min_weight in every frame is left out of the
    blend (``<=``), so it is not ``face_textured`` and its texels have weight sum 0, as the faces
    never seen."""
    import shutil

    import zarr

    from stex.io import open_store

    P = stages
    proj = tmp_path / "projection.zarr"
    shutil.copytree(P["projection"], proj)
    g = zarr.open_group(str(proj), mode="r+")
    seen = np.flatnonzero(g["face_visible"][...].any(0))
    at = seen[::3]                                     # a third of the seen faces
    cos = g["face_cos"][...]
    cos[:, at] = 0.5
    cos[:, np.setdiff1d(seen, at)] = np.maximum(cos[:, np.setdiff1d(seen, at)], 0.75)
    g["face_cos"][...] = cos
    write_global_texture(P["scene"], P["frames"], P["template"], proj, proj, tmp_path / "g.zarr",
                         {"min_weight": 0.5})
    out = open_store(tmp_path / "g.zarr", "global_texture")
    textured = out["face_textured"][...]
    assert not textured[at].any() and textured[np.setdiff1d(seen, at)].all()
    tf = open_store(P["template"], "template")["texel/face_id"][...]
    assert not out["weight_sum"][...][np.isin(tf, at)].any()
