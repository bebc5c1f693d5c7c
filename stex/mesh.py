"""Mesh topology and geometry: edge tables, non-manifold checks, cleaning, parts, orientation,
nesting, points inside a closed mesh, subdivision, decimation, face adjacency, and embedding of
vertices in another surface.

Conventions: vertices (V, 3) float in metres, depth-camera coordinates (the depth camera at the
origin looking along +z); faces (F, 3) int, counter-clockwise seen from outside: from outside
the solid for closed parts (into its cavity for a cavity's wall), from the depth camera for open
ones (a single-view scan). Corner texture coordinates, where carried, are (F, 3, 2) float64 in
stex's UV convention (u right, v down, see :mod:`stex.atlas`).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from stex.render import rasterize

log = logging.getLogger("stex.template")


# --------------------------------------------------------------------------------------------
# cleaning
# --------------------------------------------------------------------------------------------

def _edge_table(faces: np.ndarray):
    """Undirected edges of every face corner: (sorted edges (3F, 2) int64, face of each (3F,))."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    fid = np.tile(np.arange(len(f), dtype=np.int64), 3)
    return e, fid


def nonmanifold_edges(faces) -> tuple[np.ndarray, np.ndarray]:
    """Edges used by more than two faces, and boundary edges (used by exactly one face).

    Args:
        faces: (F, 3) integer vertex indices.

    Returns:
        (nonmanifold (N, 2) int32, boundary (B, 2) int32): vertex ids, smaller id first, sorted.
    """
    e, _ = _edge_table(faces)
    if len(e) == 0:
        z = np.zeros((0, 2), np.int32)
        return z, z
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return uniq[counts > 2].astype(np.int32), uniq[counts == 1].astype(np.int32)


def nonmanifold_vertices(faces) -> np.ndarray:
    """Vertices whose faces form more than one fan (e.g. two cones touching at their tips, a
    "bowtie"): the faces around a vertex are joined across the edges at that vertex that exactly
    two faces share, and a manifold vertex's faces are then one group.

    Args:
        faces: (F, 3) integer vertex indices.

    Returns:
        (N,) int32 vertex ids, sorted.
    """
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int32)
    n = 3 * len(f)
    corner_vertex = f.ravel()                     # corner 3 i + k is vertex f[i, k]
    e, fid = _edge_table(f)                       # edge j of face i: corners (k, k + 1 mod 3)
    k0 = np.repeat(np.arange(3), len(f))
    c_lo = 3 * fid + np.where(f[fid, k0] == e[:, 0], k0, (k0 + 1) % 3)
    c_hi = 3 * fid + np.where(f[fid, k0] == e[:, 0], (k0 + 1) % 3, k0)
    order = np.lexsort((e[:, 1], e[:, 0]))
    es = e[order]
    start = np.flatnonzero(np.r_[True, (es[1:] != es[:-1]).any(1)])
    count = np.diff(np.r_[start, len(es)])
    two = start[count == 2]                       # manifold edges: join the two faces' corners
    a, b = order[two], order[two + 1]
    rows = np.concatenate([c_lo[a], c_hi[a]])
    cols = np.concatenate([c_lo[b], c_hi[b]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    groups = np.unique(corner_vertex * n + comp) // n      # (vertex, fan) pairs -> their vertex
    vid, per_vertex = np.unique(groups, return_counts=True)
    return vid[per_vertex > 1].astype(np.int32)


def clean_mesh(vertices, faces, area_tol: float = 1e-12, return_corners: bool = False, camera=None):
    """Clean a triangle mesh for decimation and unwrapping.

    Steps: merge vertices with exactly equal coordinates; drop faces that use a vertex twice or
    whose area is below ``area_tol`` x (bounding-box diagonal)^2; drop repeated faces (same three
    vertices in any order, keeping the first); drop vertices no face uses; turn round the
    coherently wound parts that face the wrong way (:func:`_orient_parts`: closed parts by their
    signed volume and nesting, open parts towards the camera). Non-manifold edges (shared by more
    than two faces), non-manifold vertices (:func:`nonmanifold_vertices`), boundary edges and
    edges between faces of opposite winding are counted, not repaired.

    Args:
        vertices: (V, 3) float, metres, depth-camera coordinates.
        faces: (F, 3) int vertex indices.
        area_tol: relative area below which a face is degenerate.
        camera: the depth camera (:class:`stex.camera.Intrinsics`) that open parts should face;
            its centre is the origin and it looks along +z. None (default): a pinhole at the
            origin looking along +z whose image frames the open parts.

    Returns:
        (vertices (V', 3) float64 m, faces (F', 3) int32, report): ``report`` is a JSON-able dict
        with ``vertices_in/out``, ``faces_in/out``, ``duplicate_vertices`` (merged),
        ``degenerate_faces``, ``duplicate_faces``, ``unreferenced_vertices`` (removed),
        ``nonmanifold_edges``, ``nonmanifold_vertices``, ``boundary_edges``,
        ``inconsistent_winding_edges`` (counts), ``inverted_parts_flipped``,
        ``open_parts_flipped`` (closed and open parts turned round) and ``nonmanifold_examples``
        (up to 10 vertex-id pairs, in output numbering). Face order is kept (minus removed faces).
        With ``return_corners`` also ``corners`` (F', 3) int64: the input corner ``3 f + k``
        (corner k of input face f) that each output corner is, so that per-corner data such as
        texture coordinates can follow (``data.reshape(3 F, ...)[corners]``), faces turned round
        included.
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {F.shape}")
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"faces index vertices outside 0..{len(V) - 1}")
    if not np.isfinite(V).all():
        raise ValueError(f"vertex {int(np.flatnonzero(~np.isfinite(V).all(1))[0])} is not finite")
    report = {"vertices_in": len(V), "faces_in": len(F)}

    uniq, first, inverse = np.unique(V, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    report["duplicate_vertices"] = int(len(V) - len(uniq))
    # Keep the first occurrence's position order: renumber merged vertices by first appearance.
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    V1 = uniq[order]
    F1 = rank[inverse][F]

    repeated = (F1[:, 0] == F1[:, 1]) | (F1[:, 1] == F1[:, 2]) | (F1[:, 2] == F1[:, 0])
    diag2 = float(((V1.max(0) - V1.min(0)) ** 2).sum()) if len(V1) else 0.0
    area = 0.5 * np.linalg.norm(np.cross(V1[F1[:, 1]] - V1[F1[:, 0]], V1[F1[:, 2]] - V1[F1[:, 0]]), axis=1)
    degenerate = repeated | (area <= area_tol * diag2)
    report["degenerate_faces"] = int(degenerate.sum())
    F1 = F1[~degenerate]
    corners = np.arange(3 * len(F), dtype=np.int64).reshape(-1, 3)[~degenerate]

    key = np.sort(F1, axis=1)
    _, keep = np.unique(key, axis=0, return_index=True)
    keep.sort()
    report["duplicate_faces"] = int(len(F1) - len(keep))
    F1, corners = F1[keep], corners[keep]

    used = np.zeros(len(V1), bool)
    used[F1.ravel()] = True
    report["unreferenced_vertices"] = int((~used).sum())
    remap = np.cumsum(used) - 1
    V2 = V1[used]
    F2 = remap[F1].astype(np.int32)

    if len(F2) == 0:
        raise ValueError("the mesh has no non-degenerate faces")
    nm, boundary = nonmanifold_edges(F2)
    nm_vertices = nonmanifold_vertices(F2)
    F2, winding, turned = _orient_parts(V2, F2, camera)
    corners[turned] = corners[turned][:, [0, 2, 1]]
    report.update(vertices_out=len(V2), faces_out=len(F2), nonmanifold_edges=int(len(nm)),
                  nonmanifold_vertices=int(len(nm_vertices)), boundary_edges=int(len(boundary)), nonmanifold_examples=nm[:10].tolist(), **winding)
    if len(nm):
        log.warning("template: %d non-manifold edges (shared by > 2 faces), e.g. %s",
                    len(nm), nm[:3].tolist())
    # at the vertices of non-manifold edges the fans are counted with those edges, not alone
    lone = np.setdiff1d(nm_vertices, nm.ravel())
    if len(lone):
        log.warning("template: %d non-manifold vertices (their faces form more than one fan), e.g. %s",
                    len(lone), lone[:3].tolist())
    if winding["inverted_parts_flipped"]:
        log.warning("template: %d closed parts of the mesh faced inwards, into the solid (an outer surface "
                    "clockwise seen from outside, or a cavity's wall facing away from the cavity); their faces "
                    "were turned round", winding["inverted_parts_flipped"])
    if winding["open_parts_flipped"]:
        log.warning("template: %d open parts of the mesh faced away from the camera over most of what it sees of "
                    "them (clockwise seen from it: the visible side would be a back face); their faces were "
                    "turned round", winding["open_parts_flipped"])
    if winding["inconsistent_winding_edges"]:
        log.warning("template: %d edges join faces of opposite winding, so some faces face inwards: the "
                    "renderer treats them as back faces (unseen); re-orient the mesh's faces coherently "
                    "(e.g. MeshLab: Re-Orient all faces coherently)", winding["inconsistent_winding_edges"])
    return (V2, F2, report, corners) if return_corners else (V2, F2, report)


def mesh_parts(faces) -> np.ndarray:
    """(F,) int connected part of each face, faces joined when they share an edge."""
    e, owner = _edge_table(faces)
    if len(e) == 0:
        return np.zeros(0, np.int64)
    key = e[:, 0] * (int(e.max()) + 1) + e[:, 1]  # 1-D keys: sorting them is much faster than rows
    order = np.argsort(key, kind="stable")
    k, f = key[order], owner[order]
    same = k[1:] == k[:-1]
    n = len(owner) // 3
    adj = coo_matrix((np.ones(int(same.sum())), (f[:-1][same], f[1:][same])), (n, n))
    return connected_components(adj, directed=False)[1]


def drop_small_parts(vertices, faces, min_faces: int, return_kept: bool = False):
    """Remove connected parts (:func:`mesh_parts`) with fewer than ``min_faces`` faces, and the
    vertices only they used. Returns (vertices, faces int32, {``parts``, ``dropped_parts``,
    ``dropped_faces``}) and with ``return_kept`` the (F,) bool mask of input faces kept; face
    order is kept."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    part = mesh_parts(F)
    sizes = np.bincount(part)
    keep = sizes[part] >= int(min_faces)
    report = {"parts": int(len(sizes)), "dropped_parts": int((sizes < int(min_faces)).sum()),
              "dropped_faces": int((~keep).sum())}
    if keep.all():
        return (V, F.astype(np.int32), report) + ((keep,) if return_kept else ())
    if not keep.any():
        raise ValueError(f"every part of the mesh has fewer than {min_faces} faces (template.min_part_faces); "
                         f"the largest has {int(sizes.max())}")
    F = F[keep]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    remap = np.cumsum(used) - 1
    return (V[used], remap[F].astype(np.int32), report) + ((keep,) if return_kept else ())


def _orient_parts(V, F, camera=None):
    """Turn round the coherently wound connected parts that face the wrong way, and count the
    edges whose two faces have opposite winding (an edge both faces traverse in the same
    direction). Parts with such edges are left as they are: which way they face is not defined.

    - A **closed** part (every edge shared by exactly two faces) should enclose its solid: outward
      (positive signed volume) when it lies inside an even number of other closed parts, into its
      cavity (negative volume, e.g. the inner wall of a hollow shell) when inside an odd number
      (:func:`_nesting_depth`).
    - An **open** part (a boundary or non-manifold edges: no inside), e.g. a single-view scan,
      should face the camera: it is turned round when most of its area that the camera sees
      (pixels of a z-buffer render, other parts occluding) faces away from it
      (:func:`_parts_facing_away`). Parts the camera does not see are left as they are.

    Args:
        V: (V, 3) float vertices, metres, depth-camera coordinates. F: (F, 3) int faces.
        camera: the depth camera (:class:`stex.camera.Intrinsics`), centre at the origin looking
            along +z; None: a pinhole at the origin looking along +z whose image frames the open
            parts.

    Returns:
        (faces (F, 3) int32, {``inverted_parts_flipped``, ``open_parts_flipped``,
        ``inconsistent_winding_edges``}, (F,) bool: the faces turned round).
    """
    F = np.asarray(F, np.int64)
    V = np.asarray(V, np.float64)
    e, owner = _edge_table(F)  # corner edges in the order (0, 1), (1, 2), (2, 0) of every face
    first = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    # an edge both of whose faces run it the same way (its smaller vertex first in both, or in
    # neither) joins faces of opposite winding
    n = int(F.max()) + 1
    _, inv, counts = np.unique(2 * (e[:, 0] * n + e[:, 1]) + (first == e[:, 0]), return_inverse=True,
                               return_counts=True)
    same_way = counts[inv] > 1
    _, uinv, ucounts = np.unique(e[:, 0] * n + e[:, 1], return_inverse=True, return_counts=True)
    part = mesh_parts(F)
    n_parts = int(part.max()) + 1
    incoherent = np.zeros(n_parts, bool)
    incoherent[part[owner[same_way]]] = True
    closed = np.ones(n_parts, bool)
    closed[part[owner[ucounts[uinv] != 2]]] = False
    tri = V[F]
    volume = np.bincount(part, np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0, n_parts)
    odd = _nesting_depth(V, F, part, closed) % 2 == 1
    inverted = closed & ~incoherent & np.where(odd, volume > 0, volume < 0)
    away = _parts_facing_away(V, F, part, ~closed & ~incoherent, camera)
    out = F.copy()
    flip = (inverted | away)[part]
    out[flip] = out[flip][:, [0, 2, 1]]
    return out.astype(np.int32), {"inverted_parts_flipped": int(inverted.sum()),
                                  "open_parts_flipped": int(away.sum()),
                                  "inconsistent_winding_edges": int(same_way.sum() // 2)}, flip


def _faces_by_part(part, n_parts: int):
    """Faces grouped by part: (face ids sorted by part (F,), start of each part's run (P + 1,))."""
    order = np.argsort(part, kind="stable")
    return order, np.searchsorted(part[order], np.arange(n_parts + 1))


# Directions along which _nesting_depth takes a part's extreme vertices: the 3 axes, 6 face
# diagonals and 4 body diagonals of a cube (each way: 26 vertices).
_EXTREME_DIRECTIONS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1],
                                [0, 1, 1], [0, 1, -1], [1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], np.float64)
# ... and this many more of its vertices, evenly through its vertex list.
NESTING_SAMPLE_VERTICES = 256


def _nesting_depth(V, F, part, closed) -> np.ndarray:
    """(P,) int: for each closed part, how many other closed parts enclose it (0 for open parts).

    Part p lies inside closed part q when its sample vertices that it does not share with q all
    lie inside q (:func:`points_inside`: ray parity, whatever the winding). The sample is its extreme vertices along 13 directions (:data:`_EXTREME_DIRECTIONS`,
    both ways) and :data:`NESTING_SAMPLE_VERTICES` more: all of them, not one, so that a part
    poking out of another (an eyeball set into a closed head) is not inside it. Only pairs whose
    bounding boxes nest are tested.
    """
    n_parts = len(closed)
    depth = np.zeros(n_parts, np.int64)
    ids = np.flatnonzero(closed)
    if len(ids) < 2:
        return depth
    order, start = _faces_by_part(part, n_parts)
    verts = {p: np.unique(F[order[start[p]:start[p + 1]]]) for p in ids}
    lo = np.array([V[verts[p]].min(0) for p in ids])
    hi = np.array([V[verts[p]].max(0) for p in ids])
    for k, q in enumerate(ids):
        inside_box = (lo >= lo[k]).all(1) & (hi <= hi[k]).all(1) & (ids != q)
        if not inside_box.any():
            continue
        candidates, points = ids[inside_box], []
        for p in candidates:
            along = V[verts[p]] @ _EXTREME_DIRECTIONS.T
            spread = np.linspace(0, len(verts[p]) - 1, min(len(verts[p]), NESTING_SAMPLE_VERTICES)).astype(np.int64)
            sample = verts[p][np.r_[along.argmin(0), along.argmax(0), spread]]
            points.append(np.setdiff1d(sample, verts[q]))  # a shared vertex lies on q: parity undefined
        tested = np.array([len(x) > 0 for x in points])
        if not tested.any():
            continue
        inside = points_inside(V, F[order[start[q]:start[q + 1]]], V[np.concatenate(points)])
        owner = np.repeat(np.arange(len(candidates)), [len(x) for x in points])
        outside = np.bincount(owner, ~inside, len(candidates)) > 0
        depth[candidates[tested & ~outside]] += 1
    return depth


# The rays of :func:`points_inside` run along (RAY_SHEAR_X, RAY_SHEAR_Y, 1): off every axis, so
# that they do not run exactly along the edges of a grid-like mesh (a height field, a box).
RAY_SHEAR_X, RAY_SHEAR_Y = 0.1234567, 0.0765432


def _upward_crossings(X, Y, Z, F, px, py, pz, grid, out):
    """numba kernel of :func:`points_inside`: out[i] = how many triangles (X, Y, Z)[F] the vertical
    ray from (px, py, pz)[i] towards +Z crosses. Triangles are binned by their XY bounding box
    into a grid x grid table of cells over the mesh's XY box; a ray tests the triangles of its
    cell. Exactly-on-edge hits are not resolved (the callers' sheared rays make them unlikely)."""
    n_faces = F.shape[0]
    x0, x1, y0, y1 = np.inf, -np.inf, np.inf, -np.inf
    for f in range(n_faces):
        for k in range(3):
            v = F[f, k]
            x0, x1 = min(x0, X[v]), max(x1, X[v])
            y0, y1 = min(y0, Y[v]), max(y1, Y[v])
    sx = grid / max(x1 - x0, 1e-300)
    sy = grid / max(y1 - y0, 1e-300)
    lo = np.empty((n_faces, 2), np.int64)
    hi = np.empty((n_faces, 2), np.int64)
    count = np.zeros(grid * grid + 1, np.int64)
    for f in range(n_faces):
        a, b, c = F[f, 0], F[f, 1], F[f, 2]
        lo[f, 0] = min(grid - 1, int((min(X[a], X[b], X[c]) - x0) * sx))
        hi[f, 0] = min(grid - 1, int((max(X[a], X[b], X[c]) - x0) * sx))
        lo[f, 1] = min(grid - 1, int((min(Y[a], Y[b], Y[c]) - y0) * sy))
        hi[f, 1] = min(grid - 1, int((max(Y[a], Y[b], Y[c]) - y0) * sy))
        for i in range(lo[f, 0], hi[f, 0] + 1):
            for j in range(lo[f, 1], hi[f, 1] + 1):
                count[i * grid + j + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    cell_faces = np.empty(start[-1], np.int64)
    for f in range(n_faces):
        for i in range(lo[f, 0], hi[f, 0] + 1):
            for j in range(lo[f, 1], hi[f, 1] + 1):
                cell_faces[fill[i * grid + j]] = f
                fill[i * grid + j] += 1
    for k in range(px.shape[0]):
        out[k] = 0
        if not (x0 <= px[k] <= x1 and y0 <= py[k] <= y1):
            continue
        cell = min(grid - 1, int((px[k] - x0) * sx)) * grid + min(grid - 1, int((py[k] - y0) * sy))
        for m in range(start[cell], start[cell + 1]):
            f = cell_faces[m]
            a, b, c = F[f, 0], F[f, 1], F[f, 2]
            # barycentric coordinates of the ray's XY in the triangle's XY projection
            d = (X[b] - X[a]) * (Y[c] - Y[a]) - (X[c] - X[a]) * (Y[b] - Y[a])
            if d == 0.0:
                continue  # seen edge-on: the ray grazes it
            wb = ((px[k] - X[a]) * (Y[c] - Y[a]) - (X[c] - X[a]) * (py[k] - Y[a])) / d
            wc = ((X[b] - X[a]) * (py[k] - Y[a]) - (px[k] - X[a]) * (Y[b] - Y[a])) / d
            if wb < 0.0 or wc < 0.0 or wb + wc > 1.0:
                continue
            if Z[a] + wb * (Z[b] - Z[a]) + wc * (Z[c] - Z[a]) > pz[k]:
                out[k] += 1


_CROSSINGS_KERNEL = []  # compiled on first use: importing numba is slow, most users never need it


def points_inside(vertices, faces, points) -> np.ndarray:
    """(N,) bool: the points inside the closed mesh, by ray parity (an odd number of crossings of
    a ray from the point), whatever the winding of its faces.

    The ray of every point runs along (:data:`RAY_SHEAR_X`, :data:`RAY_SHEAR_Y`, 1). A point on the
    surface, or a ray through an edge or vertex exactly, may come out either way.

    Args:
        vertices: (V, 3) float. faces: (F, 3) int, a closed surface. points: (N, 3) float.
    """
    if not _CROSSINGS_KERNEL:
        from numba import njit  # slow to import; most runs never test points against a mesh
        _CROSSINGS_KERNEL.append(njit(cache=True, nogil=True)(_upward_crossings))
    V = np.asarray(vertices, np.float64)
    F = np.ascontiguousarray(faces, np.int64)
    P = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(P), np.int64)
    if len(F) == 0 or len(P) == 0:
        return out.astype(bool)
    # sheared so that the rays are vertical: (x, y) - z (RAY_SHEAR_X, RAY_SHEAR_Y)
    X = np.ascontiguousarray(V[:, 0] - RAY_SHEAR_X * V[:, 2])
    Y = np.ascontiguousarray(V[:, 1] - RAY_SHEAR_Y * V[:, 2])
    grid = int(np.clip(np.sqrt(len(F) / 2.0), 1, 1024))  # about 2 faces per cell of a surface seen from above
    # long slivers fall into many cells each: a coarser grid keeps the table within ~16 entries a face
    bx, by = X[F], Y[F]
    lo, span = np.array([bx.min(), by.min()]), np.array([np.ptp(bx), np.ptp(by)]) + 1e-300
    while grid > 1:
        cells = [np.minimum(grid - 1, ((b.max(1) - o) * grid / w).astype(np.int64))
                 - np.minimum(grid - 1, ((b.min(1) - o) * grid / w).astype(np.int64)) + 1
                 for b, o, w in ((bx, lo[0], span[0]), (by, lo[1], span[1]))]
        if int((cells[0] * cells[1]).sum()) <= 16 * len(F):
            break
        grid //= 2
    _CROSSINGS_KERNEL[0](X, Y, np.ascontiguousarray(V[:, 2]), F, P[:, 0] - RAY_SHEAR_X * P[:, 2],
                         P[:, 1] - RAY_SHEAR_Y * P[:, 2], np.ascontiguousarray(P[:, 2]), grid, out)
    return out % 2 == 1


# Longer side of the image of the camera :func:`_parts_facing_away` makes up when none is given
# (pixels), and the widest view angle it frames (tangent; 10 = 84 degrees off the axis).
FRAMING_CAMERA_PX = 512
FRAMING_CAMERA_MAX_TAN = 10.0


def _framing_camera(points, near: float = 1e-3):
    """(K (3, 3), width, height) of a pinhole at the origin looking along +z whose image frames
    ``points`` (those in front of it), :data:`FRAMING_CAMERA_PX` pixels on the longer side;
    None when no point is in front."""
    P = np.asarray(points, np.float64)
    P = P[P[:, 2] > near]
    if len(P) == 0:
        return None
    t = np.clip(P[:, :2] / P[:, 2:], -FRAMING_CAMERA_MAX_TAN, FRAMING_CAMERA_MAX_TAN)
    lo, hi = t.min(0), t.max(0)
    f = (FRAMING_CAMERA_PX - 1) / max(float((hi - lo).max()), 1e-9)
    width, height = (np.ceil((hi - lo) * f).astype(int) + 1).tolist()
    K = np.array([[f, 0.0, -lo[0] * f], [0.0, f, -lo[1] * f], [0.0, 0.0, 1.0]])
    return K, int(width), int(height)


def _parts_facing_away(V, F, part, candidates, camera=None) -> np.ndarray:
    """(P,) bool: the ``candidates`` parts most of whose area seen by the camera faces away from it.

    The whole mesh is rendered (:func:`stex.render.rasterize`, no back-face culling, so other
    parts occlude); each pixel counts for the face it shows, and a face faces the camera when the
    camera centre (the origin) lies on the side of its plane its normal points to. A part whose
    pixels facing away outnumber those facing the camera is marked; a part without pixels is not.

    Args:
        V, F: the mesh (metres, depth-camera coordinates; (F, 3) int).
        part: (F,) int part of each face. candidates: (P,) bool parts to decide.
        camera: :class:`stex.camera.Intrinsics` of the depth camera, or None for a pinhole at the
            origin looking along +z that frames the candidate parts (:func:`_framing_camera`).
    """
    away = np.zeros(len(candidates), bool)
    if not candidates.any():
        return away
    if camera is None:
        framing = _framing_camera(V[F[candidates[part]].ravel()])
        if framing is None:
            return away
        K, width, height = framing
    else:
        K, width, height = camera.K, camera.width, camera.height
    face_id = rasterize(V, F, K, width, height).face_id
    pixels = np.bincount(face_id[face_id >= 0], minlength=len(F)).astype(np.float64)
    v0 = V[F[:, 0]]
    facing = np.einsum("ij,ij->i", np.cross(V[F[:, 1]] - v0, V[F[:, 2]] - v0), -v0) > 0
    n_parts = len(candidates)
    towards = np.bincount(part, pixels * facing, n_parts)
    backwards = np.bincount(part, pixels * ~facing, n_parts)
    return candidates & (backwards > towards)


# --------------------------------------------------------------------------------------------
# decimation
# --------------------------------------------------------------------------------------------

def subdivide_midpoint(vertices, faces, corner_uv=None):
    """Split every triangle into four at its edge midpoints (shape unchanged: new vertices lie on
    the old faces). Returns (vertices (V + E, 3) float64, faces (4F, 3) int32), and with
    ``corner_uv`` ((F, 3, 2) texture coordinates of each face corner) the children's corner
    coordinates (4F, 3, 2), split at the midpoints the same way (the layout is unchanged)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.sort(e, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    mid = len(V) + inv.reshape(3, -1).T  # (F, 3): midpoints of edges 01, 12, 20
    V2 = np.concatenate([V, 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])])
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    F2 = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                         np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    if corner_uv is None:
        return V2, F2.astype(np.int32)
    t = np.asarray(corner_uv, np.float64)
    ta, tb, tc = t[:, 0], t[:, 1], t[:, 2]
    tab, tbc, tca = 0.5 * (ta + tb), 0.5 * (tb + tc), 0.5 * (tc + ta)
    T2 = np.concatenate([np.stack([ta, tab, tca], 1), np.stack([tab, tb, tbc], 1),
                         np.stack([tca, tbc, tc], 1), np.stack([tab, tbc, tca], 1)])
    return V2, F2.astype(np.int32), T2


# Weight of the texture coordinates in the texture-aware quadric (MeshLab's default 1): at 1 a
# decimated layout's charts can overlap, at 16 they keep apart without moving the surface
# (docs/decisions/template.md).
TEXTURE_QUADRIC_WEIGHT = 16.0


def decimate(vertices, faces, target_faces: int, corner_uv=None):
    """Quadric edge-collapse decimation (pymeshlab) to ``target_faces`` faces.

    Normals are preserved (no face flips), topology is preserved (no holes closed or opened,
    genus kept), boundaries are kept, planar regions get the planar quadric, vertices go to their
    quadric-optimal positions. Returns the input unchanged when it has at most ``target_faces``
    faces. With ``corner_uv`` the texture-aware variant runs (MeshLab's "with texture" filter:
    the quadric includes the texture coordinates with weight :data:`TEXTURE_QUADRIC_WEIGHT`, UV
    seams stay seams), which has no topology guard.

    Args:
        vertices: (V, 3) float, metres.
        faces: (F, 3) int.
        target_faces: wanted face count (> 0).
        corner_uv: optional (F, 3, 2) float texture coordinates of each face corner.

    Returns:
        (vertices (V', 3) float64 m, faces (F', 3) int32), unreferenced vertices removed; with
        ``corner_uv`` also the kept faces' corner coordinates (F', 3, 2) float64.
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int32)
    target_faces = int(target_faces)
    if target_faces < 1:
        raise ValueError(f"target_faces must be positive, got {target_faces}")
    if len(F) <= target_faces:
        out = (V.copy(), F.copy())
        return out if corner_uv is None else out + (np.array(corner_uv, np.float64),)
    import pymeshlab  # slow to import (and GPL-3.0): only decimation needs it

    # the quadrics' thresholds are absolute too (a millimetre sphere came out far off its
    # surface), so tiny faces are scaled up for it as for xatlas
    scale = working_scale(V, F)
    ms = pymeshlab.MeshSet()
    if corner_uv is None:
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=V * scale, face_matrix=F))
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=target_faces, qualitythr=0.3, preserveboundary=True, boundaryweight=1.0,
            preservenormal=True, preservetopology=True, optimalplacement=True, planarquadric=True,
            autoclean=True)
    else:
        _load_textured(ms, V * scale, F, np.asarray(corner_uv, np.float64))
        ms.meshing_decimation_quadric_edge_collapse_with_texture(
            targetfacenum=target_faces, qualitythr=0.3, extratcoordw=TEXTURE_QUADRIC_WEIGHT, preserveboundary=True,
            boundaryweight=1.0, optimalplacement=True, preservenormal=True, planarquadric=True)
    m = ms.current_mesh()
    V2 = np.asarray(m.vertex_matrix(), np.float64) / scale
    F2 = np.asarray(m.face_matrix(), np.int32)
    used = np.zeros(len(V2), bool)
    used[F2.ravel()] = True
    if not used.all():
        remap = np.cumsum(used) - 1
        V2, F2 = V2[used], remap[F2].astype(np.int32)
    if corner_uv is None:
        return V2, F2
    return V2, F2, np.asarray(m.wedge_tex_coord_matrix(), np.float64).reshape(-1, 3, 2)


def _load_textured(ms, V, F, corner_uv) -> None:
    """Add a mesh with per-corner texture coordinates to a pymeshlab MeshSet.

    MeshLab's texture-aware decimation also wants every face to name a texture, which pymeshlab's
    array constructor cannot set (the filter refuses "some faces without texture"), so the mesh
    goes through an OBJ with a one-texel material in a temporary folder. The coordinates are
    written as they are (MeshLab does not flip v); only their differences matter to it.
    """
    with tempfile.TemporaryDirectory(prefix="stex_decimate_") as d:
        d = Path(d)
        cv2.imwrite(str(d / "t.png"), np.zeros((1, 1, 3), np.uint8))
        (d / "m.mtl").write_text("newmtl m\nmap_Kd t.png\n")
        n = len(F)
        with open(d / "m.obj", "w") as fh:
            fh.write("mtllib m.mtl\n")
            np.savetxt(fh, V, fmt="v %.17g %.17g %.17g")
            np.savetxt(fh, corner_uv.reshape(-1, 2), fmt="vt %.17g %.17g")
            fh.write("usemtl m\n")
            idx = np.stack([F.astype(np.int64) + 1, np.arange(3 * n, dtype=np.int64).reshape(n, 3) + 1], 2)
            np.savetxt(fh, idx.reshape(n, 6), fmt="f %d/%d %d/%d %d/%d")
        ms.load_new_mesh(str(d / "m.obj"))
    if ms.current_mesh().face_number() != n:
        raise RuntimeError(f"pymeshlab read {ms.current_mesh().face_number()} of the {n} faces written for decimation")


def working_scale(vertices, faces) -> float:
    """Factor that brings a mesh of small faces to where xatlas and pymeshlab's decimation work:
    xatlas skips faces below an absolute area (about 1.2e-7, i.e. FLT_EPSILON), and the quadric
    decimation's thresholds are absolute too (docs/decisions/template.md). 1.0 when the median face
    area is at least 1e-6 m² (about that of a 20k-face template of a 10 cm object), so usual
    templates are untouched; else the factor that makes it 1e-4."""
    V = np.asarray(vertices, np.float64)
    tri = V[np.asarray(faces, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    med = float(np.median(area)) if len(area) else 0.0
    return 1.0 if med >= 1e-6 or med <= 0 else float(np.sqrt(1e-4 / med))


def face_areas_quality(vertices, faces):
    """(area (F,) in the vertices' units², quality (F,) in [0, 1]: 4 sqrt(3) area / sum of squared
    edge lengths, 1 for an equilateral triangle, 0 for a needle or a zero-area face)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    edges2 = sum(((tri[:, k] - tri[:, (k + 1) % 3]) ** 2).sum(1) for k in range(3))
    quality = np.where(edges2 > 0, 4 * np.sqrt(3) * area / np.maximum(edges2, 1e-300), 0.0)
    return area, quality


# --------------------------------------------------------------------------------------------
# adjacency, texel map
# --------------------------------------------------------------------------------------------

def face_adjacency(faces, return_nonmanifold: bool = False):
    """Faces sharing an edge.

    Every edge used by exactly two faces gives one pair. Edges used by more than two faces
    (non-manifold) give no pair; they are logged and, with ``return_nonmanifold``, returned.

    Args:
        faces: (F, 3) int vertex indices.

    Returns:
        pairs (E, 2) int32 face ids with pairs[:, 0] < pairs[:, 1], sorted by shared edge;
        edges (E, 2) int32 the shared edge's vertex ids, smaller first;
        and with ``return_nonmanifold`` the (N, 2) int32 non-manifold edges.
    """
    e, fid = _edge_table(faces)
    if len(e) == 0:
        z = np.zeros((0, 2), np.int32)
        return (z, z, z) if return_nonmanifold else (z, z)
    order = np.lexsort((fid, e[:, 1], e[:, 0]))
    e, fid = e[order], fid[order]
    new = np.ones(len(e), bool)
    new[1:] = (e[1:] != e[:-1]).any(1)
    start = np.flatnonzero(new)
    count = np.diff(np.append(start, len(e)))
    two = start[count == 2]
    pairs = np.stack([fid[two], fid[two + 1]], 1).astype(np.int32)
    edges = e[two].astype(np.int32)
    nm = e[start[count > 2]].astype(np.int32)
    if len(nm):
        log.warning("face adjacency: %d non-manifold edges have no face pair", len(nm))
    return (pairs, edges, nm) if return_nonmanifold else (pairs, edges)


def is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the mesh (V, 3) / (F, 3) is closed (watertight): only a closed template has an inside,
    and so links through the solid (:func:`volume_links_through_solid`)."""
    import trimesh  # slow to import; only closed-mesh checks need it

    return bool(trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                                process=False).is_watertight)


# --------------------------------------------------------------------------------------------
# embedding in the original surface
# --------------------------------------------------------------------------------------------

def embed_vertices(points, orig_vertices, orig_faces):
    """Closest point of each point on the original surface, as face id + barycentrics.

    Faces of zero area are skipped (their barycentrics are undefined). The search runs with the
    mesh scaled by a power of two that makes its median face area about 1: trimesh's
    closest-point test compares products of squared lengths with an absolute tolerance (1e-13),
    so with millimetre faces in metres it snapped points to edges and corners that are not the
    closest (docs/decisions/template.md).

    Args:
        points: (V, 3) float, metres.
        orig_vertices: (V0, 3) float, metres; orig_faces: (F0, 3) int.

    Returns:
        (face (V,) int32 original face id, bary (V, 3) float32 (sum 1), closest (V, 3) float64
        the closest points, distance (V,) float64 m).
    """
    import trimesh  # slow to import; only the closest-point search needs it

    F0 = np.asarray(orig_faces, np.int64)
    scale = _unit_area_scale(orig_vertices, F0)  # a power of two: scaling and back are exact
    V0 = np.asarray(orig_vertices, np.float64) * scale
    tri = V0[F0]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    ok = np.flatnonzero(area > 0)
    tm = trimesh.Trimesh(V0, F0[ok], process=False, validate=False)
    pts = np.asarray(points, np.float64) * scale
    closest, dist, tid = trimesh.proximity.closest_point(tm, pts)
    face = ok[tid]
    bary = trimesh.triangles.points_to_barycentric(tri[face], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(1, keepdims=True)
    return face.astype(np.int32), bary.astype(np.float32), closest / scale, np.asarray(dist) / scale


def _unit_area_scale(vertices, faces) -> float:
    """The power of two that brings the median non-zero face area of a mesh ((V, 3), (F, 3)) to
    within a factor 4 of 1 (1.0 for a mesh without area)."""
    area, _ = face_areas_quality(vertices, faces)
    area = area[area > 0]
    if not len(area):
        return 1.0
    return float(2.0 ** -np.round(0.5 * np.log2(np.median(area))))


def transfer_vertices(orig_frame_vertices, orig_faces, embedding_face, embedding_bary) -> np.ndarray:
    """Carry a mesh of the original topology to the template's topology.

    Args:
        orig_frame_vertices: (..., V0, 3) float, metres, e.g. one frame (V0, 3) or (T, V0, 3).
        orig_faces: (F0, 3) int, the original template's faces.
        embedding_face: (V,) int original face of each template vertex.
        embedding_bary: (V, 3) float barycentrics on that face.

    Returns:
        (..., V, 3) float64 template vertices: sum_k bary[:, k] * orig[faces[face, k]].
        Exact for any affine motion of the original (rigid motions included).
    """
    X = np.asarray(orig_frame_vertices, np.float64)
    corners = np.asarray(orig_faces, np.int64)[np.asarray(embedding_face, np.int64)]  # (V, 3)
    b = np.asarray(embedding_bary, np.float64)
    return np.einsum("...vkd,vk->...vd", X[..., corners, :], b)
