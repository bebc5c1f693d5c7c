"""Skeleton-driven tracking: each frame's bone rotations and root translation, solved before the
deformation graph (BodyFusion, Yu et al. ICCV 2017; DoubleFusion, CVPR 2018).

Per frame (:meth:`ArticulatedTracker.solve`, called by :func:`stex.tracking.track_sequence`
after the rigid stage):

1. the last frame's pose moved by the rigid stage's motion;
2. Levenberg-Marquardt on the pose (:mod:`stex.skeleton`: a turn per joint about its pivot and the
   root's translation; linear blend skinning) with the tracker's own data terms
   (:func:`stex.tracking.step_terms`: point-to-plane depth, optical flow against the appearance
   model, silhouette), first with closest-point pairs within twice ``max_distance_m`` then
   projective ones, and a prior pulling each joint's turn towards the last frame's
   (``skeleton_w_prior``) and, weaker, towards the template's pose (``skeleton_w_rest``);
3. a per-limb search (``skeleton_search_deg``): each limb's upper two joints try turns about three
   axes, a turn kept when it lowers the clipped rendered-vs-observed depth difference
   (:func:`stex.frame_fit.depth_residual`), since Gauss-Newton from a limb that swung several cm
   follows the nearest surface, often the body's; then the solve once more.

The graph (ED + L0) then solves on top of the skinned mesh for what the skeleton does not explain,
and the vertices the depth camera does not see keep the skinned positions (:meth:`pose_unseen`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from stex.render import rasterize, vertex_normals, vertex_visibility
from stex.skeleton import (
    Pose, Skeleton, apply_step, compose_root, identity_pose, joint_transforms, limb_joints, pose_jacobian,
    rotation_vectors, skin)
from stex.tracking import FRAME_GUARD_CLIP_M, DepthTarget, TrackParams, colour_px_scale, data_rows, lm_step, step_terms

LIMB_DEPTH = 2           # joints of each limb's chain the per-limb search turns
SEARCH_AXES = np.eye(3)  # the per-limb search turns about the camera's axes
DATA_TO_MODEL_STRIDE = 2  # every k-th depth pixel along rows and columns feeds the depth-to-mesh pairs
SEARCH_NEAR_PX = 2       # mesh pixels this close to usable depth are not counted as off the object


@dataclass
class ArticulatedParams:
    """The skeleton stage's settings (``tracking.skeleton_*`` in stex/schema.yaml)."""

    iterations: int = 8
    w_prior: float = 1e-3
    w_rest: float = 1e-5
    w_data_to_model: float = 1.0
    velocity: float = 1.0
    search_deg: tuple = (10.0, 20.0, 35.0)
    min_seen: float = 5.0
    unseen_return: float = 0.3
    reacquire_deg: tuple = (50.0, 70.0)

    @classmethod
    def from_dict(cls, d: dict) -> "ArticulatedParams":
        """From the ``tracking`` config section (keys ``skeleton_<field>``; missing ones default)."""
        out = cls()
        for name in cls.__dataclass_fields__:
            key = f"skeleton_{name}"
            if key in d and d[key] is not None:
                v = d[key]
                setattr(out, name, tuple(float(a) for a in v) if name.endswith("_deg") else type(getattr(out, name))(v))
        return out


def _search_score(X, faces, target: DepthTarget, near) -> float:
    """How well the mesh ``X`` explains the depth, for the per-limb search: the clipped depth
    difference (FRAME_GUARD_CLIP_M) where both cover a pixel, the clip where only the depth does or
    where the mesh covers a pixel farther than SEARCH_NEAR_PX from any usable depth (``near``
    (H, W) bool), over the pixels either covers. Why not :func:`stex.frame_fit.depth_residual`:
    a thin limb's pixels are mostly depth edges, which have no usable depth, and that score pays
    a limb for leaving them."""
    H, W = target.valid.shape
    d = rasterize(X, faces, target.K, W, H).depth
    m, v = d > 0, target.valid
    both = m & v
    diff = np.minimum(np.abs(d[both] - target.points[..., 2][both]), FRAME_GUARD_CLIP_M).sum()
    miss = (v & ~m).sum() + (m & ~near).sum()
    n = (m | v).sum()
    return float((diff + FRAME_GUARD_CLIP_M * miss) / n) if n else 0.0


def _pair_cost(X, pairs, huber_m) -> float:
    """Robust point-to-plane cost of :meth:`ArticulatedTracker._data_to_model` pairs at ``X``."""
    v, q, nq, w = pairs
    r = (nq * (X[v] - q)).sum(1)
    a = np.abs(r)
    return float((w * np.where(a <= huber_m, r * r, 2 * huber_m * a - huber_m ** 2)).sum())


def _pair_rows(X, pairs, huber_m):
    """(vertex ids, weighted rows d r / d x (n, 3), weighted residuals (n,)) of the pairs at ``X``."""
    v, q, nq, w = pairs
    r = (nq * (X[v] - q)).sum(1)
    sw = np.sqrt(w * np.where(np.abs(r) <= huber_m, 1.0, huber_m / np.maximum(np.abs(r), 1e-12)))
    return v, nq * sw[:, None], r * sw


class ArticulatedTracker:
    """The pose of a template's skeleton through a sequence (see the module docstring).

    skeleton: the template's (:class:`stex.skeleton.Skeleton`, weights for ``rest``'s vertices);
    rest: (V, 3) float64 the template's vertices (m), the skinned mesh at the identity pose;
    faces: (F, 3) int; params: the tracker's settings (data terms, association radius).
    """

    def __init__(self, skeleton: Skeleton, rest: np.ndarray, faces: np.ndarray, params: TrackParams,
                 ap: ArticulatedParams | None = None):
        if len(skeleton.joints) != len(rest):
            raise ValueError(f"skeleton: weights for {len(skeleton.joints)} vertices, the template has {len(rest)}")
        self.skeleton, self.rest, self.faces = skeleton, np.asarray(rest, np.float64), np.asarray(faces, np.int64)
        self.ap = ap or ArticulatedParams()
        self.anc = skeleton.ancestors()
        self.limbs = limb_joints(skeleton, min_vertices=10, depth=LIMB_DEPTH)
        self.pose = identity_pose(len(skeleton.parents))
        self.last = None        # the pose of the frame before, for the joints' velocity
        # (J, V) how much each joint's subtree moves each vertex (skin weights summed down the chain)
        self.influence = (self.anc[:, skeleton.joints] * skeleton.weights[None]).sum(2)
        self.seen = np.ones(len(skeleton.parents), bool)   # joints with data in the frame before
        self.coarse = TrackParams(**{**params.__dict__, "association": "closest",
                                     "max_distance_m": 2 * params.max_distance_m})
        self.fine = params

    def vertices(self, pose=None) -> np.ndarray:
        """(V, 3) the skinned template at ``pose`` (default: the current one)."""
        return skin(self.skeleton, self.rest, self.pose if pose is None else pose)

    def solve(self, R, t, target: DepthTarget, flow=None, silhouette=None, stats=None) -> np.ndarray:
        """This frame's pose, from the last one moved by the rigid motion x -> R x + t; returns the
        skinned vertices (V, 3) and records "skeleton_steps" and "skeleton_search_kept" in ``stats``."""
        stats = {} if stats is None else stats
        # start from the joints' predicted turn; the prior holds each joint to where it was
        # (moved with the root), so a joint no data reaches stops instead of turning on
        last = compose_root(self.skeleton, self.pose, R, t)
        seen = self.joints_seen(self.vertices(last), target)
        start = compose_root(self.skeleton, self._predicted(seen), R, t)
        half = max(1, self.ap.iterations // 2)
        steps = [0]
        pose = self._lm(start, last, target, flow, silhouette, self.coarse, half, stats, steps)
        kept = 0
        if self.ap.search_deg:
            pose, kept = self._limb_search(pose, target, back=seen & ~self.seen)
        pose = self._lm(pose, last, target, flow, silhouette, self.fine, self.ap.iterations - half, stats, steps)
        # a joint no depth reaches keeps its predicted turn: whatever moved it in the solve was
        # data of another part (the depth-to-mesh pairs reach hidden vertices too)
        pose.rotations[~seen] = start.rotations[~seen]
        stats["skeleton_steps"], stats["skeleton_search_kept"] = steps[0], kept
        stats["skeleton_unseen_joints"] = int((~seen).sum())
        self.last, self.pose, self.seen = self.pose, pose, seen
        return self.vertices()

    def joints_seen(self, X, target: DepthTarget) -> np.ndarray:
        """(J,) bool: the joints whose subtree moves at least ``min_seen`` vertices' worth (skin
        weights summed) of the mesh ``X`` (V, 3) that the depth camera sees."""
        H, W = target.valid.shape
        vis = vertex_visibility(X, self.faces, target.K, rasterize(X, self.faces, target.K, W, H).depth)[0]
        return self.influence[:, vis].sum(1) >= self.ap.min_seen

    def _predicted(self, seen=None) -> Pose:
        """The pose the joints' last turn, once more (times ``velocity``), leads to; the root is the
        rigid stage's. Why: a walking limb turns by about as much each frame, several cm at the paw,
        farther than its data pairs reach from where it was. A joint not ``seen`` ((J,) bool) does
        not go on turning (no data would stop it): it turns back towards the template's pose by
        the fraction ``unseen_return`` of its turn."""
        J = len(self.skeleton.parents)
        seen = np.ones(J, bool) if seen is None else seen
        out = self.pose.copy()
        roots = self.skeleton.parents < 0
        if self.last is not None and self.ap.velocity > 0:
            turn = rotation_vectors(np.einsum("jab,jcb->jac", self.pose.rotations, self.last.rotations))
            step = Rotation.from_rotvec(self.ap.velocity * turn).as_matrix()
            go = ~roots & seen
            out.rotations[go] = np.einsum("jab,jbc->jac", step[go], self.pose.rotations[go])
        back = ~roots & ~seen
        if self.ap.unseen_return > 0 and back.any():
            keep = rotation_vectors(self.pose.rotations[back]) * (1.0 - min(self.ap.unseen_return, 1.0))
            out.rotations[back] = Rotation.from_rotvec(keep).as_matrix()
        return out

    def pose_unseen(self, cur: np.ndarray, faces, target: DepthTarget) -> np.ndarray:
        """``cur`` (V, 3) with the vertices the depth camera does not see at the skinned pose."""
        H, W = target.valid.shape
        seen = vertex_visibility(cur, faces, target.K, rasterize(cur, faces, target.K, W, H).depth)[0]
        return np.where(seen[:, None], cur, self.vertices())

    # -- the pose's solve ------------------------------------------------------------------------

    def _prior(self, pose, prior_pose):
        """Prior residuals (r (6 J,), their Jacobian (6 J, 3 J + 3)) of the pose: each joint's turn
        from ``prior_pose`` and from the template's pose."""
        sk, ap = self.skeleton, self.ap
        J = len(sk.parents)
        R, _ = joint_transforms(sk, pose)
        r = np.concatenate([np.sqrt(ap.w_prior) * rotation_vectors(
            np.einsum("jab,jcb->jac", pose.rotations, prior_pose.rotations)).ravel(),
            np.sqrt(ap.w_rest) * rotation_vectors(pose.rotations).ravel()])
        Jp = np.zeros((6 * J, 3 * J + 3))
        for j in range(J):
            p = sk.parents[j]
            d = np.eye(3) if p < 0 else R[p].T     # d local / d delta (first order)
            Jp[3 * j:3 * j + 3, 3 * j:3 * j + 3] = np.sqrt(ap.w_prior) * d
            Jp[3 * J + 3 * j:3 * J + 3 * j + 3, 3 * j:3 * j + 3] = np.sqrt(ap.w_rest) * d
        return r, Jp

    def _lm(self, pose, prior_pose, target, flow, silhouette, p: TrackParams, iterations, stats, steps):
        """Levenberg-Marquardt steps on the pose (:func:`stex.tracking.lm_step` acceptance)."""
        sk = self.skeleton
        px_scale = colour_px_scale(self.vertices(pose), flow, silhouette)
        mu, nu, vis_cos = 0.0, 2.0, None
        guard = {"lm_rejected": 0, "lm_failed": 0}
        for it in range(iterations):
            X, D = pose_jacobian(sk, self.rest, pose, self.anc)
            depth, sil, vis_cos, cost, vid, Dw, rw = step_terms(
                X, self.faces, target, p, None if it % 4 == 0 else vis_cos, flow, silhouette, px_scale, stats)
            if it % 4 == 0:
                pairs = self._data_to_model(X, target, p)
            cost += _pair_cost(X, pairs, p.huber_m)
            vid, Dw, rw = (np.concatenate([a, b]) for a, b in zip((vid, Dw, rw), _pair_rows(X, pairs, p.huber_m)))
            rows = np.einsum("na,nap->np", Dw, D[vid])
            rp, Jp = self._prior(pose, prior_pose)
            JtJ = rows.T @ rows + Jp.T @ Jp + 1e-9 * np.eye(len(Jp.T))
            g = rows.T @ rw + Jp.T @ rp
            diag = np.diag(JtJ).copy()

            def energy_after(step, pose=pose, depth=depth, sil=sil, pairs=pairs):
                new = apply_step(sk, pose, step)
                rn, _ = self._prior(new, prior_pose)
                Xn = self.vertices(new)
                return (data_rows(Xn, p, depth, flow, sil, rows=False, px_scale=px_scale)[0] + rn @ rn
                        + _pair_cost(Xn, pairs, p.huber_m))

            step, mu, nu = lm_step(cost + rp @ rp, g, JtJ, lambda mu: np.linalg.solve(JtJ + np.diag(mu * diag), -g),
                                   energy_after, mu, nu, guard)
            if step is None:
                break
            pose = apply_step(sk, pose, step)
            steps[0] += 1
            if np.abs(step).max() < 1e-5:
                break
        return pose

    def _data_to_model(self, X, target: DepthTarget, p: TrackParams):
        """Depth-to-mesh pairs (vertex ids (n,), points (n, 3), normals (n, 3), weights (n,)): every
        DATA_TO_MODEL_STRIDE-th foreground depth pixel the rendered mesh does not explain (no surface
        there, or one more than ``huber_m`` * 3 off in depth), with the nearest vertex facing the
        camera the same way within twice ``max_distance_m``, seen or hidden: so that the depth
        reaches a limb the mesh has left or hides behind another part."""
        H, W = target.valid.shape
        k = DATA_TO_MODEL_STRIDE
        d = rasterize(X, self.faces, target.K, W, H).depth
        obs = target.points[..., 2]
        sel = target.valid & ((d <= 0) | (np.abs(d - obs) > 3 * p.huber_m))
        grid = np.zeros_like(sel)
        grid[::k, ::k] = True
        sel &= grid
        empty = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        if not sel.any() or self.ap.w_data_to_model <= 0:
            return empty
        q, nq = target.points[sel], target.normals[sel]
        dist, v = cKDTree(X).query(q, distance_upper_bound=2 * p.max_distance_m)
        ok = np.isfinite(dist)
        nv = vertex_normals(X, self.faces)
        ok[ok] &= (nv[v[ok]] * nq[ok]).sum(1) > 0
        return v[ok], q[ok], nq[ok], np.full(int(ok.sum()), self.ap.w_data_to_model * k * k / 4.0)

    def _limb_search(self, pose, target, back=None):
        """Each limb's upper joints turned by ``search_deg`` about the camera's axes, both ways, a
        turn kept where it lowers the clipped depth difference; returns (pose, turns kept). A limb
        whose first joint comes ``back`` into view ((J,) bool) also tries ``reacquire_deg``: it
        was held without data and may be far from where it is now."""
        sk = self.skeleton
        back = np.zeros(len(sk.parents), bool) if back is None else back
        near = cv2.dilate(target.valid.astype(np.uint8), np.ones((2 * SEARCH_NEAR_PX + 1,) * 2, np.uint8)) > 0
        best = _search_score(self.vertices(pose), self.faces, target, near)
        kept = 0
        for limb in self.limbs:
            for j in limb:
                cand_best = None
                R, _ = joint_transforms(sk, pose)
                Rp = np.eye(3) if sk.parents[j] < 0 else R[sk.parents[j]]
                degs = self.ap.search_deg + (self.ap.reacquire_deg if back[limb[0]] else ())
                for axis in SEARCH_AXES:
                    for deg in degs:
                        for sign in (-1.0, 1.0):
                            cand = pose.copy()
                            turn = Rotation.from_rotvec(Rp.T @ axis * np.deg2rad(sign * deg)).as_matrix()
                            cand.rotations[j] = turn @ pose.rotations[j]
                            score = _search_score(self.vertices(cand), self.faces, target, near)
                            if score < best and (cand_best is None or score < cand_best[0]):
                                cand_best = (score, cand)
                if cand_best is not None:
                    best, pose = cand_best
                    kept += 1
        return pose, kept
