"""Rigid pose tables K_{t→t'}: the rigid part of the motion between every pair of frames.

E_glo (paper Eq. geo_global) compares the shape of frame t with frame t' after aligning them
with a 6-DoF rigid transform K that "aligns M_t to M_t'", obtained "with RANSAC based rigid pose
estimation that utilizes coordinate pairs of the same vertices". The authors' code
(``Similarity/rigid_alignment.py``) runs RANSAC over 100 vertex pairs shared by all frame pairs,
then Open3D point-to-plane ICP, and sets T[j, i] = inv(T[i, j]). stex does the same, vectorised:

1. **RANSAC** (:func:`ransac_rigid`, :func:`pairwise_ransac`). The meshes share one topology,
   so vertex v of frame t corresponds to vertex v of frame t' (no matching needed). Hypotheses
   come from minimal 3-vertex samples (a triad: the first edge, then the plane normal), drawn
   from a fixed, seeded subset of ``sample_vertices`` vertices; the same sample list serves every
   frame pair (as in the authors' code), which makes the table deterministic whatever the
   threading. A sample is skipped without scoring when it is nearly collinear or its three
   vertex-to-vertex distances change by more than 2·threshold between the frames (it cannot be
   rigid). Hypotheses are scored on the subset with the MSAC loss Σ min(d², θ²) (d: distance
   between the moved vertex and its partner, θ = ``inlier_threshold_m``), stopping a score as
   soon as it exceeds the best so far; sampling stops once an all-inlier sample of the best
   model would have been drawn with probability 0.999 (``ransac_iterations`` is the upper
   bound). The best model is then refitted (Kabsch) on its inliers among *all* vertices, up to
   three times (until the inlier count stops changing).
2. **ICP** (:func:`icp_point_to_plane`). With known correspondences ICP is a weighted
   least-squares alignment, iterated Gauss-Newton on a linearised rotation: point-to-plane
   residuals n_q·(R p + t − q) (so sliding along the surface, e.g. tracking drift, costs
   nothing) plus ``icp_point_weight`` × the point-to-point residual (R p + t − q), which keeps
   the problem well posed on near-symmetric surfaces (a body of revolution can spin about its
   axis at no point-to-plane cost). Robust weights: a vertex counts only while it is within θ of
   its partner (the RANSAC inlier gate), and its point-to-plane residual gets a Huber weight
   (δ = θ/4).
What "the rigid part" is: the largest vertex set that moves rigidly within θ. For an object
with a rigid core and deforming parts (a person's hips and legs under a bending torso; the
procedural body's lower half) that is the core's motion. For a body that deforms everywhere the
largest rigid set is wherever it deforms least, which need not be the region that defines its
object frame (benchmarks/bench_poses.py measures both).

3. **Tables** (:func:`pose_table`): K is computed only for t < t' (T(T−1)/2 pairs, in blocks on
   ``threads`` threads with nogil numba kernels), and poses[t', t] = inv(poses[t, t']) exactly;
   poses[t, t] = I. ``inlier_ratio[t, t']`` is the fraction of all vertices within θ of their
   partner after alignment (symmetric).

Conventions: vertices in metres (depth-camera coordinates), poses are 4x4 float64 with
x' = R x + t (``poses[t, t']`` maps frame t's vertices onto frame t'), as in
:func:`stex.camera.transform_points`.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

from stex.config import section_params
from stex.render import vertex_normals

log = logging.getLogger("stex.poses")


#: RANSAC stops once an all-inlier sample of the best model so far would have been drawn with
#: this probability (standard adaptive stopping); ``ransac_iterations`` is the upper bound.
_CONFIDENCE = 0.999

def pose_params(params: dict | None) -> dict:
    p = section_params("poses", params)
    if p["ransac_iterations"] < 1 or p["sample_vertices"] < 3 or p["icp_iterations"] < 0:
        raise ValueError(f"poses parameters out of range: {p}")
    if not p["inlier_threshold_m"] > 0:
        raise ValueError(f"poses.inlier_threshold_m must be > 0, got {p['inlier_threshold_m']}")
    return p


# --------------------------------------------------------------------------------------------
# Kabsch (numpy, batched)
# --------------------------------------------------------------------------------------------

def kabsch(P, Q, w=None):
    """Least-squares rigid transform(s) from P to Q.

    Args:
        P, Q: (..., N, 3) float corresponding points (metres), N >= 3 not all collinear.
        w: optional (..., N) non-negative weights (default all 1).

    Returns:
        R: (..., 3, 3) float64 proper rotations (det +1), t: (..., 3) float64 metres, minimising
        Σ_n w_n ‖R p_n + t − q_n‖².
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    if P.shape != Q.shape or P.shape[-1] != 3 or P.ndim < 2:
        raise ValueError(f"kabsch needs P, Q of equal shape (..., N, 3), got {P.shape} and {Q.shape}")
    if w is None:
        w = np.ones(P.shape[:-1])
    w = np.broadcast_to(np.asarray(w, dtype=np.float64), P.shape[:-1])
    ws = w.sum(-1, keepdims=True)
    if np.any(ws <= 0):
        raise ValueError("kabsch: weights sum to zero")
    cp = (w[..., None] * P).sum(-2) / ws
    cq = (w[..., None] * Q).sum(-2) / ws
    H = np.einsum("...n,...ni,...nj->...ij", w, P - cp[..., None, :], Q - cq[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = cq - np.einsum("...ij,...j->...i", R, cp)
    return R, t


def to_matrix(R, t) -> np.ndarray:
    """(..., 3, 3) rotations and (..., 3) translations -> (..., 4, 4) float64 transforms."""
    R = np.asarray(R, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_rigid(T) -> np.ndarray:
    """Exact inverse of (..., 4, 4) rigid transforms: [Rᵀ, −Rᵀ t]."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return to_matrix(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def rotation_angle_deg(R) -> np.ndarray:
    """Rotation angle(s) of (..., 3, 3) rotations, degrees."""
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def pose_error(T_est, T_true, center=None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation error (degrees) and translation error (metres) of (..., 4, 4) pose estimates.

    Rotation error: angle of R_estᵀ R_true. Translation error: ‖K_est c − K_true c‖, how far
    apart the two transforms move the point ``center`` c ((..., 3) metres, e.g. the object's
    centroid in the source frame); default c = 0, i.e. ‖t_est − t_true‖. With meshes in
    depth-camera coordinates c = 0 is the camera centre, ~1 m from the object, so that figure
    also carries ~17 mm per degree of rotation error.
    """
    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    dR = np.swapaxes(T_est[..., :3, :3], -1, -2) @ T_true[..., :3, :3]
    d = T_est[..., :3, 3] - T_true[..., :3, 3]
    if center is not None:
        c = np.asarray(center, dtype=np.float64)
        d = d + np.einsum("...ij,...j->...i", T_est[..., :3, :3] - T_true[..., :3, :3], c)
    return rotation_angle_deg(dR), np.linalg.norm(d, axis=-1)


# --------------------------------------------------------------------------------------------
# numba kernels (one frame pair at a time; nogil so threads can share the pairs)
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _triad(a0, a1, a2, out):
    """Orthonormal frame (columns) of 3 points: e1 along a1−a0, e3 normal to the plane.
    Returns False when the points are (nearly) coincident or collinear."""
    ux, uy, uz = a1[0] - a0[0], a1[1] - a0[1], a1[2] - a0[2]
    vx, vy, vz = a2[0] - a0[0], a2[1] - a0[1], a2[2] - a0[2]
    nu = np.sqrt(ux * ux + uy * uy + uz * uz)
    nv = np.sqrt(vx * vx + vy * vy + vz * vz)
    cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    nc = np.sqrt(cx * cx + cy * cy + cz * cz)
    if nu < 1e-9 or nv < 1e-9 or nc < 0.1 * nu * nv:  # sin(angle) < 0.1: too thin a triangle
        return False
    ux, uy, uz = ux / nu, uy / nu, uz / nu
    cx, cy, cz = cx / nc, cy / nc, cz / nc
    out[0, 0], out[1, 0], out[2, 0] = ux, uy, uz
    out[0, 1], out[1, 1], out[2, 1] = cy * uz - cz * uy, cz * ux - cx * uz, cx * uy - cy * ux
    out[0, 2], out[1, 2], out[2, 2] = cx, cy, cz
    return True


@njit(cache=True, nogil=True, inline="always")
def _dist(a, b):
    return np.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


@njit(cache=True, nogil=True, inline="always")
def _sqerr(R, t, p, q):
    x = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0] - q[0]
    y = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1] - q[1]
    z = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2] - q[2]
    return x * x + y * y + z * z


@njit(cache=True, nogil=True)
def _ransac_pair(P, Q, sub, samples, thresh, R, t):
    """RANSAC + 3 inlier refits for one pair. Writes R, t; returns the inlier count over all
    vertices (0 when no hypothesis was found: R = I, t = centroid difference)."""
    th2 = thresh * thresh
    Fp = np.empty((3, 3))
    Fq = np.empty((3, 3))
    Rh = np.empty((3, 3))
    th = np.empty(3)
    cp = np.empty(3)
    best = np.inf
    found = False
    S = sub.shape[0]
    n_samples = samples.shape[0]
    n_needed = n_samples
    for h in range(n_samples):
        a, b, c = sub[samples[h, 0]], sub[samples[h, 1]], sub[samples[h, 2]]
        # a rigid motion keeps the three distances
        if (abs(_dist(P[a], P[b]) - _dist(Q[a], Q[b])) > 2 * thresh
                or abs(_dist(P[a], P[c]) - _dist(Q[a], Q[c])) > 2 * thresh
                or abs(_dist(P[b], P[c]) - _dist(Q[b], Q[c])) > 2 * thresh):
            if h + 1 >= n_needed:
                break
            continue
        if not _triad(P[a], P[b], P[c], Fp) or not _triad(Q[a], Q[b], Q[c], Fq):
            if h + 1 >= n_needed:
                break
            continue
        for k in range(3):
            for m in range(3):
                Rh[k, m] = Fq[k, 0] * Fp[m, 0] + Fq[k, 1] * Fp[m, 1] + Fq[k, 2] * Fp[m, 2]
        for k in range(3):
            cp[k] = (P[a, k] + P[b, k] + P[c, k]) / 3.0
        for k in range(3):
            th[k] = (Q[a, k] + Q[b, k] + Q[c, k]) / 3.0 - (Rh[k, 0] * cp[0] + Rh[k, 1] * cp[1] + Rh[k, 2] * cp[2])
        score = 0.0
        m = 0
        for s in range(S):
            v = sub[s]
            e = _sqerr(Rh, th, P[v], Q[v])
            if e < th2:
                score += e
                m += 1
            else:
                score += th2
            if score >= best:
                break
        if score < best:
            best = score
            R[:, :] = Rh
            t[:] = th
            found = True
            # adaptive stopping: enough samples to have drawn an all-inlier triple of a model
            # with this inlier fraction with probability _CONFIDENCE
            w3 = (m / S) ** 3
            if w3 >= 1.0:
                n_needed = 1
            elif w3 <= 0.0:
                n_needed = n_samples
            else:
                n_needed = int(np.ceil(np.log(1.0 - _CONFIDENCE) / np.log(1.0 - w3)))
        if h + 1 >= n_needed:
            break
    V = P.shape[0]
    if not found:
        R[:, :] = np.eye(3)
        for k in range(3):
            t[k] = 0.0
            for n in range(V):
                t[k] += (Q[n, k] - P[n, k]) / V
    # refit on the inliers among all vertices: one pass gathers the inliers' sums, Kabsch on them
    sp = np.empty(3)
    sq = np.empty(3)
    H = np.empty((3, 3))
    n_in = 0
    prev = -1
    for it in range(4):
        n_in = _inlier_sums(P, Q, R, t, th2, sp, sq, H)
        if it == 3 or n_in < 3 or n_in == prev:
            break
        prev = n_in
        _kabsch_sums(n_in, sp, sq, H, P[0], Q[0], R, t)
    return n_in


@njit(cache=True, nogil=True)
def _inlier_sums(P, Q, R, t, th2, sp, sq, H):
    """Count the vertices within sqrt(th2) after (R, t) and accumulate, relative to P[0] / Q[0]
    (to avoid cancellation), Σp, Σq and Σ p qᵀ over them."""
    sp[:] = 0.0
    sq[:] = 0.0
    H[:, :] = 0.0
    n_in = 0
    for n in range(P.shape[0]):
        if _sqerr(R, t, P[n], Q[n]) < th2:
            n_in += 1
            px, py, pz = P[n, 0] - P[0, 0], P[n, 1] - P[0, 1], P[n, 2] - P[0, 2]
            qx, qy, qz = Q[n, 0] - Q[0, 0], Q[n, 1] - Q[0, 1], Q[n, 2] - Q[0, 2]
            sp[0] += px
            sp[1] += py
            sp[2] += pz
            sq[0] += qx
            sq[1] += qy
            sq[2] += qz
            H[0, 0] += px * qx
            H[0, 1] += px * qy
            H[0, 2] += px * qz
            H[1, 0] += py * qx
            H[1, 1] += py * qy
            H[1, 2] += py * qz
            H[2, 0] += pz * qx
            H[2, 1] += pz * qy
            H[2, 2] += pz * qz
    return n_in


@njit(cache=True, nogil=True)
def _kabsch_sums(n, sp, sq, S, p0, q0, R, t):
    """Kabsch from the sums of :func:`_inlier_sums` (n points, relative to p0 / q0).

    The 3 x 3 products and the determinant are written out: numba's np.outer, @ and
    np.linalg.det cost seconds of compilation each (the SVD stays numba's)."""
    cp = sp / n
    cq = sq / n
    H = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            H[a, b] = S[a, b] - n * cp[a] * cq[b]
    U, _, Vt = np.linalg.svd(H)
    M = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            M[a, b] = Vt[0, a] * U[b, 0] + Vt[1, a] * U[b, 1] + Vt[2, a] * U[b, 2]
    det = (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]) - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
           + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))
    if det < 0.0:
        for a in range(3):
            for b in range(3):
                M[a, b] = Vt[0, a] * U[b, 0] + Vt[1, a] * U[b, 1] - Vt[2, a] * U[b, 2]
    R[:, :] = M
    for a in range(3):
        t[a] = (cq[a] + q0[a]) - (M[a, 0] * (cp[0] + p0[0]) + M[a, 1] * (cp[1] + p0[1])
                                  + M[a, 2] * (cp[2] + p0[2]))


@njit(cache=True, nogil=True)
def _icp_pair(P, Q, N, thresh, n_iter, point_weight, R, t):
    """Robust point-to-plane (+ point_weight · point-to-point) alignment with known
    correspondences, refining R, t in place. Returns the final inlier count."""
    th2 = thresh * thresh
    delta = 0.25 * thresh
    V = P.shape[0]
    A = np.empty((6, 6))
    g = np.empty(6)
    J = np.empty(6)
    pp = np.empty(3)
    for it in range(n_iter):
        A[:, :] = 0.0
        g[:] = 0.0
        n_in = 0
        for n in range(V):
            for k in range(3):
                pp[k] = R[k, 0] * P[n, 0] + R[k, 1] * P[n, 1] + R[k, 2] * P[n, 2] + t[k]
            ex, ey, ez = pp[0] - Q[n, 0], pp[1] - Q[n, 1], pp[2] - Q[n, 2]
            if ex * ex + ey * ey + ez * ez >= th2:
                continue
            n_in += 1
            nx, ny, nz = N[n, 0], N[n, 1], N[n, 2]
            r = nx * ex + ny * ey + nz * ez
            wr = 1.0 if abs(r) <= delta else delta / abs(r)
            # point-to-plane row: d r / d(omega, dt) = [p' x n, n]
            J[0] = pp[1] * nz - pp[2] * ny
            J[1] = pp[2] * nx - pp[0] * nz
            J[2] = pp[0] * ny - pp[1] * nx
            J[3], J[4], J[5] = nx, ny, nz
            for a in range(6):
                g[a] += wr * J[a] * r
                for b in range(a, 6):
                    A[a, b] += wr * J[a] * J[b]
            if point_weight > 0.0:
                # point-to-point rows: d e / d(omega, dt) = [-[p']x, I]
                x, y, z = pp[0], pp[1], pp[2]
                lw = point_weight
                # J_pp^T J_pp for rotation block: [p']x^T [p']x = |p|^2 I - p p^T
                s2 = x * x + y * y + z * z
                A[0, 0] += lw * (s2 - x * x)
                A[0, 1] += lw * (-x * y)
                A[0, 2] += lw * (-x * z)
                A[1, 1] += lw * (s2 - y * y)
                A[1, 2] += lw * (-y * z)
                A[2, 2] += lw * (s2 - z * z)
                # rotation-translation block: (-[p']x)^T I = [p']x
                A[0, 4] += lw * (-z)
                A[0, 5] += lw * y
                A[1, 3] += lw * z
                A[1, 5] += lw * (-x)
                A[2, 3] += lw * (-y)
                A[2, 4] += lw * x
                A[3, 3] += lw
                A[4, 4] += lw
                A[5, 5] += lw
                # gradient: J_pp^T e = [p' x e ... ] : (-[p']x)^T e = [p']x e = p' x e
                g[0] += lw * (y * ez - z * ey)
                g[1] += lw * (z * ex - x * ez)
                g[2] += lw * (x * ey - y * ex)
                g[3] += lw * ex
                g[4] += lw * ey
                g[5] += lw * ez
        if n_in < 6:
            break
        for a in range(6):
            for b in range(a):
                A[a, b] = A[b, a]
            A[a, a] += 1e-12
        x = np.linalg.solve(A, -g)
        # R <- exp([w]x) R, t <- exp([w]x) t + dt
        wx, wy, wz = x[0], x[1], x[2]
        ang = np.sqrt(wx * wx + wy * wy + wz * wz)
        Rw = np.eye(3)
        if ang > 1e-15:
            kx, ky, kz = wx / ang, wy / ang, wz / ang
            c, s = np.cos(ang), np.sin(ang)
            C = 1.0 - c
            Rw[0, 0], Rw[0, 1], Rw[0, 2] = c + kx * kx * C, kx * ky * C - kz * s, kx * kz * C + ky * s
            Rw[1, 0], Rw[1, 1], Rw[1, 2] = ky * kx * C + kz * s, c + ky * ky * C, ky * kz * C - kx * s
            Rw[2, 0], Rw[2, 1], Rw[2, 2] = kz * kx * C - ky * s, kz * ky * C + kx * s, c + kz * kz * C
        R[:, :] = Rw @ R
        tn = Rw @ t
        for k in range(3):
            t[k] = tn[k] + x[3 + k]
        if ang < 1e-7 and abs(x[3]) + abs(x[4]) + abs(x[5]) < 1e-7:  # 0.1 µrad, 0.1 µm
            break
    n_in = 0
    for n in range(V):
        if _sqerr(R, t, P[n], Q[n]) < th2:
            n_in += 1
    return n_in


@njit(cache=True, nogil=True)
def _count_inliers(P, Q, R, t, thresh):
    th2 = thresh * thresh
    n_in = 0
    for n in range(P.shape[0]):
        if _sqerr(R, t, P[n], Q[n]) < th2:
            n_in += 1
    return n_in


@njit(cache=True, nogil=True)
def _pairs_kernel(X, N, pi, pj, sub, samples, thresh, icp_iter, icp_thresh, point_weight, out_T,
                  out_ratio):
    """Pose of every pair (pi[k] -> pj[k]) into out_T[k] (4,4), inlier ratio into out_ratio[k]."""
    R = np.empty((3, 3))
    t = np.empty(3)
    V = X.shape[1]
    for k in range(pi.shape[0]):
        P = X[pi[k]]
        Q = X[pj[k]]
        n_in = _ransac_pair(P, Q, sub, samples, thresh, R, t)
        if icp_iter > 0:
            _icp_pair(P, Q, N[pj[k]], icp_thresh, icp_iter, point_weight, R, t)
            n_in = _count_inliers(P, Q, R, t, thresh)
        out_T[k, :, :] = 0.0
        out_T[k, :3, :3] = R
        out_T[k, :3, 3] = t
        out_T[k, 3, 3] = 1.0
        out_ratio[k] = n_in / V


@njit(cache=True, nogil=True)
def _icp_batch(P, Q, N, T0, thresh, n_iter, point_weight, out_T, out_n):
    R = np.empty((3, 3))
    t = np.empty(3)
    for k in range(P.shape[0]):
        R[:, :] = T0[k, :3, :3]
        t[:] = T0[k, :3, 3]
        out_n[k] = _icp_pair(P[k], Q[k], N[k], thresh, n_iter, point_weight, R, t)
        out_T[k, :, :] = 0.0
        out_T[k, :3, :3] = R
        out_T[k, :3, 3] = t
        out_T[k, 3, 3] = 1.0


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------

def _subset_and_samples(n_vertices: int, n_sub: int, n_iter: int, rng: np.random.Generator):
    """Seeded scoring subset (sorted vertex ids) and (n_iter, 3) distinct sample triples into it."""
    n_sub = min(int(n_sub), n_vertices)
    if n_vertices < 3:
        raise ValueError(f"rigid pose estimation needs at least 3 vertices, got {n_vertices}")
    sub = np.sort(rng.choice(n_vertices, n_sub, replace=False)).astype(np.int64)
    samples = np.empty((int(n_iter), 3), np.int64)
    samples[:, 0] = rng.integers(0, n_sub, n_iter)
    samples[:, 1] = (samples[:, 0] + rng.integers(1, n_sub, n_iter)) % n_sub
    third = rng.integers(0, n_sub - 2, n_iter)
    # the third index skips the two already taken
    lo = np.minimum(samples[:, 0], samples[:, 1])
    hi = np.maximum(samples[:, 0], samples[:, 1])
    third = third + (third >= lo)
    third = third + (third >= hi)
    samples[:, 2] = third
    return sub, samples


def _check_pair(P, Q, name="P, Q"):
    P = np.ascontiguousarray(P, dtype=np.float64)
    Q = np.ascontiguousarray(Q, dtype=np.float64)
    if P.shape != Q.shape or P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"{name} must both be (V, 3), got {P.shape} and {Q.shape}")
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise ValueError(f"{name}: non-finite vertex coordinates")
    return P, Q


def ransac_rigid(P, Q, n_iter: int = 500, inlier_thresh_m: float = 0.01, rng=None,
                 sample_vertices: int = 512):
    """RANSAC rigid transform between corresponding point sets (one pair).

    Args:
        P, Q: (V, 3) float corresponding points (vertex v of P ↔ vertex v of Q), metres.
        n_iter: number of minimal 3-point samples.
        inlier_thresh_m: θ, a vertex is an inlier when ‖R p + t − q‖ < θ (metres).
        rng: numpy Generator or seed (default seed 0) choosing the scoring subset and samples.
        sample_vertices: size of the scoring subset (vertices).

    Returns:
        T: (4, 4) float64 with q ≈ R p + t (best hypothesis refitted on its inliers among all
        vertices), inlier_mask: (V,) bool.
    """
    P, Q = _check_pair(P, Q)
    rng = np.random.default_rng(rng if rng is not None else 0)
    sub, samples = _subset_and_samples(P.shape[0], sample_vertices, n_iter, rng)
    R = np.empty((3, 3))
    t = np.empty(3)
    _ransac_pair(P, Q, sub, samples, float(inlier_thresh_m), R, t)
    T = to_matrix(R, t)
    mask = np.linalg.norm(P @ R.T + t - Q, axis=1) < inlier_thresh_m
    return T, mask


def _all_pairs(n: int):
    i, j = np.triu_indices(n, 1)
    return i.astype(np.int64), j.astype(np.int64)


def _run_pairs(X, N, pi, pj, p: dict, threads: int | None, icp_iter: int):
    """Run the fused per-pair kernel over pairs (pi, pj) in blocks on ``threads`` threads."""
    rng = np.random.default_rng(p["seed"])
    sub, samples = _subset_and_samples(X.shape[1], p["sample_vertices"], p["ransac_iterations"], rng)
    n = pi.shape[0]
    out_T = np.zeros((n, 4, 4))
    out_r = np.zeros(n)
    if n == 0:
        return out_T, out_r
    threads = max(1, int(threads or os.cpu_count() or 1))
    # blocks small enough for regular progress, large enough to amortise the dispatch
    block = int(np.clip(n // (threads * 20), 16, 2048))
    starts = list(range(0, n, block))
    args = (float(p["inlier_threshold_m"]), int(icp_iter), float(p["icp_threshold_m"]),
            float(p["icp_point_weight"]))

    def work(s):
        e = min(s + block, n)
        _pairs_kernel(X, N, pi[s:e], pj[s:e], sub, samples, *args, out_T[s:e], out_r[s:e])
        return e - s

    t0 = time.perf_counter()
    done, last = 0, t0
    with ThreadPoolExecutor(max_workers=threads) as ex:
        for k in ex.map(work, starts):
            done += k
            now = time.perf_counter()
            if now - last > 5.0 or done == n:
                rate = done / max(now - t0, 1e-9)
                log.info("poses: %d / %d pairs (%.0f pairs/s)", done, n, rate)
                last = now
    return out_T, out_r


def pairwise_ransac(vertices, pairs=None, n_iter: int = 500, inlier_thresh_m: float = 0.01,
                    sample_vertices: int = 512, seed: int = 0, threads: int | None = None):
    """RANSAC rigid transforms for many frame pairs at once (no ICP).

    Args:
        vertices: (T, V, 3) float per-frame vertices of one topology, metres.
        pairs: (P, 2) int frame pairs (i, j); default every i < j.
        n_iter, inlier_thresh_m, sample_vertices: as in :func:`ransac_rigid`; one seeded subset
            and sample list serve every pair.
        seed: seed of the subset and samples.
        threads: worker threads (default: all CPUs).

    Returns:
        poses: (P, 4, 4) float64 mapping frame i onto frame j, inlier_ratio: (P,) float32.
    """
    X = _check_vertices(vertices)
    pi, pj = _pairs(pairs, X.shape[0])
    p = pose_params({"ransac_iterations": n_iter, "inlier_threshold_m": inlier_thresh_m,
                 "sample_vertices": sample_vertices, "seed": seed, "icp_iterations": 0})
    T, r = _run_pairs(X, X, pi, pj, p, threads, icp_iter=0)
    return T, r.astype(np.float32)


def icp_point_to_plane(src, dst, dst_normals, T0=None, n_iter: int = 5,
                       inlier_thresh_m: float = 0.01, point_weight: float = 0.1):
    """Robust point-to-plane ICP with known correspondences (same topology), batched.

    Minimises Σ_v w_v [ρ_Huber(n_v·(R p_v + t − q_v)) + point_weight ‖R p_v + t − q_v‖²] by
    Gauss-Newton on a linearised rotation, where w_v = 1 while ‖R p_v + t − q_v‖ < θ
    (re-evaluated every iteration) and 0 otherwise; Huber δ = θ/4.

    Args:
        src, dst: (..., V, 3) float corresponding vertices (metres).
        dst_normals: (..., V, 3) float unit normals of dst.
        T0: (..., 4, 4) initial transform(s) (default identity).
        n_iter: Gauss-Newton iterations (stops early on convergence or < 6 inliers).
        inlier_thresh_m: θ (metres).
        point_weight: weight of the point-to-point term (0 = pure point-to-plane).

    Returns:
        T: (..., 4, 4) float64 refined transform(s), inlier_ratio: (...) float32 fraction of
        vertices within θ after refinement.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    nrm = np.asarray(dst_normals, dtype=np.float64)
    if src.shape != dst.shape or src.shape != nrm.shape or src.shape[-1] != 3 or src.ndim < 2:
        raise ValueError(f"icp_point_to_plane: src, dst, dst_normals must share shape (..., V, 3), "
                         f"got {src.shape}, {dst.shape}, {nrm.shape}")
    batch = src.shape[:-2]
    V = src.shape[-2]
    T0 = np.broadcast_to(np.eye(4) if T0 is None else np.asarray(T0, dtype=np.float64), batch + (4, 4))
    P = np.ascontiguousarray(src.reshape(-1, V, 3))
    Q = np.ascontiguousarray(dst.reshape(-1, V, 3))
    Nn = np.ascontiguousarray(nrm.reshape(-1, V, 3))
    T0f = np.ascontiguousarray(T0.reshape(-1, 4, 4))
    out_T = np.empty_like(T0f)
    out_n = np.empty(P.shape[0], np.int64)
    _icp_batch(P, Q, Nn, T0f, float(inlier_thresh_m), int(n_iter), float(point_weight), out_T, out_n)
    return out_T.reshape(batch + (4, 4)), (out_n / max(V, 1)).astype(np.float32).reshape(batch)


def _check_vertices(vertices) -> np.ndarray:
    X = np.ascontiguousarray(vertices, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"vertices must be (T, V, 3), got shape {X.shape}")
    if X.shape[0] < 1:
        raise ValueError("vertices: no frames (shape (0, V, 3)); a pose table needs at least one")
    if X.shape[1] < 3:
        raise ValueError(f"vertices: need at least 3 vertices per frame, got {X.shape[1]}")
    bad = ~np.isfinite(X).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"vertices: frame {int(np.flatnonzero(bad)[0])} has non-finite coordinates")
    return X


def _pairs(pairs, n_frames):
    if pairs is None:
        return _all_pairs(n_frames)
    pr = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pr.size and (pr.min() < 0 or pr.max() >= n_frames):
        raise ValueError(f"pairs refer to frames outside [0, {n_frames})")
    return np.ascontiguousarray(pr[:, 0]), np.ascontiguousarray(pr[:, 1])


def pair_poses(vertices, faces, pairs=None, params: dict | None = None, seed: int | None = None,
               threads: int | None = None):
    """Rigid poses of the given frame pairs (every pair with the same seeded samples, so a pair's
    pose does not depend on which other pairs are computed).

    Args:
        vertices: (T, V, 3) float per-frame vertices of one topology (metres).
        faces: (F, 3) int triangles, for the vertex normals of the point-to-plane ICP.
        pairs: (P, 2) int frame pairs (i, j), i != j; default every i < j.
        params, seed, threads: as in :func:`pose_table`.

    Returns:
        poses: (P, 4, 4) float64 K_{i→j} (x' ≈ R x + t), inlier_ratio: (P,) float32.
    """
    p = pose_params(params)
    if seed is not None:
        p["seed"] = int(seed)
    X = _check_vertices(vertices)
    n = X.shape[0]
    pi, pj = _pairs(pairs, n)
    N = np.stack([vertex_normals(X[k], faces) for k in range(n)]) if p["icp_iterations"] > 0 else X
    log.info("poses: %d frames, %d vertices, %d pairs, %d threads", n, X.shape[1],
             pi.size, max(1, int(threads or os.cpu_count() or 1)))
    T, r = _run_pairs(X, N, pi, pj, p, threads, icp_iter=p["icp_iterations"])
    return T, r.astype(np.float32)


def pose_table(vertices, faces, params: dict | None = None, seed: int | None = None,
               threads: int | None = None):
    """Rigid poses between every pair of frames.

    Args:
        vertices: (T, V, 3) float per-frame vertices of one topology (metres).
        faces: (F, 3) int triangles (counter-clockwise from outside), for the vertex normals of
            the point-to-plane ICP.
        params: the ``poses`` config section (missing keys take the schema defaults;
            the defaults).
        seed: overrides ``params["seed"]`` when given.
        threads: worker threads (default: all CPUs); the result does not depend on it.

    Returns:
        poses: (T, T, 4, 4) float64, poses[t, t'] = K_{t→t'} maps frame t onto frame t'
        (x' ≈ R x + t); only t < t' are estimated, poses[t', t] = inv(poses[t, t']) exactly and
        poses[t, t] = I.
        inlier_ratio: (T, T) float32, fraction of vertices within ``inlier_threshold_m`` of their
        partner after alignment (symmetric; 1 on the diagonal).
    """
    n = _check_vertices(vertices).shape[0]
    pi, pj = _all_pairs(n)
    T, r = pair_poses(vertices, faces, np.stack([pi, pj], axis=1), params, seed, threads)
    poses = np.broadcast_to(np.eye(4), (n, n, 4, 4)).copy()
    ratio = np.ones((n, n), np.float32)
    poses[pi, pj] = T
    poses[pj, pi] = invert_rigid(T)
    ratio[pi, pj] = r
    ratio[pj, pi] = r
    return poses, ratio
