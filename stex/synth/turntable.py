"""A synthetic turntable capture with truth: the synthetic scene's object in its rest pose, turned
once round its vertical axis in front of the camera (``template.from_scan``'s test and benchmark
capture).

It is a :class:`~stex.synth.scene.SyntheticScene` (same object, camera, wall, colour and
Kinect-like depth degradations) whose motion is replaced: the object does not deform (rest pose,
rest appearance) and turns by 360° over the capture, yaw(k) = 360° · k / n_frames, while the
camera's elevation swings as elevation(k) = e · cos(2π k / n_frames), so the first and last frames
look down on the object from ``e`` and the middle ones up from below: top and underside are both
seen, as when a hand-held camera moves round an object (a real turntable would need a second pass
with the object upside down). No sway: the object stands still apart from the turn.
"""

from __future__ import annotations

import numpy as np

from stex.camera import transform_points
from stex.synth.scene import SyntheticScene, rotation


class TurntableScene(SyntheticScene):
    """The ``source.synthetic`` object on a turntable.

    Args:
        cfg: a validated ``source.synthetic`` settings dict; its ``n_frames`` is the capture's
            length (one full turn over it), its motion and deformation settings are unused.
        elevation_deg: amplitude ``e`` of the camera's elevation swing (degrees).
    """

    def __init__(self, cfg: dict, elevation_deg: float = 25.0):
        super().__init__(cfg)
        self.elevation_deg = float(elevation_deg)
        self._rest = self.body.vertices(None).astype(np.float64)

    def object_to_depth(self, time_s: float) -> np.ndarray:
        """4x4 object-frame -> depth-camera transform at ``time_s`` (one turn over the capture)."""
        phase = time_s * self.fps / self.n_frames  # turns, 0 at frame 0, 1 one frame past the end
        yaw = np.deg2rad(self.cfg["yaw_offset_deg"]) + 2 * np.pi * phase
        elevation = np.deg2rad(self.elevation_deg * np.cos(2 * np.pi * phase))
        flip = np.diag([1.0, -1.0, -1.0])  # object +y up -> camera -y; object faces the camera
        T = np.eye(4)
        T[:3, :3] = rotation("x", elevation) @ flip @ rotation("y", yaw)
        T[:3, 3] = [0.0, 0.0, self.cfg["distance_m"]]
        return T

    def rest_vertices(self) -> np.ndarray:
        """(V, 3) float64 rest-pose vertices in the object frame (m, +y up)."""
        return self._rest.copy()

    def true_vertices(self, frame: int, offset_s: float = 0.0) -> np.ndarray:
        """(V, 3) float64 rest-pose vertices at ``frame`` in depth-camera coordinates, metres."""
        return transform_points(self.object_to_depth(self.time_of(frame) + offset_s), self._rest)

    def given_vertices(self, frame: int) -> np.ndarray:
        """The true vertices: a scan capture hands no meshes to tracking."""
        return self.true_vertices(frame)

    def appearance(self, frame: int) -> np.ndarray:
        """(W, W, 3) uint8 rest appearance of the object (the same at every frame)."""
        if getattr(self, "_appearance", None) is None:  # computed once: the object does not change
            self._appearance = (self.body.appearance(None, self.texture_size, self._base)
                                if self._base is not None else self.body.appearance(None))
        return self._appearance
