"""Texture dynamism: SSIM between consecutive partial textures, and the paper's selective weights.

What it computes
----------------
Kim et al. 2021, "Selective Weighting for Dynamic Textures":

- :func:`partial_texture` — the visible part of frame t copied into the atlas at the optimised
  texture coordinates ξ_t (the paper's Fig. "texture dynamism" a/c); everything else black.
- :func:`face_ssim` — the SSIM map (grey, Gaussian window) between two partial textures, and per
  face f its mean over the texels covered in both: S(f).
- :func:`dynamism_table` — S [T, F]: row t compares frames t-1 and t (row 0 copies row 1, as the
  authors' ``var_table.csv``), streaming one frame at a time.
- :func:`temporal_gate` — χ_θΩ(S) per (source frame, face). Eq. (revised_temp): the temporal
  penalty between labels a and b at face f is multiplied by min(gate[a, f], gate[b, f])
  (:func:`temporal_pair_weight`).
- :func:`spatial_face_weight` / :func:`spatial_edge_weight` — S_m(f) = min over the face's label
  set L_f of S(f, k), its gate χ_θΩ(S_m(f)), and per adjacent pair (f, f') the spatial factor
  2 - (χ(S_m(f)) + χ(S_m(f'))) / 2 ∈ {1, 1.5, 2}.
- :func:`ssim_map_image` — a picture of an SSIM map or of per-face S on the atlas.

Conventions
-----------
- Textures are atlas slices (W, W, 3) uint8 RGB in the template's texel grid (row 0 = v 0);
  ``texel_face`` (W, W) int32 is the face under each texel (-1 = empty), from
  :func:`stex.template.texel_map` at the (reduced) SSIM resolution. The authors compute SSIM at
  500² (4000² sub-atlases resized); a few hundred texels are enough and keep an SSIM map cheap
  (docs/decisions/dynamism.md).
- SSIM is dimensionless, <= 1 (1 = identical). Grey = 0.299 R + 0.587 G + 0.114 B (BT.601, as
  OpenCV), computed in float so uint8 textures keep their precision.
- **NaN in S** means "face not seen in both frames" (no common texel after erosion). The gates
  treat it as **static** (χ = 1) by default: there is no evidence of dynamism, and keeping the
  temporal smoothness is the conservative choice. This is also what the authors' code does in
  effect (texels not covered in both frames get SSIM 1, ``official_code_notes.md`` §2.3).

data_range
----------
SSIM's stabilising constants are C1 = (0.01 L)², C2 = (0.03 L)² with L the value range of the
images: 255 for uint8 grey levels, 1.0 for float images in [0, 1]. It must match the images,
otherwise C1 and C2 are wrong and S shifts towards 1 in flat regions. The authors' code called
scikit-image 0.15 ``compare_ssim`` on float images in [0, 1] without ``data_range``, which then
took the range of the float dtype, **2.0** (C1 = 0.02², C2 = 0.06²) — by accident. Here
``data_range`` defaults to 255 for uint8 input and is required for float input; pass
``data_range=2.0`` (float [0, 1]) or 510 (uint8) to reproduce the authors' values.

Erosion of the coverage
-----------------------
SSIM at a texel looks at a Gaussian window of radius r = int(3.5 σ + 0.5) texels (5 at σ = 1.5,
scikit-image's truncation). A window that reaches an uncovered texel (black in a partial texture,
gutter, another chart) compares black with texture and is meaningless, so the common coverage
(covered in both) is eroded by a (2r+1)² square before averaging: only texels whose whole window
is covered in both frames count. The authors blur each mask (11 x 11 Gaussian, σ 1.5) and keep
values >= 0.9999, which is a near-disc erosion of the same radius (the corner taps of the 11 x 11
kernel weigh < 1e-4). Eroding the intersection equals intersecting the erosions.

How the authors' code differs (``mode='authors'``)
---------------------------------------------------
``official_code_notes.md`` §2.3-2.4 (``Similarity/variance.py``, ``Selector.cpp``):

- Temporal: a (frame l, face f) is *static* if **any** texel of f has SSIM >= 0.98 between frames
  l-1 and l, with texels outside the eroded common mask counted as SSIM 1 (so any face touching
  uncovered area is static). :func:`face_ssim` with ``mode='authors'`` returns that per-face
  maximum; gate it with ``theta=0.98``. The gate is indexed by the label (source) frames, as here.
- Spatial: faces with any texel whose minimum SSIM over time is < 0.95 (10 x 10 dilation at 1000²,
  i.e. 5 texels at 500²) get weight 10, others 1 (:func:`authors_dynamic_faces`), and the edge
  factor was meant to be the mean of the two faces' weights (``mode='authors_intended'`` of
  :func:`spatial_edge_weight`). Because the loop modifies a copy, the factor is **never applied**:
  ``mode='authors'`` returns 1 on every edge.
- The authors' table also flags the last face static always (``np.unique`` includes -1); that
  bug is not reproduced.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import cv2
import numpy as np

from stex.image import grey
from stex.sampling import as_sampler, checked_frame
from stex.ssim import SSIM_SIGMA, ssim_map

log = logging.getLogger("stex.dynamism")

__all__ = [
    "THETA_OMEGA",
    "AUTHORS_STATIC_THETA",
    "partial_texture",
    "ssim_window_radius",
    "face_ssim",
    "dynamism_rows",
    "dynamism_table",
    "temporal_gate",
    "temporal_pair_weight",
    "label_set_min",
    "spatial_face_weight",
    "spatial_edge_weight",
    "authors_dynamic_faces",
    "ssim_map_image",
]

#: θ_Ω of the paper: SSIM at or above it is "static" (no evidence of dynamism)
THETA_OMEGA = 0.95
#: the authors' code: a (frame, face) is static when any texel has SSIM >= 0.98
AUTHORS_STATIC_THETA = 0.98
#: the authors' code: weight of a "dynamic" face in the (intended) spatial factor
AUTHORS_DYNAMIC_WEIGHT = 10.0

_MODES = ("paper", "authors")


# --------------------------------------------------------------------------------------------
# partial textures
# --------------------------------------------------------------------------------------------

def partial_texture(sampler_or_maps, xi_t, face_visible_t, image_t):
    """The visible part of one frame copied into the atlas (the paper's incomplete texture slice).

    Every texel of a face visible at t takes the colour of frame t's image at the position
    interpolated from ξ_t over the face's corners (bilinear lookup, as the texture volume:
    :meth:`stex.sampling.TexelSampler.slice`); all other texels are black and not covered.

    Args:
        sampler_or_maps: a :class:`stex.sampling.TexelSampler` of the atlas (build it once for a
            sequence), or a tuple (texel_face (W, W) int, texel_bary (W, W, 3) float, faces (F, 3) int).
        xi_t: (V, 2) float colour-image coordinates of the vertices at t (px; u column, v row;
            integer = pixel centre). Non-finite rows leave their faces' texels uncovered.
        face_visible_t: (F,) bool, faces seen at t (projection ``face_visible``).
        image_t: (Hc, Wc, 3) uint8 RGB colour image of frame t.

    Returns:
        (texture (W, W, 3) uint8, 0 where not covered; covered (W, W) bool, texels sampled from
        frame t).
    """
    sampler = as_sampler(sampler_or_maps)
    vis = np.asarray(face_visible_t)
    if vis.shape != (len(sampler.faces),):
        raise ValueError(f"face_visible_t must have shape ({len(sampler.faces)},), got {vis.shape}")
    if vis.dtype != np.bool_:
        raise ValueError(f"face_visible_t must be bool, got {vis.dtype}")
    xi = np.asarray(xi_t)
    if xi.ndim != 2 or xi.shape[1] != 2:
        raise ValueError(f"xi_t must be (V, 2), got {xi.shape}")
    if len(sampler.faces) and sampler.faces.max() >= len(xi):
        raise ValueError(f"xi_t has {len(xi)} vertices but faces refer to vertex {sampler.faces.max()}")
    img = np.asarray(image_t)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image_t must be (Hc, Wc, 3) uint8, got {img.shape} {img.dtype}")
    labels = np.where(vis, 0, -1).astype(np.int32)
    tex, label_map = sampler.slice(labels, [xi], [img], fill=False)
    return tex, label_map >= 0


# --------------------------------------------------------------------------------------------
# SSIM per face
# --------------------------------------------------------------------------------------------

def ssim_window_radius(sigma: float) -> int:
    """Radius (texels) of scikit-image's Gaussian SSIM window: int(3.5 sigma + 0.5)."""
    return int(3.5 * float(sigma) + 0.5)


def _erode(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask
    # outside the atlas counts as uncovered (border 0)
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def _check_data_range(data_range, *arrays):
    if data_range is None:
        if all(a.dtype == np.uint8 for a in arrays):
            return 255.0
        raise ValueError("data_range is required for non-uint8 textures (1.0 for images in [0, 1]); "
                         f"got dtypes {[str(a.dtype) for a in arrays]}")
    dr = float(data_range)
    if not np.isfinite(dr) or dr <= 0:
        raise ValueError(f"data_range must be a positive number, got {data_range}")
    return dr


def face_ssim(tex_a, covered_a, tex_b, covered_b, texel_face, n_faces: int, data_range=None,
              sigma: float = 1.5, erode_px: int | None = None, mode: str = "paper",
              return_map: bool = False):
    """Per-face SSIM between two partial textures of the same atlas.

    The SSIM map is ``skimage.metrics.structural_similarity(grey_a, grey_b,
    gaussian_weights=True, sigma=sigma, use_sample_covariance=False, data_range=data_range,
    full=True)`` on the grey images (see the module docstring for grey and ``data_range``; the
    authors' ``win_size=13`` only rescaled the covariances by 169/168 — population covariances
    are used here, as :func:`stex.metrics.masked_ssim`). The common coverage
    ``covered_a & covered_b`` is eroded by ``erode_px`` (see "Erosion" in the module docstring).

    Args:
        tex_a, tex_b: (W, W, 3) RGB or (W, W) grey textures, uint8 or float, same shape.
        covered_a, covered_b: (W, W) bool, texels holding an observation.
        texel_face: (W, W) int face id per texel, -1 = empty.
        n_faces: F, the length of the result.
        data_range: value range of the textures: None = 255 for uint8 (required for float
            input; 1.0 for images in [0, 1]).
        sigma: Gaussian window σ, texels.
        erode_px: erosion radius of the common coverage, texels; None = the window radius
            :func:`ssim_window_radius` (5 at σ 1.5); 0 = no erosion.
        mode: ``'paper'`` — S(f) is the mean SSIM over the face's texels in the eroded common
            coverage, NaN when there are none. ``'authors'`` — the authors' statistic: the
            maximum SSIM over all the face's texels, those outside the eroded common coverage
            counted as 1 (gate it at :data:`AUTHORS_STATIC_THETA`); NaN only for a face without
            texels.
        return_map: also return the SSIM map.

    Returns:
        (F,) float32 S per face; with ``return_map`` also (map (W, W) float32 SSIM, NaN outside
        the eroded common coverage, valid (W, W) bool the eroded common coverage).
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    a, b = np.asarray(tex_a), np.asarray(tex_b)
    if a.shape != b.shape:
        raise ValueError(f"tex_a and tex_b differ in shape: {a.shape} vs {b.shape}")
    if a.ndim not in (2, 3) or a.shape[0] != a.shape[1]:
        raise ValueError(f"textures must be (W, W, 3) or (W, W), got {a.shape}")
    W = a.shape[0]
    tf = np.asarray(texel_face)
    ca, cb = np.asarray(covered_a), np.asarray(covered_b)
    for name, m in (("covered_a", ca), ("covered_b", cb), ("texel_face", tf)):
        if m.shape != (W, W):
            raise ValueError(f"{name} must have shape {(W, W)}, got {m.shape}")
    if ca.dtype != np.bool_ or cb.dtype != np.bool_:
        raise ValueError(f"covered_a/covered_b must be bool, got {ca.dtype}/{cb.dtype}")
    if not np.issubdtype(tf.dtype, np.integer):
        raise ValueError(f"texel_face must be integer face ids, got {tf.dtype}")
    for name, t in (("tex_a", a), ("tex_b", b)):
        if t.dtype.kind == "f" and not np.isfinite(t).all():
            # one NaN texel (covered or not: the SSIM windows read their neighbours) made the
            # faces around it NaN, which the gate reads as static
            raise ValueError(f"{name} holds {int((~np.isfinite(t)).sum())} non-finite values "
                             f"(give uncovered texels any finite value, e.g. 0)")
    n_faces = int(n_faces)
    if n_faces < 0 or (tf.size and tf.max() >= n_faces):
        raise ValueError(f"texel_face refers to face {tf.max()} but n_faces is {n_faces}")
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    dr = _check_data_range(data_range, a, b)
    r = ssim_window_radius(sigma) if erode_px is None else int(erode_px)
    if r < 0:
        raise ValueError(f"erode_px must be >= 0, got {erode_px}")

    valid = _erode(ca & cb & (tf >= 0), r)
    smap = np.full((W, W), np.nan, np.float32)
    if valid.any():
        # scikit-image is slow to import and only an SSIM of another window needs it
        from skimage.metrics import structural_similarity

        # only the bounding box of the valid texels (plus a margin wider than the window)
        # matters: same values, less work on sparse coverage
        rows, cols = np.flatnonzero(valid.any(1)), np.flatnonzero(valid.any(0))
        m = ssim_window_radius(sigma) + 2
        r0, r1 = max(rows[0] - m, 0), min(rows[-1] + 1 + m, W)
        c0, c1 = max(cols[0] - m, 0), min(cols[-1] + 1 + m, W)
        ga, gb = grey(a[r0:r1, c0:c1]), grey(b[r0:r1, c0:c1])
        n = 2 * ssim_window_radius(sigma) + 1  # skimage wants the image at least one window wide
        if min(ga.shape) < n:
            pad = [(0, max(n - ga.shape[0], 0)), (0, max(n - ga.shape[1], 0))]
            ga, gb = np.pad(ga, pad, mode="edge"), np.pad(gb, pad, mode="edge")
        if float(sigma) == SSIM_SIGMA:
            # skimage's map by stex.ssim's kernels, the same values bit for bit, several times faster
            s = ssim_map(ga[..., None], gb[..., None], dr, None)
        else:
            _, s = structural_similarity(ga, gb, data_range=dr, gaussian_weights=True,
                                         sigma=float(sigma), use_sample_covariance=False, full=True)
        sub = s[: r1 - r0, : c1 - c0].astype(np.float32)
        smap[r0:r1, c0:c1] = np.where(valid[r0:r1, c0:c1], sub, np.nan)

    if mode == "paper":
        f = tf[valid]
        cnt = np.bincount(f, minlength=n_faces)
        tot = np.bincount(f, weights=smap[valid].astype(np.float64), minlength=n_faces)
        with np.errstate(invalid="ignore", divide="ignore"):
            S = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan).astype(np.float32)
    else:
        inside = tf >= 0
        vals = np.where(valid, smap, np.float32(1.0))[inside]
        S = np.full(n_faces, -np.inf, np.float64)
        np.maximum.at(S, tf[inside], vals.astype(np.float64))
        S = np.where(np.isfinite(S), S, np.nan).astype(np.float32)
    if return_map:
        return S, smap, valid
    return S


# --------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------

def dynamism_rows(load: Callable, frames, sampler_or_maps, data_range=None, sigma: float = 1.5,
                  erode_px: int | None = None, mode: str = "paper", min_map: np.ndarray | None = None,
                  progress: bool = False):
    """Rows of the dynamism table for the frames ``frames`` (consecutive, ascending, >= 1): row i
    compares frame frames[i] - 1 with frames[i]. Loads frames[0] - 1 .. frames[-1], each once,
    keeping one partial texture at a time (for frame-block jobs; :func:`dynamism_table` is the
    whole sequence).

    Args:
        load: ``load(t) -> (image (Hc, Wc, 3) uint8, xi_t (V, 2) float px, face_visible_t (F,) bool)``.
        frames: consecutive frame indices t >= 1.
        sampler_or_maps: the atlas at the SSIM resolution (see :func:`partial_texture`).
        data_range, sigma, erode_px, mode: as :func:`face_ssim` (textures are uint8 here, so
            data_range None = 255).
        min_map: optional (W, W) float32, updated in place to the running minimum of the SSIM
            maps, texels outside the eroded common coverage counted as 1 (the authors'
            ``min_ssim``, for :func:`authors_dynamic_faces` and pictures).
        progress: log frames done / total and the rate.

    Returns:
        (len(frames), F) float32.
    """
    sampler = as_sampler(sampler_or_maps)
    frames = np.asarray(list(frames), np.int64)
    F = len(sampler.faces)
    if frames.size == 0:
        return np.zeros((0, F), np.float32)
    if frames[0] < 1 or (np.diff(frames) != 1).any():
        raise ValueError(f"frames must be consecutive and >= 1, got {frames[:5].tolist()}...")
    tf = np.full(sampler.W * sampler.W, -1, np.int32)
    tf[sampler.index] = sampler.face
    tf = tf.reshape(sampler.W, sampler.W)
    if min_map is not None and (min_map.shape != tf.shape or min_map.dtype != np.float32):
        raise ValueError(f"min_map must be {tf.shape} float32, got {min_map.shape} {min_map.dtype}")
    out = np.empty((len(frames), F), np.float32)
    img, xi, vis = checked_frame(load, int(frames[0]) - 1, F)
    prev = partial_texture(sampler, xi, vis, img)
    t0 = time.perf_counter()
    for i, t in enumerate(frames):
        img, xi, vis = checked_frame(load, int(t), F)
        cur = partial_texture(sampler, xi, vis, img)
        del img  # one colour image in memory at a time
        res = face_ssim(prev[0], prev[1], cur[0], cur[1], tf, F, data_range=data_range, sigma=sigma,
                        erode_px=erode_px, mode=mode, return_map=min_map is not None)
        if min_map is not None:
            S, smap, valid = res
            np.minimum(min_map, np.where(valid, smap, np.float32(1.0)), out=min_map)
        else:
            S = res
        out[i] = S
        prev = cur
        if progress and ((i + 1) % 10 == 0 or i + 1 == len(frames)):
            dt = time.perf_counter() - t0
            log.info("dynamism: %d/%d frame pairs (%.1f pairs/s)", i + 1, len(frames), (i + 1) / max(dt, 1e-9))
    return out


def dynamism_table(load: Callable, n_frames: int, sampler_or_maps, data_range=None, sigma: float = 1.5,
                   erode_px: int | None = None, mode: str = "paper", return_min_map: bool = False,
                   progress: bool = False):
    """The dynamism table S [T, F] of a sequence.

    S[t, f] = :func:`face_ssim` of face f between the partial textures of frames t-1 and t
    (mean SSIM over the texels seen in both, ``mode='paper'``; NaN where not seen in both).
    Row 0 has no previous frame and copies row 1 (as the authors' ``var_table.csv``): frame 0's
    only consecutive pair is (0, 1). With T = 1 the single row is NaN.

    Frames stream: ``load(t)`` is called once per frame, in order, and only two partial textures
    are held (the paper scene's 265 colour images of 2048 x 1536 are never all in memory).
    Cost: T bilinear samplings of the covered texels plus T-1 SSIM maps of W² texels.

    Args:
        load: ``load(t) -> (image (Hc, Wc, 3) uint8, xi_t (V, 2) float px, face_visible_t (F,) bool)``.
        n_frames: T.
        sampler_or_maps: the atlas at the SSIM resolution (:class:`stex.sampling.TexelSampler` or
            (texel_face, texel_bary, faces)); e.g. ``stex.template.texel_map(texcoords,
            texcoord_faces, 512)``.
        data_range, sigma, erode_px, mode: as :func:`face_ssim`.
        return_min_map: also return the per-texel minimum SSIM over time (W, W) float32
            (texels never seen in two consecutive frames: 1).
        progress: log progress.

    Returns:
        S (T, F) float32, and with ``return_min_map`` the minimum map.
    """
    sampler = as_sampler(sampler_or_maps)
    T = int(n_frames)
    if T < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    F = len(sampler.faces)
    min_map = np.ones((sampler.W, sampler.W), np.float32) if return_min_map else None
    S = np.full((T, F), np.nan, np.float32)
    if T == 1:
        checked_frame(load, 0, F)  # still validate the one frame
    else:
        S[1:] = dynamism_rows(load, range(1, T), sampler, data_range=data_range, sigma=sigma,
                              erode_px=erode_px, mode=mode, min_map=min_map, progress=progress)
        S[0] = S[1]
    return (S, min_map) if return_min_map else S


# --------------------------------------------------------------------------------------------
# selective weights
# --------------------------------------------------------------------------------------------

def _check_S(S, name="S") -> np.ndarray:
    a = np.asarray(S)
    if a.ndim != 2:
        raise ValueError(f"{name} must be (T, F), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be float (NaN = not seen in both frames), got {a.dtype}")
    return a


def _check_theta(theta):
    th = float(theta)
    if not np.isfinite(th):
        raise ValueError(f"theta must be finite, got {theta}")
    return th


def _chi(x: np.ndarray, theta: float, nan_static: bool) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        g = x >= theta
    return np.where(np.isnan(x), bool(nan_static), g).astype(np.float32)


def temporal_gate(S, theta: float = THETA_OMEGA, nan_static: bool = True) -> np.ndarray:
    """χ_θΩ(S): 1 where S >= theta (static: temporal smoothness kept), 0 where S < theta
    (dynamic: the temporal edge is ignored).

    Args:
        S: (T, F) float dynamism table (rows = source frames l). NaN = not seen in both frames.
        theta: θ_Ω (paper 0.95; the authors' "any texel" table uses 0.98).
        nan_static: gate value of NaN entries: True -> 1 (no evidence of dynamism, keep the
            smoothness; default, and the authors' effective behaviour), False -> 0.

    Returns:
        (T, F) float32 in {0, 1}.
    """
    return _chi(_check_S(S), _check_theta(theta), nan_static)


def temporal_pair_weight(gate, faces, label_a, label_b) -> np.ndarray:
    """Eq. (revised_temp) factor min(χ(S(f, a)), χ(S(f, b))) for temporal edges.

    Args:
        gate: (T, F) float32 from :func:`temporal_gate` (rows = source frames).
        faces, label_a, label_b: int arrays of one shape, the face f and the two labels (source
            frames) of the linked nodes.

    Returns:
        float32 array of that shape in {0, 1}; multiply E_temp(a, b) at face f by it.
    """
    g = np.asarray(gate)
    if g.ndim != 2:
        raise ValueError(f"gate must be (T, F), got shape {g.shape}")
    f, a, b = np.broadcast_arrays(np.asarray(faces), np.asarray(label_a), np.asarray(label_b))
    for name, x, n in (("faces", f, g.shape[1]), ("label_a", a, g.shape[0]), ("label_b", b, g.shape[0])):
        if x.size and not np.issubdtype(x.dtype, np.integer):
            raise ValueError(f"{name} must be integer, got {x.dtype}")
        if x.size and (x.min() < 0 or x.max() >= n):
            raise ValueError(f"{name} out of range [0, {n})")
    return np.minimum(g[a, f], g[b, f]).astype(np.float32)


def _label_set_mask(label_sets, T: int, F: int) -> np.ndarray:
    L = np.asarray(label_sets)
    if L.dtype == np.bool_:
        if L.shape != (T, F):
            raise ValueError(f"label_sets as a bool mask must be (T, F) = {(T, F)}, got {L.shape}")
        return L
    if not np.issubdtype(L.dtype, np.integer):
        raise ValueError(f"label_sets must be a (T, F) bool mask or an int (..., F, K) candidate array, got {L.dtype}")
    if L.ndim < 2 or L.shape[-2] != F:
        raise ValueError(f"label_sets as candidates must be (..., F, K) with F = {F}, got {L.shape}")
    if L.size and L.max() >= T:
        raise ValueError(f"label_sets holds frame {L.max()} but S has {T} rows")
    # union over any leading (target frame) axes; -1 = padding
    f = np.broadcast_to(np.arange(F)[:, None], L.shape[-2:])
    f = np.broadcast_to(f, L.shape)
    keep = L >= 0
    mask = np.zeros((T, F), bool)
    mask[L[keep], f[keep]] = True
    return mask


def label_set_min(S, label_sets) -> np.ndarray:
    """S_m(f) = min over k in L_f of S(f, k), NaN entries skipped.

    Args:
        S: (T, F) float dynamism table.
        label_sets: the label set L_f of every face, either a (T, F) bool mask (e.g. the
            projection's ``face_visible``: every frame where f is seen) or an int candidate array
            (..., F, K) of source frames, -1 = padding (e.g. candidates [T, F, K]: L_f is the
            union over target frames).

    Returns:
        (F,) float32; NaN where the set is empty or all its entries are NaN.
    """
    S = _check_S(S)
    T, F = S.shape
    mask = _label_set_mask(label_sets, T, F)
    vals = np.where(mask & ~np.isnan(S), S, np.inf).min(0)
    return np.where(np.isfinite(vals), vals, np.nan).astype(np.float32)


def spatial_face_weight(S, label_sets, theta: float = THETA_OMEGA, nan_static: bool = True) -> np.ndarray:
    """χ_θΩ(S_m(f)) per face: 1 if every label of f is static (or has no evidence), 0 if some
    label of f is dynamic (temporal discontinuity possible there, so spatial coherence is
    enforced more).

    Args:
        S, label_sets: as :func:`label_set_min`.
        theta: θ_Ω.
        nan_static: value for faces whose S_m is NaN (no evidence): True -> 1.

    Returns:
        (F,) float32 in {0, 1}, the input of :func:`spatial_edge_weight`.
    """
    return _chi(label_set_min(S, label_sets), _check_theta(theta), nan_static)


def spatial_edge_weight(face_w, pairs, mode: str = "paper") -> np.ndarray:
    """Factor on the spatial smoothness E_spa of each adjacent face pair.

    Args:
        face_w: (F,) float per-face static gate in {0, 1} (:func:`spatial_face_weight`; for the
            authors' modes: 1 - :func:`authors_dynamic_faces`).
        pairs: (E, 2) int adjacent faces (template ``adjacency/pairs``).
        mode: ``'paper'`` — 2 - (w_f + w_f') / 2, i.e. 1 (both static), 1.5 (one dynamic) or 2
            (both dynamic); ``'authors'`` — 1 on every edge (the code's effective behaviour:
            the ×10 weighting modifies a copy, official_code_notes.md §2.4);
            ``'authors_intended'`` — the mean of the two faces' weights, 10 for a dynamic face and
            1 for a static one.

    Returns:
        (E,) float32.
    """
    w = np.asarray(face_w, np.float32)
    if w.ndim != 1:
        raise ValueError(f"face_w must be (F,), got {w.shape}")
    p = np.asarray(pairs)
    if p.ndim != 2 or p.shape[1] != 2 or not np.issubdtype(p.dtype, np.integer):
        raise ValueError(f"pairs must be (E, 2) int, got {p.shape} {p.dtype}")
    if p.size and (p.min() < 0 or p.max() >= len(w)):
        raise ValueError(f"pairs refer to faces outside [0, {len(w)})")
    if mode == "authors":
        return np.ones(len(p), np.float32)
    if np.isnan(w).any():
        raise ValueError("face_w has NaN: gate S_m first (spatial_face_weight)")
    if mode == "paper":
        return (2.0 - (w[p[:, 0]] + w[p[:, 1]]) / 2.0).astype(np.float32)
    if mode == "authors_intended":
        fw = np.where(w >= 0.5, 1.0, AUTHORS_DYNAMIC_WEIGHT)
        return ((fw[p[:, 0]] + fw[p[:, 1]]) / 2.0).astype(np.float32)
    raise ValueError(f"mode must be 'paper', 'authors' or 'authors_intended', got {mode!r}")


def authors_dynamic_faces(min_map, texel_face, n_faces: int, theta: float = THETA_OMEGA,
                          dilate_px: int | None = None) -> np.ndarray:
    """The authors' "dynamic" faces: any texel whose minimum SSIM over time is < theta, after
    a square dilation of the low-SSIM texels (``classify_case``: 10 x 10 at 1000², scaled here).

    Args:
        min_map: (W, W) float per-texel minimum SSIM over time (:func:`dynamism_table` with
            ``return_min_map``; 1 where never compared).
        texel_face: (W, W) int face per texel, -1 = empty.
        n_faces: F.
        theta: threshold (0.95 in the authors' code).
        dilate_px: side of the square dilation, texels; None = round(10 W / 1000).

    Returns:
        (F,) bool.
    """
    m = np.asarray(min_map, np.float32)
    tf = np.asarray(texel_face)
    if m.ndim != 2 or m.shape != tf.shape:
        raise ValueError(f"min_map {m.shape} and texel_face {tf.shape} must be the same (W, W)")
    n_faces = int(n_faces)
    if tf.size and tf.max() >= n_faces:
        raise ValueError(f"texel_face refers to face {tf.max()} but n_faces is {n_faces}")
    k = int(round(10 * m.shape[0] / 1000)) if dilate_px is None else int(dilate_px)
    if k < 0:
        raise ValueError(f"dilate_px must be >= 0, got {dilate_px}")
    low = (m < _check_theta(theta)).astype(np.uint8)
    if k > 1:
        low = cv2.dilate(low, np.ones((k, k), np.uint8))
    hit = (low > 0) & (tf >= 0)
    out = np.zeros(n_faces, bool)
    out[tf[hit]] = True
    return out


# --------------------------------------------------------------------------------------------
# pictures
# --------------------------------------------------------------------------------------------

def ssim_map_image(values, texel_face=None, vmin: float = 0.5, vmax: float = 1.0,
                   theta: float | None = None) -> np.ndarray:
    """A picture of SSIM on the atlas (the paper's SSIM-map figure): grey from black (<= vmin)
    to white (>= vmax); NaN / empty texels dark blue; with ``theta``, texels below it tinted red
    (the "dynamic" ones).

    Args:
        values: (W, W) float per-texel SSIM map (NaN = not compared), or (F,) float per-face S
            with ``texel_face``.
        texel_face: (W, W) int face per texel (-1 = empty), needed for per-face values.
        vmin, vmax: grey range.
        theta: optional threshold to highlight (θ_Ω).

    Returns:
        (W, W, 3) uint8 RGB.
    """
    v = np.asarray(values, np.float32)
    if v.ndim == 1:
        if texel_face is None:
            raise ValueError("per-face values need texel_face")
        tf = np.asarray(texel_face)
        if tf.ndim != 2:
            raise ValueError(f"texel_face must be (W, W), got {tf.shape}")
        if tf.size and tf.max() >= len(v):
            raise ValueError(f"texel_face refers to face {tf.max()} but values has {len(v)}")
        v = np.where(tf >= 0, v[np.maximum(tf, 0)], np.nan)
    elif v.ndim != 2:
        raise ValueError(f"values must be (W, W) or (F,), got {v.shape}")
    if not vmax > vmin:
        raise ValueError(f"vmax must exceed vmin, got {vmin}, {vmax}")
    ok = np.isfinite(v)
    g = np.clip((np.where(ok, v, vmin) - vmin) / (vmax - vmin), 0, 1)
    img = np.repeat((g * 255 + 0.5).astype(np.uint8)[..., None], 3, -1)
    if theta is not None:
        low = ok & (v < float(theta))
        img[low] = (np.stack([np.full(low.sum(), 255.0), 0.3 * g[low] * 255, 0.3 * g[low] * 255], -1)
                    + 0.5).astype(np.uint8)
    img[~ok] = (20, 20, 60)
    return img
