"""Azure Kinect calibration: the device's factory ``calibration.json`` -> a :class:`stex.camera.Calibration`
for one colour resolution and depth mode, and lens undistortion of its images.

The factory ``CalibrationInformation`` holds normalised, sensor-wide intrinsics; a mode bins the
sensor image and crops it (:data:`COLOR_RESOLUTIONS`, :data:`DEPTH_MODES`), and
:func:`calibration_from_k4a_json` turns them into the mode's pixel intrinsics, as the Azure Kinect
SDK does. :class:`Undistorter` removes the lens distortion, keeping each camera matrix.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from stex.camera import Calibration, Intrinsics


# --------------------------------------------------------------------------------------------
# Mode tables (numbers from the Azure Kinect SDK's mode-specific calibration, MIT licence).
# Each entry: (binned calibration image size, crop offset, output image size), all (x, y) pixels.
# The raw calibration is normalised to the full sensor; a mode first bins the sensor image to
# ``binned`` and then crops ``output`` starting at ``crop``.
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _ModeInfo:
    binned: tuple[int, int]
    crop: tuple[int, int]
    output: tuple[int, int]


#: Colour resolutions, keyed by the k4a name without prefix; the colour calibration is 4:3.
COLOR_RESOLUTIONS: dict[str, _ModeInfo] = {
    "720P": _ModeInfo((1280, 960), (0, 120), (1280, 720)),
    "1080P": _ModeInfo((1920, 1440), (0, 180), (1920, 1080)),
    "1440P": _ModeInfo((2560, 1920), (0, 240), (2560, 1440)),
    "1536P": _ModeInfo((2048, 1536), (0, 0), (2048, 1536)),
    "2160P": _ModeInfo((3840, 2880), (0, 360), (3840, 2160)),
    "3072P": _ModeInfo((4096, 3072), (0, 0), (4096, 3072)),
}

#: Depth modes; the depth calibration is for the 1024x1024 sensor.
DEPTH_MODES: dict[str, _ModeInfo] = {
    "NFOV_2X2BINNED": _ModeInfo((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": _ModeInfo((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": _ModeInfo((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": _ModeInfo((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": _ModeInfo((1024, 1024), (0, 0), (1024, 1024)),
}


def parse_color_resolution(value) -> str:
    """'720P' / 'RES_720P' / 'K4A_COLOR_RESOLUTION_720P' / 'MJPG_720P' / '1280x720' / (1280, 720)
    or a pyk4a ``ColorResolution`` enum -> key of ``COLOR_RESOLUTIONS``."""
    if hasattr(value, "name") and not isinstance(value, str):  # enum (pyk4a.ColorResolution)
        value = value.name
    if isinstance(value, (tuple, list)) and len(value) == 2:
        size = (int(value[0]), int(value[1]))
        for key, info in COLOR_RESOLUTIONS.items():
            if info.output == size:
                return key
        raise ValueError(f"no Azure Kinect colour resolution has size {size[0]}x{size[1]} "
                         f"(known: {', '.join(f'{m.output[0]}x{m.output[1]}' for m in COLOR_RESOLUTIONS.values())})")
    if isinstance(value, str):
        s = value.strip().upper()
        if "X" in s and s.replace("X", "").isdigit():
            w, h = s.split("X")
            return parse_color_resolution((int(w), int(h)))
        tail = s.rsplit("_", 1)[-1]
        if tail in COLOR_RESOLUTIONS:
            return tail
    raise ValueError(f"unknown Azure Kinect colour resolution {value!r} "
                     f"(expected one of {sorted(COLOR_RESOLUTIONS)} or a (width, height) pair)")


def parse_depth_mode(value) -> str:
    """'NFOV_UNBINNED' / 'K4A_DEPTH_MODE_NFOV_UNBINNED' / (640, 576) / pyk4a ``DepthMode``
    -> key of ``DEPTH_MODES``."""
    if hasattr(value, "name") and not isinstance(value, str):
        value = value.name
    if isinstance(value, (tuple, list)) and len(value) == 2:
        size = (int(value[0]), int(value[1]))
        for key, info in DEPTH_MODES.items():  # WFOV_UNBINNED comes before PASSIVE_IR
            if info.output == size:
                return key
        raise ValueError(f"no Azure Kinect depth mode has size {size[0]}x{size[1]}")
    if isinstance(value, str):
        s = value.strip().upper()
        if s.startswith("K4A_DEPTH_MODE_"):
            s = s[len("K4A_DEPTH_MODE_"):]
        if s in DEPTH_MODES:
            return s
    raise ValueError(f"unknown Azure Kinect depth mode {value!r} (expected one of {sorted(DEPTH_MODES)})")


# --------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------

_LOC_DEPTH = "CALIBRATION_CameraLocationD0"
_LOC_COLOR = "CALIBRATION_CameraLocationPV0"
_MODEL_BROWN_CONRADY = "CALIBRATION_LensDistortionModelBrownConrady"
_MODEL_RATIONAL_6KT = "CALIBRATION_LensDistortionModelRational6KT"


def _camera_entry(info: dict, location: str) -> dict:
    cams = info.get("Cameras")
    if not isinstance(cams, list) or not all(isinstance(c, dict) for c in cams):
        raise ValueError("calibration JSON: 'CalibrationInformation.Cameras' must be a list of camera objects")
    for cam in cams:
        if cam.get("Location") == location:
            return cam
    found = [c.get("Location") for c in cams]
    raise ValueError(f"calibration has no camera with Location {location!r} (found {found})")


def _rt_matrix(cam: dict, which: str) -> np.ndarray:
    """4x4 'world -> this camera' transform from a camera's Rt (row-major R, translation in m)."""
    rt = cam["Rt"]
    R = np.asarray(rt["Rotation"], dtype=np.float64)
    t = np.asarray(rt["Translation"], dtype=np.float64)
    if R.size != 9 or t.size != 3:
        raise ValueError(f"{which} camera: Rt needs 9 rotation and 3 translation numbers, got {R.size} and {t.size}")
    R, t = R.reshape(3, 3), t.reshape(3)
    # stored rounded, so re-orthonormalised below; anything farther off is not a rotation
    if not (np.isfinite(R).all() and np.isfinite(t).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-3)
            and np.linalg.det(R) > 0):
        raise ValueError(f"{which} camera: Rt.Rotation is not a rotation matrix: {R.ravel().tolist()}")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        U[:, -1] *= -1
        Rn = U @ Vt
    return Rn


def _mode_intrinsics(cam: dict, mode: _ModeInfo, which: str) -> Intrinsics:
    intr = cam["Intrinsics"]
    model = intr.get("ModelType")
    p = np.asarray(intr["ModelParameters"], dtype=np.float64)
    count = int(intr.get("ModelParameterCount", p.size))
    if count < 14 or p.size < 14:
        raise ValueError(f"{which} camera: expected 14 intrinsic parameters, got {min(count, p.size)}")
    # Parameter order in the k4a JSON / k4a_calibration_intrinsic_parameters_t:
    #   cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1   (note: p2 before p1)
    cx_n, cy_n, fx_n, fy_n, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1 = p[:14]
    if model == _MODEL_RATIONAL_6KT:
        warnings.warn(f"{which} camera uses the deprecated Rational6KT lens model (early internal devices); "
                      "its tangential term and centre of distortion have no exact OpenCV equivalent, "
                      "the distortion coefficients are an approximation", stacklevel=3)
    elif model != _MODEL_BROWN_CONRADY:
        raise ValueError(f"{which} camera: unsupported lens model {model!r} "
                         f"(expected {_MODEL_BROWN_CONRADY!r})")
    sensor = (int(cam["SensorWidth"]), int(cam["SensorHeight"]))
    if which == "colour":
        if sensor[0] * 9 // 16 == sensor[1]:
            # Legacy 16:9 colour calibration (4096x2304): the SDK re-expresses it on the 4:3
            # 4096x3072 image, which extends 384 rows above (and below) the 16:9 one.
            cx_n = cx_n * 4096 / 4096
            cy_n = (cy_n * 2304 + 384) / 3072
            fy_n = fy_n * 2304 / 3072
        elif sensor[0] * 3 // 4 != sensor[1]:
            raise ValueError(f"colour camera: unexpected sensor aspect {sensor[0]}x{sensor[1]} "
                             "(expected 4:3 or legacy 16:9)")
    elif sensor != (1024, 1024):
        raise ValueError(f"depth camera: unexpected sensor size {sensor[0]}x{sensor[1]} (expected 1024x1024)")
    bw, bh = mode.binned
    ox, oy = mode.crop
    # Normalised, 0-cornered (0 = left edge of the first pixel) -> pixels in the binned image,
    # minus the crop, minus half a pixel so that integer coordinates are pixel centres (OpenCV).
    fx = fx_n * bw
    fy = fy_n * bh
    cx = cx_n * bw - ox - 0.5
    cy = cy_n * bh - oy - 0.5
    # Brown-Conrady as k4a evaluates it equals OpenCV's rational model (codx = cody = 0).
    dist = np.array([k1, k2, p1, p2, k3, k4, k5, k6], dtype=np.float64)
    try:
        return Intrinsics.from_focal(fx, fy, cx, cy, mode.output[0], mode.output[1], dist)
    except ValueError as e:
        raise ValueError(f"{which} camera: {e}") from None


def calibration_from_k4a_json(calib, color_resolution, depth_mode) -> Calibration:
    """Mode-specific ``Calibration`` from an Azure Kinect ``calibration.json``.

    Args:
        calib: the parsed JSON (dict with key ``CalibrationInformation`` or the inner dict), or
            its text (str/bytes), as stored in a recording's ``calibration.json`` attachment or
            returned by ``k4a_device_get_raw_calibration`` / ``pyk4a ... .calibration_raw``.
        color_resolution: the recorded colour resolution: ``(width, height)`` such as
            ``(1280, 720)``, or a name: ``'720P'``, ``'RES_720P'``, ``'K4A_COLOR_RESOLUTION_720P'``,
            ``'MJPG_720P'`` (the ``K4A_COLOR_MODE`` tag), ``'1280x720'``.
        depth_mode: ``'NFOV_UNBINNED'`` (640x576), ``'NFOV_2X2BINNED'`` (320x288),
            ``'WFOV_UNBINNED'`` (1024x1024), ``'WFOV_2X2BINNED'`` (512x512), ``'PASSIVE_IR'``
            (1024x1024), optionally prefixed ``K4A_DEPTH_MODE_``, or a (width, height) pair.

    Returns:
        ``Calibration`` with ``color`` / ``depth`` ``Intrinsics`` for the recorded image sizes and
        ``depth_to_color`` (4x4, metres, X_color = R X_depth + t).

    What the JSON holds and how it is converted:

    - ``Cameras[]`` with ``Location`` ``CALIBRATION_CameraLocationD0`` (depth, 1024x1024 sensor)
      and ``CALIBRATION_CameraLocationPV0`` (colour, 4096x3072 sensor; legacy devices 4096x2304).
    - ``Intrinsics.ModelParameters`` = (cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1),
      with cx, fx divided by the sensor width and cy, fy by the sensor height, and the origin at
      the *corner* of the first pixel (the SDK's "unitized, 0-cornered" form).
    - A recording mode bins the sensor image to ``binned`` pixels and crops ``output`` pixels
      from offset ``crop`` (tables ``COLOR_RESOLUTIONS``, ``DEPTH_MODES``, the same numbers as the
      SDK's mode-specific calibration). So in the output image
      ``fx = fx_n * binned_w``, ``fy = fy_n * binned_h``,
      ``cx = cx_n * binned_w - crop_x - 0.5``, ``cy = cy_n * binned_h - crop_y - 0.5``.
      The ``- 0.5`` moves the origin from the pixel corner to the pixel centre, which is the
      stex/OpenCV convention (integer coordinates = pixel centres) and what the SDK itself
      returns as its pixel-unit calibration. E.g. 720P colour: binned 1280x960, crop (0, 120).
    - Distortion: k4a's Brown-Conrady model is OpenCV's rational model, so the OpenCV vector is
      ``(k1, k2, p1, p2, k3, k4, k5, k6)`` -- p1 and p2 are stored swapped in the JSON. (The
      deprecated ``Rational6KT`` model of pre-production devices is only approximated; a warning
      is issued.) ``MetricRadius`` (the radius in the z=1 plane beyond which the model is not
      valid) is not represented in ``Intrinsics``.
    - ``Rt`` of each camera maps a reference ("world") frame into that camera,
      X_cam = R X_world + t, R row-major, **t in metres** (the SDK multiplies by 1000 to get its
      millimetre extrinsics). The depth camera is the reference in factory calibrations (its Rt
      is the identity), but the general ``depth_to_color = Rt_color @ inv(Rt_depth)`` is used.
      The rotation is re-orthonormalised (the JSON holds float32 values).
    """
    if isinstance(calib, (bytes, bytearray, memoryview)):
        calib = bytes(calib).decode("utf-8")
    if isinstance(calib, str):
        calib = json.loads(calib)
    if not isinstance(calib, dict):
        raise ValueError(f"calibration must be a dict (parsed calibration.json), got {type(calib).__name__}")
    info = calib.get("CalibrationInformation", calib)
    if "Cameras" not in info:
        raise ValueError("calibration JSON has no 'CalibrationInformation.Cameras' list")
    color_mode = COLOR_RESOLUTIONS[parse_color_resolution(color_resolution)]
    depth_info = DEPTH_MODES[parse_depth_mode(depth_mode)]
    cam_d = _camera_entry(info, _LOC_DEPTH)
    cam_c = _camera_entry(info, _LOC_COLOR)
    try:
        depth = _mode_intrinsics(cam_d, depth_info, "depth")
        color = _mode_intrinsics(cam_c, color_mode, "colour")
        T = _rt_matrix(cam_c, "colour") @ np.linalg.inv(_rt_matrix(cam_d, "depth"))
    except (KeyError, TypeError) as e:
        raise ValueError(f"calibration JSON is missing or has a malformed field: {e!r}") from e
    T[:3, :3] = _orthonormalise(T[:3, :3])
    T[3] = (0.0, 0.0, 0.0, 1.0)
    baseline = float(np.linalg.norm(T[:3, 3]))
    if baseline > 0.5:
        warnings.warn(f"depth->colour translation is {baseline:.3f} (expected metres, ~0.032 for an "
                      "Azure Kinect); is the calibration in millimetres?", stacklevel=2)
    return Calibration(color=color, depth=depth, depth_to_color=T)


# --------------------------------------------------------------------------------------------
# Undistortion
# --------------------------------------------------------------------------------------------

class Undistorter:
    """Removes lens distortion from colour and depth images, keeping each camera matrix K.

    The remap tables are computed once (``cv2.initUndistortRectifyMap`` with R = I and
    newK = K): output pixel (u, v) of the pinhole image samples the input image where the
    distorted camera sees the same ray. Colour is interpolated bilinearly; depth uses
    nearest-neighbour so that no depth value is invented by mixing a foreground and a background
    sample or a valid value with 0 (invalid). Depth values (z along the optical axis) need no
    change, since undistortion only moves where a ray is imaged. Output pixels whose source falls
    outside the input image are 0 (black / invalid depth).

    Args:
        calibration: a ``Calibration`` with distortion coefficients.

    Attributes:
        calibration: the same calibration with zero distortion (use it with the undistorted
            images).
    """

    def __init__(self, calibration: Calibration):
        self.source = calibration
        self._maps = {}
        for name in ("color", "depth"):
            cam: Intrinsics = getattr(calibration, name)
            if np.any(cam.distortion != 0):
                m1, m2 = cv2.initUndistortRectifyMap(cam.K, cam.distortion, np.eye(3), cam.K,
                                                     (cam.width, cam.height), cv2.CV_32FC1)
                self._maps[name] = (m1, m2)
        self.calibration = Calibration(
            color=Intrinsics(calibration.color.K, calibration.color.width, calibration.color.height),
            depth=Intrinsics(calibration.depth.K, calibration.depth.width, calibration.depth.height),
            depth_to_color=calibration.depth_to_color,
        )

    def undistort_color(self, color: np.ndarray) -> np.ndarray:
        """(Hc, Wc, C) or (Hc, Wc) image (any dtype OpenCV remaps) -> same shape and dtype."""
        cam = self.source.color
        _check_shape(color, cam, "colour")
        if "color" not in self._maps:
            return color
        m1, m2 = self._maps["color"]
        return cv2.remap(color, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def undistort_depth(self, depth: np.ndarray) -> np.ndarray:
        """(Hd, Wd) uint16 mm -> (Hd, Wd) uint16 mm, nearest-neighbour, 0 outside."""
        cam = self.source.depth
        _check_shape(depth, cam, "depth")
        if "depth" not in self._maps:
            return depth
        m1, m2 = self._maps["depth"]
        return cv2.remap(depth, m1, m2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def __call__(self, color: np.ndarray | None, depth: np.ndarray | None):
        """Undistort one capture; returns ``(color, depth)`` (either may be None to skip it)."""
        return (None if color is None else self.undistort_color(color),
                None if depth is None else self.undistort_depth(depth))


def _check_shape(img: np.ndarray, cam: Intrinsics, what: str) -> None:
    if img.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"{what} image is {img.shape[1]}x{img.shape[0]} but the calibration is for "
                         f"{cam.width}x{cam.height}")


def undistort_frame(color: np.ndarray, depth: np.ndarray, calibration: Calibration):
    """Undistort one capture; returns ``(color, depth, calibration_without_distortion)``.

    Builds the remap tables on every call; for a sequence create one :class:`Undistorter`.
    """
    u = Undistorter(calibration)
    c, d = u(color, depth)
    return c, d, u.calibration
