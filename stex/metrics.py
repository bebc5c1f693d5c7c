"""Evaluation metrics: the paper's scores and the ground-truth scores a synthetic scene allows.

Every function here is pure (numpy in, numbers / dicts out); the workflow decides which images
go in. Definitions, defaults and the reasons for them are in ``docs/metrics.md``.

Conventions
-----------
- Images are (H, W, C) colour or (H, W) grey arrays, uint8 or float, in **grey levels**: values
  on the 0..``data_range`` scale (``data_range=255`` for 8-bit images and for the float images
  :func:`render_texture` returns). Computation is in float64.
- ``mask`` is an (H, W) bool array selecting the pixels that are scored (the object). Pixels
  outside it never contribute, except where a metric says so (the shift search of
  :func:`patch_shift_psnr` reads ``test`` up to ``radius`` px outside the mask; SSIM windows
  straddle the mask boundary).
- PSNR is ``10 log10(data_range^2 / MSE)`` in dB, **capped at** :data:`PSNR_CAP` (100 dB), which
  is also the value for MSE = 0 (identical images), so averages stay finite.
- A score over an empty selection is NaN (never an exception), with its pixel/patch count 0.
- Cameras, meshes and texcoords follow :mod:`stex.render` (OpenCV pinhole, metres; texcoords
  u right, v down).

Metrics
-------
- :func:`patch_shift_psnr` — the paper's misalignment-tolerant PSNR (Sec. 6.3 "Reconstruction
  error"): P x P grid patches inside the mask, each ``test`` patch translated within +-r px to its
  lowest masked MSE against ``reference``.
- :func:`masked_psnr`, :func:`masked_ssim` — plain PSNR / SSIM (Wang et al. 2004) inside a mask.
- :func:`blur` — Crete et al. 2007 no-reference blur (``skimage.measure.blur_effect``) on the
  mask's bounding-box crop, outside-mask pixels filled from the nearest object pixel.
- :func:`noise_sigma` — fine-scale noise of an image (Immerkær 1996 on its flattest pixels), to
  compare a synthetic sensor model with real frames: noise reads as sharpness in :func:`blur`.
- :func:`face_coverage`, :func:`projection_coverage`, :func:`face_areas` — surface fraction
  with texture per frame.
- :func:`render_texture`, :func:`novel_view`, :func:`input_view_visibility`,
  :func:`seen_mask_in_view`, :func:`region_psnr` — ground-truth scores from novel views, split
  into surface seen / unseen by the input camera at that frame. :func:`mesh_view`,
  :func:`view_texture` and :func:`view_seen` do what :func:`render_texture` and
  :func:`seen_mask_in_view` do from one rasterisation, for several textures on one mesh.
- :func:`temporal_flicker` — frame-to-frame change minus the true change.
- :func:`summarise` — mean / median / min / max / n of a list of per-frame scores.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from scipy import ndimage as ndi

from stex.ssim import SSIM_RADIUS, SsimCache, ssim_map
from stex.render import check_faces, check_vertices, face_visibility, rasterize, sample_texture, textured_raster

__all__ = [
    "PSNR_CAP",
    "DEFAULT_PATCH",
    "DEFAULT_RADIUS",
    "DEFAULT_H_SIZE",
    "DEFAULT_BLUR_INTERIOR_PX",
    "psnr_from_mse",
    "patch_shift_psnr",
    "masked_psnr",
    "masked_ssim",
    "blur",
    "noise_sigma",
    "face_areas",
    "face_coverage",
    "projection_coverage",
    "render_texture",
    "MeshView",
    "mesh_view",
    "view_texture",
    "view_seen",
    "novel_view",
    "input_view_visibility",
    "seen_mask_in_view",
    "region_psnr",
    "temporal_flicker",
    "summarise",
]

#: PSNR ceiling in dB; also the value reported for MSE = 0.
PSNR_CAP = 100.0
#: Default patch side P (px) of :func:`patch_shift_psnr`.
DEFAULT_PATCH = 32
#: Default shift search radius r (px) of :func:`patch_shift_psnr`.
DEFAULT_RADIUS = 4
#: Default re-blur filter size of :func:`blur` (skimage's default; Crete et al. use 9).
DEFAULT_H_SIZE = 11
#: Silhouette band (px) left out of the "interior" blur scores: a photo's pixels there mix the
#: object with the background over about the motion blur's extent, rounded up
#: (docs/decisions/metrics.md).
DEFAULT_BLUR_INTERIOR_PX = 3

# SSIM as Wang et al. 2004: 11-tap Gaussian window, sigma 1.5, population covariance.
_SSIM_PAD = SSIM_RADIUS  # the SSIM window's radius (px): masked scores keep this much around the mask


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------

def _image(x, name) -> np.ndarray:
    """(H, W) or (H, W, C) numeric -> (H, W, C) float64."""
    a = np.asarray(x)
    if a.ndim not in (2, 3) or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise ValueError(f"{name} must be an (H, W) or (H, W, C) numeric image, got shape {a.shape}"
                         f" dtype {a.dtype}")
    if a.ndim == 3 and a.shape[2] not in (1, 3):
        raise ValueError(f"{name} must have 1 or 3 channels (grey or RGB), got shape {a.shape}"
                         f"{'; drop the alpha channel: image[..., :3]' if a.shape[2] == 4 else ''}")
    finite = not np.issubdtype(a.dtype, np.floating)  # integers and bools cannot be NaN
    a = a.astype(np.float64, copy=False)
    if not finite and not np.isfinite(a).all():
        raise ValueError(f"{name} contains non-finite values ({int((~np.isfinite(a)).sum())} of {a.size})")
    return a[..., None] if a.ndim == 2 else a


def _check_scale(x, name, data_range, fix="pass data_range=1.0, or the image times 255") -> None:
    """Refuse a float image in [0, 1] scored with a ``data_range`` of grey levels: it would score
    some 48 dB too high (or, beside a uint8 image, absurdly low) without any error. Grey-level
    images never lie entirely below 1 with fractional values."""
    a = np.asarray(x)
    if float(data_range) <= 1.0 or not np.issubdtype(a.dtype, np.floating) or not a.size:
        return
    if a.max() <= 1.0 and a.min() >= 0.0 and bool(np.any(a != np.rint(a))):  # NaN: _image's error
        raise ValueError(f"{name} is a float image in [0, 1], but grey levels 0..{data_range:g} are "
                         f"expected: {fix}")


def _pair(reference, test, data_range=255.0):
    _check_scale(reference, "reference", data_range)
    _check_scale(test, "test", data_range)
    ref = _image(reference, "reference")
    tst = _image(test, "test")
    if ref.shape != tst.shape:
        raise ValueError(f"reference and test images differ in shape: {ref.shape} vs {tst.shape}")
    return ref, tst


def _same_shape(reference, test) -> tuple[int, int]:
    """(H, W) of two images :func:`_pair` would accept, checked without converting them."""
    a, b = np.asarray(reference), np.asarray(test)
    for x, name in ((a, "reference"), (b, "test")):
        if x.ndim not in (2, 3) or (x.ndim == 3 and x.shape[2] not in (1, 3)):
            _image(x, name)  # raises its error (before converting anything)
    sa = a.shape if a.ndim == 3 else a.shape + (1,)
    sb = b.shape if b.ndim == 3 else b.shape + (1,)
    if sa != sb:
        raise ValueError(f"reference and test images differ in shape: {sa} vs {sb}")
    return a.shape[0], a.shape[1]


def _mask(mask, shape, name="mask") -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)} (the image's H, W), got {m.shape}")
    return m.astype(bool, copy=False)


def _bbox(m: np.ndarray):
    """(r0, r1, c0, c1), half-open, of the True pixels of a non-empty 2-D mask."""
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _crop(mask, images, margin: int):
    """``images`` (each (H, W[, C]); None passes through) and ``mask`` ((H, W) bool) cut to the
    mask's bounding box plus ``margin`` px (clamped to the image), so that masked scores convert
    and check only the pixels they read; an empty mask or None leaves everything whole."""
    if mask is None:
        return mask, images
    m = np.asarray(mask)
    if m.ndim != 2 or not m.any() or any(np.shape(x)[:2] != m.shape for x in images if x is not None):
        return mask, images          # the callers' own checks report shapes; empty stays empty
    r0, r1, c0, c1 = _bbox(m)
    r0, c0 = max(0, r0 - margin), max(0, c0 - margin)
    r1, c1 = min(m.shape[0], r1 + margin), min(m.shape[1], c1 + margin)
    return m[r0:r1, c0:c1], [None if x is None else np.asarray(x)[r0:r1, c0:c1] for x in images]


def psnr_from_mse(mse, data_range=255.0, cap=PSNR_CAP):
    """PSNR in dB, ``min(cap, 10 log10(data_range^2 / mse))``; ``cap`` where mse <= 0; NaN stays NaN.

    Accepts a scalar (returns float) or an array (returns float64 array of the same shape).
    """
    mse_a = np.asarray(mse, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = 10.0 * np.log10(float(data_range) ** 2 / mse_a)
    p = np.where(mse_a <= 0, cap, np.minimum(p, cap))
    p = np.where(np.isnan(mse_a), np.nan, p)
    return float(p) if p.ndim == 0 else p


# --------------------------------------------------------------------------------------------
# patch-shift PSNR
# --------------------------------------------------------------------------------------------

def _shift_order(radius):
    """All integer shifts within +-radius, nearest first (ties -> the smaller shift wins)."""
    s = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    return sorted(s, key=lambda d: (d[0] ** 2 + d[1] ** 2, d[0], d[1]))


@njit(cache=True, nogil=True)
def _patch_shift_kernel(refg, mg, tp, oy, ox, P, r, shifts, best, best_k, sse0):
    """Per patch n (grid origin (oy[n], ox[n])): the minimum masked SSE over ``shifts``.

    refg (Hg, Wg, C) / mg (Hg, Wg): reference and mask on the grid (grid (0, 0) = image
    (r0, c0)); tp: test from image (r0 - r, c0 - r) on, edge-padded past the image, so that
    grid (y, x) shifted by (dy, dx) reads tp[y + dy + r, x + dx + r]. Shifts are tried in
    order; a shift replaces the best only if strictly smaller, and stops accumulating once it
    exceeds the best (same result).
    """
    C = refg.shape[2]
    for n in range(oy.shape[0]):
        gy0, gx0 = oy[n], ox[n]
        b = np.inf
        bk = 0
        for k in range(shifts.shape[0]):
            ty0 = gy0 + shifts[k, 0] + r
            tx0 = gx0 + shifts[k, 1] + r
            sse = 0.0
            for i in range(P):
                for j in range(P):
                    if mg[gy0 + i, gx0 + j]:
                        for c in range(C):
                            d = refg[gy0 + i, gx0 + j, c] - tp[ty0 + i, tx0 + j, c]
                            sse += d * d
                if k > 0 and sse >= b:
                    break
            if k == 0:
                sse0[n] = sse
            if sse < b:
                b = sse
                bk = k
        best[n] = b
        best_k[n] = bk


def patch_shift_psnr(reference, test, mask, patch=DEFAULT_PATCH, radius=DEFAULT_RADIUS,
                     data_range=255.0, min_fraction=0.5) -> dict:
    """Misalignment-tolerant PSNR (Kim et al. 2021, Sec. 6.3): grid patches shifted to their best fit.

    Definition:

    1. The grid: P x P patches tiling the bounding box of ``mask``, anchored at its top-left
       pixel (patches may run past the image's right/bottom edge; pixels there count as outside
       the mask). A patch **counts** if at least ``min_fraction`` (default 50 %) of its P^2
       pixels are in the mask; patches with less are dropped entirely, so ragged silhouette
       slivers, whose few pixels would let the shift search fit anything, are not scored.
    2. Per counted patch p with masked pixel set M_p (|M_p| = n_p), for every integer shift
       (dy, dx) with |dy|, |dx| <= r::

           SSE_p(dy, dx) = sum_{(y, x) in M_p} sum_c (ref[y, x, c] - test[y + dy, x + dx, c])^2

       ``test`` is read at the shifted position (edge-replicated outside the image); the mask is
       the reference's, so n_p does not depend on the shift. The patch keeps its minimum,
       SSE*_p (ties -> the smallest shift, so identical images pick (0, 0)).
    3. Headline: ``psnr = PSNR(MSE)`` with ``MSE = sum_p SSE*_p / (C * sum_p n_p)``, the pooled
       MSE of the shift-corrected image (pixel-weighted mean of the per-patch minimum MSEs).
       With r = 0 and every masked pixel in a counted patch it equals :func:`masked_psnr`.
       ``psnr_patch_mean`` (the mean of per-patch PSNRs) is also returned but is not the
       headline: the log is taken per patch, so flat, near-perfect patches (PSNR up to the
       100 dB cap) dominate it and it is biased upwards (Jensen), while the pooled form is the
       usual PSNR definition and comparable with plain PSNR.

    Defaults (the paper states neither): P = 32, r = 4. r must cover the residual misalignment
    between render and photo (tracking / calibration error of a few mm: 4 px ~ 7 mm at 1 m with
    fx = 560, the demo camera); P ~ 8 r keeps the shift a local correction: a 32 x 32 x 3 patch has
    enough structure that a wrong texture cannot be shifted into agreement, and a shift search
    over 81 candidates raises the PSNR of pure noise on flat patches only slightly
    (docs/decisions/metrics.md).
    For much larger images scale both with the focal length (e.g. P = 64, r = 8 at 3072p).

    Speed: a serial numba kernel (``nogil``) over patches and shifts that stops summing a shift
    once it exceeds the patch's best so far (same result; timings in docs/decisions/metrics.md).

    Args:
        reference: (H, W, C) or (H, W) uint8/float image, grey levels (the input photo).
        test: same shape, the render of the reconstructed texture (the image that is shifted).
        mask: (H, W) bool, the scored pixels of ``reference`` (object mask). ``reference``
            outside the mask is never read; ``test`` is read up to ``radius`` px outside it.
        patch: P, patch side in px (>= 1). radius: r, max shift in px per axis (>= 0).
        data_range: peak value for PSNR (255 for 8-bit grey levels).
        min_fraction: fraction of a patch's P^2 pixels that must be in the mask for it to count.

    Returns:
        dict with ``psnr`` (dB, headline), ``mse`` (grey levels^2), ``psnr_patch_mean`` (dB),
        ``psnr_unshifted`` (dB, the same patches without shifting), ``n_patches``, ``n_pixels``
        (masked pixels in counted patches), ``mask_pixels`` (all masked pixels),
        ``mean_shift_px`` (mean Euclidean length of the chosen shifts), ``frac_shift_at_radius``
        (fraction of patches whose best shift lies on the search border: if large, r is too
        small), and the parameters ``patch``, ``radius``, ``data_range``, ``min_fraction``.
        Scores are NaN when no patch counts.
    """
    H, W = _same_shape(reference, test)
    m = _mask(mask, (H, W))
    P, r = int(patch), int(radius)
    if P < 1 or r < 0:
        raise ValueError(f"patch must be >= 1 and radius >= 0, got patch={patch} radius={radius}")
    if not 0.0 < float(min_fraction) <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")
    out = {"patch": P, "radius": r, "data_range": float(data_range),
           "min_fraction": float(min_fraction), "mask_pixels": int(m.sum())}
    nan_result = dict(out, psnr=np.nan, mse=np.nan, psnr_patch_mean=np.nan, psnr_unshifted=np.nan,
                      n_patches=0, n_pixels=0, mean_shift_px=np.nan, frac_shift_at_radius=np.nan)
    if not m.any():
        return nan_result

    # grid over the mask's bounding box, padded to whole patches
    r0, r1, c0, c1 = _bbox(m)
    ny, nx = -(-(r1 - r0) // P), -(-(c1 - c0) // P)
    Hg, Wg = ny * P, nx * P
    hh, ww = min(Hg, H - r0), min(Wg, W - c0)
    mg = np.zeros((Hg, Wg), dtype=bool)
    mg[:hh, :ww] = m[r0:r0 + hh, c0:c0 + ww]
    counts = mg.reshape(ny, P, nx, P).sum(axis=(1, 3))
    keep = (counts >= float(min_fraction) * P * P) & (counts > 0)
    py, px = np.nonzero(keep)
    N = py.size
    if N == 0:
        return nan_result
    ref = np.asarray(reference)[r0:r0 + hh, c0:c0 + ww]
    _check_scale(ref, "reference", data_range)
    ref = _image(ref, "reference")
    C = ref.shape[2]
    refg = np.zeros((Hg, Wg, C))
    refg[:hh, :ww] = ref
    n_p = counts[py, px].astype(np.float64)

    # the part of test the search reads, rows r0 - r .. r0 + Hg + r (columns alike), edge-padded
    # where that runs past the image: test[y, x] = tp[y - r0 + r, x - c0 + r]
    y0, y1, x0, x1 = r0 - r, r0 + Hg + r, c0 - r, c0 + Wg + r
    tst = np.asarray(test)[max(0, y0):min(H, y1), max(0, x0):min(W, x1)]
    _check_scale(tst, "test", data_range)
    tst = _image(tst, "test")
    pads = ((max(0, -y0), max(0, y1 - H)), (max(0, -x0), max(0, x1 - W)), (0, 0))
    tp = np.ascontiguousarray(np.pad(tst, pads, mode="edge") if any(map(any, pads)) else tst)
    shifts = np.asarray(_shift_order(r), dtype=np.int64)  # (0, 0) first
    best = np.empty(N)
    best_k = np.empty(N, dtype=np.int64)
    sse0 = np.empty(N)
    _patch_shift_kernel(np.ascontiguousarray(refg), mg, tp, (py * P).astype(np.int64),
                        (px * P).astype(np.int64), P, r, shifts, best, best_k, sse0)

    denom = C * n_p
    mse = float(best.sum() / denom.sum())
    sh = np.asarray(shifts, dtype=np.float64)[best_k]
    return dict(
        out,
        psnr=psnr_from_mse(mse, data_range),
        mse=mse,
        psnr_patch_mean=float(np.mean(psnr_from_mse(best / denom, data_range))),
        psnr_unshifted=psnr_from_mse(float(sse0.sum() / denom.sum()), data_range),
        n_patches=int(N),
        n_pixels=int(n_p.sum()),
        mean_shift_px=float(np.hypot(sh[:, 0], sh[:, 1]).mean()),
        frac_shift_at_radius=float(np.mean(np.abs(sh).max(axis=1) == r)) if r > 0 else 0.0,
    )


# --------------------------------------------------------------------------------------------
# plain PSNR / SSIM
# --------------------------------------------------------------------------------------------

def masked_psnr(reference, test, mask=None, data_range=255.0) -> dict:
    """PSNR over the masked pixels: ``MSE = mean over masked pixels and channels of (ref - test)^2``.

    Args:
        reference, test: (H, W, C) or (H, W) uint8/float images, grey levels.
        mask: (H, W) bool or None (= every pixel).
        data_range: peak value (255 for 8-bit grey levels).

    Returns:
        dict ``psnr`` (dB, capped at 100), ``mse`` (grey levels^2), ``n_pixels``.
    """
    mask, (reference, test) = _crop(mask, [reference, test], 0)
    ref, tst = _pair(reference, test, data_range)
    m = _mask(mask, ref.shape[:2])
    n = int(m.sum())
    if n == 0:
        return {"psnr": np.nan, "mse": np.nan, "n_pixels": 0}
    d = ref[m] - tst[m]
    mse = float(np.mean(d * d))
    return {"psnr": psnr_from_mse(mse, data_range), "mse": mse, "n_pixels": n}


def masked_ssim(reference, test, mask=None, data_range=255.0, cache: SsimCache | None = None) -> dict:
    """Mean SSIM (Wang et al. 2004) over the masked pixels.

    The SSIM map is ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=data_range, channel_axis=-1, full=True)``
    (11 x 11 Gaussian window; computed bit for bit by :func:`stex.ssim.ssim_map`), averaged over channels and then over the masked pixels. Windows
    straddle the mask boundary (background inside a window near the silhouette does enter).
    Pixels within the window radius (5 px) of the **image** border are left out, as skimage's own
    mean does, so with an all-True mask the result equals skimage's MSSIM. For speed the map is
    computed on the mask's bounding box plus a margin larger than the window, which gives the
    same values as the full-image map at every scored pixel.

    Args:
        reference, test: (H, W, C) or (H, W) uint8/float images, grey levels; at least 11 x 11.
        mask: (H, W) bool or None (= every pixel).
        data_range: value range of the images (255 for 8-bit grey levels).
        cache: a :class:`stex.ssim.SsimCache` kept while other tests are compared with this reference in
            this mask (the same result, sooner), or None.

    Returns:
        dict ``ssim`` (dimensionless, <= 1), ``n_pixels`` (pixels averaged).
    """
    # the box plus twice the window keeps every scored pixel's window inside the crop, and the
    # image border where the box reaches it (as region_psnr)
    mask, (reference, test) = _crop(mask, [reference, test], 2 * _SSIM_PAD + 2)
    ref, tst = _pair(reference, test, data_range)
    return _ssim_means(ref, tst, [_mask(mask, ref.shape[:2])], data_range, cache)[0]


def _ssim_means(ref, tst, masks, data_range, cache: SsimCache | None = None) -> list[dict]:
    """:func:`masked_ssim` of (H, W, C) float64 images over each of ``masks`` ((H, W) bool), from
    one SSIM map computed on the bounding box of their union (plus the margin); ``cache``: a
    :class:`stex.ssim.SsimCache` shared by the calls with the same reference, or None."""
    H, W, C = ref.shape
    pad = _SSIM_PAD
    trimmed = []
    for mask in masks:
        m = mask.copy()
        m[:pad] = m[H - pad:] = False
        m[:, :pad] = m[:, W - pad:] = False
        trimmed.append(m)
    union = np.logical_or.reduce(trimmed)
    if not union.any():
        return [{"ssim": np.nan, "n_pixels": 0} for _ in masks]
    r0, r1, c0, c1 = _bbox(union)
    margin = pad + 2
    r0, c0 = max(0, r0 - margin), max(0, c0 - margin)
    r1, c1 = min(H, r1 + margin), min(W, c1 + margin)
    S = ssim_map(ref[r0:r1, c0:c1], tst[r0:r1, c0:c1], data_range, cache)
    out = []
    for m in trimmed:
        mc = m[r0:r1, c0:c1]
        n = int(mc.sum())
        out.append({"ssim": float(S[mc].mean()) if n else np.nan, "n_pixels": n})
    return out


# --------------------------------------------------------------------------------------------
# blur
# --------------------------------------------------------------------------------------------

def _blur_region(m, erode_px, fill):
    """What :func:`blur` takes from the mask alone: the mask eroded by ``erode_px``, its pixel
    count, its bounding box (None when empty) and, for ``fill="nearest"`` on a box the mask does
    not fill, the nearest mask pixel of every box pixel ((2, h, w) indices into the box)."""
    if erode_px > 0 and m.any():
        # the image's own border is not a silhouette: cv2 erodes only from mask edges
        m = cv2.erode(m.astype(np.uint8), np.ones((2 * int(erode_px) + 1,) * 2, np.uint8)) > 0
    if not m.any():
        return m, 0, None, None
    r0, r1, c0, c1 = _bbox(m)
    mc = m[r0:r1, c0:c1]
    idx = None
    if fill == "nearest" and not mc.all() and min(mc.shape) >= 4:
        idx = ndi.distance_transform_edt(~mc, return_distances=False, return_indices=True)
    return m, int(m.sum()), (r0, r1, c0, c1), idx


def blur(image, mask=None, h_size=DEFAULT_H_SIZE, fill="nearest", data_range=255.0, erode_px=0,
         cache: dict | None = None) -> dict:
    """Crete et al. 2007 no-reference blur of the object: 0 = sharp ... 1 = blurry.

    ``skimage.measure.blur_effect(crop, h_size, channel_axis=-1 (RGB -> grey), reduce_func=max)``
    on the crop of ``image`` to the bounding box of ``mask`` (eroded by ``erode_px`` first, if
    given), where the crop's pixels outside the mask are replaced first:

    - ``fill="nearest"`` (default): each gets the colour of the nearest mask pixel (Euclidean
      distance transform). This extends the object outwards without creating any edge at the
      silhouette: the measure then responds to the texture, not to the contrast between the
      object and whatever surrounds it (background in a photo, black in a render, which would
      otherwise add a perfectly sharp, method-dependent edge).
    - ``fill="mean"``: the masked mean colour (flat, but with a step at the silhouette).
    - ``fill="none"``: the crop as is.

    Compare only numbers produced by this function with the same ``h_size`` and the same kind of
    mask (skimage's Sobel-based version does not reproduce the paper's absolute values).

    Args:
        image: (H, W, 3) or (H, W) uint8/float image, grey levels.
        mask: (H, W) bool or None (= whole image).
        h_size: length of the re-blurring box filter (px), reported in the result.
        fill: "nearest", "mean" or "none".
        data_range: value range (the image is divided by it; the metric is scale-invariant).
        erode_px: the mask is first eroded by this many pixels (a (2e+1)-px square), so that a
            band along the silhouette, where a photo's pixels mix the object with the background
            (motion blur, defocus, the mask's own error), is left out; 0 = the mask as given.
        cache: a dict kept while several images are scored in the same mask: the erosion and the
            nearest-pixel fill's indices, which depend on the mask alone, are found once (keyed
            by the mask's bits); None computes them.

    Returns:
        dict ``blur`` (dimensionless in [0, 1]; NaN when the mask is empty or its bounding box
        is under 4 px on a side, where skimage's blur_effect gives NaN with divide warnings),
        ``h_size``, ``fill``, ``erode_px``, ``bbox`` (r0, r1, c0, c1) half-open, ``n_pixels``
        (masked pixels after the erosion).
    """
    from skimage.measure import blur_effect  # skimage loads slowly; only the blur score needs it

    raw = np.asarray(image)
    if raw.ndim not in (2, 3) or (raw.ndim == 3 and raw.shape[2] not in (1, 3)):
        _image(raw, "image")  # raises its error (before converting anything)
    H, W = raw.shape[:2]
    m = _mask(mask, (H, W))
    if fill not in ("nearest", "mean", "none"):
        raise ValueError(f"fill must be 'nearest', 'mean' or 'none', got {fill!r}")
    if int(erode_px) != erode_px or erode_px < 0:
        raise ValueError(f"erode_px must be a whole number of pixels >= 0, got {erode_px!r}")
    key = None if cache is None else (m.shape, int(erode_px), fill, np.packbits(m).tobytes())
    m, n_pixels, box, idx = cache[key] if key in (cache or {}) else _blur_region(m, erode_px, fill)
    if cache is not None:
        cache[key] = (m, n_pixels, box, idx)
    res = {"h_size": int(h_size), "fill": fill, "erode_px": int(erode_px), "n_pixels": n_pixels}
    if box is None:
        return dict(res, blur=np.nan, bbox=None)
    r0, r1, c0, c1 = box
    crop = _image(raw[r0:r1, c0:c1], "image") / float(data_range)  # a new array: filled below
    C = crop.shape[2]
    mc = m[r0:r1, c0:c1]
    if min(crop.shape[:2]) < 4:
        return dict(res, blur=np.nan, bbox=(r0, r1, c0, c1))
    if not mc.all():
        if fill == "nearest":
            crop = crop[idx[0], idx[1]]
        elif fill == "mean":
            crop[~mc] = crop[mc].mean(axis=0)
    if C == 3:
        b = blur_effect(crop, h_size=int(h_size), channel_axis=-1, reduce_func=np.max)
    else:
        b = blur_effect(crop.mean(axis=-1), h_size=int(h_size), reduce_func=np.max)
    return dict(res, blur=float(b), bbox=(r0, r1, c0, c1))


def noise_sigma(image, mask=None, flat_fraction=0.3) -> dict:
    """Fine-scale noise of an image: Immerkær's (1996) estimator on its flattest pixels.

    The grey image the blur metric sees (:func:`skimage.color.rgb2gray` luma weights 0.2125,
    0.7154, 0.0721: a real camera's noise is correlated across channels by demosaicing and chroma
    subsampling, a synthetic one's is not, and the channel mean would compare them unfairly) is
    filtered with the 3x3 kernel ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` (the difference of
    two Laplacians, blind to constant, linear and most smooth shading); σ = sqrt(π/2) ·
    mean|response| / 6 is the standard deviation of i.i.d. Gaussian noise that would give that
    response. Texture edges respond too, so only the ``flat_fraction`` of the selected pixels
    with the smallest Sobel gradient count (its readings on renders and real frames:
    docs/decisions/metrics.md). It compares images of like content and resolution (a synthetic
    sensor model against real frames); it is not an absolute noise level.

    Args:
        image: (H, W, 3) or (H, W) uint8/float image, grey levels.
        mask: (H, W) bool or None (= whole image); a 2-px border is always left out.
        flat_fraction: share of the selected pixels kept, lowest gradient first, in (0, 1].

    Returns:
        dict ``sigma`` (grey levels; NaN when nothing is selected), ``n_pixels`` (pixels used).
    """
    from skimage.color import rgb2gray  # skimage loads slowly; only the noise estimate needs it

    _check_scale(image, "image", 255.0, fix="give the image times 255")
    img = _image(image, "image")
    H, W = img.shape[:2]
    m = _mask(mask, (H, W)).copy()
    if not 0 < flat_fraction <= 1:
        raise ValueError(f"flat_fraction must be in (0, 1], got {flat_fraction}")
    m[:2], m[-2:], m[:, :2], m[:, -2:] = False, False, False, False
    if not m.any():
        return {"sigma": np.nan, "n_pixels": 0}
    # only the mask's bounding box (+ the filters' 1-px reach, inside the image) is filtered
    r0, r1, c0, c1 = _bbox(m)
    r0, r1, c0, c1 = r0 - 1, r1 + 1, c0 - 1, c1 + 1
    img, m = img[r0:r1, c0:c1], m[r0:r1, c0:c1]
    grey = rgb2gray(img) if img.shape[2] == 3 else img.mean(axis=-1)
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)
    response = np.abs(cv2.filter2D(grey, cv2.CV_64F, kernel))[m]
    gradient = np.hypot(cv2.Sobel(grey, cv2.CV_64F, 1, 0), cv2.Sobel(grey, cv2.CV_64F, 0, 1))[m]
    keep = gradient <= np.quantile(gradient, flat_fraction)
    return {"sigma": float(np.sqrt(np.pi / 2) * response[keep].mean() / 6), "n_pixels": int(keep.sum())}


# --------------------------------------------------------------------------------------------
# coverage
# --------------------------------------------------------------------------------------------

def face_areas(vertices, faces) -> np.ndarray:
    """(F,) float64 triangle areas (m^2 for metre vertices) of (V, 3) vertices and (F, 3) faces."""
    V = check_vertices(vertices)
    F = check_faces(faces, len(V))
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def face_coverage(face_has_texture, face_area=None) -> np.ndarray:
    """Fraction of the surface that has texture, per frame.

    Args:
        face_has_texture: (T, F) or (F,) bool (True = the face has texture at that frame), or
            signed integer frame labels (T, F) where ``label >= 0`` means textured (-1 = never
            seen); 0/1 flags must be bool (as integers they are labels, all textured).
        face_area: (F,) face areas (any unit) -> area fraction; None -> fraction of faces (the
            paper's "29.5-39.6 % of the mesh faces" counts faces).

    Returns:
        (T,) float64 fractions in [0, 1] (a scalar array of shape () for (F,) input).
    """
    a = np.asarray(face_has_texture)
    if np.issubdtype(a.dtype, np.unsignedinteger):
        # labels need -1; 0/1 flags read as labels would all count as textured
        raise ValueError(f"face_has_texture is {a.dtype}: give bool flags, or signed frame labels "
                         f"(-1 = no texture)")
    if not (a.dtype == bool or np.issubdtype(a.dtype, np.signedinteger)):
        raise ValueError(f"face_has_texture must be bool flags or signed integer frame labels, got {a.dtype}")
    has = a >= 0 if a.dtype != bool else a
    if face_area is None:
        return has.mean(axis=-1)
    w = np.asarray(face_area, dtype=np.float64)
    if w.shape != has.shape[-1:]:
        raise ValueError(f"face_area must have shape ({has.shape[-1]},), got {w.shape}")
    return (has * w).sum(axis=-1) / w.sum()


def projection_coverage(visible, face_area=None) -> np.ndarray:
    """Coverage of the naive single-frame projection baseline: a face has texture at frame t only
    if camera t sees it. ``visible``: (T, F) bool (e.g. the projection stage's visibility);
    ``face_area`` as in :func:`face_coverage`. Returns (T,) fractions."""
    return face_coverage(np.asarray(visible, dtype=bool), face_area)


# --------------------------------------------------------------------------------------------
# ground truth: renders, novel views, seen / unseen regions
# --------------------------------------------------------------------------------------------

class MeshView(NamedTuple):
    """A mesh rasterised in one camera, ready to show any texture of its atlas
    (:func:`view_texture`) and any per-face flag (:func:`view_seen`)."""

    face_id: np.ndarray  #: (H, W) int32 nearest face at each pixel centre, -1 = empty
    mask: np.ndarray     #: (H, W) bool, face_id >= 0
    uv: np.ndarray       #: (N, 2) float64 texcoords of the mask's pixels, row-major


def mesh_view(vertices, faces, texcoords, texcoord_faces, K, width, height) -> MeshView:
    """Rasterise a mesh once for :func:`view_texture` / :func:`view_seen` (arguments as
    :func:`render_texture`)."""
    raster, mask, uv = textured_raster(vertices, faces, texcoords, texcoord_faces, K, width, height)
    return MeshView(raster.face_id, mask, uv)


def view_texture(view: MeshView, texture, quantize=True) -> np.ndarray:
    """:func:`render_texture`'s image of ``texture`` on the mesh of ``view``: (H, W, C) float32
    grey levels, rounded and clipped to 0..255 unless ``quantize`` is False, 0 where empty."""
    if quantize:
        _check_scale(texture, "texture", 255.0, fix="give the texture times 255")
    return sample_texture(view.mask, view.uv, texture, quantize=quantize)


def view_seen(view: MeshView, face_flag) -> np.ndarray:
    """(H, W) bool: the pixels of ``view`` whose face has ``face_flag`` ((F,) bool) set, as
    :func:`seen_mask_in_view` from the view's raster."""
    return _face_flag_image(view.face_id, face_flag)


def _face_flag_image(face_id, face_flag) -> np.ndarray:
    flag = np.asarray(face_flag, dtype=bool)
    hit = face_id >= 0
    if hit.any() and int(face_id.max()) >= flag.shape[0]:
        raise ValueError(f"face flags hold {flag.shape[0]} faces, the view shows face {int(face_id.max())}")
    seen = np.zeros(face_id.shape, dtype=bool)
    seen[hit] = flag[face_id[hit]]
    return seen


def render_texture(vertices, faces, texcoords, texcoord_faces, texture, K, width, height,
                   quantize=True):
    """Render a textured mesh as an 8-bit camera would record it.

    :func:`stex.render.render_textured` (perspective-correct texcoords, bilinear clamp-to-edge
    sampling), rounded to integers and clipped to 0..255 so that renders of the reconstructed
    and of the true texture are quantised like the input photos. To render several textures on
    one mesh, use :func:`mesh_view` once and :func:`view_texture` per texture (the same images).

    Args:
        vertices: (V, 3) float camera-space positions, metres. faces: (F, 3) int.
        texcoords: (Vt, 2) stex texcoords (u right, v down). texcoord_faces: (F, 3) int.
        texture: (W_t, W_t, 3) (or (H_t, W_t[, C])) uint8 or float texture in grey levels 0..255.
        K: (3, 3) camera matrix; width, height: image size in px.
        quantize: False returns the bilinear float values unrounded.

    Returns:
        image: (height, width, C) float32 grey levels, 0 where empty.
        mask: (height, width) bool, True where the mesh covers the pixel centre.
    """
    view = mesh_view(vertices, faces, texcoords, texcoord_faces, K, width, height)
    return view_texture(view, texture, quantize), view.mask


def novel_view(vertices, angle_deg, center=None, axis=(0.0, 1.0, 0.0)) -> np.ndarray:
    """4x4 transform moving the object as a camera orbiting it by ``angle_deg`` would see it.

    The camera stays fixed; the object is rotated about the line through ``center`` (default:
    the vertex centroid) along ``axis`` (default: the camera's y axis, i.e. vertical in the image)
    by +angle (right-handed about ``axis``). This is the view of a camera that orbited the object
    the other way: at +90 deg about +y (y down) the object's +x side (its right side in the input
    image) faces the camera; at 180 deg the far side does. Apply it with
    ``stex.camera.transform_points(T, vertices)``; the intrinsics stay the input camera's.

    Args:
        vertices: (V, 3) float camera-space positions, metres (only used for the centroid).
        angle_deg: orbit angle in degrees.
        center: (3,) rotation centre in camera coordinates, metres; None -> mean of ``vertices``.
        axis: (3,) rotation axis in camera coordinates (normalised here).

    Returns:
        (4, 4) float64 rigid transform, camera coordinates -> camera coordinates.
    """
    c = (np.asarray(vertices, dtype=np.float64).reshape(-1, 3).mean(axis=0) if center is None
         else np.asarray(center, dtype=np.float64).reshape(3))
    if not np.isfinite(c).all():
        raise ValueError(f"the rotation centre is not finite ({c.tolist()}): "
                         f"{'vertices hold NaN or inf' if center is None else 'center'}")
    k = np.asarray(axis, dtype=np.float64).reshape(3)
    n = np.linalg.norm(k)
    if not n > 0:
        raise ValueError(f"axis must be a non-zero 3-vector, got {axis}")
    k = k / n
    a = np.deg2rad(float(angle_deg))
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    R = np.eye(3) + np.sin(a) * Kx + (1.0 - np.cos(a)) * (Kx @ Kx)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c
    return T


def input_view_visibility(vertices, faces, K, width, height, depth_tol=0.01, min_cos=0.0):
    """(F,) bool: faces the input camera sees at this frame (z-buffer + :func:`stex.render.face_visibility`).

    ``vertices`` (V, 3) are the frame's surface in the input camera's coordinates (metres), ``K``
    and ``width``/``height`` the input camera. Prefer the projection stage's visibility when it
    exists so that the split matches what the pipeline considered visible.
    """
    depth = rasterize(vertices, faces, K, width, height).depth
    vis, _ = face_visibility(vertices, faces, K, depth, depth_tol=depth_tol, min_cos=min_cos)
    return vis


def seen_mask_in_view(vertices, faces, face_visible, K, width, height) -> np.ndarray:
    """Per-pixel flag of a (novel-view) render: does it show surface the input camera saw?

    Rasterises the mesh as given (``vertices`` already moved into the novel view, e.g. with
    :func:`novel_view`) and looks up the input view's face visibility through the face id of
    each pixel: ``seen[y, x] = face_id[y, x] >= 0 and face_visible[face_id[y, x]]``. Faces only
    partly visible in the input count as unseen (as :func:`stex.render.face_visibility` does).
    Unseen object pixels are ``mask & ~seen`` with ``mask`` from :func:`render_texture` (the same
    raster, so the same pixels).

    Args:
        vertices: (V, 3) float positions in the novel view's camera coordinates, metres.
        faces: (F, 3) int. face_visible: (F,) bool, visibility in the input camera this frame.
        K, width, height: the novel-view camera.

    Returns:
        (height, width) bool.
    """
    vis = np.asarray(face_visible, dtype=bool)
    if vis.shape != (np.asarray(faces).shape[0],):
        raise ValueError(f"face_visible must have shape (F,) = ({np.asarray(faces).shape[0]},),"
                         f" got {vis.shape}")
    return _face_flag_image(rasterize(vertices, faces, K, width, height).face_id, vis)


def region_psnr(reference, test, mask, region, data_range=255.0, ssim=False,
                min_pixels: int = 1, ssim_cache: SsimCache | None = None) -> dict:
    """PSNR (and optionally SSIM) over ``mask``, split into ``mask & region`` and ``mask & ~region``.

    Typical use: ``reference`` = render of the true texture from a novel view, ``test`` = render
    of the reconstruction from the same view, ``region`` = :func:`seen_mask_in_view`.

    Returns:
        dict with ``psnr_all``, ``psnr_seen``, ``psnr_unseen`` (dB, NaN if the region has fewer
        than ``min_pixels`` pixels: a score of a few pixels says nothing about the texture),
        ``mse_*`` and ``n_all``, ``n_seen``, ``n_unseen`` (pixels, always); with ``ssim=True``
        also ``ssim_all``, ``ssim_seen``, ``ssim_unseen`` (:func:`masked_ssim` over each region;
        ``ssim_cache``: as its ``cache``).
    """
    # every region lies in the mask: its bounding box, with room for the SSIM window, suffices
    # (a box edge that is not the image's stays more than the window from every scored pixel)
    mask, (reference, test, region) = _crop(mask, [reference, test, region], 2 * _SSIM_PAD + 2)
    ref, tst = _pair(reference, test, data_range)
    m = _mask(mask, ref.shape[:2])
    reg = _mask(region, ref.shape[:2], name="region")
    out = {}
    regions = (("all", m), ("seen", m & reg), ("unseen", m & ~reg))
    # the squared error once for the three regions (masked_psnr of each would convert and check
    # the images three times): per pixel, summed over channels
    d = ref - tst
    sq = np.einsum("ijc,ijc->ij", d, d)
    small = {}
    for name, sel in regions:
        n = int(sel.sum())
        small[name] = n < min_pixels
        mse = float(sq[sel].sum() / (n * ref.shape[2])) if n else np.nan
        out[f"psnr_{name}"], out[f"mse_{name}"], out[f"n_{name}"] = psnr_from_mse(mse, data_range), mse, n
        if small[name]:
            out[f"psnr_{name}"] = out[f"mse_{name}"] = np.nan
    if ssim:  # one SSIM map for the three regions
        for (name, _), s in zip(regions, _ssim_means(ref, tst, [sel for _, sel in regions], data_range,
                                                       ssim_cache)):
            out[f"ssim_{name}"] = np.nan if small[name] else s["ssim"]
    return out


# --------------------------------------------------------------------------------------------
# temporal flicker
# --------------------------------------------------------------------------------------------

def temporal_flicker(recon_prev, recon_cur, true_prev, true_cur, mask=None) -> dict:
    """Frame-to-frame change of the reconstruction minus the true change.

    Per masked pixel and channel, with d_rec = |recon_cur - recon_prev| and
    d_true = |true_cur - true_prev| (grey levels)::

        flicker = mean |d_rec - d_true|        (0 = changes exactly as much as the truth)
        excess  = mean (d_rec - d_true)        (> 0 flickers more, < 0 is more static than truth)

    Inputs may be texture slices (mask = the texels of borrowed regions, i.e. faces the camera
    did not see at either frame) or renders from a fixed view (mask = unseen pixels).

    Args:
        recon_prev, recon_cur, true_prev, true_cur: same-shape (H, W[, C]) uint8/float, grey levels.
        mask: (H, W) bool or None (= everything).

    Returns:
        dict ``flicker``, ``excess``, ``recon_change`` (mean d_rec), ``true_change`` (mean d_true),
        all in grey levels, and ``n_pixels``.
    """
    mask, (recon_prev, recon_cur, true_prev, true_cur) = _crop(
        mask, [recon_prev, recon_cur, true_prev, true_cur], 0)
    a0, a1 = _pair(recon_prev, recon_cur)
    b0, b1 = _pair(true_prev, true_cur)
    if a0.shape != b0.shape:
        raise ValueError(f"reconstruction and truth differ in shape: {a0.shape} vs {b0.shape}")
    m = _mask(mask, a0.shape[:2])
    n = int(m.sum())
    if n == 0:
        return {"flicker": np.nan, "excess": np.nan, "recon_change": np.nan,
                "true_change": np.nan, "n_pixels": 0}
    d_rec = np.abs(a1[m] - a0[m])
    d_true = np.abs(b1[m] - b0[m])
    e = d_rec - d_true
    return {"flicker": float(np.abs(e).mean()), "excess": float(e.mean()),
            "recon_change": float(d_rec.mean()), "true_change": float(d_true.mean()),
            "n_pixels": n}


# --------------------------------------------------------------------------------------------
# aggregation
# --------------------------------------------------------------------------------------------

def summarise(values) -> dict:
    """Summary of per-frame scores: mean, median, min, max over the finite values.

    Returns:
        dict ``mean``, ``median``, ``min``, ``max`` (NaN when no value is finite), ``n`` (finite
        values used) and ``n_total`` (all values; NaN scores such as empty regions are skipped).
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    f = v[np.isfinite(v)]
    if f.size == 0:
        return {"mean": np.nan, "median": np.nan, "min": np.nan, "max": np.nan, "n": 0,
                "n_total": int(v.size)}
    return {"mean": float(f.mean()), "median": float(np.median(f)), "min": float(f.min()),
            "max": float(f.max()), "n": int(f.size), "n_total": int(v.size)}
