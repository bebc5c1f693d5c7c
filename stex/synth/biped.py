"""A procedural walking biped: one closed skinned mesh over an 11-joint skeleton, walking in place.

The body is the union of capsules (torso, pelvis, head, upper and lower arms and legs, feet)
blended by a smooth minimum and meshed by marching cubes (scikit-image), so it is one closed
surface; each vertex is skinned to the bones nearest to it (up to 4, weights falling off with the
distance beyond the nearest). The walk cycle (period ``walk_period_s``) swings the hips by
``stride_deg`` and the shoulders against them, bends the knees and elbows, and bobs the pelvis.
Its texture is the procedural body's seeded noise and strokes in an xatlas atlas, tinted per part
(shirt, trousers, skin), with the same shape-driven wrinkles and pose patch as the glTF asset
(:class:`stex.synth.skinned.SkinnedBody`, whose appearance code it shares).
"""

from __future__ import annotations

import numpy as np

from stex.atlas import build_atlas, texel_map
from stex.mesh import decimate
from stex.synth.procedural import ProceduralBody, ProceduralParams
from stex.synth.skinned import SkinnedBody

# joint: (name, parent, pivot (x, y, z) m at height 1; the bone's capsules: (start, end, radius))
# x to the body's left, y up, z forward.
JOINTS = (
    ("pelvis", -1, (0.0, 0.50, 0.0), [((-0.055, 0.49, 0.0), (0.055, 0.49, 0.0), 0.085)]),
    ("spine", 0, (0.0, 0.56, 0.0), [((0.0, 0.57, 0.0), (0.0, 0.73, 0.0), 0.095)]),
    ("head", 1, (0.0, 0.80, 0.0), [((0.0, 0.80, 0.0), (0.0, 0.84, 0.0), 0.03), ((0.0, 0.88, 0.01), (0.0, 0.92, 0.01), 0.07)]),
    ("shoulder_l", 1, (0.145, 0.75, 0.0), [((0.145, 0.75, 0.0), (0.15, 0.59, 0.0), 0.034)]),
    ("elbow_l", 3, (0.15, 0.59, 0.0), [((0.15, 0.59, 0.0), (0.15, 0.43, 0.0), 0.03)]),
    ("shoulder_r", 1, (-0.145, 0.75, 0.0), [((-0.145, 0.75, 0.0), (-0.15, 0.59, 0.0), 0.034)]),
    ("elbow_r", 5, (-0.15, 0.59, 0.0), [((-0.15, 0.59, 0.0), (-0.15, 0.43, 0.0), 0.03)]),
    ("hip_l", 0, (0.065, 0.46, 0.0), [((0.065, 0.46, 0.0), (0.065, 0.25, 0.0), 0.05)]),
    ("knee_l", 7, (0.065, 0.25, 0.0), [((0.065, 0.25, 0.0), (0.065, 0.05, 0.0), 0.04),
                                       ((0.065, 0.035, -0.01), (0.065, 0.035, 0.07), 0.035)]),
    ("hip_r", 0, (-0.065, 0.46, 0.0), [((-0.065, 0.46, 0.0), (-0.065, 0.25, 0.0), 0.05)]),
    ("knee_r", 9, (-0.065, 0.25, 0.0), [((-0.065, 0.25, 0.0), (-0.065, 0.05, 0.0), 0.04),
                                        ((-0.065, 0.035, -0.01), (-0.065, 0.035, 0.07), 0.035)]),
)
PART_TINT = {"pelvis": (0.35, 0.38, 0.6), "spine": (0.85, 0.45, 0.3), "head": (0.95, 0.8, 0.65),
             "shoulder": (0.85, 0.45, 0.3), "elbow": (0.95, 0.8, 0.65), "hip": (0.35, 0.38, 0.6),
             "knee": (0.35, 0.38, 0.6)}
SMOOTH_M = 0.012        # smooth-minimum blend of the capsules (m, at height 1)
BIPED_FACES = 4000      # faces after decimation
VOXEL_M = 0.012         # marching-cubes voxel (m, at height 1)
SKIN_FALLOFF_M = 0.02   # a bone's weight falls by e per this distance beyond the nearest bone's (m)


def _segment_distance(P, a, b):
    """(n,) distance of points P (n, 3) from the segment a-b."""
    ab = np.subtract(b, a)
    s = np.clip(((P - a) @ ab) / max(ab @ ab, 1e-12), 0, 1)
    return np.linalg.norm(P - (np.asarray(a) + s[:, None] * ab), axis=1)


def _bone_distances(P):
    """(n, J) each point's signed distance from each joint's capsules (m, at height 1)."""
    return np.stack([np.min([_segment_distance(P, a, b) - r for a, b, r in caps], 0) for _, _, _, caps in JOINTS], 1)


def biped_mesh():
    """The biped at height 1 in its rest pose: vertices (V, 3) float64, faces (F, 3) int32
    (counter-clockwise from outside), joints (V, 4) int, weights (V, 4) float."""
    # imported here: the workflow imports the synthetic scenes while it reads its rules
    from skimage.measure import marching_cubes
    lo, hi = np.array([-0.28, -0.03, -0.12]), np.array([0.28, 1.0, 0.14])
    n = np.ceil((hi - lo) / VOXEL_M).astype(int) + 1
    axes = [lo[k] + VOXEL_M * np.arange(n[k]) for k in range(3)]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d = _bone_distances(G)
    k = SMOOTH_M   # smooth minimum (log-sum-exp) of the capsules' distances
    sdf = -k * np.log(np.exp(-(d - d.min(1, keepdims=True)) / k).sum(1)) + d.min(1)
    verts, faces, _, _ = marching_cubes(sdf.reshape(n), 0.0, spacing=(VOXEL_M,) * 3)
    verts, faces = decimate(verts + lo, faces.astype(np.int32), BIPED_FACES)
    faces = np.asarray(faces, np.int32)
    db = _bone_distances(verts)
    order = np.argsort(db, axis=1)[:, :4]
    near = np.take_along_axis(db, order, 1)
    w = np.exp(-(near - near[:, :1]) / SKIN_FALLOFF_M)
    return verts, faces, order, w / w.sum(1, keepdims=True)


class BipedBody(SkinnedBody):
    """The walking biped as a synthetic deforming object (the :class:`SkinnedBody` interface)."""

    def __init__(self, size_m: float = 0.7, walk_period_s: float = 1.1, stride_deg: float = 30.0,
                 texture_size: int = 512, seed: int = 0):
        V, F, J, W = biped_mesh()
        self.size_m, self.period, self.stride = size_m, walk_period_s, np.deg2rad(stride_deg)
        self.duration = walk_period_s
        self.centre = np.array([0.0, 0.5, 0.0])
        self.scale = size_m
        self.parents = np.array([j[1] for j in JOINTS])
        self.pivots = np.array([j[2] for j in JOINTS], np.float64)
        self.joint_names = [j[0] for j in JOINTS]
        self.faces, self.joints, self.weights = F, J, W
        self.bind_vertices = V
        self.rest_vertices = (V - self.centre) * self.scale
        self.texcoords, self.texcoord_faces = build_atlas(V, F, texture_size, 2)
        self.size = texture_size
        self.texel_face, self.texel_bary = texel_map(self.texcoords, self.texcoord_faces, texture_size)
        base = ProceduralBody(ProceduralParams(seed=seed)).base_texture(texture_size)
        main = np.asarray(J[:, 0])
        tint = np.array([PART_TINT[self.joint_names[j].split("_")[0]] for j in main], np.float32)
        per_texel = np.zeros(self.texel_face.shape + (3,), np.float32)
        hit = self.texel_face >= 0
        per_texel[hit] = (self.texel_bary[hit][..., None] * tint[self.faces[self.texel_face[hit]]]).sum(1)
        self.base = (base * (0.45 + 0.9 * per_texel)).clip(0, 1).astype(np.float32)
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        self.edges = np.unique(np.sort(e, axis=1), axis=0)
        self.rest_len = np.linalg.norm(self.rest_vertices[self.edges[:, 0]] - self.rest_vertices[self.edges[:, 1]], axis=1)
        top = int(np.argmax(self.rest_vertices[:, 1]))
        self.patch = np.exp(-(np.linalg.norm(self.rest_vertices - self.rest_vertices[top], axis=1) / (0.12 * size_m)) ** 2)

    def _local_rotations(self, time_s: float) -> np.ndarray:
        """(J, 3, 3) each joint's turn from the rest pose at ``time_s`` (the walk cycle)."""
        from scipy.spatial.transform import Rotation  # here: the workflow imports the scenes while it reads its rules
        ph = 2 * np.pi * time_s / self.period
        s = self.stride
        ang = {  # rotation vectors: +x turns a limb pointing down towards the back (z -)
            "hip_l": (-s * np.sin(ph), 0, 0), "hip_r": (s * np.sin(ph), 0, 0),
            "knee_l": (s * 1.1 * max(0.0, np.sin(ph - 1.2)) + 0.1, 0, 0),
            "knee_r": (s * 1.1 * max(0.0, np.sin(ph + np.pi - 1.2)) + 0.1, 0, 0),
            "shoulder_l": (0.8 * s * np.sin(ph), 0, -0.08), "shoulder_r": (-0.8 * s * np.sin(ph), 0, 0.08),
            "elbow_l": (-0.35 - 0.3 * max(0.0, np.sin(ph)), 0, 0), "elbow_r": (-0.35 - 0.3 * max(0.0, -np.sin(ph)), 0, 0),
            "spine": (0.05, 0.12 * np.sin(ph), 0), "head": (0, -0.1 * np.sin(ph), 0.04 * np.sin(2 * ph)),
            "pelvis": (0, -0.08 * np.sin(ph), 0.03 * np.sin(ph)),
        }
        return Rotation.from_rotvec([ang[n] for n in self.joint_names]).as_matrix()

    def _joint_motions(self, time_s: float | None):
        """Each joint's motion at height 1 (R (J, 3, 3), t (J, 3)): x -> R x + t, forward kinematics."""
        Jn = len(self.parents)
        if time_s is None:
            return np.tile(np.eye(3), (Jn, 1, 1)), np.zeros((Jn, 3))
        Q = self._local_rotations(float(time_s))
        bob = np.array([0.0, 0.012 * np.cos(4 * np.pi * time_s / self.period), 0.0])
        R, t = np.empty((Jn, 3, 3)), np.empty((Jn, 3))
        for j in range(Jn):
            p, c = self.parents[j], self.pivots[j]
            lt = c - Q[j] @ c
            R[j], t[j] = (Q[j], lt + bob) if p < 0 else (R[p] @ Q[j], R[p] @ lt + t[p])
        return R, t

    def vertices(self, time_s: float | None) -> np.ndarray:
        """(V, 3) float64 posed vertices in the object frame (m, +y up)."""
        R, t = self._joint_motions(time_s)
        moved = np.einsum("vkab,vb->vka", R[self.joints], self.bind_vertices) + t[self.joints]
        return ((self.weights[..., None] * moved).sum(1) - self.centre) * self.scale

    def skeleton(self, time_s: float | None):
        """As :meth:`SkinnedBody.skeleton`: parents, joint frames (J, 4, 4) in the object frame, vertex
        joints, weights, names."""
        R, t = self._joint_motions(time_s)
        frames = np.tile(np.eye(4), (len(R), 1, 1))
        frames[:, :3, :3] = R * self.scale
        frames[:, :3, 3] = (np.einsum("jab,jb->ja", R, self.pivots) + t - self.centre) * self.scale
        return self.parents, frames, self.joints, self.weights, list(self.joint_names)
