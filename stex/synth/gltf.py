"""A small glTF 2.0 reader for skinned, animated meshes, and linear blend skinning.

Synthetic test scenes for stex are made from skinned animated glTF assets: this module reads the
skinned mesh of a ``.gltf`` (external buffers or ``data:`` URIs) or ``.glb`` file with numpy only
(JSON + binary buffers; no third-party glTF code) and poses it at any animation time.

glTF conventions (kept as they are; callers convert):

- Lengths in metres (by the specification; some assets, e.g. the Khronos *Fox*, are authored in
  centimetre-ish units - check the bounding box and scale when building a scene), right-handed,
  +Y up, the asset's front faces +Z.
- Texture coordinates: u to the right, v down, origin at the top-left of the image (row 0 of
  the image array). This is also stex's UV convention, so no flip happens here.
- Quaternions are stored (x, y, z, w); matrices are 4x4 acting on column vectors ``M @ [x,y,z,1]``
  (glTF stores them column-major; they are transposed on reading).

Skinning follows the glTF 2.0 specification (section "Skins"): the joint matrix of joint j is
``globalTransform(joint_node_j) @ inverseBindMatrix_j``, the posed vertex is
``sum_k w_k * jointMatrix(joints_k) @ v`` and **the transform of the skinned mesh's own node is
ignored** (only the joint transforms place the mesh). Posed vertices are therefore in the glTF
scene (world) frame; when every joint is at its bind pose they equal the bind-pose ``vertices``,
which are given in the mesh node's local frame (the frame of the POSITION attribute).

Public API: :func:`load_skinned_gltf`, :func:`pose_vertices`, :func:`pose_sequence`, and the
lower-level :func:`node_global_transforms`, :func:`joint_matrices`, :func:`skin_vertices`,
:func:`sample_channel`, :func:`animation_index`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stex.synth.gltf_reader import (
    MODE_NAMES, UNSUPPORTED_EXTENSIONS, GltfError, GltfNoSkinError, GltfReader, load_buffers, read_document)


UNITS_NOTE = (
    "glTF 2.0: metres (by specification; check the bounding box, some assets are authored in "
    "centimetre-like units), right-handed, +Y up, asset front faces +Z; UV u right, v down, "
    "origin top-left of the image (same as stex)."
)


# --------------------------------------------------------------------------------------------
# Data classes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AnimationChannel:
    """One animated property of one node.

    Attributes:
        node: index of the target node (into the ``SkinnedMesh.node_*`` arrays).
        path: ``"translation"``, ``"rotation"`` or ``"scale"``.
        interpolation: ``"LINEAR"``, ``"STEP"`` or ``"CUBICSPLINE"``.
        times: (K,) float64 keyframe times in seconds, strictly increasing.
        values: float64 keyframe values: (K, C) for LINEAR/STEP; (K, 3, C) for CUBICSPLINE
            holding (in-tangent, value, out-tangent) per keyframe. C = 3 (translation, metres;
            scale, unitless) or 4 (rotation quaternion x, y, z, w).
    """

    node: int
    path: str
    interpolation: str
    times: np.ndarray
    values: np.ndarray


@dataclass(frozen=True, eq=False)
class Animation:
    """A glTF animation.

    Attributes:
        name: the animation's name (``"animation_<i>"`` when the file gives none).
        duration_s: the largest keyframe time over all channels, seconds. Playback time runs
            over [0, duration_s] (glTF animations start at time 0).
        channels: the node channels (morph-target ``weights`` channels are dropped).
    """

    name: str
    duration_s: float
    channels: tuple[AnimationChannel, ...]

    def __iter__(self):  # allows ``name, duration, channels = animation``
        return iter((self.name, self.duration_s, self.channels))


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """The skinned mesh of a glTF file, with its skeleton and animations.

    Geometry (V merged vertices, F triangles, Vt distinct texture coordinates, J joints,
    N nodes of the whole file):

    Attributes:
        vertices: (V, 3) float64 bind-pose positions in the mesh node's local frame (glTF units,
            nominally metres). glTF vertices with bit-identical positions (split by glTF at UV
            seams and normal creases, and across primitives) are merged into one, so the
            topology is closed.
        faces: (F, 3) int32 triangles over ``vertices``, counter-clockwise = front (glTF).
        texcoords: (Vt, 2) float64 distinct UVs, u right / v down / origin top-left, in [0, 1]
            for in-image points; None when the mesh has no texture coordinates.
        texcoord_faces: (F, 3) int32 triangles over ``texcoords`` (separate UV indexing, like
            OBJ ``vt``); None when ``texcoords`` is None.
        texture: (H, W, 3) uint8 RGB base-colour image (row 0 = top = v 0), or None.
        base_color_factor: (4,) float64 linear RGBA factor of the material (1 when absent).
        joints: (V, 4) int32 indices into the skin's joint list (``joint_nodes``).
        weights: (V, 4) float64 skinning weights, each row sums to 1.
        inverse_bind: (J, 4, 4) float64 inverse bind matrices (mesh frame -> joint frame).
        joint_nodes: (J,) int32 node index of each joint.
        joint_names: the J joint node names.
        node_names: the N node names (``"node_<i>"`` when unnamed).
        node_parents: (N,) int32 parent node index, -1 for roots.
        node_translation: (N, 3) float64 rest local translation.
        node_rotation: (N, 4) float64 rest local rotation quaternion (x, y, z, w), unit norm.
        node_scale: (N, 3) float64 rest local scale.
        node_matrix: (N, 4, 4) float64 rest local transform (the node's ``matrix`` if it has
            one, else T @ R @ S); nodes without animation channels use this exactly.
        node_order: (N,) int32 node indices ordered parents-before-children.
        animations: list of :class:`Animation` (each also unpacks as
            ``(name, duration_s, channels)``).
        mesh_index, mesh_name, mesh_node, skin_index: where the mesh came from in the file.
        gltf_to_vertex: (V0,) int32, for each glTF vertex (primitives concatenated in order)
            its merged vertex index.
        source: path of the file read.
        units_note: a reminder of glTF's units and axes.
    """

    vertices: np.ndarray
    faces: np.ndarray
    texcoords: np.ndarray | None
    texcoord_faces: np.ndarray | None
    texture: np.ndarray | None
    base_color_factor: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    inverse_bind: np.ndarray
    joint_nodes: np.ndarray
    joint_names: list[str]
    node_names: list[str]
    node_parents: np.ndarray
    node_translation: np.ndarray
    node_rotation: np.ndarray
    node_scale: np.ndarray
    node_matrix: np.ndarray
    node_order: np.ndarray
    animations: list[Animation]
    mesh_index: int
    mesh_name: str
    mesh_node: int
    skin_index: int
    gltf_to_vertex: np.ndarray
    source: str = ""
    units_note: str = field(default=UNITS_NOTE)

    @property
    def animation_names(self) -> list[str]:
        return [a.name for a in self.animations]

    @property
    def bbox(self) -> np.ndarray:
        """(2, 3) float64 [min, max] corners of the bind-pose vertices."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])


# --------------------------------------------------------------------------------------------
# Quaternions and transforms
# --------------------------------------------------------------------------------------------


def _quat_normalize(q: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w) -> (..., 3, 3) rotation matrices (normalised first)."""
    x, y, z, w = np.moveaxis(_quat_normalize(np.asarray(q, dtype=np.float64)), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> unit quaternion (x, y, z, w)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    return _quat_normalize(np.array(q, dtype=np.float64))


def _compose_trs(t: np.ndarray, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """4x4 matrix T @ R @ S for (3,) translation, (4,) quaternion, (3,) scale (or batched)."""
    t, q, s = (np.asarray(a, dtype=np.float64) for a in (t, q, s))
    batch = np.broadcast_shapes(t.shape[:-1], q.shape[:-1], s.shape[:-1])
    M = np.zeros((*batch, 4, 4))
    M[..., :3, :3] = _quat_to_matrix(q) * s[..., None, :]
    M[..., :3, 3] = t
    M[..., 3, 3] = 1.0
    return M


def _decompose(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best-effort TRS decomposition of an affine 4x4 (exact when there is no shear)."""
    t = M[:3, 3].copy()
    A = M[:3, :3]
    s = np.linalg.norm(A, axis=0)
    if np.linalg.det(A) < 0:
        s[0] = -s[0]
    R = A / np.where(s == 0, 1.0, s)
    # re-orthonormalise (shear or numerical noise)
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] = -U[:, -1]
        R = U @ Vt
    return t, _matrix_to_quat(R), s


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions (x, y, z, w)."""
    q0, q1 = _quat_normalize(q0), _quat_normalize(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:  # nearly parallel: normalised lerp is accurate and stable
        return _quat_normalize(q0 + a * (q1 - q0))
    theta = np.arccos(min(d, 1.0))
    st = np.sin(theta)
    return (np.sin((1.0 - a) * theta) / st) * q0 + (np.sin(a * theta) / st) * q1


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def _find_skinned_node(doc: dict, mesh_index: int | None, path: Path) -> tuple[int, int, int]:
    nodes = doc.get("nodes", [])
    meshes = doc.get("meshes", [])
    candidates = [(i, n["mesh"], n["skin"]) for i, n in enumerate(nodes) if "mesh" in n and "skin" in n]
    if mesh_index is not None:
        if not 0 <= mesh_index < len(meshes):
            raise GltfError(f"{path}: mesh_index {mesh_index} out of range (file has {len(meshes)} meshes)")
        candidates = [c for c in candidates if c[1] == mesh_index]
        if not candidates:
            raise GltfError(f"{path}: mesh {mesh_index} ({meshes[mesh_index].get('name', 'unnamed')!r}) "
                            f"is not used by any node with a skin")
    if not candidates:
        names = [m.get("name", f"mesh_{i}") for i, m in enumerate(meshes)]
        raise GltfNoSkinError(f"{path}: no skinned mesh (no node has both 'mesh' and 'skin'); "
                        f"meshes in the file: {names}")
    if mesh_index is None and len({c[1] for c in candidates}) > 1:
        warnings.warn(f"{path}: several skinned meshes; using mesh {candidates[0][1]} "
                      f"(pass mesh_index to choose)", stacklevel=3)
    return candidates[0]


def _node_tree(doc: dict, path: Path):
    nodes = doc.get("nodes", [])
    N = len(nodes)
    parents = np.full(N, -1, dtype=np.int32)
    for i, n in enumerate(nodes):
        for c in n.get("children", []):
            if not 0 <= c < N:
                raise GltfError(f"{path}: node {i} has out-of-range child {c}")
            if parents[c] != -1:
                raise GltfError(f"{path}: node {c} has two parents ({parents[c]} and {i})")
            parents[c] = i
    # parents-before-children order; detects cycles
    depth = np.full(N, -1, dtype=np.int64)
    for i in range(N):
        chain, j = [], i
        while j != -1 and depth[j] < 0:
            if j in chain:
                raise GltfError(f"{path}: the node hierarchy has a cycle through node {j}")
            chain.append(j)
            j = parents[j]
        base = -1 if j == -1 else depth[j]
        for k, node in enumerate(reversed(chain)):
            depth[node] = base + 1 + k
    order = np.argsort(depth, kind="stable").astype(np.int32)

    T = np.zeros((N, 3))
    Q = np.tile([0.0, 0.0, 0.0, 1.0], (N, 1))
    S = np.ones((N, 3))
    M = np.tile(np.eye(4), (N, 1, 1))
    names = []
    for i, n in enumerate(nodes):
        names.append(str(n.get("name", f"node_{i}")))
        if "matrix" in n:
            m = np.asarray(n["matrix"], dtype=np.float64)
            if m.size != 16:
                raise GltfError(f"{path}: node {i} matrix has {m.size} numbers, expected 16")
            M[i] = m.reshape(4, 4).T  # column-major
            T[i], Q[i], S[i] = _decompose(M[i])
        else:
            T[i] = n.get("translation", [0.0, 0.0, 0.0])
            Q[i] = _quat_normalize(np.asarray(n.get("rotation", [0.0, 0.0, 0.0, 1.0]), dtype=np.float64))
            S[i] = n.get("scale", [1.0, 1.0, 1.0])
            M[i] = _compose_trs(T[i], Q[i], S[i])
    return names, parents, order, T, Q, S, M


def _load_animations(doc: dict, reader: GltfReader, path: Path) -> list[Animation]:
    out = []
    N = len(doc.get("nodes", []))
    for ai, anim in enumerate(doc.get("animations", [])):
        name = str(anim.get("name", f"animation_{ai}"))
        samplers = anim.get("samplers", [])
        channels = []
        skipped = 0
        duration = 0.0
        for ci, ch in enumerate(anim.get("channels", [])):
            target = ch.get("target", {})
            node, prop = target.get("node"), target.get("path")
            if prop == "weights" or node is None:
                skipped += 1
                continue
            if prop not in ("translation", "rotation", "scale"):
                raise GltfError(f"{path}: animation {name!r} channel {ci} has unknown path {prop!r}")
            if not 0 <= node < N:
                raise GltfError(f"{path}: animation {name!r} channel {ci} targets missing node {node}")
            si = ch.get("sampler")
            if not isinstance(si, int) or not 0 <= si < len(samplers):
                raise GltfError(f"{path}: animation {name!r} channel {ci} has bad sampler {si!r}")
            smp = samplers[si]
            interp = smp.get("interpolation", "LINEAR")
            if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
                raise GltfError(f"{path}: animation {name!r} sampler {si} has unknown "
                                f"interpolation {interp!r}")
            times = np.asarray(reader.accessor(smp["input"]), dtype=np.float64).reshape(-1)
            values = np.asarray(reader.accessor(smp["output"]), dtype=np.float64)
            C = 4 if prop == "rotation" else 3
            K = times.size
            if K == 0:
                skipped += 1
                continue
            if np.any(np.diff(times) <= 0):
                raise GltfError(f"{path}: animation {name!r} sampler {si}: keyframe times are not "
                                f"strictly increasing")
            values = values.reshape(values.shape[0], -1)
            if values.shape[1] != C:
                raise GltfError(f"{path}: animation {name!r} sampler {si}: {prop} output has "
                                f"{values.shape[1]} components, expected {C}")
            if interp == "CUBICSPLINE":
                if values.shape[0] != 3 * K:
                    raise GltfError(f"{path}: animation {name!r} sampler {si}: CUBICSPLINE needs "
                                    f"3 x {K} outputs, got {values.shape[0]}")
                values = values.reshape(K, 3, C)
            elif values.shape[0] != K:
                raise GltfError(f"{path}: animation {name!r} sampler {si}: {K} times but "
                                f"{values.shape[0]} values")
            values = np.ascontiguousarray(values)
            times.setflags(write=False)
            values.setflags(write=False)
            channels.append(AnimationChannel(int(node), prop, interp, times, values))
            duration = max(duration, float(times[-1]))
        if skipped:
            warnings.warn(f"{path}: animation {name!r}: ignored {skipped} morph-target (weights) "
                          f"or empty channel(s)", stacklevel=3)
        out.append(Animation(name, duration, tuple(channels)))
    return out


def _first_texture_info(material: dict) -> dict | None:
    info = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
    if info is None:
        sg = material.get("extensions", {}).get("KHR_materials_pbrSpecularGlossiness", {})
        info = sg.get("diffuseTexture")
    return info


def _unique_rows_first_order(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of ``a`` in order of first occurrence: (unique_index_of_first, inverse)."""
    if a.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    a = a + 0.0  # folds -0.0 into +0.0 so the byte view treats them as equal
    view = np.ascontiguousarray(a).view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()
    _, first, inv = np.unique(view, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # unique ids sorted by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order], rank[inv.ravel()]


def _canonical_skin(joints: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Influences sorted by joint index, zero-weight slots set to joint -1 (for comparisons)."""
    j = np.where(weights > 0, joints, -1)
    o = np.argsort(j, axis=1, kind="stable")
    return np.take_along_axis(j, o, 1), np.take_along_axis(weights, o, 1)


def _open_gltf(path: Path, on_skin_mismatch: str) -> tuple[dict, GltfReader]:
    """The checked glTF document of ``path`` and a reader of its buffers."""
    if not path.is_file():
        raise FileNotFoundError(f"glTF file not found: {path}")
    if on_skin_mismatch not in ("warn", "raise"):
        raise ValueError(f"on_skin_mismatch must be 'warn' or 'raise', got {on_skin_mismatch!r}")
    doc, bin_chunk = read_document(path)
    version = str(doc.get("asset", {}).get("version", "2.0"))
    if not version.startswith("2"):
        raise GltfError(f"{path}: glTF version {version}; only glTF 2.x is supported")
    for ext in doc.get("extensionsRequired", []):
        if ext in UNSUPPORTED_EXTENSIONS:
            raise GltfError(f"{path}: requires {ext} ({UNSUPPORTED_EXTENSIONS[ext]}), which this "
                            f"reader does not decode; re-export the asset without it")
    buffers = load_buffers(doc, bin_chunk, path)
    reader = GltfReader(doc, buffers, path)
    return doc, reader


# The helpers below warn with stacklevel 3: the warning names the caller of load_skinned_gltf.

def _base_color(mesh: dict, mesh_name: str, reader: GltfReader, path: Path, load_texture: bool):
    """(texcoord set, texture (H, W, 3|4) uint8 or None, base-colour factor (4,) float64) of the
    first primitive of ``mesh`` whose material has a base-colour texture."""
    tex_coord_set, texture, color_factor, tex_source = 0, None, np.ones(4), None
    first_factor = None
    for p in mesh.get("primitives", []):
        if "material" not in p:
            continue
        mat = reader.get("materials", p["material"])
        info = _first_texture_info(mat)
        factor = np.asarray(mat.get("pbrMetallicRoughness", {}).get("baseColorFactor",
                            [1.0, 1.0, 1.0, 1.0]), dtype=np.float64)
        if first_factor is None or info is not None:
            color_factor = first_factor = factor
        if info is not None:
            tex_coord_set = int(info.get("texCoord", 0))
            if "KHR_texture_transform" in info.get("extensions", {}):
                warnings.warn(f"{path}: KHR_texture_transform on the base-colour texture is "
                              f"ignored", stacklevel=3)
            tex = reader.get("textures", info["index"])
            tex_source = tex.get("source")
            if tex_source is None:
                warnings.warn(f"{path}: base-colour texture {info['index']} has no PNG/JPEG "
                              f"source (extension image?); texture is None", stacklevel=3)
            break
    if load_texture and tex_source is not None:
        texture = reader.image(tex_source)
    materials = {p.get("material") for p in mesh.get("primitives", [])}
    if len(materials) > 1:
        warnings.warn(f"{path}: mesh {mesh_name!r} has primitives with different materials "
                      f"{sorted(m for m in materials if m is not None)}; only the first textured "
                      f"one's base colour is used", stacklevel=3)
    return tex_coord_set, texture, color_factor


def _read_primitives(mesh: dict, mesh_i: int, mesh_name: str, reader: GltfReader, path: Path,
                    tex_coord_set: int):
    """Every TRIANGLES primitive of ``mesh``, concatenated: (positions (n, 3) float64, triangles
    (m, 3) int64, joints (n, 4) int64, weights (n, 4) float64 >= 0, per-primitive texcoords, whether
    every primitive has them)."""
    pos_l, uv_l, jnt_l, wgt_l, tri_l = [], [], [], [], []
    offset = 0
    have_uv = True
    for pi, prim in enumerate(mesh.get("primitives", [])):
        where = f"{path}: mesh {mesh_i} ({mesh_name!r}) primitive {pi}"
        mode = int(prim.get("mode", 4))
        if mode != 4:
            raise GltfError(f"{where} has mode {mode} ({MODE_NAMES.get(mode, 'unknown')}); only "
                            f"TRIANGLES (4) is supported")
        attrs = prim.get("attributes", {})
        if "POSITION" not in attrs:
            raise GltfError(f"{where} has no POSITION attribute")
        if prim.get("targets"):
            warnings.warn(f"{where}: morph targets are ignored", stacklevel=3)
        pos = np.asarray(reader.accessor(attrs["POSITION"]), dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise GltfError(f"{where}: POSITION must be VEC3")
        if not np.isfinite(pos).all():
            raise GltfError(f"{where}: POSITION {int(np.flatnonzero(~np.isfinite(pos).all(1))[0])} is not finite")
        n = pos.shape[0]
        if "indices" in prim:
            idx = np.asarray(reader.accessor(prim["indices"]), dtype=np.int64).reshape(-1)
        else:
            idx = np.arange(n, dtype=np.int64)
        if idx.size % 3:
            raise GltfError(f"{where}: {idx.size} indices is not a multiple of 3")
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise GltfError(f"{where}: index out of range [0, {n})")
        uv_key = f"TEXCOORD_{tex_coord_set}"
        if uv_key in attrs and have_uv:
            uv = np.asarray(reader.accessor(attrs[uv_key]), dtype=np.float64)
            if uv.shape != (n, 2):
                raise GltfError(f"{where}: {uv_key} has shape {uv.shape}, expected ({n}, 2)")
            uv_l.append(uv)
        else:
            have_uv = False
        sets = sorted(int(k.split("_")[1]) for k in attrs if k.startswith("JOINTS_"))
        if not sets or any(f"WEIGHTS_{s}" not in attrs for s in sets):
            raise GltfError(f"{where} lacks JOINTS_n/WEIGHTS_n pairs but its node has a skin")
        J = np.concatenate([np.asarray(reader.accessor(attrs[f"JOINTS_{s}"])).reshape(n, -1)
                            for s in sets], axis=1).astype(np.int64)
        W = np.concatenate([np.asarray(reader.accessor(attrs[f"WEIGHTS_{s}"]), dtype=np.float64)
                            .reshape(n, -1) for s in sets], axis=1)
        if J.shape != W.shape:
            raise GltfError(f"{where}: JOINTS and WEIGHTS have different shapes {J.shape}, {W.shape}")
        if J.shape[1] > 4:
            o = np.argsort(-W, axis=1, kind="stable")[:, :4]
            dropped = np.take_along_axis(W, np.argsort(-W, axis=1, kind="stable")[:, 4:], 1)
            if np.any(dropped > 0):
                warnings.warn(f"{where}: more than 4 influences per vertex; keeping the 4 largest "
                              f"(max dropped weight {dropped.max():.3g})", stacklevel=3)
            J, W = np.take_along_axis(J, o, 1), np.take_along_axis(W, o, 1)
        pos_l.append(pos)
        jnt_l.append(J)
        wgt_l.append(W)
        tri_l.append(idx.reshape(-1, 3) + offset)
        offset += n
    if not pos_l:
        raise GltfError(f"{path}: mesh {mesh_i} ({mesh_name!r}) has no primitives")
    pos = np.concatenate(pos_l)
    tri = np.concatenate(tri_l)
    J = np.concatenate(jnt_l)
    W = np.maximum(np.concatenate(wgt_l), 0.0)

    return pos, tri, J, W, uv_l, have_uv


def _read_skin(skin: dict, skin_i: int, reader: GltfReader, path: Path, J: np.ndarray, W: np.ndarray):
    """The skin's joint nodes (J,) int32 and inverse bind matrices (J, 4, 4) float64, and the
    vertices' joints and weights checked against it (weights renormalised to sum 1)."""
    joint_nodes = np.asarray(skin.get("joints", []), dtype=np.int32)
    n_joints = joint_nodes.size
    if n_joints == 0:
        raise GltfError(f"{path}: skin {skin_i} has no joints")
    if "inverseBindMatrices" in skin:
        ibm = np.asarray(reader.accessor(skin["inverseBindMatrices"]), dtype=np.float64)
        if ibm.shape != (n_joints, 4, 4):
            raise GltfError(f"{path}: skin {skin_i}: inverseBindMatrices has shape {ibm.shape}, "
                            f"expected ({n_joints}, 4, 4)")
        ibm = ibm.copy()
    else:
        ibm = np.tile(np.eye(4), (n_joints, 1, 1))
    W = np.where((J >= 0) & (J < n_joints), W, 0.0)
    bad = (J < 0) | (J >= n_joints)
    if np.any(bad & (W > 0)):
        raise GltfError(f"{path}: joint index out of range [0, {n_joints}) with non-zero weight")
    J = np.where(bad, 0, J)
    wsum = W.sum(axis=1)
    zero = wsum <= 0
    if np.any(zero):
        warnings.warn(f"{path}: {int(zero.sum())} vertices have all-zero skin weights; bound "
                      f"rigidly to joint 0", stacklevel=3)
        W[zero] = [1.0, 0.0, 0.0, 0.0]
        J[zero] = 0
        wsum = W.sum(axis=1)
    W = W / wsum[:, None]
    return joint_nodes, ibm, J, W


def _merge_vertices(path: Path, mesh_name: str, pos, tri, J, W, uv_l, have_uv, tex_coord_set: int,
                   on_skin_mismatch: str):
    """Vertices merged by bit-identical position and texcoords deduplicated by value:
    (vertices, faces, joints, weights, texcoords, texcoord_faces, glTF vertex -> vertex)."""
    first, inv = _unique_rows_first_order(pos)
    vertices = pos[first].copy()
    faces = inv[tri].astype(np.int32)
    cj, cw = _canonical_skin(J, W)
    rep = first[inv]
    mismatch = np.any(cj != cj[rep], axis=1) | np.any(np.abs(cw - cw[rep]) > 1e-6, axis=1)
    if np.any(mismatch):
        msg = (f"{path}: {int(mismatch.sum())} glTF vertices share a position with another vertex "
               f"but have different skinning; merged vertices keep the first one's joints/weights")
        if on_skin_mismatch == "raise":
            raise GltfError(msg)
        warnings.warn(msg, stacklevel=3)
    joints = J[first].astype(np.int32)
    weights = W[first].copy()

    if have_uv and uv_l:
        uv = np.concatenate(uv_l)
        ufirst, uinv = _unique_rows_first_order(uv)
        texcoords = uv[ufirst].copy()
        texcoord_faces = uinv[tri].astype(np.int32)
    else:
        warnings.warn(f"{path}: mesh {mesh_name!r} has no TEXCOORD_{tex_coord_set} on every "
                      f"primitive; texcoords are None", stacklevel=3)
        texcoords = texcoord_faces = None

    degenerate = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    if np.any(degenerate):
        warnings.warn(f"{path}: dropped {int(degenerate.sum())} triangles that are degenerate after "
                      f"merging vertices", stacklevel=3)
        faces = faces[~degenerate]
        if texcoord_faces is not None:
            texcoord_faces = texcoord_faces[~degenerate]
    return vertices, faces, joints, weights, texcoords, texcoord_faces, inv


def load_skinned_gltf(path, mesh_index: int | None = None, *, load_texture: bool = True,
                      on_skin_mismatch: str = "warn") -> SkinnedMesh:
    """Read the skinned mesh, its skeleton, animations and base-colour texture from a glTF file.

    Args:
        path: a ``.gltf`` (JSON; buffers as files next to it or ``data:`` URIs) or ``.glb`` file.
        mesh_index: index into the file's ``meshes`` of the skinned mesh to read; None = the
            mesh of the first node that has both a mesh and a skin.
        load_texture: decode the base-colour image (PNG/JPEG via Pillow); False gives None.
        on_skin_mismatch: what to do when glTF vertices merged by identical position carry
            different joints/weights: ``"warn"`` (keep the first vertex's skinning) or ``"raise"``.

    All primitives of the mesh are merged (each must be TRIANGLES). Vertices are merged by
    bit-identical position; texture coordinates are deduplicated by identical value and indexed
    separately (``texcoord_faces``). Up to 4 influences are kept per vertex (if JOINTS_1/
    WEIGHTS_1 exist, the 4 largest weights are kept, with a warning); weights are renormalised.
    Morph targets are ignored (warning).

    Raises:
        FileNotFoundError: ``path``, or a buffer/image file it refers to, is missing (named).
        GltfError (a ValueError): malformed file, no skinned mesh, a non-triangle primitive,
            a compression extension that is not supported, ...
    """
    path = Path(path)
    doc, reader = _open_gltf(path, on_skin_mismatch)

    node_i, mesh_i, skin_i = _find_skinned_node(doc, mesh_index, path)
    mesh = reader.get("meshes", mesh_i)
    mesh_name = str(mesh.get("name", f"mesh_{mesh_i}"))
    skin = reader.get("skins", skin_i)

    tex_coord_set, texture, color_factor = _base_color(mesh, mesh_name, reader, path, load_texture)
    pos, tri, J, W, uv_l, have_uv = _read_primitives(mesh, mesh_i, mesh_name, reader, path, tex_coord_set)
    joint_nodes, ibm, J, W = _read_skin(skin, skin_i, reader, path, J, W)
    vertices, faces, joints, weights, texcoords, texcoord_faces, inv = _merge_vertices(
        path, mesh_name, pos, tri, J, W, uv_l, have_uv, tex_coord_set, on_skin_mismatch)

    names, parents, order, T, Q, S, M = _node_tree(doc, path)
    if np.any((joint_nodes < 0) | (joint_nodes >= len(names))):
        raise GltfError(f"{path}: skin {skin_i} refers to a missing node")
    animations = _load_animations(doc, reader, path)

    for a in (vertices, faces, joints, weights, ibm, joint_nodes, parents, order, T, Q, S, M):
        a.setflags(write=False)
    return SkinnedMesh(
        vertices=vertices, faces=np.ascontiguousarray(faces),
        texcoords=texcoords,
        texcoord_faces=None if texcoord_faces is None else np.ascontiguousarray(texcoord_faces),
        texture=texture, base_color_factor=color_factor,
        joints=joints, weights=weights, inverse_bind=ibm, joint_nodes=joint_nodes,
        joint_names=[names[j] for j in joint_nodes], node_names=names, node_parents=parents,
        node_translation=T, node_rotation=Q, node_scale=S, node_matrix=M, node_order=order,
        animations=animations, mesh_index=int(mesh_i), mesh_name=mesh_name, mesh_node=int(node_i),
        skin_index=int(skin_i), gltf_to_vertex=inv.astype(np.int32), source=str(path),
    )


# --------------------------------------------------------------------------------------------
# Animation sampling and skinning
# --------------------------------------------------------------------------------------------


def animation_index(mesh: SkinnedMesh, animation) -> int:
    """Index of ``animation`` (an int index or a name) in ``mesh.animations``."""
    names = mesh.animation_names
    if isinstance(animation, (int, np.integer)) and not isinstance(animation, bool):
        if not 0 <= int(animation) < len(names):
            raise GltfError(f"animation index {animation} out of range; {len(names)} animations: {names}")
        return int(animation)
    if isinstance(animation, str):
        if animation in names:
            return names.index(animation)
        raise GltfError(f"unknown animation {animation!r}; available animations: {names}")
    raise TypeError(f"animation must be an int index or a name, got {type(animation).__name__}")


def sample_channel(channel: AnimationChannel, time_s: float) -> np.ndarray:
    """Value of a channel at ``time_s`` seconds: (3,) or (4,) float64 (rotations normalised).

    Times before the first / after the last keyframe are clamped to them.
    """
    times, vals, interp = channel.times, channel.values, channel.interpolation
    K = times.size
    cubic = interp == "CUBICSPLINE"

    def value(k):
        return vals[k, 1] if cubic else vals[k]

    if K == 1 or time_s <= times[0]:
        out = value(0)
    elif time_s >= times[-1]:
        out = value(K - 1)
    else:
        k = int(np.searchsorted(times, time_s, side="right")) - 1
        t0, t1 = times[k], times[k + 1]
        td = t1 - t0
        s = (time_s - t0) / td
        if interp == "STEP":
            out = vals[k]
        elif interp == "LINEAR":
            if channel.path == "rotation":
                out = _slerp(vals[k], vals[k + 1], s)
            else:
                out = (1.0 - s) * vals[k] + s * vals[k + 1]
        else:  # CUBICSPLINE (glTF spec, Appendix C): Hermite with tangents scaled by td
            s2, s3 = s * s, s * s * s
            v0, b0 = vals[k, 1], vals[k, 2]      # value and out-tangent at k
            v1, a1 = vals[k + 1, 1], vals[k + 1, 0]  # value and in-tangent at k+1
            out = ((2 * s3 - 3 * s2 + 1) * v0 + td * (s3 - 2 * s2 + s) * b0
                   + (-2 * s3 + 3 * s2) * v1 + td * (s3 - s2) * a1)
    out = np.array(out, dtype=np.float64)
    if channel.path == "rotation":
        out = _quat_normalize(out)
    return out


def _playback_time(anim: Animation, time_s: float, loop: bool) -> float:
    t = float(time_s)
    if not np.isfinite(t):
        raise ValueError(f"time must be finite, got {time_s}")
    d = anim.duration_s
    if d <= 0:
        return 0.0
    if loop:
        return t % d  # t = k * duration maps to 0 (the same pose for a cyclic animation)
    return min(max(t, 0.0), d)


def node_global_transforms(mesh: SkinnedMesh, animation=None, time_s: float = 0.0, *,
                           loop: bool = False) -> np.ndarray:
    """(N, 4, 4) float64 global (scene-frame) transforms of every node at ``time_s`` seconds.

    ``animation`` is an index, a name, or None for the rest pose (the nodes' own TRS/matrix).
    Unanimated properties keep their rest values. Time is clamped to [0, duration], or
    wrapped modulo the duration when ``loop`` is True.
    """
    local = mesh.node_matrix.copy()
    if animation is not None:
        anim = mesh.animations[animation_index(mesh, animation)]
        t = _playback_time(anim, time_s, loop)
        trs: dict[int, list[np.ndarray]] = {}
        for ch in anim.channels:
            if ch.node not in trs:
                trs[ch.node] = [mesh.node_translation[ch.node].copy(),
                                mesh.node_rotation[ch.node].copy(), mesh.node_scale[ch.node].copy()]
            slot = {"translation": 0, "rotation": 1, "scale": 2}[ch.path]
            trs[ch.node][slot] = sample_channel(ch, t)
        for node, (tt, qq, ss) in trs.items():
            local[node] = _compose_trs(tt, qq, ss)
    glob = np.empty_like(local)
    parents = mesh.node_parents
    for n in mesh.node_order:
        p = parents[n]
        glob[n] = local[n] if p < 0 else glob[p] @ local[n]
    return glob


def joint_matrices(mesh: SkinnedMesh, animation=None, time_s: float = 0.0, *,
                   loop: bool = False) -> np.ndarray:
    """(J, 4, 4) float64 skinning matrices globalTransform(joint) @ inverseBind(joint).

    See :func:`node_global_transforms` for the arguments. Per the glTF spec the skinned mesh
    node's own transform does not enter.
    """
    glob = node_global_transforms(mesh, animation, time_s, loop=loop)
    return glob[mesh.joint_nodes] @ mesh.inverse_bind


def skin_vertices(mesh: SkinnedMesh, joint_mats: np.ndarray) -> np.ndarray:
    """Linear blend skinning of the bind-pose vertices with (J, 4, 4) joint matrices.

    Returns (V, 3) float64: ``sum_k weights[:, k] * joint_mats[joints[:, k]] @ [v, 1]``.
    With joint_mats = identity (every joint at its bind pose) this returns ``mesh.vertices``.
    """
    joint_mats = np.asarray(joint_mats, dtype=np.float64)
    if joint_mats.shape != (mesh.joint_nodes.size, 4, 4):
        raise ValueError(f"joint_mats must have shape ({mesh.joint_nodes.size}, 4, 4), "
                         f"got {joint_mats.shape}")
    A = joint_mats[:, :3, :]  # (J, 3, 4) affine part
    blended = np.einsum("vk,vkij->vij", mesh.weights, A[mesh.joints])  # (V, 3, 4)
    v = mesh.vertices
    return np.einsum("vij,vj->vi", blended[:, :, :3], v) + blended[:, :, 3]


def pose_vertices(mesh: SkinnedMesh, animation, time_s: float, *, loop: bool = False) -> np.ndarray:
    """Skinned vertex positions at ``time_s`` seconds of ``animation``.

    Args:
        mesh: from :func:`load_skinned_gltf`.
        animation: index or name into ``mesh.animations``; None = the rest pose of the nodes.
        time_s: seconds; clamped to [0, duration] (or wrapped modulo duration if ``loop``).

    Returns:
        (V, 3) float64 positions in the glTF scene frame (same units as ``mesh.vertices``).
        The skinned mesh node's own transform is ignored, as the glTF 2.0 spec requires; when
        the joints are at their bind pose the result equals ``mesh.vertices``.
    """
    return skin_vertices(mesh, joint_matrices(mesh, animation, time_s, loop=loop))


def pose_sequence(mesh: SkinnedMesh, animation, times_s, *, loop: bool = False) -> np.ndarray:
    """(T, V, 3) float64 skinned vertices at each of ``times_s`` (seconds); see :func:`pose_vertices`."""
    times = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
    if times.ndim != 1:
        raise ValueError(f"times_s must be a 1-D sequence, got shape {times.shape}")
    out = np.empty((times.size, mesh.vertices.shape[0], 3))
    for i, t in enumerate(times):
        out[i] = pose_vertices(mesh, animation, float(t), loop=loop)
    return out
