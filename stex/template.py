"""Template stage: clean, decimate and UV-unwrap the template mesh once for the whole sequence.

What it computes
----------------
- :func:`clean_mesh` — merges exactly duplicated vertices, drops degenerate and duplicated faces
  and unreferenced vertices, turns round the coherently wound parts that face the wrong way
  (closed parts by signed volume and nesting, open parts towards the depth camera), and reports
  non-manifold and boundary edges and faces of opposite winding (reported, not fixed).
- :func:`decimate` — pymeshlab quadric edge collapse to a target face count (the paper's
  templates have 10-30k faces; default 20k). A no-op when the mesh is already small enough.
- :func:`build_atlas` — a UV atlas from xatlas in one square ``resolution`` x ``resolution``
  texture with ``gutter_px`` empty texels between charts, and **no mirrored UV triangles**.
- :func:`keep_layout` — instead of a new atlas (``template.uv: mesh``), the mesh's own texture
  coordinates (an artist's layout), carried through cleaning, decimation (MeshLab's texture-aware
  quadric collapse) and subdivision, and refused where they tile or overlap.
- :func:`face_adjacency` — pairs of faces sharing a manifold edge and that edge.
- :func:`texel_map` — per texel of the atlas: the face whose UV triangle holds its centre and
  the barycentrics of that centre.
- :func:`embed_vertices` / :func:`transfer_vertices` — where each template vertex lies on the
  *original* template surface, so per-frame meshes of the original topology (``given/vertices``,
  ``truth/vertices`` in the scene store) can be carried to the decimated topology.
- :func:`prepare_template` / :func:`write_template` — the whole stage (scene store in,
  ``template`` store out, see :mod:`stex.io`).

Conventions
-----------
Vertices are metres in depth-camera coordinates (never recentred; the depth camera sits at the
origin looking along +z); faces are counter-clockwise seen from outside: from outside the solid for
closed parts (into its cavity for a cavity's wall), from the depth camera for open ones (a
single-view scan). Texcoords follow stex (see :mod:`stex.render`): u right, v **down**, origin at
the texture's top-left corner, texel (r, c) centred at ((c + .5) / W, (r + .5) / W).

**UV orientation.** With v pointing down, a UV triangle is *front-facing* (the texture image shows
the surface as seen from outside, not mirrored) when its signed area

    A = (u1 - u0) (v2 - v0) - (v1 - v0) (u2 - u0)

is **negative**: counter-clockwise on the screen with rows growing downward. (Exported to OBJ,
v -> 1 - v, this becomes the usual positive / counter-clockwise UV winding of OpenGL tools.)
:func:`uv_flipped` marks faces with A > 0; :func:`build_atlas` guarantees there are none.

Why xatlas mirrors charts, and the fix
--------------------------------------
xatlas' packer may "rotate" a chart by 90 degrees to pack it better (``PackOptions.rotate_charts``,
on by default), and it does so by swapping u and v — a *transposition*, i.e. a mirror image.
``ChartOptions.fix_winding`` does not help (it concerns the parameterisation, which is fine).
Measured: a subdivision-5 icosphere comes out with 10,240 of its 20,480 UV triangles mirrored
(3 of 6 charts); with ``rotate_charts`` off, none. :func:`build_atlas` therefore

1. charts and packs with xatlas' defaults (pass 1),
2. mirrors every chart whose area-weighted orientation is wrong (u -> -u, turning the
   transposition into a true 90-degree rotation); a face still wrong after that (a fold inside a
   chart; not observed so far) becomes a chart of its own and is mirrored alone,
3. repacks the fixed charts with xatlas (``use_input_mesh_uvs``, ``rotate_charts`` off, so no new
   mirror images) into exactly ``resolution`` x ``resolution`` texels, searching the texel density
   (texels per metre) that just fits one atlas,
4. mirrors back, each inside its own box, the small charts the repack returns wholly mirrored
   (a sliver triangle of a mesh from depth; 2-4-face fans at the pole of a noisy 500k-face scan),
   and checks that no triangle is mirrored and all texcoords lie in [0, 1].

xatlas skips faces below an absolute area (about 1.2e-7 in the mesh's units), so a mesh of tiny
faces is scaled up for it (:func:`working_scale`) and the texel density scaled back to texels per
metre. The scale comes from the median face area, so the faces of a small part (a 4 mm eye on a
10 cm body) can still fall below the limit: their UVs collapse, and a warning says how many faces
in which parts. (Scaling up until such parts' well-shaped faces clear the limit gave them UV area,
but xatlas then packed their few-texel charts closer than the gutter, 68-568 texels at 1024-2048^2.)

Steps 1-3 run in a child process (:func:`stex.isolated.call_in_child`) that exits without
destroying its xatlas atlas: ``xatlas::Destroy`` joins xatlas' worker threads and once waited for
them for good. The child costs about 0.3 s (a fresh interpreter importing numpy, xatlas and this
module).

Cost for 20k faces at 4096^2: charting ~3-5 s, each repack ~0.6 s (up to ``pack_search_steps``).
Which charts the packer transposes depends on the layout, so ``flipped_xatlas`` varies with the
resolution; the result never has mirrored triangles.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from stex.isolated import call_in_child

log = logging.getLogger("stex.template")

__all__ = [
    "clean_mesh",
    "nonmanifold_edges",
    "nonmanifold_vertices",
    "decimate",
    "build_atlas",
    "uv_signed_area",
    "uv_flipped",
    "layout_from_corners",
    "uv_overlaps",
    "outside_unit_square",
    "keep_layout",
    "uv_charts",
    "face_adjacency",
    "texel_map",
    "faces_without_texel",
    "gutter_conflicts",
    "border_gap",
    "embed_vertices",
    "transfer_vertices",
    "prepare_template",
    "write_template",
    "atlas_preview",
    "preview_template",
]


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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e, owner = _edge_table(faces)
    if len(e) == 0:
        return np.zeros(0, np.int64)
    key = e[:, 0] * (int(e.max()) + 1) + e[:, 1]  # 1-D keys: sorting them is ~10x faster than rows
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


_CROSSINGS_KERNEL = []  # compiled on first use: importing numba costs ~0.8 s, most users never need it


def points_inside(vertices, faces, points) -> np.ndarray:
    """(N,) bool: the points inside the closed mesh, by ray parity (an odd number of crossings of
    a ray from the point), whatever the winding of its faces.

    The ray of every point runs along (:data:`RAY_SHEAR_X`, :data:`RAY_SHEAR_Y`, 1). A point on the
    surface, or a ray through an edge or vertex exactly, may come out either way.

    Args:
        vertices: (V, 3) float. faces: (F, 3) int, a closed surface. points: (N, 3) float.
    """
    if not _CROSSINGS_KERNEL:
        from numba import njit
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
    from stex.render import rasterize

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


# Weight of the texture coordinates in the texture-aware quadric (MeshLab's default 1). At 1, a
# 100k-face bumpy sphere with an xatlas layout decimated to 20k faces had two charts overlapping
# (25 texels of 4096^2; 98.8 % of the texels still covered, surface point of a texel moved 2.1 mm
# at the 99th percentile); at 16: no overlap, 99.99 % covered, 0.39 mm, and the surface itself no
# farther from the input (mean 0.063 mm against 0.068). Same trend on an icosphere 1280 -> 640
# faces; it levels off from 4-16 up (benchmarks/bench_template.py --own-layout).
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
    import pymeshlab

    # the quadrics' thresholds are absolute too: at 1 mm scale a sphere came out up to 0.7 radii
    # off its surface, so tiny faces are scaled up for it as for xatlas
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
    import tempfile

    import cv2

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


# --------------------------------------------------------------------------------------------
# UV atlas
# --------------------------------------------------------------------------------------------

def uv_signed_area(texcoords, texcoord_faces) -> np.ndarray:
    """(F,) float64 signed area of each UV triangle, in texcoord units (u right, v down).

    Negative = front-facing in stex's convention (see the module docstring), positive = mirrored.
    """
    p = np.asarray(texcoords, np.float64)[np.asarray(texcoord_faces)]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]


def uv_flipped(texcoords, texcoord_faces) -> np.ndarray:
    """(F,) bool: UV triangles that are mirrored (signed area > 0 with v pointing down).

    Zero-area UV triangles are not counted as flipped (see :func:`uv_signed_area`).
    """
    return uv_signed_area(texcoords, texcoord_faces) > 0


def uv_charts(texcoord_faces, n_texcoords: int | None = None) -> np.ndarray:
    """(F,) int32 chart id of each face: connected components of faces sharing a texcoord.

    Charts are numbered by their lowest face index (chart 0 holds face 0).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tf = np.asarray(texcoord_faces, np.int64)
    F = len(tf)
    n_t = int(tf.max()) + 1 if n_texcoords is None else int(n_texcoords)
    # bipartite graph faces <-> texcoords; components restricted to faces
    rows = np.repeat(np.arange(F), 3)
    cols = F + tf.ravel()
    g = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(F + n_t, F + n_t))
    _, lab = connected_components(g, directed=False)
    lab = lab[:F]
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(first)  # component ids in order of first face
    relabel = np.empty(lab.max() + 1, np.int64)
    relabel[np.unique(lab)[order]] = np.arange(len(order))
    return relabel[lab].astype(np.int32)


def _xatlas_pack_options(resolution, gutter_px, rotate, texels_per_unit=0.0):
    import xatlas

    po = xatlas.PackOptions()
    po.resolution = int(resolution)
    po.padding = int(gutter_px)
    po.bilinear = True
    po.rotate_charts = bool(rotate)
    po.texels_per_unit = float(texels_per_unit)
    return po


def _repack(positions, tfaces, uv, resolution, gutter_px, texels_per_unit):
    """xatlas pack of given UV charts into one resolution^2 atlas; None if they do not fit."""
    import xatlas

    a = xatlas.Atlas()
    a.add_mesh(positions.astype(np.float32), tfaces.astype(np.uint32), None, uv.astype(np.float32))
    co = xatlas.ChartOptions()
    co.use_input_mesh_uvs = True
    a.generate(co, _xatlas_pack_options(resolution, gutter_px, False, texels_per_unit))
    if a.atlas_count != 1:
        return None
    if (a.width, a.height) != (resolution, resolution):
        raise RuntimeError(f"xatlas packed into {a.width}x{a.height}, expected {resolution}^2")
    vmap, idx, out_uv = a[0]
    return np.asarray(vmap, np.int64), np.asarray(idx, np.int64), np.asarray(out_uv, np.float64), a.utilization


def working_scale(vertices, faces) -> float:
    """Factor that brings a mesh of small faces to where xatlas and pymeshlab's decimation work:
    xatlas skips faces below an absolute area (about 1.2e-7, i.e. FLT_EPSILON; a 5 mm sphere of 5k
    faces got no chart at all), and the quadric decimation of a 1 mm sphere of 82k faces left
    vertices up to 0.7 radii off its surface. 1.0 when the median face area is at least 1e-6 m² (a 20k-face template of a 10 cm
    object has ~1.6e-6), so usual templates are untouched; else the factor that makes it 1e-4."""
    V = np.asarray(vertices, np.float64)
    tri = V[np.asarray(faces, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    med = float(np.median(area)) if len(area) else 0.0
    return 1.0 if med >= 1e-6 or med <= 0 else float(np.sqrt(1e-4 / med))


#: xatlas gives faces of less area than this (in its float32 input units; FLT_EPSILON) no chart.
XATLAS_MIN_AREA = 1.2e-7
#: Faces of at least this quality (:func:`_face_areas_quality`) count as well-shaped, not
#: needle-thin, in the warning about faces xatlas collapsed.
WELL_SHAPED_QUALITY = 0.2


def _face_areas_quality(vertices, faces):
    """(area (F,) in the vertices' units², quality (F,) in [0, 1]: 4 sqrt(3) area / sum of squared
    edge lengths, 1 for an equilateral triangle, 0 for a needle or a zero-area face)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    edges2 = sum(((tri[:, k] - tri[:, (k + 1) % 3]) ** 2).sum(1) for k in range(3))
    quality = np.where(edges2 > 0, 4 * np.sqrt(3) * area / np.maximum(edges2, 1e-300), 0.0)
    return area, quality


def _xatlas_layout(V, F, resolution, gutter_px, pack_search_steps):
    """xatlas' part of :func:`build_atlas` (steps 1-3 of the module docstring), run in a child
    process by :func:`stex.isolated.call_in_child`.

    Args:
        V: (V, 3) float64 vertices at the working scale; F: (F, 3) int64 faces.
        resolution, gutter_px, pack_search_steps: as :func:`build_atlas`.

    Returns:
        dict: ``vmap`` (Vt,) int64 and ``idx`` (F, 3) int64 (pass 1's texcoord -> vertex map and
        texcoord faces, folded faces split off), ``best``
        (vmap2, idx2, uv2 in [0, 1] of the inner square, xatlas utilisation) of the densest
        repack that fitted, or None, ``best_tpu`` its texel density (per working-scale unit),
        ``hi`` the lowest density that did not fit, ``info`` (flipped_xatlas, flipped_charts,
        fold_faces, time_chart_s, time_pack_s).
    """
    import xatlas

    inner = resolution - 2 * gutter_px
    info: dict = {}
    t0 = time.perf_counter()
    a = xatlas.Atlas()
    a.add_mesh(V.astype(np.float32), F.astype(np.uint32))
    co = xatlas.ChartOptions()
    co.fix_winding = True
    a.generate(co, _xatlas_pack_options(resolution, gutter_px, True))
    vmap, idx, uv = (np.asarray(x) for x in a[0])
    vmap, idx = vmap.astype(np.int64), idx.astype(np.int64)
    if idx.shape != F.shape or not np.array_equal(vmap[idx], F):
        raise RuntimeError("xatlas changed the faces (degenerate faces? run clean_mesh first)")
    w1, h1, tpu1 = a.width, a.height, float(a.texels_per_unit)
    info["time_chart_s"] = time.perf_counter() - t0

    # xatlas' uv have v growing with its image rows, and front-facing = positive area in them
    # (before its packer transposes charts). Work in texel units.
    px = uv.astype(np.float64) * [w1, h1]
    area = uv_signed_area(px, idx)
    info["flipped_xatlas"] = int((area < 0).sum())
    # each texcoord's chart, from xatlas (the same partition as uv_charts, without importing
    # scipy into the child: 0.4 s of its 0.7 s start; faces xatlas ignored share its "no chart"
    # label and have no UV area, so they are never mirrored either way)
    t_chart = np.unique(np.asarray(a.get_mesh_vertex_assignment(0)[1], np.int64), return_inverse=True)[1]
    t_chart = t_chart.reshape(-1)
    mirrored = np.bincount(t_chart[idx[:, 0]], area, int(t_chart.max()) + 1) < 0
    info["flipped_charts"] = int(mirrored.sum())
    px[mirrored[t_chart], 0] *= -1.0
    fold = uv_signed_area(px, idx) < 0
    info["fold_faces"] = int(fold.sum())
    if fold.any():  # each folded face becomes a chart of its own, mirrored
        fi = np.flatnonzero(fold)
        new = px[idx[fi]].reshape(-1, 2).copy()
        new[:, 0] *= -1.0
        base = len(px)
        px = np.concatenate([px, new])
        vmap = np.concatenate([vmap, vmap[idx[fi]].ravel()])
        idx = idx.copy()
        idx[fi] = base + np.arange(3 * len(fi)).reshape(-1, 3)

    # Repack into exactly inner^2: largest texel density (texels per metre) that fits.
    t1 = time.perf_counter()
    positions = V[vmap]
    uv_in = (px - px.min(0)) / max(float(np.ptp(px, axis=0).max()), 1e-12)
    tpu = tpu1 * inner / max(w1, h1)  # pass 1's density scaled to fill the atlas
    best, lo, hi, tries = None, None, None, 0
    while tries < pack_search_steps or best is None:
        if tries >= pack_search_steps + 30:
            break
        r = _repack(positions, idx, uv_in, inner, gutter_px, tpu)
        tries += 1
        if r is not None:
            best, lo = r, tpu
        else:
            hi = tpu
        if lo is not None and hi is not None and hi / lo < 1.01:
            break
        tpu = 0.92 * tpu if lo is None else 1.08 * tpu if hi is None else 0.5 * (lo + hi)
    info["time_pack_s"] = time.perf_counter() - t1
    return dict(vmap=vmap, idx=idx, best=best, best_tpu=lo, hi=hi, info=info)


def build_atlas(vertices, faces, resolution: int = 2048, gutter_px: int = 4, return_info: bool = False,
                pack_search_steps: int = 7, return_texels: bool = False):
    """A UV atlas of the mesh: xatlas charts packed into one square texture, no mirrored charts.

    See the module docstring for the procedure and why pass 1's charts need fixing.

    Args:
        vertices: (V, 3) float, metres.
        faces: (F, 3) int, counter-clockwise seen from outside; no degenerate faces
            (run :func:`clean_mesh` first).
        resolution: side of the square atlas W, texels.
        gutter_px: empty texels xatlas keeps around every chart (its ``padding``); with its
            bilinear reserve two charts end up at least 2 * gutter_px + 2 texels apart
            (measured with :func:`gutter_conflicts`). The charts are packed into the inner
            (resolution - 2 gutter_px)^2 texels, so that every chart also keeps gutter_px empty
            texels from the atlas border (:func:`border_gap`): xatlas itself packs up to half a
            texel from it, where a viewer's default REPEAT wrap (glTF) and any filter reach across
            to the opposite edge.
        return_info: also return a dict of statistics.
        pack_search_steps: repacks tried when searching the largest texel density that fits
            (bracket, then bisection to 1 %).
        return_texels: also return the atlas' :func:`texel_map` (made anyway for the statistics).

    Returns:
        texcoords (Vt, 2) float32 in [0, 1]^2 (u right, v down), texcoord_faces (F, 3) int32
        (face i of ``faces`` <-> row i), with ``return_info`` a dict: ``flipped_xatlas``
        (mirrored triangles in xatlas' own output), ``flipped_charts`` (charts mirrored back),
        ``fold_faces`` (faces split into their own chart), ``charts``, ``texels_per_unit``
        (texels per metre), ``utilization`` (fraction of the resolution^2 texels whose centre a
        UV triangle holds, as :func:`texel_map` rasterises it), ``xatlas_utilization`` (xatlas'
        own figure for the packed square, which counts its conservative chart rasters: higher),
        ``faces_without_texel`` (faces holding no texel centre), ``degenerate_uv_faces``,
        ``working_scale``, timings in s; and with ``return_texels`` the
        tuple (face_id (W, W) int32, bary (W, W, 3) float32) of :func:`texel_map`.

    Raises:
        RuntimeError: the charts do not fit one atlas even at a tiny texel density (the message
            names ``template.atlas_size`` and ``template.gutter_px``), or xatlas misbehaved.
    """
    F = np.asarray(faces, np.int64)
    scale = working_scale(vertices, F)  # texel densities below are per scaled unit
    V = np.asarray(vertices, np.float64) * scale
    resolution, gutter_px = int(resolution), int(gutter_px)
    if gutter_px < 0 or resolution - 2 * gutter_px < 8:
        raise ValueError(f"need gutter_px >= 0 and resolution - 2 gutter_px >= 8, got {resolution}, {gutter_px}")
    inner = resolution - 2 * gutter_px  # the charts' square: a gutter to the border on every side
    # xatlas runs in a child process that never destroys its atlas (its destructor can hang for
    # good, see stex.isolated)
    lay = call_in_child(_xatlas_layout, V, F, resolution, gutter_px, pack_search_steps)
    info = lay["info"]
    vmap, idx = lay["vmap"], lay["idx"]
    if info["fold_faces"]:
        log.warning("template: %d UV triangles folded inside their chart; split into own charts",
                    info["fold_faces"])
    if lay["best"] is None:
        # every chart takes at least a texel plus its padding, whatever the density
        n_charts = int(uv_charts(idx).max()) + 1  # folded faces included
        raise RuntimeError(f"xatlas could not pack the {n_charts} charts into one {inner}^2 "
                           f"atlas ({resolution}^2, template.atlas_size, less template.gutter_px {gutter_px} "
                           f"on each side) even at {lay['hi'] * scale:.3g} texels per metre; raise "
                           f"template.atlas_size or lower template.gutter_px")
    best_tpu = lay["best_tpu"]
    vmap2, idx2, uv2, util = lay["best"]
    if not np.array_equal(vmap[vmap2[idx2]], F):
        raise RuntimeError("xatlas repack changed the faces")
    texcoords = (uv2 * inner + gutter_px) / resolution  # the inner square, a gutter from each border
    texcoords[:, 1] = 1.0 - texcoords[:, 1]  # xatlas rows -> stex v (front-facing: area < 0)
    texcoords = texcoords.astype(np.float32)
    tfaces = idx2.astype(np.int32)
    flipped = uv_flipped(texcoords, tfaces)
    # Small charts can come back from the repack wholly mirrored: a triangle that pass 1 flattened
    # to a sliver (a mesh from depth), fans of 2-4 slivers at the pole of a noisy 500k-face scan.
    # A chart's corners are its own, so mirroring it inside its own box fixes it without moving
    # it or touching any other chart.
    chart2 = uv_charts(tfaces, len(texcoords))
    n2 = int(chart2.max()) + 1
    chart_faces = np.bincount(chart2, minlength=n2)
    whole = (np.bincount(chart2, flipped, n2) == chart_faces) & (chart_faces > 0)
    if whole.any():
        corner_chart = np.empty(len(texcoords), np.int64)
        corner_chart[tfaces.ravel()] = np.repeat(chart2, 3)
        sel = whole[corner_chart]
        lo = np.full(n2, np.inf)
        hi = np.full(n2, -np.inf)
        np.minimum.at(lo, corner_chart[sel], texcoords[sel, 0])
        np.maximum.at(hi, corner_chart[sel], texcoords[sel, 0])
        c = corner_chart[sel]
        texcoords[sel, 0] = (lo[c] + hi[c] - texcoords[sel, 0]).astype(np.float32)
    info["repack_mirrored_charts"] = int(whole.sum())
    flipped = uv_flipped(texcoords, tfaces)
    if flipped.any():
        bad = np.flatnonzero(flipped)
        raise RuntimeError(f"{len(bad)} UV triangles still mirrored after the fix (faces {bad[:10].tolist()}"
                           f"{' ...' if len(bad) > 10 else ''}, in {len(np.unique(chart2[bad]))} charts that are "
                           f"only partly mirrored)")
    if texcoords.min() < 0 or texcoords.max() > 1:
        raise RuntimeError("texcoords outside [0, 1] after packing")
    face_id, bary = texel_map(texcoords, tfaces, resolution)
    collapsed = uv_signed_area(texcoords, tfaces) == 0
    info.update(charts=n2, texels_per_unit=best_tpu * scale,  # mirroring back kept every chart
                utilization=float((face_id >= 0).mean()), xatlas_utilization=float(util),
                faces_without_texel=int(len(faces_without_texel(face_id, len(F)))),
                degenerate_uv_faces=int(collapsed.sum()), working_scale=scale)
    if collapsed.any():
        log.warning("template: %s", _collapsed_message(vertices, F, collapsed, scale))
    log.info("template: atlas %d^2, %d charts (%d mirrored by xatlas, %d triangles), %.1f%% used, "
             "%.1f s charting + %.1f s packing", resolution, info["charts"], info["flipped_charts"],
             info["flipped_xatlas"], 100 * info["utilization"], info["time_chart_s"], info["time_pack_s"])
    out = (texcoords, tfaces) + ((info,) if return_info else ())
    return out + ((face_id, bary),) if return_texels else out


def _collapsed_message(vertices, faces, collapsed, scale) -> str:
    """Why faces got no area in the atlas and where they are: ``collapsed`` (F,) bool, ``scale``
    the working scale xatlas saw the mesh at."""
    area, quality = _face_areas_quality(vertices, faces)
    part = mesh_parts(faces)
    hit = np.bincount(part[collapsed], minlength=int(part.max()) + 1)
    sizes = np.bincount(part)
    worst = np.argsort(-hit, kind="stable")[: min(3, int((hit > 0).sum()))]
    where = ", ".join(f"{hit[k]} of the {sizes[k]} faces of part {k}" for k in worst)
    limit = XATLAS_MIN_AREA / scale ** 2  # in m²
    small = int((collapsed & (area * scale ** 2 < XATLAS_MIN_AREA)).sum())
    thin = int((collapsed & (quality < WELL_SHAPED_QUALITY)).sum())
    return (f"{int(collapsed.sum())} faces have no area in the atlas, so each takes the colour of one texel: "
            f"{small} of them are below xatlas' area limit at the working scale x{scale:.3g} (faces under "
            f"{limit:.2g} m²; the scale follows the median face area, so a small part's faces can be under it), "
            f"{thin} are needle-thin; they lie in {int((hit > 0).sum())} of the mesh's {len(sizes)} connected parts "
            f"(numbered in face order: {where}); enlarge, thicken or remove such parts (template.min_part_faces "
            f"drops parts of few faces)")


def faces_without_texel(face_id, n_faces: int) -> np.ndarray:
    """(N,) int64 ids of the faces whose UV triangle holds no texel centre of the texel map
    ``face_id`` (W, W) int (-1 = empty): they have no texture of their own (a lookup on them reads
    neighbouring texels)."""
    has = np.zeros(int(n_faces), bool)
    fid = np.asarray(face_id)
    has[fid[fid >= 0]] = True
    return np.flatnonzero(~has)


def layout_from_corners(corner_uv):
    """Shared texture coordinates from per-corner ones: (texcoords (Vt, 2) float64, the distinct
    rows of ``corner_uv`` (F, 3, 2) in order of first use; texcoord_faces (F, 3) int32)."""
    t = np.asarray(corner_uv, np.float64).reshape(-1, 2)
    uniq, first, inv = np.unique(t, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return uniq[order], rank[inv.reshape(-1)].reshape(-1, 3).astype(np.int32)


def uv_overlaps(texcoords, texcoord_faces, size: int, face_id=None) -> tuple[int, tuple[int, int] | None]:
    """Texel centres that lie inside two or more UV triangles: (their number, (row, col) of one
    of them or None). The layout is rasterised (:func:`texel_map`) with the faces in order (or
    ``face_id``, that raster if already made) and in reverse; where the two disagree, a centre
    has two owners. The rasteriser counts a centre on an edge as inside every triangle that edge
    bounds, so a centre on a shared edge, or on the touching borders of two charts, has two owners
    too: such a centre counts only when it lies strictly inside both (more than 1e-6 texel from
    their edges)."""
    tf = np.asarray(texcoord_faces, np.int64)
    forward = texel_map(texcoords, tf, size)[0] if face_id is None else np.asarray(face_id)
    backward, _ = texel_map(texcoords, tf[::-1], size)
    backward = np.where(backward >= 0, len(tf) - 1 - backward, -1)
    rows, cols = np.nonzero(forward != backward)
    if len(rows):
        tc = np.asarray(texcoords, np.float64) * size - 0.5        # texel units, centres at integers
        centre = np.column_stack([cols, rows]).astype(np.float64)
        inside = np.ones(len(rows), bool)
        for owner in (forward, backward):
            f = owner[rows, cols]
            ok = f >= 0
            inside &= ok
            inside[ok] &= _strictly_inside(centre[ok], tc[tf[f[ok]]], 1e-6)
        rows, cols = rows[inside], cols[inside]
    return int(len(rows)), ((int(rows[0]), int(cols[0])) if len(rows) else None)


def _strictly_inside(p, tri, eps: float) -> np.ndarray:
    """(n, 2) points, (n, 3, 2) triangles -> (n,) bool: the point lies more than ``eps`` inside
    every edge (either winding; a triangle of zero area contains nothing). Signed areas by
    :func:`uv_signed_area`: of the triangle, and of each edge with the point."""
    idx = np.arange(3 * len(p)).reshape(-1, 3)
    sign = np.sign(uv_signed_area(tri.reshape(-1, 2), idx))
    out = sign != 0
    for i in range(3):
        a, b = tri[:, i], tri[:, (i + 1) % 3]
        twice_area = uv_signed_area(np.stack([a, b, p], 1).reshape(-1, 2), idx)
        out &= sign * twice_area / np.maximum(np.linalg.norm(b - a, axis=1), 1e-300) > eps
    return out


def outside_unit_square(uv) -> np.ndarray:
    """(..., 2) texture coordinates -> (...) bool: not finite or outside [0, 1] (a layout that
    tiles or wraps; a texture slice holds the unit square once)."""
    t = np.asarray(uv, np.float64)
    return ~np.isfinite(t).all(-1) | (t < 0).any(-1) | (t > 1).any(-1)


#: :func:`keep_layout` refuses a layout in which more than this fraction of the faces have zero UV
#: area: most faces would then share single texels (a few collapsed faces are only warned about).
MAX_COLLAPSED_UV_FRACTION = 0.5


def _refuse_collapsed_layout(area, texcoords) -> None:
    """Raise ValueError when more than :data:`MAX_COLLAPSED_UV_FRACTION` of the UV triangles
    (signed areas ``area`` (F,)) have zero area; ``texcoords`` (Vt, 2) for the message."""
    zero = int((area == 0).sum())
    if zero > MAX_COLLAPSED_UV_FRACTION * len(area):
        distinct = len(np.unique(np.asarray(texcoords), axis=0))
        raise ValueError(f"template.uv: mesh: {zero} of the {len(area)} faces have zero area in the mesh's texture "
                         f"coordinates (OBJ vt, glTF TEXCOORD_0; {distinct} distinct coordinate pairs): that is no "
                         f"layout that gives faces texels of their own; use template.uv: xatlas")


def keep_layout(corner_uv, resolution: int):
    """The mesh's own UV layout as the atlas (``template.uv: mesh``), checked for what one texture
    per face needs.

    Args:
        corner_uv: (F, 3, 2) float texture coordinates of each face corner, u right, v down.
        resolution: atlas side W, texels (the layout is read at this size; it is not moved).

    Returns:
        texcoords (Vt, 2) float32, texcoord_faces (F, 3) int32 (as :func:`build_atlas`), info
        dict: ``charts``, ``mirrored_faces`` (UV triangles mirrored in stex's convention: a
        layout may be mirrored as a whole, which nothing downstream minds),
        ``degenerate_uv_faces``, ``overlap_texels`` (0), ``utilization``.

    Raises:
        ValueError: coordinates outside [0, 1] (a layout that tiles or wraps), not finite, or
            UV triangles that overlap (several faces sharing texels, e.g. mirrored halves of a
            game asset painted once): a time-varying texture needs texels of its own for every
            face. Also a layout that holds no texel centre at all, or in which more than
            :data:`MAX_COLLAPSED_UV_FRACTION` of the faces have zero UV area (e.g. every
            coordinate (0, 0): an asset exported without a real layout). The message says where.
    """
    t = np.asarray(corner_uv, np.float64)
    bad = outside_unit_square(t).any(axis=1)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise ValueError(f"template.uv: mesh: {int(bad.sum())} faces have texture coordinates outside [0, 1] or not finite "
                         f"(e.g. {np.round(t[f], 4).tolist()}): a layout that tiles or wraps cannot give every "
                         f"face texels of its own; use template.uv: xatlas")
    texcoords, tfaces = layout_from_corners(t)
    area = uv_signed_area(texcoords, tfaces)
    _refuse_collapsed_layout(area, texcoords)
    face_id, _ = texel_map(texcoords, tfaces, resolution)
    if not (face_id >= 0).any():
        raise ValueError(f"template.uv: mesh: the mesh's texture coordinates (OBJ vt, glTF TEXCOORD_0) hold no texel "
                         f"centre of the {resolution}^2 atlas (template.atlas_size): its UV triangles are too small "
                         f"to carry a texture; use template.uv: xatlas")
    overlap, where = uv_overlaps(texcoords, tfaces, resolution, face_id)
    if overlap:
        r, c = where
        raise ValueError(f"template.uv: mesh: UV triangles overlap at {overlap} texels of the {resolution}^2 atlas "
                         f"(e.g. texel row {r}, column {c}: u {(c + .5) / resolution:.4f}, v {(r + .5) / resolution:.4f}, "
                         f"v down): faces sharing texels cannot each get their own texture (mirrored or "
                         f"stacked islands); lay them out apart, or use template.uv: xatlas")
    info = {"source": "mesh", "charts": int(uv_charts(tfaces, len(texcoords)).max()) + 1,
            "mirrored_faces": int((area > 0).sum()), "degenerate_uv_faces": int((area == 0).sum()),
            "overlap_texels": 0, "utilization": float((face_id >= 0).mean())}
    if info["degenerate_uv_faces"]:
        log.warning("template: %d faces have no area in the mesh's own UV layout: they take the colour of one "
                    "texel", info["degenerate_uv_faces"])
    log.info("template: the mesh's own UV layout at %d^2: %d charts, %.1f%% used, %d of %d triangles mirrored",
             resolution, info["charts"], 100 * info["utilization"], info["mirrored_faces"], len(tfaces))
    return texcoords.astype(np.float32), tfaces, info


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


def texel_map(texcoords, texcoord_faces, size: int):
    """Rasterise a UV layout: which face and where on it each texel centre lies.

    Texel (r, c) of a size x size atlas samples texcoord ((c + .5) / size, (r + .5) / size).
    A centre on a shared edge goes to one face; where UV triangles overlap, the lowest face
    index wins (see :func:`stex.render.rasterize`).

    Args:
        texcoords: (Vt, 2) float, u right, v down.
        texcoord_faces: (F, 3) int.
        size: atlas side W, texels.

    Returns:
        (face_id (size, size) int32, -1 where no face; bary (size, size, 3) float32, weights of
        the face's corners 0, 1, 2, summing to 1; 0 where no face).
    """
    from stex.render import rasterize

    tc = np.asarray(texcoords, np.float64)
    px = np.column_stack([tc[:, 0] * size - 0.5, tc[:, 1] * size - 0.5, np.ones(len(tc))])
    r = rasterize(px, texcoord_faces, np.eye(3), size, size)
    return r.face_id, r.bary


def atlas_digest(texcoords, texcoord_faces, size: int) -> str:
    """A short fingerprint (16 hex digits) of a UV atlas: its texcoords (Vt, 2), texcoord_faces
    (F, 3) and side ``size``. Texture stores record the one of the template they were made in
    (attr ``atlas_digest``), so that a texture of another atlas of the same side, which would
    read as noise on this one, is refused instead of scored (:func:`check_atlas`)."""
    import hashlib

    h = hashlib.sha256(str(int(size)).encode())
    # float32: the fingerprint of one layout does not depend on how its floats were stored
    h.update(np.ascontiguousarray(texcoords, np.float32).tobytes())
    h.update(np.ascontiguousarray(texcoord_faces, np.int32).tobytes())
    return h.hexdigest()[:16]


def template_atlas_digest(template) -> str:
    """:func:`atlas_digest` of an open ``template`` store."""
    return atlas_digest(template["texcoords"][...], template["texcoord_faces"][...],
                        int(template.attrs["atlas_size"]))


def check_atlas(stores, template, template_where) -> str:
    """Raise ValueError when one of ``stores`` ((where, open texture store) pairs, e.g. a
    sequence's block stores) records another atlas than the open ``template`` store's (at
    ``template_where``); stores without the attr (written before it existed) pass. Returns the
    template's :func:`atlas_digest` (computed once for all the stores)."""
    have = template_atlas_digest(template)
    for where, store in stores:
        made_in = store.attrs.get("atlas_digest")
        if made_in is not None and made_in != have:
            raise ValueError(f"{where} holds textures of another UV atlas than the template {template_where} "
                             f"(atlas {made_in}, the template's is {have}): a run's stores must come from "
                             f"one template (another run's or scene's?)")
    return have


def border_gap(face_id) -> int:
    """Empty texels between the atlas border and the nearest covered texel (face_id (W, W) int,
    -1 = empty, as :func:`texel_map` returns it); W when nothing is covered."""
    rows, cols = np.nonzero(np.asarray(face_id) >= 0)
    if not len(rows):
        return int(np.shape(face_id)[0])
    H, W = np.shape(face_id)
    return int(min(rows.min(), cols.min(), H - 1 - rows.max(), W - 1 - cols.max()))


def gutter_conflicts(face_id, face_chart, gutter_px: int) -> int:
    """Number of covered texels with a texel of *another* chart within ``gutter_px`` texels
    (Chebyshev distance): 0 means every two charts are at least ``gutter_px`` empty texels
    apart (at texel-centre coverage, as rasterised by :func:`texel_map`)."""
    from scipy import ndimage

    fid = np.asarray(face_id)
    lab = np.where(fid >= 0, np.asarray(face_chart)[np.maximum(fid, 0)], -1).astype(np.int32)
    if gutter_px <= 0:
        return 0
    size = 2 * int(gutter_px) + 1
    big = int(lab.max()) + 1  # (a huge cval would overflow inside ndimage)
    mx = ndimage.maximum_filter(lab, size=size, mode="constant", cval=-1)
    mn = ndimage.minimum_filter(np.where(lab >= 0, lab, big), size=size, mode="constant", cval=big)
    covered = lab >= 0
    return int((covered & ((mx != lab) | (mn != lab))).sum())


# --------------------------------------------------------------------------------------------
# embedding in the original surface
# --------------------------------------------------------------------------------------------

def embed_vertices(points, orig_vertices, orig_faces):
    """Closest point of each point on the original surface, as face id + barycentrics.

    Faces of zero area are skipped (their barycentrics are undefined). The search runs with the
    mesh scaled by a power of two that makes its median face area about 1: trimesh's
    closest-point test compares products of squared lengths with an absolute tolerance (1e-13),
    so with ~1 mm faces in metres it snapped points to edges and corners that are not the closest
    (0.18 mm off on a 10 cm sphere of 82k faces).

    Args:
        points: (V, 3) float, metres.
        orig_vertices: (V0, 3) float, metres; orig_faces: (F0, 3) int.

    Returns:
        (face (V,) int32 original face id, bary (V, 3) float32 (sum 1), closest (V, 3) float64
        the closest points, distance (V,) float64 m).
    """
    import trimesh

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
    area, _ = _face_areas_quality(vertices, faces)
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


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------

#: Fraction of the faces that may hold no texel centre without a warning. Tiny faces legitimately
#: miss every centre, but at the default 2048^2 none did on the fox (2304 faces after subdivision,
#: 0.6 m and 1.5 m), the demo's procedural body (9024), a KillingFusion template from depth (20k
#: after decimation) and a bumpy 82k-face sphere decimated to 20k; the 1.5 m fox at 256^2 has
#: 3.2 %, at 128^2 55 %.
MAX_FACES_WITHOUT_TEXEL = 0.01


def _warn_faces_without_texel(face_id, uv_area, size: int, gutter: int, keep_uv: bool) -> int:
    """Count the faces without a texel centre in ``face_id`` (W, W); warn, naming the settings,
    when those with UV area (``uv_area`` (F,) signed; collapsed ones are warned about where they
    collapse) exceed :data:`MAX_FACES_WITHOUT_TEXEL` of the faces."""
    n_faces = len(uv_area)
    missing = faces_without_texel(face_id, n_faces)
    n = int((uv_area[missing] != 0).sum())
    if n > MAX_FACES_WITHOUT_TEXEL * n_faces:
        fix = ("raise template.atlas_size (the mesh's own layout is read at that size)" if keep_uv else
               f"raise template.atlas_size (or lower template.gutter_px, now {gutter})")
        log.warning("template: %d of the %d faces (%.1f %%) hold no texel centre of the %d^2 atlas, so they get no "
                    "texture of their own (lookups on them read neighbouring texels): the atlas is too small for "
                    "the mesh; %s", n, n_faces, 100.0 * n / n_faces, size, fix)
    return int(len(missing))


def prepare_template(mesh, params: dict, camera=None) -> dict:
    """Run the template stage on a mesh.

    Args:
        mesh: :class:`stex.readers.meshes.Mesh` (original template, depth-camera coordinates, m).
        params: the ``template`` config section: ``target_faces``, ``decimate``, ``atlas_size``,
            ``gutter_px``, ``uv`` (``xatlas``: a new atlas; ``mesh``: the mesh's own texture
            coordinates, carried through cleaning, decimation and subdivision, see
            :func:`keep_layout`); completed with the schema's defaults and validated
            (:func:`stex.config.section_params`: unknown keys and bad values raise ValueError).
        camera: the scene's depth camera (:class:`stex.camera.Intrinsics`, e.g.
            ``Calibration.depth``): open parts of the mesh (a single-view scan) are turned to face
            what it sees of them (:func:`clean_mesh`). Its centre is the origin of the mesh's
            coordinates, looking along +z. None (default): a pinhole at the origin looking along
            +z that frames the open parts.

    Returns:
        dict with the ``template`` store's arrays (keys as in :data:`stex.io.ARTIFACTS`) and
        ``"attrs"``: a JSON-able dict of the stage's report.

    A warning names faces that hold no texel centre of the atlas when they are more than
    :data:`MAX_FACES_WITHOUT_TEXEL` of the faces (an atlas too small for the mesh).
    """
    from stex.config import section_params

    params = section_params("template", params)
    t0 = time.perf_counter()
    keep_uv = params["uv"] == "mesh"
    corner_uv = None
    if keep_uv:
        if mesh.texcoords is None or mesh.texcoord_faces is None:
            raise ValueError("template.uv is 'mesh' but the template mesh has no texture coordinates (OBJ vt, "
                             "glTF TEXCOORD_0); use template.uv: xatlas")
        corner_uv = np.asarray(mesh.texcoords, np.float64)[np.asarray(mesh.texcoord_faces, np.int64)]
    V, F, report, corners = clean_mesh(mesh.vertices, mesh.faces, return_corners=True, camera=camera)
    V, F, parts, kept = drop_small_parts(V, F, int(params["min_part_faces"]), return_kept=True)
    if keep_uv:  # the corners' coordinates follow the faces that stay, turned round or not
        corner_uv = corner_uv.reshape(-1, 2)[corners][kept]
    report.update(parts)
    if parts["dropped_parts"]:
        log.info("template: dropped %d of %d parts with fewer than %d faces (%d faces)", parts["dropped_parts"],
                 parts["parts"], int(params["min_part_faces"]), parts["dropped_faces"])
    extent = float(np.ptp(V, axis=0).max())
    if extent > 5.0:  # the tracking stage refuses it at the first frame; say why here already
        log.warning("template: the mesh is %.3g m across: an object one RGB-D camera films is under a few metres; "
                    "is it in millimetres or centimetres? (it must be in metres)", extent)
    log.info("template: cleaned %d -> %d faces (%s)", report["faces_in"], report["faces_out"],
             {k: report[k] for k in ("duplicate_vertices", "degenerate_faces", "duplicate_faces",
                                     "unreferenced_vertices", "nonmanifold_edges", "nonmanifold_vertices",
                                     "boundary_edges")})
    t1 = time.perf_counter()
    decimated = bool(params["decimate"]) and len(F) > int(params["target_faces"])
    if decimated and keep_uv:
        V, F, corner_uv = decimate(V, F, int(params["target_faces"]), corner_uv=corner_uv)
        log.info("template: decimated to %d faces, %d vertices (UV layout kept)", len(F), len(V))
    elif decimated:
        V, F = decimate(V, F, int(params["target_faces"]))
        log.info("template: decimated to %d faces, %d vertices", len(F), len(V))
    # Low-poly assets (e.g. game models) are split until they have enough vertices to carry the
    # tracker's data term; midpoint splits leave the shape exactly as it was.
    subdivided = 0
    while not decimated and len(F) * 4 <= int(params["min_faces"]):
        if keep_uv:
            V, F, corner_uv = subdivide_midpoint(V, F, corner_uv)
        else:
            V, F = subdivide_midpoint(V, F)
        subdivided += 1
    if subdivided:
        log.info("template: subdivided %d times to %d faces", subdivided, len(F))
    t2 = time.perf_counter()
    # Keep the template on the original surface so that transfer_vertices reproduces it exactly.
    emb_face, emb_bary, closest, dist = embed_vertices(V, mesh.vertices, mesh.faces)
    V = closest
    t3 = time.perf_counter()
    size, gutter = int(params["atlas_size"]), int(params["gutter_px"])
    if keep_uv:
        tc, tf, info = keep_layout(corner_uv, size)
        face_id, bary = texel_map(tc, tf, size)
    else:
        tc, tf, info, (face_id, bary) = build_atlas(V, F, size, gutter, return_info=True, return_texels=True)
    t4 = time.perf_counter()
    pairs, edges = face_adjacency(F)
    info["faces_without_texel"] = _warn_faces_without_texel(face_id, uv_signed_area(tc, tf), size, gutter, keep_uv)
    chart = uv_charts(tf, len(tc))
    conflicts = gutter_conflicts(face_id, chart, gutter)
    whose = " in the mesh's own UV layout (bilinear lookups there mix in the neighbour)" if keep_uv else ""
    if conflicts:
        log.warning("template: %d texels closer than %d texels to another chart%s", conflicts, gutter, whose)
    to_border = border_gap(face_id)
    if to_border < gutter:
        log.warning("template: a chart %d texels from the atlas border (gutter %d)%s", to_border, gutter, whose)
    t5 = time.perf_counter()
    attrs = {
        "atlas_size": size, "gutter_px": gutter,
        "counts": {"vertices": len(V), "faces": len(F), "texcoords": len(tc), "charts": info["charts"],
                   "adjacent_pairs": len(pairs), "covered_texels": int((face_id >= 0).sum()),
                   "faces_in": int(len(mesh.faces))},
        "clean_report": report,
        "decimated": decimated,
        "subdivided": subdivided,
        "uv": "mesh" if keep_uv else "xatlas",
        "flipped_fixed": info.get("flipped_xatlas", 0),
        "atlas": {k: v for k, v in info.items()},
        "gutter_conflicts": conflicts,
        "border_gap_px": to_border,
        "embedding_max_distance_m": float(dist.max()) if len(dist) else 0.0,
        "timings_s": {"clean": t1 - t0, "decimate": t2 - t1, "embed": t3 - t2, "atlas": t4 - t3,
                      "adjacency_texels": t5 - t4},
    }
    return {
        "vertices": V.astype(np.float32), "faces": F.astype(np.int32),
        "texcoords": tc, "texcoord_faces": tf, "face_chart": chart,
        "adjacency/pairs": pairs, "adjacency/edges": edges,
        "texel/face_id": face_id, "texel/bary": bary,
        "embedding/face": emb_face, "embedding/bary": emb_bary,
        "attrs": attrs,
    }


def hidden_from_color(depth_m, calibration, select, tolerance_m: float = 0.05) -> np.ndarray:
    """(Hd, Wd) bool: depth pixels in ``select`` that the colour camera cannot see, because a
    selected point more than ``tolerance_m`` nearer lands within a depth pixel's footprint of them
    in the colour image.

    The two cameras are a few centimetres apart, so background just beside the object in the depth
    image can land behind the object in the colour image, inside its mask. The tolerance keeps the
    object's own receding sides (tiny scene, stride 1: 2 cm drops 18 % of its silhouette, 5 cm 6 %,
    and the background strip either way).
    """
    import cv2

    from stex.camera import depth_pixels_in_color

    out = np.zeros(depth_m.size, bool)
    idx, px, z = depth_pixels_in_color(depth_m, calibration, select)
    if idx.size == 0:
        return out.reshape(depth_m.shape)
    c = calibration.color
    zbuf = np.full((c.height, c.width), np.inf, np.float32)
    np.minimum.at(zbuf, (px[:, 1], px[:, 0]), z.astype(np.float32))
    # a depth pixel covers about this many colour pixels: the nearest surface over that footprint
    k = 2 * int(np.ceil(c.fx / calibration.depth.fx)) + 1
    zbuf = cv2.erode(zbuf, np.ones((k, k), np.uint8))
    out[idx] = z > zbuf[px[:, 1], px[:, 0]] + tolerance_m
    return out.reshape(depth_m.shape)


def template_from_frame(depth_mm, mask_color, calibration, stride: int = 2, max_jump_m: float = 0.05):
    """A template from one frame: the surface its depth image sees inside its colour mask.

    The mask is carried into the depth image (:func:`stex.tracking.mask_in_depth`), without the
    points the colour camera cannot see (:func:`hidden_from_color`: background behind the object
    that lands in its mask); depth pixels without a value are carried into the colour image at the
    object's median depth and kept where they land in the mask; the region is closed and its holes
    filled. Pixels without a value in it get the depth of their nearest valid pixel in the mask,
    then a 5-px median smooths the result.
    :func:`template_from_depth` turns it into triangles (``stride`` depth px apart; no triangle
    across a depth jump of ``max_jump_m``, e.g. a nose in front of a chest).

    Args:
        depth_mm: (Hd, Wd) uint16 depth, millimetres, 0 = invalid. mask_color: (Hc, Wc) bool.
        calibration: :class:`stex.camera.Calibration`.

    Returns:
        (vertices (V, 3) float64 depth-camera metres, faces (F, 3) int32), faces towards the camera.
    """
    import cv2
    from scipy import ndimage

    from stex.camera import depth_pixels_in_color
    from stex.tracking import mask_in_depth

    mask_color = np.asarray(mask_color, bool)
    d = np.asarray(depth_mm).astype(np.float64) / 1000.0
    seen = mask_in_depth(mask_color, np.asarray(depth_mm), calibration)
    seen &= ~hidden_from_color(d, calibration, seen)
    if not seen.any():
        raise ValueError("template_from_frame: no valid depth inside the mask")
    # depth pixels without a value cannot be carried into the colour image by their own depth:
    # they are carried at the object's median depth (the parallax error is small at its distance)
    idx, px, _ = depth_pixels_in_color(np.full(d.shape, float(np.median(d[seen]))), calibration)
    no_depth = np.zeros(d.size, bool)
    no_depth[idx] = mask_color[px[:, 1], px[:, 0]]
    no_depth = no_depth.reshape(d.shape) & (d <= 0)
    k = 2 * stride + 1
    region = ndimage.binary_fill_holes(cv2.morphologyEx((seen | no_depth).astype(np.uint8), cv2.MORPH_CLOSE,
                                                        np.ones((k, k), np.uint8)) > 0)
    # every pixel takes its nearest object depth before the median, so that the median at the
    # silhouette does not mix in the background or zeros
    nearest = ndimage.distance_transform_edt(~seen, return_distances=False, return_indices=True)
    filled = np.where(region, cv2.medianBlur(d[tuple(nearest)].astype(np.float32), 5), 0.0)
    return template_from_depth(filled, calibration.depth.K, region, stride=stride, max_jump_m=max_jump_m)


def write_template(scene_path, params: dict, out, frames_path=None, masks_path=None) -> None:
    """Read the template mesh from the ``scene`` store, run the stage, write the ``template`` store.

    With ``params['from_depth']`` the mesh is instead :func:`template_from_frame` of the first
    frame of ``frames_path`` (a ``frames`` store) inside its mask from ``masks_path``.
    """
    from stex.camera import Calibration
    from stex.config import section_params
    from stex.io import create_store, open_store
    from stex.readers.meshes import Mesh

    # defaults filled in, as the store records them; refuses uv: mesh with from_depth too
    params = section_params("template", params)
    scene = open_store(scene_path, "scene")
    has_template = scene.attrs.get("has_template", False) and "template/vertices" in scene
    if params["from_depth"]:
        if frames_path is None or masks_path is None:
            raise ValueError("template.from_depth needs the first frame block and its masks")
        frames, masks = open_store(frames_path, "frames"), open_store(masks_path, "masks")
        fid = int(frames.attrs["frame_ids"][0])
        if has_template:
            log.warning("template: template.from_depth is set, so the source's template mesh is not used")
        if "given/vertices" in scene:
            log.warning("template: the source's per-frame meshes refer to its own template, not to one from "
                        "depth; tracking.mode given cannot use them")
        try:
            V, F = template_from_frame(frames["depth"][0], masks["mask"][0],
                                       Calibration.from_dict(scene.attrs["calibration"]),
                                       stride=int(params["from_depth_stride_px"]))
        except ValueError as e:
            raise ValueError(f"{frames_path}: frame {fid}: template.from_depth: {e}") from e
        log.info("template: %d faces from the depth of frame %d", len(F), fid)
        mesh, origin = Mesh(V, F), f"depth of frame {fid}"
    elif has_template:
        has_uv = "template/texcoords" in scene and "template/texcoord_faces" in scene
        mesh = Mesh(np.asarray(scene["template/vertices"][...], np.float64),
                    np.asarray(scene["template/faces"][...], np.int32),
                    np.asarray(scene["template/texcoords"][...], np.float64) if has_uv else None,
                    np.asarray(scene["template/texcoord_faces"][...], np.int32) if has_uv else None)
        origin = "source"
    else:
        kind = (scene.attrs.get("source") or {}).get("kind", "<kind>")
        raise ValueError(f"{scene_path}: the source has no template mesh; set source.{kind}.template, or "
                         f"template.from_depth to build one from the first frame's depth (one view only)")
    calibration = scene.attrs.get("calibration")
    # the mesh is in depth-camera coordinates at frame 0: open parts are turned to face that camera
    camera = Calibration.from_dict(calibration).depth if calibration else None
    try:
        result = prepare_template(mesh, params, camera=camera)
    except (ValueError, RuntimeError) as e:  # name the mesh: the stage's errors speak of faces only
        raise type(e)(f"{scene_path}: template ({origin}): {e}") from e
    attrs = result.pop("attrs")
    attrs["origin"] = origin
    with create_store(out, "template", attrs=attrs, params=params) as store:
        for name, arr in result.items():
            store.write(name, arr)
    log.info("template: wrote %s (%d faces, atlas %d^2)", out, attrs["counts"]["faces"], attrs["atlas_size"])


# --------------------------------------------------------------------------------------------
# preview
# --------------------------------------------------------------------------------------------

def atlas_preview(texcoords, texcoord_faces, face_chart, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 RGB picture of the atlas: each chart in its own colour (the same
    hue family, lighter towards higher face ids inside a chart), empty texels dark grey."""
    import colorsys

    face_id, _ = texel_map(texcoords, texcoord_faces, size)
    chart = np.asarray(face_chart)
    n = int(chart.max()) + 1 if len(chart) else 0
    golden = 0.618033988749895
    palette = np.array([colorsys.hsv_to_rgb((k * golden) % 1.0, 0.55 + 0.35 * ((k * 7) % 3) / 2, 0.95)
                        for k in range(max(n, 1))]) * 255
    img = np.full((size, size, 3), 40, np.uint8)
    hit = face_id >= 0
    img[hit] = palette[chart[face_id[hit]]].astype(np.uint8)
    return img


def preview_template(template_path, out_png, size: int = 1024) -> None:
    """Write the atlas picture of a ``template`` store to ``out_png``."""
    from stex.io import open_store
    from stex.preview import _label, write_png

    g = open_store(template_path, "template")
    img = atlas_preview(g["texcoords"][...], g["texcoord_faces"][...], g["face_chart"][...], size)
    c = g.attrs["counts"]
    title = (f"atlas {g.attrs['atlas_size']}^2, {c['charts']} charts, {c['faces']} faces, "
             f"gutter {g.attrs['gutter_px']} px")
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    write_png(out_png, _label(img, title))


# --------------------------------------------------------------------------------------------
# a template from one depth image
# --------------------------------------------------------------------------------------------

def template_from_depth(depth_m, K, mask=None, stride: int = 2, max_jump_m: float = 0.02):
    """A triangle mesh of the surface one depth image sees (for sources without a template).

    Pixels on a grid of ``stride`` that have valid depth (and lie in ``mask``) become vertices;
    each grid square whose corners are valid and whose depth range is below ``max_jump_m``
    becomes two triangles, oriented so that their normals face the camera (the outside).

    Args:
        depth_m: (H, W) float depth in metres, 0 = invalid. K: (3, 3) depth camera matrix.
        mask: (H, W) bool foreground, or None.

    Returns:
        (vertices (V, 3) float64 camera-space metres, faces (F, 3) int32).
    """
    from stex.camera import backproject_depth

    d = np.asarray(depth_m, np.float64)
    if not np.isfinite(d).all():
        raise ValueError("depth has non-finite values")
    ok = d > 0
    if mask is not None:
        ok &= np.asarray(mask, bool)
    P = backproject_depth(d, K)[::stride, ::stride]
    ok = ok[::stride, ::stride]
    z = d[::stride, ::stride]
    h, w = ok.shape
    index = np.full((h, w), -1, np.int64)
    index[ok] = np.arange(ok.sum())
    a, b, c, e = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    zs = np.stack([z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]])
    good = (a >= 0) & (b >= 0) & (c >= 0) & (e >= 0) & (zs.max(0) - zs.min(0) < max_jump_m)
    # Image x right, y down, camera looking along +z: (a, c, b) winds towards the camera.
    t1 = np.stack([a[good], c[good], b[good]], 1)
    t2 = np.stack([b[good], c[good], e[good]], 1)
    faces = np.concatenate([t1, t2])
    if len(faces) == 0:
        raise ValueError("no valid depth surface to build a template from (empty mask or depth?)")
    V = P[ok]
    used = np.unique(faces)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[faces].astype(np.int32)
