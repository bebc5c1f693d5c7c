"""Tracking stage: non-rigid tracking of the template through the depth stream.

Embedded deformation (Sumner et al. 2007) with the L0 motion regulariser of Guo et al. (2015):

- A deformation graph over the template (:mod:`stex.deformation`: geodesic nodes, links along the
  surface and, on a closed template, through the solid). Ours: a link's smoothness term is
  weighted by its length (at the frame's start) in node spacings to the power
  ``link_length_power`` (links shorter than a spacing: 1), so the body bends less on the scale of
  its long links than locally.
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
  12x12 block-Jacobi preconditioner. J^T J is assembled directly as 12x12 node-pair blocks
  (:func:`stex.deformation.normal_equations`), and the mesh is rasterised for visibility every
  ``VISIBILITY_EVERY`` steps, not every step.
  A step is kept only if it lowers the energy (robust costs at the step's correspondences);
  otherwise it is solved again with Levenberg-Marquardt damping (:func:`_solve_frame`). And a
  frame keeps the best, by the clipped rendered-vs-observed depth difference
  (:func:`depth_residual`), of its solve, its rigid fit and its prediction (:func:`track_sequence`).
- Colour terms (see :func:`track_sequence`): optical flow (DIS, over the object's box) from an
  appearance model in the template's atlas rendered at the predicted pose to the current image,
  as a reprojection term (:mod:`stex.flow`); and a silhouette term (:func:`silhouette_field`,
  weight ``w_silhouette``, on by default): rim vertices onto the mask's boundary, and no visible vertex outside the mask.

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
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from stex.camera import backproject_depth, project_points
from stex.deformation import (
    DeformationGraph, NormalPattern, block_jacobi, build_graph, compose_rigid, deform, identity_params,
    normal_equations, rigid_fit, rotation_terms)
from stex.flow import AppearanceModel, flow_constraints, flow_image
from stex.frame_fit import depth_residual
from stex.render import rasterize, sample_bilinear, vertex_normals, vertex_visibility
from stex.tracking_quality import QualityMonitor

log = logging.getLogger("stex.tracking")


SILHOUETTE_MAX_PX = 20.0  # farther from the mask's boundary, a vertex is not on the rim it sees
VISIBILITY_EVERY = 4  # Gauss-Newton steps per rasterisation of the mesh for visibility
FRAME_GUARD_CLIP_M = 0.05  # depth differences clipped here when judging a frame's solve (m)
FRAME_GUARD_MARGIN = 1.05  # a solve fitting the depth this much worse than the prediction or rigid fit is dropped


# -- the depth frame ------------------------------------------------------------------------------

@dataclass
class DepthTarget:
    """Foreground depth points of one frame: points/normals (H, W, 3) float64, valid (H, W) where
    they have a normal; measured / foreground (H, W): pixels with depth / of the object, edges too."""

    points: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    K: np.ndarray
    measured: np.ndarray | None = None     # None: unknown (as valid)
    foreground: np.ndarray | None = None   # None: as valid
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
    measured = depth_m > 0
    ok = measured & foreground if foreground is not None else measured.copy()
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
    seen, ok = ok, ok & smooth & (nn > 0)
    normals = np.where(ok[..., None], n / np.maximum(nn, 1e-12)[..., None], 0.0)
    return DepthTarget(np.where(ok[..., None], P, 0.0), normals, ok, np.asarray(K, np.float64), measured, seen)


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
    rigid_max_iterations: int = 60
    rigid_coarse_distance_m: float = 0.4
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


def _huber_sqrt_weight(r, delta):
    return np.sqrt(np.where(np.abs(r) <= delta, 1.0, delta / np.maximum(np.abs(r), 1e-12)))


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

    Why: at 2048 x 1536 the field over the whole image costs many times the field over the
    object's box (docs/decisions/tracking.md).
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


def _huber_cost(r, delta):
    """Huber cost (n,) of residuals r (n,) whose IRLS weights are :func:`_huber_sqrt_weight` squared:
    r^2 within ``delta``, 2 delta |r| - delta^2 beyond (so that the weighted square majorises it)."""
    a = np.abs(r)
    return np.where(a <= delta, r * r, 2.0 * delta * a - delta * delta)


def data_rows(Vd, p: TrackParams, depth=None, flow=None, silhouette=None, rows=True, px_scale=None):
    """The data-like residuals of one Gauss-Newton step at vertices ``Vd`` (V, 3), for fixed
    correspondences: ``depth`` = (vertex ids (n,), target points (n, 3), target normals (n, 3)),
    ``flow`` = (ids, target colour px (n, 2), colour K, depth_to_color, weights (n,)),
    ``silhouette`` = (ids, signed distance (Hc, Wc), gradient (Hc, Wc, 2), colour K, depth_to_color).
    The colour terms' pixel residuals are turned into metres with ``px_scale`` (V,), each
    vertex's metres per colour pixel fixed for the solve (at the vertices it starts from): with
    the current z / fx instead, moving a vertex towards the camera would shrink its cost, and a
    solve whose depth data has run out slides the mesh at the camera (docs/decisions/tracking.md).

    Returns (robust cost, float: sum of the Huber costs times the terms' weights, and, with
    ``rows``, lists of vertex ids, weighted rows d r / d x'_i (n, 3) and weighted residuals (n,)
    as :func:`normal_equations` takes them). The weighted squares sum to at least the cost, equal
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


def colour_px_scale(V0, flow, silhouette):
    """Metres per colour pixel at each vertex of ``V0`` (V,), fixed for a solve (see :func:`data_rows`);
    None without colour terms. Flow and silhouette both carry (colour K, depth_to_color) at 2, 3."""
    colour = flow if flow is not None else silhouette
    return _colour_projection(V0, colour[2], colour[3])[1] if colour is not None else None


def step_terms(Vd, faces, target, p: TrackParams, visibility, flow, silhouette, px_scale, stats):
    """The data-like terms of one Gauss-Newton step at vertices ``Vd`` (V, 3): associates depth
    (within ``p.max_distance_m``; ``visibility`` as :func:`_correspondences`) and the silhouette's
    rim, records the counts in ``stats``. Returns (depth, silhouette terms as :func:`data_rows`
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
    cost, vids, Dws, rws = data_rows(Vd, p, depth, flow, sil, px_scale=px_scale)
    vids.append(np.zeros(0, np.int64))   # so that the concatenations below never see []
    Dws.append(np.zeros((0, 3)))
    rws.append(np.zeros(0))
    return (depth, sil, (vis, cos), cost, np.concatenate(vids).astype(np.int64), np.concatenate(Dws),
            np.concatenate(rws))


def lm_step(energy, g, JtJ, solve, energy_after, mu, nu, stats):
    """Levenberg-Marquardt acceptance of one Gauss-Newton step (see :func:`_solve_frame`).

    ``solve(mu)`` gives the step for damping mu (relative to J^T J's diagonal), ``energy_after(step)``
    the energy after it; ``g`` = J^T r and ``JtJ`` (anything with ``@``) give the predicted decrease.
    Returns (step, or None when no damping up to LM_MAX_TRIES descends or solves, mu, nu); counts
    "lm_rejected" / "lm_failed" in ``stats``."""
    for _ in range(LM_MAX_TRIES + 1):
        try:                    # data on a line or a plane: singular in floating point, damp more
            delta = solve(mu)
        except np.linalg.LinAlgError:
            delta = None
        new_energy = np.nan if delta is None else energy_after(delta)
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


def _solve_frame(V0, faces, node_pos, graph, target, p: TrackParams, x_init, flow=None, silhouette=None):
    """Gauss-Newton + HQS for the incremental warp of one frame. Returns (x, stats).

    ``flow`` = (vertex ids (n,), target colour pixels (n, 2), colour K, depth_to_color) adds a
    reprojection term pulling those vertices to where optical flow moved them in the colour image.
    ``silhouette`` = (signed distance (Hc, Wc), its gradient (Hc, Wc, 2), colour K, depth_to_color)
    of :func:`silhouette_field` adds the silhouette term (weight ``p.w_silhouette``).

    Step acceptance (Levenberg-Marquardt, :func:`lm_step`): a Gauss-Newton step is taken only if it lowers the
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
        graph.normal_pattern = NormalPattern(graph, N)
    pattern = graph.normal_pattern
    stats = {"n_corr": 0, "data_rms_m": np.nan, "lm_rejected": 0, "lm_failed": 0}
    sr = np.sqrt(p.w_rot)
    mu, nu = 0.0, 2.0
    px_scale = colour_px_scale(V0, flow, silhouette)

    def smooth_res(x):
        return _link_residuals(x, node_pos, j_, k_, d_jk)

    def prior_cost(x, rot_res=None):  # rotation and smoothness: sums of squares, as in the normal equations
        rot_res = rotation_terms(x)[0] if rot_res is None else rot_res
        return float(p.w_rot * (rot_res ** 2).sum() + beta * (w_smooth[:, None] * (smooth_res(x) - s) ** 2).sum())

    for rnd in range(p.l0_rounds):
        for it in range(p.gn_iterations):
            Vd = deform(V0, node_pos, graph, x)
            # Visibility changes little between Gauss-Newton steps: the mesh is rasterised on
            # every VISIBILITY_EVERY-th step only (the association itself is redone every step).
            depth, sil, vis_cos, cost, vid, Dw, rw = step_terms(
                Vd, faces, target, p, None if it % VISIBILITY_EVERY == 0 else vis_cos, flow, silhouette,
                px_scale, stats)
            rr, Jr = rotation_terms(x)
            energy = cost + prior_cost(x, rr)
            # smoothness with HQS: sqrt(w_smooth * beta) * (r_jk - s_jk)
            JtJ, g, diag_blocks = normal_equations(
                pattern, graph, local, vid, Dw, rw, rr * sr, Jr * sr, smooth_res(x) - s, beta * w_smooth, d_jk,
                p.damping)
            # CSR: scipy's CSR mat-vec is faster than its BSR one at 12x12 blocks
            JtJ = JtJ.tocsr()
            diag = JtJ.diagonal()

            def solve(mu):
                # 12x12 block-Jacobi preconditioner (of the damped matrix)
                blocks = diag_blocks + mu * np.einsum("ni,ij->nij", diag.reshape(N, 12), np.eye(12))
                lhs = JtJ if mu == 0 else JtJ + sp.diags(mu * diag)
                return cg(lhs, -g, rtol=p.cg_tol, maxiter=200, M=block_jacobi(blocks))[0]

            def energy_after(delta):
                x_new = x + delta.reshape(N, 12)
                return data_rows(deform(V0, node_pos, graph, x_new), p, depth, flow, sil, rows=False,
                                  px_scale=px_scale)[0] + prior_cost(x_new)

            delta, mu, nu = lm_step(energy, g, JtJ, solve, energy_after, mu, nu, stats)
            if delta is None:
                break
            x = x + delta.reshape(N, 12)
            if np.abs(delta).max() < 1e-6:
                break
        s = _l0_step(smooth_res(x), w_smooth, p.l0_lambda, beta)
        stats["l0_active"] = int(s.any(1).sum())
        beta *= p.l0_beta_growth
    return x, stats


RIGID_STEP_TOL_M = 1e-4    # the rigid stage has converged once a step moves no vertex farther (m)
RIGID_MIN_COVERAGE = 0.5   # below this share of visible vertices with depth pairs, the fine level is not trusted
RIGID_LEVEL_STEPS = 12     # Gauss-Newton steps per coarse level at most (the total is rigid_max_iterations)


def _rigid_steps(P0, c0, R, t, faces, target, p: TrackParams, flow, silhouette, px_scale, max_steps, tol_m, stats):
    """Gauss-Newton steps of :func:`_solve_rigid` at one association (``p.association``, radius
    ``p.max_distance_m``) from the motion (R (3, 3), t (3,)) of the centred vertices ``P0`` (V, 3)
    about ``c0``; stops after ``max_steps``, at a step below 1e-6 in every unknown, or (``tol_m``
    > 0) once a step moves no vertex farther than ``tol_m`` metres. Returns (R, t, steps taken,
    how far the last step moved the farthest vertex (m; 0 where no step descends any more), the
    share of visible vertices with a depth pair at the last step)."""
    mu, nu = 0.0, 2.0
    vis_cos, radius = None, np.linalg.norm(P0, axis=1).max()
    last_m, coverage, it = np.inf, 0.0, 0
    for it in range(max_steps):
        Q = P0 @ R.T
        depth, sil, vis_cos, cost, vid, Dw, rw = step_terms(
            Q + c0 + t, faces, target, p, None if it % VISIBILITY_EVERY == 0 else vis_cos, flow, silhouette,
            px_scale, stats)
        coverage = len(depth[0]) / max(int(vis_cos[0].sum()), 1)
        # x'_i = exp([w]) Q_i + c0 + t + dt: d r / dw = Q_i x D_i, d r / dt = D_i (D_i: d r / d x'_i)
        J = np.concatenate([np.cross(Q[vid], Dw), Dw], axis=1)
        JtJ = J.T @ J + p.damping * np.eye(6)
        g = J.T @ rw
        diag = np.diag(JtJ).copy()

        def moved(delta):
            return P0 @ (Rotation.from_rotvec(delta[:3]).as_matrix() @ R).T + c0 + t + delta[3:]

        delta, mu, nu = lm_step(
            cost, g, JtJ, lambda mu: np.linalg.solve(JtJ + np.diag(mu * diag), -g),
            lambda delta: data_rows(moved(delta), p, depth, flow, sil, rows=False, px_scale=px_scale)[0],
            mu, nu, stats)
        if delta is None:       # no damping descends: at the minimum of these pairs
            last_m = 0.0
            break
        R = Rotation.from_rotvec(delta[:3]).as_matrix() @ R
        t = t + delta[3:]
        last_m = np.linalg.norm(delta[:3]) * radius + np.linalg.norm(delta[3:])
        if np.abs(delta).max() < 1e-6 or last_m < tol_m:
            break
    return R, t, it + 1, last_m, coverage


def _solve_rigid(V0, faces, target, p: TrackParams, flow=None, silhouette=None):
    """Gauss-Newton for one rigid motion of the whole mesh ``V0`` (V, 3): returns (R (3, 3), t (3,),
    stats), the moved vertices being ``V0 @ R.T + t``.

    The data terms, their association and the step acceptance are :func:`_solve_frame`'s (no
    graph priors); the unknowns are 6: a rotation vector, applied about the mesh's current
    centroid, and a translation. A turn is taken whole in one step, where one graph node held
    rigid by a large rotation weight turns only a little per step (its rotation term grows with
    the square of the turn, so a turn of a few degrees is still far off after the rigid stage's
    steps).

    First ``p.gn_iterations`` steps at ``p.association`` within ``p.max_distance_m`` (the fine
    level). Where they have not converged (the last step still moves a vertex by more than
    RIGID_STEP_TOL_M, or fewer than RIGID_MIN_COVERAGE of the visible vertices found a depth
    pair: the object has moved farther than the association reaches), the stage goes coarse to
    fine (:func:`_rigid_coarse_to_fine`) and keeps whichever motion explains the depth better.
    Why: a fixed count of fine steps, each moving a few cm, covers only part of a large jump,
    and the non-rigid stage then shears the mesh from there (issue 55).
    """
    c0 = V0.mean(0)
    P0 = V0 - c0
    stats = {"n_corr": 0, "data_rms_m": np.nan, "lm_rejected": 0, "lm_failed": 0, "rigid_coarse_to_fine": 0}
    px_scale = colour_px_scale(V0, flow, silhouette)
    R, t, steps, last_m, coverage = _rigid_steps(P0, c0, np.eye(3), np.zeros(3), faces, target, p, flow,
                                                 silhouette, px_scale, p.gn_iterations, 0.0, stats)
    if last_m > RIGID_STEP_TOL_M or coverage < RIGID_MIN_COVERAGE:
        R, t, steps = _rigid_coarse_to_fine(P0, c0, (R, t), faces, target, p, flow, silhouette, px_scale, steps,
                                            stats)
    stats["rigid_steps"] = steps
    return R, c0 + t - c0 @ R.T, stats


RIGID_TURNS_DEG = (-90.0, -45.0, 45.0, 90.0, 180.0)  # turns about each principal axis the search starts from


def _rigid_coarse_to_fine(P0, c0, fine, faces, target, p: TrackParams, flow, silhouette, px_scale, steps, stats):
    """The rigid stage's coarse-to-fine search (see :func:`_solve_rigid`): (R, t, steps in all).

    Start poses: no motion, the fine level's motion ``fine`` = (R, t), and the translation that
    moves the visible vertices' centroid onto the foreground depth's, alone and with the turns
    RIGID_TURNS_DEG about each principal axis of the mesh (a turn of more than about 30 degrees leads closest-point pairs to the wrong side
    of a round body). Each start runs one level of closest-point pairs within
    ``p.rigid_coarse_distance_m``; the one that then explains the depth best (:func:`depth_residual`)
    goes on, the radius halving per level down to ``p.max_distance_m``, ending at the fine
    level's association; each level until a step moves no vertex by more than a fiftieth of its
    radius (RIGID_STEP_TOL_M at the finest), ``p.rigid_max_iterations`` steps after the search at
    most. The fine level's motion is kept where it fits the depth better."""
    def fit(R, t):
        return depth_residual(P0 @ R.T + c0 + t, faces, target, FRAME_GUARD_CLIP_M)

    def level(R, t, radius, budget):
        final = radius <= p.max_distance_m
        lp = p if final else TrackParams(**{**p.__dict__, "association": "closest", "max_distance_m": radius})
        return _rigid_steps(P0, c0, R, t, faces, target, lp, flow, silhouette, px_scale,
                            budget if final else min(budget, RIGID_LEVEL_STEPS),
                            RIGID_STEP_TOL_M if final else radius / 50, stats)[:3]

    stats["rigid_coarse_to_fine"] = 1
    H, W = target.valid.shape
    starts = [(np.eye(3), np.zeros(3)), fine]
    V = P0 + c0
    vis = vertex_visibility(V, faces, target.K, rasterize(V, faces, target.K, W, H).depth)[0]
    if target.valid.any() and vis.any():
        shift = target.points[target.valid].mean(0) - V[vis].mean(0)
        axes = np.linalg.eigh(P0.T @ P0)[1].T
        starts += [(np.eye(3), shift)] + [(Rotation.from_rotvec(np.deg2rad(a) * ax).as_matrix(), shift)
                                          for ax in axes for a in RIGID_TURNS_DEG]
    radius = max(p.rigid_coarse_distance_m, p.max_distance_m)
    best = None
    for R, t in starts:
        R, t, n = level(R, t, radius, RIGID_LEVEL_STEPS)
        steps += n
        score = fit(R, t)
        if best is None or score < best[0]:
            best = (score, R, t)
    _, R, t = best
    budget = p.rigid_max_iterations
    while budget > 0 and radius > p.max_distance_m:
        radius = max(radius / 2, p.max_distance_m)
        R, t, n = level(R, t, radius, budget)
        budget -= n
        steps += n
    if fit(*fine) <= fit(R, t):
        return *fine, steps
    return R, t, steps


REST_FIT_SEEN_WEIGHT = 1e4   # the rest-shape fit's weight of a seen vertex's position (against w_rot, w_reg)
REST_FIT_ITERATIONS = 2      # Gauss-Newton steps per L0 round of the rest-shape fit
REST_FIT_CG_TOL = 1e-3       # the fit starts from the last frame's: it need not converge in one frame


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
    for a while carries every deformation it was dragged through. Warped from the rest shape
    instead, with the links between parts that move differently broken by the L0 step, the hidden
    side of a part follows that part's seen side as it sits on the template
    (docs/decisions/tracking.md, docs/tracking.md).
    """
    node_pos = rest[graph.nodes]
    N = len(node_pos)
    x = np.array(x_init, np.float64, copy=True)
    j_, k_ = graph.edges[:, 0], graph.edges[:, 1]
    d_jk = node_pos[k_] - node_pos[j_]
    w_smooth = _link_weights(d_jk, p)
    local = rest[:, None, :] - node_pos[graph.vertex_nodes]
    if graph.normal_pattern is None:
        graph.normal_pattern = NormalPattern(graph, N)
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
            rr, Jr = rotation_terms(x)
            JtJ, g, diag_blocks = normal_equations(graph.normal_pattern, graph, local, vid, Dw, rw, rr * sr,
                                                    Jr * sr, smooth_res(x) - s, beta * w_smooth, d_jk, p.damping)
            delta = cg(JtJ.tocsr(), -g, rtol=REST_FIT_CG_TOL, maxiter=200, M=block_jacobi(diag_blocks))[0]
            x = x + delta.reshape(N, 12)
            if np.abs(delta).max() < 1e-6:
                break
        s = _l0_step(smooth_res(x), w_smooth, p.l0_lambda, beta)
        beta *= p.l0_beta_growth
    return x


@dataclass
class Observation:
    """One frame as the tracker sees it: the depth target and, for the flow term, the colour
    image, (Hc, Wc, 3) uint8 RGB or (Hc, Wc) grey, with the calibration (None disables the flow
    term; :func:`flow_image` makes the channels the flow tracks)."""

    target: DepthTarget
    image: np.ndarray | None = None
    calibration: object | None = None
    mask: np.ndarray | None = None  # (Hc, Wc) bool foreground, for the flow term


def track_sequence(template_vertices, faces, observations, params: TrackParams, progress=True,
                   texcoords=None, texcoord_faces=None, articulated=None):
    """Track the template through a sequence of :class:`Observation`; yields
    (frame position, vertices (V, 3) float64 depth-camera metres, stats dict).

    The template must be roughly aligned with the first frame (as the synthetic scenes' and
    the authors' templates are); frame 0 is solved like any other, starting from the template.
    The flow term's appearance model lives in the template's atlas (``texcoords`` (Vt, 2),
    ``texcoord_faces`` (F, 3)); without one, an atlas is built with xatlas. ``articulated``
    (:class:`stex.articulated.ArticulatedTracker`, for a template with a skeleton) poses the
    skeleton after the rigid stage, and the graph solves on top of the skinned mesh.
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
    model, prev_image = None, None
    monitor = QualityMonitor(F, texcoords, texcoord_faces, params, rest=V0)   # judges each frame (lost / ok)
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
        silhouette = _silhouette_term(obs, params)
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
                if articulated is not None:   # the bones' motion first, the graph on what it leaves
                    rigid = rigid0 = articulated.solve(R, tr, obs.target, flow, silhouette, rstats)
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
        # Frame-level guard: the frame keeps the best of the prediction, the rigid fit and the full solve.
        cur, fallback = _frame_guard(cur, rigid0, pred0, F, obs.target, pos, stats)
        if stats["n_corr"] == 0:   # no depth pair held the graph: its nodes keep the rigid solution (flagged below)
            cur = rigid0
        if articulated is not None:
            cur = articulated.pose_unseen(cur, F, obs.target)
        elif params.unseen_from_rest and not params.rigid_only:
            cur, rest_warp = _pose_unseen_from_rest(V0, F, graph, rest_warp, prev, cur, obs.target, params, stats)
        stats["seconds"] = time.perf_counter() - tf
        stats.update(guard, frame_fallback=int(fallback), rigid_steps=rstats["rigid_steps"],
                     rigid_coarse_to_fine=rstats["rigid_coarse_to_fine"])
        if progress:
            # Overshooting steps are routine on thin parts (see _solve_frame), and a round near its
            # minimum often finds no step that still descends: counted on the progress line. A
            # frame that falls back warns above.
            log.info("tracking: frame %d done (%d correspondences, rms %.2f mm, %.2f s; %.2f frames/s; "
                     "%d steps re-solved with damping, %d rounds stopped)", pos, stats["n_corr"],
                     1000 * stats["data_rms_m"], stats["seconds"], (pos + 1) / (time.perf_counter() - t0),
                     guard["lm_rejected"], guard["lm_failed"])
        # judged against the appearance of earlier frames only: before this frame's capture
        stats["quality"] = monitor.frame(pos, cur, obs, model if use_flow else None, image)
        before, prev = prev, cur
        if use_flow:
            if model is None:
                if texcoords is None:
                    texcoords, texcoord_faces = monitor.atlas()
                model = AppearanceModel(texcoords, texcoord_faces, F, params.model_size, image.shape[2])
            if image.shape[2] != model.channels:
                raise ValueError(f"tracking: frame position {pos}: the flow's image has {image.shape[2]} channels, "
                                 f"the earlier frames' {model.channels} (a grey frame among colour ones?)")
            stats["model_texels_added"], stats["model_texels_refreshed"] = model.capture(
                cur, image, obs.calibration, params.model_min_cos, pos, params.model_refresh_cos)
            prev_image = image
        yield pos, cur, stats


def _silhouette_term(obs: Observation, params: TrackParams):
    """The silhouette term's data for a frame (mask crop, colour K, depth-to-colour), or None."""
    if params.w_silhouette <= 0 or obs.mask is None or not obs.mask.any():
        return None
    cal = obs.calibration
    return (*silhouette_crop(obs.mask, cal.color.K), cal.depth_to_color)


def _frame_guard(cur, rigid0, pred0, faces, target: DepthTarget, pos: int, stats: dict):
    """The frame's mesh (V, 3): the best of the solve ``cur``, the rigid fit ``rigid0`` and the
    prediction ``pred0`` by how well each explains the whole depth frame (:func:`depth_residual`,
    rendered vs observed, silhouette included), and whether it is not the solve; records the
    kept mesh's fit in ``stats["depth_residual_m"]``.

    Why: the step guard holds the correspondences fixed, so a solve can still walk off with its own
    associations (losing pairs lowers the cost)."""
    meshes = {"solve": cur, "rigid": rigid0, "prediction": pred0}
    if cur is rigid0:                   # rigid_only: the solve is the rigid fit, render it once
        del meshes["rigid"]
    fits = {name: depth_residual(V, faces, target, FRAME_GUARD_CLIP_M) for name, V in meshes.items()}
    stats["depth_residual_m"] = fits["solve"]
    fallback = fits["solve"] > FRAME_GUARD_MARGIN * min(fits.values())
    if fallback:
        best = min(fits, key=fits.get)
        log.warning("tracking: frame %d: guard: the solve explains the depth worse (mean clipped depth "
                    "difference %.1f mm) than the %s (%.1f mm): keeping the %s",
                    pos, 1000 * fits["solve"], best, 1000 * fits[best], best)
        cur = meshes[best]
        stats["depth_residual_m"] = fits[best]   # the fit of the mesh the frame keeps
    return cur, fallback


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
