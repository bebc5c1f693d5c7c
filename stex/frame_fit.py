"""How well a mesh fits one frame of the tracker's input, measured without ground truth: the
clipped depth difference (:func:`depth_residual`), the depth scale (:func:`depth_scale_ratio`),
the silhouette overlap (:func:`silhouette_iou`), and, before tracking starts, whether the
template fits the object at the first frame at all (:func:`template_fit_problem`).

``target`` arguments are :class:`stex.tracking.DepthTarget` (foreground depth points ``points``
(H, W, 3) metres, ``valid`` (H, W) bool, depth intrinsics ``K`` (3, 3)).
"""

from __future__ import annotations

import numpy as np

from stex.camera import transform_points
from stex.masks import mask_iou
from stex.render import rasterize, vertex_visibility

MIN_TEMPLATE_FACES = 20          # fewer faces of non-zero area cannot follow a surface
MIN_TEMPLATE_OVERLAP = 0.05      # share of the smaller of mesh and object (depth pixels) they must share
TEMPLATE_UNITS_RATIO = 5.0       # median mesh depth this many times the object's, or its inverse: wrong units


def depth_residual(vertices, faces, target: DepthTarget, clip_m: float = 0.05, union: bool = True) -> float:
    """Mean |rendered - observed| depth (m), each difference clipped at ``clip_m``: how well a
    mesh explains one depth frame. With ``union`` over the union of the mesh's and the
    foreground's pixels, a pixel covered by only one counting ``clip_m`` (silhouette included);
    otherwise over the pixels both cover."""
    H, W = target.valid.shape
    d = rasterize(vertices, faces, target.K, W, H).depth
    obs = target.points[..., 2]
    have_mesh, have_obs = d > 0, target.valid
    if not union:
        both = have_mesh & have_obs
        return float(np.minimum(np.abs(d[both] - obs[both]), clip_m).mean()) if both.any() else 0.0
    union = have_mesh | have_obs
    if not union.any():
        return 0.0
    diff = np.full(union.sum(), clip_m)
    both = (have_mesh & have_obs)[union]
    diff[both] = np.minimum(np.abs(d[union][both] - obs[union][both]), clip_m)
    return float(diff.mean())


def depth_scale_ratio(vertices, faces, target: DepthTarget, min_pixels: int = 20) -> float | None:
    """Median rendered depth over median observed depth on the pixels both the mesh and the
    foreground depth cover, or None where they share fewer than ``min_pixels``: about 1 for a mesh
    in metres in the depth camera's coordinates, 1000 for one in millimetres. The silhouette
    cannot tell (a mesh 1000 times larger and farther projects the same), the depth can."""
    H, W = target.valid.shape
    d = rasterize(vertices, faces, target.K, W, H).depth
    both = (d > 0) & target.valid
    if both.sum() < min_pixels:
        return None
    return float(np.median(d[both]) / np.median(target.points[..., 2][both]))


def silhouette_iou(vertices, faces, mask, calibration) -> float:
    """Intersection over union of the mesh's silhouette in the colour camera and ``mask``.

    vertices (V, 3) depth-camera metres, faces (F, 3), mask (Hc, Wc) bool foreground of the
    colour image. How well a tracked mesh covers the object, without any ground truth: near 1
    while the tracker follows, falling when it loses a part (:func:`stex.masks.mask_iou`).
    """
    c = calibration.color
    if mask.shape != (c.height, c.width):
        raise ValueError(f"mask is {mask.shape[1]}x{mask.shape[0]}, the colour camera {c.width}x{c.height}")
    covered = rasterize(transform_points(calibration.depth_to_color, vertices), faces, c.K, c.width, c.height).depth > 0
    return mask_iou(covered, mask)


def template_fit_problem(vertices, faces, target, reach_m: float) -> str | None:
    """What makes a template unfit to start tracking at the first frame, or None where it fits.

    Args:
        vertices: (V, 3) float the template (m, depth-camera coordinates, as the tracker takes it).
        faces: (F, 3) int.
        target: the first frame's foreground depth (see the module docstring).
        reach_m: how far (m) the tracker's rigid stage looks for the object
            (``tracking.rigid_coarse_distance_m``).

    In order: fewer than MIN_TEMPLATE_FACES faces of non-zero area; a median depth of the
    vertices TEMPLATE_UNITS_RATIO or more times the object's (or as much less: millimetres,
    centimetres, or not in the depth camera's frame); a mesh that projects to no depth pixel; one
    that shares less than MIN_TEMPLATE_OVERLAP of the smaller of its own and the object's depth
    pixels (wrong place); one whose depth differs from the object's by more than ``reach_m``
    (median over the pixels both cover: wrong place along the view). The answer is a sentence naming the
    figures. Without foreground depth at the frame there is nothing to compare: None (the
    tracking stage warns about frames without depth).
    Why: such a template is tracked without one depth correspondence and every later stage runs
    on a mesh that never touched the object.
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if len(F):
        e1, e2 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
        n_faces = int((np.linalg.norm(np.cross(e1, e2), axis=1) > 1e-12).sum())
    else:
        n_faces = 0
    if n_faces < MIN_TEMPLATE_FACES:
        return (f"it has {n_faces} face{'s' * (n_faces != 1)} of non-zero area; tracking a surface needs at least "
                f"{MIN_TEMPLATE_FACES} (a template of the object's surface has thousands)")
    if not target.valid.any():
        return None
    obs = target.points[target.valid]
    z_obs, z_mesh = float(np.median(obs[:, 2])), float(np.median(V[:, 2]))
    ratio = z_mesh / z_obs
    if z_mesh <= 0 or not 1 / TEMPLATE_UNITS_RATIO < ratio < TEMPLATE_UNITS_RATIO:
        where = (f"{ratio:.{0 if ratio >= 10 else 2}f} times as far from the depth camera as the object's depth reads"
                 if z_mesh > 0 else "behind the depth camera")
        return (f"its vertices lie {where} (median depth {z_mesh:.4g} against {z_obs:.2f} m): the template must be "
                f"in metres (millimetres give 1000, centimetres 100) and in the depth camera's coordinates")
    H, W = target.valid.shape
    raster = rasterize(V, F, target.K, W, H).depth
    covered = raster > 0
    if not covered.any():
        return "it projects to no pixel of the depth image: it lies outside the depth camera's view"
    both = int((covered & target.valid).sum())
    share = both / min(int(covered.sum()), int(target.valid.sum()))
    vis = vertex_visibility(V, F, target.K, raster)[0]
    offset = obs.mean(0) - V[vis if vis.any() else slice(None)].mean(0)
    off = (f"the object's depth lies {np.linalg.norm(offset):.2f} m from the template's camera-facing side "
           f"(x {offset[0]:+.2f}, y {offset[1]:+.2f}, z {offset[2]:+.2f} m)")
    if share < MIN_TEMPLATE_OVERLAP:
        return (f"it shares {both} depth pixels with the object ({100 * share:.1f} % of the smaller of the two, "
                f"below {100 * MIN_TEMPLATE_OVERLAP:g} %): {off}")
    # along the view, where both cover the image: a loose mask's background does not count there
    overlap = covered & target.valid
    gap = float(np.median(raster[overlap] - target.points[..., 2][overlap]))
    if abs(gap) > reach_m:
        return (f"where it overlaps the object in the depth image it lies {abs(gap):.2f} m "
                f"{'behind' if gap > 0 else 'in front of'} the object's depth (median), farther than the tracker "
                f"looks for it (tracking.rigid_coarse_distance_m {reach_m:g} m)")
    return None
