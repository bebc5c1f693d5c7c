"""Textures of another UV layout carried into the run's atlas.

Another method's textures (the authors' ``TextureMappingNonRigid``, a different template
stage, another run's atlas) live in their own UV layout: another mesh of the same object, in the
same coordinates as the run's template, with its own texture coordinates. To score them beside
ours, every texel of the run's atlas reads the other texture where the other mesh holds the same
surface point:

1. the texel's point on the run's template: its face and barycentrics (``texel/face_id``,
   ``texel/bary`` of the ``template`` store) on the template's vertices;
2. the closest point of the other mesh (:func:`closest_surface_points`: exact point-triangle
   distances over the triangles near each small cube of points, each answer proven exact by a
   distance bound or else taken from trimesh);
3. that point's texture coordinates in the other layout, interpolated with its barycentrics;
4. per texture, a bilinear read there (:meth:`AtlasTransfer.apply`, the renderer's
   clamp-to-edge lookup) after the other texture's
   empty texels next to its charts took their nearest chart colour (so bilinear reads at a chart's
   border do not mix in the background).

Texels farther than ``max_distance_m`` from the other mesh read nothing (black: untextured for
the coverage scores); a mesh farther than that from most of the template is refused (wrong
coordinates or units). :func:`atlas_transfer` builds the map once; applying it to a slice is one
bilinear lookup per texel (:func:`stex.render.sample_bilinear`, as the renderer reads textures).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from stex.atlas import outside_unit_square, texel_map
from stex.mesh import nonmanifold_edges
from stex.render import check_faces, check_vertices, sample_bilinear, texcoords_to_pixels
from stex.sampling import fill_gutter

log = logging.getLogger("stex.resample")

__all__ = ["closest_surface_points", "AtlasTransfer", "atlas_transfer"]

GUTTER_FILL_PX = 2        # rings of the other texture's empty texels filled before bilinear reads
CHUNK_TEXELS = 1 << 20    # texels whose closest points are found together (memory)


@njit(cache=True, nogil=True)
def _closest_on_triangle(tri, j, px, py, pz):
    """Closest point of triangle ``tri[j]`` (3, 3) to (px, py, pz) (Ericson, Real-Time Collision
    Detection 5.1.5) as barycentric weights (wa, wb, wc); scalar code, no temporaries."""
    ax, ay, az = tri[j, 0, 0], tri[j, 0, 1], tri[j, 0, 2]
    abx, aby, abz = tri[j, 1, 0] - ax, tri[j, 1, 1] - ay, tri[j, 1, 2] - az
    acx, acy, acz = tri[j, 2, 0] - ax, tri[j, 2, 1] - ay, tri[j, 2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0
    # b - p = ap - ab
    d3 = d1 - (abx * abx + aby * aby + abz * abz)
    d4 = d2 - (acx * abx + acy * aby + acz * abz)
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return 1.0 - v, v, 0.0
    # c - p = ap - ac
    d5 = d1 - (abx * acx + aby * acy + abz * acz)
    d6 = d2 - (acx * acx + acy * acy + acz * acz)
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return 1.0 - w, 0.0, w
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - w, w
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return 1.0 - v - w, v, w


@njit(cache=True, parallel=True)
def _closest_in_cells(points, cell_of, centre, reach, cand_ptr, cand, tri):
    """Per point: the closest of its cell's candidate triangles, and whether that is proven to be
    the closest of all (its distance at most ``reach`` − |point − cell centre|)."""
    n = points.shape[0]
    face = np.full(n, -1, np.int64)
    bary = np.zeros((n, 3))
    dist = np.full(n, np.inf)
    proven = np.zeros(n, np.bool_)
    for i in prange(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        c = cell_of[i]
        best = np.inf
        for m in range(cand_ptr[c], cand_ptr[c + 1]):
            j = cand[m]
            wa, wb, wc = _closest_on_triangle(tri, j, px, py, pz)
            qx = wa * tri[j, 0, 0] + wb * tri[j, 1, 0] + wc * tri[j, 2, 0] - px
            qy = wa * tri[j, 0, 1] + wb * tri[j, 1, 1] + wc * tri[j, 2, 1] - py
            qz = wa * tri[j, 0, 2] + wb * tri[j, 1, 2] + wc * tri[j, 2, 2] - pz
            d = qx * qx + qy * qy + qz * qz
            if d < best:
                best = d
                face[i] = j
                bary[i, 0] = wa
                bary[i, 1] = wb
                bary[i, 2] = wc
        best = np.sqrt(best)
        dist[i] = best
        ex, ey, ez = px - centre[c, 0], py - centre[c, 1], pz - centre[c, 2]
        proven[i] = best <= reach - np.sqrt(ex * ex + ey * ey + ez * ez)
    return face, bary, dist, proven


def _surface_samples(tri, spacing):
    """Points on every triangle (a barycentric grid of n_t = ceil(longest edge / spacing)
    steps) and their triangle ids: every point of a triangle is within ``spacing`` of one of its
    own samples (a grid cell's edges are at most longest edge / n_t)."""
    longest = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2).max(1)
    steps = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
    pts, ids = [], []
    for n in np.unique(steps):
        sel = np.flatnonzero(steps == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        ok = i + j <= n
        w = np.column_stack([i[ok], j[ok], n - i[ok] - j[ok]]) / n     # (m, 3)
        pts.append(np.einsum("mk,tkd->tmd", w, tri[sel]).reshape(-1, 3))
        ids.append(np.repeat(sel, len(w)))
    return np.concatenate(pts), np.concatenate(ids)


def closest_surface_points(points, vertices, faces):
    """The closest point of a triangle mesh to each point, exactly.

    Each triangle is sampled so that every point of it lies within s (half the median edge) of
    one of its samples. The points are binned in cubes of side s; a cube's candidate triangles
    are those with a sample within R = (its half-diagonal + 2 s) of its centre. Every other
    triangle is farther than R − s from the centre, so a point's closest candidate (numba) is
    proven the closest of all when its distance is at most R − s − |point − centre|: always for
    points on or near the surface. The rest (points about s or more off the mesh) are answered
    by ``trimesh.proximity.closest_point``. Faces of zero area are skipped.

    Args:
        points: (n, 3) float, metres. vertices: (V, 3) float, metres; faces: (F, 3) int.

    Returns:
        (face (n,) int64 index into ``faces``, bary (n, 3) float64 weights of its corners (sum 1),
        distance (n,) float64 m).
    """
    from scipy.spatial import cKDTree  # scipy.spatial loads slowly; only the closest points need it

    P = np.ascontiguousarray(points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got shape {P.shape}")
    if not np.isfinite(P).all():
        raise ValueError(f"points hold {int((~np.isfinite(P).all(1)).sum())} non-finite points")
    V = check_vertices(vertices)
    F = check_faces(faces, len(V))  # the rasteriser's checks: shape, integer, index range
    tri_all = V[F]
    area = np.linalg.norm(np.cross(tri_all[:, 1] - tri_all[:, 0], tri_all[:, 2] - tri_all[:, 0]), axis=1)
    keep = np.flatnonzero(area > 0)
    if len(keep) == 0:
        raise ValueError("the mesh has no face of non-zero area")
    if len(P) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    tri = np.ascontiguousarray(tri_all[keep])
    spacing = 0.5 * float(np.median(np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2)))
    samples, owner = _surface_samples(tri, spacing)
    # points in cubes of side s
    h = spacing
    origin = P.min(axis=0)
    ijk = P - origin
    ijk /= h
    ijk = np.floor(ijk, out=ijk).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])
    cells, cell_of = np.unique(key, return_inverse=True)
    cz, rest = np.divmod(cells, dims[0] * dims[1])
    cy, cx = np.divmod(rest, dims[0])
    centre = origin + (np.column_stack([cx, cy, cz]) + 0.5) * h
    reach = h * np.sqrt(3.0) / 2.0 + 2.0 * spacing     # R
    near = cKDTree(samples).query_ball_point(centre, reach, workers=-1)
    cand_lists = [np.unique(owner[np.asarray(x, np.int64)]) for x in near]
    cand_ptr = np.zeros(len(cells) + 1, np.int64)
    cand_ptr[1:] = np.cumsum([len(x) for x in cand_lists])
    cand = np.concatenate(cand_lists).astype(np.int64) if cand_ptr[-1] else np.zeros(0, np.int64)
    face, bary, dist, proven = _closest_in_cells(P, cell_of.astype(np.int64).ravel(), centre,
                                                 reach - spacing, cand_ptr, cand, tri)
    unproven = np.flatnonzero(~proven)
    if len(unproven):
        import trimesh  # loads slowly; only the points the cells cannot prove need it

        tm = trimesh.Trimesh(V, F[keep], process=False, validate=False)
        closest, d, tid = trimesh.proximity.closest_point(tm, P[unproven])
        b = trimesh.triangles.points_to_barycentric(tri[tid], closest)
        b = np.clip(b, 0.0, None)
        face[unproven], bary[unproven] = tid, b / b.sum(1, keepdims=True)
        dist[unproven] = d
    log.debug("closest points: %d of %d proven exact, %d by trimesh", len(P) - len(unproven),
              len(P), len(unproven))
    return keep[face], bary, dist


@dataclass
class AtlasTransfer:
    """Where each texel of the run's atlas reads a texture of another UV layout.

    texel_uv: (W, W, 2) float32 texture coordinates (u right, v down, [0, 1]) in the other
    layout of every covered texel of the run's atlas; NaN where the texel reads nothing.
    covered: (W, W) bool, texels inside the run's charts. distance_m: (W, W) float32, texel to
    the other mesh, metres (NaN where uncovered). other_texcoords (Vt', 2), other_texcoord_faces
    (F', 3): the other layout, rasterised (cached per texture side) to fill its gutter before
    reading. gutter_px: rings of the run's gutter filled after reading.
    """

    texel_uv: np.ndarray
    covered: np.ndarray
    distance_m: np.ndarray
    other_texcoords: np.ndarray
    other_texcoord_faces: np.ndarray
    gutter_px: int = 4
    _other_covered: dict = field(default_factory=dict, repr=False)   # texture side -> (S, S) bool

    @property
    def reads(self) -> np.ndarray:
        """(W, W) bool, texels that read the other texture."""
        return np.isfinite(self.texel_uv[..., 0])

    def apply(self, texture) -> np.ndarray:
        """(W, W, 3) uint8: ``texture`` ((S, S, 3) uint8 in the other layout) in the run's atlas;
        texels that read nothing are black, and the run's gutter is filled from its charts."""
        tex = np.asarray(texture)
        if tex.ndim != 3 or tex.shape[2] != 3 or tex.dtype != np.uint8 or tex.shape[0] != tex.shape[1]:
            raise ValueError(f"expected a square (S, S, 3) uint8 texture in the other layout, got "
                             f"{tex.shape} {tex.dtype}")
        S = tex.shape[0]
        if S not in self._other_covered:
            self._other_covered[S] = texel_map(self.other_texcoords, self.other_texcoord_faces, S)[0] >= 0
        other_cov = self._other_covered[S]
        src = np.array(tex, order="C", copy=True)
        fill_gutter(src, other_cov, other_cov, GUTTER_FILL_PX)
        reads = self.reads
        # the renderer's bilinear clamp-to-edge lookup, rounded to grey levels
        vals = sample_bilinear(src, texcoords_to_pixels(self.texel_uv[reads], S, S))
        out = np.zeros(self.texel_uv.shape[:2] + (3,), np.uint8)
        out[reads] = np.clip(np.floor(vals + 0.5), 0, 255).astype(np.uint8)
        # the gutter around the run's charts (texels that read nothing stay black)
        fill_gutter(out, self.covered, self.covered, self.gutter_px)
        return out


def _interpolate(bary, corners, values):
    """(n, d) sum_k bary[:, k] * values[corners[:, k]], one corner at a time (no (n, 3, d)
    temporary: 8 M texels at paper scale)."""
    out = bary[:, :1] * values[corners[:, 0]]
    for k in (1, 2):
        out += bary[:, k:k + 1] * values[corners[:, k]]
    return out


def atlas_transfer(texel_face, texel_bary, vertices, faces, other_vertices, other_faces,
                   other_texcoords, other_texcoord_faces, max_distance_m: float = 0.01,
                   gutter_px: int = 4, where: str = "the other mesh") -> AtlasTransfer:
    """The map from another UV layout into the run's atlas (see the module docstring).

    Args:
        texel_face: (W, W) int, template face per texel, -1 = none; texel_bary: (W, W, 3) float
            (``template`` store ``texel/face_id``, ``texel/bary``).
        vertices: (V, 3) float m, faces (F, 3) int: the run's template.
        other_vertices (V', 3) float m, other_faces (F', 3) int, other_texcoords (Vt', 2) float
            (u right, v down), other_texcoord_faces (F', 3) int: the other layout's mesh, in the
            template's coordinates.
        max_distance_m: texels farther than this from the other mesh read nothing.
        gutter_px: rings of the run's gutter filled after each transfer (the template's gutter).
        where: names the other mesh in errors.

    Raises:
        ValueError if the other mesh has no texture coordinates or is farther than
        ``max_distance_m`` from most texels (not in the template's coordinates).
    """
    if other_texcoords is None or other_texcoord_faces is None:
        raise ValueError(f"{where}: no texture coordinates (an OBJ with vt, or a glTF with TEXCOORD_0, is needed)")
    tf = np.asarray(texel_face)
    W = tf.shape[0]
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    TF = np.asarray(other_texcoord_faces, np.int64)
    T = np.asarray(other_texcoords, np.float64)
    used = T[np.unique(TF)]
    outside = int(outside_unit_square(used).sum())
    if outside:  # as template.uv: mesh refuses it
        raise ValueError(f"{where}: {outside} of its {len(used)} texture coordinates lie outside [0, 1] "
                         f"(a tiling layout, e.g. u up to {used[:, 0].max():.3g}); the slices cover the unit "
                         f"square once")

    holes, own = len(nonmanifold_edges(other_faces)[1]), len(nonmanifold_edges(F)[1])
    if holes > 2 * own + 16:  # its holes' texels read the nearest faces' texels instead
        log.warning("%s: %d boundary edges against the template's %d: where it has holes the template's "
                    "texels read its nearest faces", where, holes, own)
    idx = np.flatnonzero(tf.ravel() >= 0)
    bary_flat = np.asarray(texel_bary).reshape(-1, 3)

    def median_distance(sel):
        P = _interpolate(bary_flat[sel].astype(np.float64), F[tf.ravel()[sel]], V)
        return float(np.median(closest_surface_points(P, other_vertices, other_faces)[2]))

    def refuse(med):
        raise ValueError(f"{where}: the template's surface is {1000 * med:.1f} mm from it at the median "
                         f"texel (over {1000 * max_distance_m:.1f} mm): is it in the template's coordinates "
                         f"and units (depth-camera metres)?")

    # a mesh elsewhere (other coordinates or units) is refused from a few texels first: its
    # points are all off the surface, which the exact search answers slowly
    if len(idx):
        first = median_distance(idx[:: max(1, len(idx) // 4096)])
        if first > max_distance_m:
            refuse(first)
    texel_uv = np.full((W * W, 2), np.nan, np.float32)
    distance = np.full(W * W, np.nan, np.float32)
    for start in range(0, len(idx), CHUNK_TEXELS):   # in chunks: bounded memory at 4096²
        sl = idx[start:start + CHUNK_TEXELS]
        P = _interpolate(bary_flat[sl].astype(np.float64), F[tf.ravel()[sl]], V)
        face, bary, dist = closest_surface_points(P, other_vertices, other_faces)
        uv = _interpolate(bary, TF[face], T)
        uv[dist > max_distance_m] = np.nan
        texel_uv[sl] = uv
        distance[sl] = dist
    dist = distance[idx]
    med = float(np.median(dist)) if len(dist) else 0.0
    if med > max_distance_m:
        refuse(med)
    far = int((dist > max_distance_m).sum())
    if far:
        log.warning("%s: %d of %d texels are over %.1f mm from it and read nothing", where, far, len(idx),
                    1000 * max_distance_m)
    return AtlasTransfer(texel_uv.reshape(W, W, 2), tf >= 0, distance.reshape(W, W), T,
                         TF.astype(np.int32), int(gutter_px))
