"""SHOT descriptors (Tombari et al. 2010) on geodesic neighbourhoods, for the local similarity
E_loc of :mod:`stex.similarity` (whose docstring gives the choices: geodesic neighbourhoods on the
template's edge graph, the reference implementation's local reference frame and bins, z signed by
the vertex normal), and the mesh input checks the similarity functions share.

Conventions: vertices in metres; faces (F, 3) int vertex indices.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numba import njit

from stex.render import vertex_normals

__all__ = ["SHOT_DIM", "Neighbourhoods", "mesh_resolution", "geodesic_neighbourhoods",
           "shot_descriptors", "check_vertices", "check_faces", "check_neighbourhoods",
           "positive", "mesh_edges"]

#: SHOT length: 32 volumes (8 azimuth × 2 elevation × 2 radial) × 11 cosine bins
SHOT_DIM = 352
_SHOT_BINS = 10  # cosine bins per volume, + 1 (the reference code's nr_shape_bins + 1 entries)
_SHOT_MIN_NEIGHBOURS = 3


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------

def check_vertices(vertices, name="vertices") -> np.ndarray:
    """(V, 3) float64 contiguous copy of ``vertices``; ValueError naming ``name`` if the shape is
    wrong, V = 0 or a coordinate is not finite."""
    V = np.asarray(vertices)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] == 0:
        raise ValueError(f"{name} must have shape (V, 3) with V > 0, got {V.shape}")
    V = np.ascontiguousarray(V, dtype=np.float64)
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} contain non-finite coordinates: vertex {int(np.flatnonzero(bad)[0])}")
    return V


def check_faces(faces, n_vertices: int) -> np.ndarray:
    """(F, 3) int64 contiguous copy of ``faces``; ValueError if the shape or dtype is wrong, F = 0
    or an index is outside [0, n_vertices)."""
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F > 0, got {F.shape}")
    if not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces must be an integer array, got dtype {F.dtype}")
    F = np.ascontiguousarray(F, dtype=np.int64)
    bad = ((F < 0) | (F >= n_vertices)).any(axis=1)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise ValueError(f"faces index out of range: face {f} is {F[f].tolist()} but there are "
                         f"{n_vertices} vertices")
    return F


def positive(value, name: str) -> float:
    """``value`` as a float; ValueError naming ``name`` unless it is finite and > 0."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v



# --------------------------------------------------------------------------------------------
# geodesic neighbourhoods
# --------------------------------------------------------------------------------------------

class Neighbourhoods(NamedTuple):
    """Per-vertex neighbour lists in CSR form (unpacks as ``ptr, idx, dist``).

    Attributes:
        ptr: (V + 1,) int64; the neighbours of vertex i are ``idx[ptr[i]:ptr[i + 1]]``.
        idx: (N,) int32 neighbour vertex indices, the vertex itself first, then by increasing
            distance.
        dist: (N,) float32 edge-graph (Dijkstra) distances from vertex i, metres.
    """

    ptr: np.ndarray
    idx: np.ndarray
    dist: np.ndarray


def mesh_edges(faces) -> np.ndarray:
    """(E, 2) int unique undirected edges (sorted pairs, lexicographic order) of (F, 3) faces."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def mesh_resolution(vertices, faces) -> float:
    """Mean edge length (metres) of a triangle mesh ((V, 3) float, (F, 3) int): SHOT's "mesh
    resolution" unit (the authors' SHOT radius is 5 of them)."""
    V = check_vertices(vertices)
    e = mesh_edges(check_faces(faces, V.shape[0]))
    return float(np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1).mean())


def _edge_csr(V, F):
    e = mesh_edges(F)
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)
    n = V.shape[0]
    A = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]),
                                                 np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    A = A.tocsr()  # duplicate (i, j) pairs cannot occur: edges are unique
    return (A.indptr.astype(np.int64), A.indices.astype(np.int64), A.data.astype(np.float64))


@njit(cache=True, nogil=True, inline="always")
def _heap_push(hd, hv, n, d, v):
    """Push (d, v) on the binary min-heap hd[:n], hv[:n]; returns the new size."""
    i = n
    while i > 0:
        p = (i - 1) >> 1
        if hd[p] <= d:
            break
        hd[i] = hd[p]
        hv[i] = hv[p]
        i = p
    hd[i] = d
    hv[i] = v
    return n + 1


@njit(cache=True, nogil=True, inline="always")
def _heap_pop(hd, hv, n):
    """Remove the root of the heap of size n (its (d, v) must be read before); returns n - 1."""
    n -= 1
    d, v = hd[n], hv[n]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and hd[c + 1] < hd[c]:
            c += 1
        if hd[c] >= d:
            break
        hd[i] = hd[c]
        hv[i] = hv[c]
        i = c
    hd[i] = d
    hv[i] = v
    return n


@njit(cache=True, nogil=True)
def _bounded_dijkstra(indptr, indices, weights, radius):
    n = indptr.shape[0] - 1
    dist = np.full(n, np.inf)
    touched = np.empty(n, np.int64)
    # every push strictly lowers some dist[v], so the heap never holds more than the edge count
    hd = np.empty(indices.shape[0] + 1)
    hv = np.empty(indices.shape[0] + 1, np.int64)
    cap = max(16, 8 * n)
    out_idx = np.empty(cap, np.int32)
    out_d = np.empty(cap, np.float32)
    ptr = np.zeros(n + 1, np.int64)
    pos = 0
    for s in range(n):
        hs = _heap_push(hd, hv, 0, 0.0, s)
        dist[s] = 0.0
        touched[0] = s
        nt = 1
        while hs > 0:
            d, u = hd[0], hv[0]
            hs = _heap_pop(hd, hv, hs)
            if d > dist[u]:
                continue  # stale entry
            if pos == cap:
                cap *= 2
                a = np.empty(cap, np.int32)
                a[:pos] = out_idx[:pos]
                out_idx = a
                b = np.empty(cap, np.float32)
                b[:pos] = out_d[:pos]
                out_d = b
            out_idx[pos] = u
            out_d[pos] = d
            pos += 1
            for k in range(indptr[u], indptr[u + 1]):
                v = indices[k]
                nd = d + weights[k]
                if nd <= radius and nd < dist[v]:
                    if dist[v] == np.inf:
                        touched[nt] = v
                        nt += 1
                    dist[v] = nd
                    hs = _heap_push(hd, hv, hs, nd, v)
        ptr[s + 1] = pos
        for i in range(nt):
            dist[touched[i]] = np.inf
    return ptr, out_idx[:pos].copy(), out_d[:pos].copy()


def geodesic_neighbourhoods(vertices, faces, radius_m: float) -> Neighbourhoods:
    """Every vertex's neighbours within ``radius_m`` along the mesh's edge graph (bounded Dijkstra).

    Args:
        vertices: (V, 3) float positions, metres (normally the template's).
        faces: (F, 3) int.
        radius_m: geodesic radius, metres. Edge-path distances overestimate the true geodesic
            distance (docs/decisions/similarity.md).

    Returns:
        :class:`Neighbourhoods` ``(ptr (V+1,) int64, idx int32, dist float32)``; each list starts
        with the vertex itself (distance 0) and is sorted by distance.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    radius = positive(radius_m, "radius_m")
    ptr, idx, dist = _bounded_dijkstra(*_edge_csr(V, F), radius)
    return Neighbourhoods(ptr, idx, dist)


# --------------------------------------------------------------------------------------------
# SHOT
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _offset(P, j, px, py, pz):
    """Offset of vertex j from the point (px, py, pz) and its length."""
    dx, dy, dz = P[j, 0] - px, P[j, 1] - py, P[j, 2] - pz
    return dx, dy, dz, math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True)
def _shot_kernel(P, N, ptr, idx, radius, out):
    nb = _SHOT_BINS
    stride = nb + 1
    r12 = 0.5 * radius
    r14 = 0.25 * radius
    r34 = 0.75 * radius
    pi = np.pi
    hist = np.zeros(out.shape[1])
    C = np.zeros((3, 3))
    for i in range(P.shape[0]):
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        for a in range(3):
            for b in range(3):
                C[a, b] = 0.0
        wsum = 0.0
        cnt = 0
        for k in range(ptr[i], ptr[i + 1]):
            j = idx[k]
            dx, dy, dz, d = _offset(P, j, px, py, pz)
            if d >= radius or d == 0.0:
                continue  # outside the spherical support in this frame, or the vertex itself
            w = radius - d
            C[0, 0] += w * dx * dx
            C[0, 1] += w * dx * dy
            C[0, 2] += w * dx * dz
            C[1, 1] += w * dy * dy
            C[1, 2] += w * dy * dz
            C[2, 2] += w * dz * dz
            wsum += w
            cnt += 1
        for q in range(out.shape[1]):
            out[i, q] = 0.0
        if cnt < _SHOT_MIN_NEIGHBOURS:
            continue
        C[1, 0] = C[0, 1]
        C[2, 0] = C[0, 2]
        C[2, 1] = C[1, 2]
        for a in range(3):
            for b in range(3):
                C[a, b] /= wsum
        _, evec = np.linalg.eigh(C)  # ascending eigenvalues
        xx, xy, xz = evec[0, 2], evec[1, 2], evec[2, 2]
        zx, zy, zz = evec[0, 0], evec[1, 0], evec[2, 0]
        # x: majority of neighbours on the positive side, ties by the weighted sum
        npos = 0
        sw = 0.0
        for k in range(ptr[i], ptr[i + 1]):
            j = idx[k]
            dx, dy, dz, d = _offset(P, j, px, py, pz)
            if d >= radius or d == 0.0:
                continue
            p = dx * xx + dy * xy + dz * xz
            if p >= 0.0:
                npos += 1
            sw += (radius - d) * p
        if 2 * npos < cnt or (2 * npos == cnt and sw < 0.0):
            xx, xy, xz = -xx, -xy, -xz
        # z: along the mesh's vertex normal
        if zx * N[i, 0] + zy * N[i, 1] + zz * N[i, 2] < 0.0:
            zx, zy, zz = -zx, -zy, -zz
        yx = zy * xz - zz * xy
        yy = zz * xx - zx * xz
        yz = zx * xy - zy * xx
        for q in range(hist.shape[0]):
            hist[q] = 0.0
        for k in range(ptr[i], ptr[i + 1]):
            j = idx[k]
            dx, dy, dz, d = _offset(P, j, px, py, pz)
            if d >= radius or d == 0.0:
                continue
            cs = N[j, 0] * zx + N[j, 1] * zy + N[j, 2] * zz
            cs = min(1.0, max(-1.0, cs))
            bd = (1.0 + cs) * nb / 2.0
            lx = dx * xx + dy * xy + dz * xz
            ly = dx * yx + dy * yy + dz * yz
            lz = dx * zx + dy * zy + dz * zz
            if abs(lx) < 1e-30:
                lx = 0.0
            if abs(ly) < 1e-30:
                ly = 0.0
            if abs(lz) < 1e-30:
                lz = 0.0
            # volume: azimuth sector s (centred at -7pi/8 + s pi/4), elevation, radial shell
            az = math.atan2(ly, lx)
            sector = min(int((az + pi) / (pi / 4.0)), 7)
            up = 1 if lz > 0.0 else 0
            outer = 1 if d > r12 else 0
            vol = sector * 4 + outer * 2 + up
            step = int(math.floor(bd + 0.5))
            base = vol * stride
            # cosine: the adjacent bin
            rem = bd - step
            wgt = 1.0 - abs(rem)
            if rem > 0.0:
                hist[base + min(step + 1, nb)] += rem
            elif rem < 0.0:
                hist[base + max(step - 1, 0)] -= rem
            # radius: the adjacent shell
            if outer == 1:
                rd = (d - r34) / r12
                if d > r34:
                    wgt += 1.0 - rd
                else:
                    wgt += 1.0 + rd
                    hist[(vol - 2) * stride + step] -= rd
            else:
                rd = (d - r14) / r12
                if d < r14:
                    wgt += 1.0 + rd
                else:
                    wgt += 1.0 - rd
                    hist[(vol + 2) * stride + step] += rd
            # elevation: the adjacent (upper / lower) volume
            ic = min(1.0, max(-1.0, lz / d))
            inc = math.acos(ic)
            if up == 0:
                idist = (inc - 0.75 * pi) / (0.5 * pi)
                if inc > 0.75 * pi:
                    wgt += 1.0 - idist
                else:
                    wgt += 1.0 + idist
                    hist[(vol + 1) * stride + step] -= idist
            else:
                idist = (inc - 0.25 * pi) / (0.5 * pi)
                if inc < 0.25 * pi:
                    wgt += 1.0 + idist
                else:
                    wgt += 1.0 - idist
                    hist[(vol - 1) * stride + step] += idist
            # azimuth: the adjacent sector
            if lx != 0.0 or ly != 0.0:
                adist = (az - (-0.875 * pi + sector * 0.25 * pi)) / (0.25 * pi)
                adist = max(-0.5, min(adist, 0.5))
                if adist > 0.0:
                    wgt += 1.0 - adist
                    hist[(((sector + 1) % 8) * 4 + outer * 2 + up) * stride + step] += adist
                else:
                    wgt += 1.0 + adist
                    hist[(((sector + 7) % 8) * 4 + outer * 2 + up) * stride + step] -= adist
            hist[base + step] += wgt
        norm = 0.0
        for q in range(hist.shape[0]):
            norm += hist[q] * hist[q]
        if norm > 0.0:
            inv = 1.0 / math.sqrt(norm)
            for q in range(hist.shape[0]):
                out[i, q] = hist[q] * inv


def check_neighbourhoods(nbh, n_vertices: int):
    """(ptr (V + 1,) int64, idx (N,) int64) of CSR neighbour lists ``nbh`` (``(ptr, idx[, dist])``),
    checked against ``n_vertices``; ValueError otherwise."""
    try:
        ptr, idx = nbh[0], nbh[1]
    except (TypeError, IndexError, KeyError):
        raise ValueError("neighbourhoods must be (ptr, idx[, dist]) as returned by "
                         "geodesic_neighbourhoods") from None
    ptr = np.ascontiguousarray(ptr, dtype=np.int64)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if ptr.shape != (n_vertices + 1,) or ptr[0] != 0 or ptr[-1] != idx.shape[0] or (np.diff(ptr) < 0).any():
        raise ValueError(f"neighbourhoods ptr must be a non-decreasing (V + 1,) = ({n_vertices + 1},) "
                         f"array from 0 to len(idx) = {idx.shape[0]}, got shape {ptr.shape}")
    if idx.size and (idx.min() < 0 or idx.max() >= n_vertices):
        raise ValueError(f"neighbourhoods idx holds vertex ids outside [0, {n_vertices})")
    return ptr, idx


def shot_descriptors(vertices, faces, neighbourhoods, radius_m: float | None = None) -> np.ndarray:
    """SHOT descriptors (Tombari et al. 2010) of every vertex of one frame's mesh.

    Args:
        vertices: (V, 3) float positions of this frame, metres.
        faces: (F, 3) int (for the vertex normals: area-weighted, :func:`stex.render.vertex_normals`).
        neighbourhoods: a :class:`Neighbourhoods` / ``(ptr, idx[, dist])`` (normally the
            template's, computed once with :func:`geodesic_neighbourhoods`), or a float radius in
            metres to compute geodesic neighbourhoods on these vertices.
        radius_m: the support radius R, metres; required with precomputed neighbourhoods (the
            radius they were made with), defaults to the radius when one is given.

    Returns:
        (V, 352) float32 unit descriptors (all zero for a vertex with fewer than 3 neighbours
        within R in this frame). See the module docstring for the reference frame and bins.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    if isinstance(neighbourhoods, (int, float, np.floating, np.integer)):
        r = positive(neighbourhoods, "neighbourhoods radius")
        nbh = geodesic_neighbourhoods(V, F, r)
        radius = r if radius_m is None else positive(radius_m, "radius_m")
    else:
        nbh = neighbourhoods
        if radius_m is None:
            raise ValueError("radius_m is required with precomputed neighbourhoods (the radius "
                             "they were made with)")
        radius = positive(radius_m, "radius_m")
    ptr, idx = check_neighbourhoods(nbh, V.shape[0])
    N = np.ascontiguousarray(vertex_normals(V, F), dtype=np.float64)
    out = np.empty((V.shape[0], SHOT_DIM), np.float32)
    _shot_kernel(V, N, ptr, idx, radius, out)
    return out
