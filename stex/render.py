"""CPU rasterisation, visibility and textured rendering of triangle meshes (numba).

What it computes
----------------
- :func:`rasterize` — a z-buffer render of a triangle mesh given in camera coordinates: per-pixel
  depth (metres), the id of the nearest face and the perspective-correct barycentrics of the
  pixel centre on that face.
- :func:`face_normals`, :func:`vertex_normals` — unit normals (area-weighted for vertices).
- :func:`vertex_visibility`, :func:`face_visibility` — which vertices / faces the camera sees,
  by testing each *vertex* against the rendered depth map (face-id pixels alone miss the many
  faces smaller than a pixel), plus back-facing / grazing-angle rejection. The depth test
  compares against the surface's tangent plane, not a constant depth, so slanted surfaces are
  not mistaken for occluded ones (see the comment above ``_plane_depth_test``).
- :func:`interpolate_attributes`, :func:`sample_bilinear`, :func:`texcoords_to_pixels`,
  :func:`textured_raster`, :func:`sample_texture`, :func:`render_textured` — per-pixel attribute
  interpolation, bilinear image sampling and rendering of a textured mesh (synthetic scenes,
  evaluation, previews); the last is the two before it, which several textures on one mesh
  share.

Conventions
-----------
- Cameras are OpenCV pinholes (x right, y down, z forward, metres), see :mod:`stex.camera`.
  ``K`` is a (3, 3) matrix whose last row is (0, 0, 1); a skew ``K[0, 1]`` is honoured.
- Pixel (row r, column c) samples the image-plane point (u, v) = (c, r): integer pixel
  coordinates are pixel **centres**.
- Meshes are (V, 3) vertex positions in camera coordinates and (F, 3) vertex indices. Faces are
  counter-clockwise seen from outside (trimesh convention): the outward normal is
  (v1 - v0) x (v2 - v0).
- **Texture coordinates** (stated here once for stex): texcoords live in [0, 1]^2 with u to the
  right and v **downward**; (0, 0) is the top-left corner of the texture image (the glTF
  convention; OBJ/OpenGL files use v upward and are flipped, v -> 1 - v, at import/export only).
  The centre of texel (row r, column c) of a W x H texture is at ((c + 0.5) / W, (r + 0.5) / H),
  so texcoords map to texture pixel coordinates by (u * W - 0.5, v * H - 0.5)
  (:func:`texcoords_to_pixels`). Texcoords are indexed separately from positions
  (``texcoord_faces`` (F, 3) into ``texcoords`` (Vt, 2), like OBJ ``vt``), so UV seams work.

Rasterisation rules (deterministic)
-----------------------------------
- A triangle is drawn only if all three vertices have z > ``near``; triangles crossing or behind
  the near plane are **skipped entirely** (no clipping). For stex's use (an object well in front of
  the camera) this never triggers; it only makes bad input harmless.
- No back-face culling: the nearest surface wins whatever its orientation (open meshes show their
  inner side). Zero-area (in the image) triangles are skipped.
- Coverage is inclusive: a pixel centre exactly on an edge belongs to the triangle. Edge functions
  are evaluated with the edge's endpoints in a canonical (vertex-index) order and vertex
  projections are computed once per vertex, so two triangles sharing an edge get exactly opposite
  edge values: no cracks, no pixel missed between neighbours.
- Depth test: a fragment is written when its float32 depth is strictly less than the stored one.
  Faces are drawn in index order, so among fragments with equal float32 depth the **lowest face
  index wins**. The same input always gives the same bytes.

Why numba
---------
A numba z-buffer was faster on the project machine than headless OpenGL, pyrender and open3d
ray casting (docs/decisions/render.md), and it needs no system libraries. Kernels are ``@njit(cache=True, nogil=True)``: serial, but they release the
GIL so callers may render several frames from threads.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = [
    "Raster",
    "rasterize",
    "face_normals",
    "vertex_normals",
    "vertex_visibility",
    "face_visibility",
    "interpolate_attributes",
    "sample_bilinear",
    "texcoords_to_pixels",
    "textured_raster",
    "sample_texture",
    "render_textured",
]


class Raster(NamedTuple):
    """Result of :func:`rasterize` for an image of H rows and W columns.

    Attributes:
        depth: (H, W) float32, z (along the optical axis) of the nearest surface in metres;
            0 where no face covers the pixel centre.
        face_id: (H, W) int32, index of the nearest face; -1 where empty.
        bary: (H, W, 3) float32, perspective-correct barycentric coordinates of the pixel centre's
            surface point w.r.t. vertices (v0, v1, v2) of ``face_id`` (they sum to 1, so
            ``sum_i bary[..., i] * vertices[faces[face_id, i]]`` is the 3-D hit point); 0 where
            empty.
    """

    depth: np.ndarray
    face_id: np.ndarray
    bary: np.ndarray


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------

def check_vertices(vertices, name="vertices") -> np.ndarray:
    """``vertices`` as a contiguous (V, 3) float64 array; ValueError naming ``name`` and the first
    bad vertex when the shape, dtype or finiteness is wrong."""
    v = np.asarray(vertices)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {v.shape}")
    if not np.issubdtype(v.dtype, np.floating) and not np.issubdtype(v.dtype, np.integer):
        raise ValueError(f"{name} must be numeric, got dtype {v.dtype}")
    v = np.ascontiguousarray(v, dtype=np.float64)
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        n = int((~finite).sum())
        raise ValueError(
            f"{name} contain non-finite coordinates: vertex index {i} is {v[i].tolist()}"
            f" ({n} bad vertices in total)")
    return v


def check_faces(faces, n_vertices, name="faces") -> np.ndarray:
    """``faces`` as a contiguous (F, 3) int64 array ((0, 3) when empty); ValueError naming ``name``
    and the first bad face when the shape, dtype or an index outside [0, n_vertices) is wrong."""
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name} must have shape (F, 3), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {f.dtype}")
    f = np.ascontiguousarray(f, dtype=np.int64)
    lo, hi = int(f.min()), int(f.max())
    if lo < 0 or hi >= n_vertices:
        bad = int(np.flatnonzero(((f < 0) | (f >= n_vertices)).any(axis=1))[0])
        raise ValueError(
            f"{name} index out of range: face {bad} is {f[bad].tolist()} but there are "
            f"{n_vertices} vertices")
    return f


def _check_K(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"camera matrix K must be 3x3, got shape {K.shape}")
    if not np.isfinite(K).all() or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"camera matrix K must be finite with last row (0, 0, 1), got {K.tolist()}")
    return K


def _check_size(width, height):
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    return width, height


# --------------------------------------------------------------------------------------------
# rasterisation
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def project_vertices(V, K, near, px, py, iz):
    """Per-vertex pixel coordinates and 1/z (iz = 0 marks z <= near or a non-finite projection)."""
    fx, s, cx = K[0, 0], K[0, 1], K[0, 2]
    k10, fy, cy = K[1, 0], K[1, 1], K[1, 2]
    for i in range(V.shape[0]):
        x, y, z = V[i, 0], V[i, 1], V[i, 2]
        if z > near:
            inv = 1.0 / z
            px[i] = (fx * x + s * y) * inv + cx
            py[i] = (k10 * x + fy * y) * inv + cy
            iz[i] = inv
            if not (np.isfinite(px[i]) and np.isfinite(py[i])):
                iz[i] = 0.0  # overflow (|x| ~ 1e300): treat like a vertex behind the camera
        else:
            px[i] = 0.0
            py[i] = 0.0
            iz[i] = 0.0


@njit(cache=True, nogil=True)
def raster_kernel(V, F, K, near, depth, face_id, bary):
    """Z-buffer of the triangles F (F, 3) int64 of V (V, 3) float64 camera-space metres through the
    pinhole K into ``depth`` (H, W) float32 (0 = empty, as it starts), ``face_id`` (H, W) int32
    and ``bary`` (H, W, 3) float32, in place; triangles with a vertex at or behind
    ``near`` are skipped. See the module docstring for the rules."""
    H, W = depth.shape
    nv = V.shape[0]
    px = np.empty(nv)
    py = np.empty(nv)
    iz = np.empty(nv)
    project_vertices(V, K, near, px, py, iz)
    wmax = W - 1.0
    hmax = H - 1.0
    # per-edge line coefficients: E(p) = A*x + B*y + C for the edges opposite v0, v1, v2, i.e.
    # (v1,v2), (v2,v0), (v0,v1); E_k / sum(E) are the screen-space barycentrics
    A = np.empty(3)
    B = np.empty(3)
    C = np.empty(3)
    for f in range(F.shape[0]):
        i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
        iz0, iz1, iz2 = iz[i0], iz[i1], iz[i2]
        if iz0 == 0.0 or iz1 == 0.0 or iz2 == 0.0:
            continue  # a vertex at or behind the near plane: skip the triangle
        x0, y0 = px[i0], py[i0]
        x1, y1 = px[i1], py[i1]
        x2, y2 = px[i2], py[i2]
        # bounding box of pixel centres, clamped in float before converting to int
        xmin = max(np.ceil(min(x0, min(x1, x2))), 0.0)
        xmax = min(np.floor(max(x0, max(x1, x2))), wmax)
        if xmin > xmax:
            continue
        ymin = max(np.ceil(min(y0, min(y1, y2))), 0.0)
        ymax = min(np.floor(max(y0, max(y1, y2))), hmax)
        if ymin > ymax:
            continue
        area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        if area == 0.0:
            continue
        orient = 1.0 if area > 0.0 else -1.0
        # canonical edge orientation (lower vertex index first) -> exactly opposite values on
        # the two triangles sharing an edge; then flip to this triangle's orientation.
        for k in range(3):
            if k == 0:
                ia, ib = i1, i2
            elif k == 1:
                ia, ib = i2, i0
            else:
                ia, ib = i0, i1
            sgn = orient
            if ib < ia:
                ia, ib = ib, ia
                sgn = -sgn
            ax, ay = px[ia], py[ia]
            bx, by = px[ib], py[ib]
            a = -(by - ay)
            b = bx - ax
            c = -(a * ax + b * ay)
            A[k] = sgn * a
            B[k] = sgn * b
            C[k] = sgn * c
        A0, A1, A2 = A[0], A[1], A[2]
        c0, c1 = int(xmin), int(xmax)
        for r in range(int(ymin), int(ymax) + 1):
            fy_ = float(r)
            r0 = B[0] * fy_ + C[0]
            r1 = B[1] * fy_ + C[1]
            r2 = B[2] * fy_ + C[2]
            for c in range(c0, c1 + 1):
                fx_ = float(c)
                w0 = A0 * fx_ + r0
                if not w0 >= 0.0:
                    continue
                w1 = A1 * fx_ + r1
                if not w1 >= 0.0:
                    continue
                w2 = A2 * fx_ + r2
                if not w2 >= 0.0:
                    continue
                ws = w0 + w1 + w2
                if not ws > 0.0:
                    continue
                q0 = w0 * iz0
                q1 = w1 * iz1
                q2 = w2 * iz2
                qs = q0 + q1 + q2  # = ws / z
                z = np.float32(ws / qs)
                d = depth[r, c]
                if d == 0.0 or z < d:
                    depth[r, c] = z
                    face_id[r, c] = f
                    inv = 1.0 / qs
                    bary[r, c, 0] = q0 * inv
                    bary[r, c, 1] = q1 * inv
                    bary[r, c, 2] = q2 * inv


def rasterize(vertices, faces, K, width, height, near=1e-3) -> Raster:
    """Z-buffer render of a triangle mesh in camera coordinates.

    Args:
        vertices: (V, 3) float32/float64 vertex positions in camera coordinates, metres.
            Non-finite values raise ``ValueError`` naming the first bad vertex index.
        faces: (F, 3) integer (any int dtype) vertex indices; F may be 0.
        K: (3, 3) pinhole camera matrix (last row 0, 0, 1), pixels.
        width, height: image size W, H in pixels.
        near: near-plane distance in metres; triangles with any vertex at z <= near are skipped
            (not clipped).

    Returns:
        :class:`Raster` ``(depth (H, W) float32 metres, 0 = empty; face_id (H, W) int32, -1 =
        empty; bary (H, W, 3) float32 perspective-correct barycentrics)``. Pixel (r, c) samples
        the point (u, v) = (c, r). Ties in float32 depth go to the lowest face index; see the
        module docstring for the coverage rule.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    K = _check_K(K)
    W, H = _check_size(width, height)
    depth = np.zeros((H, W), dtype=np.float32)
    face_id = np.full((H, W), -1, dtype=np.int32)
    bary = np.zeros((H, W, 3), dtype=np.float32)
    if F.shape[0] > 0:
        raster_kernel(V, F, K, float(near), depth, face_id, bary)
    return Raster(depth, face_id, bary)


# --------------------------------------------------------------------------------------------
# normals
# --------------------------------------------------------------------------------------------

def _face_cross(V, F):
    v0 = V[F[:, 0]]
    return np.cross(V[F[:, 1]] - v0, V[F[:, 2]] - v0)


def _normalize_rows(n):
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.zeros_like(n)
    np.divide(n, norm, out=out, where=norm > 0)
    return out


def face_normals(vertices, faces) -> np.ndarray:
    """Unit face normals.

    Args:
        vertices: (V, 3) float positions; faces: (F, 3) int, counter-clockwise seen from outside.

    Returns:
        (F, 3) float64 unit vectors along (v1 - v0) x (v2 - v0) (outward for trimesh-convention
        meshes); zero rows for degenerate (zero-area) faces.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    return _normalize_rows(_face_cross(V, F))


@njit(cache=True, nogil=True, inline="always")
def _tri_cross(V, i0, i1, i2):
    """(v1 - v0) x (v2 - v0) of one triangle, as three floats."""
    ax = V[i1, 0] - V[i0, 0]
    ay = V[i1, 1] - V[i0, 1]
    az = V[i1, 2] - V[i0, 2]
    bx = V[i2, 0] - V[i0, 0]
    by = V[i2, 1] - V[i0, 1]
    bz = V[i2, 2] - V[i0, 2]
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(cache=True, nogil=True)
def _vertex_normals_kernel(V, F, out):
    out[:] = 0.0
    for f in range(F.shape[0]):
        i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
        # |cross| = 2 * area: area weighting for free
        nx, ny, nz = _tri_cross(V, i0, i1, i2)
        for i in (i0, i1, i2):
            out[i, 0] += nx
            out[i, 1] += ny
            out[i, 2] += nz
    for i in range(out.shape[0]):
        n = np.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2)
        if n > 0.0:
            out[i, 0] /= n
            out[i, 1] /= n
            out[i, 2] /= n


def _vertex_normals(V, F):
    out = np.empty_like(V)
    _vertex_normals_kernel(V, F, out)
    return out


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Args:
        vertices: (V, 3) float positions; faces: (F, 3) int, counter-clockwise seen from outside.

    Returns:
        (V, 3) float64: normalised sum of the incident faces' (v1 - v0) x (v2 - v0) (i.e. unit
        normals weighted by face area); zero rows for vertices used by no (non-degenerate) face.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    return _vertex_normals(V, F)


# --------------------------------------------------------------------------------------------
# visibility
# --------------------------------------------------------------------------------------------
#
# The depth test (is a point occluded?). A point P (a vertex) with surface normal n is compared
# with the rendered depth map D in the (2*window+1)^2 neighbourhood of its nearest pixel. For
# each non-empty pixel p of the neighbourhood, D[p] is compared with the depth, along p's ray, of
# the plane through P with normal n ("tangent plane"): z_plane(p) = (n . P) / (n . d_p) with
# d_p = K^-1 (c, r, 1) (pixels whose ray meets the plane behind the camera or from the other side
# are skipped). P passes if  min_p (D[p] - z_plane(p)) >= -depth_tol,  i.e. nothing in the
# neighbourhood is more than depth_tol in front of P's surface, and at least one pixel was
# compared (an all-empty neighbourhood fails). With n = (0, 0, -1)
# (``tangent_plane=False``) z_plane(p) = P_z and this is the plain test  P_z <= min_p D[p] + tol.
#
# Why the tangent plane: the plain test also rejects slanted surfaces whose own depth changes by
# more than depth_tol across the window; the tangent-plane test misses far fewer truly visible
# faces and accepts hardly any occluded ones (docs/decisions/render.md).
# The remaining misses are grazing faces at the foot of bumps, where the neighbour pixels cover a
# long stretch of surface that bends up in front of the face's plane.
# Why one-sided: a point in front of the rendered surface is not occluded (with the depth map of
# the same mesh this only happens for sub-pixel geometry at silhouettes, which is visible).

@njit(cache=True, nogil=True)
def _plane_depth_test(Px, Py, Pz, nx, ny, nz, K, Minv, depth, tol, window):
    H, W = depth.shape
    if not Pz > 0.0:
        return False
    u = (K[0, 0] * Px + K[0, 1] * Py) / Pz + K[0, 2]
    v = (K[1, 0] * Px + K[1, 1] * Py) / Pz + K[1, 2]
    # nearest pixel centre must be inside: [-0.5, W-0.5) x [-0.5, H-0.5)
    if not (u >= -0.5 and u < W - 0.5 and v >= -0.5 and v < H - 0.5):
        return False
    c = int(np.floor(u + 0.5))
    r = int(np.floor(v + 0.5))
    nP = nx * Px + ny * Py + nz * Pz
    compared = False
    for rr in range(max(r - window, 0), min(r + window, H - 1) + 1):
        b = rr - K[1, 2]
        for cc in range(max(c - window, 0), min(c + window, W - 1) + 1):
            d = depth[rr, cc]
            if d <= 0.0:
                continue
            a = cc - K[0, 2]
            dx = Minv[0, 0] * a + Minv[0, 1] * b
            dy = Minv[1, 0] * a + Minv[1, 1] * b
            nd = nx * dx + ny * dy + nz
            # the plane must be hit in front of the camera along this ray, from the side that
            # faces the camera at P (same sign of n.d and n.P); otherwise skip this pixel
            if nd * nP <= 0.0:
                continue
            compared = True
            # occluded if d - z_plane < -tol, z_plane = nP / nd (> 0); multiply instead of
            # dividing: d + tol < nP / nd  <=>  (d + tol) * nd > nP  when nd < 0 (and < when > 0)
            lhs = (d + tol) * nd
            if (nd < 0.0 and lhs > nP) or (nd > 0.0 and lhs < nP):
                return False
    # no comparable (non-empty) neighbour: not visible (nothing to take colour from)
    return compared


@njit(cache=True, nogil=True)
def _vertex_vis_kernel(V, N, K, Minv, depth, tol, window, plane, vis, cos):
    for i in range(V.shape[0]):
        Px, Py, Pz = V[i, 0], V[i, 1], V[i, 2]
        nx, ny, nz = N[i, 0], N[i, 1], N[i, 2]
        dist = np.sqrt(Px * Px + Py * Py + Pz * Pz)
        cs = 0.0
        if dist > 0.0:
            cs = -(nx * Px + ny * Py + nz * Pz) / dist
        cos[i] = max(cs, 0.0)
        vis[i] = False
        if not cs > 0.0:
            continue
        if not plane:
            nx, ny, nz = 0.0, 0.0, -1.0
        vis[i] = _plane_depth_test(Px, Py, Pz, nx, ny, nz, K, Minv, depth, tol, window)


@njit(cache=True, nogil=True)
def _face_vis_kernel(V, F, K, Minv, depth, tol, window, min_cos, plane, vis, cos):
    for f in range(F.shape[0]):
        i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
        nx, ny, nz = _tri_cross(V, i0, i1, i2)
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        cx = (V[i0, 0] + V[i1, 0] + V[i2, 0]) / 3.0
        cy = (V[i0, 1] + V[i1, 1] + V[i2, 1]) / 3.0
        cz = (V[i0, 2] + V[i1, 2] + V[i2, 2]) / 3.0
        dist = np.sqrt(cx * cx + cy * cy + cz * cz)
        cs = 0.0
        if nn > 0.0 and dist > 0.0:
            nx /= nn
            ny /= nn
            nz /= nn
            cs = -(nx * cx + ny * cy + nz * cz) / dist
        cs = min(max(cs, 0.0), 1.0)
        cos[f] = cs
        vis[f] = False
        if not (cs > 0.0 and cs > min_cos):
            continue
        if not plane:
            nx, ny, nz = 0.0, 0.0, -1.0
        ok = True
        for k in range(3):
            i = F[f, k]
            if not _plane_depth_test(V[i, 0], V[i, 1], V[i, 2], nx, ny, nz, K, Minv, depth,
                                     tol, window):
                ok = False
                break
        vis[f] = ok


def _check_depth(depth):
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be an (H, W) map, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        # the stores hold uint16 millimetres: read as metres every depth test would pass
        raise ValueError(f"depth must be float metres, got {d.dtype} (uint16 millimetres? divide by 1000)")
    return np.ascontiguousarray(d, dtype=np.float32)


def _check_window(window):
    window = int(window)
    if window < 0:
        raise ValueError(f"window must be >= 0, got {window}")
    return window


def vertex_visibility(vertices, faces, K, depth, depth_tol=0.01, window=1, tangent_plane=True):
    """Which vertices the camera sees, by a depth test against a rendered depth map.

    A vertex is visible if (1) its nearest pixel (round(u), round(v)) is inside the image,
    (2) it is not occluded: its z is at most ``depth_tol`` behind the minimum rendered depth over
    the non-empty pixels of the (2*window+1)^2 neighbourhood of that pixel (no non-empty pixel ->
    not visible); with ``tangent_plane=True`` (default) each neighbour pixel's depth is compared
    with the depth of the vertex's tangent plane along that pixel's ray instead of with z, so a
    slanted surface's own depth change across the window does not count as occlusion (identical
    to the plain test for a fronto-parallel surface; see the comment above
    ``_plane_depth_test`` for the measurements), and (3) its area-weighted vertex normal faces
    the camera: cos > 0 between the normal and the direction from the vertex to the camera
    centre (the origin). The test is one-sided: a vertex in front of the rendered surface is not
    occluded.

    Args:
        vertices: (V, 3) float camera-space positions, metres. faces: (F, 3) int (for normals).
        K: (3, 3) camera matrix of the depth map.
        depth: (H, W) float32 depth in metres, 0 = empty — normally ``rasterize(...).depth`` of
            the same mesh (render once, reuse).
        depth_tol: metres. window: neighbourhood half-size in pixels (1 -> 3x3).
        tangent_plane: see (2); False gives the plain z <= min depth + depth_tol test.

    Returns:
        visible: (V,) bool.
        cos: (V,) float32, cosine between vertex normal and direction to the camera, clipped at
            0, for **every** vertex (independent of the depth test; mask with ``visible``).
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    K = _check_K(K)
    depth = _check_depth(depth)
    window = _check_window(window)
    N = _vertex_normals(V, F)
    vis = np.zeros(V.shape[0], dtype=np.bool_)
    cos = np.zeros(V.shape[0], dtype=np.float64)
    if V.shape[0]:
        Minv = np.linalg.inv(K[:2, :2])
        _vertex_vis_kernel(V, N, K, Minv, depth, float(depth_tol), window, bool(tangent_plane),
                           vis, cos)
    return vis, cos.astype(np.float32)


def face_visibility(vertices, faces, K, depth, depth_tol=0.01, min_cos=0.0, window=1,
                    tangent_plane=True):
    """Which faces the camera sees fully, by vertex depth tests and the viewing angle.

    A face is visible if it is front-facing, cos(face normal, ray from the face centroid to the
    camera) > ``min_cos``, and none of its three vertices is occluded by the depth test of
    :func:`vertex_visibility` (nearest pixel inside the image, at most ``depth_tol`` behind the
    minimum rendered depth of the (2*window+1)^2 neighbourhood; with ``tangent_plane=True`` the
    comparison is against the **face's plane** along each neighbour pixel's ray; no per-vertex
    normal test). Faces smaller than a pixel, which own no pixel of a face-id buffer, are found
    this way; partially occluded faces are not visible.

    Args:
        vertices: (V, 3) float camera-space positions, metres. faces: (F, 3) int, counter-clockwise
            seen from outside.
        K: (3, 3) camera matrix of the depth map.
        depth: (H, W) float32 metres, 0 = empty — normally ``rasterize(...).depth``.
        depth_tol: metres. min_cos: minimum cosine (0 -> any front-facing face).
        window: neighbourhood half-size in pixels (1 -> 3x3).
        tangent_plane: False gives the plain z <= min depth + depth_tol vertex test.

    Returns:
        visible: (F,) bool.
        cos: (F,) float32, the viewing cosine clipped to [0, 1], for **every** face (0 for
            back-facing and degenerate faces; mask with ``visible``).
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    K = _check_K(K)
    depth = _check_depth(depth)
    window = _check_window(window)
    vis = np.zeros(F.shape[0], dtype=np.bool_)
    cos = np.zeros(F.shape[0], dtype=np.float64)
    if F.shape[0]:
        Minv = np.linalg.inv(K[:2, :2])
        _face_vis_kernel(V, F, K, Minv, depth, float(depth_tol), window, float(min_cos),
                         bool(tangent_plane), vis, cos)
    return vis, cos.astype(np.float32)


# --------------------------------------------------------------------------------------------
# attributes, sampling, textured rendering
# --------------------------------------------------------------------------------------------

def interpolate_attributes(raster: Raster, faces, attributes) -> np.ndarray:
    """Perspective-correct per-pixel interpolation of per-vertex attributes.

    Args:
        raster: a :class:`Raster` from :func:`rasterize`.
        faces: (F, 3) int indices into ``attributes`` — the faces used for rasterising, or any
            (F, 3) table with the same face order (e.g. OBJ-style texcoord faces).
        attributes: (N, D) or (N,) numeric per-vertex values.

    Returns:
        (H, W, D) float32 (or (H, W) for 1-D attributes): sum_i bary_i * attributes[faces[f, i]]
        at pixels with a face, 0 where empty.
    """
    attr = np.asarray(attributes)
    squeeze = attr.ndim == 1
    if squeeze:
        attr = attr[:, None]
    if attr.ndim != 2:
        raise ValueError(f"attributes must have shape (N, D) or (N,), got {np.shape(attributes)}")
    F = check_faces(faces, attr.shape[0], name="faces")
    fid = np.asarray(raster.face_id)
    H, W = fid.shape
    if fid.size and fid.max() >= F.shape[0]:
        raise ValueError(f"raster has face id {int(fid.max())} but only {F.shape[0]} faces were given")
    out = np.zeros((H, W, attr.shape[1]), dtype=np.float32)
    hit = fid >= 0
    if hit.any():
        f = F[fid[hit]]                              # (N, 3)
        b = np.asarray(raster.bary)[hit].astype(np.float64)  # (N, 3)
        a = attr.astype(np.float64, copy=False)
        val = (b[:, 0:1] * a[f[:, 0]] + b[:, 1:2] * a[f[:, 1]] + b[:, 2:3] * a[f[:, 2]])
        out[hit] = val
    return out[..., 0] if squeeze else out


@njit(cache=True, nogil=True, inline="always")
def bilinear_taps(u, v, W, H):
    """The four taps of a clamp-to-edge bilinear lookup at pixel coordinates (u, v) of a W x H
    image: (r0, c0, r1, c1, w00, w01, w10, w11). Shared by every bilinear kernel in stex."""
    u = min(max(u, 0.0), W - 1.0)
    v = min(max(v, 0.0), H - 1.0)
    c0 = int(np.floor(u))
    r0 = int(np.floor(v))
    c1 = min(c0 + 1, W - 1)
    r1 = min(r0 + 1, H - 1)
    a = u - c0
    b = v - r0
    return r0, c0, r1, c1, (1.0 - a) * (1.0 - b), a * (1.0 - b), (1.0 - a) * b, a * b


@njit(cache=True, nogil=True)
def _bilinear_kernel(img, uv, out):
    H, W, C = img.shape
    for i in range(uv.shape[0]):
        u = uv[i, 0]
        v = uv[i, 1]
        if not (u == u and v == v):
            for k in range(C):
                out[i, k] = np.nan
            continue
        r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(u, v, W, H)
        for k in range(C):
            out[i, k] = (w00 * img[r0, c0, k] + w01 * img[r0, c1, k]
                         + w10 * img[r1, c0, k] + w11 * img[r1, c1, k])


def _kernel_image(image, name: str, shapes: str) -> np.ndarray:
    """``image`` as an array the sampling kernels take: 2-D or 3-D, not empty, numeric; bool as
    uint8, float16 as float32, byte order native. ``name`` and ``shapes`` word the errors."""
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise ValueError(f"{name} must be {shapes}, got shape {img.shape}")
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{name} must not be empty, got shape {img.shape}")
    if img.dtype == np.bool_:
        return img.astype(np.uint8)
    if not np.issubdtype(img.dtype, np.number) or np.issubdtype(img.dtype, np.complexfloating):
        raise ValueError(f"{name} must be numeric, got dtype {img.dtype}")
    if img.dtype == np.float16 or not img.dtype.isnative:
        # the kernels are compiled for native-endian dtypes; float16 has no numba type
        return img.astype(np.float32 if img.dtype.kind == "f" else img.dtype.newbyteorder("="))
    return img


def sample_bilinear(image, uv) -> np.ndarray:
    """Bilinear image lookup with clamp-to-edge.

    Args:
        image: (H, W) or (H, W, C) array of any numeric dtype (bool is treated as 0/1).
        uv: (..., 2) float **pixel** coordinates, u = column, v = row; integer = pixel centre.
            Coordinates outside the image are clamped to [0, W-1] x [0, H-1] (equal to OpenCV's
            ``BORDER_REPLICATE``); NaN coordinates give NaN.

    Returns:
        float32 array of shape (..., C) for a 3-D image, (...) for a 2-D image.
    """
    img = _kernel_image(image, "image", "(H, W) or (H, W, C)")
    gray = img.ndim == 2
    img3 = np.ascontiguousarray(img[:, :, None] if gray else img)
    uv = np.asarray(uv, dtype=np.float64)
    if uv.shape[-1:] != (2,):
        raise ValueError(f"uv must have shape (..., 2), got {uv.shape}")
    lead = uv.shape[:-1]
    flat = np.ascontiguousarray(uv.reshape(-1, 2))
    out = np.empty((flat.shape[0], img3.shape[2]), dtype=np.float32)
    if flat.shape[0]:
        _bilinear_kernel(img3, flat, out)
    if gray:
        return out[:, 0].reshape(lead)
    return out.reshape(lead + (img3.shape[2],))


def texcoords_to_pixels(texcoords, width, height) -> np.ndarray:
    """Map stex texcoords ((..., 2) in [0, 1]^2, v downward, (0, 0) = top-left corner of the
    image) to float64 pixel coordinates (u * width - 0.5, v * height - 0.5) of a
    width x height texture (integer = texel centre)."""
    t = np.asarray(texcoords, dtype=np.float64)
    if t.shape[-1:] != (2,):
        raise ValueError(f"texcoords must have shape (..., 2), got {t.shape}")
    out = np.empty_like(t)
    out[..., 0] = t[..., 0] * width - 0.5
    out[..., 1] = t[..., 1] * height - 0.5
    return out


def textured_raster(vertices, faces, texcoords, texcoord_faces, K, width, height,
                    near=1e-3) -> tuple[Raster, np.ndarray, np.ndarray]:
    """Rasterise a textured mesh and interpolate its texture coordinates at the covered pixel
    centres: what :func:`render_textured` does before sampling, kept so that several textures
    on one mesh share it (:func:`sample_texture` per texture).

    Args:
        vertices, faces, texcoords, texcoord_faces, K, width, height, near: as
            :func:`render_textured`.

    Returns:
        raster: :class:`Raster`.
        mask: (H, W) bool, True where a face covers the pixel centre.
        uv: (N, 2) float64 texcoords of the N covered pixels in row-major order (the order of
            ``image[mask]``), interpolated with the raster's perspective-correct barycentrics.
    """
    V = check_vertices(vertices)
    F = check_faces(faces, V.shape[0])
    tc = np.asarray(texcoords, dtype=np.float64)
    if tc.ndim != 2 or tc.shape[1] != 2:
        raise ValueError(f"texcoords must have shape (Vt, 2), got {tc.shape}")
    TF = check_faces(texcoord_faces, tc.shape[0], name="texcoord_faces")
    if TF.shape[0] != F.shape[0]:
        raise ValueError(f"texcoord_faces has {TF.shape[0]} rows but faces has {F.shape[0]}")
    raster = rasterize(V, F, K, width, height, near=near)
    mask = raster.face_id >= 0
    f = TF[raster.face_id[mask]]
    b = raster.bary[mask].astype(np.float64)
    uv = b[:, 0:1] * tc[f[:, 0]] + b[:, 1:2] * tc[f[:, 1]] + b[:, 2:3] * tc[f[:, 2]]
    return raster, mask, uv


@njit(cache=True, nogil=True)
def _sample_texture_kernel(tex, uv, pixels, out, quantize):
    """out[pixels[i]] = the bilinear value of ``tex`` ((Ht, Wt, C)) at texcoords uv[i], as
    :func:`texcoords_to_pixels` then :func:`sample_bilinear` compute it (float32), and with
    ``quantize`` rounded half to even and clipped to 0..255 as numpy's rint and clip do."""
    Ht, Wt, C = tex.shape
    for i in range(uv.shape[0]):
        u = uv[i, 0] * Wt - 0.5
        v = uv[i, 1] * Ht - 0.5
        p = pixels[i]
        if not (u == u and v == v):
            for k in range(C):
                out[p, k] = np.nan
            continue
        r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(u, v, Wt, Ht)
        for k in range(C):
            x = np.float32(w00 * tex[r0, c0, k] + w01 * tex[r0, c1, k]
                           + w10 * tex[r1, c0, k] + w11 * tex[r1, c1, k])
            if quantize:
                x = min(max(np.rint(x), np.float32(0.0)), np.float32(255.0))
            out[p, k] = x


def sample_texture(mask, uv, texture, quantize: bool = False) -> np.ndarray:
    """An image of ``texture`` sampled bilinearly (clamp-to-edge) at the covered pixels.

    Args:
        mask, uv: from :func:`textured_raster`.
        texture: (Ht, Wt, C) (or (Ht, Wt)) image, any numeric dtype.
        quantize: round the samples (half to even) and clip them to 0..255.

    Returns:
        (H, W, C) (or (H, W)) float32 in the texture's value units, 0 where ``mask`` is False:
        the values of :func:`sample_bilinear` at :func:`texcoords_to_pixels` of ``uv``, in one
        pass that writes them into the image.
    """
    tex = np.asarray(texture)
    if tex.ndim not in (2, 3):
        raise ValueError(f"texture must be (Ht, Wt, C) or (Ht, Wt), got shape {tex.shape}")
    image = np.zeros(mask.shape + tex.shape[2:], dtype=np.float32)
    uv = np.asarray(uv, dtype=np.float64)
    if not uv.shape[0]:
        return image
    tex = _kernel_image(tex, "texture", "(Ht, Wt, C) or (Ht, Wt)")
    tex3 = np.ascontiguousarray(tex[:, :, None] if tex.ndim == 2 else tex)
    pixels = np.flatnonzero(mask)
    if len(pixels) != uv.shape[0]:
        raise ValueError(f"uv holds {uv.shape[0]} points for the mask's {len(pixels)} pixels")
    _sample_texture_kernel(tex3, np.ascontiguousarray(uv), pixels,
                           image.reshape(len(mask.ravel()), tex3.shape[2]), bool(quantize))
    return image


def render_textured(vertices, faces, texcoords, texcoord_faces, texture, K, width, height,
                    near=1e-3):
    """Render a textured mesh: rasterise, interpolate texcoords, sample the texture bilinearly
    (:func:`textured_raster`, then :func:`sample_texture`).

    Args:
        vertices: (V, 3) float camera-space positions, metres. faces: (F, 3) int.
        texcoords: (Vt, 2) float stex texcoords (see module docstring: v downward, glTF).
        texcoord_faces: (F, 3) int indices into ``texcoords``, one row per face (may differ from
            ``faces`` — UV seams).
        texture: (Ht, Wt, C) (or (Ht, Wt)) image, any numeric dtype.
        K, width, height, near: as in :func:`rasterize`.

    Returns:
        image: (H, W, C) (or (H, W)) float32 in the texture's value units (no rescaling of
            uint8), 0 where empty. Texcoords are interpolated with perspective-correct
            barycentrics, then sampled with :func:`sample_bilinear` (clamp-to-edge).
        mask: (H, W) bool, True where a face covers the pixel centre.
    """
    _, mask, uv = textured_raster(vertices, faces, texcoords, texcoord_faces, K, width, height, near)
    return sample_texture(mask, uv, texture), mask
