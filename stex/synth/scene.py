"""Synthetic RGB-D scenes with ground truth: one camera watching a deforming, turning object.

A scene is a deterministic function of its settings (``source.synthetic`` in the config): every
frame can be rendered on its own, so frame-block jobs run in parallel and give the same bytes
whatever the blocking.

Geometry: the object (a :class:`~stex.synth.procedural.ProceduralBody` or a skinned glTF asset,
:class:`~stex.synth.skinned.SkinnedBody`) sits ``distance_m`` in front of the depth camera, tilted
by ``elevation_deg`` so the camera looks at it from above, and turns about its vertical axis with
yaw(t) = yaw_range · sin(2π t / yaw_period): each frame sees about a third of the surface, most
of it is seen at some frame, and the underside and a strip of the back are never seen. A textured
wall behind it gives the background (colour and depth).

Degradations (each a switch): motion blur (sub-frame renders averaged over the exposure), colour
sensor noise, exposure/white-balance drift, Kinect-like depth noise (σ ∝ z²) with holes and
edge drop-outs, and a smooth tangential tracking drift of the meshes handed to the 'given'
tracking mode (the truth stays exact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from stex.camera import Calibration, Intrinsics, transform_points
from stex.render import rasterize, render_textured, sample_bilinear, vertex_normals
from stex.synth.biped import BipedBody
from stex.synth.procedural import ProceduralBody, ProceduralParams
from stex.synth.skinned import SkinnedBody


def rotation(axis: str, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (radians) about the coordinate axis ``axis`` ("x", "y" or "z")."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _smooth_series(rng: np.random.Generator, n_terms: int = 3):
    """A smooth zero-mean random function of time in [-1, 1], fixed by ``rng``."""
    freqs = rng.uniform(0.05, 0.4, n_terms)  # Hz
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    amps = rng.uniform(0.5, 1.0, n_terms)
    amps /= amps.sum()
    return lambda t: float(np.sum(amps * np.sin(2 * np.pi * freqs * t + phases)))


@dataclass
class FrameRender:
    """One rendered frame: sensor data and its ground truth."""

    color: np.ndarray        # (Hc, Wc, 3) uint8, with degradations
    depth_mm: np.ndarray     # (Hd, Wd) uint16, with degradations, 0 = invalid
    true_mask: np.ndarray    # (Hc, Wc) bool
    true_depth: np.ndarray   # (Hd, Wd) float32 m, noise free
    appearance: np.ndarray   # (W, W, 3) uint8, true texture at this frame
    timestamp: float         # s


class SyntheticScene:
    """A synthetic scene built from the ``source.synthetic`` settings dict (schema defaults)."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        self.n_frames = int(cfg["n_frames"])
        if self.n_frames < 1:
            raise ValueError(f"synthetic scene needs n_frames >= 1, got {self.n_frames}")
        self.fps = float(cfg["fps"])
        self.seed = int(cfg["seed"])
        self.texture_size = int(cfg["texture_size"])
        c, d = cfg["color"], cfg["depth"]
        color = Intrinsics.from_focal(c["fx"], c["fx"], (c["width"] - 1) / 2, (c["height"] - 1) / 2, c["width"], c["height"])
        depth = Intrinsics.from_focal(d["fx"], d["fx"], (d["width"] - 1) / 2, (d["height"] - 1) / 2, d["width"], d["height"])
        T = np.eye(4)
        T[:3, :3] = rotation("x", np.deg2rad(cfg["depth_to_color"]["rotation_deg"][0])) @ \
            rotation("y", np.deg2rad(cfg["depth_to_color"]["rotation_deg"][1])) @ \
            rotation("z", np.deg2rad(cfg["depth_to_color"]["rotation_deg"][2]))
        T[:3, 3] = cfg["depth_to_color"]["translation_m"]
        self.calibration = Calibration(color, depth, T)

        kind = cfg["object"]
        if kind == "procedural":
            p = cfg["procedural"]
            self.body = ProceduralBody(ProceduralParams(
                height=p["height_m"], radius=p["radius_m"], n_around=p["n_around"],
                n_rings=p["n_rings"], bend=p["bend_rad"], bend_period=p["bend_period_s"],
                twist=p["twist_rad"], twist_period=p["twist_period_s"], squash=p["squash"],
                squash_period=p["squash_period_s"], bulge=p["bulge"], bulge_period=p["bulge_period_s"],
                wrinkle_depth=p["wrinkle_depth"], wrinkle_stripes=p["wrinkle_stripes"],
                patch_strength=p["patch_strength"], patch_size=p["patch_size"],
                stretch_tint=p["stretch_tint"], seed=self.seed))
            self._base = self.body.base_texture(self.texture_size)
        elif kind == "gltf":
            g = cfg["gltf"]
            if not g.get("path"):
                raise ValueError("source.synthetic.gltf.path must name a .gltf/.glb file for object: gltf")
            self.body = SkinnedBody(g["path"], animation=g["animation"], size_m=g["size_m"],
                                    texture_size=self.texture_size, seed=self.seed)
            self._base = None
        elif kind == "biped":
            b = cfg["biped"]
            self.body = BipedBody(size_m=b["size_m"], walk_period_s=b["walk_period_s"], stride_deg=b["stride_deg"],
                                  texture_size=self.texture_size, seed=self.seed)
            self._base = None
        else:
            raise ValueError(f"unknown synthetic object {kind!r} (procedural | gltf | biped)")
        self.faces = self.body.faces
        self.texcoords = self.body.texcoords
        self.texcoord_faces = self.body.texcoord_faces

        rng = np.random.default_rng(self.seed + 1)
        self._gain = [_smooth_series(rng) for _ in range(3)]
        self._drift_k = rng.normal(0, 1, (4, 3)) * 12.0      # spatial frequencies, 1/m
        self._drift_dir = rng.normal(0, 1, (4, 3))
        self._drift_phase = rng.uniform(0, 2 * np.pi, 4)
        self._wall = self._wall_texture()

    # -- motion --------------------------------------------------------------------------------
    def object_to_depth(self, time_s: float) -> np.ndarray:
        """4x4 object-frame -> depth-camera transform at ``time_s``."""
        cfg = self.cfg
        yaw = np.deg2rad(cfg["yaw_offset_deg"] + cfg["yaw_range_deg"] * np.sin(2 * np.pi * time_s / cfg["yaw_period_s"]))
        flip = np.diag([1.0, -1.0, -1.0])  # object +y up -> camera -y; object faces the camera
        R = rotation("x", np.deg2rad(cfg["elevation_deg"])) @ flip @ rotation("y", yaw)
        sway = 0.03 * np.array([np.sin(2 * np.pi * time_s / 2.9), 0.5 * np.sin(2 * np.pi * time_s / 3.7), 0.0])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([0.0, 0.0, cfg["distance_m"]]) + sway
        return T

    def time_of(self, frame: int) -> float:
        return frame / self.fps

    def true_vertices(self, frame: int, offset_s: float = 0.0) -> np.ndarray:
        """(V, 3) float64 true vertices of ``frame`` in depth-camera coordinates, metres."""
        t = self.time_of(frame) + offset_s
        return transform_points(self.object_to_depth(t), self.body.vertices(t)).astype(np.float64)

    def rest_shape_vertices(self, frame: int) -> np.ndarray:
        """(V, 3) float64 undeformed rest-shape vertices placed as the object is at ``frame``
        (depth-camera coordinates, metres): what a scan of the still object gives."""
        rest = self.body.vertices(None)
        return transform_points(self.object_to_depth(self.time_of(frame)), rest).astype(np.float64)

    def skeleton(self, frame: int = 0):
        """The object's skin at ``frame`` in depth-camera coordinates, as
        :func:`stex.skeleton.skeleton_from_skin` takes it (parents, joint frames (J, 4, 4), vertex
        joints, weights, names), or None for an object without one."""
        if not hasattr(self.body, "skeleton"):
            return None
        parents, frames, joints, weights, names = self.body.skeleton(self.time_of(frame))
        return parents, self.object_to_depth(self.time_of(frame)) @ frames, joints, weights, names

    def given_vertices(self, frame: int) -> np.ndarray:
        """Vertices handed to 'given' tracking mode: the truth plus the optional tracking drift."""
        V = self.true_vertices(frame)
        drift = self.cfg["degradations"]["tracking_drift"]
        if not drift["enabled"]:
            return V
        # Smooth field over the rest shape, oscillating in time with period_s, projected onto the
        # tangent plane so it slides the surface along itself (what tracking drift looks like).
        # It averages out over time: a drift constant in time would be indistinguishable from
        # a shifted texture, and no photometric method could (or would need to) undo it.
        t = self.time_of(frame)
        rest = self.body.rest_vertices
        field = np.zeros_like(rest)
        for k, d, ph in zip(self._drift_k, self._drift_dir, self._drift_phase):
            field += np.sin(rest @ k + ph + 2 * np.pi * t / drift["period_s"])[:, None] * d
        field /= np.abs(field).max() + 1e-12
        n = vertex_normals(V, self.faces).astype(np.float64)
        tangential = field - (field * n).sum(1, keepdims=True) * n
        tangential *= drift["amplitude_m"] / (np.linalg.norm(tangential, axis=1).max() + 1e-12)
        return V + tangential

    # -- rendering -----------------------------------------------------------------------------
    def appearance(self, frame: int) -> np.ndarray:
        """(W, W, 3) uint8 true texture of the object at ``frame``."""
        t = self.time_of(frame)
        if self._base is not None:
            return self.body.appearance(t, self.texture_size, self._base)
        return self.body.appearance(t)

    def _wall_texture(self) -> np.ndarray:
        rng = np.random.default_rng(self.seed + 2)
        n = 512
        noise = ndimage.gaussian_filter(rng.standard_normal((n, n)), 3, mode="wrap")
        noise /= noise.std()
        yy, xx = np.mgrid[0:n, 0:n]
        mortar = ((yy % 32) < 3) | (((xx + 32 * ((yy // 32) % 2)) % 64) < 3)
        wall = 0.62 + 0.05 * noise - 0.25 * mortar
        wall = wall[..., None] * np.array([0.95, 0.85, 0.72])
        return (wall.clip(0, 1) * 255).astype(np.float32)

    def _render_color(self, V_depth: np.ndarray, texture: np.ndarray):
        cal = self.calibration
        Vc = transform_points(cal.depth_to_color, V_depth)
        img, mask = render_textured(Vc, self.faces, self.texcoords, self.texcoord_faces, texture,
                                    cal.color.K, cal.color.width, cal.color.height)
        return img, mask

    def _wall_color(self) -> np.ndarray:
        """Colour image of the wall alone (a plane z = wall_distance in depth coordinates)."""
        if getattr(self, "_wall_img", None) is not None:
            return self._wall_img
        cal = self.calibration
        W, H = cal.color.size
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        rays = np.stack([(u - cal.color.cx) / cal.color.fx, (v - cal.color.cy) / cal.color.fy, np.ones_like(u)], -1)
        R, t = cal.depth_to_color[:3, :3], cal.depth_to_color[:3, 3]
        # Plane in depth coordinates: z = Zw; colour camera centre in depth coordinates: -R^T t.
        o = -R.T @ t
        d = rays @ R  # R^T applied to each ray
        lam = (self.cfg["wall_distance_m"] - o[2]) / d[..., 2]
        X = o + lam[..., None] * d
        px = (X[..., :2] / 4.0 + 0.5) * self._wall.shape[0]  # the wall texture spans 4 m
        self._wall_img = sample_bilinear(self._wall, np.mod(px, self._wall.shape[0] - 1))
        return self._wall_img

    def render_frame(self, frame: int) -> FrameRender:
        """Render ``frame``: degraded colour and depth, plus the exact mask, depth and appearance."""
        if not 0 <= frame < self.n_frames:
            raise IndexError(f"frame {frame} outside the scene's 0..{self.n_frames - 1}")
        cfg = self.cfg
        deg = cfg["degradations"]
        cal = self.calibration
        rng = np.random.default_rng([self.seed, frame])
        appearance = self.appearance(frame)
        tex = appearance.astype(np.float32)
        V = self.true_vertices(frame)
        img, mask = self._render_color(V, tex)
        wall = self._wall_color()
        color = np.where(mask[..., None], img, wall)
        if deg["motion_blur"]["enabled"]:
            n = int(deg["motion_blur"]["samples"])
            exposure = float(deg["motion_blur"]["exposure"]) / self.fps
            acc = np.zeros_like(color)
            for k in range(n):
                off = (k / max(n - 1, 1) - 0.5) * exposure
                sub, sub_mask = self._render_color(self.true_vertices(frame, off), tex)
                acc += np.where(sub_mask[..., None], sub, wall)
            color = acc / n
        if deg["exposure_drift"]["enabled"]:
            t = self.time_of(frame)
            a = float(deg["exposure_drift"]["amplitude"])
            gain = np.array([1.0 + a * g(t) for g in self._gain], np.float32)
            color = color * gain
        if deg["sensor_noise"]["enabled"]:
            color = color + rng.normal(0, deg["sensor_noise"]["sigma"], color.shape)
        color = (color + 0.5).clip(0, 255).astype(np.uint8)

        depth_true = rasterize(V, self.faces, cal.depth.K, cal.depth.width, cal.depth.height).depth
        depth_true = np.where(depth_true > 0, depth_true, np.float32(cfg["wall_distance_m"])).astype(np.float32)
        depth = depth_true.astype(np.float64)
        dn = deg["depth_noise"]
        if dn["enabled"]:
            depth = depth + rng.normal(0, 1, depth.shape) * dn["sigma_1m"] * depth**2
            holes = ndimage.gaussian_filter(rng.random(depth.shape), 2.0)
            holes = holes > np.quantile(holes, 1 - dn["hole_fraction"])
            grad = ndimage.maximum_filter(depth_true, 3) - ndimage.minimum_filter(depth_true, 3)
            edge = (grad > 0.05) & (rng.random(depth.shape) < dn["edge_dropout"])
            depth[holes | edge] = 0
        depth_mm = np.round(depth * 1000).clip(0, 65535).astype(np.uint16)
        return FrameRender(color, depth_mm, mask, depth_true, appearance, self.time_of(frame))
