"""Tracking stage: non-rigid tracking of the template through the depth stream.

Embedded deformation (Sumner et al. 2007) with the L0 motion regulariser of Guo et al. (2015):

- A deformation graph of nodes sampled over the template with geodesic spacing; each vertex is
  bound to its k geodesically nearest nodes with weights (1 - d/d_max)^2, normalised. Nodes are
  linked to their geodesic neighbours and, on a closed template, also through the solid (ours:
  links whose midpoint is inside the mesh), so the side the camera does not see follows the
  side it sees. Ours too: a link's smoothness term is weighted by its length (at the frame's
  start) in node spacings to the power ``link_length_power`` (links shorter than a spacing: 1),
  so the body bends less on the scale of its long links than locally.
- Each frame solves for an **incremental** warp from the previous frame's mesh (as Guo et al.):
  first one rigid motion of the whole mesh (:func:`_solve_rigid`: a rotation vector and a
  translation, same data terms), so that unseen regions follow the global motion; then per node
  an affine A_j and translation t_j, x'_i = sum_j w_ij (A_j (x_i - g_j) + g_j + t_j).
- Energy: projective point-to-plane data term against the frame's foreground depth (Huber
  weighted, visible vertices only), rotation term ||A^T A - I||^2, and the graph smoothness
  residuals r_jk = A_j (g_k - g_j) + g_j + t_j - (g_k + t_k) under an L0 penalty (the number of
  node pairs whose motions differ), solved by half-quadratic splitting: auxiliary s_jk,
  hard-thresholded (s = r where |r|^2 > lambda/beta, else 0), with beta increasing.
- Each (x-step) is Gauss-Newton with the normal equations solved by conjugate gradients with a
  12x12 block-Jacobi preconditioner (measured: 20 ms for 3,600 unknowns). J^T J is assembled
  directly as 12x12 node-pair blocks (every data-like residual of a vertex folds into one 3x3
  matrix first; :func:`_normal_equations`), not as a sparse Jacobian times its transpose, and
  the mesh is rasterised for visibility every ``VISIBILITY_EVERY`` steps, not every step.
  A step is kept only if it lowers the energy (robust costs at the step's correspondences);
  otherwise it is solved again with Levenberg-Marquardt damping (:func:`_solve_frame`). And a
  frame keeps the best, by the clipped rendered-vs-observed depth difference
  (:func:`depth_residual`), of its solve, its rigid fit and its prediction (:func:`track_sequence`).
- Colour terms (see :func:`track_sequence`): optical flow (DIS, over the object's box) from an
  appearance model in the template's atlas rendered at the predicted pose to the current image,
  as a reprojection term (ours: on grey and on two chromaticity channels, each its own flow,
  :func:`flow_image`, so shading that comes and goes, as wrinkles do, does not draw the targets
  off); and a silhouette term (:func:`silhouette_field`, weight ``w_silhouette``, on by
  default): rim vertices onto the mask's boundary, and no visible vertex outside the mask.

- Ours (``unseen_from_rest``): after each frame, the vertices the depth camera does not see are
  posed by a warp of the template itself (:func:`fit_rest_warp`: the same graph and priors, L0
  included, fitted to the seen vertices), so a hidden side follows its part's seen side as they
  sit on the template instead of carrying every deformation the incremental warps dragged it
  through.

The frame is initialised from the previous frame's mesh, or with ``constant_velocity`` from it
moved once more by the previous frame's rigid motion.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse import csgraph
from scipy.sparse.linalg import LinearOperator, cg
from scipy.spatial.transform import Rotation

from stex.camera import backproject_depth, depth_pixels_in_color, project_points, transform_points
from stex.render import rasterize, sample_bilinear, vertex_normals, vertex_visibility

log = logging.getLogger("stex.tracking")

PARAMS_PER_NODE = 12  # A (3x3, row-major) then t (3)
SILHOUETTE_MAX_PX = 20.0  # farther from the mask's boundary, a vertex is not on the rim it sees
VISIBILITY_EVERY = 4  # Gauss-Newton steps per rasterisation of the mesh for visibility
FRAME_GUARD_CLIP_M = 0.05  # depth differences clipped here when judging a frame's solve (m)
FRAME_GUARD_MARGIN = 1.05  # a solve fitting the depth this much worse than the prediction or rigid fit is dropped


# -- deformation graph -------------------------------------------------------------------------

@dataclass
class DeformationGraph:
    """Nodes over a mesh and each vertex's binding.

    nodes: (N,) int32 vertex index of each node; vertex_nodes (V, k) int32; vertex_weights (V, k)
    float64 (rows sum to 1; padding entries have weight 0); edges (E, 2) int32 node pairs j < k;
    normal_pattern: the block pattern of the tracker's normal equations, built on first use.
    """

    nodes: np.ndarray
    vertex_nodes: np.ndarray
    vertex_weights: np.ndarray
    edges: np.ndarray
    normal_pattern: object = field(default=None, repr=False, compare=False)


def edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(V, V) sparse symmetric matrix of mesh edge lengths (metres)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    w = np.maximum(w, 1e-9)  # zero-length edges would vanish from the sparse matrix
    n = len(vertices)
    g = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    return g.tocsr()


def build_graph(vertices: np.ndarray, faces: np.ndarray, spacing_m: float, k: int = 4,
                node_neighbours: int = 6, volume_links: int = 0,
                volume_range: float = 9.0) -> DeformationGraph:
    """Sample nodes with geodesic spacing ``spacing_m`` and bind each vertex to ``k`` nodes.

    Greedy covering in vertex order (deterministic): a vertex not within ``spacing_m`` (geodesic,
    along mesh edges) of an existing node becomes a node. Vertices are bound to their k
    geodesically nearest nodes within 2.5 spacings (Euclidean nearest if none, e.g. on a tiny
    island); nodes are linked to up to ``node_neighbours`` nearest nodes within that range, and,
    with ``volume_links`` > 0 on a closed mesh, through the solid to up to that many nodes within
    ``volume_range`` spacings (:func:`volume_links_through_solid`).
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    G = edge_graph(V, F)
    n = len(V)
    covered = np.zeros(n, bool)
    nodes = []
    # Vertices not on any face are skipped (they cannot be reached along edges).
    used = np.zeros(n, bool)
    used[F.ravel()] = True
    covered[~used] = True
    order = np.flatnonzero(~covered)
    pos = 0
    while pos < len(order):
        v = order[pos]
        if covered[v]:
            pos += 1
            continue
        nodes.append(v)
        d = csgraph.dijkstra(G, indices=v, limit=spacing_m)
        covered |= np.isfinite(d)
        pos += 1
    nodes = np.asarray(nodes, np.int32)
    reach = 2.5 * spacing_m
    D = csgraph.dijkstra(G, indices=nodes, limit=reach)  # (N, V)
    Dt = D.T  # (V, N)
    kk = min(k + 1, len(nodes))
    idx = np.argsort(Dt, axis=1, kind="stable")[:, :kk]
    dist = np.take_along_axis(Dt, idx, axis=1)
    dmax = dist[:, -1] if kk > k else np.full(n, reach)
    dmax = np.where(np.isfinite(dmax), dmax, reach)
    vn, vd = idx[:, :k], dist[:, :k]
    w = np.where(np.isfinite(vd), np.clip(1 - vd / np.maximum(dmax[:, None], 1e-12), 0, 1) ** 2, 0.0)
    # A vertex whose nearest node sits at d_max gets weight 0 everywhere: keep the nearest.
    lonely = w.sum(1) <= 1e-12
    if lonely.any():
        from scipy.spatial import cKDTree
        _, nn = cKDTree(V[nodes]).query(V[lonely], k=1)
        vn[lonely] = 0
        vn[lonely, 0] = nn
        w[lonely] = 0
        w[lonely, 0] = 1
    w /= w.sum(1, keepdims=True)
    # Node-node links from geodesic distances between nodes.
    DN = D[:, nodes]
    np.fill_diagonal(DN, np.inf)
    nb = min(node_neighbours, max(len(nodes) - 1, 0))
    pairs = []
    if nb > 0:
        near = np.argsort(DN, axis=1, kind="stable")[:, :nb]
        for j in range(len(nodes)):  # N is a few hundred; vectorising buys nothing here
            for kq in near[j]:
                if np.isfinite(DN[j, kq]):
                    pairs.append((min(j, kq), max(j, kq)))
    edges = np.unique(np.asarray(pairs, np.int32).reshape(-1, 2), axis=0)
    if volume_links > 0:
        edges = volume_links_through_solid(V, F, nodes, edges, volume_links, volume_range * spacing_m)
    return DeformationGraph(nodes, vn.astype(np.int32), w, edges)


def is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the mesh (V, 3) / (F, 3) is closed (watertight): only a closed template has an inside,
    and so links through the solid (:func:`volume_links_through_solid`)."""
    import trimesh

    return bool(trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                                process=False).is_watertight)


def volume_links_through_solid(vertices: np.ndarray, faces: np.ndarray, nodes: np.ndarray,
                               edges: np.ndarray, k: int, max_distance_m: float) -> np.ndarray:
    """``edges`` (E, 2) int32 plus links from every node to its ``k`` Euclidean nearest nodes
    within ``max_distance_m`` whose midpoint lies inside the closed mesh.

    Why: along the surface, a closed body's far side is linked to the side the camera sees only
    around the silhouette, so while it is unseen the regularisers carry the seen side's bend and
    twist over to it late and weakly; a link through the solid ties the two sides directly (the
    volumetric idea of VolumeDeform / DynamicFusion's Euclidean graph). A link whose midpoint is
    outside (between two legs, across a concavity) is not made, and neither is any on an open
    mesh (a template from one depth frame has no inside): (E', 2) is then ``edges`` unchanged.
    """
    from scipy.spatial import cKDTree

    from stex.template import points_inside

    V = np.asarray(vertices, np.float64)
    if len(nodes) < 2:
        return edges
    if not is_closed(V, faces):
        log.info("deformation graph: mesh not closed, no links through the solid")
        return edges
    P = V[nodes]
    d, idx = cKDTree(P).query(P, k=min(k + 1, len(P)))
    j = np.repeat(np.arange(len(P)), idx.shape[1] - 1)
    q = idx[:, 1:].ravel()
    near = d[:, 1:].ravel() <= max_distance_m
    cand = np.unique(np.sort(np.stack([j[near], q[near]], 1), axis=1), axis=0)
    if len(edges):
        known = set(map(tuple, np.asarray(edges).tolist()))
        cand = cand[[tuple(c) not in known for c in cand.tolist()]]
    if not len(cand):
        return edges
    # ray parity, any winding (trimesh's contains took 3.3 of the demo graph's 4.0 s; same links)
    inside = points_inside(V, faces, 0.5 * (P[cand[:, 0]] + P[cand[:, 1]]))
    log.info("deformation graph: %d links through the solid (of %d candidates)", int(inside.sum()), len(cand))
    out = np.concatenate([np.asarray(edges, np.int32).reshape(-1, 2), cand[inside].astype(np.int32)])
    return np.unique(out, axis=0)


# -- deformation ----------------------------------------------------------------------------------

def identity_params(n_nodes: int) -> np.ndarray:
    """(N, 12) parameters of the identity warp."""
    x = np.zeros((n_nodes, PARAMS_PER_NODE))
    x[:, [0, 4, 8]] = 1.0
    return x


def deform(vertices: np.ndarray, node_pos: np.ndarray, graph: DeformationGraph, x: np.ndarray) -> np.ndarray:
    """Apply the ED warp ``x`` (N, 12) to (V, 3) vertices bound as in ``graph``."""
    A = x[:, :9].reshape(-1, 3, 3)
    t = x[:, 9:]
    g = node_pos[graph.vertex_nodes]                      # (V, k, 3)
    local = vertices[:, None, :] - g                      # (V, k, 3)
    moved = np.einsum("vkab,vkb->vka", A[graph.vertex_nodes], local) + g + t[graph.vertex_nodes]
    return (graph.vertex_weights[..., None] * moved).sum(1)


# -- the depth frame ------------------------------------------------------------------------------

@dataclass
class DepthTarget:
    """Foreground depth points of one frame: points/normals (H, W, 3) float64, valid (H, W)."""

    points: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    K: np.ndarray
    tree: object = None          # cKDTree of the valid points, built on first use
    flat_points: np.ndarray | None = None
    flat_normals: np.ndarray | None = None


def depth_target(depth_m: np.ndarray, K: np.ndarray, foreground: np.ndarray | None = None,
                 max_jump_m: float = 0.03) -> DepthTarget:
    """Points and normals of a depth map (metres; 0 = invalid), restricted to ``foreground``.

    Normals from central differences; pixels whose neighbours jump by more than ``max_jump_m``
    (depth edges) get no normal and are not used.
    """
    if not np.isfinite(depth_m).all():
        bad = np.argwhere(~np.isfinite(depth_m))[0]
        raise ValueError(f"depth has non-finite values (first at row {bad[0]}, column {bad[1]})")
    P = backproject_depth(depth_m, K)
    ok = depth_m > 0
    if foreground is not None:
        ok &= foreground
    dx = np.zeros_like(P)
    dy = np.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dy[1:-1] = P[2:] - P[:-2]
    n = np.cross(dy, dx)  # points towards the camera for a surface facing it
    nn = np.linalg.norm(n, axis=-1)
    z = depth_m
    smooth = np.zeros_like(ok)
    smooth[1:-1, 1:-1] = (
        (np.abs(z[1:-1, 2:] - z[1:-1, :-2]) < max_jump_m) & (np.abs(z[2:, 1:-1] - z[:-2, 1:-1]) < max_jump_m)
        & (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0) & (z[:-2, 1:-1] > 0))
    ok &= smooth & (nn > 0)
    normals = np.where(ok[..., None], n / np.maximum(nn, 1e-12)[..., None], 0.0)
    return DepthTarget(np.where(ok[..., None], P, 0.0), normals, ok, np.asarray(K, np.float64))


def mask_in_depth(mask_color: np.ndarray, depth_mm: np.ndarray, calibration) -> np.ndarray:
    """(Hd, Wd) bool: depth pixels whose 3-D point lands on the colour-resolution mask."""
    d = depth_mm.astype(np.float64) / 1000.0
    idx, px, _ = depth_pixels_in_color(d, calibration)
    out = np.zeros(d.size, bool)
    out[idx] = mask_color[px[:, 1], px[:, 0]]
    return out.reshape(d.shape)


# -- one frame's solve ------------------------------------------------------------------------------

@dataclass
class TrackParams:
    """Weights and schedule of the per-frame solve (see stex/schema.yaml, section tracking)."""

    node_spacing_m: float = 0.05
    k_nodes: int = 4
    volume_links: int = 20
    volume_link_range: float = 9.0
    link_length_power: float = 1.5
    w_rot: float = 10.0
    w_reg: float = 1.0
    l0_lambda: float = 1e-4
    l0_beta0: float = 1.0
    l0_beta_growth: float = 4.0
    l0_rounds: int = 3
    gn_iterations: int = 4
    max_distance_m: float = 0.05
    huber_m: float = 0.005
    association: str = "projective"
    rigid_association: str = "projective"
    rigid_iterations: int = 12
    rigid_w_flow: float = 0.25
    w_point: float = 0.0
    w_silhouette: float = 4.0
    silhouette_rim_cos: float = 0.05
    w_flow: float = 0.25
    flow_consistency_px: float = 1.0
    flow_min_cos: float = 0.15
    flow_age_frames: float = 0.0
    flow_passes: int = 2
    flow_erode_px: int = 1
    flow_channels: str = "grey+chroma"
    rigid_only: bool = False
    model_size: int = 1024
    model_min_cos: float = 0.3
    model_refresh_cos: float | None = 0.4
    min_normal_dot: float = 0.5
    cg_tol: float = 1e-6
    damping: float = 1e-6
    constant_velocity: bool = False
    unseen_from_rest: bool = True

    @classmethod
    def from_dict(cls, d: dict) -> "TrackParams":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})


def _correspondences(Vd: np.ndarray, faces: np.ndarray, target: DepthTarget, p: TrackParams, max_dist: float,
                     visibility: tuple | None = None):
    """Data association for the camera-visible vertices: (vertex ids, target points, target
    normals) of usable pairs, and every vertex's visibility and cos in the depth camera
    (``visibility`` = (vis, cos) from an earlier call reuses them instead of rasterising).
    ``p.association`` 'closest' pairs each vertex with the nearest
    foreground depth point (robust to motion along the surface and across the silhouette);
    'projective' with the depth pixel it projects to (faster, the classic DynamicFusion choice)."""
    H, W = target.valid.shape
    if visibility is None:
        raster = rasterize(Vd, faces, target.K, W, H)
        vis, cos = vertex_visibility(Vd, faces, target.K, raster.depth)
    else:
        vis, cos = visibility
    ids = np.flatnonzero(vis)
    if p.association == "closest":
        if target.tree is None:
            from scipy.spatial import cKDTree
            target.flat_points = target.points[target.valid]
            target.flat_normals = target.normals[target.valid]
            target.tree = cKDTree(target.flat_points)
        if len(target.flat_points) == 0:
            return ids[:0], np.zeros((0, 3)), np.zeros((0, 3)), vis, cos
        dist, j = target.tree.query(Vd[ids], distance_upper_bound=max_dist)
        ok = np.isfinite(dist)
        ids, j = ids[ok], j[ok]
        q, nq = target.flat_points[j], target.flat_normals[j]
    else:
        uv, z = project_points(Vd[ids], target.K)
        px = np.rint(np.nan_to_num(uv, nan=-1)).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H) & (z > 0)
        ids, px = ids[inside], px[inside]
        ok = target.valid[px[:, 1], px[:, 0]]
        ids, px = ids[ok], px[ok]
        q, nq = target.points[px[:, 1], px[:, 0]], target.normals[px[:, 1], px[:, 0]]
    nv = vertex_normals(Vd, faces)[ids]
    # Depth normals point to the camera; so do the outward normals of visible mesh vertices.
    close = (np.linalg.norm(Vd[ids] - q, axis=1) < max_dist) & ((nv * nq).sum(1) > p.min_normal_dot)
    return ids[close], q[close], nq[close], vis, cos


def _rot_terms(x: np.ndarray):
    """Residuals (6N,) and Jacobian blocks for ||A^T A - I|| per node."""
    N = len(x)
    A = x[:, :9].reshape(N, 3, 3)
    c = [A[:, :, i] for i in range(3)]  # columns
    pairs = [(0, 1), (0, 2), (1, 2), (0, 0), (1, 1), (2, 2)]
    res = np.empty((N, 6))
    J = np.zeros((N, 6, 9))
    for m, (a, b) in enumerate(pairs):
        res[:, m] = (c[a] * c[b]).sum(1) - (1.0 if a == b else 0.0)
        # d(c_a . c_b)/dA[r, a] = c_b[r]; d/dA[r, b] += c_a[r]; A[r, col] is index 3r + col
        for rr in range(3):
            J[:, m, 3 * rr + a] += c[b][:, rr]
            J[:, m, 3 * rr + b] += c[a][:, rr]
    return res, J


def _huber_sqrt_weight(r, delta):
    return np.sqrt(np.where(np.abs(r) <= delta, 1.0, delta / np.maximum(np.abs(r), 1e-12)))


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion (Kabsch) taking points ``src`` (n, 3) to ``dst`` (n, 3):
    (R (3, 3), t (3,)) with dst ~ src @ R.T + t."""
    a, b = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise ValueError(f"rigid_fit needs two (n >= 3, 3) point sets of one shape, got {a.shape} and {b.shape}")
    ca, cb = a.mean(0), b.mean(0)
    U, _, Wt = np.linalg.svd((b - cb).T @ (a - ca))
    U[:, 2] *= np.linalg.det(U @ Wt)
    R = U @ Wt
    return R, cb - ca @ R.T


def _colour_projection(X, Kc, Tdc):
    """Pixels of depth-camera points ``X`` (n, 3) in the colour camera, the metres per pixel at
    each (z / fx), and d(pixel * z / fx)/dX (n, 2, 3) with the scale held fixed."""
    Xc = X @ Tdc[:3, :3].T + Tdc[:3, 3]
    z = Xc[:, 2]
    proj = np.stack([Kc[0, 0] * Xc[:, 0] / z + Kc[0, 2], Kc[1, 1] * Xc[:, 1] / z + Kc[1, 2]], 1)
    scale = z / Kc[0, 0]
    Jx = np.stack([np.stack([Kc[0, 0] / z, 0 * z, -Kc[0, 0] * Xc[:, 0] / z**2], 1),
                   np.stack([0 * z, Kc[1, 1] / z, -Kc[1, 1] * Xc[:, 1] / z**2], 1)], 1) * scale[:, None, None]
    return proj, scale, Jx @ Tdc[:3, :3]


def silhouette_field(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance to the boundary of ``mask`` (H, W) bool, in pixels, positive outside,
    as float32 (H, W), and its gradient (H, W, 2) (d/du, d/dv)."""
    import cv2

    m = np.asarray(mask, bool)
    if m.ndim != 2:
        raise ValueError(f"mask must be (H, W), got shape {m.shape}")
    if not m.any():
        raise ValueError("silhouette_field: the mask is empty")
    inside = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # the boundary sits half a pixel between an inside and an outside pixel centre
    sdf = np.where(m, 0.5 - inside, outside - 0.5).astype(np.float32)
    gv, gu = np.gradient(sdf)
    return sdf, np.stack([gu, gv], -1).astype(np.float32)


def silhouette_crop(mask: np.ndarray, K: np.ndarray, margin_px: int = 64):
    """:func:`silhouette_field` of ``mask`` (H, W) bool over its bounding box grown by
    ``margin_px``: (signed distance (h, w) float32, gradient (h, w, 2), K (3, 3) float64 with the
    principal point moved to the crop, so that projecting with it gives crop pixels).

    Why: at 2048 x 1536 the field over the whole image takes 0.52 s, over the object's box 0.03 s.
    It is exact wherever a vertex can count (|distance| < SILHOUETTE_MAX_PX < ``margin_px``):
    the box holds the whole mask and background beyond it on every side (beyond the box,
    sample_bilinear clamps to its edge, so a vertex there still sees a large distance).
    """
    m = np.asarray(mask, bool)
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    if not len(rows):
        raise ValueError("silhouette_crop: the mask is empty")
    y0, x0 = max(rows[0] - margin_px, 0), max(cols[0] - margin_px, 0)
    y1, x1 = min(rows[-1] + margin_px + 1, m.shape[0]), min(cols[-1] + margin_px + 1, m.shape[1])
    Kc = np.array(K, np.float64)
    Kc[0, 2] -= x0
    Kc[1, 2] -= y0
    return (*silhouette_field(m[y0:y1, x0:x1]), Kc)


# -- normal equations ---------------------------------------------------------------------------
#
# Every data-like residual (depth, point, flow, silhouette) has the form sw * D . x'_i for one
# vertex i, and x'_i depends on a node j's 12 parameters through w_ij [A_j row r] . [local; 1].
# So a vertex's residuals fold into one 3x3 information matrix M_i = sum sw^2 D D^T and a 3-vector
# b_i = sum sw^2 r D, and J^T J gains G_a^T M_i G_b = w_a w_b M[r, s] h_a[c] h_b[d] between node
# slots a, b (h = [local; 1]). The graph-smoothness residuals have the same shape (two slots,
# h = [g_k - g_j; 1] and [0; -1], M = w I). Accumulating these 12x12 node-pair blocks directly
# (numba) replaces building the sparse Jacobian and the sparse product J^T J, which took about
# a third of a paper-scale solve.

@njit(cache=True, nogil=True)
def _vertex_information(n_vertices, vid, Dw, rw):
    """Fold weighted residuals rw (n,) with rows Dw (n, 3) per vertex vid (n,) into
    M (V, 3, 3) = sum Dw Dw^T and b (V, 3) = sum rw Dw."""
    M = np.zeros((n_vertices, 3, 3))
    b = np.zeros((n_vertices, 3))
    for i in range(len(vid)):
        v = vid[i]
        for a in range(3):
            b[v, a] += rw[i] * Dw[i, a]
            for c in range(3):
                M[v, a, c] += Dw[i, a] * Dw[i, c]
    return M, b


@njit(cache=True, nogil=True)
def _accumulate_normal(blocks, grad, nodes, h, M, b, bidx):
    """blocks (nb, 12, 12) += G^T M G and grad (N, 12) += G^T b for points (n,) with slots
    nodes (n, s), h (n, s, 4) (the slot weight folded in), M (n, 3, 3), b (n, 3), and bidx
    (n, s, s) the block of each slot pair."""
    n, s = nodes.shape
    for i in range(n):
        for a in range(s):
            ja = nodes[i, a]
            for r in range(3):
                for c in range(4):
                    pa = 3 * r + c if c < 3 else 9 + r
                    grad[ja, pa] += h[i, a, c] * b[i, r]
            for q in range(s):
                blk = bidx[i, a, q]
                for r in range(3):
                    for c in range(4):
                        hac = h[i, a, c]
                        if hac == 0.0:
                            continue
                        pa = 3 * r + c if c < 3 else 9 + r
                        for r2 in range(3):
                            m = M[i, r, r2] * hac
                            if m == 0.0:
                                continue
                            for d in range(4):
                                pb = 3 * r2 + d if d < 3 else 9 + r2
                                blocks[blk, pa, pb] += m * h[i, q, d]


class _NormalPattern:
    """Block-sparse (BSR, 12x12 blocks) pattern of J^T J for one deformation graph: a block for
    every pair of nodes sharing a vertex or a graph edge, and the diagonal."""

    def __init__(self, graph: DeformationGraph, n_nodes: int):
        N = n_nodes
        vn = graph.vertex_nodes.astype(np.int64)
        ends = graph.edges.astype(np.int64).reshape(-1, 2)
        keys = np.concatenate([(vn[:, :, None] * N + vn[:, None, :]).ravel(),
                               (ends[:, :, None] * N + ends[:, None, :]).ravel(),
                               np.arange(N) * (N + 1)])
        self.keys = np.unique(keys)
        rows = self.keys // N
        self.indices = (self.keys % N).astype(np.int32)
        self.indptr = np.searchsorted(rows, np.arange(N + 1)).astype(np.int32)
        self.vertex_blocks = np.searchsorted(self.keys, vn[:, :, None] * N + vn[:, None, :])
        self.edge_blocks = np.searchsorted(self.keys, ends[:, :, None] * N + ends[:, None, :])
        self.diag = np.searchsorted(self.keys, np.arange(N) * (N + 1))
        self.n_nodes = N


def _normal_equations(pattern: _NormalPattern, graph: DeformationGraph, local, vid, Dw, rw,
                      rot_res, rot_jac, smooth_res, smooth_weight, d_jk, damping=0.0):
    """J^T J (BSR, 12N x 12N) and J^T r (12N,) of the weighted residuals of one GN step.

    vid (n,) vertex of each data-like residual, Dw (n, 3) its row d r / d x'_i, rw (n,) its
    value (weights folded in); rot_res (N, 6) / rot_jac (N, 6, 9) the rotation residuals and their
    Jacobian w.r.t. A (weight folded in); smooth_res (E, 3) the graph residuals r_jk - s_jk, with
    weight smooth_weight (scalar or (E,); its square root scales each residual), d_jk (E, 3) = g_k - g_j;
    damping is added to the diagonal. Also returns the (N, 12, 12) diagonal blocks.
    """
    N = pattern.n_nodes
    blocks = np.zeros((len(pattern.keys), 12, 12))
    grad = np.zeros((N, 12))
    if len(vid):
        M, b = _vertex_information(len(local), vid, Dw, rw)
        act = np.unique(vid)
        w = graph.vertex_weights[act]
        h = np.concatenate([local[act] * w[..., None], w[..., None]], axis=2)
        _accumulate_normal(blocks, grad, graph.vertex_nodes[act].astype(np.int64), h, M[act], b[act],
                           pattern.vertex_blocks[act])
    E = len(smooth_res)
    if E:
        h = np.zeros((E, 2, 4))
        h[:, 0, :3] = d_jk
        h[:, 0, 3] = 1.0
        h[:, 1, 3] = -1.0
        sw = np.broadcast_to(np.asarray(smooth_weight, np.float64), (E,))
        M = np.eye(3)[None] * sw[:, None, None]
        _accumulate_normal(blocks, grad, graph.edges.astype(np.int64), h, M, smooth_res * sw[:, None],
                           pattern.edge_blocks)
    blocks[pattern.diag, :9, :9] += np.einsum("nmi,nmj->nij", rot_jac, rot_jac)
    grad[:, :9] += np.einsum("nmi,nm->ni", rot_jac, rot_res)
    blocks[pattern.diag] += np.eye(12) * damping
    JtJ = sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=(12 * N, 12 * N))
    return JtJ, grad.ravel(), blocks[pattern.diag]


def _huber_cost(r, delta):
    """Huber cost (n,) of residuals r (n,) whose IRLS weights are :func:`_huber_sqrt_weight` squared:
    r^2 within ``delta``, 2 delta |r| - delta^2 beyond (so that the weighted square majorises it)."""
    a = np.abs(r)
    return np.where(a <= delta, r * r, 2.0 * delta * a - delta * delta)


def _data_rows(Vd, p: TrackParams, depth=None, flow=None, silhouette=None, rows=True, px_scale=None):
    """The data-like residuals of one Gauss-Newton step at vertices ``Vd`` (V, 3), for fixed
    correspondences: ``depth`` = (vertex ids (n,), target points (n, 3), target normals (n, 3)),
    ``flow`` = (ids, target colour px (n, 2), colour K, depth_to_color, weights (n,)),
    ``silhouette`` = (ids, signed distance (Hc, Wc), gradient (Hc, Wc, 2), colour K, depth_to_color).
    The colour terms' pixel residuals are turned into metres with ``px_scale`` (V,), each
    vertex's metres per colour pixel fixed for the solve (at the vertices it starts from): with
    the current z / fx instead, moving a vertex towards the camera would shrink its cost, and a
    solve whose depth data has run out slides the mesh at the camera (measured on the fox: the
    whole mesh ~1 m off in one frame).

    Returns (robust cost, float: sum of the Huber costs times the terms' weights, and, with
    ``rows``, lists of vertex ids, weighted rows d r / d x'_i (n, 3) and weighted residuals (n,)
    as :func:`_normal_equations` takes them). The weighted squares sum to at least the cost, equal
    where no residual is past the Huber threshold.
    """
    vids, Dws, rws = [], [], []
    cost = 0.0

    def add(ids, r, D, weight):
        nonlocal cost
        cost += float((weight * _huber_cost(r, p.huber_m)).sum())
        if rows:
            sw = _huber_sqrt_weight(r, p.huber_m) * np.sqrt(weight)
            vids.append(ids)
            Dws.append(D * sw[:, None])
            rws.append(r * sw)

    if depth is not None and len(depth[0]):
        ids, q, nq = depth
        diff = Vd[ids] - q
        add(ids, (nq * diff).sum(1), nq, 1.0)   # point-to-plane
        if p.w_point > 0:  # a little point-to-point: pins motion along flat surfaces
            for axis in range(3):
                D = np.zeros((len(ids), 3))
                D[:, axis] = 1.0
                add(ids, diff[:, axis], D, p.w_point)
    # flow: (pi(T_dc x'_i) - u_i) * z / fx, about metres at the vertex
    if flow is not None and len(flow[0]):
        fid, u_t, Kc, Tdc, fw = flow
        proj, scale, Dm = _colour_projection(Vd[fid], Kc, Tdc)
        s0 = px_scale[fid]
        rf = (proj - u_t) * s0[:, None]                      # (n, 2)
        Dm = Dm * (s0 / np.maximum(scale, 1e-9))[:, None, None]
        for m in range(2):
            add(fid, rf[:, m], Dm[:, m], p.w_flow * fw)
    # silhouette: sdf(pi(T_dc x'_i)) * z / fx
    if silhouette is not None and len(silhouette[0]):
        sid, sdf, sdf_grad, Kc, Tdc = silhouette
        proj, scale, Dm = _colour_projection(Vd[sid], Kc, Tdc)
        front = (scale > 1e-6) & np.isfinite(proj).all(1)
        Dm = Dm * (px_scale[sid] / np.maximum(scale, 1e-9))[:, None, None]
        scale = px_scale[sid]
        proj = np.where(front[:, None], proj, 0.0)
        d_px = np.where(front, sample_bilinear(sdf, proj), SILHOUETTE_MAX_PX)  # behind the camera: far off
        grad = sample_bilinear(sdf_grad, proj)              # (n, 2) px per px
        add(sid, d_px * scale, np.einsum("na,nab->nb", grad, Dm) * front[:, None], p.w_silhouette)
    return cost, vids, Dws, rws


def _silhouette_rim(Vd, vis, cos, silhouette, p: TrackParams):
    """Vertex ids (n,) of the silhouette term at ``Vd``: visible vertices on the rim (cos below
    ``p.silhouette_rim_cos``, two-sided: the rim lies on the mask's boundary) or outside the mask
    (one-sided), within SILHOUETTE_MAX_PX of its boundary and in front of the colour camera."""
    sdf, _, Kc, Tdc = silhouette
    cand = np.flatnonzero(vis)
    proj, scale, _ = _colour_projection(Vd[cand], Kc, Tdc)
    inside = (scale > 1e-6) & np.isfinite(proj).all(1)   # nothing behind the camera
    proj = np.where(inside[:, None], proj, 0.0)
    d_px = sample_bilinear(sdf, proj)
    rim = (cos[cand] < p.silhouette_rim_cos) | (d_px > 0)
    return cand[rim & inside & (np.abs(d_px) < SILHOUETTE_MAX_PX)]


LM_MAX_TRIES = 6     # damped re-solves of one Gauss-Newton step before the round gives up
LM_MU_MIN = 1e-4     # first damping (relative to J^T J's diagonal) after a rejected step


def _px_scale(V0, flow, silhouette):
    """Metres per colour pixel at each vertex of ``V0`` (V,), fixed for a solve (see :func:`_data_rows`);
    None without colour terms. Flow and silhouette both carry (colour K, depth_to_color) at 2, 3."""
    colour = flow if flow is not None else silhouette
    return _colour_projection(V0, colour[2], colour[3])[1] if colour is not None else None


def _step_terms(Vd, faces, target, p: TrackParams, visibility, flow, silhouette, px_scale, stats):
    """The data-like terms of one Gauss-Newton step at vertices ``Vd`` (V, 3): associates depth
    (within ``p.max_distance_m``; ``visibility`` as :func:`_correspondences`) and the silhouette's
    rim, records the counts in ``stats``. Returns (depth, silhouette terms as :func:`_data_rows`
    takes them, (vis, cos), robust cost, vertex ids (n,) int64, weighted rows (n, 3), weighted
    residuals (n,))."""
    ids, q, nq, vis, cos = _correspondences(Vd, faces, target, p, p.max_distance_m, visibility)
    depth = (ids, q, nq)
    if len(ids):
        stats["n_corr"] = len(ids)
        stats["data_rms_m"] = float(np.sqrt(np.mean(((nq * (Vd[ids] - q)).sum(1)) ** 2)))
    if flow is not None and len(flow[0]):
        stats["n_flow"] = len(flow[0])
    sil = None
    if silhouette is not None and p.w_silhouette > 0:
        sid = _silhouette_rim(Vd, vis, cos, silhouette, p)
        sil = (sid, *silhouette)
        stats["n_silhouette"] = len(sid)
    cost, vids, Dws, rws = _data_rows(Vd, p, depth, flow, sil, px_scale=px_scale)
    vids.append(np.zeros(0, np.int64))   # so that the concatenations below never see []
    Dws.append(np.zeros((0, 3)))
    rws.append(np.zeros(0))
    return (depth, sil, (vis, cos), cost, np.concatenate(vids).astype(np.int64), np.concatenate(Dws),
            np.concatenate(rws))


def _lm_step(energy, g, JtJ, solve, energy_after, mu, nu, stats):
    """Levenberg-Marquardt acceptance of one Gauss-Newton step (see :func:`_solve_frame`).

    ``solve(mu)`` gives the step for damping mu (relative to J^T J's diagonal), ``energy_after(step)``
    the energy after it; ``g`` = J^T r and ``JtJ`` (anything with ``@``) give the predicted decrease.
    Returns (step, or None when no damping up to LM_MAX_TRIES descends, mu, nu); counts
    "lm_rejected" / "lm_failed" in ``stats``."""
    for _ in range(LM_MAX_TRIES + 1):
        delta = solve(mu)
        new_energy = energy_after(delta)
        # the weighted squares majorise the robust costs: a true descent step lowers both
        # (a converged step may change the energy by round-off only)
        actual = energy - new_energy
        if np.isfinite(new_energy) and actual >= -1e-9 * energy:
            if mu > 0:  # Nielsen's update: less damping the better the model predicted
                predicted = -(2.0 * g @ delta + delta @ (JtJ @ delta))
                rho = min(actual / predicted, 1.0) if predicted > 0 else 1.0
                mu = max(mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), LM_MU_MIN)
            return delta, mu, 2.0
        stats["lm_rejected"] += 1
        log.debug("solve: step rejected (energy %.4g -> %.4g, mu %.2g)", energy, new_energy, mu)
        mu = max(mu * nu, LM_MU_MIN)
        nu *= 2.0
    stats["lm_failed"] += 1
    return None, mu, nu


def _link_residuals(x, node_pos, j_, k_, d_jk):
    """The graph's smoothness residuals (E, 3) r_jk = A_j (g_k - g_j) + g_j + t_j - (g_k + t_k) of
    the warp ``x`` (N, 12), nodes at ``node_pos`` (N, 3), links j_ -> k_ (E,), d_jk = g_k - g_j."""
    A = x[:, :9].reshape(-1, 3, 3)
    return np.einsum("eab,eb->ea", A[j_], d_jk) + node_pos[j_] + x[j_, 9:] - node_pos[k_] - x[k_, 9:]


def _link_weights(d_jk, p: TrackParams):
    """Each link's smoothness weight (E,): w_reg times its length (d_jk (E, 3), m) in node spacings
    to the power ``link_length_power`` (links shorter than a spacing: 1)."""
    return p.w_reg * np.maximum(1.0, np.linalg.norm(d_jk, axis=1) / p.node_spacing_m) ** p.link_length_power


def _l0_step(r_jk, w_smooth, lam, beta):
    """The HQS s-step of the L0 regulariser, a hard threshold: the auxiliary s_jk (E, 3) is the
    link's residual r_jk (E, 3) where its weighted square exceeds lam / beta (the link's motion
    difference pays for itself), else 0."""
    keep = (r_jk**2).sum(1) * w_smooth > lam / beta
    return np.where(keep[:, None], r_jk, 0.0)


def _block_jacobi(blocks):
    """The 12x12 block-Jacobi preconditioner of the (N, 12, 12) diagonal blocks, for scipy's cg."""
    N = len(blocks)
    inv = np.linalg.inv(blocks + np.eye(12) * 1e-12)
    return LinearOperator((12 * N, 12 * N), matvec=lambda v: np.einsum("nab,nb->na", inv, v.reshape(N, 12)).ravel())


def _solve_frame(V0, faces, node_pos, graph, target, p: TrackParams, x_init, flow=None, silhouette=None):
    """Gauss-Newton + HQS for the incremental warp of one frame. Returns (x, stats).

    ``flow`` = (vertex ids (n,), target colour pixels (n, 2), colour K, depth_to_color) adds a
    reprojection term pulling those vertices to where optical flow moved them in the colour image.
    ``silhouette`` = (signed distance (Hc, Wc), its gradient (Hc, Wc, 2), colour K, depth_to_color)
    of :func:`silhouette_field` adds the silhouette term (weight ``p.w_silhouette``).

    Step acceptance (Levenberg-Marquardt, :func:`_lm_step`): a Gauss-Newton step is taken only if it lowers the
    frame's energy (robust data costs with this step's correspondences, rotation, smoothness);
    otherwise it is solved again with the damping mu * diag(J^T J) raised (x2, x4, ...) up to
    LM_MAX_TRIES times, and the round stops if none lowers it. The damping is 0 until a step is
    rejected (solves that never overshoot are unchanged), then follows Nielsen's update with
    LM_MU_MIN as its floor. Why: the rotation term ||A^T A - I||^2 is flat to first order along
    rotations, so a node that the data and its links hold only weakly can get a large rotation
    from the undamped linear solve, which the true term then prices at metres of motion.
    stats: "lm_rejected" (steps re-solved with more damping), "lm_failed" (rounds stopped).
    """
    N = len(node_pos)
    x = x_init.copy()
    e = graph.edges
    j_, k_ = e[:, 0], e[:, 1]
    d_jk = node_pos[k_] - node_pos[j_]                    # (E, 3)
    # each link's smoothness weight: w_reg times its length in node spacings to a power
    # (TrackParams.link_length_power), the same in the cost, the normal equations and the L0 step
    w_smooth = _link_weights(d_jk, p)
    beta = p.l0_beta0
    s = np.zeros((len(e), 3))
    # Constant Jacobian pieces of the data term: d x'_i / d(A_j, t_j).
    local = V0[:, None, :] - node_pos[graph.vertex_nodes]  # (V, k, 3)
    if graph.normal_pattern is None:
        graph.normal_pattern = _NormalPattern(graph, N)
    pattern = graph.normal_pattern
    stats = {"n_corr": 0, "data_rms_m": np.nan, "lm_rejected": 0, "lm_failed": 0}
    sr = np.sqrt(p.w_rot)
    mu, nu = 0.0, 2.0
    px_scale = _px_scale(V0, flow, silhouette)

    def smooth_res(x):
        return _link_residuals(x, node_pos, j_, k_, d_jk)

    def prior_cost(x, rot_res=None):  # rotation and smoothness: sums of squares, as in the normal equations
        rot_res = _rot_terms(x)[0] if rot_res is None else rot_res
        return float(p.w_rot * (rot_res ** 2).sum() + beta * (w_smooth[:, None] * (smooth_res(x) - s) ** 2).sum())

    for rnd in range(p.l0_rounds):
        for it in range(p.gn_iterations):
            Vd = deform(V0, node_pos, graph, x)
            # Visibility changes little between Gauss-Newton steps: the mesh is rasterised on
            # every VISIBILITY_EVERY-th step only (the association itself is redone every step).
            depth, sil, vis_cos, cost, vid, Dw, rw = _step_terms(
                Vd, faces, target, p, None if it % VISIBILITY_EVERY == 0 else vis_cos, flow, silhouette,
                px_scale, stats)
            rr, Jr = _rot_terms(x)
            energy = cost + prior_cost(x, rr)
            # smoothness with HQS: sqrt(w_smooth * beta) * (r_jk - s_jk)
            JtJ, g, diag_blocks = _normal_equations(
                pattern, graph, local, vid, Dw, rw, rr * sr, Jr * sr, smooth_res(x) - s, beta * w_smooth, d_jk,
                p.damping)
            # CSR: scipy's CSR mat-vec is ~1.7x faster than its BSR one at 12x12 blocks
            JtJ = JtJ.tocsr()
            diag = JtJ.diagonal()

            def solve(mu):
                # 12x12 block-Jacobi preconditioner (of the damped matrix)
                blocks = diag_blocks + mu * np.einsum("ni,ij->nij", diag.reshape(N, 12), np.eye(12))
                lhs = JtJ if mu == 0 else JtJ + sp.diags(mu * diag)
                return cg(lhs, -g, rtol=p.cg_tol, maxiter=200, M=_block_jacobi(blocks))[0]

            def energy_after(delta):
                x_new = x + delta.reshape(N, 12)
                return _data_rows(deform(V0, node_pos, graph, x_new), p, depth, flow, sil, rows=False,
                                  px_scale=px_scale)[0] + prior_cost(x_new)

            delta, mu, nu = _lm_step(energy, g, JtJ, solve, energy_after, mu, nu, stats)
            if delta is None:
                break
            x = x + delta.reshape(N, 12)
            if np.abs(delta).max() < 1e-6:
                break
        s = _l0_step(smooth_res(x), w_smooth, p.l0_lambda, beta)
        stats["l0_active"] = int(s.any(1).sum())
        beta *= p.l0_beta_growth
    return x, stats


def _solve_rigid(V0, faces, target, p: TrackParams, flow=None, silhouette=None):
    """Gauss-Newton for one rigid motion of the whole mesh ``V0`` (V, 3): returns (R (3, 3), t (3,),
    stats), the moved vertices being ``V0 @ R.T + t``.

    The data terms, their association and the step acceptance are :func:`_solve_frame`'s
    (``p.gn_iterations`` steps, no graph priors); the unknowns are 6: a rotation vector, applied
    about the mesh's current centroid, and a translation. A turn is taken whole in one step,
    where one graph node held rigid by a large rotation weight turns only a little per step (its
    rotation term grows with the square of the turn: a 10 degree turn of a sphere was 14 mm
    off after 12 such steps).
    """
    c0 = V0.mean(0)
    P0 = V0 - c0
    R, t = np.eye(3), np.zeros(3)           # moved vertices: P0 @ R.T + c0 + t
    stats = {"n_corr": 0, "data_rms_m": np.nan, "lm_rejected": 0, "lm_failed": 0}
    mu, nu = 0.0, 2.0
    px_scale = _px_scale(V0, flow, silhouette)
    vis_cos = None
    for it in range(p.gn_iterations):
        Q = P0 @ R.T
        depth, sil, vis_cos, cost, vid, Dw, rw = _step_terms(
            Q + c0 + t, faces, target, p, None if it % VISIBILITY_EVERY == 0 else vis_cos, flow, silhouette,
            px_scale, stats)
        # x'_i = exp([w]) Q_i + c0 + t + dt: d r / dw = Q_i x D_i, d r / dt = D_i (D_i: d r / d x'_i)
        J = np.concatenate([np.cross(Q[vid], Dw), Dw], axis=1)
        JtJ = J.T @ J + p.damping * np.eye(6)
        g = J.T @ rw
        diag = np.diag(JtJ).copy()

        def moved(delta):
            return P0 @ (Rotation.from_rotvec(delta[:3]).as_matrix() @ R).T + c0 + t + delta[3:]

        delta, mu, nu = _lm_step(
            cost, g, JtJ, lambda mu: np.linalg.solve(JtJ + np.diag(mu * diag), -g),
            lambda delta: _data_rows(moved(delta), p, depth, flow, sil, rows=False, px_scale=px_scale)[0],
            mu, nu, stats)
        if delta is None:
            break
        R = Rotation.from_rotvec(delta[:3]).as_matrix() @ R
        t = t + delta[3:]
        if np.abs(delta).max() < 1e-6:
            break
    return R, c0 + t - c0 @ R.T, stats


REST_FIT_SEEN_WEIGHT = 1e4   # the rest-shape fit's weight of a seen vertex's position (against w_rot, w_reg)
REST_FIT_ITERATIONS = 2      # Gauss-Newton steps per L0 round of the rest-shape fit
REST_FIT_CG_TOL = 1e-3       # the fit starts from the last frame's: it need not converge in one frame


def compose_rigid(x: np.ndarray, node_pos: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """ED parameters (N, 12) of the warp ``x`` (nodes at ``node_pos`` (N, 3)) followed by the rigid
    motion y = R y + t: deform(V, node_pos, graph, result) == deform(V, node_pos, graph, x) @ R.T + t."""
    out = np.array(x, np.float64, copy=True)
    N = len(out)
    out[:, :9] = (R[None] @ out[:, :9].reshape(N, 3, 3)).reshape(N, 9)
    out[:, 9:] = (node_pos + out[:, 9:]) @ R.T + t - node_pos
    return out


def fit_rest_warp(rest: np.ndarray, graph: DeformationGraph, x_init: np.ndarray, seen: np.ndarray,
                  positions: np.ndarray, p: TrackParams) -> np.ndarray:
    """The ED warp of the rest shape that puts the vertices ``seen`` at ``positions`` and moves the
    rest as the graph's priors say, with the L0 regulariser: (N, 12) parameters, nodes at
    ``rest[graph.nodes]``.

    Args:
        rest: (V, 3) float the template (m), the shape the warp starts from.
        graph: the tracker's deformation graph of ``rest``.
        x_init: (N, 12) float the warp the Gauss-Newton steps start from (last frame's, moved
            by this frame's rigid motion).
        seen: (n,) int vertex ids held to ``positions`` (n, 3) float (m), with weight
            REST_FIT_SEEN_WEIGHT each.
        p: rotation, smoothness (with ``link_length_power``, link lengths on the rest shape) and
            L0 settings, as in the frame's solve.

    Why: the frame's solve warps the previous frame's mesh, so a side the camera has not seen
    for a while carries every deformation it was dragged through (on the demo the hidden back of
    its rigid lower half drifted 9.8 mm by frame 40). Warped from the rest shape instead, with the
    links between parts that move differently broken by the L0 step, the hidden side of a part
    follows that part's seen side as it sits on the template (measured: 8.1 mm, docs/tracking.md).
    """
    node_pos = rest[graph.nodes]
    N = len(node_pos)
    x = np.array(x_init, np.float64, copy=True)
    j_, k_ = graph.edges[:, 0], graph.edges[:, 1]
    d_jk = node_pos[k_] - node_pos[j_]
    w_smooth = _link_weights(d_jk, p)
    local = rest[:, None, :] - node_pos[graph.vertex_nodes]
    if graph.normal_pattern is None:
        graph.normal_pattern = _NormalPattern(graph, N)
    sw, sr = np.sqrt(REST_FIT_SEEN_WEIGHT), np.sqrt(p.w_rot)
    vid = np.repeat(seen, 3)                               # one residual per axis
    Dw = np.tile(np.eye(3) * sw, (len(seen), 1))
    s = np.zeros((len(j_), 3))
    beta = p.l0_beta0

    def smooth_res(x):
        return _link_residuals(x, node_pos, j_, k_, d_jk)

    for _ in range(p.l0_rounds):
        for _ in range(REST_FIT_ITERATIONS):
            rw = (deform(rest, node_pos, graph, x)[seen] - positions).ravel() * sw
            rr, Jr = _rot_terms(x)
            JtJ, g, diag_blocks = _normal_equations(graph.normal_pattern, graph, local, vid, Dw, rw, rr * sr,
                                                    Jr * sr, smooth_res(x) - s, beta * w_smooth, d_jk, p.damping)
            delta = cg(JtJ.tocsr(), -g, rtol=REST_FIT_CG_TOL, maxiter=200, M=_block_jacobi(diag_blocks))[0]
            x = x + delta.reshape(N, 12)
            if np.abs(delta).max() < 1e-6:
                break
        s = _l0_step(smooth_res(x), w_smooth, p.l0_lambda, beta)
        beta *= p.l0_beta_growth
    return x


FLOW_CHANNELS = ("grey", "chroma", "grey+chroma")
CHROMA_DARK = 30.0   # grey levels added to R + G + B: a dark pixel's chromaticity is mostly noise


def flow_image(image: np.ndarray, channels: str = "grey+chroma") -> np.ndarray:
    """The images the flow term tracks, (Hc, Wc, C) uint8, from a colour image.

    Args:
        image: (Hc, Wc, 3) uint8 RGB, or (Hc, Wc) grey (then the one grey channel, whatever
            ``channels`` says).
        channels: "grey" (luma), "chroma" (two chromaticity channels, (R - G) / S and
            (R + G - 2 B) / S with S = R + G + B + CHROMA_DARK, mapped around 128), or both.

    Why chromaticity: shading that darkens the three channels alike (a wrinkle, a shadow, the
    camera's exposure) leaves it unchanged, while it moves grey; the flow against an appearance
    model captured frames earlier then still finds the surface (on the demo the wrinkles' stripes
    drew grey flow targets 1-2 px off, chroma 0.1-0.2 px: docs/tracking.md).
    """
    if channels not in FLOW_CHANNELS:
        raise ValueError(f"flow channels must be one of {FLOW_CHANNELS}, got {channels!r}")
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8)[..., None]
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"the flow term needs an (H, W, 3) RGB or (H, W) grey image, got shape {img.shape}")
    import cv2

    out = []
    if channels in ("grey", "grey+chroma"):
        out.append(cv2.cvtColor(np.ascontiguousarray(img, np.uint8), cv2.COLOR_RGB2GRAY))
    if channels in ("chroma", "grey+chroma"):
        f = img.astype(np.float32)
        S = f.sum(2) + CHROMA_DARK
        out.append((128 + 400 * (f[..., 0] - f[..., 1]) / S).clip(0, 255).astype(np.uint8))
        out.append((128 + 200 * (f[..., 0] + f[..., 1] - 2 * f[..., 2]) / S).clip(0, 255).astype(np.uint8))
    return np.stack(out, -1)


@dataclass
class Observation:
    """One frame as the tracker sees it: the depth target and, for the flow term, the colour
    image, (Hc, Wc, 3) uint8 RGB or (Hc, Wc) grey, with the calibration (None disables the flow
    term; :func:`flow_image` makes the channels the flow tracks)."""

    target: DepthTarget
    image: np.ndarray | None = None
    calibration: object | None = None
    mask: np.ndarray | None = None  # (Hc, Wc) bool foreground, for the flow term


def _colour_view(vertices, faces, calibration):
    """Vertices in the colour camera, their raster, visibility/cos and pixel positions."""
    c = calibration.color
    Vc = transform_points(calibration.depth_to_color, vertices)
    raster = rasterize(Vc, faces, c.K, c.width, c.height)
    vis, cos = vertex_visibility(Vc, faces, c.K, raster.depth)
    uv, _ = project_points(Vc, c.K)
    return Vc, raster, vis, cos, uv


class AppearanceModel:
    """A texture of the template in a UV atlas (the flow's ``channels``: :func:`flow_image`), each
    texel filled when first seen well.

    The tracker's flow term compares the current image with this model rendered at the
    predicted pose, so flow errors do not accumulate from frame to frame: a surface point's
    appearance is fixed the first time it is seen at a good angle, and replaced only when it is
    later seen much more squarely (``refresh_margin`` of :meth:`capture`). A texel captured at
    a grazing angle, just after it came into view, is captured where the mesh is least held
    (no texel there yet to give it flow) and carries that mesh's drift into every later frame.
    """

    def __init__(self, texcoords, texcoord_faces, faces, size: int = 1024, channels: int = 1):
        from stex.template import texel_map

        self.texcoords = np.asarray(texcoords, np.float64)
        self.texcoord_faces = np.asarray(texcoord_faces, np.int64)
        self.faces = np.asarray(faces, np.int64)
        face_id, bary = texel_map(self.texcoords, self.texcoord_faces, size)
        self.texels = np.flatnonzero(face_id.ravel() >= 0)
        self.texel_face = face_id.ravel()[self.texels]
        self.texel_bary = bary.reshape(-1, 3)[self.texels].astype(np.float64)
        self.channels = channels
        self.texture = np.zeros((size, size, channels + 1), np.float32)  # the channels, then filled
        self.captured_at = np.full(size * size, -1, np.int32)  # frame position of each texel's capture
        self.captured_cos = np.zeros(size * size, np.float32)   # its face's viewing cosine then
        self.size = size
        # one texcoord per vertex (any corner's): where a vertex sits in the atlas
        self.vertex_texel = np.zeros(int(self.faces.max()) + 1, np.int64)
        px = np.clip((self.texcoords[self.texcoord_faces.ravel()] * size).astype(np.int64), 0, size - 1)
        self.vertex_texel[self.faces.ravel()] = px[:, 1] * size + px[:, 0]

    def capture(self, vertices, image, calibration, min_cos: float = 0.5, frame: int = 0,
                refresh_margin: float | None = None) -> tuple[int, int]:
        """Fill still-empty texels of faces seen at cos > ``min_cos`` from ``image``, and with
        ``refresh_margin`` also capture again the filled texels whose face is now seen at a
        cosine more than ``refresh_margin`` above the one of their capture.

        Args:
            vertices: (V, 3) float mesh in the depth camera (m).
            image: (Hc, Wc, channels) (or (Hc, Wc) with one channel) the flow's image.
            calibration: the rig (:class:`stex.camera.Calibration`).
            min_cos: least viewing cosine of a captured face.
            frame: frame position, recorded per texel (``captured_at``).
            refresh_margin: cosine margin of a re-capture (None: a texel is never replaced).

        Returns:
            (texels filled for the first time, texels captured again).
        """
        from stex.render import face_visibility, sample_bilinear

        c = calibration.color
        Vc = transform_points(calibration.depth_to_color, vertices)
        depth = rasterize(Vc, self.faces, c.K, c.width, c.height).depth
        vis, cos = face_visibility(Vc, self.faces, c.K, depth, min_cos=min_cos)
        flat = self.texture.reshape(-1, self.channels + 1)
        seen = vis[self.texel_face]
        filled = flat[self.texels, -1] > 0
        new = seen & ~filled
        todo = new.copy()
        if refresh_margin is not None:
            texel_cos = cos[self.texel_face]
            todo |= seen & filled & (texel_cos > self.captured_cos[self.texels] + refresh_margin)
        if not todo.any():
            return 0, 0
        f = self.faces[self.texel_face[todo]]
        X = (self.texel_bary[todo][:, :, None] * Vc[f]).sum(1)
        uv, _ = project_points(X, c.K)
        idx = self.texels[todo]
        flat[idx, :-1] = sample_bilinear(image, uv).reshape(len(idx), self.channels)
        flat[idx, -1] = 1.0
        self.captured_at[idx] = frame
        self.captured_cos[idx] = cos[self.texel_face[todo]]
        n_new = int(new.sum())
        return n_new, int(todo.sum()) - n_new

    def render(self, vertices, calibration):
        """The model at ``vertices`` in the colour camera: (image (Hc, Wc, channels) float32, valid
        (Hc, Wc) bool)."""
        from stex.render import render_textured

        c = calibration.color
        Vc = transform_points(calibration.depth_to_color, vertices)
        img, mask = render_textured(Vc, self.faces, self.texcoords, self.texcoord_faces, self.texture,
                                    c.K, c.width, c.height)
        return img[..., :-1], mask & (img[..., -1] > 0.999)


def flow_constraints(pred_vertices, faces, model: AppearanceModel, image, mask, calibration,
                     consistency_px=1.0, min_cos=0.15, erode_px=1, prev_image=None, crop_margin_px=64):
    """Colour-image targets for vertices: optical flow (DIS, forward-backward checked) from the
    appearance model rendered at the predicted pose to the current ``image`` ((Hc, Wc, C) uint8,
    :func:`flow_image`, the model's channels; or (Hc, Wc) with one), each channel on its own.

    Only vertices seen at a good angle, away from the silhouette and from unknown model texels
    (eroded by ``erode_px``), whose flow lands inside the current ``mask``, are used. The flow is
    computed over the box of the model and the mask grown by ``crop_margin_px``.
    Returns (vertex ids (n,), target colour pixels (n, 2)); a vertex appears once per channel
    whose flow passes.
    """
    import cv2

    from stex.render import sample_bilinear

    c = calibration.color
    pred, valid = model.render(pred_vertices, calibration)
    _, _, vis, cos, uv = _colour_view(pred_vertices, faces, calibration)
    kernel = np.ones((2 * erode_px + 1,) * 2, np.uint8)
    core = cv2.erode(valid.astype(np.uint8), kernel) > 0
    ids = np.flatnonzero(vis & (cos > min_cos))
    px = np.rint(uv[ids]).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < c.width) & (px[:, 1] >= 0) & (px[:, 1] < c.height)
    ids, px = ids[ok], px[ok]
    ids = ids[core[px[:, 1], px[:, 0]]]
    if len(ids) == 0:
        return ids, np.zeros((0, 2))
    # Flow only over the object's box (model and mask, with a margin for the motion and DIS's
    # patches): at colour-camera resolution the whole image costs several times more.
    box = valid if mask is None else (valid | mask)
    rows, cols = np.flatnonzero(box.any(1)), np.flatnonzero(box.any(0))
    y0, y1 = max(rows[0] - crop_margin_px, 0), min(rows[-1] + crop_margin_px + 1, c.height)
    x0, x1 = max(cols[0] - crop_margin_px, 0), min(cols[-1] + crop_margin_px + 1, c.width)
    crop = (slice(y0, y1), slice(x0, x1))
    img = np.atleast_3d(image)[crop]                     # (h, w, C): a grey image is one channel
    # Fill what the model does not know with the previous image (the prediction is the previous
    # pose): it moves like the object does, whereas pasting the current image there would pin the
    # flow to zero around it and make the tracker lag behind the motion.
    fill = img if prev_image is None else np.atleast_3d(prev_image)[crop]
    known = valid[crop]
    pred = np.atleast_3d(pred)[crop]
    offset = np.array([x0, y0], np.float64)
    u0 = uv[ids]
    inside = None if mask is None else cv2.erode(mask.astype(np.uint8), kernel) > 0
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    out_ids, out_targets = [], []
    for ch in range(img.shape[2]):
        pred8 = np.where(known, pred[..., ch], fill[..., ch]).clip(0, 255).astype(np.uint8)
        cur8 = np.ascontiguousarray(img[..., ch])
        fw = dis.calc(pred8, cur8, None)
        bw = dis.calc(cur8, pred8, None)
        u1 = u0 + sample_bilinear(fw, u0 - offset)
        back = sample_bilinear(bw, u1 - offset)
        ok = np.linalg.norm(u1 + back - u0, axis=1) < consistency_px
        ok &= (u1[:, 0] >= x0) & (u1[:, 0] <= x1 - 1) & (u1[:, 1] >= y0) & (u1[:, 1] <= y1 - 1)  # box is inside the image
        if inside is not None:
            q = np.rint(u1).astype(np.int64).clip(0, [c.width - 1, c.height - 1])
            ok &= inside[q[:, 1], q[:, 0]]
        out_ids.append(ids[ok])
        out_targets.append(u1[ok])
    return np.concatenate(out_ids), np.concatenate(out_targets)


def track_sequence(template_vertices, faces, observations, params: TrackParams, progress=True,
                   texcoords=None, texcoord_faces=None):
    """Track the template through a sequence of :class:`Observation`; yields
    (frame position, vertices (V, 3) float64 depth-camera metres, stats dict).

    The template must be roughly aligned with the first frame (as the synthetic scenes' and
    the authors' templates are); frame 0 is solved like any other, starting from the template.
    The flow term's appearance model lives in the template's atlas (``texcoords`` (Vt, 2),
    ``texcoord_faces`` (F, 3)); without one, an atlas is built with xatlas.
    """
    V0 = np.asarray(template_vertices, np.float64)
    F = np.asarray(faces, np.int64)
    graph = build_graph(V0, F, params.node_spacing_m, params.k_nodes,
                        volume_links=params.volume_links, volume_range=params.volume_link_range)
    log.info("tracking: %d vertices, %d nodes, %d node edges", len(V0), len(graph.nodes), len(graph.edges))
    # The rigid stage (6 unknowns, _solve_rigid) is cheap: more iterations and a wider association
    # radius let it catch fast motion before the non-rigid stage refines.
    rigid_params = TrackParams(**{**params.__dict__, "gn_iterations": params.rigid_iterations,
                                  "max_distance_m": 2 * params.max_distance_m,
                                  "association": params.rigid_association,
                                  "w_flow": params.rigid_w_flow})
    refine_params = TrackParams(**{**params.__dict__, "l0_rounds": 1})
    prev = before = V0
    rest_warp = identity_params(len(graph.nodes))   # the warp from the template (unseen_from_rest)
    model = None
    prev_image = None
    t0 = time.perf_counter()
    for pos, obs in enumerate(observations):
        tf = time.perf_counter()
        # Constant-velocity prediction: the last frame's rigid motion once more (extrapolating
        # each vertex instead lets unobserved parts run away along their own last step).
        if params.constant_velocity and pos > 1:
            R, tr = rigid_fit(before, prev)
            pred = prev @ R.T + tr
        else:
            pred = prev
        use_flow = params.w_flow > 0 and obs.image is not None
        image = flow_image(obs.image, params.flow_channels) if use_flow else None
        silhouette = None
        if params.w_silhouette > 0 and obs.mask is not None and obs.mask.any():
            cal = obs.calibration
            silhouette = (*silhouette_crop(obs.mask, cal.color.K), cal.depth_to_color)
        # Each pass re-measures the flow from the model rendered at the latest estimate: DIS
        # under-estimates motion by a few per cent, and new model texels would inherit that lag.
        guard = {"lm_rejected": 0, "lm_failed": 0}
        pred0 = pred
        for npass in range(max(1, params.flow_passes) if use_flow and model is not None else 1):
            flow = None
            if use_flow and model is not None:
                fid, u1 = flow_constraints(pred, F, model, image, obs.mask, obs.calibration,
                                           params.flow_consistency_px, params.flow_min_cos,
                                           erode_px=params.flow_erode_px, prev_image=prev_image)
                # Texels captured early carry less accumulated error: trust them more.
                age = model.captured_at[model.vertex_texel[fid]].astype(np.float64)
                age[age < 0] = pos
                weight = 1.0 / (1.0 + age / params.flow_age_frames) if params.flow_age_frames > 0 else np.ones(len(fid))
                flow = (fid, u1, obs.calibration.color.K, obs.calibration.depth_to_color, weight)
            # 1. rigid part, so that unseen regions follow the global motion exactly (the first
            # pass has done the large motion; later passes only refine, with one L0 round)
            if npass == 0:
                R, tr, rstats = _solve_rigid(pred, F, obs.target, rigid_params, flow, silhouette)
                rigid = rigid0 = pred @ R.T + tr
                for key in guard:
                    guard[key] += rstats[key]
            else:
                rigid = pred
            # 2. non-rigid increment on top, with the graph's nodes at the current vertices (the
            # bindings stay those of the template, so they do not drift)
            if params.rigid_only:
                cur, stats = rigid, rstats
            else:
                x, stats = _solve_frame(rigid, F, rigid[graph.nodes], graph, obs.target,
                                        params if npass == 0 else refine_params,
                                        identity_params(len(graph.nodes)), flow, silhouette)
                cur = deform(rigid, rigid[graph.nodes], graph, x)
                for key in guard:
                    guard[key] += stats[key]
            pred = cur
        if not np.isfinite(cur).all():
            raise ValueError(f"tracking diverged at frame position {pos}: non-finite vertices "
                             f"({stats.get('n_corr', 0)} depth correspondences in the last solve)")
        # Frame-level guard: the step guard holds the correspondences fixed, so a solve can still
        # walk off with its own associations (losing pairs lowers the cost). Judged by how well each
        # mesh explains the whole depth frame (rendered vs observed, silhouette included), the
        # frame keeps the best of the prediction, the rigid fit and the full solve.
        meshes = {"solve": cur, "rigid": rigid0, "prediction": pred0}
        if cur is rigid0:                   # rigid_only: the solve is the rigid fit, render it once
            del meshes["rigid"]
        fits = {name: depth_residual(V, F, obs.target, FRAME_GUARD_CLIP_M) for name, V in meshes.items()}
        stats["depth_residual_m"] = fits["solve"]
        fallback = fits["solve"] > FRAME_GUARD_MARGIN * min(fits.values())
        if fallback:
            best = min(fits, key=fits.get)
            log.warning("tracking: frame %d: guard: the solve explains the depth worse (mean clipped depth "
                        "difference %.1f mm) than the %s (%.1f mm): keeping the %s",
                        pos, 1000 * fits["solve"], best, 1000 * fits[best], best)
            cur = meshes[best]
            stats["depth_residual_m"] = fits[best]   # the fit of the mesh the frame keeps
        if params.unseen_from_rest and not params.rigid_only:
            cur, rest_warp = _pose_unseen_from_rest(V0, F, graph, rest_warp, prev, cur, obs.target, params, stats)
        stats["seconds"] = time.perf_counter() - tf
        stats.update(guard, frame_fallback=int(fallback))
        if progress:
            # Overshooting steps are routine on thin parts (see _solve_frame), and a round near its
            # minimum often finds no step that still descends: counted on the progress line. A
            # frame that falls back warns above.
            log.info("tracking: frame %d done (%d correspondences, rms %.2f mm, %.2f s; %.2f frames/s; "
                     "%d steps re-solved with damping, %d rounds stopped)", pos, stats["n_corr"],
                     1000 * stats["data_rms_m"], stats["seconds"], (pos + 1) / (time.perf_counter() - t0),
                     guard["lm_rejected"], guard["lm_failed"])
        before, prev = prev, cur
        if use_flow:
            if model is None:
                if texcoords is None:
                    from stex.template import build_atlas
                    texcoords, texcoord_faces = build_atlas(V0, F, params.model_size, 2)
                model = AppearanceModel(texcoords, texcoord_faces, F, params.model_size, image.shape[2])
            if image.shape[2] != model.channels:
                raise ValueError(f"tracking: frame position {pos}: the flow's image has {image.shape[2]} channels, "
                                 f"the earlier frames' {model.channels} (a grey frame among colour ones?)")
            stats["model_texels_added"], stats["model_texels_refreshed"] = model.capture(
                cur, image, obs.calibration, params.model_min_cos, pos, params.model_refresh_cos)
            prev_image = image
        yield pos, cur, stats


def _pose_unseen_from_rest(rest, faces, graph, rest_warp, prev, cur, target: DepthTarget, p: TrackParams, stats):
    """The frame's mesh ``cur`` (V, 3) with the vertices the depth camera does not see posed by
    :func:`fit_rest_warp` to the ones it sees; returns (mesh, the rest warp). ``rest_warp`` is the
    last frame's, the fit's start once moved by the rigid motion from ``prev`` to ``cur``."""
    H, W = target.valid.shape
    seen = vertex_visibility(cur, faces, target.K, rasterize(cur, faces, target.K, W, H).depth)[0]
    if seen.sum() < 3 or seen.all():
        return cur, rest_warp
    R, t = rigid_fit(prev, cur)
    rest_warp = fit_rest_warp(rest, graph, compose_rigid(rest_warp, rest[graph.nodes], R, t),
                              np.flatnonzero(seen), cur[seen], p)
    posed = deform(rest, rest[graph.nodes], graph, rest_warp)
    stats["unseen_moved_m"] = float(np.linalg.norm(posed[~seen] - cur[~seen], axis=1).mean())
    return np.where(seen[:, None], cur, posed), rest_warp


def depth_residual(vertices, faces, target: DepthTarget, clip_m: float = 0.05, union: bool = True) -> float:
    """Mean |rendered - observed| depth (m), each difference clipped at ``clip_m``: how well a
    mesh explains one depth frame. With ``union`` over the union of the mesh's and the
    foreground's pixels, a pixel covered by only one counting ``clip_m`` (silhouette included);
    otherwise over the pixels both cover."""
    H, W = target.valid.shape
    d = rasterize(vertices, faces, target.K, W, H).depth
    obs = target.points[..., 2]
    have_mesh, have_obs = d > 0, target.valid
    if not union:
        both = have_mesh & have_obs
        return float(np.minimum(np.abs(d[both] - obs[both]), clip_m).mean()) if both.any() else 0.0
    union = have_mesh | have_obs
    if not union.any():
        return 0.0
    diff = np.full(union.sum(), clip_m)
    both = (have_mesh & have_obs)[union]
    diff[both] = np.minimum(np.abs(d[union][both] - obs[union][both]), clip_m)
    return float(diff.mean())


def depth_scale_ratio(vertices, faces, target: DepthTarget, min_pixels: int = 20) -> float | None:
    """Median rendered depth over median observed depth on the pixels both the mesh and the
    foreground depth cover, or None where they share fewer than ``min_pixels``: about 1 for a mesh
    in metres in the depth camera's coordinates, 1000 for one in millimetres. The silhouette
    cannot tell (a mesh 1000 times larger and farther projects the same), the depth can."""
    H, W = target.valid.shape
    d = rasterize(vertices, faces, target.K, W, H).depth
    both = (d > 0) & target.valid
    if both.sum() < min_pixels:
        return None
    return float(np.median(d[both]) / np.median(target.points[..., 2][both]))


def silhouette_iou(vertices, faces, mask, calibration) -> float:
    """Intersection over union of the mesh's silhouette in the colour camera and ``mask``.

    vertices (V, 3) depth-camera metres, faces (F, 3), mask (Hc, Wc) bool foreground of the
    colour image. How well a tracked mesh covers the object, without any ground truth: near 1
    while the tracker follows, falling when it loses a part (:func:`stex.masks.mask_iou`).
    """
    from stex.masks import mask_iou

    c = calibration.color
    if mask.shape != (c.height, c.width):
        raise ValueError(f"mask is {mask.shape[1]}x{mask.shape[0]}, the colour camera {c.width}x{c.height}")
    covered = rasterize(transform_points(calibration.depth_to_color, vertices), faces, c.K, c.width, c.height).depth > 0
    return mask_iou(covered, mask)


# -- the stage ------------------------------------------------------------------------------------

def observations_from_stores(frames, masks, calibration, use_flow: bool = True):
    """Yield :class:`Observation` of every frame of ``frames``/``masks`` (:class:`FrameSequence`)."""
    K = calibration.depth.K
    for fid in frames.frame_ids:
        depth_mm = frames.read("depth", fid)
        mask = masks.read("mask", fid)
        fg = mask_in_depth(mask, depth_mm, calibration)
        target = depth_target(depth_mm.astype(np.float64) / 1000.0, K, fg)
        yield Observation(target, frames.read("color", fid) if use_flow else None, calibration, mask)


def write_tracking(scene_path, template_path, frames_paths, masks_paths, params: dict, out) -> None:
    """Tracking stage: per-frame vertices of the template, written as the ``tracking`` store.

    ``params`` is the ``tracking`` config section. Mode ``track`` runs :func:`track_sequence` on
    the depth stream; mode ``given`` carries the source's per-frame meshes (``given/vertices`` of
    the scene, on the original template's topology) over to the template's topology. In both
    modes each frame's mesh is also scored against the frame itself (:func:`silhouette_iou`,
    :func:`depth_residual`), and frames below ``min_silhouette_iou`` are named in a warning and
    in the store's ``poorly_fitted_frames``; given meshes below it at every frame raise
    ``ValueError`` (they and the calibration disagree) and no store is written.
    """
    from stex.camera import Calibration
    from stex.io import FrameSequence, create_store, open_store
    from stex.template import transfer_vertices

    scene = open_store(scene_path, "scene")
    template = open_store(template_path, "template")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    frames = FrameSequence(frames_paths, "frames")
    V0 = np.asarray(template["vertices"][...], np.float64)
    F = np.asarray(template["faces"][...], np.int64)
    T = len(frames)
    mode = params["mode"]
    masks = FrameSequence(masks_paths, "masks")
    last = []   # the observation of the frame being tracked (track_sequence consumes them)

    def observed():
        for ob in observations_from_stores(frames, masks, cal, use_flow=mode == "track" and params["w_flow"] > 0):
            last[:] = [ob]
            yield ob

    with create_store(out, "tracking", attrs={"frame_ids": frames.frame_ids, "mode": mode}, params=params) as store:
        verts = store.create("vertices", (T, len(V0), 3))
        residual = np.full(T, np.nan)
        n_corr = np.zeros(T, np.int64)
        seconds = np.zeros(T)
        iou = np.zeros(T)
        fit = np.zeros(T)
        if mode == "given":
            if "given/vertices" not in scene:
                raise ValueError(f"{scene_path}: tracking.mode is 'given' but the source supplied no per-frame meshes")
            if template.attrs.get("origin", "source") != "source":
                raise ValueError(f"{template_path}: tracking.mode given: the template was built from the "
                                 f"{template.attrs['origin']} (template.from_depth), and the source's per-frame "
                                 f"meshes refer to the source's template; use tracking.mode track")
            given = scene["given/vertices"]
            orig_faces = np.asarray(scene["template/faces"][...])
            ef, eb = template["embedding/face"][...], template["embedding/bary"][...]
            solved = ((k, transfer_vertices(given[k], orig_faces, ef, eb), None) for k, _ in enumerate(observed()))
        elif mode == "track":
            solved = track_sequence(V0, F, observed(), TrackParams.from_dict(params),
                                    texcoords=template["texcoords"][...], texcoord_faces=template["texcoord_faces"][...])
        else:
            raise ValueError(f"unknown tracking.mode {mode!r} (track | given)")
        no_depth = []  # frames without foreground depth: the mesh there is carried by colour and prior only
        for k, V, st in solved:
            if k == 0:
                _check_depth_scale(V, F, last[0].target, frames.frame_ids[0],
                                   template_path if mode == "track" else scene_path)
            if not last[0].target.valid.any() or (st is not None and st["n_corr"] == 0):
                no_depth.append(int(frames.frame_ids[k]))
            verts[k] = V
            # how well the mesh explains the frame, measured alike in both modes (no truth needed;
            # the tracker's frame guard has already measured the depth fit of the mesh it keeps)
            iou[k] = silhouette_iou(V, F, last[0].mask, cal)
            fit[k] = depth_residual(V, F, last[0].target, FRAME_GUARD_CLIP_M) if st is None else st["depth_residual_m"]
            if st is not None:
                residual[k] = st["data_rms_m"]
                n_corr[k] = st["n_corr"]
                seconds[k] = st["seconds"]
        threshold = float(params["min_silhouette_iou"])
        poor = [int(f) for f, v in zip(frames.frame_ids, iou) if v < threshold]
        if mode == "given" and len(poor) == T:
            # a tracker can lose the object; given meshes that miss it at every frame disagree with the camera
            raise ValueError(
                f"{scene_path}: tracking.mode given: the source's per-frame meshes cover the frames' masks poorly at "
                f"every frame (silhouette IoU {iou.min():.2f}-{iou.max():.2f}, below tracking.min_silhouette_iou "
                f"{threshold:g}): the meshes and the camera disagree. Check that the meshes are in depth-camera "
                f"coordinates in metres, the depth intrinsics and the depth-to-colour extrinsics, or the masks "
                f"(previews/masks.png; if they are known to be loose, lower tracking.min_silhouette_iou)")
        if poor:
            worst = int(np.argmin(iou))
            if poor[0] == frames.frame_ids[0]:
                # at the first frame nothing has been lost yet: the mesh itself misses part of the object
                why = (f"already at the first frame (IoU {iou[0]:.2f}), so the mesh does not cover the whole object "
                       f"(a partial template, e.g. built from one depth image) or the masks are loose "
                       f"(previews/masks.png); later frames can be no better")
            else:
                why = "the mesh has likely lost part of the object there"
            log.warning("tracking: the mesh covers the object's mask poorly (silhouette IoU below %.2f) at %d of %d "
                        "frames, first at frame %d, worst %.2f at frame %d: %s, and texture taken from those frames "
                        "will be misplaced (frames: %s)%s",
                        threshold, len(poor), T, poor[0], iou[worst], frames.frame_ids[worst], why, _runs(poor),
                        _lost_mesh_hint(poor[0] == frames.frame_ids[0], params, V0, F))
        if no_depth:
            log.warning("tracking: no depth of the object to fit at %d of %d frames (%s): no valid depth inside "
                        "the mask, or none near the mesh; the mesh there is carried by the colour terms and the "
                        "prior only (check those frames' depth images)", len(no_depth), T, _runs(no_depth))
        store.attrs["poorly_fitted_frames"] = poor
        store.write("silhouette_iou", iou)
        store.write("depth_fit_m", fit)
        store.write("residual_m", np.nan_to_num(residual, nan=-1.0))
        store.write("n_correspondences", n_corr)
        store.write("seconds", seconds)


def _check_depth_scale(vertices, faces, target: DepthTarget, frame_id: int, where) -> None:
    """Refuse a mesh whose depth at the first frame is off by more than 1.5x from the observed
    depth (:func:`depth_scale_ratio`): a template or given meshes in millimetres or centimetres, or
    not in the depth camera's coordinates, would otherwise be tracked without one correspondence."""
    ratio = depth_scale_ratio(vertices, faces, target)
    if ratio is not None and not 1 / 1.5 < ratio < 1.5:
        raise ValueError(
            f"{where}: at frame {frame_id} the mesh lies {ratio:.{0 if ratio >= 10 else 2}f} times as far from "
            f"the depth camera as the depth image reads where they overlap: the mesh must be in metres "
            f"(millimetres give 1000, centimetres 100) and in the depth camera's coordinates. The depth is "
            f"read where the frame's mask puts the object, so a mask that marks the background instead (an "
            f"inverted mask) gives such a ratio too: look at the masks (previews/masks.png)")


def _lost_mesh_hint(from_first_frame: bool, params: dict, vertices, faces) -> str:
    """What to try, appended to the tracking stage's warning about poorly fitted frames: for a
    tracked mesh that loses the object (not one that misses it from the first frame, ``from_first_frame``,
    nor given meshes), the settings that can help; ``params`` the ``tracking`` config section,
    ``vertices`` (V, 3) and ``faces`` (F, 3) the template (only a closed one gets links through
    the solid). "" where none applies."""
    if (from_first_frame or params["mode"] != "track" or params["volume_links"] == 0
            or not is_closed(vertices, faces)):
        return ""
    # links through the solid hold back parts that turn against each other (docs/tracking.md:
    # the Fox's standing animation 13.1 mm with them, 6.1 mm without)
    return (f". If the object is made of parts that turn against each other (an animal, a person's head and "
            f"arms), try tracking.volume_links: 0 (now {params['volume_links']}; docs/tracking.md); fast, thin "
            f"limbs need per-frame meshes from elsewhere (tracking.mode: given)")


def _runs(ids) -> str:
    """'3, 6-39' for [3, 6, 7, ..., 39]: consecutive integers as ranges."""
    out, start = [], None
    for i, v in enumerate(ids):
        if start is None:
            start = v
        if i + 1 == len(ids) or ids[i + 1] != v + 1:
            out.append(str(start) if start == v else f"{start}-{v}")
            start = None
    return ", ".join(out)


def plot_tracking_fit(tracking_path, out) -> None:
    """Write a PNG of how well the tracked (or given) mesh explains each frame: the silhouette
    IoU against the mask, with ``min_silhouette_iou`` and the poorly fitted frames marked, and
    the clipped depth difference (``silhouette_iou`` and ``depth_fit_m`` of the store)."""
    from stex.io import open_store
    from stex.preview import pyplot

    plt = pyplot()
    store = open_store(tracking_path, "tracking")
    ids = np.asarray(store.attrs["frame_ids"])
    iou = np.asarray(store["silhouette_iou"][...], np.float64)
    fit_mm = 1000 * np.asarray(store["depth_fit_m"][...], np.float64)
    params = store.attrs.get("params", {})
    threshold = params.get("min_silhouette_iou")
    poor = np.isin(ids, store.attrs["poorly_fitted_frames"])
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 4.6), dpi=120, sharex=True)
    a1.plot(ids, iou, marker=".", label="silhouette IoU (mesh vs mask)")
    if threshold is not None:
        a1.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"min_silhouette_iou {threshold:g}")
    if poor.any():
        a1.plot(ids[poor], iou[poor], "x", color="tab:red", label=f"poorly fitted ({int(poor.sum())} frames)")
    a1.set_ylabel("IoU")
    a1.set_title(f"tracking ({store.attrs['mode']}): how well the mesh explains each frame", fontsize=9)
    a2.plot(ids, fit_mm, marker=".", color="tab:green", label="mean |rendered - observed| depth, clipped at 5 cm")
    a2.set_ylabel("mm")
    a2.set_xlabel("frame")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
