"""Projection stage: Φ and visibility of the deformed template in every colour image.

For every frame t, the tracked vertices (``tracking`` store, depth-camera coordinates) are moved
into the colour camera through ``Calibration.depth_to_color`` and projected with the colour
pinhole: Φ_t (V, 2) colour-pixel coordinates (integer = pixel centre). Texture comes from the
colour images, so visibility is decided **in the colour camera**: the mesh is rasterised there
(:func:`stex.render.rasterize`) and every vertex / face is tested against that depth map. The
texture-coordinate optimisation starts from Φ, and the tables (E_qual, candidates) read the
per-(frame, face) visibility and cosine.

Visibility rules (``params`` = the ``projection`` config section), and how they compare with the
authors' code (``Mapper4D.cpp::ConstructVertree``, see ``official_code_notes.md`` §2.2):

- **Depth test** against the colour-camera render of the mesh itself, with the tangent-plane test
  of :func:`stex.render.vertex_visibility` / :func:`stex.render.face_visibility` and tolerance
  ``depth_tol_m`` (default 1 cm) over a (2·``window_px``+1)² neighbourhood. The authors compare
  the vertex depth with the *sensor* depth at the nearest depth pixel with 5 cm. Rendering the
  tracked mesh is exact for self-occlusion, needs no depth-to-colour warp, is unaffected by depth
  holes and noise, and lets the tolerance be 1 cm instead of 5 cm (5 cm lets a fold's far side
  through). What it cannot see is occlusion by *other* objects (hands, props); the foreground mask
  below removes most of those.
- **Facing**: cosine between the surface normal (area-weighted vertex normal, or face normal) and
  the direction to the camera. ``cos_mode: view_ray`` (default) uses the ray from the point to the
  colour-camera centre — the true foreshortening of the surface in the image. ``optical_axis``
  reproduces the authors' code (normal · camera z axis; their view-ray variant is commented out
  at L306): off the image centre it over- or under-states the foreshortening by up to the ray's
  angle to the axis (±34° at the border of a 2048 px image with fx = 1500, ±45° on an Azure
  Kinect wide colour mode), so a face seen edge-on near the border can get cos ≈ 0.5 and pass the
  later θ_n = 0.3 quality test. In both modes a point must face the camera along its view ray
  (cos_view > 0, otherwise its colour is not in the image at all); the mode then decides the
  stored cosine and the ``min_cos`` threshold (default 0: any front-facing point). The stored
  cosines are given for **every** vertex/face (clipped to [0, 1]) so later stages can apply
  θ_n = 0.3 themselves.
- **Image margin**: the projection must lie at least ``margin_px`` (default 20, as the authors)
  inside the colour image: u ∈ [m, Wc-1-m], v ∈ [m, Hc-1-m]. The authors also apply it in the
  depth image; stex does not look at depth images here.
- **Foreground mask** (``use_mask``, default true): the ``masks`` store's mask, eroded by
  ``mask_erode_px`` (default 2 px; GrabCut boundaries are a few px off), must be set at the
  nearest pixel of the projection. The authors drop a (face, frame) when any corner's texture
  coordinate falls on a mask pixel < 1 (``BackgroundSubtraction``), and keep the frame at weight
  0.001 in the proxy colour; stex decides it here, once, for vertices and faces alike.
- **Faces**: a face is visible when its own test passes (front-facing face normal, cos > min_cos,
  its three corners pass the depth test against the face's plane) **and** its three vertices are
  visible — the authors' rule that the frame set of a face is the intersection of its vertices'
  sets. So every visible face has Φ and (later) ξ at all its corners.
- **Glimpsed faces** (``face_glimpsed``, stex's addition): visible, or the face's own test passes
  and its three corners project inside the margin and the mask as segmented (not eroded: on thin
  parts, a few px wide, the eroded mask keeps nothing). The vertex rule drops faces whose
  corner sits on a silhouette although the image shows the face; on a low-poly model (the Fox:
  1,051 of 2,304 faces visible in no frame) those are 3-15 % of the object's pixels in every
  input view. The labeling textures faces that no frame sees but some frame glimpses from that
  frame (:func:`stex.labeling.glimpse_sources`) instead of filling them from their neighbours.
"""

from __future__ import annotations

import cv2
import numpy as np

from stex.camera import Calibration, transform_points
from stex.config import section_params
from stex.render import face_normals, face_visibility, rasterize, vertex_normals, vertex_visibility


COS_MODES = ("view_ray", "optical_axis")


def projection_params(params: dict | None) -> dict:
    p = section_params("projection", params)
    if p["cos_mode"] not in COS_MODES:
        raise ValueError(f"projection.cos_mode must be one of {COS_MODES}, got {p['cos_mode']!r}")
    return p


def erode_mask(mask: np.ndarray, erode_px: int) -> np.ndarray:
    """(H, W) bool mask eroded by ``erode_px`` pixels (a disc; 0 = unchanged)."""
    mask = np.asarray(mask, dtype=bool)
    if erode_px <= 0:
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
    return cv2.erode(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def project_frame(vertices_depth, faces, calibration: Calibration, params: dict | None = None,
                  mask: np.ndarray | None = None) -> dict:
    """Project one frame's mesh into the colour image and decide visibility there.

    Args:
        vertices_depth: (V, 3) float vertex positions in **depth-camera** coordinates, metres.
        faces: (F, 3) int triangles, counter-clockwise seen from outside.
        calibration: the sensor's :class:`~stex.camera.Calibration` (colour intrinsics and
            ``depth_to_color``).
        params: the ``projection`` config section (missing keys take the schema defaults):
            ``depth_tol_m`` (m), ``window_px`` (px), ``tangent_plane``, ``min_cos``,
            ``cos_mode`` ('view_ray' | 'optical_axis'), ``margin_px`` (px), ``use_mask``,
            ``mask_erode_px`` (px), ``near_m`` (m). See the module docstring.
        mask: (Hc, Wc) bool foreground mask of this frame at colour resolution, **not yet
            eroded**; used when ``params['use_mask']`` (required then).

    Returns:
        dict with
        ``phi`` (V, 2) float32 colour-pixel coordinates (u = column, v = row; integer = pixel
        centre), for every vertex;
        ``vertex_visible`` (V,) bool; ``vertex_cos`` (V,) float32 in [0, 1];
        ``face_visible`` (F,) bool; ``face_cos`` (F,) float32 in [0, 1] — cosines per
        ``cos_mode`` for every vertex/face whatever its visibility (0 when back-facing);
        ``face_glimpsed`` (F,) bool — ``face_visible``, or the face's own test passes and its
        corners project inside the margin and the (uneroded) mask (module docstring).

    Raises:
        ValueError: a vertex at or behind ``near_m`` in the colour camera (it has no
            projection), a missing mask, or a mask of the wrong size.
    """
    p = projection_params(params)
    Kc = calibration.color.K
    Wc, Hc = calibration.color.width, calibration.color.height
    Vd = np.asarray(vertices_depth, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if Vd.ndim != 2 or Vd.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {Vd.shape}")
    Xc = transform_points(calibration.depth_to_color, Vd).astype(np.float64)
    z = Xc[:, 2]
    bad = ~(z > p["near_m"])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"vertex {i} is at z = {z[i]:.4f} m in the colour camera (<= near_m "
                         f"{p['near_m']} m; {int(bad.sum())} such vertices): it has no projection")
    u = (Kc[0, 0] * Xc[:, 0] + Kc[0, 1] * Xc[:, 1]) / z + Kc[0, 2]
    v = (Kc[1, 0] * Xc[:, 0] + Kc[1, 1] * Xc[:, 1]) / z + Kc[1, 2]
    phi = np.stack([u, v], axis=1)

    raster = rasterize(Xc, F, Kc, Wc, Hc, near=p["near_m"])
    tol, win, plane = float(p["depth_tol_m"]), int(p["window_px"]), bool(p["tangent_plane"])
    vvis, vcos = vertex_visibility(Xc, F, Kc, raster.depth, depth_tol=tol, window=win,
                                   tangent_plane=plane)
    # face_visibility's own min_cos is on the view-ray cosine; the threshold is applied below
    fvis, fcos = face_visibility(Xc, F, Kc, raster.depth, depth_tol=tol, min_cos=0.0,
                                 window=win, tangent_plane=plane)
    if p["cos_mode"] == "optical_axis":
        # the authors' weight: normal . (0, 0, -1) in the colour camera (normals point outward,
        # the camera looks along +z); still only for points facing the camera along their ray
        vcos = np.where(vcos > 0, np.clip(-vertex_normals(Xc, F)[:, 2], 0.0, 1.0), 0.0).astype(np.float32)
        fcos = np.where(fcos > 0, np.clip(-face_normals(Xc, F)[:, 2], 0.0, 1.0), 0.0).astype(np.float32)
    min_cos = float(p["min_cos"])
    vvis &= vcos > min_cos
    fvis &= fcos > min_cos

    m = float(p["margin_px"])
    inside = (u >= m) & (u <= Wc - 1 - m) & (v >= m) & (v <= Hc - 1 - m)
    vvis &= inside
    # face_glimpsed: the face's own test with its corners inside the margin and the mask as
    # segmented — faces on a silhouette fail the vertex rule below although the image shows them
    own = fvis & inside[F].all(axis=1)
    if p["use_mask"]:
        if mask is None:
            raise ValueError("projection.use_mask is set but no mask was given")
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (Hc, Wc):
            raise ValueError(f"mask has shape {mask.shape}, the colour image is {(Hc, Wc)}")
        fg = erode_mask(mask, int(p["mask_erode_px"]))
        c = np.clip(np.floor(u + 0.5).astype(np.int64), 0, Wc - 1)
        r = np.clip(np.floor(v + 0.5).astype(np.int64), 0, Hc - 1)
        vvis &= fg[r, c]
        # not eroded: on thin parts (the Fox's legs, a few px wide) that keeps nothing
        own &= mask[r, c][F].all(axis=1)
    # a face's frame set is the intersection of its vertices' sets (the authors' rule)
    if F.shape[0]:
        fvis &= vvis[F].all(axis=1)
    return {
        "phi": phi.astype(np.float32),
        "vertex_visible": vvis,
        "vertex_cos": vcos.astype(np.float32),
        "face_visible": fvis,
        "face_cos": fcos.astype(np.float32),
        "face_glimpsed": own | fvis,
    }
