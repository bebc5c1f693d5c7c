"""Sampling images into the atlas's texels, shared by the volume, the dynamism, the observations
and the global texture.

What it computes
----------------
- :class:`TexelSampler` — the atlas-side precomputation of a texture slice. For every covered
  texel of the atlas (``texel/face_id`` >= 0 of the template store): its face f, the label
  l = ``labels_t[f]`` (the source frame chosen for f, -1 = none), the position of the texel on
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
- :func:`nearest_seen_texels` — where the texels of never-seen faces take their colour from.
- :func:`label_colors` — a picture of a label map (each source frame its own colour, -1 black),
  as the paper's figures.
- :func:`as_sampler`, :func:`checked_frame` — the argument checks shared by the callers that
  take "a sampler or the texel maps" and a per-frame ``load`` callable.

Cost
----
The (target frame, face) pairs are grouped by label and each face's texels are listed once per
atlas (stable argsorts), so each source frame's image and ξ are read **once per pass** of
several slices (:meth:`TexelSampler.sample`), not once per slice: a slice draws on most of the
sequence, and decoding its sources again for every slice dominated the cost
(docs/decisions/volume.md). A sequence costs O(T * W^2) (the authors' ``Renderer.cpp`` renders
T^2 passes, ``official_code_notes.md`` §2.5). Per slice: one pass over the covered texels for
the lookup, plus one scan of the atlas and the rings for the gutter. Kernels are numba
``@njit(cache=True, nogil=True)`` (serial; blocks are the unit of parallelism).
"""

from __future__ import annotations

import colorsys

import cv2
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from stex.render import bilinear_taps

__all__ = ["TexelSampler", "fill_gutter", "label_colors", "nearest_seen_texels", "as_sampler",
           "checked_frame"]


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------

def _group_by(keys, n_groups):
    """Positions of ``keys`` (n,) int in 0..n_groups-1 grouped by key (stable):
    (order (n,) int64, start (n_groups + 1,) int64); group g is ``order[start[g]:start[g + 1]]``."""
    order = np.argsort(keys, kind="stable")
    start = np.zeros(n_groups + 1, np.int64)
    np.cumsum(np.bincount(keys, minlength=n_groups), out=start[1:])
    return order, start


@njit(cache=True, nogil=True)
def _pair_positions(pair_slice, pair_face, face_start, face_texels, tex_bary, faces, xi, n_cov,
                    pos, target):
    """For every covered texel of the given (slice, face) pairs whose position is finite: its image
    position ``x = sum_k bary_k * xi[faces[f, k]]`` into ``pos`` (n, 2) (u, v) and its
    place ``slice * n_cov + texel`` in the (S, N) sample arrays into ``target``. Returns how many
    were written (texels whose ξ is not finite are skipped)."""
    j = 0
    for p in range(pair_face.shape[0]):
        f = pair_face[p]
        a0, a1, a2 = faces[f, 0], faces[f, 1], faces[f, 2]
        base = np.int64(pair_slice[p]) * n_cov
        for q in range(face_start[f], face_start[f + 1]):
            i = face_texels[q]
            b0 = np.float64(tex_bary[i, 0])
            b1 = np.float64(tex_bary[i, 1])
            b2 = np.float64(tex_bary[i, 2])
            pos[j, 0] = b0 * xi[a0, 0] + b1 * xi[a1, 0] + b2 * xi[a2, 0]
            pos[j, 1] = b0 * xi[a0, 1] + b1 * xi[a1, 1] + b2 * xi[a2, 1]
            if np.isfinite(pos[j, 0]) and np.isfinite(pos[j, 1]):  # in pos's own dtype
                target[j] = base + i
                j += 1
    return j


@njit(cache=True, nogil=True)
def _scatter(vals, target, colours, sampled):
    """``colours[target] = vals``, ``sampled[target] = True`` (numpy's fancy assignment of 3-byte
    rows is several times slower)."""
    for j in range(target.shape[0]):
        t = target[j]
        colours[t, 0] = vals[j, 0]
        colours[t, 1] = vals[j, 1]
        colours[t, 2] = vals[j, 2]
        sampled[t] = True


@njit(cache=True, nogil=True)
def _expand(index, face, labels_t, colours, sampled, image, ok, label_map):
    """Covered-texel samples of one slice to the atlas: ``image``/``ok``/``label_map`` (W*W, ...)
    get the colour, True and the face's label at ``index`` where ``sampled``."""
    for i in range(index.shape[0]):
        if sampled[i]:
            t = index[i]
            image[t, 0] = colours[i, 0]
            image[t, 1] = colours[i, 1]
            image[t, 2] = colours[i, 2]
            ok[t] = True
            label_map[t] = labels_t[face[i]]


@njit(cache=True, nogil=True)
def _lookup_bilinear(img, pos, vals):
    """Bilinear lookup of ``img`` (H, W, 3) uint8 at finite ``pos`` (n, 2), exactly as
    :func:`stex.render.sample_bilinear`, rounded to uint8 into ``vals`` (n, 3)."""
    H, Wd, C = img.shape
    for j in range(pos.shape[0]):
        r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(pos[j, 0], pos[j, 1], Wd, H)
        for k in range(3):
            val = np.float32(w00 * img[r0, c0, k] + w01 * img[r0, c1, k]
                             + w10 * img[r1, c0, k] + w11 * img[r1, c1, k])
            x = np.floor(val + np.float32(0.5))
            vals[j, k] = np.uint8(min(max(x, 0.0), 255.0))


def _lookup_bicubic(img, pos, vals):
    """OpenCV ``remap`` (INTER_CUBIC, a = -0.75, BORDER_REPLICATE: clamp-to-edge like the bilinear
    lookup; saturated to uint8) of ``img`` at finite ``pos`` (n, 2) into ``vals`` (n, 3)."""
    H, W = img.shape[:2]
    m = len(pos)
    rows = -(-m // 1024)                 # remap's maps are 2-D, each side below 32768
    u = np.zeros(rows * 1024, np.float32)
    v = np.zeros(rows * 1024, np.float32)
    # clamp first, as the bilinear lookup does: remap's replicated border then only pads taps
    u[:m] = np.clip(pos[:, 0], 0, W - 1)
    v[:m] = np.clip(pos[:, 1], 0, H - 1)
    out = cv2.remap(img, u.reshape(rows, 1024), v.reshape(rows, 1024), cv2.INTER_CUBIC,
                    borderMode=cv2.BORDER_REPLICATE)
    vals[:] = out.reshape(-1, 3)[:m]


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
    """The atlas-side precomputation of :func:`stex.volume.volume_slice`, done once for the template.

    Args:
        texel_face: (W, W) int face id per texel, -1 = empty (template ``texel/face_id``).
        texel_bary: (W, W, 3) float barycentrics (template ``texel/bary``).
        faces: (F, 3) int vertex indices (template ``faces``): ξ arrays are indexed by vertex.
        interpolation: how a source image is read at a texel's position: ``"bicubic"`` (OpenCV
            INTER_CUBIC) or ``"bilinear"``. A texel's position falls between pixel centres, and a
            render reads the slice again between texels: bilinear interpolation at half a pixel
            averages two pixels, so an image textured and rendered that way is blurrier than the
            photo it came from (measured in docs/decisions/volume.md).
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
        # the covered texels of face f: _face_texels[_face_start[f]:_face_start[f + 1]]
        order, self._face_start = _group_by(self.face, len(self.faces))
        self._face_texels = order.astype(np.int32)

    # texels looked up per call of the lookup kernel: bounds the position buffers (12 B a texel)
    CHUNK_TEXELS = 1 << 22

    def sample(self, labels, coords, images):
        """Colours of the covered texels for S target frames at once, each source frame's image
        and ξ read once for all S (a sequence's slices share most of their source frames).

        Args:
            labels: (S, F) int source frame of each face at each of the S target frames, -1 = none.
            coords, images: as in :func:`stex.volume.volume_slice`.

        Returns:
            (colours (S, N, 3) uint8, sampled (S, N) bool) over the N covered texels
            (``self.index`` gives their flat atlas positions); 0 / False where not sampled.
        """
        labels = np.ascontiguousarray(labels, dtype=np.int32)
        if labels.ndim != 2 or labels.shape[1] != len(self.faces):
            raise ValueError(f"labels must have shape (S, {len(self.faces)}), got {labels.shape}")
        S, N = labels.shape[0], len(self.index)
        colours = np.zeros((S * N, 3), np.uint8)
        sampled = np.zeros(S * N, np.bool_)
        n_labels = int(labels.max()) + 1 if labels.size else 0
        # the (slice, face) pairs of label l: pair_slice/pair_face[start[l]:start[l + 1]]
        pairs = np.flatnonzero(labels.ravel() >= 0)
        order, start = _group_by(labels.ravel()[pairs], max(n_labels, 0))
        pair_slice, pair_face = np.divmod(pairs[order], len(self.faces))
        per_pair = np.diff(self._face_start)[pair_face]
        # OpenCV's maps are float32; the bilinear lookup is stex.render's, in float64
        lookup, pos_dtype = ((_lookup_bicubic, np.float32) if self.interpolation == "bicubic"
                             else (_lookup_bilinear, np.float64))
        for l in range(n_labels):
            a, b = int(start[l]), int(start[l + 1])
            if b <= a:
                continue
            xi = np.ascontiguousarray(_get(coords, l), dtype=np.float64)
            if xi.ndim != 2 or xi.shape[1] != 2:
                raise ValueError(f"coords[{l}] must be (V, 2), got {xi.shape}")
            img = np.ascontiguousarray(_get(images, l))
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"images[{l}] must be (Hc, Wc, 3) uint8, got {img.shape} {img.dtype}")
            # split the pairs of this label so that no chunk holds more than CHUNK_TEXELS texels
            ends = np.cumsum(per_pair[a:b])
            cuts = np.searchsorted(ends, np.arange(self.CHUNK_TEXELS, ends[-1], self.CHUNK_TEXELS),
                                   side="right")
            for p0, p1 in zip(np.r_[0, cuts] + a, np.r_[cuts, b - a] + a):
                n = int(per_pair[p0:p1].sum())
                if n == 0:
                    continue
                pos = np.empty((n, 2), pos_dtype)
                target = np.empty(n, np.int64)
                m = _pair_positions(pair_slice[p0:p1], pair_face[p0:p1], self._face_start,
                                    self._face_texels, self.bary, self.faces, xi, N, pos, target)
                if m == 0:
                    continue
                vals = np.empty((m, 3), np.uint8)
                lookup(img, pos[:m], vals)
                _scatter(vals, target[:m], colours, sampled)
        return colours.reshape(S, N, 3), sampled.reshape(S, N)

    def slices(self, labels, coords, images, gutter_px: int = 4, fill: bool = True):
        """The slices of S target frames, sampled together (:meth:`sample`), one at a time.

        Args:
            labels: (S, F) int, one row per target frame; coords, images, gutter_px as in
                :func:`stex.volume.volume_slice`; ``fill`` as in :meth:`slice`.

        Yields:
            (slice (W, W, 3) uint8, label_map (W, W) int32) per target frame, in order.
        """
        labels = np.asarray(labels)
        colours, sampled = self.sample(labels, coords, images)
        W = self.W
        for k in range(len(colours)):
            image = np.zeros((W * W, 3), np.uint8)
            ok = np.zeros(W * W, np.bool_)
            label_map = np.full(W * W, -1, np.int32)
            _expand(self.index, self.face, np.ascontiguousarray(labels[k], dtype=np.int32),
                    colours[k], sampled[k], image, ok, label_map)
            image = image.reshape(W, W, 3)
            if fill:
                fill_gutter(image, ok.reshape(W, W), self.covered, gutter_px)
            yield image, label_map.reshape(W, W)

    def slice(self, labels_t, coords, images, gutter_px: int = 4, fill: bool = True):
        """One slice; see :func:`stex.volume.volume_slice` (same arguments and result). ``fill=False`` leaves
        texels without colour black (no :func:`fill_gutter`; partial textures need no fill)."""
        labels = np.asarray(labels_t)
        if labels.shape != (len(self.faces),):
            raise ValueError(f"labels_t must have shape ({len(self.faces)},), got {labels.shape}")
        return next(self.slices(labels[None], coords, images, gutter_px, fill))



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
# never-seen faces
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _corner_texels(texel_face, texel_bary, vertices, faces, seen_face):
    """Per seen face and corner, the face's texel nearest (3-D) to that corner: (F, 3) int64 flat
    texel indices, -1 for faces without texels and faces not seen."""
    best = np.full((faces.shape[0], 3), np.inf)
    texel = np.full((faces.shape[0], 3), -1, np.int64)
    for t in range(texel_face.shape[0]):
        f = texel_face[t]
        if f < 0 or not seen_face[f]:
            continue
        p = np.zeros(3)
        for k in range(3):
            for d in range(3):
                p[d] += texel_bary[t, k] * vertices[faces[f, k], d]
        for k in range(3):
            dist = 0.0
            for d in range(3):
                dist += (p[d] - vertices[faces[f, k], d]) ** 2
            if dist < best[f, k]:
                best[f, k] = dist
                texel[f, k] = t
    return texel


def nearest_seen_texels(texel_face, texel_bary, vertices, faces, never_seen, k: int = 4):
    """Where the texels of never-seen faces take their colour from.

    The paper leaves faces that no frame sees black. stex colours each of their texels by
    inverse-distance weighting of the ``k`` nearest (3-D, template at rest) vertices of seen
    faces, each vertex represented by the seen texel nearest to it — a texture-space fill that
    also reaches charts without any seen texel, where a 2-D dilation inside the chart cannot.
    A vertex's nearest seen texel is searched among each seen face's texel nearest to each of its
    corners (three per face): the nearest texel of all lies, but for folds finer than a texel,
    in a face around the vertex, and the search then needs no tree over millions of texels
    (docs/decisions/volume.md). (A k-d tree over the seen *texels*
    for the never-seen ones is far slower still: most never-seen texels lie far from the seen
    surface, and such queries visit a large part of a million-point tree.)

    Args:
        texel_face: (W, W) int face per texel (-1 empty); texel_bary: (W, W, 3).
        vertices: (V, 3) template vertices (m); faces: (F, 3).
        never_seen: (F,) bool.
        k: seen vertices blended per texel.

    Returns:
        (targets (n,) int64 flat texel indices, sources (n, k) int64 flat texel indices,
        weights (n, k) float32 summing to 1). Empty when every face is seen or none is. The
        ``harmonic`` fill (:class:`stex.fill.SeamFill`) starts from this one.
    """
    tf = np.ascontiguousarray(np.asarray(texel_face).ravel(), dtype=np.int32)
    ns = np.asarray(never_seen, bool)
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    covered = tf >= 0
    unseen = covered & ns[np.where(covered, tf, 0)]
    corner = _corner_texels(tf, np.ascontiguousarray(np.asarray(texel_bary).reshape(-1, 3), dtype=np.float32),
                            V, F, ~ns)
    candidates = np.unique(corner[corner >= 0])                  # seen texels near a corner
    if not unseen.any() or not candidates.size:
        return np.zeros(0, np.int64), np.zeros((0, k), np.int64), np.zeros((0, k), np.float32)
    bary = np.asarray(texel_bary).reshape(-1, 3)

    def points(idx):
        return np.einsum("nk,nkd->nd", bary[idx].astype(np.float64), V[F[tf[idx]]])

    anchors = np.unique(F[~ns])                                  # vertices of seen faces
    _, rep = cKDTree(points(candidates)).query(V[anchors])       # their nearest seen texel
    dst = np.flatnonzero(unseen)
    kk = min(k, anchors.size)
    dist, near = cKDTree(V[anchors]).query(points(dst), k=kk)
    dist, near = dist.reshape(dst.size, kk), near.reshape(dst.size, kk)
    w = 1.0 / np.maximum(dist, 1e-6)
    w /= w.sum(axis=1, keepdims=True)
    return dst.astype(np.int64), candidates[rep[near]].astype(np.int64), w.astype(np.float32)


# --------------------------------------------------------------------------------------------
# argument checks shared by the samplers' callers
# --------------------------------------------------------------------------------------------

def as_sampler(sampler_or_maps) -> TexelSampler:
    """A :class:`TexelSampler` from either a sampler (returned as is) or a tuple
    (texel_face (W, W) int, texel_bary (W, W, 3) float, faces (F, 3) int); ValueError otherwise."""
    if isinstance(sampler_or_maps, TexelSampler):
        return sampler_or_maps
    try:
        texel_face, texel_bary, faces = sampler_or_maps
    except (TypeError, ValueError):
        raise ValueError("sampler_or_maps must be a stex.sampling.TexelSampler or a tuple "
                         "(texel_face (W, W), texel_bary (W, W, 3), faces (F, 3))") from None
    return TexelSampler(texel_face, texel_bary, faces)


def checked_frame(load, t, n_faces):
    """``load(t)`` checked: (image, xi_t, face_visible_t (n_faces,) bool); ValueError naming the
    frame when ``load`` returns something else."""
    out = load(t)
    try:
        image, xi, vis = out
    except (TypeError, ValueError):
        raise ValueError(f"load({t}) must return (image, xi_t, face_visible_t)") from None
    vis = np.asarray(vis)
    if vis.shape != (n_faces,):
        raise ValueError(f"frame {t}: face_visible_t must have shape ({n_faces},), got {vis.shape}")
    return image, xi, vis.astype(np.bool_, copy=False)
