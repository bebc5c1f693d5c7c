"""Masks stage: foreground masks at colour resolution by GrabCut seeded from depth.

The depth image says where the object is (valid depth inside [near, far] metres) and where it
is not (valid depth beyond the range). Those depth pixels are carried into the colour image
through the calibration (depth -> colour extrinsic, colour intrinsics), and become GrabCut seeds:

- sure foreground: the in-range region, eroded by ``sure_erode_px``;
- probable foreground: the in-range region (holes filled);
- probable background: a band of ``bg_margin_px`` around it, where depth edges and parallax
  between the two cameras make depth unreliable;
- sure background: everything else (out-of-range or invalid depth far from the object).

A real object rarely floats: it stands on a table or the floor, which is in range too and
touches it. Optionally (``support_plane_tolerance_m``), that support is removed from the
in-range depth points before they become seeds (:func:`object_depth_pixels`): the plane the
object stands on (:func:`support_plane`: of the dominant planes of those points, found by RANSAC,
``skimage.measure.ransac``, the first with the object on its camera side), with everything
beyond it.

GrabCut (OpenCV) then places the boundary on colour edges. Large images are segmented at a
reduced size (``max_pixels``) and the result is upsampled.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np
from scipy import ndimage

from stex.camera import Calibration, backproject_depth, depth_pixels_in_color


GC_BGD, GC_FGD, GC_PR_BGD, GC_PR_FGD = cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD


class PlaneModel:
    """A plane n·p + d = 0 (unit n) for ``skimage.measure.ransac``: three points define it, the
    residual of a point is its distance (m). Both of skimage's model interfaces (``from_estimate``,
    0.26+, and the older ``estimate``)."""

    def __init__(self, normal=None, offset=0.0):
        self.normal = None if normal is None else np.asarray(normal, np.float64)
        self.offset = float(offset)

    def __bool__(self):
        return self.normal is not None

    @classmethod
    def from_estimate(cls, points):
        model = cls()
        model.estimate(points)
        return model

    def estimate(self, points) -> bool:
        """Least-squares plane through ``points`` (N >= 3, 3); False if they are collinear."""
        P = np.asarray(points, np.float64)
        centre = P.mean(0)
        _, sv, vt = np.linalg.svd(P - centre, full_matrices=False)
        if sv.shape[0] < 2 or sv[1] <= 1e-9 * max(sv[0], 1e-300):
            self.normal = None
            return False
        self.normal = vt[-1]
        self.offset = -float(self.normal @ centre)
        return True

    def residuals(self, points):
        return np.abs(np.asarray(points, np.float64) @ self.normal + self.offset)


def dominant_plane(points: np.ndarray, tolerance_m: float, seed: int = 0, max_points: int = 5000,
                   trials: int = 200) -> tuple[np.ndarray, float]:
    """The plane through most of the (N, 3) points (metres), by RANSAC.

    RANSAC (``skimage.measure.ransac``, ``trials`` draws of 3 points, inliers within
    ``tolerance_m``) runs on at most ``max_points`` of the points, evenly spaced; the plane is
    then refitted to its inliers.

    Returns:
        (normal (3,) float64 unit, offset float m): the plane normal·p + offset = 0, oriented so
        that the camera centre is on its positive side (offset > 0). The signed distance of a
        point p from the plane is normal·p + offset.
    """
    from skimage.measure import ransac  # scikit-image is slow to import; only the support plane needs it

    P = np.asarray(points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3:
        raise ValueError(f"a plane needs (N >= 3, 3) points, got shape {P.shape}")
    sample = P[np.linspace(0, len(P) - 1, min(len(P), max_points)).astype(np.int64)]
    with warnings.catch_warnings():  # skimage warns "No inliers found"; the error below says more
        warnings.simplefilter("ignore", UserWarning)
        model, _ = ransac(sample, PlaneModel, min_samples=3, residual_threshold=tolerance_m,
                          max_trials=trials, rng=np.random.default_rng(seed))
    if model is None or not model:
        raise ValueError("support_plane: no plane found (the points are collinear?)")
    n, d = model.normal, model.offset
    if d < 0:  # the camera centre (origin) on the positive side
        n, d = -n, -d
    return n, d


def support_plane(points: np.ndarray, tolerance_m: float, seed: int = 0, candidates: int = 3,
                  max_beyond: float = 0.2, min_fraction: float = 0.05):
    """The plane the object stands on, among the (N, 3) in-range points (metres), or None.

    The dominant plane (:func:`dominant_plane`) is not always the support: a flat object (a
    shirt held up) can hold more points than the floor. A support has the object on its camera
    side, so a plane is taken only if at most ``max_beyond`` of the points off it lie beyond it
    (a shirt has the person behind it); otherwise the next dominant plane of the points off it is
    tried, up to ``candidates`` planes. A plane holding less than ``min_fraction`` of the points
    ends the search.

    Returns:
        (normal (3,), offset m, fraction of the points on the plane), as :func:`dominant_plane`
        orients it; or None when no plane qualifies.
    """
    P = np.asarray(points, np.float64)
    rest = P
    for k in range(candidates):
        try:
            n, d = dominant_plane(rest, tolerance_m, seed=seed + k)
        except ValueError:
            if k == 0:  # the points themselves hold no plane: say so
                raise
            return None  # what the earlier planes left holds none
        dist = P @ n + d
        on = np.abs(dist) <= tolerance_m
        if on.mean() < min_fraction:
            return None
        if not (~on).any() or (dist[~on] < 0).mean() <= max_beyond:
            return n, d, float(on.mean())
        rest = rest[np.abs(rest @ n + d) > tolerance_m]
    return None


def object_depth_pixels(depth_mm: np.ndarray, K: np.ndarray, near_m: float, far_m: float,
                        plane_tolerance_m: float = 0.0, seed: int = 0, info: dict | None = None) -> np.ndarray:
    """(Hd, Wd) bool: the depth pixels taken for the object.

    Valid depth inside [near_m, far_m]; with ``plane_tolerance_m`` > 0, minus the support plane
    (:func:`support_plane` of those points, RANSAC seeded with ``seed``; none if no plane
    qualifies) and everything on its far side, i.e. every point whose signed distance from the
    plane is at most ``plane_tolerance_m``. ``info``, if given, receives ``support_plane``:
    [nx, ny, nz, offset m, fraction of the in-range points on it], or None.
    """
    if depth_mm.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth_mm.shape}")
    d = depth_mm.astype(np.float64) / 1000.0
    keep = (d >= near_m) & (d <= far_m)
    if plane_tolerance_m > 0 and keep.sum() >= 3:
        P = backproject_depth(d, K)
        plane = support_plane(P[keep], plane_tolerance_m, seed=seed)
        if info is not None:
            info["support_plane"] = None if plane is None else [*map(float, plane[0]), plane[1], plane[2]]
        if plane is not None:
            n, off, _ = plane
            keep &= (P @ n + off) > plane_tolerance_m
    return keep


def depth_region_in_color(depth_mm: np.ndarray, calibration: Calibration, near_m: float,
                          far_m: float, select: np.ndarray | None = None) -> np.ndarray:
    """(Hc, Wc) bool: colour pixels covered by depth points inside [near_m, far_m] (and, if
    given, in the (Hd, Wd) bool ``select``, e.g. :func:`object_depth_pixels`).

    Each depth pixel is splatted as a square of the size it covers in the colour image, so the
    region has no gaps when the colour image is finer than the depth image.
    """
    if depth_mm.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth_mm.shape}")
    d = depth_mm.astype(np.float64) / 1000.0
    inside = (d >= near_m) & (d <= far_m)
    if select is not None:
        inside &= np.asarray(select, bool)
    c = calibration.color
    region = np.zeros((c.height, c.width), np.uint8)
    if not inside.any():
        return region.astype(bool)
    _, px, z = depth_pixels_in_color(d, calibration, inside)
    region[px[:, 1], px[:, 0]] = 1
    # Footprint of a depth pixel in the colour image, in colour pixels.
    scale = c.fx / calibration.depth.fx * float(np.median(z) if len(z) else 1.0) / float(np.median(d[inside]))
    k = int(np.ceil(scale)) + 1
    region = cv2.morphologyEx(region, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    return region.astype(bool)


def why_no_object_depth(depth_mm: np.ndarray, calibration: Calibration, params: dict) -> str:
    """Why a frame's depth seeds no mask, in words naming the setting or input to check: no
    valid depth at all, none in the depth range (with the range the depth does span: a unit
    mistake shows there), none left off the support plane, or in-range depth that lands outside
    the colour image (the calibration). ``params`` is the ``masks`` config section."""
    near, far = params["depth_near_m"], params["depth_far_m"]
    d = np.asarray(depth_mm, np.float64) / 1000.0
    valid = d > 0
    if not valid.any():
        return "the depth image has no valid pixel (all 0: a dropped depth frame?)"
    inside = valid & (d >= near) & (d <= far)
    lo, med, hi = np.percentile(d[valid], [1, 50, 99])
    if not inside.any():
        return (f"no depth inside masks.depth_near_m..depth_far_m = [{near:g}, {far:g}] m; this frame's valid "
                f"depth spans {lo:.3g}-{hi:.3g} m, median {med:.3g} m; check the range, and that depth is in "
                f"millimetres")
    if not len(depth_pixels_in_color(d, calibration, inside)[0]):
        return (f"the {int(inside.sum())} depth pixels inside [{near:g}, {far:g}] m all land outside the colour "
                f"image: check the calibration (depth and colour intrinsics, depth_to_color in metres)")
    if params["support_plane_tolerance_m"] > 0:
        return (f"nothing in [{near:g}, {far:g}] m is left off the support plane; lower "
                f"masks.support_plane_tolerance_m, or set it to 0 when nothing stands on a support in view")
    return f"GrabCut took none of the in-range depth's region; check masks.depth_near_m/depth_far_m = [{near:g}, {far:g}] m"


def grabcut_seeds(region: np.ndarray, sure_erode_px: int, bg_margin_px: int) -> np.ndarray:
    """(H, W) uint8 GrabCut labels (cv2.GC_*) from a bool in-range region."""
    region = ndimage.binary_fill_holes(region)
    seeds = np.full(region.shape, GC_BGD, np.uint8)
    if not region.any():
        return seeds
    disk = lambda r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))  # noqa: E731
    r8 = region.astype(np.uint8)
    near = cv2.dilate(r8, disk(bg_margin_px)) > 0 if bg_margin_px > 0 else region
    sure = cv2.erode(r8, disk(sure_erode_px)) > 0 if sure_erode_px > 0 else region
    seeds[near] = GC_PR_BGD
    seeds[region] = GC_PR_FGD
    seeds[sure] = GC_FGD
    return seeds


def grabcut_mask(color: np.ndarray, seeds: np.ndarray, iterations: int = 5,
                 max_pixels: int = 500_000, seed: int = 0) -> np.ndarray:
    """(H, W) bool foreground from GrabCut on an (H, W, 3) uint8 RGB image with seed labels.

    Returns all-False if there is no foreground seed. Deterministic for a given ``seed``
    (OpenCV's GMM initialisation uses its global RNG, which is reseeded here).
    """
    if color.shape[:2] != seeds.shape:
        raise ValueError(f"colour {color.shape[:2]} and seeds {seeds.shape} differ in size")
    if not np.isin(seeds, (GC_FGD, GC_PR_FGD)).any():
        return np.zeros(seeds.shape, bool)
    H, W = seeds.shape
    factor = 1.0
    img, lab = color, seeds
    while (H * factor) * (W * factor) > max_pixels:
        factor /= 2
    if factor < 1:
        size = (max(1, round(W * factor)), max(1, round(H * factor)))
        img = cv2.resize(color, size, interpolation=cv2.INTER_AREA)
        lab = cv2.resize(seeds, size, interpolation=cv2.INTER_NEAREST)
    cv2.setRNGSeed(seed)
    mask = lab.copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    bgr = np.ascontiguousarray(img[..., ::-1])
    if np.isin(mask, (GC_BGD, GC_PR_BGD)).any():
        cv2.grabCut(bgr, mask, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    fg = np.isin(mask, (GC_FGD, GC_PR_FGD)).astype(np.uint8)
    if factor < 1:
        fg = cv2.resize(fg.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR) >= 0.5
        fg[seeds == GC_FGD] = True
        fg[seeds == GC_BGD] = False
    fg = fg.astype(bool)
    # Keep the components that contain sure foreground; fill holes inside the object.
    lbl, n = ndimage.label(fg)
    keep = np.unique(lbl[(seeds == GC_FGD) & fg])
    keep = keep[keep > 0]
    if keep.size:
        fg = np.isin(lbl, keep)
    return ndimage.binary_fill_holes(fg)


def compute_mask(color: np.ndarray, depth_mm: np.ndarray, calibration: Calibration, params: dict,
                 seed: int = 0, info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Foreground mask of one frame: returns (mask (Hc, Wc) bool, seeds (Hc, Wc) uint8).

    ``params`` is the validated ``masks`` config section (depth_near_m, depth_far_m,
    support_plane_tolerance_m, sure_erode_px, bg_margin_px, iterations, max_pixels). ``info``, if
    given, receives the support plane (:func:`object_depth_pixels`).
    """
    near, far = params["depth_near_m"], params["depth_far_m"]
    select = object_depth_pixels(depth_mm, calibration.depth.K, near, far, params["support_plane_tolerance_m"],
                                 seed=seed, info=info)
    region = depth_region_in_color(depth_mm, calibration, near, far, select)
    seeds = grabcut_seeds(region, params["sure_erode_px"], params["bg_margin_px"])
    return grabcut_mask(color, seeds, params["iterations"], params["max_pixels"], seed), seeds


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 if both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def plane_in_color(depth_mm: np.ndarray, calibration: Calibration, plane, tolerance_m: float) -> np.ndarray:
    """(Hc, Wc) bool: colour pixels covered by depth points within ``tolerance_m`` of ``plane``
    ([nx, ny, nz, offset m, ...], depth-camera coordinates), e.g. the support plane removed."""
    d = depth_mm.astype(np.float64) / 1000.0
    P = backproject_depth(d, calibration.depth.K)
    on = (d > 0) & (np.abs(P @ np.asarray(plane[:3], np.float64) + plane[3]) <= tolerance_m)
    return depth_region_in_color(depth_mm, calibration, 0.0, np.inf, on)
