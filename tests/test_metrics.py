"""Tests of stex.metrics (the metric code of issue 7)."""

import numpy as np
import pytest
from scipy import ndimage as ndi
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from stex import metrics as ev
from stex.ssim import SSIM_WEIGHTS, SsimCache, ssim_filter, ssim_map
from stex.camera import transform_points


def textured_image(h=192, w=256, seed=0):
    """A smooth random colour image spanning ~30..225 (structure at several scales)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3))
    for s in (1.5, 4.0):
        img += ndi.gaussian_filter(rng.normal(size=(h, w, 3)), (s, s, 0)) * s
    img -= img.mean()
    img *= 60.0 / img.std()
    return np.clip(img + 128.0, 30.0, 225.0)


def disk(h, w, radius, cy=None, cx=None):
    cy = h / 2 if cy is None else cy
    cx = w / 2 if cx is None else cx
    y, x = np.mgrid[0:h, 0:w]
    return (y - cy) ** 2 + (x - cx) ** 2 <= radius ** 2


def brute_force_patch_shift(ref, tst, mask, P, r, min_fraction=0.5):
    """Slow, obvious implementation of the documented definition."""
    ref = ref.astype(float).reshape(ref.shape[0], ref.shape[1], -1)
    tst = tst.astype(float).reshape(ref.shape)
    H, W, C = ref.shape
    rows = np.flatnonzero(mask.any(1))
    cols = np.flatnonzero(mask.any(0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    tot_sse, tot_n, per_patch = 0.0, 0, []
    for y0 in range(r0, r1, P):
        for x0 in range(c0, c1, P):
            pix = [(y, x) for y in range(y0, y0 + P) for x in range(x0, x0 + P)
                   if y < H and x < W and mask[y, x]]
            if len(pix) == 0 or len(pix) < min_fraction * P * P:
                continue
            best = np.inf
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    sse = 0.0
                    for y, x in pix:
                        yy = min(max(y + dy, 0), H - 1)
                        xx = min(max(x + dx, 0), W - 1)
                        sse += ((ref[y, x] - tst[yy, xx]) ** 2).sum()
                    best = min(best, sse)
            tot_sse += best
            tot_n += len(pix)
            per_patch.append(best / (C * len(pix)))
    return tot_sse / (C * tot_n), len(per_patch), np.array(per_patch)


# ---------------------------------------------------------------------------------- patch shift

def test_patch_shift_identical_is_capped():
    ref = textured_image()
    mask = disk(*ref.shape[:2], 80)
    res = ev.patch_shift_psnr(ref, ref.copy(), mask)
    assert res["psnr"] == ev.PSNR_CAP and res["psnr_patch_mean"] == ev.PSNR_CAP
    assert res["mse"] == 0.0 and res["mean_shift_px"] == 0.0
    assert res["n_patches"] > 10 and res["patch"] == 32 and res["radius"] == 4


def test_patch_shift_forgives_a_shift():
    ref = textured_image()
    rng = np.random.default_rng(1)
    noisy = ref + rng.normal(0, 4.0, ref.shape)
    shifted = np.roll(noisy, (3, -2), axis=(0, 1))  # test content moved 3 px down, 2 px left
    mask = disk(*ref.shape[:2], 80)
    plain_aligned = ev.masked_psnr(ref, noisy, mask)["psnr"]
    plain_shifted = ev.masked_psnr(ref, shifted, mask)["psnr"]
    ps = ev.patch_shift_psnr(ref, shifted, mask, patch=32, radius=4)
    assert plain_shifted < plain_aligned - 10.0
    assert abs(ps["psnr"] - plain_aligned) < 0.3
    assert abs(ps["mean_shift_px"] - np.hypot(3, 2)) < 1e-9
    assert ps["psnr_unshifted"] < plain_aligned - 10.0
    # r < shift: cannot fully recover, best shifts pile up on the search border
    ps2 = ev.patch_shift_psnr(ref, shifted, mask, patch=32, radius=2)
    assert ps2["psnr"] < ps["psnr"] - 3.0 and ps2["frac_shift_at_radius"] == 1.0


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0])
def test_patch_shift_noise_level(sigma):
    ref = textured_image(256, 320, seed=2)
    rng = np.random.default_rng(3)
    tst = ref + rng.normal(0, sigma, ref.shape)
    mask = disk(256, 320, 120)
    res = ev.patch_shift_psnr(ref, tst, mask)
    assert abs(res["psnr"] - 20 * np.log10(255 / sigma)) < 0.2


def test_patch_shift_respects_mask():
    ref = textured_image(seed=4)
    rng = np.random.default_rng(5)
    tst = ref + rng.normal(0, 6.0, ref.shape)
    mask = disk(*ref.shape[:2], 70)
    base = ev.patch_shift_psnr(ref, tst, mask, radius=4)
    ref_g, tst_g = ref.copy(), tst.copy()
    ref_g[~mask] = rng.uniform(0, 255, ((~mask).sum(), 3))
    far = ~ndi.binary_dilation(mask, iterations=4 + 1)  # test is read up to r px outside the mask
    tst_g[far] = rng.uniform(0, 255, (far.sum(), 3))
    other = ev.patch_shift_psnr(ref_g, tst_g, mask, radius=4)
    assert other["psnr"] == pytest.approx(base["psnr"], abs=1e-12)
    assert other["n_patches"] == base["n_patches"]


@pytest.mark.parametrize("seed,P,r,gray", [(0, 5, 2, False), (1, 4, 1, True), (2, 6, 3, False)])
def test_patch_shift_matches_brute_force(seed, P, r, gray):
    rng = np.random.default_rng(seed)
    H, W = 17, 23
    shape = (H, W) if gray else (H, W, 3)
    ref = rng.integers(0, 256, shape).astype(np.uint8)
    tst = np.clip(ref.astype(float) + rng.normal(0, 20, shape), 0, 255)
    tst = np.roll(tst, (1, -1), axis=(0, 1))
    mask = rng.random((H, W)) < 0.75
    mask[0, :] = False  # bbox not at the image corner
    res = ev.patch_shift_psnr(ref, tst, mask, patch=P, radius=r)
    mse, n, per = brute_force_patch_shift(ref, tst, mask, P, r)
    assert res["n_patches"] == n
    assert res["mse"] == pytest.approx(mse, rel=1e-12)
    assert res["psnr_patch_mean"] == pytest.approx(
        np.mean(10 * np.log10(255.0 ** 2 / per)), rel=1e-12)


def test_patch_shift_r0_equals_plain_psnr_and_empty_mask():
    ref = textured_image(seed=6)
    tst = ref + np.random.default_rng(7).normal(0, 8, ref.shape)
    full = np.ones(ref.shape[:2], bool)
    res = ev.patch_shift_psnr(ref, tst, full, patch=32, radius=0)
    assert res["psnr"] == pytest.approx(ev.masked_psnr(ref, tst, full)["psnr"], abs=1e-9)
    empty = ev.patch_shift_psnr(ref, tst, np.zeros_like(full))
    assert np.isnan(empty["psnr"]) and empty["n_patches"] == 0


def test_patch_counts_at_exactly_min_fraction_and_border_shifts_are_chebyshev():
    """Two documented patch-shift details: a patch with exactly ``min_fraction`` of its P^2
    pixels in the mask counts ("at least 50 %", docs/metrics.md), and
    ``frac_shift_at_radius`` counts shifts on the square search border (|dy| or |dx| = r), so a
    pure shift along one axis by r is flagged as "r too small"."""
    rng = np.random.default_rng(21)
    ref = rng.uniform(30, 225, (12, 12, 3))
    mask = np.zeros((12, 12), bool)
    mask[2:10, 2:6] = True                       # P = 8: one patch, 8 x 4 = exactly half masked
    res = ev.patch_shift_psnr(ref, ref, mask, patch=8, radius=1)
    assert res["n_patches"] == 1 and res["n_pixels"] == 32
    assert ev.patch_shift_psnr(ref, ref, mask, patch=8, radius=1, min_fraction=0.51)["n_patches"] == 0
    big = textured_image(64, 64, seed=22)
    moved = np.roll(big, 2, axis=0)               # content 2 px down, no horizontal shift
    full = np.ones((64, 64), bool)
    res = ev.patch_shift_psnr(big, moved, full, patch=16, radius=2)
    assert res["mean_shift_px"] == pytest.approx(2.0, abs=1e-12)
    assert res["frac_shift_at_radius"] == 1.0


# ----------------------------------------------------------------------------------- psnr/ssim

def test_masked_psnr_matches_skimage():
    ref = textured_image(seed=8)
    tst = np.clip(ref + np.random.default_rng(9).normal(0, 7, ref.shape), 0, 255)
    ours = ev.masked_psnr(ref, tst, np.ones(ref.shape[:2], bool), data_range=255)
    assert ours["psnr"] == pytest.approx(peak_signal_noise_ratio(ref, tst, data_range=255), abs=1e-10)
    assert ev.masked_psnr(ref, ref)["psnr"] == ev.PSNR_CAP


def test_psnr_is_capped_at_100_db():
    """The cap is part of the metric's definition (module docstring, docs/metrics.md: 100 dB,
    also the value for MSE = 0): a near-perfect image scores 100, not 168 dB, and the cap is
    not a free constant (scores of different runs are averaged against it)."""
    assert ev.PSNR_CAP == 100.0
    assert ev.psnr_from_mse(0.0) == 100.0
    assert ev.psnr_from_mse(1e-12) == 100.0                 # 10 log10(255^2 / 1e-12) = 168 dB
    np.testing.assert_array_equal(ev.psnr_from_mse(np.array([0.0, 1e-9, 65025.0])), [100.0, 100.0, 0.0])
    ref = textured_image(32, 32, seed=23)
    assert ev.masked_psnr(ref, ref + 1e-6)["psnr"] == 100.0


def test_masked_ssim_matches_skimage():
    ref = textured_image(seed=10)
    tst = np.clip(ref + np.random.default_rng(11).normal(0, 10, ref.shape), 0, 255)
    kw = dict(data_range=255.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
              use_sample_covariance=False)
    mssim, S = structural_similarity(ref, tst, full=True, **kw)
    ours = ev.masked_ssim(ref, tst, np.ones(ref.shape[:2], bool), data_range=255)
    assert ours["ssim"] == pytest.approx(mssim, abs=1e-12)
    # a small mask: the crop gives the full-image map's values
    mask = disk(*ref.shape[:2], 30, cy=70, cx=150)
    small = ev.masked_ssim(ref, tst, mask, data_range=255)
    assert small["ssim"] == pytest.approx(S.mean(axis=-1)[mask].mean(), abs=1e-12)
    assert small["n_pixels"] == mask.sum()


def test_ssim_map_is_skimages_bit_for_bit():
    """The SSIM map's own kernels (the Gaussian window, the formulas) give skimage's map exactly,
    on uint8-valued and on arbitrary float images, with a cache or without: the evaluation's
    scores do not move by a bit. A cached reference is used only for the same pixels."""
    kw = dict(data_range=255.0, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    rng = np.random.default_rng(5)
    for shape in [(6, 9), (11, 40), (57, 43), (120, 90)]:
        x = rng.normal(120, 60, shape)
        assert np.array_equal(ssim_filter(x, SSIM_WEIGHTS),
                              ndi.gaussian_filter(x, 1.5, mode="reflect", truncate=3.5)), shape
    for shape in [(11, 40, 3), (37, 23, 3), (64, 80, 1), (120, 90, 3)]:
        ref = rng.integers(0, 256, shape).astype(np.float64)
        tests = [np.clip(ref + rng.normal(0, s, shape), 0, 255).round() for s in (5, 30)]
        tests.append(rng.uniform(0, 255, shape))
        cache = SsimCache()
        for tst in tests:
            S = structural_similarity(ref, tst, full=True, **kw)[1].reshape(shape[0], shape[1], -1).mean(axis=-1)
            assert np.array_equal(ssim_map(ref, tst, 255.0, None), S), shape
            assert np.array_equal(ssim_map(ref, tst, 255.0, cache), S), shape
        # the same shape and the same pixels on the cache's sparse sample, one pixel off it changed
        other = ref.copy()
        other[1, 1] = 255.0 - other[1, 1]
        S = structural_similarity(other, tests[0], full=True, **kw)[1].reshape(shape[0], shape[1], -1).mean(axis=-1)
        assert np.array_equal(ssim_map(other, tests[0], 255.0, cache), S), shape
    # the masked mean on the mask's box equals the full-image map's mean exactly
    ref = textured_image(seed=10)
    tst = np.clip(ref + np.random.default_rng(11).normal(0, 10, ref.shape), 0, 255)
    S = structural_similarity(ref, tst, full=True, **kw)[1].mean(axis=-1)
    mask = disk(*ref.shape[:2], 30, cy=70, cx=150)
    cache = SsimCache()
    assert ev.masked_ssim(ref, tst, mask, cache=cache)["ssim"] == S[mask].mean()
    assert ev.masked_ssim(ref, tst, mask, cache=cache)["ssim"] == S[mask].mean()


def test_blur_with_a_cache_equals_blur_without():
    """The mask's erosion and fill indices kept in a cache between images give the same blur; a
    mask differing in one pixel is not confused with a cached one."""
    rng = np.random.default_rng(8)
    images = [textured_image(seed=s) for s in (1, 2, 3)]
    mask = disk(*images[0].shape[:2], 40, cy=60, cx=90)
    other = mask.copy()
    other[60, 130 - 1] = ~other[60, 130 - 1]
    cache = {}
    for img in images:
        for m in (mask, other, rng.random(mask.shape) > 0.3):
            for erode in (0, 3):
                for fill in ("nearest", "mean"):
                    plain = ev.blur(img, m, fill=fill, erode_px=erode)
                    cached = ev.blur(img, m, fill=fill, erode_px=erode, cache=cache)
                    assert cached == plain or (np.isnan(plain["blur"]) and np.isnan(cached["blur"]))
    assert len(cache) == 3 * 2 * 2 + 2 * 2 * 2   # the random masks are new each time


def test_region_scores_on_the_masks_box_equal_the_full_image_ones():
    """region_psnr works on the mask's bounding box (plus the SSIM window): the same PSNR and
    SSIM as over the whole image, for a mask inside the image and one touching its border."""
    ref = textured_image(seed=13)
    tst = np.clip(ref + np.random.default_rng(14).normal(0, 10, ref.shape), 0, 255)
    kw = dict(data_range=255.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
              use_sample_covariance=False)
    S = structural_similarity(ref, tst, full=True, **kw)[1].mean(axis=-1)
    H, W = ref.shape[:2]
    inside = np.zeros((H, W), bool)
    inside[5:H - 5, 5:W - 5] = True                        # skimage leaves the 5 px border out
    region = (np.arange(W) % 7 < 3)[None, :].repeat(H, axis=0)   # stripes: splits any disk
    for mask in (disk(H, W, 30, cy=70, cx=150), disk(H, W, 40, cy=10, cx=W - 12)):
        r = ev.region_psnr(ref, tst, mask, region, ssim=True)
        for name, sel in (("all", mask), ("seen", mask & region), ("unseen", mask & ~region)):
            d = (ref - tst)[sel]
            assert r[f"psnr_{name}"] == pytest.approx(10 * np.log10(255.0 ** 2 / np.mean(d * d)), abs=1e-9)
            assert r[f"ssim_{name}"] == pytest.approx(S[sel & inside].mean(), abs=1e-12)
            assert r[f"n_{name}"] == sel.sum()


def test_regions_below_min_pixels_are_not_scored():
    ref = textured_image(seed=13)
    tst = np.clip(ref + np.random.default_rng(14).normal(0, 10, ref.shape), 0, 255)
    H, W = ref.shape[:2]
    mask = disk(H, W, 30, cy=70, cx=150)
    region = np.zeros((H, W), bool)
    region[70, 150:153] = True                              # 3 px seen
    full = ev.region_psnr(ref, tst, mask, region, ssim=True)
    r = ev.region_psnr(ref, tst, mask, region, ssim=True, min_pixels=100)
    assert np.isfinite(full["psnr_seen"]) and full["n_seen"] == 3
    assert np.isnan(r["psnr_seen"]) and np.isnan(r["ssim_seen"]) and np.isnan(r["mse_seen"])
    assert r["n_seen"] == 3                                  # the size is still reported
    for k in ("psnr_all", "psnr_unseen", "ssim_unseen"):     # the large regions are scored as before
        assert r[k] == full[k]


# ---------------------------------------------------------------------------------------- blur

def test_blur_orders_sharp_and_blurred():
    ref = textured_image(seed=12)
    mask = disk(*ref.shape[:2], 80)
    background = np.zeros_like(ref)
    sharp = np.where(mask[..., None], ref, background)
    soft = np.where(mask[..., None], ndi.gaussian_filter(ref, (2, 2, 0)), background)
    b_sharp = ev.blur(sharp, mask)
    b_soft = ev.blur(soft, mask)
    assert b_soft["blur"] > b_sharp["blur"] + 0.05
    assert b_sharp["h_size"] == 11 and ev.blur(sharp, mask, h_size=9)["h_size"] == 9
    assert 0.0 <= b_sharp["blur"] <= 1.0
    # the nearest fill makes the score independent of what surrounds the object
    white = np.where(mask[..., None], ref, 255.0)
    assert ev.blur(white, mask)["blur"] == pytest.approx(b_sharp["blur"], abs=1e-12)
    assert ev.blur(white, mask, fill="none")["blur"] != pytest.approx(b_sharp["blur"], abs=1e-3)


def test_blur_definition_and_fills_on_an_asymmetric_mask():
    """blur() is skimage's blur_effect with reduce_func=max (docs/metrics.md) on the crop: an
    image blurred along one axis only scores that axis's blur, not the mean of both. On an
    off-centre, non-square mask, the "nearest" fill still makes the score independent of the
    background, and "mean" equals "none" on the same image with the background already set
    to the masked mean colour."""
    from skimage.measure import blur_effect

    img = ndi.gaussian_filter(textured_image(64, 80, seed=24), (0, 3, 0))   # blurred along x only
    res = ev.blur(img, None)
    want = blur_effect(img / 255.0, h_size=11, channel_axis=-1, reduce_func=np.max)
    assert res["blur"] == pytest.approx(want, abs=1e-12)
    assert res["blur"] > blur_effect(img / 255.0, h_size=11, channel_axis=-1, reduce_func=np.mean) + 0.05
    H, W = 96, 128
    ref = textured_image(H, W, seed=25)
    y, x = np.mgrid[0:H, 0:W]
    mask = (((y - 40) / 25.0) ** 2 + ((x - 75) / 45.0) ** 2 <= 1) & (x > y + 10)   # no symmetry
    black = np.where(mask[..., None], ref, 0.0)
    white = np.where(mask[..., None], ref, 255.0)
    assert ev.blur(black, mask)["blur"] == pytest.approx(ev.blur(white, mask)["blur"], abs=1e-12)
    filled = np.where(mask[..., None], ref, ref[mask].mean(axis=0))
    mean_fill = ev.blur(black, mask, fill="mean")["blur"]
    assert mean_fill == pytest.approx(ev.blur(filled, mask, fill="none")["blur"], abs=1e-12)
    assert mean_fill != pytest.approx(ev.blur(black, mask, fill="none")["blur"], abs=1e-3)


def test_blur_erode_leaves_out_the_silhouette_band():
    """A sharp ring just inside the silhouette (a photo's object/background mix) reads as
    sharpness; the eroded mask leaves it out and scores the interior alone."""
    smooth = ndi.gaussian_filter(textured_image(seed=5), (3, 3, 0))
    mask = disk(*smooth.shape[:2], 70)
    inner = ndi.binary_erosion(mask, np.ones((5, 5), bool))
    ringed = smooth.copy()
    ring = mask & ~inner                                    # 2 px wide
    ringed[ring] = np.where(np.indices(mask.shape).sum(0)[ring, None] % 2, 20.0, 235.0)
    plain, with_ring = ev.blur(smooth, mask), ev.blur(ringed, mask)
    assert with_ring["blur"] < plain["blur"] - 0.05          # the band reads as sharp texture
    e_plain, e_ring = ev.blur(smooth, mask, erode_px=3), ev.blur(ringed, mask, erode_px=3)
    assert e_ring["blur"] == pytest.approx(e_plain["blur"], abs=1e-12)
    assert e_ring["erode_px"] == 3 and e_ring["n_pixels"] < inner.sum() and plain["erode_px"] == 0
    # the image border is not a silhouette: a mask filling the image is not eroded
    full = ev.blur(smooth, np.ones(mask.shape, bool), erode_px=3)
    assert full["n_pixels"] == mask.size and full["bbox"] == (0, mask.shape[0], 0, mask.shape[1])
    assert np.isnan(ev.blur(smooth, disk(*mask.shape, 2), erode_px=3)["blur"])   # nothing left
    with pytest.raises(ValueError, match="erode_px"):
        ev.blur(smooth, mask, erode_px=-1)
    with pytest.raises(ValueError, match="erode_px"):
        ev.blur(smooth, mask, erode_px=1.5)


def test_noise_sigma_recovers_gaussian_noise_and_ignores_shading():
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:200, 0:240].astype(np.float64)
    shading = 80 + 0.3 * xx + 0.2 * yy + 10 * np.sin(xx / 40)      # smooth: no fine-scale response
    clean = np.repeat(shading[..., None], 3, axis=-1)
    assert ev.noise_sigma(clean, flat_fraction=1.0)["sigma"] < 0.05
    noisy = clean + rng.normal(0, 3.0, clean.shape[:2])[..., None]  # the same noise in every channel
    assert ev.noise_sigma(noisy, flat_fraction=1.0)["sigma"] == pytest.approx(3.0, rel=0.05)
    # noise independent per channel is partly averaged out by the luma the blur metric sees
    independent = clean + rng.normal(0, 3.0, clean.shape)
    expected = 3.0 * np.sqrt(0.2125**2 + 0.7154**2 + 0.0721**2)
    assert ev.noise_sigma(independent, flat_fraction=1.0)["sigma"] == pytest.approx(expected, rel=0.05)
    # the flattest pixels of a picture with sharp edges (big squares): the edges are left out
    squares = np.repeat((60.0 + 120.0 * (((yy // 20) + (xx // 20)) % 2))[..., None], 3, axis=-1)
    assert ev.noise_sigma(squares, flat_fraction=1.0)["sigma"] > 0.3
    assert ev.noise_sigma(squares)["sigma"] < 0.01
    mask = np.zeros(clean.shape[:2], bool)
    assert np.isnan(ev.noise_sigma(noisy, mask)["sigma"]) and ev.noise_sigma(noisy, mask)["n_pixels"] == 0
    with pytest.raises(ValueError, match="flat_fraction"):
        ev.noise_sigma(noisy, flat_fraction=0.0)


# ------------------------------------------------------------------------------------ coverage

def test_coverage_helpers():
    has = np.array([[True, False, False, True], [True, True, True, True]])
    area = np.array([1.0, 1.0, 2.0, 4.0])
    np.testing.assert_allclose(ev.face_coverage(has, area), [5 / 8, 1.0])
    np.testing.assert_allclose(ev.face_coverage(has), [0.5, 1.0])
    labels = np.array([[0, -1, -1, 3], [1, 1, 2, 0]])
    np.testing.assert_allclose(ev.face_coverage(labels, area), [5 / 8, 1.0])
    np.testing.assert_allclose(ev.projection_coverage(has.astype(np.uint8) > 0, area), [5 / 8, 1.0])
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2.0]])
    F = np.array([[0, 1, 2], [0, 1, 3]])
    np.testing.assert_allclose(ev.face_areas(V, F), [0.5, 1.0])


def test_temporal_flicker():
    rng = np.random.default_rng(13)
    t0, t1 = rng.uniform(0, 255, (2, 20, 30, 3))
    mask = np.ones((20, 30), bool)
    same = ev.temporal_flicker(t0 + 5, t1 + 5, t0, t1, mask)  # offset, same change
    assert same["flicker"] == pytest.approx(0.0, abs=1e-12) and same["n_pixels"] == 600
    static = ev.temporal_flicker(t0, t0, t0, t1, mask)  # reconstruction frozen
    assert static["flicker"] > 10 and static["excess"] < 0
    noisy = ev.temporal_flicker(t0, t0 + rng.normal(0, 8, t0.shape), t0, t0, mask)
    assert noisy["flicker"] > 3 and noisy["excess"] == pytest.approx(noisy["flicker"])


def test_summarise():
    s = ev.summarise([1.0, 2.0, 6.0, np.nan])
    assert s == {"mean": 3.0, "median": 2.0, "min": 1.0, "max": 6.0, "n": 3, "n_total": 4}
    assert np.isnan(ev.summarise([])["mean"])


# ------------------------------------------------------------------------ novel view / regions

def uv_sphere(n_lat=24, n_lon=48, radius=0.5, center=(0.0, 0.0, 2.0)):
    """Lat-long sphere with a seam: u = longitude / 2pi, v = polar angle / pi (from the top, -y)."""
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon + 1)
    T, Ph = np.meshgrid(th, ph, indexing="ij")
    P = np.stack([np.sin(T) * np.cos(Ph), -np.cos(T), np.sin(T) * np.sin(Ph)], -1).reshape(-1, 3)
    V = P * radius + np.asarray(center)
    tc = np.stack([Ph / (2 * np.pi), T / np.pi], -1).reshape(-1, 2)
    idx = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    # orient counter-clockwise seen from outside
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = (n * (V[F].mean(1) - np.asarray(center))).sum(1) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    return V, F, tc


@pytest.fixture(scope="module")
def sphere_scene():
    V, F, tc = uv_sphere()
    W = 64
    tex = np.zeros((W, W, 3), np.uint8)
    tex[:, W // 2:] = (255, 0, 0)   # u in [0.5, 1): longitude pi..2pi, z < centre: faces the camera
    tex[:, : W // 2] = (0, 0, 255)  # the far side
    K = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    return V, F, tc, tex, K, 160, 120


def test_render_texture_and_novel_view_180(sphere_scene):
    V, F, tc, tex, K, w, h = sphere_scene
    img, mask = ev.render_texture(V, F, tc, F, tex, K, w, h)
    assert img.dtype == np.float32 and np.array_equal(img, np.rint(img)) and not img[~mask].any()
    assert tuple(img[60, 80]) == (255, 0, 0)
    T = ev.novel_view(V, 180.0)
    V2 = transform_points(T, V)
    assert np.allclose(V2.mean(0), V.mean(0))
    img2, mask2 = ev.render_texture(V2, F, tc, F, tex, K, w, h)
    assert tuple(img2[60, 80]) == (0, 0, 255)
    assert abs(int(mask2.sum()) - int(mask.sum())) < 0.02 * mask.sum()
    # +90 deg about +y brings the object's +x side (longitude 0, u = 0 -> the blue/red seam at
    # u = 0 == 1) to the front
    T90 = ev.novel_view(V, 90.0)
    x_side = V.mean(0) + np.array([0.5, 0, 0])
    assert np.allclose(transform_points(T90, x_side[None])[0], V.mean(0) + [0, 0, -0.5])
    np.testing.assert_allclose(ev.novel_view(V, 360.0), np.eye(4), atol=1e-12)


def test_seen_unseen_split(sphere_scene):
    V, F, tc, tex, K, w, h = sphere_scene
    vis = ev.input_view_visibility(V, F, K, w, h)
    assert 0.3 < vis.mean() < 0.5  # less than the front half of a sphere at finite distance
    seen0 = ev.seen_mask_in_view(V, F, vis, K, w, h)
    _, mask0 = ev.render_texture(V, F, tc, F, tex, K, w, h)
    assert (seen0 & ~mask0).sum() == 0
    assert seen0[mask0].mean() > 0.85  # the input view: partially visible rim faces are unseen
    V2 = transform_points(ev.novel_view(V, 180.0), V)
    seen = ev.seen_mask_in_view(V2, F, vis, K, w, h)
    truth, mask = ev.render_texture(V2, F, tc, F, tex, K, w, h)
    assert seen[mask].mean() < 0.02
    # a reconstruction right on the seen side and wrong on the unseen side
    recon = truth.copy()
    recon[mask & ~seen] = 128
    front = transform_points(ev.novel_view(V, 20.0), V)
    seen20 = ev.seen_mask_in_view(front, F, vis, K, w, h)
    truth20, mask20 = ev.render_texture(front, F, tc, F, tex, K, w, h)
    recon20 = truth20.copy()
    recon20[mask20 & ~seen20] = 128
    res = ev.region_psnr(truth20, recon20, mask20, seen20, ssim=True)
    assert res["psnr_seen"] == ev.PSNR_CAP and res["psnr_unseen"] < 10
    assert res["n_seen"] + res["n_unseen"] == res["n_all"] == mask20.sum()
    assert res["n_seen"] > 0 and res["n_unseen"] > 0
    assert res["ssim_seen"] > res["ssim_unseen"]
    # the three regions share one SSIM map: the same as each region scored on its own
    for name, sel in (("all", mask20), ("seen", mask20 & seen20), ("unseen", mask20 & ~seen20)):
        assert res[f"ssim_{name}"] == ev.masked_ssim(truth20, recon20, sel)["ssim"]
    res180 = ev.region_psnr(truth, recon, mask, seen)
    assert res180["n_unseen"] > 0.98 * mask.sum()


def test_inputs_of_another_convention_are_refused_not_scored():
    """Conventions a caller easily gets wrong gave plausible numbers: a float image in [0, 1]
    scored against 0..255 (70.6 dB instead of 22.5), RGBA (alpha counted as a perfect channel),
    0/1 integer flags read as frame labels (100 % coverage), a NaN centroid (a NaN view)."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (40, 40, 3)).astype(np.uint8)
    noisy = np.clip(rgb + rng.normal(0, 20, rgb.shape), 0, 255)
    m = np.ones((40, 40), bool)
    want = ev.masked_psnr(rgb, noisy, m)["psnr"]
    assert ev.masked_psnr(rgb / 255, noisy / 255, m, data_range=1.0)["psnr"] == pytest.approx(want)
    for f in (lambda: ev.masked_psnr(rgb / 255, noisy / 255, m), lambda: ev.masked_psnr(rgb, noisy / 255, m),
              lambda: ev.masked_ssim(rgb / 255, noisy / 255, m),
              lambda: ev.patch_shift_psnr(rgb / 255, noisy / 255, m, patch=8, radius=1),
              lambda: ev.noise_sigma(rgb / 255, m)):
        with pytest.raises(ValueError, match=r"float image in \[0, 1\]"):
            f()
    assert ev.masked_psnr(np.zeros((40, 40, 3)), noisy, m)["psnr"] < 10   # black stays scoreable
    rgba = np.dstack([rgb, np.full((40, 40), 255, np.uint8)])
    for f in (lambda: ev.masked_psnr(rgba, rgba, m), lambda: ev.blur(rgba, m), lambda: ev.noise_sigma(rgba, m),
              lambda: ev.patch_shift_psnr(rgba, rgba, m, patch=8, radius=1)):
        with pytest.raises(ValueError, match="1 or 3 channels.*alpha"):
            f()
    with pytest.raises(ValueError, match="bool flags"):
        ev.face_coverage(np.array([[1, 0, 0, 0]], np.uint8))
    assert ev.face_coverage(np.array([[1, 0, 0, 0]], bool)) == pytest.approx(0.25)
    assert ev.face_coverage(np.array([[3, -1, 0, -1]])) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="not finite"):
        ev.novel_view(np.array([[0, 0, 1], [np.nan, 0, 1.0]]), 30)
    with pytest.raises(ValueError, match=r"faces index out of range: face 0 is \[0, 1, -1\]"):
        ev.face_areas(np.eye(3), [[0, 1, -1]])
    tri = np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="texture times 255"):
        ev.render_texture(np.array([[0, 0, 1.0], [0.1, 0, 1], [0, 0.1, 1]]), tri, np.eye(3)[:, :2], tri,
                          rng.random((8, 8, 3)), np.array([[100, 0, 20], [0, 100, 20], [0, 0, 1.0]]), 40, 40)


def test_blur_of_a_crop_under_four_pixels_is_nan():
    """A mask whose bounding box is under 4 px on a side (a sliver of an object) has no blur
    score: NaN, as an empty mask, and without the divide-by-zero warnings skimage's blur_effect
    prints for such a crop (one per frame of a run would bury the log); from 4 px on it is
    scored."""
    import warnings

    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (20, 20, 3)).astype(np.uint8)
    for side, scored in ((1, False), (3, False), (4, True)):
        m = np.zeros((20, 20), bool)
        m[5:5 + side, 2:18] = True
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got = ev.blur(img, m)
        assert np.isfinite(got["blur"]) == scored, (side, got)
        assert got["bbox"] == (5, 5 + side, 2, 18)
