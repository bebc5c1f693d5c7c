"""Candidate pruning: which frame pairs get a rigid pose, an E_glo render and a place in the
labeling's candidates.

The data term prefers source frames whose shape is close to the target's (E_glo, E_loc, E_str),
so a frame far from t in shape rarely wins a face's candidate slot while a nearer frame sees that
face well. Comparing every frame with every other costs T² poses and T² depth renders; instead
each target t is compared with a bounded set of source frames, chosen by a cheap per-frame shape
descriptor:

1. **Descriptor** (:func:`shape_descriptors`): the tracked vertices of a seeded subset,
   rigidly aligned (Kabsch, two rounds of generalised Procrustes against the mean shape) so that
   the object's motion in the camera does not count, then projected onto the leading principal
   components of the aligned shapes. Euclidean distance between descriptors approximates the RMS
   vertex distance of the aligned shapes.
2. **Neighbours** (:func:`nearest_sources`): target t keeps its ``k`` source frames nearest in
   shape (that see anything), and then, walking on nearest first, every frame that a face
   still needs: each face is owed its ``coverage`` nearest frames that see it (all of them
   when fewer see it). A face that t's nearest frames never see (the far side of a turning
   object) still gets frames that do see it, so no face loses its candidates, while the set
   stays bounded whatever T is. ``k = 0`` means every frame (the full tables). The walk takes
   each face's own nearest frames, which differ from face to face; ``mode="cover"`` instead
   chooses the owed frames as a greedy set cover (near shapes first among frames that cover
   about as much), so fewer frames serve the faces the nearest frames miss.
3. **Pairs** (:func:`pose_pairs`): the unordered frame pairs {t, l}, l in t's source set, each
   given one rigid pose (K_{l→t} is the inverse of K_{t→l}).

Conventions: frames are sequence positions 0..T-1; vertices in metres.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from stex.poses import invert_rigid, kabsch

__all__ = ["shape_descriptors", "nearest_sources", "pose_pairs", "pair_index", "directed_poses"]

#: principal components kept in the descriptor: the procedural and captured motions we measured
#: put nearly all of the aligned shapes' variance in a handful of components, so more only costs
DESCRIPTOR_DIMS = 32

#: ways to choose the frames owed to faces (``poses.coverage_mode``)
COVER_MODES = ("walk", "cover")

#: the set cover takes the nearest frame covering at least this share of what the best frame
#: covers: a pick is never much worse than the greedy one, so the set stays small, while among
#: frames that cover about as much the nearer shape wins
COVER_GAIN_RATIO = 0.5


def shape_descriptors(vertices, n_vertices: int = 512, dims: int = DESCRIPTOR_DIMS,
                      seed: int = 0) -> np.ndarray:
    """Per-frame shape descriptors: aligned vertex positions, PCA-reduced.

    Args:
        vertices: (T, V, 3) float tracked vertices (metres), one topology.
        n_vertices: size of the seeded vertex subset (all when V is smaller).
        dims: principal components kept (at most T and 3·n_vertices).
        seed: seed of the subset.

    Returns:
        (T, D) float32, D = min(dims, T, 3·n), in metres·sqrt(n): the Euclidean distance of two
        rows is the root of the summed squared vertex distance of the two aligned subsets,
        restricted to the leading components.
    """
    X = np.asarray(vertices, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] < 1 or X.shape[1] < 3:
        raise ValueError(f"vertices must be (T, V, 3) with T >= 1, V >= 3, got {X.shape}")
    if not np.isfinite(X).all():
        raise ValueError("vertices: non-finite coordinates")
    T, V = X.shape[:2]
    rng = np.random.default_rng(seed)
    sub = np.sort(rng.choice(V, min(int(n_vertices), V), replace=False))
    P = X[:, sub] - X[:, sub].mean(axis=1, keepdims=True)
    ref = P[0]
    for _ in range(2):  # generalised Procrustes: align to the reference, then to the mean
        R, t = kabsch(P, np.broadcast_to(ref, P.shape))
        P = np.einsum("tij,tvj->tvi", R, P) + t[:, None]
        ref = P.mean(axis=0)
    Y = P.reshape(T, -1)
    Y = Y - Y.mean(axis=0)
    d = min(int(dims), T, Y.shape[1])
    U, S, _ = np.linalg.svd(Y, full_matrices=False)
    return (U[:, :d] * S[:d]).astype(np.float32)


def nearest_sources(descriptors, visible, k: int, is_source=None, coverage: int | None = None,
                    mode: str = "walk", cover_ratio: float = COVER_GAIN_RATIO) -> np.ndarray:
    """The source frames each target is compared with (module docstring, step 2).

    Args:
        descriptors: (T, D) float :func:`shape_descriptors`.
        visible: (T, F) bool, face f seen at frame t (``projection`` face_visible); None = every
            frame sees one face (the k nearest frames overall).
        k: the target's nearest source frames taken whatever they see (>= 0; 0 = every frame
            for every target).
        is_source: (T,) bool, the frames that may texture (``data_term.source_stride``); None = all.
        coverage: frames each face is owed: after the k nearest, the walk goes on, nearest
            first, taking a frame while some face it sees has fewer than min(coverage, frames
            that see it) taken; None = k.
        mode: how the frames owed to faces are chosen after the k nearest: ``walk`` (every
            frame, nearest first, that some owed face needs) or ``cover`` (a greedy set cover:
            repeatedly the nearest frame whose count of owed faces it sees is at least
            ``cover_ratio`` of the best remaining frame's, until no face is owed).
        cover_ratio: in (0, 1]; 1 = the plain greedy set cover (fewest frames), smaller prefers
            nearer shapes over frames that cover more.

    Returns:
        (T, N) int32, row t: its source frames ascending, -1 padding. t itself is in its row when
        it is a source. With k = 0 every row is 0..T-1 (non-sources included, as the full tables).
    """
    D = np.asarray(descriptors, np.float64)
    T = D.shape[0]
    k = int(k)
    if k < 0:
        raise ValueError(f"poses.nearest_frames must be >= 0, got {k}")
    if k == 0:
        return np.broadcast_to(np.arange(T, dtype=np.int32), (T, T)).copy()
    vis = np.ones((T, 1), bool) if visible is None else np.asarray(visible, bool)
    if vis.shape[0] != T:
        raise ValueError(f"visible has {vis.shape[0]} frames, the descriptors {T}")
    src = np.ones(T, bool) if is_source is None else np.asarray(is_source, bool)
    vis = vis & src[:, None]
    srcs = np.flatnonzero(vis.any(axis=1))          # sources that see anything
    c = k if coverage is None else int(coverage)
    if c < 0:
        raise ValueError(f"poses.coverage_frames must be >= 0, got {coverage}")
    if mode not in COVER_MODES:
        raise ValueError(f"poses.coverage_mode must be one of {COVER_MODES}, got {mode!r}")
    if not 0.0 < float(cover_ratio) <= 1.0:
        raise ValueError(f"cover_ratio must be in (0, 1], got {cover_ratio}")
    need = np.minimum(c, vis.sum(axis=0)).astype(np.int64)   # (F,) frames each face is owed
    fr, fa = np.nonzero(vis)
    vptr = np.searchsorted(fr, np.arange(T + 1)).astype(np.int64)
    vidx = fa.astype(np.int64)
    count = np.zeros(vis.shape[1], np.int64)
    taken = np.empty(T, np.int64)
    if mode == "cover":   # face -> frames that see it, and each frame's owed faces at the start
        ff, ft = np.nonzero(vis.T)
        fptr = np.searchsorted(ff, np.arange(vis.shape[1] + 1)).astype(np.int64)
        fidx = ft.astype(np.int64)
        gain0 = (vis & (need > 0)[None]).sum(axis=1).astype(np.int64)
        gain = np.empty(T, np.int64)
        rank = np.empty(T, np.int64)
    rows = []
    for t in range(T):
        dist = np.linalg.norm(D[srcs] - D[t], axis=1)
        dist[srcs == t] = -1.0                       # t first (ties at distance 0)
        order = srcs[np.argsort(dist, kind="stable")].astype(np.int64)
        if mode == "cover":
            n = _cover(order, vptr, vidx, fptr, fidx, need, count, gain0, gain, rank, taken, k,
                       float(cover_ratio))
        else:
            n = _walk(order, vptr, vidx, need, count, taken, k)
        rows.append(np.sort(taken[:n]))
    N = max((r.size for r in rows), default=0)
    out = np.full((T, max(N, 1)), -1, np.int32)
    for t, r in enumerate(rows):
        out[t, :r.size] = r
    return out


@njit(cache=True, nogil=True)
def _walk(order, vptr, vidx, need, count, taken, k):
    """Walk the sources nearest first; take the first k, then a frame while some face it sees
    is still owed frames. A frame not taken sees only faces owed nothing, so it need not be
    counted. Writes taken[:n], returns n; count is scratch (F,)."""
    count[:] = 0
    unsat = 0
    for f in range(need.shape[0]):
        if need[f] > 0:
            unsat += 1
    n = 0
    for i in range(order.shape[0]):
        if unsat == 0 and i >= k:
            break
        l = order[i]
        take = i < k
        for q in range(vptr[l], vptr[l + 1]):
            f = vidx[q]
            if count[f] < need[f]:
                take = True
                count[f] += 1
                if count[f] == need[f]:
                    unsat -= 1
        if take:
            taken[n] = l
            n += 1
    return n


@njit(cache=True, nogil=True)
def _cover(order, vptr, vidx, fptr, fidx, need, count, gain0, gain, rank, taken, k, ratio):
    """Take the first k of ``order``, then greedily, while some face is owed frames, the first
    frame in ``order`` whose gain (owed faces it sees) is >= ratio times the largest gain.
    Gains are updated when a face stops being owed, so a pick costs O(T). Writes taken[:n],
    returns n; count, gain and rank are scratch."""
    count[:] = 0
    gain[:] = gain0
    rank[:] = -1
    unsat = 0
    for f in range(need.shape[0]):
        if need[f] > 0:
            unsat += 1
    for i in range(order.shape[0]):
        rank[order[i]] = i
    n = 0
    i = 0
    while True:
        if i < k and i < order.shape[0]:
            l = order[i]
            i += 1
        else:
            if unsat == 0:
                break
            best = 0
            for j in range(order.shape[0]):
                if gain[order[j]] > best:
                    best = gain[order[j]]
            if best == 0:
                break
            l = -1
            for j in range(order.shape[0]):
                if gain[order[j]] > 0 and gain[order[j]] >= ratio * best:
                    l = order[j]
                    break
        taken[n] = l
        n += 1
        gain[l] = 0
        rank[l] = -2                       # taken: never picked again
        for q in range(vptr[l], vptr[l + 1]):
            f = vidx[q]
            if count[f] < need[f]:
                count[f] += 1
                if count[f] == need[f]:    # no longer owed: frames seeing it gain less
                    unsat -= 1
                    for r in range(fptr[f], fptr[f + 1]):
                        m = fidx[r]
                        if rank[m] >= 0:
                            gain[m] -= 1
    return n


def pose_pairs(neighbours) -> np.ndarray:
    """(P, 2) int32 unordered frame pairs (i < j, lexicographic) of every target and its
    sources in ``neighbours`` ((T, N) int, -1 padding; :func:`nearest_sources`)."""
    nb = np.asarray(neighbours, np.int64)
    t = np.broadcast_to(np.arange(nb.shape[0])[:, None], nb.shape)
    ok = (nb >= 0) & (nb != t)
    i = np.minimum(t[ok], nb[ok])
    j = np.maximum(t[ok], nb[ok])
    T = max(nb.shape[0], int(nb.max(initial=0)) + 1)
    key = np.unique(i * T + j)
    return np.stack([key // T, key % T], axis=1).astype(np.int32)


def pair_index(pairs, n_frames: int, t, l) -> np.ndarray:
    """Row of each unordered pair {t, l} in ``pairs`` ((P, 2), i < j, lexicographic); -1 where
    t == l. Raises ValueError naming the first pair that is not in the table."""
    pr = np.asarray(pairs, np.int64)
    T = int(n_frames)
    t = np.asarray(t, np.int64)
    l = np.asarray(l, np.int64)
    key = np.minimum(t, l) * T + np.maximum(t, l)
    keys = pr[:, 0] * T + pr[:, 1]
    pos = np.searchsorted(keys, key)
    pos_c = np.minimum(pos, max(keys.size - 1, 0))
    found = (keys.size > 0) & (keys[pos_c] == key) if keys.size else np.zeros(key.shape, bool)
    miss = ~found & (t != l)
    if miss.any():
        a = np.argwhere(miss)[0]
        raise ValueError(f"frame pair ({int(t[tuple(a)])}, {int(l[tuple(a)])}) has no pose in the "
                         f"pose table (pruned by poses.nearest_frames?)")
    return np.where(t == l, -1, pos_c)


def directed_poses(pairs, poses, n_frames: int, t, l) -> np.ndarray:
    """K_{t→l} for arrays of frame pairs from the sparse table (``pairs`` (P, 2) i < j,
    ``poses`` (P, 4, 4) K_{i→j}): the stored pose, its exact inverse for t > l, the identity for
    t == l. Returns (t.shape) + (4, 4) float64."""
    t = np.asarray(t, np.int64)
    l = np.asarray(l, np.int64)
    idx = pair_index(pairs, n_frames, t, l)
    P = np.asarray(poses, np.float64)
    out = np.broadcast_to(np.eye(4), t.shape + (4, 4)).copy()
    fwd = (idx >= 0) & (t < l)
    back = (idx >= 0) & (t > l)
    out[fwd] = P[idx[fwd]]
    out[back] = invert_rigid(P[idx[back]])
    return out
