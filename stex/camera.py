"""Camera models and coordinate conventions used everywhere in stex.

Conventions (stated once, here):

- Pinhole cameras in the OpenCV convention: x right, y down, z forward; lengths in metres.
- Pixel coordinates: the centre of pixel (row r, column c) is at (u, v) = (c, r); i.e. integer
  coordinates are pixel centres, as in OpenCV's ``projectPoints``.
- Meshes, depth points and poses live in **depth-camera coordinates** (the authors' convention).
  ``Calibration.depth_to_color`` maps a depth-camera point X_d to the colour camera,
  X_c = R X_d + t (4x4, metres).
- Depth images are stored as uint16 millimetres (0 = invalid) and used as float metres in code.
- Distortion coefficients follow OpenCV's order (k1, k2, p1, p2, k3, k4, k5, k6); stex projects
  with the pinhole model only, so readers undistort (or report) when coefficients are non-zero.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera.

    Attributes:
        K: (3, 3) float64 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels.
        width, height: image size in pixels.
        distortion: (8,) float64 OpenCV coefficients (k1, k2, p1, p2, k3, k4, k5, k6).
    """

    K: np.ndarray
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(8))

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix must be 3x3, got shape {K.shape}")
        fx, fy = K[0, 0], K[1, 1]
        if not (np.isfinite(K).all() and fx > 0 and fy > 0):
            raise ValueError(f"camera matrix needs finite positive focal lengths, got fx={fx}, fy={fy}")
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2].tolist() != [0.0, 0.0, 1.0]:
            # projection and back-projection use fx, fy, cx, cy only
            raise ValueError(f"camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), "
                             f"got {K.tolist()}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        cx, cy = K[0, 2], K[1, 2]
        if not (-0.5 <= cx <= int(self.width) - 0.5 and -0.5 <= cy <= int(self.height) - 0.5):
            raise ValueError(f"principal point ({cx:g}, {cy:g}) lies outside the {int(self.width)}x{int(self.height)} "
                             f"image (intrinsics of another resolution, or cx/cy swapped?)")
        dist = np.zeros(8)
        d = np.asarray(self.distortion, dtype=np.float64).ravel()
        if d.size > 8:
            raise ValueError(f"at most 8 distortion coefficients, got {d.size}")
        if not np.isfinite(d).all():
            raise ValueError(f"distortion coefficients must be finite, got {d.tolist()}")
        for what, v in (("width", self.width), ("height", self.height)):
            if isinstance(v, (float, np.floating)) and v != int(v):
                raise ValueError(f"image {what} must be a whole number of pixels, got {v}")
        dist[: d.size] = d
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "distortion", dist)

    @classmethod
    def from_focal(cls, fx, fy, cx, cy, width, height, distortion=()) -> "Intrinsics":
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(K, width, height, np.asarray(distortion, dtype=np.float64))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    def resolution_mismatch(self) -> str | None:
        """Why these intrinsics may belong to another image size, or None.

        Suspect when the principal point is more than ``MAX_PRINCIPAL_OFFSET`` of the width (height)
        from the image centre ((width - 1) / 2, (height - 1) / 2) in x (y). Valid either way: the
        readers warn, they do not refuse.
        """
        ox = abs(self.cx - (self.width - 1) / 2) / self.width
        oy = abs(self.cy - (self.height - 1) / 2) / self.height
        if max(ox, oy) <= MAX_PRINCIPAL_OFFSET:
            return None
        size = f"{self.width}x{self.height}"
        return (f"principal point ({self.cx:g}, {self.cy:g}) is {100 * ox:.0f} % of the width and "
                f"{100 * oy:.0f} % of the height from the centre of the {size} image (more than "
                f"{100 * MAX_PRINCIPAL_OFFSET:.0f} %; real cameras' are within about 10 %): the intrinsics may "
                f"belong to another resolution, {2 * self.cx + 1:g}x{2 * self.cy + 1:g} (2*cx+1 by 2*cy+1); "
                f"give the intrinsics of the {size} images (stex.camera.Intrinsics.scaled converts them)")

    def scaled(self, factor: float) -> "Intrinsics":
        """The same camera for an image resized by ``factor`` (pixel centres preserved)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Intrinsics(K, round(self.width * factor), round(self.height * factor), self.distortion)

    def to_dict(self) -> dict:
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height,
            "distortion": [float(x) for x in self.distortion],
        }

    @classmethod
    def from_dict(cls, d: dict, name: str = "camera") -> "Intrinsics":
        """From ``{fx, fy, cx, cy, width, height[, distortion]}``; ValueError naming ``name`` (e.g.
        'color camera') and the key when ``d`` is missing, lacks a key or holds a bad value.
        ``"distortion": null`` means no distortion, as a missing key or ``[]`` (all zero)."""
        if not isinstance(d, dict):
            raise ValueError(f"{name}: missing (a dict of fx, fy, cx, cy, width, height)")
        distortion = d.get("distortion")
        try:
            return cls.from_focal(d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"],
                                  () if distortion is None else distortion)
        except KeyError as e:
            raise ValueError(f"{name}: missing key {e}") from None
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name}: {e}") from None


# The colour and depth cameras of an RGB-D sensor sit 1-6 cm apart (Kinect v1/v2, Azure Kinect,
# RealSense); a larger translation is a unit mistake, not a rig.
MAX_BASELINE_M = 0.5

# Real RGB-D cameras have the principal point near the image centre: the shared samples (Kinect v1,
# Structure sensor, Azure Kinect colour) within 1 %, the Azure Kinect's NFOV depth modes (a crop of
# the sensor) 10.6 % of the height off. Intrinsics of half the resolution are 25 % off, those of
# 720p given for 1080p 17 %. Fraction of the width (x) or height (y).
MAX_PRINCIPAL_OFFSET = 0.15


@dataclass(frozen=True)
class Calibration:
    """Colour and depth cameras of one RGB-D sensor.

    Attributes:
        color, depth: the two cameras.
        depth_to_color: (4, 4) float64 rigid transform, depth-camera -> colour-camera, metres.
    """

    color: Intrinsics
    depth: Intrinsics
    depth_to_color: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        T = np.array(self.depth_to_color, dtype=np.float64)  # a copy: the last row is set below
        if T.shape == (3, 4):
            T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"depth_to_color must be a finite 4x4 (or 3x4) matrix, got shape {T.shape}")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
            # transform_points uses the top 3x4 only: another last row would be stored, never applied
            raise ValueError(f"depth_to_color's last row must be (0, 0, 0, 1) (a rigid transform), got "
                             f"{T[3].tolist()}: give [[R, t], [0, 0, 0, 1]] or the 3x4 [R | t]")
        T[3] = (0.0, 0.0, 0.0, 1.0)
        R = T[:3, :3]
        err, det = float(np.abs(R @ R.T - np.eye(3)).max()), float(np.linalg.det(R))
        if err > 1e-4 or det < 0:
            raise ValueError(f"depth_to_color rotation is not a proper rotation matrix (R Rt differs from the "
                             f"identity by {err:.2g}, det {det:.4g}; it must be orthonormal to 1e-4 with det +1)")
        baseline = float(np.linalg.norm(T[:3, 3]))
        if baseline > MAX_BASELINE_M:
            raise ValueError(f"depth_to_color translation is {baseline:.3g} m, but the two cameras of one RGB-D "
                             f"sensor are centimetres apart: is it in millimetres? It must be in metres")
        object.__setattr__(self, "depth_to_color", T)

    def warn_suspicious(self, source: str) -> None:
        """Warn (``UserWarning``, naming ``source``, e.g. the calibration file) about valid but
        probably wrong values: intrinsics that look like another resolution's. Readers call it
        once; not in ``__post_init__``, as every stage rebuilds the calibration from scene.zarr."""
        for name, cam in (("color", self.color), ("depth", self.depth)):
            msg = cam.resolution_mismatch()
            if msg:
                warnings.warn(f"{source}: {name} camera: {msg}", stacklevel=2)

    def to_dict(self) -> dict:
        return {
            "color": self.color.to_dict(),
            "depth": self.depth.to_dict(),
            "depth_to_color": self.depth_to_color.tolist(),
            "convention": "OpenCV pinhole, metres; depth_to_color maps depth-camera points to colour-camera points",
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Calibration":
        cams = [Intrinsics.from_dict(d.get(which), f"{which} camera") for which in ("color", "depth")]
        if "depth_to_color" not in d:
            raise ValueError("no 'depth_to_color' transform")
        return cls(*cams, np.asarray(d["depth_to_color"], dtype=np.float64))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (..., 3) points; returns the same shape and float dtype."""
    points = np.asarray(points)
    out = points @ T[:3, :3].T + T[:3, 3]
    return out.astype(np.result_type(points.dtype, np.float32), copy=False)


def project_points(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (..., 3) camera-space points with a pinhole K.

    Returns:
        uv: (..., 2) pixel coordinates (integer = pixel centre); NaN where z <= 0.
        z: (...,) depth along the optical axis, metres.
    """
    points = np.asarray(points, dtype=np.float64)
    z = points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(z > 0, 1.0 / z, np.nan)
    u = K[0, 0] * points[..., 0] * inv + K[0, 1] * points[..., 1] * inv + K[0, 2]
    v = K[1, 1] * points[..., 1] * inv + K[1, 2]
    return np.stack([u, v], axis=-1), z


def backproject_depth(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-project an (H, W) depth map in metres to (H, W, 3) camera-space points (0 stays 0)."""
    H, W = depth_m.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = depth_m.astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)


def backproject_pixels(depth_m: np.ndarray, K: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(N, 3) float64 camera-space points of the (H, W) depth map's pixels at flat indices ``idx``
    (N,) int: the rows of ``backproject_depth(depth_m, K).reshape(-1, 3)[idx]``, without the
    whole image's points (a depth image holds ten times more pixels than the object)."""
    d = np.asarray(depth_m)
    v, u = np.divmod(np.asarray(idx, np.int64), d.shape[1])
    z = d.reshape(-1)[idx].astype(np.float64)
    x = (u.astype(np.float64) - K[0, 2]) / K[0, 0] * z
    y = (v.astype(np.float64) - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)


def depth_pixels_in_color(depth_m: np.ndarray, calibration: "Calibration", select=None):
    """Where the depth pixels land in the colour image (through depth_to_color and the colour K).

    Args:
        depth_m: (Hd, Wd) depth in metres, 0 = invalid. select: optional (Hd, Wd) bool.

    Returns:
        idx (N,) int64 flat indices of the depth pixels with depth > 0 (and in ``select``) whose
        point lands in front of the colour camera and inside its image; px (N, 2) int64 their
        nearest colour pixel (column, row); z (N,) float64 their colour-camera depth, metres.
    """
    d = np.asarray(depth_m)
    if d.ndim != 2:
        raise ValueError(f"depth_m must be an (Hd, Wd) map, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"depth_m must be float metres, got {d.dtype} (uint16 millimetres? divide by 1000)")
    d = d.astype(np.float64, copy=False)
    valid = d > 0
    if select is not None:
        sel = np.asarray(select)
        if sel.shape != d.shape:
            raise ValueError(f"select must have the depth map's shape {d.shape}, got {sel.shape}")
        valid &= sel.astype(bool, copy=False)
    idx = np.flatnonzero(valid)
    P = backproject_pixels(d, calibration.depth.K, idx)
    uv, z = project_points(transform_points(calibration.depth_to_color, P), calibration.color.K)
    c = calibration.color
    ok = (z > 0) & np.isfinite(uv).all(1)
    px = np.rint(uv[ok]).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < c.width) & (px[:, 1] >= 0) & (px[:, 1] < c.height)
    return idx[ok][inside], px[inside], z[ok][inside]


def mask_in_depth(mask_color: np.ndarray, depth_mm: np.ndarray, calibration) -> np.ndarray:
    """(Hd, Wd) bool: depth pixels whose 3-D point lands on the colour-resolution mask."""
    d = depth_mm.astype(np.float64) / 1000.0
    idx, px, _ = depth_pixels_in_color(d, calibration)
    out = np.zeros(d.size, bool)
    out[idx] = mask_color[px[:, 1], px[:, 0]]
    return out.reshape(d.shape)


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """4x4 world->camera transform for an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear upwards in the image (OpenCV's -y).
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    z = np.asarray(target, dtype=np.float64).reshape(3) - eye
    if not (np.isfinite(z).all() and np.linalg.norm(z) > 0):
        raise ValueError(f"look_at needs a finite target apart from the eye, got eye {eye.tolist()}, "
                         f"target {np.asarray(target).tolist()}")
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, dtype=np.float64).reshape(3), z)
    if not np.linalg.norm(x) > 1e-9:
        raise ValueError(f"look_at: the viewing direction {z.tolist()} is parallel to up {list(up)}; "
                         f"give another up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T
