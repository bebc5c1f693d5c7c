"""A skinned, animated glTF asset as a synthetic deforming object (linear blend skinning).

The asset is centred and scaled so its largest extent is ``size_m`` metres (glTF files use any
unit; the Khronos Fox is in centimetres). Its appearance is the asset's base-colour texture
modulated by the shape, as for the procedural body: wrinkle stripes where the surface around a
vertex is compressed relative to the bind pose, and a patch (around the highest vertex) whose
colour follows the animation phase, so frames of similar pose have similar texture.
"""

from __future__ import annotations

import cv2
import numpy as np

from stex.atlas import texel_map
from stex.synth.gltf import load_skinned_gltf, node_global_transforms, pose_vertices
from stex.synth.procedural import ProceduralBody, ProceduralParams


class SkinnedBody:
    def __init__(self, path, animation=0, size_m: float = 0.5, texture_size: int = 512, seed: int = 0):
        self.mesh = load_skinned_gltf(path)
        names = self.mesh.animation_names
        if not names:
            raise ValueError(f"{path}: the asset has no animation")
        self.animation = animation
        idx = animation if isinstance(animation, int) else names.index(animation) if animation in names else None
        if idx is None or not 0 <= idx < len(names):
            raise ValueError(f"{path}: no animation {animation!r}; available: {names}")
        self.duration = float(self.mesh.animations[idx].duration_s)
        lo, hi = self.mesh.vertices.min(0), self.mesh.vertices.max(0)
        self.centre = (lo + hi) / 2
        self.scale = size_m / float((hi - lo).max())
        self.faces = np.asarray(self.mesh.faces, np.int32)
        self.texcoords = np.asarray(self.mesh.texcoords, np.float64)
        self.texcoord_faces = np.asarray(self.mesh.texcoord_faces, np.int32)
        self.rest_vertices = (np.asarray(self.mesh.vertices) - self.centre) * self.scale
        self.size = texture_size
        if self.mesh.texture is not None:
            base = cv2.resize(self.mesh.texture, (texture_size, texture_size), interpolation=cv2.INTER_AREA)
            self.base = base.astype(np.float32) / 255.0
        else:
            self.base = ProceduralBody(ProceduralParams(n_around=8, n_rings=4, seed=seed)).base_texture(texture_size)

        self.texel_face, self.texel_bary = texel_map(self.texcoords, self.texcoord_faces, texture_size)
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        self.edges = np.unique(np.sort(e, axis=1), axis=0)
        self.rest_len = np.linalg.norm(self.rest_vertices[self.edges[:, 0]] - self.rest_vertices[self.edges[:, 1]], axis=1)
        top = int(np.argmax(self.rest_vertices[:, 1]))
        d = np.linalg.norm(self.rest_vertices - self.rest_vertices[top], axis=1)
        self.patch = np.exp(-(d / (0.12 * size_m)) ** 2)

    def vertices(self, time_s: float | None) -> np.ndarray:
        """(V, 3) float64 posed vertices in the object frame (m, +y up)."""
        if time_s is None:
            return self.rest_vertices.copy()
        v = pose_vertices(self.mesh, self.animation, float(time_s), loop=True)
        return (v - self.centre) * self.scale

    def skeleton(self, time_s: float | None):
        """The skin at ``time_s`` (None: bind pose) in the object frame: (parents (J,) int, -1 for
        roots; joint frames (J, 4, 4) float64, m, scaled with the asset; vertex joints (V, 4) int;
        weights (V, 4) float; joint names)."""
        m = self.mesh
        glob = node_global_transforms(m, None if time_s is None else self.animation,
                                      0.0 if time_s is None else float(time_s), loop=True)
        to_object = np.diag([self.scale, self.scale, self.scale, 1.0])
        to_object[:3, 3] = -self.centre * self.scale
        index = {int(n): j for j, n in enumerate(m.joint_nodes)}
        parents = np.full(len(m.joint_nodes), -1, np.int64)
        for j, n in enumerate(m.joint_nodes):
            p = int(m.node_parents[n])
            while p >= 0 and p not in index:   # a joint's nearest ancestor that is a joint
                p = int(m.node_parents[p])
            parents[j] = index.get(p, -1)
        return parents, to_object @ glob[m.joint_nodes], m.joints, m.weights, list(m.joint_names)

    def pose_parameter(self, time_s: float | None) -> float:
        return 0.0 if time_s is None else float(np.sin(2 * np.pi * time_s / self.duration))

    def vertex_compression(self, time_s: float | None) -> np.ndarray:
        """(V,) mean relative shortening of the edges around each vertex (0 = none)."""
        V = self.vertices(time_s)
        ratio = np.linalg.norm(V[self.edges[:, 0]] - V[self.edges[:, 1]], axis=1) / np.maximum(self.rest_len, 1e-12)
        comp = np.clip(1 - ratio, 0, 1)
        acc = np.zeros(len(V))
        cnt = np.zeros(len(V))
        for k in (0, 1):
            np.add.at(acc, self.edges[:, k], comp)
            np.add.at(cnt, self.edges[:, k], 1)
        return acc / np.maximum(cnt, 1)

    def _per_texel(self, per_vertex: np.ndarray) -> np.ndarray:
        out = np.zeros(self.texel_face.shape, np.float64)
        hit = self.texel_face >= 0
        f = self.faces[self.texel_face[hit]]
        out[hit] = (self.texel_bary[hit] * per_vertex[f]).sum(1)
        return out

    def appearance(self, time_s: float | None) -> np.ndarray:
        """(size, size, 3) uint8 true texture at ``time_s``."""
        comp = self._per_texel(self.vertex_compression(time_s))
        v = (np.arange(self.size) + 0.5) / self.size
        stripes = 0.5 + 0.5 * np.cos(2 * np.pi * 40 * v)[:, None]
        wrinkle = np.clip(comp / 0.1, 0, 1) * stripes
        tex = self.base * (1 - 0.6 * wrinkle)[..., None]
        pose = self.pose_parameter(time_s)
        tint = np.array([0.92, 0.18, 0.15] if pose >= 0 else [0.15, 0.3, 0.92], np.float32)
        k = (0.85 * abs(pose) * self._per_texel(self.patch))[..., None]
        tex = tex * (1 - k) + tint * k
        return (tex * 255 + 0.5).clip(0, 255).astype(np.uint8)
