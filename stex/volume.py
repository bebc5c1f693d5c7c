"""Texture volume: one W x W slice of the fixed atlas per frame, from the labelled source frames.

What it computes
----------------
- :class:`TexelSampler` / :func:`volume_slice` — the slice of one target frame t. For every
  covered texel of the atlas (``texel/face_id`` >= 0 of the template store): its face f, the label
  l = ``labels_t[f]`` (the source frame chosen for f at t, -1 = none), the position of the texel on
  frame l's colour image, ``x = sum_k bary_k * xi_l[faces[f, k]]`` (barycentric interpolation of
  the face corners' texture coordinates ξ_l, colour pixels, integer = pixel centre), and a bicubic
  lookup of frame l's colour image there (OpenCV ``remap`` INTER_CUBIC, clamp-to-edge), saturated
  to uint8; or, with ``interpolation="bilinear"``, a bilinear lookup exactly as
  :func:`stex.render.sample_bilinear`, rounded to uint8. Bicubic, because a slice is read again
  between its texels when rendered, and two bilinear resamplings visibly soften the photo.
- Gutter filling (:func:`fill_gutter`): covered texels left without colour (face unlabelled, or a
  non-finite ξ) are filled first, from their coloured neighbours, ring by ring without a distance
  limit (inside charts only); then ``gutter_px`` rings of empty texels around the charts are
  filled the same way, so bilinear lookups and mip-maps do not bleed black. Each new texel is the
  mean of its already-filled 8-neighbours (a nearest-valid dilation). Beyond ``gutter_px`` the
  atlas stays black (0).
- :func:`label_colors` — a picture of a label map (each source frame its own colour, -1 black),
  as the paper's figures.

Cost
----
The covered texels are grouped by label with a counting sort, so each source image is read
**once per slice** and a sequence costs O(T * W^2) (the authors' ``Renderer.cpp`` renders
T^2 passes, ``official_code_notes.md`` §2.5). Per slice: one pass over the covered texels for the
lookup, plus one scan of the atlas and the rings for the gutter. Kernels are numba
``@njit(cache=True, nogil=True)`` (serial; slices are the unit of parallelism).

Label map
---------
The returned ``label_map`` (W, W) int32 holds the source frame each texel was sampled from;
-1 in the gutter, on empty texels, on texels of unlabelled faces and where ξ was not finite
(those are filled colours, not observations).
"""

from __future__ import annotations

import colorsys

import cv2
import numpy as np
from numba import njit

from stex.render import bilinear_taps

__all__ = ["TexelSampler", "volume_slice", "fill_gutter", "label_colors", "nearest_seen_texels",
           "write_volume"]


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _group_by_label(tex_face, labels, n_labels):
    """Counting sort of the covered texels by their label (labels -1..n_labels-1).

    Returns (texel label (N,) int32, order (N,) int32 texel positions grouped by label,
    start (n_labels + 2,) int64: group of label l is order[start[l + 1]:start[l + 2]])."""
    N = tex_face.shape[0]
    lab = np.empty(N, np.int32)
    counts = np.zeros(n_labels + 2, np.int64)
    for i in range(N):
        l = labels[tex_face[i]]
        if l < -1 or l >= n_labels:
            l = -1
        lab[i] = l
        counts[l + 2] += 1
    start = np.zeros(n_labels + 2, np.int64)
    for k in range(1, n_labels + 2):
        start[k] = start[k - 1] + counts[k]
    # start[l + 1] = first position of label l (l = -1 .. n_labels - 1)
    fill = start.copy()
    order = np.empty(N, np.int32)
    for i in range(N):
        k = lab[i] + 1
        order[fill[k]] = i
        fill[k] += 1
    return lab, order, start


@njit(cache=True, nogil=True)
def _texel_position(i, tex_face, tex_bary, faces, xi):
    """Image position (u, v) of covered texel ``i``: its barycentrics applied to ξ of its face."""
    f = tex_face[i]
    b0 = np.float64(tex_bary[i, 0])
    b1 = np.float64(tex_bary[i, 1])
    b2 = np.float64(tex_bary[i, 2])
    a0, a1, a2 = faces[f, 0], faces[f, 1], faces[f, 2]
    return (b0 * xi[a0, 0] + b1 * xi[a1, 0] + b2 * xi[a2, 0],
            b0 * xi[a0, 1] + b1 * xi[a1, 1] + b2 * xi[a2, 1])


@njit(cache=True, nogil=True)
def _sample_group(sel, tex_index, tex_face, tex_bary, faces, xi, img, out, ok):
    """Sample image ``img`` at the ξ-interpolated positions of the texels ``sel`` (positions in the
    compact covered-texel arrays); writes ``out`` (W*W, 3) uint8 and ``ok`` (W*W,) bool."""
    H, Wd, C = img.shape
    for j in range(sel.shape[0]):
        i = sel[j]
        u, v = _texel_position(i, tex_face, tex_bary, faces, xi)
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(u, v, Wd, H)
        t = tex_index[i]
        for k in range(3):
            val = np.float32(w00 * img[r0, c0, k] + w01 * img[r0, c1, k]
                             + w10 * img[r1, c0, k] + w11 * img[r1, c1, k])
            x = np.floor(val + np.float32(0.5))
            out[t, k] = np.uint8(min(max(x, 0.0), 255.0))
        ok[t] = True


@njit(cache=True, nogil=True)
def _group_positions(sel, tex_index, tex_face, tex_bary, faces, xi, pos, target):
    """The ξ-interpolated image positions of the texels ``sel``: ``pos`` (n, 2) float32 (u, v),
    NaN where ξ is not finite; ``target`` (n,) their flat atlas index."""
    for j in range(sel.shape[0]):
        i = sel[j]
        pos[j, 0], pos[j, 1] = _texel_position(i, tex_face, tex_bary, faces, xi)
        target[j] = tex_index[i]


def _sample_group_cubic(sel, tex_index, tex_face, tex_bary, faces, xi, img, out, ok):
    """Bicubic variant of :func:`_sample_group`: OpenCV's ``remap`` (INTER_CUBIC, a = -0.75,
    BORDER_REPLICATE: clamp-to-edge like the bilinear lookup; saturated to uint8)."""
    n = sel.shape[0]
    pos = np.empty((n, 2), np.float32)
    target = np.empty(n, np.int64)
    _group_positions(sel, tex_index, tex_face, tex_bary, faces, xi, pos, target)
    good = np.isfinite(pos).all(axis=1)
    if not good.any():
        return
    pos, target = pos[good], target[good]
    H, W = img.shape[:2]
    m = len(target)
    rows = -(-m // 1024)                 # remap's maps are 2-D, each side below 32768
    u = np.zeros(rows * 1024, np.float32)
    v = np.zeros(rows * 1024, np.float32)
    # clamp first, as the bilinear lookup does: remap's replicated border then only pads taps
    u[:m] = np.clip(pos[:, 0], 0, W - 1)
    v[:m] = np.clip(pos[:, 1], 0, H - 1)
    vals = cv2.remap(img, u.reshape(rows, 1024), v.reshape(rows, 1024), cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_REPLICATE)
    out[target] = vals.reshape(-1, 3)[:m]
    ok[target] = True


@njit(cache=True, nogil=True)
def _fill_rings(img, valid, allowed, frontier, max_rings):
    """Grow ``valid`` into ``allowed`` texels ring by ring (8-neighbourhood), starting from
    ``frontier`` (flat indices of the allowed, invalid texels next to a valid one); each new
    texel gets the mean of its neighbours valid before its ring. ``max_rings`` < 0: no limit.
    img (H, W, C) uint8 and valid (H, W) bool are modified in place. Returns texels filled."""
    H, W, C = img.shape
    mark = np.zeros((H, W), np.uint8)  # 1 = queued in the current frontier
    fr = frontier.copy()
    n = fr.shape[0]
    for j in range(n):
        mark[fr[j] // W, fr[j] % W] = 1
    total = 0
    ring = 0
    acc = np.zeros((max(n, 1), C), np.float32)
    while n > 0 and (max_rings < 0 or ring < max_rings):
        ring += 1
        if acc.shape[0] < n:
            acc = np.zeros((n, C), np.float32)
        for j in range(n):
            p = fr[j]
            r = p // W
            c = p - r * W
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            cnt = 0
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= H:
                    continue
                for dc in range(-1, 2):
                    cc = c + dc
                    if cc < 0 or cc >= W:
                        continue
                    if valid[rr, cc]:
                        s0 += img[rr, cc, 0]
                        s1 += img[rr, cc, 1]
                        s2 += img[rr, cc, 2]
                        cnt += 1
            acc[j, 0] = s0 / cnt + 0.5
            acc[j, 1] = s1 / cnt + 0.5
            acc[j, 2] = s2 / cnt + 0.5
        for j in range(n):
            p = fr[j]
            r = p // W
            c = p - r * W
            for k in range(C):
                img[r, c, k] = np.uint8(min(acc[j, k], 255.0))
            valid[r, c] = True
            mark[r, c] = 0
        total += n
        if max_rings >= 0 and ring >= max_rings:
            break
        # next frontier: allowed invalid neighbours of this ring
        m = 0
        nxt = np.empty(max(2 * n, 16), np.int64)
        for j in range(n):
            p = fr[j]
            r = p // W
            c = p - r * W
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= H:
                    continue
                for dc in range(-1, 2):
                    cc = c + dc
                    if cc < 0 or cc >= W:
                        continue
                    if valid[rr, cc] or not allowed[rr, cc] or mark[rr, cc]:
                        continue
                    if m == nxt.shape[0]:
                        tmp = np.empty(2 * m, np.int64)
                        tmp[:m] = nxt[:m]
                        nxt = tmp
                    nxt[m] = rr * W + cc
                    mark[rr, cc] = 1
                    m += 1
        fr = nxt
        n = m
    return total


def fill_gutter(image, valid, covered, gutter_px: int):
    """Fill texels without colour in place: first the covered ones (no distance limit, inside
    charts), then ``gutter_px`` rings of empty texels around the charts.

    Args:
        image: (W, W, 3) uint8, modified in place.
        valid: (W, W) bool, texels that hold a colour (not modified).
        covered: (W, W) bool, texels inside a chart (``texel_face >= 0``).
        gutter_px: rings of empty texels to fill (0: none).

    Returns:
        (filled_inside, filled_gutter): counts of texels filled.
    """
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (W, W, 3) uint8, got {image.shape} {image.dtype}")
    if not image.flags.c_contiguous:
        raise ValueError("image must be C-contiguous (it is filled in place)")
    v = np.array(valid, dtype=np.bool_, copy=True)
    cov = np.ascontiguousarray(covered, dtype=np.bool_)
    def frontier(allowed):
        near = cv2.dilate(v.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        return np.flatnonzero((allowed & ~v & near).ravel()).astype(np.int64)

    inside = 0
    if (cov & ~v).any() and v.any():
        inside = _fill_rings(image, v, cov, frontier(cov), -1)
    gutter = 0
    if gutter_px > 0 and v.any():
        gutter = _fill_rings(image, v, ~cov, frontier(~cov), int(gutter_px))
    return int(inside), int(gutter)


# --------------------------------------------------------------------------------------------
# slices
# --------------------------------------------------------------------------------------------

def _get(source, s):
    return source(s) if callable(source) else source[s]


class TexelSampler:
    """The atlas-side precomputation of :func:`volume_slice`, done once for the template.

    Args:
        texel_face: (W, W) int face id per texel, -1 = empty (template ``texel/face_id``).
        texel_bary: (W, W, 3) float barycentrics (template ``texel/bary``).
        faces: (F, 3) int vertex indices (template ``faces``): ξ arrays are indexed by vertex.
        interpolation: how a source image is read at a texel's position: ``"bicubic"`` (OpenCV
            INTER_CUBIC) or ``"bilinear"``. A texel's position falls between pixel centres, and a
            render reads the slice again between texels: bilinear interpolation at half a pixel
            averages two pixels, so an image textured and rendered that way is blurrier than the
            photo it came from (demo, Crete blur of the photos resampled at offsets within ±0.5 px:
            0.3531 → bilinear 0.3789, bicubic 0.3578; ``benchmarks/bench_blur_noise.py
            results/demo``).
    """

    INTERPOLATIONS = ("bicubic", "bilinear")

    def __init__(self, texel_face, texel_bary, faces, interpolation: str = "bicubic"):
        if interpolation not in self.INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {self.INTERPOLATIONS}, got {interpolation!r}")
        self.interpolation = interpolation
        tf = np.asarray(texel_face)
        if tf.ndim != 2 or tf.shape[0] != tf.shape[1]:
            raise ValueError(f"texel_face must be (W, W), got {tf.shape}")
        tb = np.asarray(texel_bary)
        if tb.shape != tf.shape + (3,):
            raise ValueError(f"texel_bary must be {tf.shape + (3,)}, got {tb.shape}")
        self.W = tf.shape[0]
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {self.faces.shape}")
        self.covered = tf >= 0
        self.index = np.flatnonzero(self.covered.ravel()).astype(np.int64)
        self.face = np.ascontiguousarray(tf.ravel()[self.index], dtype=np.int32)
        if len(self.face) and self.face.max() >= len(self.faces):
            raise ValueError("texel_face refers to faces beyond len(faces)")
        self.bary = np.ascontiguousarray(tb.reshape(-1, 3)[self.index], dtype=np.float32)

    def slice(self, labels_t, coords, images, gutter_px: int = 4, fill: bool = True):
        """One slice; see :func:`volume_slice` (same arguments and result). ``fill=False`` leaves
        texels without colour black (no :func:`fill_gutter`; partial textures need no fill)."""
        labels = np.ascontiguousarray(labels_t, dtype=np.int32)
        if labels.shape != (len(self.faces),):
            raise ValueError(f"labels_t must have shape ({len(self.faces)},), got {labels.shape}")
        W = self.W
        n_labels = int(labels.max()) + 1 if labels.size else 0
        lab, order, start = _group_by_label(self.face, labels, max(n_labels, 0))
        out = np.zeros((W * W, 3), np.uint8)
        ok = np.zeros(W * W, np.bool_)
        for l in range(n_labels):
            a, b = start[l + 1], start[l + 2]
            if b <= a:
                continue
            xi = np.ascontiguousarray(_get(coords, l), dtype=np.float64)
            if xi.ndim != 2 or xi.shape[1] != 2:
                raise ValueError(f"coords[{l}] must be (V, 2), got {xi.shape}")
            img = np.ascontiguousarray(_get(images, l))
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"images[{l}] must be (Hc, Wc, 3) uint8, got {img.shape} {img.dtype}")
            sample = _sample_group_cubic if self.interpolation == "bicubic" else _sample_group
            sample(order[a:b], self.index, self.face, self.bary, self.faces, xi, img, out, ok)
        label_map = np.full(W * W, -1, np.int32)
        sampled = ok[self.index]
        label_map[self.index[sampled]] = lab[sampled]
        image = out.reshape(W, W, 3)
        if fill:
            fill_gutter(image, ok.reshape(W, W), self.covered, gutter_px)
        return image, label_map.reshape(W, W)


def volume_slice(texel_face, texel_bary, faces, labels_t, coords, images, gutter_px: int = 4,
                 interpolation: str = "bicubic"):
    """The texture-volume slice of one target frame.

    Args:
        texel_face: (W, W) int32 face per texel, -1 = empty. texel_bary: (W, W, 3) float32.
        faces: (F, 3) int vertex indices.
        labels_t: (F,) int32 source frame of each face at this target frame, -1 = none. Labels
            index ``coords`` and ``images`` (local frame indices of the sequence).
        coords: ξ, per source frame s an (V, 2) float array of colour-pixel coordinates of the
            vertices (integer = pixel centre; NaN = not available): anything ``coords[s]`` works
            on (a (T, V, 2) array, a zarr array, a dict) or a callable ``coords(s)``.
        images: source frame s -> (Hc, Wc, 3) uint8 RGB colour image, likewise indexable or
            callable. Only the frames that occur in ``labels_t`` are read, each once.
        gutter_px: rings of empty texels around the charts to fill (see :func:`fill_gutter`).
        interpolation: "bicubic" or "bilinear" (see :class:`TexelSampler`).

    Returns:
        (slice (W, W, 3) uint8, label_map (W, W) int32; -1 where the colour is not sampled).

    For many slices of one atlas, build a :class:`TexelSampler` once and call its ``slice``.
    """
    return TexelSampler(texel_face, texel_bary, faces, interpolation).slice(labels_t, coords, images,
                                                                          gutter_px)


def label_colors(label_map) -> np.ndarray:
    """(W, W, 3) uint8 picture of a label map: source frame l in hue (l * golden ratio) mod 1
    with saturation/value varied by (l mod 3), so neighbouring frames get distinct colours;
    -1 (no label) black."""
    lm = np.asarray(label_map)
    out = np.zeros(lm.shape + (3,), np.uint8)
    valid = lm >= 0
    if not valid.any():
        return out
    n = int(lm.max()) + 1
    golden = 0.618033988749895
    pal = np.array([colorsys.hsv_to_rgb((k * golden) % 1.0, 0.5 + 0.2 * (k % 3), 1.0 - 0.15 * ((k // 3) % 3))
                    for k in range(n)]) * 255.0
    out[valid] = np.round(pal[lm[valid]]).astype(np.uint8)
    return out


# --------------------------------------------------------------------------------------------
# never-seen faces, the stage writer
# --------------------------------------------------------------------------------------------

def nearest_seen_texels(texel_face, texel_bary, vertices, faces, never_seen, k: int = 4):
    """Where the texels of never-seen faces take their colour from.

    The paper leaves faces that no frame sees black. stex colours each of their texels by
    inverse-distance weighting of the ``k`` nearest (3-D, template at rest) vertices of seen
    faces, each vertex represented by the seen texel nearest to it — a texture-space fill that
    also reaches charts without any seen texel, where a 2-D dilation inside the chart cannot.
    (A k-d tree over the seen *texels* is far slower: most never-seen texels lie far from the
    seen surface, and such queries visit a large part of a million-point tree.)

    Args:
        texel_face: (W, W) int face per texel (-1 empty); texel_bary: (W, W, 3).
        vertices: (V, 3) template vertices (m); faces: (F, 3).
        never_seen: (F,) bool.
        k: seen vertices blended per texel.

    Returns:
        (targets (n,) int64 flat texel indices, sources (n, k) int64 flat texel indices,
        weights (n, k) float32 summing to 1). Empty when every face is seen or none is.
    """
    from scipy.spatial import cKDTree

    tf = np.asarray(texel_face).ravel()
    ns = np.asarray(never_seen, bool)
    covered = tf >= 0
    face = np.where(covered, tf, 0)
    unseen = covered & ns[face]
    seen = covered & ~ns[face]
    if not unseen.any() or not seen.any():
        return np.zeros(0, np.int64), np.zeros((0, k), np.int64), np.zeros((0, k), np.float32)
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    bary = np.asarray(texel_bary, np.float64).reshape(-1, 3)

    def points(idx):
        return np.einsum("nk,nkd->nd", bary[idx], V[F[tf[idx]]])

    seen_texels = np.flatnonzero(seen)
    anchors = np.unique(F[~ns])                                  # vertices of seen faces
    _, rep = cKDTree(points(seen_texels)).query(V[anchors])      # their nearest seen texel
    dst = np.flatnonzero(unseen)
    kk = min(k, anchors.size)
    dist, near = cKDTree(V[anchors]).query(points(dst), k=kk)
    dist, near = dist.reshape(dst.size, kk), near.reshape(dst.size, kk)
    w = 1.0 / np.maximum(dist, 1e-6)
    w /= w.sum(axis=1, keepdims=True)
    return dst.astype(np.int64), seen_texels[rep[near]].astype(np.int64), w.astype(np.float32)


def write_volume(template_path, labels_path, coords_path, frames_paths, positions, params: dict,
                 out) -> None:
    """Volume stage for one block of frames: write a ``volume`` store.

    Args:
        template_path: ``template`` store (atlas, texel map).
        labels_path: ``labels`` store (labels [T, F], never_seen).
        coords_path: ``texcoords`` store (ξ) or ``projection`` store (Φ), as the observations.
        frames_paths: ``frames`` block stores (colour images).
        positions: [start, stop) sequence positions of the slices to write.
        params: the ``volume`` config section (gutter_px, image_cache, interpolation).
        out: path of the store.
    """
    import functools
    import logging
    import time

    from stex.config import section_params
    from stex.io import FrameSequence, create_store, open_store, position_range
    from stex.observations import open_coordinates

    log = logging.getLogger("stex.volume")
    p = section_params("volume", params)
    template = open_store(template_path, "template")
    labels_store = open_store(labels_path, "labels")
    ids = list(labels_store.attrs["frame_ids"])
    start, stop = position_range(positions, len(ids), "slice")
    faces = np.asarray(template["faces"][...], np.int64)
    labels = np.asarray(labels_store["labels"][start:stop], np.int32)
    if labels.shape[1] != len(faces):
        raise ValueError(f"{labels_path}: labels for {labels.shape[1]} faces, template has {len(faces)}")
    coords, _, _ = open_coordinates(coords_path)
    frames = FrameSequence(list(frames_paths), "frames")
    tf = template["texel/face_id"][...]
    tb = template["texel/bary"][...]
    sampler = TexelSampler(tf, tb, faces, p["interpolation"])
    never = np.asarray(labels_store["never_seen"][...], bool)
    dst, src, weight = nearest_seen_texels(tf, tb, template["vertices"][...], faces, never)
    gutter = int(p["gutter_px"])

    @functools.lru_cache(maxsize=int(p["image_cache"]))
    def image(l):  # consecutive slices mostly share their source frames
        return frames.read("color", ids[l])

    @functools.lru_cache(maxsize=int(p["image_cache"]))
    def xi(l):
        return np.asarray(coords[l], np.float64)

    W = sampler.W
    t0 = time.perf_counter()
    attrs = {"frame_ids": ids[start:stop], "first_position": start, "gutter_px": gutter,
             "never_seen_texels": int(dst.size)}
    with create_store(out, "volume", attrs=attrs, params=p) as store:
        a_tex = store.create("texture", (stop - start, W, W, 3))
        a_lab = store.create("label_map", (stop - start, W, W))
        for k in range(stop - start):
            tex, lm = sampler.slice(labels[k], xi, image, gutter_px=0)
            if dst.size:
                flat = tex.reshape(-1, 3)
                flat[dst] = np.round(np.einsum("nk,nkc->nc", weight, flat[src].astype(np.float32)))
            fill_gutter(tex, sampler.covered, sampler.covered, gutter)
            a_tex[k] = tex
            a_lab[k] = lm.astype(np.int16)
            log.info("volume: slice %d (%d/%d), %.2f s per slice", ids[start + k], k + 1,
                     stop - start, (time.perf_counter() - t0) / (k + 1))
