"""Evaluation stage: score reconstructions with the paper's metrics and against ground truth.

The metric definitions live in :mod:`stex.metrics` (``docs/metrics.md``); this module decides
which images go in, scores every method with the same code, and writes the tables, plots and
pictures of the report.

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
- :func:`write_evaluation` — the stage: reads the Kim 2019 global texture over the source
  frames (the ``global_texture`` store, :func:`stex.stages.global_texture.write_global_texture`), builds the
  naive per-frame projection baseline, scores ``ours`` (corrected volume),
  ``ours_uncorrected`` (volume), ``global`` and ``projection`` on the chosen frames, temporal
  flicker in borrowed regions, and writes ``evaluation.json``, one CSV per table, ``tables.rst``
  and PNG figures into a folder.
- :func:`score_frames` — the scoring of :func:`write_evaluation` for one frame block, into a
  JSON file of per-frame records, so that the workflow scores blocks in separate jobs (as soon
  as each block's slices exist) and ``write_evaluation(records_paths=...)`` merges them.
- :func:`evaluate_results` — :func:`write_evaluation` of a finished run's folder with other
  methods' texture slices (:class:`TextureSlices`: PNG files or a texture store in the run's
  atlas, or in another UV layout carried into it by :mod:`stex.resample`) scored beside ours by
  the same code (``stex evaluate``).
- :func:`rst_tables` — reStructuredText tables laid out like the paper's Table 3 (reconstruction
  error and blur per method), coverage, ground truth and timing, over one or several scenes.

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

Held-out protocol
-----------------
With ``data_term.source_stride`` = k only every k-th frame may texture anything (attr
``source_frames`` of the tables stores); every frame is still a target. Frames that are not
sources are scored as ``held_out``: their own photo was not used by ``ours`` nor by ``global``
(built from the source frames only by the ``global_texture`` stage, which takes the same
``data_term.source_stride``; its attr ``source_frames`` is checked against the tables'). The naive
``projection`` baseline of a held-out frame is its own photo, so it is left out of the held-out
summaries.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np

from stex import metrics as ev
from stex.io import library_versions, move_into_place, partial_path, short_ids, write_json
from stex.camera import Calibration, transform_points
from stex.config import RESERVED_METHOD_NAMES, scoring_settings
from stex.preview import pyplot

log = logging.getLogger("stex.evaluation")

__all__ = [
    "Atlas",
    "METHODS",
    "METHOD_NAMES",
    "method_name",
    "TextureSlices",
    "check_replaceable",
    "evaluation_params",
    "image_scores",
    "coverage_scores",
    "truth_views",
    "frame_views",
    "method_views",
    "reference_blur",
    "score_frame",
    "score_methods",
    "vertex_motion",
    "summarise_frames",
    "SUMMARY_METRICS",
    "table_rows",
    "timing_rows",
    "rst_tables",
    "dynamism_regions",
    "score_frames",
    "write_evaluation",
    "evaluate_results",
    "nan_for_none",
]

#: Methods scored by :func:`write_evaluation`, in table order.
METHODS = ("ours", "ours_uncorrected", "global", "projection")
#: Their names in tables and plots.
METHOD_NAMES = {"input": "Input images", "ours": "Ours", "ours_uncorrected": "Ours, uncorrected",
                "global": "Kim et al. 2019 (global)", "projection": "Per-frame projection"}


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


# the authors' texture volume files (TextureMappingNonRigid, ColorCorrection), in preference order
AUTHORS_SLICE_NAMES = ("Smooth_{frame:06d}.png", "Frame_{frame:06d}.png")


class TextureSlices:
    """Another method's texture slices, to score beside ours in the run's atlas.

    ``path`` is either a folder of PNG files ``texture_{frame:05d}.png``
    (:data:`stex.export.PNG_SLICE_NAME`, what ``stex export --what png`` writes; 8-bit RGB, one
    per frame id; the authors' ``Smooth_{frame:06d}.png``, else ``Frame_{frame:06d}.png``, as
    their code writes into ``atlas/<atlas_path>/video/``) or a stex texture store: a ``corrected``
    or ``volume`` zarr store, or a folder of such block stores (e.g. another run's
    ``corrected/``). Black texels (0, 0, 0) count as "no texture" for the coverage scores.

    Slices in the run's atlas are read as they are. Slices in another UV layout need
    ``uv_mesh``: that layout's mesh (OBJ with ``vt``, or glTF), in the run's template
    coordinates; :meth:`into_atlas` then carries every slice into the run's atlas
    (:mod:`stex.resample`).
    """

    def __init__(self, path, uv_mesh=None):
        from stex.export import PNG_SLICE_NAME
        from stex.io import FrameSequence, StoreError

        self.path = Path(path)
        if not self.path.exists():
            raise StoreError(f"{self.path}: no such texture folder or store")
        self.uv_mesh = None if uv_mesh is None else Path(uv_mesh)
        if self.uv_mesh is not None and not self.uv_mesh.is_file():
            raise StoreError(f"{self.uv_mesh}: no such mesh file (the UV layout of {self.path})")
        self.transfer = None
        is_store = any((self.path / f).exists() for f in (".zgroup", ".zattrs", "zarr.json"))
        stores = [self.path] if is_store else sorted(self.path.glob("block_*.zarr"))
        self._seq = None
        if stores:
            import zarr
            kind = zarr.open_group(str(stores[0]), mode="r").attrs.get("stex_artifact")
            if kind not in ("corrected", "volume"):
                raise StoreError(f"{stores[0]}: expected a 'corrected' or 'volume' store, found {kind!r}")
            self._seq = FrameSequence([str(x) for x in stores], kind)
            self.frame_ids = [int(i) for i in self._seq.frame_ids]
        else:
            # stex's names, else the authors' texture volume (atlas/<atlas_path>/video/):
            # Smooth_%06d.png (colour-corrected, what their viewer shows), else Frame_%06d.png
            for name in (PNG_SLICE_NAME, *AUTHORS_SLICE_NAMES):
                head, tail = name.split("{frame:")[0], ".png"
                found = {int(f.name[len(head):-len(tail)]): f for f in self.path.glob(f"{head}*{tail}")
                         if f.name[len(head):-len(tail)].isdigit()}
                if found:
                    break
            self._name = name
            if not found:
                raise StoreError(f"{self.path}: no texture_<frame>.png files (nor the authors' Smooth_<frame>.png "
                                 f"or Frame_<frame>.png) and no block_*.zarr stores")
            self._files = found
            self.frame_ids = sorted(found)

    def into_atlas(self, template, template_path="the run's template") -> None:
        """Carry the slices from ``uv_mesh``'s layout into the atlas of ``template`` (an open
        ``template`` store, at ``template_path``) on every :meth:`read`. Without ``uv_mesh`` the
        slices must be in that atlas: stex stores that record another one raise ValueError."""
        from stex.readers.meshes import load_mesh
        from stex.resample import atlas_transfer
        from stex.stages.template import check_atlas

        if self.uv_mesh is None:
            if self._seq is not None:
                try:
                    check_atlas(zip(self._seq.paths, self._seq.groups), template, template_path)
                except ValueError as exc:
                    raise ValueError(f"{exc}; slices in another UV layout need that layout's mesh "
                                     f"(--uv-mesh NAME=MESH, or other_methods' uv_mesh)") from None
            return
        mesh = load_mesh(self.uv_mesh)
        self.transfer = atlas_transfer(
            template["texel/face_id"][...], template["texel/bary"][...], template["vertices"][...],
            template["faces"][...], mesh.vertices, mesh.faces, mesh.texcoords, mesh.texcoord_faces,
            gutter_px=int(template.attrs.get("gutter_px", 0)), where=str(self.uv_mesh))

    def read(self, frame_id: int) -> np.ndarray:
        """(W, W, 3) uint8 slice of ``frame_id`` (in the run's atlas once :meth:`into_atlas` ran)."""
        from stex.io import StoreError

        if self.uv_mesh is not None and self.transfer is None:
            raise RuntimeError(f"{self.path}: slices in the layout of {self.uv_mesh}: call into_atlas first")
        if self._seq is not None:
            tex = np.asarray(self._seq.read("texture", frame_id), np.uint8)
        else:
            from PIL import Image
            f = self._files.get(int(frame_id))
            if f is None:
                raise StoreError(f"{self.path}: no {self._name.format(frame=int(frame_id))}")
            try:
                with Image.open(f) as im:
                    if im.mode != "RGB":
                        raise StoreError(f"{f}: an 8-bit RGB PNG is needed, found mode {im.mode}")
                    tex = np.asarray(im)
            except OSError as exc:  # truncated or not an image: PIL's message does not name the file
                raise StoreError(f"{f}: cannot read the image ({exc})") from None
        if self.transfer is not None:
            try:
                tex = self.transfer.apply(tex)
            except ValueError as exc:
                raise ValueError(f"{self.path}, frame {frame_id}: {exc}") from exc
        return tex


def _other_methods(others) -> dict:
    """``{name: TextureSlices}`` of the setting ``other_methods``, names checked."""
    out = {}
    from stex.config import other_method_paths

    for name, (path, uv_mesh) in other_method_paths(others).items():
        if not re.fullmatch(r"[a-z][a-z0-9_]*", str(name)) or name in RESERVED_METHOD_NAMES:
            raise ValueError(f"method name {name!r}: use lower-case letters, digits and '_', "
                             f"not one of {', '.join(RESERVED_METHOD_NAMES)}")
        out[name] = TextureSlices(path, uv_mesh)
    return out


def method_name(method: str) -> str:
    """The name tables and figures show for a method (an other method's own name)."""
    return METHOD_NAMES.get(method, method)


def evaluation_params(params: dict | None = None) -> dict:
    """The evaluation settings: the schema's ``evaluation`` section (stex/schema.yaml, the one
    place the defaults live) updated with ``params``; unknown keys and bad values raise
    ValueError."""
    from stex.config import section_params

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
                   blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX) -> dict:
    """``blur_input`` and ``blur_input_interior`` of :func:`image_scores`: the photo's own blur
    inside ``mask`` and inside it eroded by ``blur_interior_px``, which depend on no render."""
    return {"blur_input": ev.blur(reference, mask, h_size=h_size)["blur"],
            "blur_input_interior": ev.blur(reference, mask, h_size=h_size,
                                           erode_px=blur_interior_px)["blur"]}


def image_scores(reference, test, mask, patch=ev.DEFAULT_PATCH, radius=ev.DEFAULT_RADIUS,
                 h_size=ev.DEFAULT_H_SIZE, blur_interior_px=ev.DEFAULT_BLUR_INTERIOR_PX,
                 reference_scores=None) -> dict:
    """The input-view scores of one render against one photo, inside ``mask``.

    Args:
        reference: (H, W, 3) uint8/float photo, grey levels 0..255.
        test: (H, W, 3) render of the same view, grey levels.
        mask: (H, W) bool, the scored pixels.
        patch, radius: patch-shift PSNR P and r (px). h_size: blur filter length (px).
        blur_interior_px: the mask's erosion (px) for the ``*_interior`` blur scores.
        reference_scores: :func:`reference_blur` of ``reference`` in ``mask`` with the same
            settings, when several renders are scored against one photo; None computes it.

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
        "ssim": ev.masked_ssim(ref, composite, m)["ssim"],
        "blur": ev.blur(tst, m, h_size=h_size)["blur"],
        "blur_input": rb["blur_input"],
        "blur_interior": ev.blur(tst, m, h_size=h_size, erode_px=blur_interior_px)["blur"],
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
#: region the camera sees at t is often a few silhouette pixels (the Fox: 1-5 px at 5 of 40
#: frames), and their PSNR entered the means like a whole view's.
MIN_REGION_PX = 100


def _truth_region_scores(prefix, truth_img, truth_mask, rec_img, rec_mask, seen) -> dict:
    m = truth_mask & rec_mask
    region = np.zeros_like(m) if seen is None else seen
    r = ev.region_psnr(truth_img, rec_img, m, region, ssim=True, min_pixels=MIN_REGION_PX)
    out = {f"{prefix}_{k}": r[k] for k in ("psnr_all", "psnr_seen", "psnr_unseen",
                                           "ssim_all", "ssim_seen", "ssim_unseen")}
    out[f"{prefix}_n_seen"], out[f"{prefix}_n_unseen"] = r["n_seen"], r["n_unseen"]
    out[f"{prefix}_iou"] = _iou(truth_mask, rec_mask)
    return out


def _novel_scores(prefix, truth, views, ever) -> dict:
    """Novel-view scores of one render (``views`` of :func:`method_views`) against the true
    render: :func:`_truth_region_scores`, and, with ``ever`` (the novel view's pixels on surface
    some source frame saw, or None), the unseen region split into surface some source frame saw
    (borrowed from another frame: what the labeling decides) and surface no frame saw (filled: a
    guess for any method)."""
    out = _truth_region_scores(prefix, *truth["novel"], *views["novel"], views["novel_seen"])
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
    photo_blur = reference_blur(img, scored, h_size, blur_interior_px)
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
                         blur_interior_px=blur_interior_px, reference_scores=photo_blur)
        s["mask_iou"] = mask_iou
        if face_has_texture is not None:
            s.update(coverage_scores(face_has_texture[name], area, seen_faces))
        if truth is not None:
            s.update(_truth_region_scores("gt_input", *truth["input"], rec, rmask, geom["input_seen"]))
            s.update(truth_blur)
            s.update(_novel_scores("gt_novel", truth, views, geom["novel_ever"]))
            if surface is not None:
                on_surface = views if same else method_views(texture, surface, a, calibration,
                                                             geometry=surface_geom)
                s.update(_novel_scores("gt_truegeom", truth, on_surface, surface_geom["novel_ever"]))
                # the input view too: on the tracked mesh the tracker's error cancels there (a
                # texel read where the tracked mesh projects is rendered back to that pixel); on
                # the true surface a texel read from the wrong place counts against the texture
                s.update(_truth_region_scores("gt_truegeom_input", *truth["input"], *on_surface["input"],
                                              surface_geom["input_seen"]))
        if return_views:
            s["views"] = views
        out[name] = s
    return out


# --------------------------------------------------------------------------------------------
# aggregation and tables
# --------------------------------------------------------------------------------------------

def vertex_motion(prev_vertices, vertices) -> float:
    """Mean vertex displacement between two frames, (V, 3) each in metres -> millimetres."""
    a = np.asarray(prev_vertices, np.float64)
    b = np.asarray(vertices, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"vertex arrays differ in shape: {a.shape} vs {b.shape}")
    return float(np.linalg.norm(b - a, axis=1).mean() * 1000.0)


#: Per-frame scores summarised (and plotted) by :func:`write_evaluation`.
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
                   "flicker", "flicker_excess")


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


def _fmt(x, digits=2, scale=1.0):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x * scale:.{digits}f}"


def _grid(header: list[str], rows: list[list[str]]) -> str:
    """A reStructuredText grid table."""
    cols = list(zip(*([header] + rows)))
    widths = [max(len(c) for c in col) for col in cols]
    line = "+" + "+".join("-" * (w + 2) for w in widths) + "+"
    head = "+" + "+".join("=" * (w + 2) for w in widths) + "+"

    def row(cells):
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    return "\n".join([line, row(header), head] + [x for r in rows for x in (row(r), line)]) + "\n"


def _mean(summary, subset, method, metric):
    try:
        return summary[subset][method][metric]["mean"]
    except KeyError:
        return math.nan


def table_rows(summaries: dict) -> dict:
    """The paper-style tables as lists of rows (header first) over scenes ``{scene: summary}``,
    where a summary is ``evaluation.json``'s ``summary`` (plus its ``held_out_label`` and
    ``blur_interior_px``).

    Returns ``{table name: [header, row, ...]}`` for ``reconstruction``, ``coverage`` and
    ``ground_truth`` (the last only when some scene has ground truth).
    """
    scenes = list(summaries)
    rec = [["Metric", "Method"] + scenes]
    # the pipeline's methods, then other methods scored beside them (stex evaluate --texture)
    others = list(dict.fromkeys(m for s in scenes for m in summaries[s].get("all", {})
                                if m not in METHODS))
    methods = list(METHODS) + others

    def add(table, label, method, subset, metric, digits=2, scale=1.0, name=None, count=False):
        vals = [_mean(summaries[s], subset, method, metric) for s in scenes]
        if all(not math.isfinite(v) for v in vals):
            return
        first = "" if any(r[0] == label for r in table[1:]) else label   # group label once
        cells = [_fmt(v, digits, scale) for v in vals]
        if count:  # a region absent from most frames (e.g. seen at t, from behind): say over how many
            for k, s in enumerate(scenes):
                got = summaries[s].get(subset, {}).get(method, {}).get(metric, {})
                if math.isfinite(vals[k]) and got.get("n", 0) < got.get("n_total", 0):
                    cells[k] += f" ({got['n']} of {got['n_total']} frames)"
        table.append([first, name or method_name(method)] + cells)

    for m in methods:
        add(rec, "PSNR, dB (every frame)", m, "all", "psnr")
    for s in scenes:
        if summaries[s].get("n_held_out", 0):
            for m in ["global", "ours", "ours_uncorrected"] + others:
                label = summaries[s].get("held_out_label", "")
                add(rec, "PSNR, dB (held-out frames)", m, "held_out", "psnr",
                    name=method_name(m) + (f" {label}" if m in ("ours", "ours_uncorrected") else ""))
            break
    for m in methods:
        add(rec, "Plain PSNR, dB (every frame)", m, "all", "psnr_plain")
    for m in methods:
        add(rec, "SSIM (every frame)", m, "all", "ssim", digits=4)
    add(rec, "Blurriness (Crete et al.)", "ours", "all", "blur_input", digits=4, name=METHOD_NAMES["input"])
    add(rec, "Blurriness (Crete et al.)", "ours", "all", "blur_truth", digits=4,
        name="true appearance, rendered")
    for m in ["global", "ours", "ours_uncorrected", "projection"] + others:
        add(rec, "Blurriness (Crete et al.)", m, "all", "blur", digits=4)
    # the same without the silhouette band, where a photo mixes object and background
    bands = sorted({summaries[s].get("blur_interior_px") for s in scenes} - {None})
    inner = ("Blurriness, object interior (mask eroded by "
             + " / ".join(str(b) for b in bands) + " px)")
    add(rec, inner, "ours", "all", "blur_input_interior", digits=4, name=METHOD_NAMES["input"])
    add(rec, inner, "ours", "all", "blur_truth_interior", digits=4, name="true appearance, rendered")
    for m in ["global", "ours", "ours_uncorrected", "projection"] + others:
        add(rec, inner, m, "all", "blur_interior", digits=4)
    # the blur metric reads noise as sharpness: how noisy the inputs are belongs beside it
    add(rec, "Noise, grey levels (Immerkær)", "ours", "all", "noise_input", digits=2,
        name=METHOD_NAMES["input"])

    cov = [["Coverage (mean over frames)", "Method"] + scenes]
    for metric, label in (("coverage_faces", "faces, %"), ("coverage_area", "surface area, %"),
                          ("coverage_seen", "of the faces seen by some frame, %")):
        for m in methods:
            add(cov, label, m, "all", metric, digits=1, scale=100.0)
    out = {"reconstruction": rec, "coverage": cov}

    gt = [["Ground truth (novel view unless stated)", "Method"] + scenes]
    for metric, label, digits in (("gt_novel_psnr_all", "PSNR, dB, whole object", 2),
                                  ("gt_novel_psnr_seen", "PSNR, dB, seen at t", 2),
                                  ("gt_novel_psnr_unseen", "PSNR, dB, unseen at t", 2),
                                  ("gt_novel_psnr_borrowed", "PSNR, dB, unseen at t, seen by another frame", 2),
                                  ("gt_novel_psnr_never_seen", "PSNR, dB, never seen", 2),
                                  ("gt_novel_ssim_unseen", "SSIM, unseen at t", 4),
                                  ("gt_input_psnr_all", "PSNR, dB, input view", 2),
                                  ("gt_input_psnr_seen", "PSNR, dB, input view, seen at t", 2),
                                  ("gt_input_psnr_unseen", "PSNR, dB, input view, unseen at t", 2),
                                  ("gt_truegeom_psnr_unseen", "on the true surface: PSNR, dB, unseen at t", 2),
                                  ("gt_truegeom_psnr_borrowed", "on the true surface: PSNR, dB, unseen at t, seen by another frame", 2),
                                  ("gt_truegeom_psnr_never_seen", "on the true surface: PSNR, dB, never seen", 2),
                                  ("gt_truegeom_input_psnr_all", "on the true surface: PSNR, dB, input view", 2),
                                  ("gt_truegeom_input_psnr_seen", "on the true surface: PSNR, dB, input view, seen at t", 2),
                                  ("gt_truegeom_input_psnr_unseen", "on the true surface: PSNR, dB, input view, unseen at t", 2),
                                  ("flicker", "flicker in borrowed regions, grey levels", 2)):
        for m in methods:
            add(gt, label, m, "all", metric, digits=digits, count=True)
    if len(gt) > 1:
        out["ground_truth"] = gt
    return out


def timing_rows(timing: dict) -> list[list[str]]:
    """Rows (header first) of the timing table from ``{stage: seconds}`` or
    ``{scene: {stage: seconds}}``."""
    if timing and all(isinstance(v, dict) for v in timing.values()):
        scenes = list(timing)
        stages = list(dict.fromkeys(k for v in timing.values() for k in v))
    else:
        scenes, stages, timing = ["time"], list(timing or {}), {"time": dict(timing or {})}
    rows = [["Stage"] + [f"{s} (min)" for s in scenes]]
    for st in stages:
        rows.append([st] + [_fmt(timing[s].get(st, math.nan), 2, 1 / 60) for s in scenes])
    return rows


def sampling_rows(steps) -> list[list[str]]:
    """Rows (header first) of the paper's sampling table from :func:`stex.texcoords.sampling_table`'s
    rows of one run (a list), or of several runs (``{run: rows}``: a row per run and measure, and
    the error ratio averaged over the runs, as the paper averages its datasets): per key-frame
    sampling 1/n, the error ratio (final all-frame Eq. 1 energy over that with every frame a key
    frame), the key frames, the stage time and the speed-up."""
    runs = steps if isinstance(steps, dict) else {"": steps}
    order = sorted({int(r["step"]) for rows in runs.values() for r in rows})
    rows = [["Texture-coordinate optimisation"] + [f"1/{n}" for n in order]]

    def row(label, rs, key, digits):
        by = {int(r["step"]): r for r in rs}
        return [label] + [str(by[n][key]) if digits is None and n in by else
                          _fmt(by[n][key] if n in by else math.nan, digits) for n in order]

    for name, rs in runs.items():
        prefix = f"{name}: " if name else ""
        rows.append(row(prefix + "error ratio", rs, "error_ratio", 4))
        rows.append(row(prefix + "key frames", rs, "keyframes", None))
        rows.append(row(prefix + "stage time, s", rs, "seconds", 1))
        rows.append(row(prefix + "speed-up", rs, "speedup", 2))
    if len(runs) > 1:
        mean = [float(np.nanmean([next((r["error_ratio"] for r in rs if int(r["step"]) == n), math.nan)
                                  for rs in runs.values()])) for n in order]
        rows.append(["mean error ratio over the runs"] + [_fmt(v, 4) for v in mean])
    return rows


def rst_tables(summaries: dict, timing: dict | None = None, sampling=None) -> str:
    """reStructuredText (no HTML) tables like the paper's, over scenes ``{scene: summary}``.

    Sections: reconstruction error and blur per method (the paper's Table 3: PSNR every frame,
    PSNR on held-out frames, blur), coverage, ground truth (synthetic scenes) and timing per
    stage (``{stage: seconds}`` or ``{scene: {stage: seconds}}``, shown in minutes as the
    paper's Table 1), and the sampling table of one run or several (:func:`sampling_rows`).
    """
    titles = {"reconstruction": "Texture reconstruction error and blurriness",
              "coverage": "Coverage",
              "ground_truth": "Ground truth (synthetic scenes)",
              "timing": "Computation time",
              "sampling": "Texture-coordinate optimisation: key-frame sampling"}
    notes = {
        "reconstruction": "PSNR inside the object mask between input photos and renders of the "
                          "texture on the tracked mesh; the patch-shift PSNR translates 32 x 32 "
                          "patches by up to 4 px (docs/metrics.md). Blur: Crete et al. 2007 "
                          "(skimage, h_size 11), smaller is sharper; 'object interior' "
                          "leaves out a band along the silhouette, where a photo's pixels mix "
                          "the object with the background.",
        "coverage": "Faces (or area) with texture per frame, averaged over the scored frames.",
        "ground_truth": "Renders of the texture on our tracked mesh against the true appearance "
                        "on the true mesh, from the opposite side (novel view), split into the "
                        "surface the camera sees at t and the rest. 'On the true surface': the "
                        "same texture rendered on the true geometry (the template carried onto "
                        "the true mesh), so that only the texture's own error remains; in the "
                        "input view the tracked mesh forgives a frame's own texels the tracker's "
                        "error at that frame (they come back to the pixels they were read from), "
                        "the true surface does not.",
        "timing": "Wall time per stage.",
        "sampling": "The texture-coordinate stage run with key frames every n-th frame (1/n) and "
                    "the displacements interpolated between them, then refined over all frames "
                    "(Kim et al. 2021 §4). Error ratio: the final all-frame Eq. 1 energy divided "
                    "by that with every frame a key frame (1/1). The runs ran one after another "
                    "in one job (rule texcoords_sampling).",
    }
    tabs = table_rows(summaries)
    if timing:
        tabs["timing"] = timing_rows(timing)
    if sampling:
        tabs["sampling"] = sampling_rows(sampling)
    parts = []
    for name, rows in tabs.items():
        t = titles[name]
        parts.append(f"{t}\n{'-' * len(t)}\n\n{notes[name]}\n\n{_grid(rows[0], rows[1:])}")
    return "\n".join(parts)


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------

def _finite_or_none(x):
    if isinstance(x, dict):
        return {str(k): _finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _check_frames(name, path, ids, expected, needed=None):
    """A store's frames: exactly the scene's, or (``needed`` given) at least those."""
    if needed is None:
        if list(ids) != list(expected):
            raise ValueError(f"{name} store {path} holds frames {short_ids(ids)}, the scene has "
                             f"{short_ids(expected)}")
        return
    missing = sorted(set(needed) - set(ids))
    if missing or not set(ids) <= set(expected):
        raise ValueError(f"{name} store {path} holds frames {short_ids(ids)}; frames "
                         f"{short_ids(missing or sorted(set(ids) - set(expected)))} "
                         f"{'are needed' if missing else 'are not frames of the scene'}")


def _crop_box(masks, pad=4):
    m = np.zeros_like(masks[0])
    for x in masks:
        m |= x
    if not m.any():
        return 0, m.shape[0], 0, m.shape[1]
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return (max(0, rows[0] - pad), min(m.shape[0], rows[-1] + 1 + pad),
            max(0, cols[0] - pad), min(m.shape[1], cols[-1] + 1 + pad))


class _Inputs:
    """The stores of an evaluation, opened and checked, and what scoring one frame reads.

    ``block`` ([start, stop) sequence positions) keeps the frames to score inside a frame
    block; the frame-block stores then need to hold only those frames (and, with truth, each
    one's predecessor, for the flicker). Without it they must hold every frame of the scene.
    """

    def __init__(self, scene_path, frames_paths, masks_paths, template_path, tracking_path,
                 projection_path, labels_path, volume_paths, corrected_paths, params, *,
                 global_texture_path, truth_paths, coords_path, data_term_paths, frames, block):
        from stex.io import FrameSequence, StoreError, open_store
        from stex.stages.observations import open_coordinates
        from stex.stages.template import check_atlas
        from stex.sampling import TexelSampler

        self.p = p = evaluation_params(params)
        self.scene_path, self.template_path = scene_path, template_path
        scene = open_store(scene_path, "scene")
        self.ids = ids = [int(i) for i in scene.attrs["frame_ids"]]
        T = len(ids)
        self.pos_of = {fid: k for k, fid in enumerate(ids)}
        self.cal = Calibration.from_dict(scene.attrs["calibration"])
        self.template = template = open_store(template_path, "template")
        self.tracking = tracking = open_store(tracking_path, "tracking")
        projection = open_store(projection_path, "projection")
        labels_store = open_store(labels_path, "labels")
        for name, path, g in (("tracking", tracking_path, tracking), ("projection", projection_path, projection),
                              ("labels", labels_path, labels_store)):
            _check_frames(name, path, g.attrs["frame_ids"], ids)
        self.atlas = atlas = Atlas.from_store(template)
        F = len(atlas.faces)
        if tracking["vertices"].shape[1] != template["vertices"].shape[0]:
            raise ValueError(f"tracking store {tracking_path} has {tracking['vertices'].shape[1]} "
                             f"vertices, template {template_path} has {len(template['vertices'])}")
        for name, path, arr in (("projection", projection_path, projection["face_visible"]),
                                ("labels", labels_path, labels_store["labels"])):
            if arr.shape[1] != F:
                raise ValueError(f"{name} store {path} has {arr.shape[1]} faces, template has {F}")
        W = int(template.attrs["atlas_size"])

        # the global baseline (Kim 2019), built from the source frames by the global_texture stage
        global_store = open_store(global_texture_path, "global_texture")
        check_atlas([(global_texture_path, global_store)], template, template_path)
        self.global_tex = np.asarray(global_store["texture"][...], np.uint8)
        self.global_faces = np.asarray(global_store["face_textured"][...], bool)
        if self.global_tex.shape[0] != W:
            raise ValueError(f"global_texture store {global_texture_path} is "
                             f"{self.global_tex.shape[0]} texels wide, template {template_path} "
                             f"atlas_size is {W}")
        if self.global_faces.shape != (F,):
            raise ValueError(f"global_texture store {global_texture_path} has "
                             f"{len(self.global_faces)} faces, template {template_path} has {F}")
        self.global_path = global_texture_path
        self.global_sources = global_sources = [int(i) for i in global_store.attrs["source_frames"]]
        if not set(global_sources) <= set(ids):
            raise ValueError(f"global_texture store {global_texture_path} was built from frames "
                             f"{short_ids(global_sources)} that are not all frames of the scene "
                             f"{scene_path} ({short_ids(ids)})")
        self.seconds_global = float(global_store.attrs["seconds"])

        # held-out protocol: the frames allowed to texture
        sources = set(global_sources)
        k = global_store.attrs.get("params", {}).get("source_stride")
        if data_term_paths:
            data_term_attrs = open_store(list(data_term_paths)[0], "data_term").attrs
            src = data_term_attrs.get("source_frames")
            if src is not None:
                sources = {int(i) for i in src}
                k = data_term_attrs.get("params", {}).get("source_stride")
            if sorted(sources) != sorted(global_sources):
                raise ValueError(f"global_texture store {global_texture_path} was built from source "
                                 f"frames {short_ids(sorted(global_sources))}, the tables "
                                 f"{list(data_term_paths)[0]} allow {short_ids(sorted(sources))} "
                                 f"(global_texture and tables must use the same source_stride)")
        self.sources = sorted(sources)
        self.stride_label = "" if len(sources) == T else (f"(1/{k})" if k else f"({len(sources)}/{T} frames)")
        self.is_source = np.array([i in sources for i in ids])

        score_ids = list(ids[::int(p["stride"])]) if frames is None else [int(f) for f in frames]
        bad = [f for f in score_ids if f not in self.pos_of]
        if bad or not score_ids:
            raise ValueError(f"frames to score {bad or score_ids} are not frames of the scene "
                             f"{scene_path} ({short_ids(ids)})")
        if block is not None:
            start, stop = (int(x) for x in block)
            if not 0 <= start < stop <= T:
                raise ValueError(f"frame block [{start}, {stop}) is outside the scene's {T} frames")
            score_ids = [f for f in score_ids if start <= self.pos_of[f] < stop]
        self.score_ids = score_ids
        fig_t = score_ids[len(score_ids) // 2] if score_ids else ids[0]
        fig_t = fig_t if p["figure_frame"] is None else int(p["figure_frame"])
        if fig_t not in self.pos_of:
            raise ValueError(f"figure_frame {fig_t} is not a frame of the scene ({short_ids(ids)})")
        self.fig_pos = self.pos_of[fig_t]

        # ground truth
        self.truth = None
        self.true_embedding = None
        if truth_paths and "truth" not in scene:
            raise StoreError(f"{scene_path}: truth stores given but the scene has no truth/vertices")
        # what the frame-block stores must hold: with a block, its frames to score and (flicker)
        # their predecessors; else every frame of the scene
        needed = None
        if block is not None:
            needed = set(score_ids)
            if truth_paths:
                needed |= {ids[self.pos_of[f] - 1] for f in score_ids if self.pos_of[f] > 0}
        self.photos = FrameSequence(list(frames_paths), "frames")
        self.masks = FrameSequence(list(masks_paths), "masks")
        self.volume = FrameSequence(list(volume_paths), "volume")
        self.corrected = FrameSequence(list(corrected_paths), "corrected")
        check_atlas([(p, g) for seq in (self.volume, self.corrected) for p, g in zip(seq.paths, seq.groups)],
                    template, template_path)
        for name, paths, seq in (("frames", frames_paths, self.photos), ("masks", masks_paths, self.masks),
                                 ("volume", volume_paths, self.volume),
                                 ("corrected", corrected_paths, self.corrected)):
            _check_frames(name, ", ".join(str(x) for x in paths), seq.frame_ids, ids,
                          None if needed is None else (set(score_ids) if name == "masks" else needed))
        if self.volume.groups[0]["texture"].shape[1] != W:
            raise ValueError(f"volume stores are {self.volume.groups[0]['texture'].shape[1]} texels "
                             f"wide, template atlas_size is {W}")
        if truth_paths:
            self.truth = FrameSequence(list(truth_paths), "truth")
            _check_frames("truth", ", ".join(str(x) for x in truth_paths), self.truth.frame_ids, ids,
                          needed)
            self.true_atlas = Atlas.from_store(scene, "template/")
            self.true_vertices = scene["truth/vertices"]
            # the template's embedding in the scene's mesh carries the truth onto the template
            if "embedding" in template:
                emb_face = np.asarray(template["embedding/face"][...], np.int64)
                if (len(emb_face) == template["vertices"].shape[0]
                        and emb_face.max(initial=-1) < len(self.true_atlas.faces)):
                    self.true_embedding = (emb_face, np.asarray(template["embedding/bary"][...], np.float64))
            if self.true_vertices.shape[0] != T:
                raise ValueError(f"{scene_path}: truth/vertices has {self.true_vertices.shape[0]} "
                                 f"frames, the scene has {T}")

        self.face_visible = np.asarray(projection["face_visible"][...], bool)
        self.labels = labels_store["labels"]
        self.seen_faces = (self.face_visible & self.is_source[:, None]).any(axis=0)
        self.coords, _, _ = open_coordinates(coords_path or projection_path)
        if self.coords.shape[0] != T:
            raise ValueError(f"texture coordinates {coords_path or projection_path} hold "
                             f"{self.coords.shape[0]} frames, the scene has {T}")
        self.sampler = TexelSampler(template["texel/face_id"][...], template["texel/bary"][...], atlas.faces)
        # the volume fills never-seen faces from the nearest seen surface: they carry texture too
        self.filled = (np.asarray(labels_store["never_seen"][...], bool)
                       if int(self.volume.attrs.get("never_seen_texels", 0)) > 0
                       else np.zeros(F, bool))

        # other methods' slices, scored beside ours
        self.others = _other_methods(p["other_methods"])
        self.methods = METHODS + tuple(self.others)
        want = set(score_ids)
        if truth_paths:  # the flicker of a frame compares it with its predecessor
            want |= {ids[self.pos_of[f] - 1] for f in score_ids if self.pos_of[f] > 0}
        for name, src in self.others.items():
            src.into_atlas(template, template_path)
            missing = sorted(want - set(src.frame_ids))
            if missing:
                why = ("; the frame before each scored frame is read too, for the flicker: give the slices "
                       "from one frame earlier" if set(missing) - set(score_ids) else "")
                raise ValueError(f"method {name!r}: {src.path} has no slices for frames {short_ids(missing)}{why}")
            self._other_slice(name, score_ids[0] if score_ids else src.frame_ids[0])  # fail early
        self.texel_face = np.asarray(template["texel/face_id"][...]) if self.others else None

    def textures(self, t):
        """Every method's texture slice (W, W, 3) at sequence position t."""
        from stex.global_texture import projection_texture

        fid = self.ids[t]
        proj_tex, _ = projection_texture(self.sampler, np.asarray(self.coords[t], np.float64),
                                         self.face_visible[t], self.photos.read("color", fid))
        out = {"ours": self.corrected.read("texture", fid),
               "ours_uncorrected": self.volume.read("texture", fid),
               "global": self.global_tex, "projection": proj_tex}
        for name in self.others:
            out[name] = self._other_slice(name, fid)
        return out

    def _other_slice(self, name, fid):
        """Other method ``name``'s slice of frame ``fid``, checked against the atlas."""
        src = self.others[name]
        tex = src.read(fid)
        if tex.shape != self.global_tex.shape:
            raise ValueError(f"method {name!r}: {src.path} slices are {tex.shape} (frame {fid}), "
                             f"the atlas ({self.template_path}) is {self.global_tex.shape}")
        return tex

    def has_texture(self, t, textures):
        """Every method's faces with texture (F,) bool at position t (``textures``: what
        :meth:`textures` gave; an other method textures the faces with a texel not black)."""
        lab = (np.asarray(self.labels[t]) >= 0) | self.filled
        out = {"ours": lab, "ours_uncorrected": lab, "global": self.global_faces,
               "projection": self.face_visible[t]}
        for name in self.others:
            has = np.zeros(len(self.atlas.faces), bool)
            f = self.texel_face[textures[name].any(axis=2)]
            has[f[f >= 0]] = True
            out[name] = has
        return out

    def truth_at(self, t):
        """:func:`truth_views` at position t."""
        from stex.mesh import transfer_vertices

        surface = None
        if self.true_embedding is not None:
            surface = transfer_vertices(np.asarray(self.true_vertices[t], np.float64),
                                        self.true_atlas.faces, *self.true_embedding)
        return truth_views(self.true_vertices[t], self.true_atlas,
                           self.truth.read("appearance", self.ids[t]), self.cal,
                           self.p["novel_angle_deg"], template_vertices=surface)

    def novel_renders(self, t, tv, texs):
        """Novel-view renders of every method (and the truth) at t, for the flicker."""
        g = frame_views(self.tracking["vertices"][t], self.atlas, self.cal, tv["novel_transform"],
                        self.face_visible[t], input_view=False)
        out = {m: (ev.view_texture(g["novel"], tex), g["novel"].mask, g["novel_seen"])
               for m, tex in texs.items()}
        out["truth"] = tv["novel"]
        return out


def _score_run(inp: _Inputs, frame_ids, progress) -> list[dict]:
    """Score consecutive frames; the first one's predecessor is rendered afresh for the
    flicker, later ones reuse the renders of the frame before."""
    p, out, prev_novel = inp.p, [], {}
    for fid in frame_ids:
        t = inp.pos_of[fid]
        V = inp.tracking["vertices"][t]
        motion = vertex_motion(inp.tracking["vertices"][t - 1], V) if t > 0 else math.nan
        image, mask = inp.photos.read("color", fid), inp.masks.read("mask", fid)
        texs = inp.textures(t)
        has = inp.has_texture(t, texs)
        tv = inp.truth_at(t) if inp.truth is not None else None
        rec = {"frame": fid, "position": t, "held_out": bool(not inp.is_source[t]),
               "motion_mm": motion, "methods": {}}
        novel_now = {}
        # a property of the photo, not of a method: once per frame, stored with every method
        noise = ev.noise_sigma(image, mask)["sigma"]
        scores = score_methods({m: texs[m] for m in inp.methods}, V, inp.atlas, image, mask, inp.cal,
                               face_has_texture=has, seen_faces=inp.seen_faces,
                               face_visible=inp.face_visible[t], truth=tv, patch=p["patch"],
                               radius=p["radius"], h_size=p["h_size"],
                               blur_interior_px=p["blur_interior_px"], return_views=tv is not None)
        for m, s in scores.items():
            if tv is not None:
                v = s.pop("views")
                novel_now[m] = (v["novel"][0], v["novel"][1], v["novel_seen"])
            s["noise_input"] = noise
            rec["methods"][m] = s
        if tv is not None:
            novel_now["truth"] = tv["novel"]
        if tv is not None and t > 0:
            prev = prev_novel.get(t - 1) or inp.novel_renders(t - 1, inp.truth_at(t - 1), inp.textures(t - 1))
            tp_img, tp_mask = prev["truth"]
            for m in inp.methods:
                r_img, r_mask, seen = novel_now[m]
                p_img, p_mask, p_seen = prev[m]
                # borrowed in both frames: object in all four renders, unseen at t-1 and at t
                sel = tv["novel"][1] & tp_mask & r_mask & p_mask & ~seen & ~p_seen
                fl = ev.temporal_flicker(p_img, r_img, tp_img, tv["novel"][0], sel)
                rec["methods"][m].update(flicker=fl["flicker"], flicker_excess=fl["excess"],
                                         flicker_pixels=fl["n_pixels"])
        prev_novel = {t: novel_now} if tv is not None else {}
        out.append(rec)
        progress(rec)
    return out


def _score(inp: _Inputs, score_ids, threads: int) -> list[dict]:
    """Per-frame records of ``score_ids``, in order; runs of consecutive frames in threads."""
    lock, done, t0 = threading.Lock(), [0], time.perf_counter()

    def progress(rec):
        with lock:
            done[0] += 1
            log.info("evaluation: frame %d (%d/%d%s) ours PSNR %.2f dB, global %.2f dB; "
                     "%.2f s per frame", rec["frame"], done[0], len(score_ids),
                     ", held out" if rec["held_out"] else "", rec["methods"]["ours"]["psnr"],
                     rec["methods"]["global"]["psnr"], (time.perf_counter() - t0) / done[0])

    # frames are scored independently (the flicker re-renders a run's first predecessor), so
    # runs of consecutive frames go to threads: the renders and most metrics release the GIL
    n = len(score_ids)
    n_threads = max(1, min(int(threads), n))
    runs = [score_ids[k * n // n_threads:(k + 1) * n // n_threads] for k in range(n_threads)]
    with ThreadPoolExecutor(n_threads) as pool:
        return [rec for run in pool.map(lambda r: _score_run(inp, r, progress), runs) for rec in run]


def _json_params(p: dict) -> dict:
    """The settings as they read back from JSON (tuples as lists), for comparisons."""
    return json.loads(json.dumps(_finite_or_none(p)))


def nan_for_none(x):
    """The inverse of ``_finite_or_none`` for what ``evaluation.json`` files hold: every null
    (in nested dicts and lists) back to NaN, so that records and summaries read from JSON score
    and summarise as the ones computed in-process."""
    if isinstance(x, dict):
        return {k: nan_for_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [nan_for_none(v) for v in x]
    return math.nan if x is None else x


def score_frames(scene_path, frames_paths, masks_paths, template_path, tracking_path,
                 projection_path, labels_path, volume_paths, corrected_paths, out_path,
                 params: dict | None = None, *, global_texture_path, truth_paths=None,
                 coords_path=None, data_term_paths=None, frames=None, block=None,
                 threads: int = 1) -> dict:
    """Evaluation, one frame block: score every method on the block's frames to score.

    The part of :func:`write_evaluation` that takes the time, split by frame block so that
    blocks are scored in separate processes (jobs) as soon as their slices exist; the records
    are merged by ``write_evaluation(..., records_paths=[...])``.

    Args:
        scene_path ... frames: the stores, settings and frames to score, as for
            :func:`write_evaluation`.
        out_path: JSON file to write (:func:`stex.io.write_json`: built aside, moved into place).
        block: [start, stop) sequence positions: score only the frames to score in it. The
            frame-block stores may then be just the ones holding those frames (and, with
            truth, each one's predecessor, for the flicker).
        threads: frames scored at once (runs of consecutive frames, one per thread); the
            result does not depend on it.

    Writes ``out_path``: ``{"stex_artifact": "evaluation_frames", "params"`` (the scoring
    settings, :func:`stex.config.scoring_settings`), ``"frame_ids",
    "source_frames", "scored_frames", "frames": [record, ...], "seconds"}`` with the records of
    ``evaluation.json`` (NaN as null). A block with no frame to score writes an empty list.

    Returns:
        the file's content.
    """
    t_start = time.perf_counter()
    inp = _Inputs(scene_path, frames_paths, masks_paths, template_path, tracking_path,
                  projection_path, labels_path, volume_paths, corrected_paths, params,
                  global_texture_path=global_texture_path, truth_paths=truth_paths,
                  coords_path=coords_path, data_term_paths=data_term_paths, frames=frames, block=block)
    records = _score(inp, inp.score_ids, threads) if inp.score_ids else []
    doc = _finite_or_none({"stex_artifact": "evaluation_frames", "params": scoring_settings(inp.p),
                           "frame_ids": inp.ids, "source_frames": inp.sources,
                           "scored_frames": inp.score_ids, "frames": records,
                           "seconds": time.perf_counter() - t_start})
    write_json(out_path, doc)
    log.info("evaluation: %d frames of block %s scored in %.1f s; written to %s", len(records),
             block, doc["seconds"], out_path)
    return doc



def _load_records(records_paths, inp: _Inputs) -> tuple[list[dict], float]:
    """Records of :func:`score_frames` files, checked against the evaluation's inputs, in
    scene order, and the seconds they took."""
    from stex.io import StoreError

    records, seconds, want = [], 0.0, _json_params(scoring_settings(inp.p))
    for path in records_paths:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise StoreError(f"{path}: not a readable evaluation_frames file ({e})") from e
        if not isinstance(doc, dict) or doc.get("stex_artifact") != "evaluation_frames":
            raise StoreError(f"{path}: not an evaluation_frames file")
        got = scoring_settings(doc["params"])  # records of older versions held the figures' too
        if got != want:
            diff = sorted(k for k in set(want) | set(got) if got.get(k) != want.get(k))
            raise ValueError(f"{path} was scored with other evaluation settings ({', '.join(diff)})")
        if doc["frame_ids"] != inp.ids or doc["source_frames"] != inp.sources:
            raise ValueError(f"{path} was scored on frames {short_ids(doc['frame_ids'])} with "
                             f"source frames {short_ids(doc['source_frames'])}; the scene has "
                             f"{short_ids(inp.ids)}, sources {short_ids(inp.sources)}")
        records += nan_for_none(doc["frames"])
        seconds += float(doc["seconds"])
    records.sort(key=lambda r: r["position"])
    got = [r["frame"] for r in records]
    if got != inp.score_ids:
        missing = sorted(set(inp.score_ids) - set(got))
        extra = sorted(f for f in set(got) if got.count(f) > 1 or f not in inp.score_ids)
        raise ValueError(f"records {', '.join(str(p) for p in records_paths)}: frames to score "
                         f"{short_ids(missing)} missing, {short_ids(extra)} twice or not to score")
    return records, seconds


def write_evaluation(scene_path, frames_paths, masks_paths, template_path, tracking_path,
                     projection_path, labels_path, volume_paths, corrected_paths, out_dir,
                     params: dict | None = None, *, global_texture_path, truth_paths=None,
                     coords_path=None, observations_path=None, data_term_paths=None, frames=None,
                     records_paths=None, timing: dict | None = None, threads: int = 1,
                     others: dict | None = None, sampling_path=None) -> dict:
    """Evaluation stage: score every method on the chosen frames and write the report content.

    Args:
        scene_path: ``scene`` store (calibration, frame ids; truth/vertices and the scene
            template's atlas on synthetic scenes).
        frames_paths, masks_paths: ``frames`` / ``masks`` block stores (photos, GrabCut masks).
        template_path: ``template`` store (faces, atlas, texel map, face charts).
        tracking_path: ``tracking`` store (vertices [T, V, 3]).
        projection_path: ``projection`` store (face_visible [T, F]).
        labels_path: ``labels`` store (labels [T, F], never_seen).
        volume_paths, corrected_paths: ``volume`` / ``corrected`` block stores
            (``ours_uncorrected`` / ``ours``).
        params: the evaluation settings (:func:`evaluation_params`).
        global_texture_path: (keyword, required) ``global_texture`` store, the ``global``
            method (:func:`stex.stages.global_texture.write_global_texture`: texture (W, W, 3) uint8,
            face_textured (F,) bool, attrs source_frames and seconds); its source frames must be
            the tables' source frames.
        truth_paths: ``truth`` block stores (synthetic scenes) -> ground-truth scores and flicker.
        coords_path: ``texcoords`` store (ξ) or the projection store (Φ, the default): the
            texture coordinates of the baselines, as used by the volume.
        data_term_paths: ``tables`` block stores: attr ``source_frames`` marks the frames that may
            texture (held-out protocol); without, the global texture's ``source_frames``.
        frames: global frame ids to score; None -> every ``stride``-th frame of the scene.
        out_dir: folder to write (built in ``<out_dir>.partial-<host>-<pid>`` and moved into
            place when complete, replacing an older evaluation's).
        observations_path: ``observations`` store -> the SSIM-dynamism figure.
        records_paths: :func:`score_frames` files whose records together cover the frames to
            score (checked: same settings, frames and sources): merged instead of scoring here.
        timing: ``{stage: seconds}`` for the timing table, or None.
        sampling_path: :func:`stex.stages.texcoords.write_sampling_table`'s JSON -> the paper's
            sampling table (``sampling`` in ``evaluation.json``, ``table_sampling.csv``), or None.
        threads: frames scored at once (runs of consecutive frames, one per thread); the
            result does not depend on it.
        others: ``{name: path}`` other methods' texture slices in the template's atlas
            (:class:`TextureSlices`: a folder of ``texture_<frame>.png`` or a texture store), or
            ``{name: {"slices": path, "uv_mesh": mesh}}`` for slices in that mesh's UV layout,
            scored by the same code beside ours and shown in every table under ``name``: added
            to the settings' ``other_methods``.

    Writes into ``out_dir``: ``evaluation.json`` (params, per-frame records
    ``frames[i] = {frame, position, held_out, motion_mm, methods: {method: {metric: value}}}``,
    ``summary`` (:func:`summarise_frames`), ``tables`` (:func:`table_rows`)); ``per_frame.csv``
    (one row per frame x method); ``table_<name>.csv`` per table; ``tables.rst``
    (:func:`rst_tables`) and ``tables.html``; figures ``psnr_per_frame.png``, ``blur_vs_motion.png``,
    ``side_by_side.png``, ``label_map.png`` and, with observations, ``dynamism.png``.

    Returns:
        the ``evaluation.json`` content (NaN as None).
    """
    from stex.io import open_store

    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    check_replaceable(out_dir)       # before the scoring, which takes minutes
    sampling = None
    if sampling_path is not None:
        try:
            sampling = json.loads(Path(sampling_path).read_text())["steps"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{sampling_path}: not a sampling table ({exc})") from exc
    if others:
        params = dict(params or {})
        from stex.config import other_method_paths

        params["other_methods"] = {**params.get("other_methods", {}), **{
            k: ({"slices": p, "uv_mesh": m} if m else p) for k, (p, m) in other_method_paths(others).items()}}
    inp = _Inputs(scene_path, frames_paths, masks_paths, template_path, tracking_path,
                  projection_path, labels_path, volume_paths, corrected_paths, params,
                  global_texture_path=global_texture_path, truth_paths=truth_paths,
                  coords_path=coords_path, data_term_paths=data_term_paths, frames=frames, block=None)
    p, ids, T = inp.p, inp.ids, len(inp.ids)
    log.info("evaluation: global texture %s from %d source frames (built in %.1f s)",
             global_texture_path, len(inp.global_sources), inp.seconds_global)
    if records_paths is None:
        records = _score(inp, inp.score_ids, threads)
        seconds_scoring = time.perf_counter() - t_start
    else:
        records, seconds_scoring = _load_records(list(records_paths), inp)
        log.info("evaluation: %d frames' records read from %d files (scored in %.1f s)",
                 len(records), len(records_paths), seconds_scoring)

    # vertex motion of every frame (the blur figure's x axis)
    tracked = np.asarray(inp.tracking["vertices"][...])
    motion = np.full(T, math.nan)
    for t in range(1, T):
        motion[t] = vertex_motion(tracked[t - 1], tracked[t])

    summary = summarise_frames(records, inp.methods)
    summary["n_frames"] = len(records)
    summary["n_held_out"] = int(sum(r["held_out"] for r in records))
    summary["held_out_label"] = inp.stride_label
    summary["blur_interior_px"] = int(p["blur_interior_px"])
    scene_name = str(Path(scene_path).parent.name or "scene")
    tabs = table_rows({scene_name: summary})
    result = {
        "params": p,
        "scene": scene_name,
        "frame_ids": ids,
        "source_frames": inp.sources,
        "scored_frames": inp.score_ids,
        "methods": list(inp.methods),
        "has_truth": inp.truth is not None,
        "frames": records,
        "summary": summary,
        "tables": tabs,
        "sampling": sampling,
        "seconds": {"global_texture": inp.seconds_global, "scoring": seconds_scoring},
        "libraries": library_versions(),
    }

    # built in this writer's <out_dir>.partial-<host>-<pid> and moved into place: a folder at
    # out_dir is complete
    final_dir, out_dir = out_dir, partial_path(out_dir)
    out_dir.mkdir(parents=True)

    def write_all(out_dir):
        fig_pos = inp.fig_pos
        _write_csvs(out_dir, records, tabs, timing, sampling)
        from stex.reporting import tables_html  # the report embeds HTML

        rst = rst_tables({scene_name: summary}, timing, sampling)
        (out_dir / "tables.rst").write_text(rst)
        (out_dir / "tables.html").write_bytes(tables_html(rst))
        _plot_psnr(out_dir / "psnr_per_frame.png", records)
        _plot_blur_motion(out_dir / "blur_vs_motion.png", records, ids, motion)
        _picture_side_by_side(out_dir / "side_by_side.png", fig_pos, ids, inp.photos, inp.masks,
                              inp.textures, tracked[fig_pos], inp.atlas, inp.cal,
                              inp.truth_at(fig_pos) if inp.truth is not None else None,
                              inp.face_visible[fig_pos])
        _picture_label_map(out_dir / "label_map.png", inp.volume.read("label_map", ids[fig_pos]),
                           ids[fig_pos])
        if observations_path is not None:
            obs = open_store(observations_path, "observations")
            _check_frames("observations", observations_path, obs.attrs["frame_ids"], ids)
            if "dynamism" in obs:
                _plot_dynamism(out_dir / "dynamism.png", np.asarray(obs["dynamism"][...], np.float32),
                               np.asarray(inp.template["face_chart"][...]),
                               ev.face_areas(inp.template["vertices"][...], inp.atlas.faces), ids,
                               int(p["dynamism_regions"]))
        result["seconds"]["total"] = time.perf_counter() - t_start
        (out_dir / "evaluation.json").write_text(json.dumps(_finite_or_none(result), indent=1))

    try:
        write_all(out_dir)
    except BaseException:
        shutil.rmtree(out_dir, ignore_errors=True)
        raise
    if final_dir.exists():
        try:
            check_replaceable(final_dir)
        except BaseException:
            shutil.rmtree(out_dir, ignore_errors=True)
            raise
    move_into_place(out_dir, final_dir)
    log.info("evaluation: %d frames in %.1f s; written to %s", len(records),
             time.perf_counter() - t_start, final_dir)
    return _finite_or_none(result)



#: what an evaluation folder holds (write_evaluation): only such a folder is replaced
_EVALUATION_FILES = re.compile(r"^(evaluation\.json|per_frame\.csv|table_\w+\.csv|tables\.(rst|html)|\w+\.png)$")


def check_replaceable(out_dir) -> None:
    """Refuse to replace ``out_dir`` unless it is missing, empty or an earlier evaluation's folder (an
    ``evaluation.json`` and only the files an evaluation writes): a mistyped ``--out`` must not
    delete a run, its textures or anything else."""
    out_dir = Path(out_dir)
    if not out_dir.exists():
        if not out_dir.name or out_dir.name in (".", ".."):
            raise ValueError(f"{out_dir}: give the evaluation a folder of its own (a new name)")
        return
    if not out_dir.is_dir():
        raise ValueError(f"{out_dir} exists and is not a folder: give the evaluation a new folder")
    names = sorted(p.name for p in out_dir.iterdir())
    if not names:  # an empty folder: nothing to lose
        return
    others = [n for n in names if not (_EVALUATION_FILES.match(n) and (out_dir / n).is_file())]
    if "evaluation.json" not in names or others:
        what = f"it holds {others[:3]}" if others else "it has no evaluation.json"
        raise ValueError(f"{out_dir} exists and is not an evaluation folder ({what}); it would be "
                         f"replaced: give a new folder, or an earlier evaluation's")


def evaluate_results(results_dir, out_dir, others: dict | None = None, frames=None,
                     stride: int | None = None, threads: int = 1) -> dict:
    """:func:`write_evaluation` of a finished run's folder, with other methods beside ours.

    Finds the stores of ``results/<scene>`` as the workflow lays them out (the scene's own
    block list, not a glob; ξ or Φ as its observations used; truth on synthetic scenes) and
    scores them with the run's evaluation settings (its ``evaluation/evaluation.json``, else the
    defaults).

    Args:
        results_dir: the run's folder (``results/<scene>``).
        out_dir: folder to write (as :func:`write_evaluation`; not the run's own
            ``evaluation``, which the workflow owns).
        others: ``{name: path or {"slices": path, "uv_mesh": mesh}}`` other methods' slices
            (:class:`TextureSlices`; :func:`write_evaluation`).
        frames: frame ids to consider, or None (all); every ``stride``-th of them is scored.
        stride: score every k-th frame; None -> the run's setting.
        threads: frames scored at once.

    Returns:
        the ``evaluation.json`` content. ``out_dir`` holds what the workflow's evaluation folder
        holds (with the run's sampling table, ``tables.html``) but the timing table: the stage
        times are the run's (``stex tables results/<scene>``).
    """
    from stex.io import StoreError, open_store, run_block_paths

    R = Path(results_dir)
    if not (R / "scene.zarr").exists():
        raise StoreError(f"{R}: not a results folder (no scene.zarr)")
    if Path(out_dir).resolve() == (R / "evaluation").resolve():
        raise ValueError(f"{out_dir} is the run's own evaluation folder: write elsewhere")
    scene = open_store(R / "scene.zarr", "scene")

    def blocks(kind):
        return run_block_paths(R, kind, scene)

    params = {}
    previous = R / "evaluation" / "evaluation.json"
    if previous.exists():
        params = dict(json.loads(previous.read_text()).get("params", {}))
    if stride is not None:
        params["stride"] = int(stride)
    params = evaluation_params(params)
    coords = R / "projection.zarr"
    observations = R / "observations.zarr"
    if observations.exists():
        if open_store(observations, "observations").attrs.get("coordinates") == "texcoords":
            coords = R / "texcoords.zarr"
    elif (R / "texcoords.zarr").exists():
        coords = R / "texcoords.zarr"
    chosen = None if frames is None else [int(f) for f in frames][::int(params["stride"])]
    sampling = R / "texcoords_sampling.json"
    return write_evaluation(
        R / "scene.zarr", blocks("frames"), blocks("masks"), R / "template.zarr", R / "tracking.zarr",
        R / "projection.zarr", R / "labels.zarr", blocks("volume"), blocks("corrected"), out_dir,
        params, global_texture_path=R / "global_texture.zarr",
        truth_paths=blocks("truth") if "truth" in scene else None, coords_path=coords,
        observations_path=observations if observations.exists() else None,
        data_term_paths=blocks("data_term"), frames=chosen, threads=threads, others=others,
        sampling_path=sampling if sampling.is_file() else None)


# --------------------------------------------------------------------------------------------
# files and figures
# --------------------------------------------------------------------------------------------

def _write_csvs(out_dir: Path, records, tabs, timing, sampling=None):
    keys = list(dict.fromkeys(k for r in records for s in r["methods"].values() for k in s))
    with open(out_dir / "per_frame.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "position", "held_out", "motion_mm", "method"] + keys)
        for r in records:
            for m, s in r["methods"].items():
                w.writerow([r["frame"], r["position"], int(r["held_out"]), _csv(r["motion_mm"]), m]
                           + [_csv(s.get(k, math.nan)) for k in keys])
    all_tabs = dict(tabs)
    if timing:
        all_tabs["timing"] = timing_rows(timing)
    if sampling:
        all_tabs["sampling"] = sampling_rows(sampling)
    for name, rows in all_tabs.items():
        with open(out_dir / f"table_{name}.csv", "w", newline="") as f:
            csv.writer(f).writerows(rows)


def _csv(x):
    return "" if isinstance(x, float) and not math.isfinite(x) else x


def _finish(plt, fig, ax, path, xlabel, ylabel):
    """Label, legend and grid a one-axis figure, write it to ``path`` and close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _plot_psnr(path, records):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    x = [r["frame"] for r in records]
    for m in (records[0]["methods"] if records else METHODS):
        ax.plot(x, [r["methods"][m]["psnr"] for r in records], marker=".", label=method_name(m))
    held = [r["frame"] for r in records if r["held_out"]]
    for i, h in enumerate(held):
        ax.axvline(h, color="0.85", lw=3, zorder=0, label="held-out frame" if i == 0 else None)
    _finish(plt, fig, ax, path, "frame", "patch-shift PSNR (dB)")


def _plot_blur_motion(path, records, ids, motion):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    x = [r["frame"] for r in records]
    ax.plot(x, [r["methods"]["ours"]["blur_input"] for r in records], "k.-", label="input")
    if all("blur_truth" in r["methods"]["ours"] for r in records):
        ax.plot(x, [r["methods"]["ours"]["blur_truth"] for r in records], "k:", label="true appearance")
    others = [m for m in (records[0]["methods"] if records else ()) if m not in METHODS]
    for m in ["ours", "global"] + others:
        ax.plot(x, [r["methods"][m]["blur"] for r in records], ".-", label=method_name(m))
    ax.set_xlabel("frame")
    ax.set_ylabel("blur (Crete), smaller is sharper")
    ax2 = ax.twinx()
    ax2.bar(ids, np.nan_to_num(motion), color="0.6", alpha=0.35, width=0.8, label="vertex motion")
    ax2.set_ylabel("mean vertex motion (mm/frame)")
    ax.set_zorder(ax2.get_zorder() + 1)
    ax.patch.set_visible(False)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


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


def _plot_dynamism(path, S, face_chart, face_area, ids, n_regions):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    for c, s in dynamism_regions(S, face_chart, face_area, n_regions):
        ax.plot(ids, s, ".-", label=f"chart {c}")
    ax.axhline(0.95, color="k", ls="--", lw=0.8, label="θ_Ω = 0.95")
    _finish(plt, fig, ax, path, "frame", "SSIM dynamism S (area-weighted mean)")


def _picture_side_by_side(path, t, ids, photos, masks, textures, V, atlas, cal, tv, face_visible):
    plt = pyplot()
    texs = textures(t)
    image = photos.read("color", ids[t])
    shown = ["ours", "global", "projection"]
    geom = frame_views(V, atlas, cal, None if tv is None else tv["novel_transform"], face_visible)
    views = {m: method_views(texs[m], V, atlas, cal, geometry=geom) for m in shown}
    top = [("input", image.astype(np.float32))] + [(m, views[m]["input"][0]) for m in shown]
    box = _crop_box([masks.read("mask", ids[t])] + [views[m]["input"][1] for m in shown])
    rows = [[(METHOD_NAMES[n] if n != "input" else "input photo", im, box) for n, im in top]]
    if tv is not None:
        nbox = _crop_box([tv["novel"][1]] + [views[m]["novel"][1] for m in shown])
        rows.append([("truth, novel view", tv["novel"][0], nbox)]
                    + [(METHOD_NAMES[m] + ", novel view", views[m]["novel"][0], nbox) for m in shown])
    fig, axes = plt.subplots(len(rows), 4, figsize=(10, 2.8 * len(rows)), dpi=120, squeeze=False)
    for r, row in enumerate(rows):
        for c, (title, im, (r0, r1, c0, c1)) in enumerate(row):
            axes[r, c].imshow(np.clip(im[r0:r1, c0:c1], 0, 255).astype(np.uint8))
            axes[r, c].set_title(title, fontsize=8)
            axes[r, c].axis("off")
    fig.suptitle(f"frame {ids[t]}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _picture_label_map(path, label_map, frame_id):
    from PIL import Image

    from stex.sampling import label_colors

    Image.fromarray(label_colors(np.asarray(label_map))).save(path)
