"""The viewer's data as arrays: pure functions, no files (the folder is written by
:mod:`stex.viewer.write`).

The page draws in three.js's camera convention (x right, y up, looking down -z): positions are
the tracked vertices moved into the colour camera's frame and then to ``(x, -y, -z)``
(:func:`stex.export.opencv_to_viewer`), so the input colour camera is three.js's default camera
at the origin and the page only adds the colour camera's projection.
"""

from __future__ import annotations

import numpy as np

from stex.camera import transform_points
from stex.export import opencv_to_viewer, split_seams

__all__ = ["viewer_positions", "quantize_positions", "corner_buffers"]

#: levels of the uint16 position code
_LEVELS = 65535


def viewer_positions(vertices, depth_to_color) -> np.ndarray:
    """(V, 3) depth-camera vertices (m) -> (V, 3) float64 positions in the page's frame: the
    colour camera's coordinates as ``(x, -y, -z)``, metres.

    Args:
        vertices: (V, 3) float, OpenCV depth-camera coordinates, metres.
        depth_to_color: (4, 4) rigid transform, depth camera -> colour camera.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise ValueError(f"vertices must be finite with shape (V, 3), got shape {v.shape}")
    T = np.asarray(depth_to_color, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"depth_to_color must be a finite (4, 4) transform, got shape {T.shape}")
    return opencv_to_viewer(transform_points(T, v))


def quantize_positions(positions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Code (T, V, 3) positions as uint16 per axis over their bounding box: half the bytes of
    float32, decoded on the page as ``offset + code * step``.

    Args:
        positions: (T, V, 3) finite float positions, metres.

    Returns:
        code: (T, V, 3) uint16. offset: (3,) float64, the box's low corner (m). step: (3,)
        float64, metres per code level (box extent / 65535; 1 on an axis without extent). The
        decoded positions are within ``step / 2`` of ``positions`` on each axis.
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] == 0 or p.shape[1] == 0:
        raise ValueError(f"positions must have shape (T, V, 3) with T, V > 0, got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("positions must be finite")
    lo = p.min(axis=(0, 1))
    extent = p.max(axis=(0, 1)) - lo
    step = np.where(extent > 0, extent / _LEVELS, 1.0)
    code = np.clip(np.rint((p - lo) / step), 0, _LEVELS).astype(np.uint16)
    return code, lo, step


def corner_buffers(faces, texcoords, texcoord_faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The template's mesh in the layout a GPU draws: one vertex per distinct (position,
    texcoord) corner pair (:func:`stex.export.split_seams`).

    Args:
        faces: (F, 3) int position indices. texcoords: (Vt, 2) float stex texcoords (u right,
            v down from the atlas's top row). texcoord_faces: (F, 3) int.

    Returns:
        vertex_index: (N,) uint32, the template vertex of each GPU vertex. uv: (N, 2) float32,
        its stex texcoords (the page uploads textures with row 0 first, so v is used as is).
        index: (3 F,) uint32, the triangles into the N GPU vertices.
    """
    f = np.asarray(faces)
    tc = np.asarray(texcoords, dtype=np.float64)
    if tc.ndim != 2 or tc.shape[1] != 2 or not np.isfinite(tc).all():
        raise ValueError(f"texcoords must be finite with shape (Vt, 2), got shape {tc.shape}")
    vi, ti, new_faces = split_seams(f, texcoord_faces)
    if ti.size and (ti.min() < 0 or ti.max() >= len(tc)):
        raise ValueError(f"texcoord_faces index texcoords out of range 0..{len(tc) - 1}")
    return (vi.astype(np.uint32), tc[ti].astype(np.float32),
            new_faces.reshape(-1).astype(np.uint32))
