"""Evaluation scores: every method's texture slice rendered on one frame's mesh and scored with
the paper's metrics, and against ground truth; pure functions over arrays.

The metric definitions live in :mod:`stex.metrics` (``docs/metrics.md``); this module decides
which images go in and scores every method with the same code. The stage that reads the stores,
scores the chosen frames and writes the report is :mod:`stex.stages.evaluation`; the tables are
laid out by :mod:`stex.reporting`.

What it computes
----------------
- :func:`score_frame` — one frame t, one method's texture slice (W, W, 3) on the tracked mesh at
  t, rendered in the input colour camera (the depth camera moved by ``depth_to_color``):
  patch-shift PSNR, plain PSNR and SSIM against the input photo, the blur of the render and of
  the photo, all inside the (GrabCut) mask intersected with the render's silhouette; the
  coverage of the surface; and, on synthetic scenes, ground-truth scores: the texture on OUR
  tracked mesh against the TRUE appearance on the TRUE mesh, from a novel view (default: 180°
  about the vertical axis through the true object's centre) and from the input view, split into
  the regions seen / unseen by the camera at t.
- :func:`score_methods` — :func:`score_frame` for several methods' slices on one frame's mesh,
  which shares what does not depend on the texture (the rasterised mesh, the photo's blur).
- :func:`image_scores`, :func:`reference_blur`, :func:`coverage_scores`, :func:`truth_views`,
  :func:`frame_views`, :func:`method_views` — the pieces of :func:`score_frame`, for callers
  that score other images.
- :func:`vertex_motion`, :func:`summarise_frames`, :func:`dynamism_regions` — what the report
  aggregates and plots.

Masks
-----
Input-view scores use ``mask & rendered``: the GrabCut mask of the photo intersected with the
pixels the tracked mesh covers. Every method is rendered on the same geometry, so the
intersection is the same for all of them; it keeps silhouette errors of the tracking (pixels of
the object the mesh misses, rendered black) out of a score meant for the texture. The overlap
is reported (``mask_iou``). For SSIM the render is composited over the photo outside that
mask, so the windows that cross the silhouette compare the photo's background with itself
instead of with the render's black. Ground-truth scores use the true render's mask intersected
with ours (``gt_*_iou``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from stex import metrics as ev
from stex.camera import Calibration, transform_points
from stex.config import section_params
from stex.reporting import METHODS
from stex.ssim import SsimCache

__all__ = [
    "Atlas",
    "evaluation_params",
    "image_scores",
    "coverage_scores",
    "truth_views",
    "frame_views",
    "method_views",
    "reference_blur",
    "score_frame",
    "score_methods",
    "MIN_REGION_PX",
    "vertex_motion",
    "summarise_frames",
    "SUMMARY_METRICS",
    "dynamism_regions",
]


class Atlas(NamedTuple):
    """The fixed topology and UV atlas of a mesh sequence.

    faces: (F, 3) int vertex indices; texcoords: (Vt, 2) float in [0, 1]^2 (u right, v down);
    texcoord_faces: (F, 3) int indices into texcoords.
    """

    faces: np.ndarray
    texcoords: np.ndarray
    texcoord_faces: np.ndarray

    @classmethod
    def from_store(cls, store, prefix: str = "") -> "Atlas":
        """The atlas held in a store's ``{prefix}faces``, ``texcoords``, ``texcoord_faces``: the
        template store (prefix "") or a synthetic scene's true template (prefix "template/")."""
        return cls(np.asarray(store[prefix + "faces"][...], np.int64), np.asarray(store[prefix + "texcoords"][...]),
                   np.asarray(store[prefix + "texcoord_faces"][...], np.int64))


def evaluation_params(params: dict | None = None) -> dict:
    """The evaluation settings: the schema's ``evaluation`` section (stex/schema.yaml, the one
    place the defaults live) updated with ``params``; unknown keys and bad values raise
    ValueError."""
    return section_params("evaluation", params)


# --------------------------------------------------------------------------------------------
# scoring one frame
# --------------------------------------------------------------------------------------------

def _camera(calibration) -> tuple[np.ndarray, int, int, np.ndarray]:
    cal = calibration if isinstance(calibration, Calibration) else Calibration.from_dict(calibration)
    return cal.color.K, cal.color.width, cal.color.height, cal.depth_to_color


def _atlas(atlas) -> Atlas:
    a = Atlas(*atlas)
    faces = np.asarray(a.faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"atlas faces must be (F, 3), got {faces.shape}")
    if np.asarray(a.texcoord_faces).shape != faces.shape:
        raise ValueError(f"atlas texcoord_faces must have the faces' shape {faces.shape}, "
                         f"got {np.asarray(a.texcoord_faces).shape}")
    return a


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = int((a | b).sum())
    return float((a & b).sum() / u) if u else math.nan


def reference_blur(reference, mask, h_size=ev.DEFAULT_H_SIZE,
                   blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX, blur_cache=None) -> dict:
    """``blur_input`` and ``blur_input_interior`` of :func:`image_scores`: the photo's own blur
    inside ``mask`` and inside it eroded by ``blur_interior_px``, which depend on no render
    (``blur_cache``: as :func:`stex.metrics.blur`'s ``cache``)."""
    return {"blur_input": ev.blur(reference, mask, h_size=h_size, cache=blur_cache)["blur"],
            "blur_input_interior": ev.blur(reference, mask, h_size=h_size, erode_px=blur_interior_px,
                                           cache=blur_cache)["blur"]}


def image_scores(reference, test, mask, patch=ev.DEFAULT_PATCH, radius=ev.DEFAULT_RADIUS,
                 h_size=ev.DEFAULT_H_SIZE, blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX,
                 reference_scores=None, ssim_cache=None, blur_cache=None) -> dict:
    """The input-view scores of one render against one photo, inside ``mask``.

    Args:
        reference: (H, W, 3) uint8/float photo, grey levels 0..255.
        test: (H, W, 3) render of the same view, grey levels.
        mask: (H, W) bool, the scored pixels.
        patch, radius: patch-shift PSNR P and r (px). h_size: blur filter length (px).
        blur_interior_px: the mask's erosion (px) for the ``*_interior`` blur scores.
        reference_scores: :func:`reference_blur` of ``reference`` in ``mask`` with the same
            settings, when several renders are scored against one photo; None computes it.
        ssim_cache: :class:`stex.ssim.SsimCache` kept for the renders scored against this
            photo in this mask (the same scores, sooner), or None. blur_cache: the same for the
            blur's mask work (:func:`stex.metrics.blur`'s ``cache``), or None.

    Returns:
        dict ``psnr`` (patch-shift, dB), ``psnr_unshifted`` (same patches, no shift, dB),
        ``psnr_plain`` (masked PSNR over all mask pixels, dB), ``ssim`` (1; of ``test`` inside the
        mask composited over ``reference`` outside it, so windows crossing the mask's edge see
        the photo's own background on both sides), ``blur`` (of
        ``test``, 0 sharp .. 1 blurry), ``blur_input`` (of ``reference``, same mask and code),
        ``blur_interior`` / ``blur_input_interior`` (the same inside the mask eroded by
        ``blur_interior_px``: without the silhouette band where a photo mixes object and
        background),
        ``mean_shift_px``, ``n_patches``, ``n_pixels`` (mask pixels).
    """
    ref = np.asarray(reference)
    tst = np.asarray(test)
    m = np.asarray(mask, bool)
    if ref.shape != tst.shape or ref.shape[:2] != m.shape:
        raise ValueError(f"reference {ref.shape}, test {tst.shape} and mask {m.shape} differ in size")
    # SSIM windows straddle the silhouette: outside the mask they compare the photo with itself,
    # not with the render's black background, so the score is about the texture
    composite = np.where(m[..., None], tst, ref)
    ps = ev.patch_shift_psnr(ref, tst, m, patch=patch, radius=radius)
    rb = reference_scores or reference_blur(ref, m, h_size, blur_interior_px)
    return {
        "psnr": ps["psnr"],
        "psnr_unshifted": ps["psnr_unshifted"],
        "psnr_plain": ev.masked_psnr(ref, tst, m)["psnr"],
        "ssim": ev.masked_ssim(ref, composite, m, cache=ssim_cache)["ssim"],
        "blur": ev.blur(tst, m, h_size=h_size, cache=blur_cache)["blur"],
        "blur_input": rb["blur_input"],
        "blur_interior": ev.blur(tst, m, h_size=h_size, erode_px=blur_interior_px, cache=blur_cache)["blur"],
        "blur_input_interior": rb["blur_input_interior"],
        "mean_shift_px": ps["mean_shift_px"],
        "n_patches": ps["n_patches"],
        "n_pixels": int(m.sum()),
    }


def coverage_scores(face_has_texture, face_area, seen_faces=None) -> dict:
    """Surface with texture at one frame.

    Args:
        face_has_texture: (F,) bool, the faces the method textures at this frame (a label >= 0
            for ours, visible now for projection, seen in some frame for global).
        face_area: (F,) float face areas of the frame's mesh (m^2).
        seen_faces: (F,) bool, faces seen by some source frame (the most any method can
            texture from observations), or None.

    Returns:
        dict ``coverage_faces`` (fraction of faces, the paper's measure), ``coverage_area``
        (fraction of the surface area) and ``coverage_seen`` (fraction of the seen faces that
        have texture; NaN without ``seen_faces`` or when none is seen).
    """
    has = np.asarray(face_has_texture, bool)
    area = np.asarray(face_area, np.float64)
    if area.shape != has.shape or has.ndim != 1:
        raise ValueError(f"face_has_texture {has.shape} and face_area {area.shape} must both be (F,)")
    out = {"coverage_faces": float(ev.face_coverage(has)),
           "coverage_area": float(ev.face_coverage(has, area))}
    seen = None if seen_faces is None else np.asarray(seen_faces, bool)
    if seen is not None and seen.shape != has.shape:
        raise ValueError(f"seen_faces must have shape {has.shape}, got {seen.shape}")
    out["coverage_seen"] = (float(has[seen].mean()) if seen is not None and seen.any() else math.nan)
    return out


def truth_views(true_vertices, true_atlas, appearance, calibration,
                novel_angle_deg=180.0, template_vertices=None) -> dict:
    """Renders of the true appearance on the true mesh at one frame, in the input colour camera
    and in the novel view.

    Args:
        true_vertices: (V0, 3) float true vertices, depth-camera coordinates (m).
        true_atlas: :class:`Atlas` of the true mesh (the scene template's faces and texcoords).
        appearance: (W0, W0, 3) uint8 true texture at this frame, in ``true_atlas``.
        calibration: :class:`stex.camera.Calibration` (or its dict).
        novel_angle_deg: orbit angle of the novel view about the vertical (camera y) axis
            through the true mesh's centroid (deg).
        template_vertices: optional (V, 3) the true surface at this frame in the *template's*
            topology (the true vertices carried by the template's embedding), depth-camera
            coordinates (m): the methods' textures are then also scored on the true geometry.

    Returns:
        dict ``novel_transform`` (4, 4), colour-camera -> novel-view coordinates (apply it to
        every mesh compared in this view), ``input`` and ``novel``: (image (H, W, 3) float32,
        mask (H, W) bool); ``template_vertices`` as given (None if not).
    """
    K, w, h, d2c = _camera(calibration)
    a = _atlas(true_atlas)
    Vc = transform_points(d2c, np.asarray(true_vertices, np.float64))
    N = ev.novel_view(Vc, novel_angle_deg)
    return {
        "novel_transform": N,
        "input": ev.render_texture(Vc, a.faces, a.texcoords, a.texcoord_faces, appearance, K, w, h),
        "novel": ev.render_texture(transform_points(N, Vc), a.faces, a.texcoords,
                                   a.texcoord_faces, appearance, K, w, h),
        "template_vertices": None if template_vertices is None else np.asarray(template_vertices, np.float64),
    }


def frame_views(vertices, atlas, calibration, novel_transform=None, face_visible=None,
                seen_faces=None, input_view=True) -> dict:
    """One frame's mesh rasterised once for every method's texture (:func:`method_views`).

    Args:
        vertices: (V, 3) vertices at this frame (tracked, or the true surface in the template's
            topology), depth-camera coordinates (m).
        atlas, calibration: as :func:`method_views`.
        novel_transform: (4, 4) from :func:`truth_views`, or None (no novel view).
        face_visible: (F,) bool faces the camera sees at this frame, or None.
        seen_faces: (F,) bool faces some source frame saw, or None.
        input_view: False leaves the input camera's view out (only the novel view is needed).

    Returns:
        dict of :class:`stex.metrics.MeshView` ``input`` and ``novel`` (None when not asked
        for), and (H, W) bool images (None without the flags): ``input_seen`` (pixels of the
        input view on faces seen at this frame), ``novel_seen`` (the same in the novel view) and
        ``novel_ever`` (novel-view pixels on faces some source frame saw).
    """
    K, w, h, d2c = _camera(calibration)
    a = _atlas(atlas)
    Vc = transform_points(d2c, np.asarray(vertices, np.float64))
    view_in = ev.mesh_view(Vc, a.faces, a.texcoords, a.texcoord_faces, K, w, h) if input_view else None
    view_nov = None
    if novel_transform is not None:
        Vn = transform_points(np.asarray(novel_transform, np.float64), Vc)
        view_nov = ev.mesh_view(Vn, a.faces, a.texcoords, a.texcoord_faces, K, w, h)

    def seen(view, flag):
        return None if view is None or flag is None else ev.view_seen(view, flag)

    return {"input": view_in, "novel": view_nov, "input_seen": seen(view_in, face_visible),
            "novel_seen": seen(view_nov, face_visible),
            "novel_ever": seen(view_nov, None if face_visible is None else seen_faces)}


def method_views(texture, vertices, atlas, calibration, novel_transform=None,
                 face_visible=None, geometry=None) -> dict:
    """Renders of one method's texture slice on the tracked mesh.

    Args:
        texture: (W, W, 3) uint8 texture slice in ``atlas``.
        vertices: (V, 3) tracked vertices at this frame, depth-camera coordinates (m).
        atlas: :class:`Atlas` of the tracked mesh (template faces, texcoords, texcoord_faces).
        calibration: :class:`stex.camera.Calibration` (or its dict).
        novel_transform: (4, 4) from :func:`truth_views`, or None (no novel view).
        face_visible: (F,) bool faces the camera sees at this frame (projection stage), for the
            seen mask of the novel view; None -> no seen mask.
        geometry: :func:`frame_views` of these arguments, to share it between textures; None
            computes it (then ``vertices`` ... ``face_visible`` are used).

    Returns:
        dict ``input`` (image float32 (H, W, 3), mask (H, W) bool) and, with a novel transform,
        ``novel`` (image, mask) and ``novel_seen`` ((H, W) bool or None).
    """
    tex = np.asarray(texture)
    if tex.ndim != 3 or tex.shape[2] != 3:
        raise ValueError(f"texture must be (W, W, 3), got {tex.shape}")
    g = geometry or frame_views(vertices, atlas, calibration, novel_transform, face_visible)
    out = {}
    if g["input"] is not None:
        out["input"] = (ev.view_texture(g["input"], tex), g["input"].mask)
    if g["novel"] is not None:
        out["novel"] = (ev.view_texture(g["novel"], tex), g["novel"].mask)
        out["novel_seen"] = g["novel_seen"]
    return out


#: Ground-truth regions of fewer pixels than this are not scored (NaN): seen from behind, the
#: region the camera sees at t is often a few silhouette pixels, whose PSNR would enter the
#: means like a whole view's (docs/decisions/evaluation.md).
MIN_REGION_PX = 100


def _truth_region_scores(prefix, truth_img, truth_mask, rec_img, rec_mask, seen, ssim_cache=None) -> dict:
    """A render's scores against the true render in one view (``region_psnr`` with SSIM over both
    silhouettes, split by ``seen``), keys prefixed; ``ssim_cache``: a :class:`stex.ssim.SsimCache`
    for the renders compared with this true render, or None."""
    m = truth_mask & rec_mask
    region = np.zeros_like(m) if seen is None else seen
    r = ev.region_psnr(truth_img, rec_img, m, region, ssim=True, min_pixels=MIN_REGION_PX,
                       ssim_cache=ssim_cache)
    out = {f"{prefix}_{k}": r[k] for k in ("psnr_all", "psnr_seen", "psnr_unseen",
                                           "ssim_all", "ssim_seen", "ssim_unseen")}
    out[f"{prefix}_n_seen"], out[f"{prefix}_n_unseen"] = r["n_seen"], r["n_unseen"]
    out[f"{prefix}_iou"] = _iou(truth_mask, rec_mask)
    return out


def _novel_scores(prefix, truth, views, ever, ssim_cache=None) -> dict:
    """Novel-view scores of one render (``views`` of :func:`method_views`) against the true
    render: :func:`_truth_region_scores`, and, with ``ever`` (the novel view's pixels on surface
    some source frame saw, or None), the unseen region split into surface some source frame saw
    (borrowed from another frame: what the labeling decides) and surface no frame saw (filled: a
    guess for any method). ``ssim_cache``: as :func:`_truth_region_scores`."""
    out = _truth_region_scores(prefix, *truth["novel"], *views["novel"], views["novel_seen"], ssim_cache)
    if ever is not None:
        (t_img, t_mask), (r_img, r_mask) = truth["novel"], views["novel"]
        r = ev.region_psnr(t_img, r_img, t_mask & r_mask & ~views["novel_seen"], ever,
                           min_pixels=MIN_REGION_PX)
        out.update({f"{prefix}_psnr_borrowed": r["psnr_seen"], f"{prefix}_n_borrowed": r["n_seen"],
                    f"{prefix}_psnr_never_seen": r["psnr_unseen"], f"{prefix}_n_never_seen": r["n_unseen"]})
    return out


def score_frame(texture, vertices, atlas, image, mask, calibration, *, face_has_texture=None,
                seen_faces=None, face_visible=None, truth=None,
                novel_angle_deg=180.0, patch=ev.DEFAULT_PATCH,
                radius=ev.DEFAULT_RADIUS, h_size=ev.DEFAULT_H_SIZE, return_views=False,
                blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX) -> dict:
    """Score one method's texture slice at one frame.

    Args:
        texture: (W, W, 3) uint8 texture slice in ``atlas``.
        vertices: (V, 3) float tracked vertices at this frame, depth-camera coordinates (m).
        atlas: :class:`Atlas` (or a (faces, texcoords, texcoord_faces) tuple) of the tracked mesh.
        image: (Hc, Wc, 3) uint8 input colour photo of this frame.
        mask: (Hc, Wc) bool object mask of the photo (GrabCut).
        calibration: :class:`stex.camera.Calibration` (or its dict): colour camera and
            depth_to_color.
        face_has_texture: (F,) bool faces the method textures at this frame -> coverage scores.
        seen_faces: (F,) bool faces seen by some source frame (``coverage_seen``).
        face_visible: (F,) bool faces the camera sees at this frame (projection stage): the
            seen / unseen split of the ground-truth scores.
        truth: the output of :func:`truth_views` for this frame (synthetic scenes), or None.
        novel_angle_deg: only used to compute ``truth`` when a tuple (true_vertices, true_atlas,
            appearance) is passed instead.
        patch, radius, h_size, blur_interior_px: metric parameters (px), see
            :func:`image_scores`.
        return_views: also return the renders (key ``views``, see :func:`method_views`).

    Returns:
        flat dict of floats: :func:`image_scores` keys and ``mask_iou`` (render silhouette vs
        mask); with ``face_has_texture`` the :func:`coverage_scores` keys (area on this frame's
        mesh); with ``truth`` ``gt_novel_*`` and ``gt_input_*``: ``psnr_all/seen/unseen`` (dB),
        ``ssim_all/seen/unseen``, ``n_seen``, ``n_unseen`` (px), ``iou`` (true vs our
        silhouette); with ``seen_faces`` too, ``gt_novel_psnr_borrowed`` / ``_never_seen`` (dB)
        and ``gt_novel_n_borrowed`` / ``_never_seen`` (px): the novel view's region unseen at t
        split into surface some source frame saw and surface no frame saw; ``blur_truth``: the
        blur of the true appearance rendered in the input view (inside the mask, the render's and
        the true silhouette); and, when ``truth`` holds
        ``template_vertices``, the same novel-view keys with prefix ``gt_truegeom`` and the
        input-view ones (``gt_input_*``) with prefix ``gt_truegeom_input`` for the texture
        rendered on the true surface instead of the tracked one.
    """
    return score_methods({"method": texture}, vertices, atlas, image, mask, calibration,
                         face_has_texture=None if face_has_texture is None else {"method": face_has_texture},
                         seen_faces=seen_faces, face_visible=face_visible, truth=truth,
                         novel_angle_deg=novel_angle_deg, patch=patch, radius=radius, h_size=h_size,
                         return_views=return_views, blur_interior_px=blur_interior_px)["method"]


def score_methods(textures: dict, vertices, atlas, image, mask, calibration, *,
                  face_has_texture: dict | None = None, seen_faces=None, face_visible=None,
                  truth=None, novel_angle_deg=180.0, patch=ev.DEFAULT_PATCH,
                  radius=ev.DEFAULT_RADIUS, h_size=ev.DEFAULT_H_SIZE, return_views=False,
                  blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX) -> dict:
    """:func:`score_frame` of several methods' texture slices on one frame's mesh.

    Every method is rendered on the same geometry, so the mesh is rasterised once per view and
    what depends only on the photo, the mesh or the truth (the photo's and the true render's
    blur, the seen masks) is computed once; the scores equal :func:`score_frame`'s per method.

    Args:
        textures: {name: (W, W, 3) uint8 texture slice in ``atlas``}.
        face_has_texture: {name: (F,) bool} (the same names), or None.
        the rest: as :func:`score_frame`.

    Returns:
        {name: :func:`score_frame`'s dict}, in the order of ``textures``.
    """
    K, w, h, _ = _camera(calibration)
    img = np.asarray(image)
    if img.shape != (h, w, 3):
        raise ValueError(f"image must be the colour camera's ({h}, {w}, 3), got {img.shape}")
    m = np.asarray(mask, bool)
    if m.shape != (h, w):
        raise ValueError(f"mask must be ({h}, {w}), got {m.shape}")
    if face_has_texture is not None and set(face_has_texture) != set(textures):
        raise ValueError(f"face_has_texture names {sorted(face_has_texture)} differ from the "
                         f"textures' {sorted(textures)}")
    a = _atlas(atlas)
    if truth is not None and not isinstance(truth, dict):
        truth = truth_views(*truth, calibration, novel_angle_deg)
    novel_t = None if truth is None else truth["novel_transform"]
    geom = frame_views(vertices, a, calibration, novel_t, face_visible,
                       seen_faces if truth is not None else None)
    rmask = geom["input"].mask
    scored = m & rmask
    # every method's render is compared with the same photo and true renders in the same masks
    # (one geometry): the mask work of the blur and the references' side of the SSIM maps once
    blur_cache, ssim_cache = {}, SsimCache()
    photo_blur = reference_blur(img, scored, h_size, blur_interior_px, blur_cache)
    mask_iou = _iou(m, rmask)
    area = None if face_has_texture is None else ev.face_areas(vertices, a.faces)
    surface = surface_geom = same = None
    if truth is not None:
        # the sharpness a texture can have through this renderer: the true appearance rendered
        # in the same view (no sensor noise, which the Crete metric reads as sharpness)
        t_img, t_mask = truth["input"]
        t_scored = scored & t_mask
        truth_blur = {"blur_truth": ev.blur(t_img, t_scored, h_size=h_size)["blur"],
                      "blur_truth_interior": ev.blur(t_img, t_scored, h_size=h_size,
                                                     erode_px=blur_interior_px)["blur"]}
        surface = truth.get("template_vertices")
        if surface is not None:
            # the same texture on the true surface: what is left is the texture's own error
            # (the tracked mesh adds its geometric error to every method); 'given' meshes
            # without drift are the true surface already (to float32, the tracking store's
            # precision), and their renders are reused
            same = np.array_equal(np.asarray(surface, np.float32), np.asarray(vertices, np.float32))
            surface_geom = geom if same else frame_views(surface, a, calibration, novel_t, face_visible,
                                                         seen_faces)
    out = {}
    for name, texture in textures.items():
        views = method_views(texture, vertices, a, calibration, geometry=geom)
        rec = views["input"][0]
        s = image_scores(img, rec, scored, patch=patch, radius=radius, h_size=h_size,
                         blur_interior_px=blur_interior_px, reference_scores=photo_blur,
                         ssim_cache=ssim_cache, blur_cache=blur_cache)
        s["mask_iou"] = mask_iou
        if face_has_texture is not None:
            s.update(coverage_scores(face_has_texture[name], area, seen_faces))
        if truth is not None:
            s.update(_truth_region_scores("gt_input", *truth["input"], rec, rmask, geom["input_seen"],
                                          ssim_cache))
            s.update(truth_blur)
            s.update(_novel_scores("gt_novel", truth, views, geom["novel_ever"], ssim_cache))
            if surface is not None:
                on_surface = views if same else method_views(texture, surface, a, calibration,
                                                             geometry=surface_geom)
                s.update(_novel_scores("gt_truegeom", truth, on_surface, surface_geom["novel_ever"],
                                       ssim_cache))
                # the input view too: on the tracked mesh the tracker's error cancels there (a
                # texel read where the tracked mesh projects is rendered back to that pixel); on
                # the true surface a texel read from the wrong place counts against the texture
                s.update(_truth_region_scores("gt_truegeom_input", *truth["input"], *on_surface["input"],
                                              surface_geom["input_seen"], ssim_cache))
        if return_views:
            s["views"] = views
        out[name] = s
    return out


# --------------------------------------------------------------------------------------------
# aggregation
# --------------------------------------------------------------------------------------------

def vertex_motion(prev_vertices, vertices) -> float:
    """Mean vertex displacement between two frames, (V, 3) each in metres -> millimetres."""
    a = np.asarray(prev_vertices, np.float64)
    b = np.asarray(vertices, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"vertex arrays differ in shape: {a.shape} vs {b.shape}")
    return float(np.linalg.norm(b - a, axis=1).mean() * 1000.0)


#: Per-frame scores summarised (and plotted) by :func:`stex.stages.evaluation.write_evaluation`.
SUMMARY_METRICS = ("psnr", "psnr_unshifted", "psnr_plain", "ssim", "blur", "blur_input", "blur_truth",
                   "blur_interior", "blur_input_interior", "blur_truth_interior",
                   "noise_input",
                   "mask_iou", "coverage_faces", "coverage_area", "coverage_seen",
                   "gt_novel_psnr_all", "gt_novel_psnr_seen", "gt_novel_psnr_unseen",
                   "gt_novel_psnr_borrowed", "gt_novel_psnr_never_seen",
                   "gt_novel_ssim_all", "gt_novel_ssim_seen", "gt_novel_ssim_unseen",
                   "gt_input_psnr_all", "gt_input_psnr_seen", "gt_input_psnr_unseen",
                   "gt_input_ssim_all", "gt_novel_iou",
                   "gt_truegeom_psnr_unseen", "gt_truegeom_psnr_borrowed", "gt_truegeom_psnr_never_seen",
                   "gt_truegeom_ssim_unseen",
                   "gt_truegeom_input_psnr_all", "gt_truegeom_input_psnr_seen",
                   "gt_truegeom_input_psnr_unseen", "gt_truegeom_input_ssim_all",
                   "flicker", "flicker_excess", "flicker_change", "flicker_true_change")


def summarise_frames(frames: list[dict], methods=METHODS) -> dict:
    """Summaries of per-frame records (as in ``evaluation.json`` ``frames``).

    Returns ``{subset: {method: {metric: stex.metrics.summarise(...)}}}`` for the subsets
    ``all`` (every scored frame), ``source`` (frames that were sources) and ``held_out``
    (frames that were not; the projection baseline is left out there, it uses the frame's own
    photo).
    """
    subsets = {"all": frames, "source": [f for f in frames if not f["held_out"]],
               "held_out": [f for f in frames if f["held_out"]]}
    out = {}
    for name, sel in subsets.items():
        out[name] = {}
        for m in methods:
            if name == "held_out" and m == "projection":
                continue
            rows = [f["methods"][m] for f in sel if m in f["methods"]]
            out[name][m] = {k: ev.summarise([r.get(k, math.nan) for r in rows])
                            for k in SUMMARY_METRICS if any(k in r for r in rows)}
    return out


def dynamism_regions(S, face_chart, face_area, n_regions: int) -> list[tuple[int, np.ndarray]]:
    """Charts to plot in the SSIM-dynamism figure: the ``n_regions // 2`` most dynamic and the
    most static (lowest / highest mean S) among the charts with finite S in at least half the
    frames, each with its per-frame area-weighted mean S.

    Args:
        S: (T, F) float SSIM dynamism (NaN = not seen in both frames).
        face_chart: (F,) int chart of each face. face_area: (F,) float.
        n_regions: charts to return.

    Returns:
        list of (chart id, (T,) float per-frame mean S, NaN where no face of the chart is seen).
    """
    S = np.asarray(S, np.float64)
    chart = np.asarray(face_chart)
    area = np.asarray(face_area, np.float64)
    ok = np.isfinite(S)
    n_ch = int(chart.max()) + 1 if chart.size else 0
    num = np.zeros((S.shape[0], n_ch))
    den = np.zeros((S.shape[0], n_ch))
    for t in range(S.shape[0]):
        np.add.at(num[t], chart, np.where(ok[t], S[t], 0.0) * area)
        np.add.at(den[t], chart, ok[t] * area)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(den > 0, num / den, np.nan)
    n_finite = np.isfinite(mean).sum(0)
    valid = (n_finite >= 1) & (2 * n_finite >= S.shape[0])   # at least half the frames
    cand = np.flatnonzero(valid)
    if cand.size == 0:
        return []
    overall = np.nanmean(mean[:, cand], axis=0)
    order = cand[np.argsort(overall)]
    k = max(1, n_regions // 2)
    pick = list(dict.fromkeys(list(order[:k]) + list(order[::-1][:n_regions - k])))
    return [(int(c), mean[:, c]) for c in pick]


