"""Mesh files: OBJ (keeping texture coordinates indexed per corner), OFF, PLY, glTF/GLB.

Returns plain arrays in stex conventions (texcoords v downward: OBJ's upward v is flipped here,
at import, and nowhere else).
"""

from __future__ import annotations

import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stex.synth.gltf import GltfNoSkinError, load_skinned_gltf


@dataclass
class Mesh:
    """A triangle mesh.

    vertices (V, 3) float64 m; faces (F, 3) int32; texcoords (Vt, 2) float64 or None;
    texcoord_faces (F, 3) int32 or None (per-corner index into texcoords).
    """

    vertices: np.ndarray
    faces: np.ndarray
    texcoords: np.ndarray | None = None
    texcoord_faces: np.ndarray | None = None


def _read_obj(path: Path) -> Mesh:
    verts, tcs, faces, tfaces = [], [], [], []
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if parts[0] == "v":
                    verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
                elif parts[0] == "vt":
                    tcs.append([float(parts[1]), float(parts[2]) if len(parts) > 2 else 0.0])
                elif parts[0] == "f":
                    corners = [p.split("/") for p in parts[1:]]
                    # negative indices count back from the last vertex read so far (OBJ spec)
                    vi = [_obj_index(int(c[0]), len(verts)) for c in corners]
                    ti = [_obj_index(int(c[1]), len(tcs)) if len(c) > 1 and c[1] else 0 for c in corners]
                    for k in range(1, len(vi) - 1):  # fan-triangulate polygons
                        faces.append([vi[0], vi[k], vi[k + 1]])
                        tfaces.append([ti[0], ti[k], ti[k + 1]])
            except (ValueError, IndexError) as exc:
                raise ValueError(f"{path}:{lineno}: cannot parse OBJ line {line.strip()!r}") from exc
    if not verts or not faces:
        raise ValueError(f"{path}: OBJ has no vertices or no faces")
    V = np.asarray(verts, np.float64)
    F = np.asarray(faces, np.int64)
    F = F - 1  # OBJ indices are 1-based
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"{path}: face refers to a vertex outside 1..{len(V)}")
    tc = tf = None
    TF = np.asarray(tfaces, np.int64)
    if tcs and not (TF != 0).all():
        warnings.warn(f"{path}: {int((TF == 0).any(1).sum())} of {len(TF)} faces have no texture coordinates "
                      f"(f v/vt); the mesh's texture coordinates are left out", stacklevel=2)
    if tcs and (TF != 0).all():
        tc = np.asarray(tcs, np.float64)
        tc[:, 1] = 1.0 - tc[:, 1]  # OBJ v points up; stex v points down
        tf = (TF - 1).astype(np.int32)
        if tf.min() < 0 or tf.max() >= len(tc):
            raise ValueError(f"{path}: face refers to a texcoord outside 1..{len(tc)}")
    return Mesh(V, F.astype(np.int32), tc, tf)


def _obj_index(i: int, n_read: int) -> int:
    """1-based OBJ index; a negative one counts back from the ``n_read`` elements read so far
    (-1 = the last). 0, or one before the first element, stays invalid (refused later)."""
    return i + n_read + 1 if i < 0 else i


def _read_static_gltf(path: Path) -> Mesh:
    """A glTF/GLB without a skin, read with trimesh (node transforms applied, meshes joined);
    TEXCOORD_0 kept per vertex (glTF's v already points down, as stex's)."""
    import trimesh  # slow to import; OBJ files are read without it

    try:
        tm = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:
        raise ValueError(f"{path}: cannot read glTF ({exc})") from exc
    if len(tm.faces) == 0:
        raise ValueError(f"{path}: glTF has no triangles")
    F = np.asarray(tm.faces, np.int32)
    uv = getattr(tm.visual, "uv", None)
    if uv is None or len(uv) != len(tm.vertices):
        return Mesh(np.asarray(tm.vertices, np.float64), F)
    tc = np.asarray(uv, np.float64).copy()
    tc[:, 1] = 1.0 - tc[:, 1]  # trimesh turns glTF's v into OBJ's upward v; back to glTF's
    return Mesh(np.asarray(tm.vertices, np.float64), F, tc, F.copy())


def load_mesh(path: str | Path) -> Mesh:
    """Load a triangle mesh from OBJ, OFF, PLY, STL, glTF or GLB, keeping vertex order. A glTF
    with a skin is read in its bind pose (:func:`stex.synth.gltf.load_skinned_gltf`), one without
    as a plain mesh."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".obj":
        mesh = _read_obj(path)
    elif suffix in (".gltf", ".glb"):
        try:
            sk = load_skinned_gltf(path)
            mesh = Mesh(np.asarray(sk.vertices, np.float64), np.asarray(sk.faces, np.int32),
                        np.asarray(sk.texcoords, np.float64), np.asarray(sk.texcoord_faces, np.int32))
        except GltfNoSkinError:
            mesh = _read_static_gltf(path)
    else:
        import trimesh  # slow to import; OBJ files are read without it
        try:
            tm = trimesh.load(path, process=False, maintain_order=True, force="mesh")
        except Exception as exc:
            raise ValueError(f"{path}: cannot read mesh ({exc})") from exc
        if len(tm.faces) == 0:
            raise ValueError(f"{path}: mesh has no faces")
        mesh = Mesh(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int32))
    F = mesh.faces
    if len(F) and (F.min() < 0 or F.max() >= len(mesh.vertices)):
        bad = int(np.flatnonzero((F < 0).any(1) | (F >= len(mesh.vertices)).any(1))[0])
        raise ValueError(f"{path}: face {bad} refers to vertex {F[bad].tolist()}, outside 0..{len(mesh.vertices) - 1}")
    for name, tag, values in (("vertex", "v", mesh.vertices), ("texture coordinate", "vt", mesh.texcoords)):
        if values is not None and not np.isfinite(values).all():
            # refused here, naming the file (and the OBJ line), not later by the store, naming neither
            bad = int(np.flatnonzero(~np.isfinite(values).all(1))[0])
            if suffix == ".obj":  # the line as written (the stored v of a vt is flipped)
                lineno, text = _obj_line(path, tag, bad)
                raise ValueError(f"{path}:{lineno}: {name} {bad} is not finite: {text!r}")
            raise ValueError(f"{path}: {name} {bad} is not finite ({np.asarray(values[bad]).tolist()})")
    return mesh


def _obj_line(path: Path, tag: str, index: int) -> tuple[int, str]:
    """Number (from 1) and text of the ``index``-th (from 0) ``tag`` line ('v', 'vt') of an OBJ."""
    with open(path, "r", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split(None, 1)
            if parts and parts[0] == tag:
                if index == 0:
                    return lineno, line.strip()
                index -= 1
    raise ValueError(f"{path}: fewer {tag} lines than were read (the file changed?)")


def check_same_topology(reference_faces: np.ndarray, n_vertices: int, mesh: Mesh, where: str) -> None:
    """Raise ValueError naming ``where`` unless ``mesh`` has ``n_vertices`` vertices and the
    reference's triangles, in any order (per-frame meshes must share the template's topology).

    A per-frame mesh only supplies vertex positions, so the order in which its reader lists the
    triangles does not matter: OBJ fans each polygon in place, trimesh (OFF, PLY) lists every
    polygon's first triangle before the second ones. A triangle counts as the same with its
    corners rotated (the same winding), not reversed. The error names the first face of ``mesh``
    that the reference lacks (or has fewer times)."""
    faces, ref = np.asarray(mesh.faces), np.asarray(reference_faces)
    counts = f"{len(faces)} faces / {len(mesh.vertices)} vertices vs {len(ref)} faces / {n_vertices} vertices"
    if len(mesh.vertices) != n_vertices or faces.shape != ref.shape:
        raise ValueError(f"{where}: mesh topology differs from the template ({counts})")
    if np.array_equal(faces, ref):
        return
    a, b = _rotated_to_smallest(faces), _rotated_to_smallest(ref)
    if np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])]):
        return  # the same triangles, listed in another order
    left = Counter(map(tuple, b.tolist()))
    for i, tri in enumerate(map(tuple, a.tolist())):
        if not left[tri]:
            break
        left[tri] -= 1
    if tri in left:  # used up
        why = "occurs more often than among the template's triangles"
    elif _rotated_to_smallest(faces[i:i + 1, ::-1])[0].tolist() in b.tolist():
        why = "is among the template's triangles with the other winding (corners reversed)"
    else:
        why = "is not among the template's triangles"
    raise ValueError(
        f"{where}: mesh topology differs from the template ({counts}): its face {i} {faces[i].tolist()} {why}; the "
        f"template's face {i} is {ref[i].tolist()} (vertex indices from 0; the faces may be in another order)")


def _rotated_to_smallest(F: np.ndarray) -> np.ndarray:
    """(F, 3) triangles with their corners rotated (winding kept) to the lexicographically smallest
    of their three rotations: the smallest index first, and of two such corners (a degenerate
    triangle such as [1, 3, 1]) the one followed by the smaller index, so that every rotation of a
    triangle gives the same row."""
    F = np.asarray(F)
    best = F
    for k in (1, 2):
        c = np.roll(F, -k, axis=1)
        less = (c[:, 0] < best[:, 0]) | ((c[:, 0] == best[:, 0]) & ((c[:, 1] < best[:, 1])
                                                                   | ((c[:, 1] == best[:, 1]) & (c[:, 2] < best[:, 2]))))
        best = np.where(less[:, None], c, best)
    return best


def write_obj(path: str | Path, mesh: Mesh, mtl: str | None = None) -> None:
    """Write an OBJ (texcoords flipped back to OBJ's upward v)."""
    with open(path, "w") as fh:
        if mtl:
            fh.write(f"mtllib {mtl}\nusemtl material0\n")
        np.savetxt(fh, mesh.vertices, fmt="v %.6f %.6f %.6f")
        if mesh.texcoords is not None:
            tc = mesh.texcoords.copy()
            tc[:, 1] = 1.0 - tc[:, 1]
            np.savetxt(fh, tc, fmt="vt %.6f %.6f")
            f = np.stack([mesh.faces + 1, mesh.texcoord_faces + 1], -1).reshape(-1, 6)
            np.savetxt(fh, f, fmt="f %d/%d %d/%d %d/%d")
        else:
            np.savetxt(fh, mesh.faces + 1, fmt="f %d %d %d")
