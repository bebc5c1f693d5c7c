"""Small test shapes shared by tests and benchmarks."""

from __future__ import annotations

import numpy as np
import trimesh

# Three tall smooth protrusions on the camera-facing side hide parts of the surface behind them
# (a tenth of the front-facing faces are occluded, docs/decisions/synth.md); (direction, height, width).
_BUMPS = [((0.6, 0.1, -0.8), 0.6, 0.22), ((-0.5, 0.5, -0.7), 0.5, 0.25), ((-0.2, -0.7, -0.7), 0.5, 0.22)]


def bumpy_sphere(subdivisions: int = 5, radius: float = 0.4, distance: float = 1.5):
    """A self-occluding blob in camera coordinates: an icosphere (20,480 faces at subdivision 5)
    radially displaced by smooth bumps, centred ``distance`` metres in front of the camera.

    Returns (vertices (V, 3) float64 m, faces (F, 3) int64).
    """
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = np.asarray(m.vertices)
    bump = 0.1 * np.sin(3.0 * d[:, 0] + 0.3) * np.sin(4.0 * d[:, 1] + 1.1) * np.sin(3.0 * d[:, 2] + 0.7)
    for c, height, width in _BUMPS:
        c = np.asarray(c) / np.linalg.norm(c)
        bump += height * np.exp(-((d - c) ** 2).sum(axis=1) / width ** 2)
    v = d * (radius * (1.0 + bump))[:, None]
    v[:, 2] += distance
    return v, np.asarray(m.faces, dtype=np.int64)
