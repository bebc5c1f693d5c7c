"""Geometric similarity between frames: E_glo (depth renders) and E_loc (SHOT descriptors).

The data term of the labeling (paper §"Data Term") prefers source frames l whose shape is close
to the target frame t's: E_geo = ω_g E_glo + (1 − ω_g) E_loc, ω_g = 0.9.

E_glo — global similarity (:func:`global_similarity`)
-----------------------------------------------------
For target t and source l, render K_{t→l}(M_t) (frame t's mesh moved rigidly onto frame l) and
M_l in the depth camera (all frames share it; the object moves) and average, over the **union**
of the two silhouettes, the clipped depth difference min(clip, |D_a − D_b|). A pixel covered by
only one silhouette counts as the clip (the authors' code renders background as depth 0, so
|Δ| = the depth, ≫ clip). The mean is divided by the clip, so E_glo lies in [0, 1] and the step
function / weighting applied later is scale-free; the diagonal is 0.

Choices, deliberately:

- ``clip_m = 0.1`` by default, the authors' ``simcheck.py``. The paper's Eq. geo_global writes
  min(1, ·), which in metres never bites (a silhouette mismatch would then weigh ~1.5, the
  object's distance, not a fixed penalty). 0.1 m is larger than the depth differences a
  deformation causes (centimetres), so those stay graded, while a silhouette mismatch is the
  maximum penalty.
- The denominator is the union of the silhouettes, as the paper says. The authors' code divides
  by the number of pixels where the two depths *differ* (``mask = d > 0``), which drops pixels
  where both meshes agree exactly and so inflates the mean; stex follows the paper.
- An empty union (both meshes outside the image) gives 0, as in the authors' code.
- ``scale`` renders at a fraction of the depth resolution (``Intrinsics.scaled``): the renders
  dominate the stage, one per (target, source) pair, T² without candidate pruning
  (``sources``, :mod:`stex.pruning`). Renders of M_l in its own camera are made once per call,
  only for the sources some row names, and shared by all target rows.

E_loc — local similarity (:func:`stex.shot.geodesic_neighbourhoods`, :func:`stex.shot.shot_descriptors`,
:func:`local_similarity_faces`, :func:`local_similarity_triples`)
----------------------------------------------------------------------------------------------
E_loc(t, f, l) = −(1/3) Σ_j med_j(t, l) over the face's three vertices, where med_j is the
median over the vertex's ``median_hops``-ring of the per-vertex similarity τ_u(t)·τ_u(l) of
SHOT descriptors (Tombari et al. 2010). Values lie in [−1, 0] (SHOT histograms are
non-negative and unit length); −1 means identical local shape.

- **Neighbourhoods are geodesic** (the paper: "we exploit the geodesic distance"): a bounded
  Dijkstra on the template's edge graph, computed once and reused for every frame (the topology
  is fixed); positions and normals come from each frame. A neighbour counts for a frame's
  descriptor only while it lies within the support radius R in that frame (SHOT's spherical
  support), so a stretched region loses neighbours and a bent one keeps them. Edge-graph
  distances overestimate the true geodesic a little (docs/decisions/similarity.md).
- **SHOT as in the reference implementation** (Tombari's code, as in PCL
  ``SHOTEstimation::interpolateSingleChannel``): local reference frame from the covariance of
  the neighbours around the vertex weighted by (R − d); x = largest eigenvector, signed by the
  majority of neighbours (tie broken by the (R − d)-weighted sum); 32 volumes (8 azimuth × 2
  elevation × 2 radial) × 11 bins of cos(neighbour normal, z); the reference code's linear
  interpolation into the neighbouring cosine bin, radial shell, elevation and azimuth volume;
  unit L2 norm. **Difference**: z (the smallest eigenvector) is signed by the mesh's own vertex
  normal instead of a majority vote: the template is consistently oriented, and on a nearly
  flat patch SHOT's z vote is an almost-tie that flips at random. A vertex with fewer than 3
  neighbours in its support gets an all-zero descriptor (similarity 0 with everything).
- **Median filtering of the similarities, not of the descriptors.** The paper says it filters
  "SHOT descriptor values"; the authors' binary filters the similarity table over 2 hops (usage
  string ``m``). stex filters similarities: a per-bin median of sparse histograms is mostly
  zeros and no longer a unit descriptor, filtering 352 values per vertex and frame costs ~352×
  more than one value per vertex and frame pair, and the filter is applied only to the pairs
  actually needed. ``median_hops = 0`` switches it off.
- **Similarity = dot product** of unit descriptors (the cosine similarity); the authors'
  measure is not recoverable from their binary (``official_code_notes.md`` §2.3). It is
  symmetric, 1 for identical descriptors and what the paper's "τ_j · τ_j'" writes.
- **Memory / streaming**: descriptors are (T, V, 352) — 3.7 GB in float32 at 10k vertices and
  265 frames, 1.9 GB in float16, which changes E_loc little (docs/decisions/similarity.md). The E_loc
  functions accept any array-like indexed by
  frame (numpy, zarr; float16, float32 or float64). They hold the targets of a call in chunks
  of ``target_chunk`` frames and load each source frame once per chunk, as float32 (numba has
  no float16; float16 is widened by a bit-exact numba kernel, ~3x faster than numpy's), so
  memory is (target_chunk + 1) × V × D × 4 bytes (+ the caller's table) whatever T is. The
  workflow calls them per block of target frames.

E_str — local strain (:func:`face_strain`, :func:`strain_similarity`; not in the paper)
------------------------------------------------------------------------------------------
E_str(t, f, l) = min(1, ‖s_f(t) − s_f(l)‖₁ / clip) ∈ [0, 1], where s_f(t) is the log stretch of
face f's three edges at frame t relative to the template (ln |e_k(t)| − ln |e_k(rest)|), averaged
``rings`` times over the faces sharing a vertex. The paper's premise is "similar shape, similar
texture"; SHOT describes the *orientation* of the surface around a vertex (normals), which a
bend changes little on the convex side and a compression not at all, while folds and wrinkles
of cloth and skin follow how the surface is *compressed or stretched*. Only differences
s_f(t) − s_f(l) enter, so the rest shape cancels; the smoothing averages the tracking noise of
single edges out. The tracked mesh gives s_f(t) also where the camera does not see f at t,
which is where the data term matters most (the source of a face unseen at t is chosen by shape
alone); on the demo it chooses better sources for the faces unseen at t than E_glo and E_loc
(docs/decisions/similarity.md).

Conventions: vertices in metres in depth-camera coordinates; poses 4x4 float64 with
poses[t, l] mapping frame t's vertices onto frame l (x' = R x + t, :mod:`stex.poses`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
from numba import njit

from stex.camera import Intrinsics
from stex.render import project_vertices, raster_kernel
from stex.shot import check_faces, check_neighbourhoods, check_vertices, mesh_edges, positive

__all__ = [
    "global_similarity",
    "vertex_rings",
    "vertex_similarity",
    "median_filter_vertices",
    "local_similarity_faces",
    "local_similarity_triples",
    "face_strain",
    "strain_similarity",
    "strain_noise",
]



# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------

def _check_frames_vertices(vertices) -> np.ndarray:
    X = np.asarray(vertices)
    if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] == 0 or X.shape[1] == 0:
        raise ValueError(f"vertices must have shape (T, V, 3) with T, V > 0, got {X.shape}")
    X = np.ascontiguousarray(X, dtype=np.float64)
    bad = ~np.isfinite(X).all(axis=2)
    if bad.any():
        t, v = np.argwhere(bad)[0]
        raise ValueError(f"vertices contain non-finite coordinates: frame {t}, vertex {v}"
                         f" ({int(bad.sum())} bad vertices in total)")
    return X


def _check_poses(poses, n_frames: int) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.shape != (n_frames, n_frames, 4, 4):
        raise ValueError(f"poses must have shape (T, T, 4, 4) = ({n_frames}, {n_frames}, 4, 4), "
                         f"got {P.shape}")
    bad = ~np.isfinite(P).all(axis=(2, 3)) | (np.abs(P[:, :, 3] - [0, 0, 0, 1]) > 1e-9).any(axis=2)
    if bad.any():
        t, l = np.argwhere(bad)[0]
        raise ValueError(f"poses[{t}, {l}] is not a finite rigid 4x4 transform (last row must be "
                         f"0 0 0 1): {P[t, l].tolist()}")
    return np.ascontiguousarray(P)


def _check_frame_ids(ids, n_frames: int, name: str) -> np.ndarray:
    a = np.asarray(ids)
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be a 1-D integer array of frame indices, got "
                         f"shape {a.shape} dtype {a.dtype}")
    a = a.astype(np.int64)
    bad = (a < 0) | (a >= n_frames)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{i}] = {a[i]} is not a frame index in [0, {n_frames})")
    return a


def _threads(threads) -> int:
    n = int(threads) if threads is not None else 1
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {threads!r}")
    return n


# --------------------------------------------------------------------------------------------
# E_glo
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _image_box(px, py, iz, W, H, box):
    """Pixel box [r0, r1) x [c0, c1) holding every pixel the rasteriser can write for vertices
    projected to (px, py) (iz = 0: behind the near plane, never drawn); empty -> r0 = r1 = 0."""
    xmin, xmax, ymin, ymax = np.inf, -np.inf, np.inf, -np.inf
    for i in range(px.shape[0]):
        if iz[i] != 0.0:
            xmin = min(xmin, px[i])
            xmax = max(xmax, px[i])
            ymin = min(ymin, py[i])
            ymax = max(ymax, py[i])
    c0 = int(max(np.ceil(xmin), 0.0)) if xmin <= W - 1.0 else W
    c1 = int(min(np.floor(xmax), W - 1.0)) + 1 if xmax >= 0.0 else 0
    r0 = int(max(np.ceil(ymin), 0.0)) if ymin <= H - 1.0 else H
    r1 = int(min(np.floor(ymax), H - 1.0)) + 1 if ymax >= 0.0 else 0
    if c0 >= c1 or r0 >= r1:
        box[0] = box[1] = box[2] = box[3] = 0
    else:
        box[0], box[1], box[2], box[3] = r0, r1, c0, c1


@njit(cache=True, nogil=True)
def _render_own(X, frames, F, K, near, own, boxes):
    """own[s] = depth of frame frames[s]'s mesh; boxes[s] = its pixel box (r0, r1, c0, c1)."""
    S, H, W = own.shape
    nv = X.shape[1]
    fid = np.empty((H, W), np.int32)
    bary = np.empty((H, W, 3), np.float32)
    px = np.empty(nv)
    py = np.empty(nv)
    iz = np.empty(nv)
    for s in range(S):
        l = frames[s]
        raster_kernel(X[l], F, K, near, own[s], fid, bary)  # only depth is read; own[s] starts at 0
        project_vertices(X[l], K, near, px, py, iz)
        _image_box(px, py, iz, W, H, boxes[s])


@njit(cache=True, nogil=True)
def _global_row(Xt, poses_t, cols, slot, t, F, K, near, own, boxes, clip, depth, fid, bary, out):
    """out[j] = E_glo(t, cols[j]) for the sources cols (-1: padding, 1); poses_t[j] =
    K_{t→cols[j]}; slot[l] = the row of frame l in own / boxes. depth must be all 0 on entry
    (left all 0)."""
    S, H, W = own.shape
    nv = Xt.shape[0]
    Y = np.empty((nv, 3))
    px = np.empty(nv)
    py = np.empty(nv)
    iz = np.empty(nv)
    box = np.zeros(4, np.int64)
    for j in range(cols.shape[0]):
        l = cols[j]
        if l < 0:
            out[j] = 1.0
            continue
        if l == t:
            out[j] = 0.0
            continue
        P = poses_t[j]
        for i in range(nv):
            x, y, z = Xt[i, 0], Xt[i, 1], Xt[i, 2]
            for k in range(3):
                Y[i, k] = P[k, 0] * x + P[k, 1] * y + P[k, 2] * z + P[k, 3]
        raster_kernel(Y, F, K, near, depth, fid, bary)
        project_vertices(Y, K, near, px, py, iz)
        _image_box(px, py, iz, W, H, box)
        ob = boxes[slot[l]]
        # union of the two boxes (an empty box has r0 = r1)
        if box[0] == box[1]:
            r0, r1, c0, c1 = ob[0], ob[1], ob[2], ob[3]
        elif ob[0] == ob[1]:
            r0, r1, c0, c1 = box[0], box[1], box[2], box[3]
        else:
            r0, r1 = min(box[0], ob[0]), max(box[1], ob[1])
            c0, c1 = min(box[2], ob[2]), max(box[3], ob[3])
        D = own[slot[l]]
        s = 0.0
        n = 0
        for r in range(r0, r1):
            for c in range(c0, c1):
                a = depth[r, c]
                b = D[r, c]
                if a > 0.0 and b > 0.0:
                    s += min(clip, abs(np.float64(a) - np.float64(b)))
                    n += 1
                elif a > 0.0 or b > 0.0:
                    s += clip
                    n += 1
        out[j] = s / (n * clip) if n > 0 else 0.0
        for r in range(box[0], box[1]):  # reset what this render wrote
            for c in range(box[2], box[3]):
                depth[r, c] = 0.0


def global_similarity(vertices, faces, poses, K, width, height, targets=None, clip_m: float = 0.1,
                      scale: float = 1.0, threads: int = 1, near: float = 1e-3,
                      sources=None) -> np.ndarray:
    """E_glo: clipped depth difference of the rigidly aligned meshes, for target rows × sources.

    Args:
        vertices: (T, V, 3) float tracked vertices of every frame, metres, depth-camera coordinates
            (a zarr array is read whole: T·V·3 values).
        faces: (F, 3) int vertex indices.
        poses: without ``sources``, (T, T, 4, 4) float64 with poses[t, l] mapping frame t's mesh
            onto frame l (x' = R x + t); with ``sources``, (n, N, 4, 4): poses[i, j] =
            K_{targets[i]→sources[i, j]} (any value at padding).
        K: (3, 3) depth camera matrix (pixels) for a ``width`` x ``height`` image.
        targets: (n,) int target frames (rows); None = all T frames.
        clip_m: the clip of the per-pixel depth difference, metres (module docstring).
        scale: render at this fraction of the depth resolution (0.5 = half width and height),
            with :meth:`stex.camera.Intrinsics.scaled`.
        threads: worker threads over target rows (numba kernels release the GIL).
        near: near plane of the renders, metres.
        sources: (n, N) int source frames of each row (-1 padding; candidate pruning,
            :mod:`stex.pruning`); None = every frame 0..T-1. Only the frames named are rendered.

    Returns:
        (n, N) float32 in [0, 1] (N = T without ``sources``): row i, column j = mean over the
        union of the silhouettes of K_{t→l}(M_t) and M_l in the depth camera of
        min(clip, |ΔD|) / clip (a pixel in only one silhouette counts 1), t = targets[i],
        l = sources[i, j] (or j); 0 at l = t and where the union is empty, 1 at padding.
    """
    X = _check_frames_vertices(vertices)
    T, nv = X.shape[:2]
    F = check_faces(faces, nv)
    clip = positive(clip_m, "clip_m")
    scale = positive(scale, "scale")
    near = positive(near, "near")
    n_threads = _threads(threads)
    tg = np.arange(T, dtype=np.int64) if targets is None else _check_frame_ids(targets, T, "targets")
    if sources is None:
        P = _check_poses(poses, T)[tg]
        cols = np.broadcast_to(np.arange(T, dtype=np.int64), (tg.size, T))
    else:
        cols = np.asarray(sources, np.int64)
        if cols.ndim != 2 or cols.shape[0] != tg.size:
            raise ValueError(f"sources must be (n, N) with n = {tg.size} targets, got {cols.shape}")
        if cols.size and (cols.max() >= T or cols.min() < -1):
            raise ValueError(f"sources hold frames outside [-1, {T})")
        P = np.asarray(poses, np.float64)
        if P.shape != cols.shape + (4, 4):
            raise ValueError(f"poses must be (n, N, 4, 4) = {cols.shape + (4, 4)} with sources, got {P.shape}")
        P = np.where((cols >= 0)[..., None, None], P, np.eye(4))
        bad = ~np.isfinite(P).all(axis=(2, 3)) | (np.abs(P[:, :, 3] - [0, 0, 0, 1]) > 1e-9).any(axis=2)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(f"poses[{i}, {j}] (target {int(tg[i])}, source {int(cols[i, j])}) is not "
                             f"a finite rigid 4x4 transform: {P[i, j].tolist()}")
    intr = Intrinsics(np.asarray(K, dtype=np.float64), width, height)
    if not np.allclose(intr.K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"camera matrix K must have last row (0, 0, 1), got {intr.K.tolist()}")
    if scale != 1.0:
        intr = intr.scaled(scale)
    H, W = intr.height, intr.width
    Kc = np.ascontiguousarray(intr.K)

    frames = np.unique(cols[cols >= 0])              # the frames rendered in their own pose
    slot = np.full(T, -1, np.int64)
    slot[frames] = np.arange(frames.size)
    own = np.zeros((frames.size, H, W), np.float32)
    boxes = np.zeros((frames.size, 4), np.int64)
    _render_own(X, frames, F, Kc, near, own, boxes)
    cols = np.ascontiguousarray(cols)
    P = np.ascontiguousarray(P)

    out = np.zeros(cols.shape, np.float32)

    def work(rows):
        depth = np.zeros((H, W), np.float32)
        fid = np.empty((H, W), np.int32)
        bary = np.empty((H, W, 3), np.float32)
        row = np.empty(cols.shape[1], np.float64)
        for i in rows:
            t = int(tg[i])
            _global_row(X[t], P[i], cols[i], slot, t, F, Kc, near, own, boxes, clip, depth, fid,
                        bary, row)
            out[i] = row

    chunks = [c for c in np.array_split(np.arange(tg.size), n_threads) if c.size]
    if len(chunks) <= 1:
        for c in chunks:
            work(c)
    else:
        with ThreadPoolExecutor(max_workers=len(chunks)) as ex:
            list(ex.map(work, chunks))
    return out


# --------------------------------------------------------------------------------------------
# neighbourhoods
# --------------------------------------------------------------------------------------------

def vertex_rings(faces, n_vertices: int, hops: int) -> tuple[np.ndarray, np.ndarray]:
    """The k-ring of every vertex (vertices at most ``hops`` edges away, itself included).

    Args:
        faces: (F, 3) int. n_vertices: V. hops: k >= 0 (0 -> each vertex alone).

    Returns:
        ptr (V + 1,) int64 and idx (N,) int64 in CSR form, each ring sorted by vertex index.
    """
    n = int(n_vertices)
    if n <= 0:
        raise ValueError(f"n_vertices must be positive, got {n_vertices!r}")
    F = check_faces(faces, n)
    if int(hops) != hops or hops < 0:
        raise ValueError(f"hops must be a non-negative integer, got {hops!r}")
    e = mesh_edges(F)
    A = sp.coo_matrix((np.ones(2 * len(e), np.int8), (np.concatenate([e[:, 0], e[:, 1]]),
                                                     np.concatenate([e[:, 1], e[:, 0]]))),
                      shape=(n, n)).tocsr() + sp.identity(n, dtype=np.int8, format="csr")
    A.data[:] = 1
    R = sp.identity(n, dtype=np.int8, format="csr")
    for _ in range(int(hops)):
        R = R @ A
        R.data[:] = 1  # keep the pattern only (counts would overflow int8)
    R.sort_indices()
    return R.indptr.astype(np.int64), R.indices.astype(np.int64)


# --------------------------------------------------------------------------------------------
# E_loc
# --------------------------------------------------------------------------------------------

def vertex_similarity(desc_a, desc_b) -> np.ndarray:
    """Per-vertex similarity of two frames' descriptors: the dot product τ_a · τ_b.

    Args:
        desc_a, desc_b: (V, D) float16/float32/float64 unit descriptors.

    Returns:
        (V,) float32 in [0, 1] for SHOT (non-negative unit histograms); 0 for a zero descriptor.
    """
    a = np.asarray(desc_a)
    b = np.asarray(desc_b)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"descriptors must be two (V, D) arrays of one shape, got {a.shape} and {b.shape}")
    return np.einsum("vd,vd->v", a.astype(np.float32, copy=False),
                     b.astype(np.float32, copy=False)).astype(np.float32)


@njit(cache=True, nogil=True, inline="always")
def _median(buf, n):
    """Median of buf[:n] (sorted in place; n >= 1); the mean of the middle two for even n."""
    for i in range(1, n):  # insertion sort: rings hold ~20 values
        x = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > x:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = x
    h = n // 2
    if n % 2 == 1:
        return buf[h]
    return 0.5 * (buf[h - 1] + buf[h])


@njit(cache=True, nogil=True)
def _median_kernel(values, rptr, ridx, out):
    buf = np.empty(max(1, int(np.max(rptr[1:] - rptr[:-1]))), np.float64)
    for k in range(values.shape[0]):
        for v in range(values.shape[1]):
            n = 0
            for q in range(rptr[v], rptr[v + 1]):
                buf[n] = values[k, ridx[q]]
                n += 1
            out[k, v] = _median(buf, n)


def median_filter_vertices(values, rings) -> np.ndarray:
    """Median of per-vertex values over each vertex's ring.

    Args:
        values: (V,) or (n, V) float per-vertex values (n independent rows).
        rings: (ptr, idx) from :func:`vertex_rings` (every ring non-empty).

    Returns:
        float32 array of the shape of ``values``: out[..., v] = median of values[..., ring(v)]
        (mean of the middle two for an even count, as ``np.median``).
    """
    a = np.asarray(values, dtype=np.float64)
    squeeze = a.ndim == 1
    a2 = np.ascontiguousarray(a[None] if squeeze else a)
    if a2.ndim != 2:
        raise ValueError(f"values must be (V,) or (n, V), got shape {a.shape}")
    rptr, ridx = _check_rings(rings, a2.shape[1])
    out = np.empty(a2.shape, np.float64)
    _median_kernel(a2, rptr, ridx, out)
    out = out.astype(np.float32)
    return out[0] if squeeze else out


def _check_rings(rings, n_vertices):
    ptr, idx = check_neighbourhoods(rings, n_vertices)
    if (np.diff(ptr) == 0).any():
        v = int(np.flatnonzero(np.diff(ptr) == 0)[0])
        raise ValueError(f"rings must be non-empty: vertex {v} has none")
    return ptr, idx


@njit(cache=True, nogil=True)
def _half_bits_to_float(h, out):
    """float16 bit patterns (uint16, any shape, C order) -> float32 values (out: uint32 bits).

    numpy's float16 -> float32 conversion at every frame load of a target block would rival
    the E_loc kernels (docs/decisions/similarity.md); this is the classic shift and
    rescale (exact for normals and subnormals), vectorised by LLVM. Inf / NaN map to NaN."""
    hf = h.ravel()
    ob = out.ravel()
    of = ob.view(np.float32)
    for i in range(hf.shape[0]):
        # the magnitude bits << 13 are the float32 with the same mantissa and exponent - 112
        ob[i] = (np.uint32(hf[i]) & np.uint32(0x7FFF)) << np.uint32(13)
    for i in range(hf.shape[0]):
        x = hf[i]
        if (x & 0x7FFF) >= 0x7C00:
            of[i] = np.nan  # inf / NaN: caught by the kernels' finiteness test
        else:
            v = of[i] * np.float32(5.192296858534828e33)  # 2^112
            of[i] = -v if (x & 0x8000) else v


# reassociation lets LLVM vectorise the 352-term sum; no nnan/ninf, so the finiteness test of
# the callers stays valid
@njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _dot(a, b):
    s = np.float32(0.0)
    for d in range(a.shape[0]):
        s += a[d] * b[d]
    return s


@njit(cache=True, nogil=True, inline="always")
def _vertex_median(v, dt, dl, s, rptr, ridx, sim, sim_stamp, buf):
    """Median over the ring of v of the similarities of dt and dl, memoised per stamp s.
    Returns NaN when a similarity is not finite (non-finite descriptor values)."""
    n = 0
    bad = False
    for q in range(rptr[v], rptr[v + 1]):
        u = ridx[q]
        if sim_stamp[u] != s:
            sim[u] = _dot(dt[u], dl[u])
            sim_stamp[u] = s
        x = sim[u]
        if not (x == x and abs(x) < np.inf):
            bad = True
        buf[n] = x
        n += 1
    if bad:
        return np.nan
    return _median(buf, n)


@njit(cache=True, nogil=True)
def _loc_faces_kernel(dl, dts, slots, rows, F, rptr, ridx, out):
    """out[rows[k], :] = E_loc of every face for target dts[slots[k]] and source dl.
    Returns the index k of the first pair with a non-finite similarity, or -1."""
    nv = dl.shape[0]
    sim = np.empty(nv, np.float32)
    sim_stamp = np.full(nv, -1, np.int64)
    med = np.empty(nv, np.float64)
    buf = np.empty(max(1, int(np.max(rptr[1:] - rptr[:-1]))), np.float64)
    for k in range(slots.shape[0]):
        dt = dts[slots[k]]
        for v in range(nv):
            m = _vertex_median(v, dt, dl, k, rptr, ridx, sim, sim_stamp, buf)
            if m != m:
                return k
            med[v] = m
        r = rows[k]
        for f in range(F.shape[0]):
            out[r, f] = -(med[F[f, 0]] + med[F[f, 1]] + med[F[f, 2]]) / 3.0
    return -1


@njit(cache=True, nogil=True)
def _loc_triples_kernel(dl, dts, slots, face_ids, rows, F, rptr, ridx, out):
    """out[rows[k]] = E_loc(target dts[slots[k]], face face_ids[k], source dl); slots sorted.
    Returns the index k of the first triple with a non-finite similarity, or -1."""
    nv = dl.shape[0]
    sim = np.empty(nv, np.float32)
    sim_stamp = np.full(nv, -1, np.int64)
    med = np.empty(nv, np.float64)
    med_stamp = np.full(nv, -1, np.int64)
    buf = np.empty(max(1, int(np.max(rptr[1:] - rptr[:-1]))), np.float64)
    for k in range(slots.shape[0]):
        s = slots[k]
        dt = dts[s]
        f = face_ids[k]
        acc = 0.0
        for j in range(3):
            v = F[f, j]
            if med_stamp[v] != s:
                m = _vertex_median(v, dt, dl, s, rptr, ridx, sim, sim_stamp, buf)
                if m != m:
                    return k
                med[v] = m
                med_stamp[v] = s
            acc += med[v]
        out[rows[k]] = -acc / 3.0
    return -1


def _check_descriptors(descriptors):
    """(array-like, T, V) of a (T, V, D) descriptor table without reading it."""
    shape = getattr(descriptors, "shape", None)
    if shape is None:
        descriptors = np.asarray(descriptors)
        shape = descriptors.shape
    if len(shape) != 3 or 0 in tuple(shape):
        raise ValueError(f"descriptors must have shape (T, V, D) with T, V, D > 0, got {tuple(shape)}")
    return descriptors, int(shape[0]), int(shape[1])


def _load_frame(descriptors, t: int, n_vertices: int) -> np.ndarray:
    """Frame t's descriptors as C-contiguous float32 (no copy for a float32 numpy table)."""
    d = np.asarray(descriptors[t])
    if d.ndim != 2 or d.shape[0] != n_vertices:
        raise ValueError(f"descriptors[{t}] has shape {d.shape}, expected ({n_vertices}, D)")
    if d.dtype == np.float16:
        out = np.empty(d.shape, np.uint32)
        _half_bits_to_float(np.ascontiguousarray(d).view(np.uint16), out)
        return out.view(np.float32)
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"descriptors must be float16/float32/float64, got {d.dtype} at frame {t}")
    return np.ascontiguousarray(d, dtype=np.float32)


def _rings_for(faces_checked, n_vertices, median_hops, rings):
    if rings is None:
        return vertex_rings(faces_checked, n_vertices, median_hops)
    return _check_rings(rings, n_vertices)


def _stream(descriptors, n_vertices, targets, sources, target_chunk, run):
    """Call run(dl, dts, sel, slots) for every source frame and chunk of target frames, where
    dts stacks the chunk's target descriptors, sel indexes the entries (targets == chunk member
    and sources == that source) sorted by target, and slots are their rows in dts. run returns
    the position in sel of an entry with non-finite descriptors, or -1 (-> ValueError)."""
    chunk = int(target_chunk)
    if chunk < 1:
        raise ValueError(f"target_chunk must be >= 1, got {target_chunk!r}")
    uniq_t = np.unique(targets)
    for c0 in range(0, uniq_t.size, chunk):
        members = uniq_t[c0:c0 + chunk]
        in_chunk = np.flatnonzero(np.isin(targets, members))
        frames = [_load_frame(descriptors, int(t), n_vertices) for t in members]
        if len({(f.dtype, f.shape) for f in frames}) > 1:
            raise ValueError("descriptors of the target frames differ in dtype or length")
        dts = np.stack(frames)
        slot_of = np.searchsorted(members, targets[in_chunk])
        order = np.lexsort((slot_of, sources[in_chunk]))  # by source, then target slot
        sel = in_chunk[order]
        slots = slot_of[order]
        src = sources[sel]
        cuts = np.flatnonzero(np.diff(src)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, src.size]):
            dl = _load_frame(descriptors, int(src[a]), n_vertices)
            if dl.dtype != dts.dtype or dl.shape[1] != dts.shape[2]:
                raise ValueError(f"descriptors of frame {int(src[a])} are {dl.shape[1]} x {dl.dtype}, "
                                 f"those of the targets {dts.shape[2]} x {dts.dtype}")
            bad = run(dl, dts, sel[a:b], np.ascontiguousarray(slots[a:b]))
            if bad >= 0:
                raise ValueError(f"descriptors of frame {int(targets[sel[a + bad]])} or "
                                 f"{int(src[a])} contain non-finite values")


def local_similarity_faces(descriptors, faces, pairs, median_hops: int = 2, rings=None,
                           target_chunk: int = 16) -> np.ndarray:
    """E_loc for (target, source) frame pairs over all faces.

    Args:
        descriptors: (T, V, D) unit descriptors of every frame (numpy or zarr, float16 or
            float32), indexed one frame at a time (module docstring, "Memory").
        faces: (F, 3) int.
        pairs: (n, 2) int frame pairs (t, l) (target, source).
        median_hops: ring size of the median filter of the per-vertex similarities (authors: 2;
            0 = none). Ignored when ``rings`` is given.
        rings: optional precomputed :func:`vertex_rings` ``(ptr, idx)``.
        target_chunk: target frames held in memory at once (float32, V·D·4 bytes each).

    Returns:
        (n, F) float32 in [−1, 0]: row k = −(1/3) Σ_j median_{u ∈ ring(v_j)} τ_u(t_k)·τ_u(l_k)
        over each face's vertices v_j.
    """
    descriptors, T, nv = _check_descriptors(descriptors)
    F = check_faces(faces, nv)
    pr = np.asarray(pairs)
    if pr.ndim != 2 or pr.shape[1] != 2:
        raise ValueError(f"pairs must have shape (n, 2), got {pr.shape}")
    t = _check_frame_ids(pr[:, 0], T, "pairs[:, 0] (targets)")
    l = _check_frame_ids(pr[:, 1], T, "pairs[:, 1] (sources)")
    rptr, ridx = _rings_for(F, nv, median_hops, rings)
    out = np.empty((t.size, F.shape[0]), np.float32)

    def run(dl, dts, sel, slots):
        return _loc_faces_kernel(dl, dts, slots, sel.astype(np.int64), F, rptr, ridx, out)

    _stream(descriptors, nv, t, l, target_chunk, run)
    return out


def local_similarity_triples(descriptors, faces, targets, face_ids, sources, median_hops: int = 2,
                             rings=None, target_chunk: int = 16) -> np.ndarray:
    """E_loc for explicit (target t, face f, source l) triples (candidate labels).

    Per-vertex similarities and their medians are computed once per (t, l) pair and vertex that
    some triple needs, so many faces sharing a pair cost no more than :func:`local_similarity_faces`.

    Args:
        descriptors, faces, median_hops, rings, target_chunk: as in :func:`local_similarity_faces`.
        targets, face_ids, sources: (n,) int arrays of the triples.

    Returns:
        (n,) float32, equal to ``local_similarity_faces(..., pairs=[(t, l)])[0, f]`` per triple.
    """
    descriptors, T, nv = _check_descriptors(descriptors)
    F = check_faces(faces, nv)
    t = _check_frame_ids(targets, T, "targets")
    l = _check_frame_ids(sources, T, "sources")
    fi = np.asarray(face_ids)
    if (fi.ndim != 1 or fi.shape != t.shape or l.shape != t.shape
            or (fi.size and not np.issubdtype(fi.dtype, np.integer))):
        raise ValueError(f"targets, face_ids and sources must be 1-D integer arrays of one length, "
                         f"got {t.shape}, {fi.shape} ({fi.dtype}), {l.shape}")
    fi = fi.astype(np.int64)
    bad = (fi < 0) | (fi >= F.shape[0])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"face_ids[{i}] = {fi[i]} is not a face index in [0, {F.shape[0]})")
    rptr, ridx = _rings_for(F, nv, median_hops, rings)
    out = np.empty(t.size, np.float32)

    def run(dl, dts, sel, slots):
        return _loc_triples_kernel(dl, dts, slots, np.ascontiguousarray(fi[sel]),
                                   sel.astype(np.int64), F, rptr, ridx, out)

    _stream(descriptors, nv, t, l, target_chunk, run)
    return out


# --------------------------------------------------------------------------------------------
# E_str: local strain
# --------------------------------------------------------------------------------------------

def face_strain(vertices, rest_vertices, faces, rings: int = 3) -> np.ndarray:
    """Smoothed log stretch of every face's edges at every frame (module docstring, E_str).

    Args:
        vertices: (T, V, 3) float tracked vertices (m; numpy or zarr, read whole).
        rest_vertices: (V, 3) float template vertices (m): the reference lengths.
        faces: (F, 3) int.
        rings: passes of averaging over the faces that share a vertex with the face (0 = none).

    Returns:
        (T, F, 3) float32: ln(|e_k(t)| / |e_k(rest)|) for the edges k = (v0 v1, v1 v2, v2 v0),
        smoothed. A zero-length edge in the rest shape raises; one at a frame (a collapsed
        face of a tracked or given mesh) counts as 1e-6 of its rest length, so that face is
        dissimilar to every normal frame (E_str clipped to 1) instead of NaN.
    """
    X = _check_frames_vertices(vertices)
    R = check_vertices(rest_vertices, "rest_vertices")
    if R.shape[0] != X.shape[1]:
        raise ValueError(f"rest_vertices has {R.shape[0]} vertices, vertices {X.shape[1]}")
    Fc = check_faces(faces, R.shape[0])
    if int(rings) < 0:
        raise ValueError(f"rings must be >= 0, got {rings}")
    nF = Fc.shape[0]

    def lengths(P):  # (..., V, 3) -> (..., F, 3)
        return np.stack([np.linalg.norm(P[..., Fc[:, (k + 1) % 3], :] - P[..., Fc[:, k], :], axis=-1)
                         for k in range(3)], axis=-1)

    rest = lengths(R)
    if not (rest > 0).all():
        raise ValueError(f"face {int(np.argwhere(~(rest > 0))[0, 0])} has a zero-length edge in the rest shape")
    out = np.empty((X.shape[0], nF, 3), np.float32)
    # faces sharing a vertex, row-normalised: the averaging operator
    inc = sp.csr_matrix((np.ones(Fc.size), (np.repeat(np.arange(nF), 3), Fc.ravel())),
                        shape=(nF, R.shape[0]))
    A = (inc @ inc.T).tocsr()
    A.data[:] = 1.0
    A = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
    for t in range(X.shape[0]):
        s = np.log(np.maximum(lengths(X[t]) / rest, 1e-6))
        for _ in range(int(rings)):
            s = A @ s
        out[t] = s
    return out


def strain_similarity(strain, target: int, clip: float = 0.1, sources=None,
                      tolerance: float = 0.0) -> np.ndarray:
    """E_str(target, f, l) for every source frame l (or those in ``sources``) and face f
    (module docstring).

    Args:
        strain: (T, F, 3) float from :func:`face_strain`.
        target: sequence position t of the target frame.
        clip: strain difference (sum over the 3 edges of |Δ ln length|) that counts as fully
            dissimilar (1).
        sources: optional (N,) int source frames (rows of the result; -1 padding gives 1).
        tolerance: strain difference that still counts as the same strain, one for every face
            or (F,) per face (0): a tracked mesh's drift stretches a surface that does not
            deform, and without the tolerance those differences would rank frames where the
            strain says nothing. E_str = min(max(d - tolerance, 0) / clip, 1).

    Returns:
        (T, F) (or (N, F)) float32 in [0, 1]; the row of ``target`` is 0.
    """
    S = np.asarray(strain)
    if S.ndim != 3 or S.shape[2] != 3:
        raise ValueError(f"strain must be (T, F, 3), got {S.shape}")
    t = int(target)
    if not 0 <= t < S.shape[0]:
        raise ValueError(f"target {t} outside 0..{S.shape[0] - 1}")
    c = positive(clip, "clip")
    tol = np.asarray(tolerance, np.float32)
    if tol.ndim > 1 or (tol.ndim == 1 and tol.shape[0] != S.shape[1]) or not (tol >= 0).all():
        raise ValueError(f"tolerance must be a number >= 0 or {S.shape[1]} of them (one per face), "
                         f"got {tolerance!r}")
    rows = S if sources is None else S[np.where(np.asarray(sources, np.int64) >= 0, sources, t)]
    d = np.abs(rows - S[t][None]).sum(axis=2, dtype=np.float32)
    out = np.minimum(np.maximum(d - tol, np.float32(0.0)) / np.float32(c), np.float32(1.0))
    if sources is not None:
        out[np.asarray(sources, np.int64) < 0] = 1.0
    return out


def strain_noise(strain, frames=None, quantile: float = 0.25) -> float:
    """How much the tracked meshes' strain moves where the surface does not deform: the strain
    noise that a tracking's drift adds, estimated without the truth.

    Each face's strain is compared with its own median over the frames (sum over the 3 edges of
    the absolute difference) and the median of that over the frames is the face's typical
    change; the result is the ``quantile`` of the faces' typical changes. Why a low quantile:
    most objects have a part that barely deforms (a torso, a rigid half), where the tracked
    strain changes only by the drift, while the deforming faces change more.

    Args:
        strain: (T, F, 3) float from :func:`face_strain`.
        frames: optional (T,) bool, the frames to use (e.g. not lost by the tracking); all
            by default.
        quantile: in (0, 1).

    Returns:
        float >= 0, in the units of :func:`strain_similarity`'s ``clip`` and ``tolerance``;
        0 for fewer than 2 frames.
    """
    S = np.asarray(strain, np.float64)
    if S.ndim != 3 or S.shape[2] != 3:
        raise ValueError(f"strain must be (T, F, 3), got {S.shape}")
    if not 0.0 < float(quantile) < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {quantile}")
    if frames is not None:
        keep = np.asarray(frames, bool)
        if keep.shape != (S.shape[0],):
            raise ValueError(f"frames must be ({S.shape[0]},) bool, got shape {keep.shape}")
        S = S[keep]
    if S.shape[0] < 2 or S.shape[1] == 0:
        return 0.0
    change = np.median(np.abs(S - np.median(S, axis=0)[None]).sum(axis=2), axis=0)   # (F,)
    return float(np.quantile(change, float(quantile)))
