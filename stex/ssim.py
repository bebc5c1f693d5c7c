"""SSIM maps (Wang et al. 2004) as scikit-image computes them, bit for bit, in numba kernels, and a
cache of the reference side of the maps for several test images compared with one reference.

``skimage.metrics.structural_similarity(ref, tst, data_range=R, channel_axis=-1,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True)`` is the definition;
:func:`ssim_map` does the same floating-point operations in the same order (the Gaussian window
as scipy's correlate1d sums a symmetric kernel, the map's formulas as skimage writes them), in
one pass per filtered image, and tests/test_metrics.py checks the two for equality. Used by
:mod:`stex.metrics` (masked SSIM, region scores), where the evaluation spends much of its time.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy import ndimage as ndi

__all__ = ["SSIM_SIGMA", "SSIM_RADIUS", "SSIM_WEIGHTS", "SsimCache", "ssim_weights", "ssim_filter", "ssim_map"]

#: skimage's Gaussian SSIM window: sigma (px) and radius int(3.5 sigma + 0.5) (truncate 3.5): 11 taps
SSIM_SIGMA = 1.5
SSIM_RADIUS = int(3.5 * SSIM_SIGMA + 0.5)


class SsimCache:
    """The reference side of SSIM maps kept while several test images are compared with the same
    reference crops (every method's render against one true render or photo).

    An SSIM map filters five images (x, y, x², y², xy; Gaussian, per channel); x's two depend on
    the reference alone. An entry is found by the reference crop's shape and a sparse sample of
    its pixels and used only when the crop equals the stored one pixel for pixel, so the maps are
    the ones computed afresh, bit for bit. Holds the crop and two (h, w) float64 arrays per
    channel for every reference crop: keep one per frame.
    """

    def __init__(self):
        self._entries: dict = {}

    def reference(self, ref: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per channel of ``ref`` ((h, w, C) float64), its Gaussian-weighted local mean ux and
        variance vx ((h, w) float64 each), from the cache or computed now."""
        key = (ref.shape, ref[::17, ::13].tobytes())
        for stored, stats in self._entries.get(key, ()):
            if np.array_equal(stored, ref):
                return stats
        stats = [_ssim_reference(np.ascontiguousarray(ref[..., ch])) for ch in range(ref.shape[2])]
        self._entries.setdefault(key, []).append((ref, stats))
        return stats


def ssim_weights() -> np.ndarray:
    """skimage's SSIM window (gaussian_weights=True): scipy's Gaussian of sigma 1.5 truncated at
    3.5 sigma, (11,) float64, read from scipy itself as its response to a unit impulse (exact:
    every other term of that sum is a zero)."""
    impulse = np.zeros(2 * SSIM_RADIUS + 1)
    impulse[SSIM_RADIUS] = 1.0
    return ndi.gaussian_filter1d(impulse, SSIM_SIGMA, mode="constant", truncate=3.5)


SSIM_WEIGHTS = ssim_weights()


@njit(cache=True, nogil=True, inline="always")
def _mirrored_rows(i, k, h):
    """Rows i + k and i - k (k < 0) of an image of h rows, mirrored at its edges as scipy's
    'reflect' mode (the edge row repeated)."""
    ia, ib = i + k, i - k
    if ia < 0:
        ia = -ia - 1
    if ib >= h:
        ib = 2 * h - ib - 1
    return ia, ib


@njit(cache=True, nogil=True)
def ssim_filter(x, w):
    """``scipy.ndimage.gaussian_filter(x, 1.5, mode='reflect', truncate=3.5)`` of a (h, w)
    float64 image with h, w >= 6, bit for bit: rows then columns, each output the centre tap times
    its weight plus, outermost pair first, each symmetric pair's sum times its weight, as scipy's
    correlate1d sums a symmetric kernel; edges reflected (d c b a | a b c d). w: the (2r + 1,)
    weights (:func:`ssim_weights`). A whole row at a time, so the sums vectorise."""
    h, wd = x.shape
    r = (w.shape[0] - 1) // 2
    tmp = np.empty((h, wd))
    for i in range(h):
        for j in range(wd):
            tmp[i, j] = x[i, j] * w[r]
        for k in range(-r, 0):
            ia, ib = _mirrored_rows(i, k, h)
            for j in range(wd):
                tmp[i, j] += (x[ia, j] + x[ib, j]) * w[r + k]
    out = np.empty((h, wd))
    line = np.empty(wd + 2 * r)
    for i in range(h):
        for j in range(wd):
            line[r + j] = tmp[i, j]
        for k in range(r):
            line[r - 1 - k] = tmp[i, k]
            line[r + wd + k] = tmp[i, wd - 1 - k]
        for j in range(wd):
            out[i, j] = line[r + j] * w[r]
        for k in range(-r, 0):
            for j in range(wd):
                out[i, j] += (line[r + j + k] + line[r + j - k]) * w[r + k]
    return out


@njit(cache=True, nogil=True)
def _ssim_reference_kernel(x, w):
    ux = ssim_filter(x, w)
    uxx = ssim_filter(x * x, w)
    vx = np.empty_like(ux)
    for i in range(ux.shape[0]):
        for j in range(ux.shape[1]):
            vx[i, j] = 1.0 * (uxx[i, j] - ux[i, j] * ux[i, j])
    return ux, vx


def _ssim_reference(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ux, vx) of one (h, w) float64 reference channel, as skimage computes them (population
    covariance: cov_norm 1)."""
    return _ssim_reference_kernel(x, SSIM_WEIGHTS)


@njit(cache=True, nogil=True, inline="always")
def _reflect_ends(line, r, wd):
    """Fill the r entries either side of line[r:r + wd] by reflection (d c b a | a b c d | d c b a)."""
    for k in range(r):
        line[r - 1 - k] = line[r + k]
        line[r + wd + k] = line[r + wd - 1 - k]


@njit(cache=True, nogil=True)
def _ssim_channel(x, y, ux, vx, w, C1, C2, S, ch):
    """One channel of skimage's SSIM map into S[:, :, ch]: the test's three filtered images (y,
    y², xy; :func:`ssim_filter`'s sums, products formed as numpy forms them) and its formulas,
    operation for operation (A1 = 2 ux uy + C1, A2 = 2 vxy + C2, B1 = ux² + uy² + C1,
    B2 = vx + vy + C2, S = A1 A2 / B1 B2). One output row at a time: the column pass of the
    eleven input rows it reads goes into three line buffers, then the row pass and the formulas,
    so no full-size intermediate image is written."""
    h, wd = x.shape
    r = (w.shape[0] - 1) // 2
    w0 = w[r]
    ly, lyy, lxy = np.empty(wd + 2 * r), np.empty(wd + 2 * r), np.empty(wd + 2 * r)
    for i in range(h):
        for j in range(wd):
            q = y[i, j]
            ly[r + j] = q * w0
            lyy[r + j] = (q * q) * w0
            lxy[r + j] = (x[i, j] * q) * w0
        for k in range(-r, 0):
            ia, ib = _mirrored_rows(i, k, h)
            wk = w[r + k]
            for j in range(wd):
                p, q = y[ia, j], y[ib, j]
                ly[r + j] += (p + q) * wk
                lyy[r + j] += (p * p + q * q) * wk
                lxy[r + j] += (x[ia, j] * p + x[ib, j] * q) * wk
        _reflect_ends(ly, r, wd)
        _reflect_ends(lyy, r, wd)
        _reflect_ends(lxy, r, wd)
        for j in range(wd):
            b = ly[r + j] * w0
            byy = lyy[r + j] * w0
            bxy = lxy[r + j] * w0
            for k in range(-r, 0):
                wk = w[r + k]
                b += (ly[r + j + k] + ly[r + j - k]) * wk
                byy += (lyy[r + j + k] + lyy[r + j - k]) * wk
                bxy += (lxy[r + j + k] + lxy[r + j - k]) * wk
            a = ux[i, j]
            vy = 1.0 * (byy - b * b)
            vxy = 1.0 * (bxy - a * b)
            A1 = 2 * a * b + C1
            A2 = 2 * vxy + C2
            B1 = a * a + b * b + C1
            B2 = vx[i, j] + vy + C2
            S[i, j, ch] = (A1 * A2) / (B1 * B2)


@njit(cache=True, nogil=True)
def _channel_mean(S):
    """``S.mean(axis=-1)`` of an (h, w, C) float64 array as numpy computes it for a few channels:
    the channels summed in order, then divided by C."""
    h, wd, C = S.shape
    out = np.empty((h, wd))
    for i in range(h):
        for j in range(wd):
            acc = S[i, j, 0]
            for c in range(1, C):
                acc += S[i, j, c]
            out[i, j] = acc / C
    return out


def ssim_map(ref: np.ndarray, tst: np.ndarray, data_range, cache: SsimCache | None) -> np.ndarray:
    """The SSIM map of two (h, w, C) float64 images, averaged over channels: (h, w) float64.

    The arithmetic of ``skimage.metrics.structural_similarity(ref, tst, data_range=data_range,
    channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True)``
    step for step (tests/test_metrics.py compares the two for equality), with the reference's
    filtered images from ``cache`` when one is given.
    """
    if min(ref.shape[:2]) < 2 * SSIM_RADIUS + 1:  # skimage's own error for an image under a window
        from skimage.metrics import structural_similarity  # skimage loads slowly; only this needs it

        _, S = structural_similarity(ref, tst, data_range=float(data_range), channel_axis=-1,
                                     gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False,
                                     full=True)
        return S.reshape(ref.shape[0], ref.shape[1], -1).mean(axis=-1)
    stats = cache.reference(ref) if cache is not None else [
        _ssim_reference(np.ascontiguousarray(ref[..., ch])) for ch in range(ref.shape[2])]
    R = float(data_range)
    C1, C2 = (0.01 * R) ** 2, (0.03 * R) ** 2
    S = np.empty(ref.shape, np.float64)
    for ch, (ux, vx) in enumerate(stats):
        _ssim_channel(np.ascontiguousarray(ref[..., ch]), np.ascontiguousarray(tst[..., ch]), ux, vx,
                      SSIM_WEIGHTS, C1, C2, S, ch)
    return _channel_mean(S)
