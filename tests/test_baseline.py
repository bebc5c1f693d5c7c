"""Baselines: Kim et al. 2019's single global texture and the naive per-frame projection."""
import cv2
import numpy as np
import pytest

from stex.baseline import global_texture, projection_texture
from conftest import grid_atlas
from stex.template import texel_map
from stex.volume import TexelSampler

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
