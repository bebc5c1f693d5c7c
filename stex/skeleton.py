"""A template's skeleton: joints, linear blend skinning, and the pose's derivatives.

A :class:`Skeleton` is what the template store holds under ``skeleton/*``: J joints, each with
its parent (``-1`` for a root; parents come before their children), its frame at the template's
own pose (``bind``, a 4x4 in template coordinates, metres; its translation is the joint's
pivot), and per template vertex up to 4 joint indices and weights summing to 1. The template's
own vertices are the skinned mesh at the identity pose.

A :class:`Pose` is one local rotation per joint, expressed in template coordinates (``Q_j``:
the turn of joint j about its pivot relative to its parent, as the template sits), and the root's
translation. Joint j moves template points by ``M_j = M_parent . T(c_j) Q_j T(-c_j)`` (roots:
``T(translation) T(c_j) Q_j T(-c_j)``), ``c_j`` the pivot. The skinned vertex is
``x_i' = sum_k w_ik M_{j_ik} x_i`` (linear blend skinning).

Derivatives (:func:`pose_jacobian`) are taken for a small turn ``delta_j`` of joint j about its
*current* pivot in camera coordinates (and the whole subtree with it): d x_i' / d delta_j =
-[u_ij - s_ij p_j]_x, ``p_j`` the moved pivot, ``u_ij`` the weighted sum of the vertex's moved
positions under the joints of j's subtree, ``s_ij`` their weight; the update is
``Q_j <- Exp(R_parent^T delta_j) Q_j`` (:func:`apply_step`).

The rig file a user gives (``template.rig``, :func:`read_rig`) is JSON:
``{"joints": [{"name": str, "parent": int (-1 root), "position": [x, y, z]}, ...],
"vertex_joints": [[j, ...], ...], "vertex_weights": [[w, ...], ...]}`` with positions in the
source template's coordinates (metres), one row of up to 4 joints and weights per source
template vertex, in its order.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

MAX_INFLUENCES = 4  # joints per vertex, as glTF's JOINTS_0 / WEIGHTS_0


@dataclass
class Skeleton:
    """Joints and skin weights of a template (see the module docstring).

    parents (J,) int64, -1 for roots, each parent before its children; bind (J, 4, 4) float64
    joint frames at the template's pose (template coordinates, m); joints (V, 4) int64 and
    weights (V, 4) float64 (rows sum to 1; unused slots weight 0); names: J joint names.
    """

    parents: np.ndarray
    bind: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    names: list = field(default_factory=list)

    def __post_init__(self):
        self.parents = np.asarray(self.parents, np.int64)
        self.bind = np.asarray(self.bind, np.float64)
        self.joints = np.asarray(self.joints, np.int64)
        self.weights = np.asarray(self.weights, np.float64)
        J = len(self.parents)
        if not self.names:
            self.names = [f"joint_{j}" for j in range(J)]
        if self.bind.shape != (J, 4, 4) or len(self.names) != J:
            raise ValueError(f"skeleton: {J} parents but bind {self.bind.shape} and {len(self.names)} names")
        if self.joints.shape != self.weights.shape or self.joints.ndim != 2:
            raise ValueError(f"skeleton: vertex joints {self.joints.shape} and weights {self.weights.shape} differ")
        bad = np.flatnonzero(self.parents >= np.arange(J))
        if len(bad):
            raise ValueError(f"skeleton: joint {bad[0]} ({self.names[bad[0]]}) comes before its parent "
                             f"{self.parents[bad[0]]}: parents must come first")
        if len(self.joints) and (self.joints.min() < 0 or self.joints.max() >= J):
            raise ValueError(f"skeleton: vertex joint indices outside 0..{J - 1}")
        s = self.weights.sum(1)
        if len(s) and (not np.isfinite(s).all() or np.abs(s - 1).max() > 1e-3 or self.weights.min() < 0):
            i = int(np.argmax(np.abs(s - 1)))
            raise ValueError(f"skeleton: vertex {i}'s weights sum to {s[i]:.4g}, must be non-negative and sum to 1")

    @property
    def pivots(self) -> np.ndarray:
        """(J, 3) float64 joint positions at the template's pose (m)."""
        return self.bind[:, :3, 3]

    @property
    def inverse_bind(self) -> np.ndarray:
        """(J, 4, 4) float64 inverse bind matrices (template coordinates -> joint frame)."""
        return np.linalg.inv(self.bind)

    def ancestors(self) -> np.ndarray:
        """(J, J) bool: [a, j] when a is j or one of its ancestors."""
        J = len(self.parents)
        anc = np.eye(J, dtype=bool)
        for j in range(J):
            if self.parents[j] >= 0:
                anc[:, j] |= anc[:, self.parents[j]]
        return anc


def skeleton_from_skin(parents, joint_frames, joints, weights, names=None) -> Skeleton:
    """A :class:`Skeleton` from a skin whose joints may come in any order (a glTF skin): joints
    reordered parents first, unused influences dropped, weights renormalised.

    parents (J,) int (-1 root) into the same list; joint_frames (J, 4, 4) float joint frames at
    the template's pose in template coordinates; joints (V, k) int, weights (V, k) float."""
    parents = np.asarray(parents, np.int64)
    J = len(parents)
    order, placed = [], np.zeros(J, bool)
    while len(order) < J:
        ready = [j for j in range(J) if not placed[j] and (parents[j] < 0 or placed[parents[j]])]
        if not ready:
            raise ValueError("skeleton: the joints' parents form a cycle")
        for j in ready:
            placed[j] = True
        order += ready
    order = np.array(order)
    new_index = np.empty(J, np.int64)
    new_index[order] = np.arange(J)
    new_parents = np.where(parents[order] >= 0, new_index[np.maximum(parents[order], 0)], -1)
    w = np.asarray(weights, np.float64)
    s = w.sum(1, keepdims=True)
    if (s <= 0).any():
        raise ValueError(f"skeleton: vertex {int(np.flatnonzero(s[:, 0] <= 0)[0])} has no skin weight")
    names = [f"joint_{j}" for j in range(J)] if names is None else list(names)
    return Skeleton(new_parents, np.asarray(joint_frames, np.float64)[order],
                    new_index[np.asarray(joints, np.int64)], w / s, [names[j] for j in order])


def skeleton_arrays(skeleton: Skeleton, prefix: str = "skeleton/") -> dict:
    """The store arrays of a skeleton (``prefix`` + parents, bind, inverse_bind, vertex_joints,
    vertex_weights; :data:`stex.artifacts.ARTIFACTS`); the joint names go in an attr."""
    return {f"{prefix}parents": skeleton.parents.astype(np.int32), f"{prefix}bind": skeleton.bind,
            f"{prefix}inverse_bind": skeleton.inverse_bind, f"{prefix}vertex_joints": skeleton.joints.astype(np.int32),
            f"{prefix}vertex_weights": skeleton.weights.astype(np.float32)}


def skeleton_from_arrays(arrays, names=None, prefix: str = "skeleton/") -> Skeleton | None:
    """The :class:`Skeleton` of :func:`skeleton_arrays`' arrays (any mapping with ``[...]``
    access and ``in``, e.g. an open store), or None where they are absent."""
    if f"{prefix}parents" not in arrays:
        return None
    return Skeleton(*(np.asarray(arrays[prefix + k][...]) for k in ("parents", "bind", "vertex_joints",
                                                                   "vertex_weights")), list(names or []))


def carry_skeleton(skeleton: Skeleton, faces, emb_face, emb_bary) -> Skeleton:
    """The skeleton of a template whose vertices lie on the source mesh (``faces`` (F0, 3), the
    source's, which ``skeleton``'s vertex weights refer to) at faces ``emb_face`` (V,) with
    barycentrics ``emb_bary`` (V, 3) (:func:`stex.mesh.embed_vertices`): each vertex's weights are
    the barycentric blend of its face corners', the 4 largest kept and renormalised."""
    J = len(skeleton.parents)
    corners = np.asarray(faces, np.int64)[np.asarray(emb_face, np.int64)]        # (V, 3)
    dense = np.zeros((len(corners), J))
    rows = np.arange(len(corners))
    for c in range(3):
        for k in range(skeleton.joints.shape[1]):
            np.add.at(dense, (rows, skeleton.joints[corners[:, c], k]),
                      emb_bary[:, c] * skeleton.weights[corners[:, c], k])
    dense = np.pad(np.maximum(dense, 0.0), ((0, 0), (0, max(0, MAX_INFLUENCES - J))))  # 4 slots even for J < 4
    top = np.argsort(-dense, axis=1, kind="stable")[:, :MAX_INFLUENCES]
    w = np.take_along_axis(dense, top, 1)
    top = np.where(top < J, top, 0)            # padding slots: joint 0 at weight 0
    s = w.sum(1, keepdims=True)
    if (s <= 0).any():
        raise ValueError("skeleton: a template vertex got no skin weight from its source face")
    return Skeleton(skeleton.parents, skeleton.bind, top, w / s, skeleton.names)


def read_rig(path, n_vertices: int) -> Skeleton:
    """The :class:`Skeleton` of a rig file (JSON, the module docstring's format) for a source
    template of ``n_vertices`` vertices; ValueError naming the file and what is wrong."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        joints = doc["joints"]
        parents = [int(j["parent"]) for j in joints]
        names = [str(j.get("name", f"joint_{i}")) for i, j in enumerate(joints)]
        pos = np.array([j["position"] for j in joints], np.float64).reshape(len(joints), 3)
        vj, vw = doc["vertex_joints"], doc["vertex_weights"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a rig file ({type(e).__name__}: {e}); expected JSON with joints "
                         f"[{{name, parent, position}}], vertex_joints and vertex_weights") from e
    if len(vj) != n_vertices or len(vw) != n_vertices:
        raise ValueError(f"{path}: {len(vj)} vertex_joints and {len(vw)} vertex_weights rows, the template has "
                         f"{n_vertices} vertices (one row each, in the template's vertex order)")
    J = np.zeros((n_vertices, MAX_INFLUENCES), np.int64)
    W = np.zeros((n_vertices, MAX_INFLUENCES))
    for i, (a, b) in enumerate(zip(vj, vw)):
        if len(a) != len(b) or not 1 <= len(a) <= MAX_INFLUENCES:
            raise ValueError(f"{path}: vertex {i}: {len(a)} joints and {len(b)} weights (1 to {MAX_INFLUENCES}, alike)")
        J[i, :len(a)], W[i, :len(b)] = a, b
    if not all(-1 <= p < len(parents) for p in parents) or (J >= len(parents)).any() or (J < 0).any():
        raise ValueError(f"{path}: a joint index outside 0..{len(parents) - 1}")
    frames = np.tile(np.eye(4), (len(parents), 1, 1))
    frames[:, :3, 3] = pos
    try:
        return skeleton_from_skin(parents, frames, J, W, names)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


# -- poses -----------------------------------------------------------------------------------------

@dataclass
class Pose:
    """Local rotations (J, 3, 3) float64 in template coordinates and the root translation (3,) m."""

    rotations: np.ndarray
    translation: np.ndarray

    def copy(self) -> "Pose":
        return Pose(self.rotations.copy(), self.translation.copy())


def identity_pose(n_joints: int) -> Pose:
    """The template's own pose."""
    return Pose(np.tile(np.eye(3), (n_joints, 1, 1)), np.zeros(3))


def joint_transforms(skeleton: Skeleton, pose: Pose):
    """Each joint's motion of template points, x' = R_j x + t_j: (R (J, 3, 3), t (J, 3))."""
    c = skeleton.pivots
    J = len(c)
    R, t = np.empty((J, 3, 3)), np.empty((J, 3))
    for j in range(J):
        Q, p = pose.rotations[j], skeleton.parents[j]
        local_t = c[j] - Q @ c[j]
        if p < 0:
            R[j], t[j] = Q, local_t + pose.translation
        else:
            R[j], t[j] = R[p] @ Q, R[p] @ local_t + t[p]
    return R, t


def skin(skeleton: Skeleton, rest: np.ndarray, pose: Pose) -> np.ndarray:
    """(V, 3) float64 linear blend skinning of the template vertices ``rest`` (V, 3) at ``pose``."""
    R, t = joint_transforms(skeleton, pose)
    moved = np.einsum("vkab,vb->vka", R[skeleton.joints], rest) + t[skeleton.joints]   # (V, k, 3)
    return (skeleton.weights[..., None] * moved).sum(1)


def pose_jacobian(skeleton: Skeleton, rest: np.ndarray, pose: Pose, anc: np.ndarray | None = None):
    """The skinned vertices (V, 3) and d x_i' / d(delta, translation): (V, 3, 3 J + 3) float64,
    delta_j a small turn of joint j (and its subtree) about its moved pivot in camera
    coordinates, the last 3 columns the root translation (see the module docstring).
    ``anc`` is :meth:`Skeleton.ancestors` (computed when None)."""
    anc = skeleton.ancestors() if anc is None else anc
    R, t = joint_transforms(skeleton, pose)
    moved = np.einsum("vkab,vb->vka", R[skeleton.joints], rest) + t[skeleton.joints]   # (V, k, 3)
    X = (skeleton.weights[..., None] * moved).sum(1)
    p = np.einsum("jab,jb->ja", R, skeleton.pivots) + t                                 # moved pivots
    sub = anc[:, skeleton.joints] * skeleton.weights[None]                              # (J, V, k)
    u = np.einsum("jvk,vka->vja", sub, moved) - sub.sum(2).T[..., None] * p[None]      # (V, J, 3)
    V, J = len(X), len(p)
    D = np.zeros((V, 3, 3 * J + 3))
    # d x / d delta = delta x u = -[u]_x delta
    D[:, 0, 1:3 * J:3], D[:, 0, 2:3 * J:3] = u[..., 2], -u[..., 1]
    D[:, 1, 0:3 * J:3], D[:, 1, 2:3 * J:3] = -u[..., 2], u[..., 0]
    D[:, 2, 0:3 * J:3], D[:, 2, 1:3 * J:3] = u[..., 1], -u[..., 0]
    roots = skeleton.parents < 0
    if roots.sum() != 1:
        raise ValueError(f"skeleton: {int(roots.sum())} root joints; the pose's translation needs exactly one")
    D[:, :, 3 * J:] = np.eye(3)
    return X, D


def apply_step(skeleton: Skeleton, pose: Pose, step: np.ndarray) -> Pose:
    """The pose after the step (3 J + 3,) of :func:`pose_jacobian`'s unknowns."""
    R, _ = joint_transforms(skeleton, pose)
    J = len(skeleton.parents)
    delta = step[:3 * J].reshape(J, 3)
    out = pose.copy()
    for j in range(J):
        p = skeleton.parents[j]
        local = delta[j] if p < 0 else R[p].T @ delta[j]
        out.rotations[j] = Rotation.from_rotvec(local).as_matrix() @ pose.rotations[j]
    out.translation = pose.translation + step[3 * J:]
    return out


def compose_root(skeleton: Skeleton, pose: Pose, R: np.ndarray, t: np.ndarray) -> Pose:
    """The pose moved as a whole by the rigid motion x -> R x + t (camera coordinates)."""
    root = int(np.flatnonzero(skeleton.parents < 0)[0])
    c = skeleton.pivots[root]
    out = pose.copy()
    out.rotations[root] = R @ pose.rotations[root]
    out.translation = R @ (c + pose.translation) + t - c
    return out


def rotation_vectors(rotations: np.ndarray) -> np.ndarray:
    """(J, 3) rotation vectors (rad) of (J, 3, 3) rotations."""
    return Rotation.from_matrix(rotations).as_rotvec()


def limb_joints(skeleton: Skeleton, min_vertices: int = 1, depth: int = 2) -> list[list[int]]:
    """Limbs for the per-limb search: for every joint that starts a branch (its parent has two or
    more children) and skins at least ``min_vertices`` vertices in its subtree, the joint and its
    first descendants down the chain, ``depth`` joints at most."""
    J = len(skeleton.parents)
    children = [np.flatnonzero(skeleton.parents == j) for j in range(J)]
    anc = skeleton.ancestors()
    main = skeleton.joints[np.arange(len(skeleton.joints)), skeleton.weights.argmax(1)]
    limbs = []
    for j in range(J):
        p = skeleton.parents[j]
        if p < 0 or len(children[p]) < 2:
            continue
        if anc[j, main].sum() < min_vertices:
            continue
        chain = [j]
        while len(chain) < depth and len(children[chain[-1]]):
            chain.append(int(children[chain[-1]][0]))
        limbs.append(chain)
    return limbs
