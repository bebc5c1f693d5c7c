"""Template stage, artifact side: read the template mesh from the ``scene`` store (or the first
frame's depth), run :func:`stex.template.prepare_template`, write the ``template`` store; the
atlas preview; and the atlas digest that texture stores are checked against."""


from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stex.atlas import atlas_digest
from stex.camera import Calibration, mask_in_depth
from stex.config import section_params
from stex.io import create_store, open_store
from stex.preview import label_image, write_png
from stex.readers.meshes import Mesh
from stex.scan import align_to_view, frame_points, rotation_angle_deg
from stex.skeleton import read_rig, skeleton_from_arrays
from stex.template import atlas_preview, prepare_template, template_from_frame

log = logging.getLogger("stex.template")


def template_atlas_digest(template) -> str:
    """:func:`atlas_digest` of an open ``template`` store."""
    return atlas_digest(template["texcoords"][...], template["texcoord_faces"][...],
                        int(template.attrs["atlas_size"]))


def check_atlas(stores, template, template_where) -> str:
    """Raise ValueError when one of ``stores`` ((where, open texture store) pairs, e.g. a
    sequence's block stores) records another atlas than the open ``template`` store's (at
    ``template_where``); stores without the attr (written before it existed) pass. Returns the
    template's :func:`atlas_digest` (computed once for all the stores)."""
    have = template_atlas_digest(template)
    for where, store in stores:
        made_in = store.attrs.get("atlas_digest")
        if made_in is not None and made_in != have:
            raise ValueError(f"{where} holds textures of another UV atlas than the template {template_where} "
                             f"(atlas {made_in}, the template's is {have}): a run's stores must come from "
                             f"one template (another run's or scene's?)")
    return have


def align_template(mesh: Mesh, frames_path, masks_path, calibration: Calibration, params: dict,
                   masks_params: dict | None = None) -> tuple[Mesh, dict]:
    """``mesh`` moved rigidly to where the first frame of ``frames_path`` sees the object inside
    its mask from ``masks_path`` (:func:`stex.scan.align_to_view`); returns it and a record
    (transform 4x4 as lists, fitness, rmse_m, rotation_deg, translation_m). ValueError when the
    fit is below ``params['align_min_fitness']``."""
    if frames_path is None or masks_path is None:
        raise ValueError("template.align and template.from_scan need the first frame block and its masks")
    frames, masks = open_store(frames_path, "frames"), open_store(masks_path, "masks")
    fid = int(frames.attrs["frame_ids"][0])
    m = section_params("masks", masks_params)
    depth = frames["depth"][0]
    P = frame_points(depth, mask_in_depth(masks["mask"][0], depth, calibration), frames["color"][0], calibration,
                     m["depth_near_m"], m["depth_far_m"])[0]
    try:
        a = align_to_view(mesh.vertices, mesh.faces, P, voxel_m=float(params["align_voxel_m"]))
    except ValueError as e:
        raise ValueError(f"{masks_path}: frame {fid}: template.align: {e}") from e
    record = {"transform": a.transform.tolist(), "fitness": a.fitness, "rmse_m": a.rmse, "frame": fid,
              "rotation_deg": rotation_angle_deg(a.transform[:3, :3]),
              "translation_m": float(np.linalg.norm(a.transform[:3, 3]))}
    if a.fitness < float(params["align_min_fitness"]):
        raise ValueError(f"{frames_path}: frame {fid}: template.align: only {100 * a.fitness:.0f} % of the frame's "
                         f"object points lie within {1000 * a.inlier_m:.0f} mm of the aligned template (template."
                         f"align_min_fitness {params['align_min_fitness']}): another object, a wrong mask, or a "
                         f"template in other units?")
    V = mesh.vertices @ a.transform[:3, :3].T + a.transform[:3, 3]
    log.info("template: aligned to frame %d (turned %.1f degrees, moved %.3f m; %.0f %% of its points within "
             "%.0f mm, rms %.1f mm)", fid, record["rotation_deg"], record["translation_m"], 100 * a.fitness,
             1000 * a.inlier_m, 1000 * a.rmse)
    return Mesh(V, mesh.faces, mesh.texcoords, mesh.texcoord_faces), record


def write_template(scene_path, params: dict, out, frames_path=None, masks_path=None, scan_path=None,
                   masks_params: dict | None = None) -> None:
    """Read the template mesh from the ``scene`` store, run the stage, write the ``template`` store.

    With ``params['from_depth']`` the mesh is instead :func:`template_from_frame` of the first
    frame of ``frames_path`` (a ``frames`` store) inside its mask from ``masks_path``; with
    ``params['from_scan']`` the fused mesh of the ``scan`` store at ``scan_path``. With
    ``params['align']`` or ``from_scan`` the mesh is first aligned to that first frame
    (:func:`align_template`; ``masks_params`` the masks section, for the object's depth range).
    """
    # defaults filled in, as the store records them; refuses uv: mesh with from_depth too
    params = section_params("template", params)
    scene = open_store(scene_path, "scene")
    has_template = scene.attrs.get("has_template", False) and "template/vertices" in scene
    if params["from_scan"] and params["from_depth"]:
        raise ValueError("template.from_scan and template.from_depth both set: choose one source of the template")
    if params["from_scan"]:
        if scan_path is None:
            raise ValueError("template.from_scan needs the scan store (rule scan)")
        scan = open_store(scan_path, "scan")
        if "given/vertices" in scene:
            log.warning("template: the source's per-frame meshes refer to its own template, not to the scan's; "
                        "tracking.mode given cannot use them")
        mesh, origin = Mesh(np.asarray(scan["vertices"][...], np.float64), np.asarray(scan["faces"][...], np.int32)), "scan"
        log.info("template: %d faces fused from the scan %s", len(mesh.faces), scan_path)
    elif params["from_depth"]:
        if frames_path is None or masks_path is None:
            raise ValueError("template.from_depth needs the first frame block and its masks")
        frames, masks = open_store(frames_path, "frames"), open_store(masks_path, "masks")
        fid = int(frames.attrs["frame_ids"][0])
        if has_template:
            log.warning("template: template.from_depth is set, so the source's template mesh is not used")
        if "given/vertices" in scene:
            log.warning("template: the source's per-frame meshes refer to its own template, not to one from "
                        "depth; tracking.mode given cannot use them")
        try:
            V, F = template_from_frame(frames["depth"][0], masks["mask"][0],
                                       Calibration.from_dict(scene.attrs["calibration"]),
                                       stride=int(params["from_depth_stride_px"]))
        except ValueError as e:
            raise ValueError(f"{frames_path}: frame {fid}: template.from_depth: {e}") from e
        log.info("template: %d faces from the depth of frame %d", len(F), fid)
        mesh, origin = Mesh(V, F), f"depth of frame {fid}"
    elif has_template:
        has_uv = "template/texcoords" in scene and "template/texcoord_faces" in scene
        mesh = Mesh(np.asarray(scene["template/vertices"][...], np.float64),
                    np.asarray(scene["template/faces"][...], np.int32),
                    np.asarray(scene["template/texcoords"][...], np.float64) if has_uv else None,
                    np.asarray(scene["template/texcoord_faces"][...], np.int32) if has_uv else None)
        origin = "source"
    else:
        kind = (scene.attrs.get("source") or {}).get("kind", "<kind>")
        raise ValueError(f"{scene_path}: the source has no template mesh; set source.{kind}.template, or "
                         f"template.from_depth to build one from the first frame's depth (one view only)")
    skeleton = _source_skeleton(scene, scene_path, params, mesh, origin)
    calibration = scene.attrs.get("calibration")
    alignment = None
    if params["from_scan"] or params["align"]:
        mesh, alignment = align_template(mesh, frames_path, masks_path, Calibration.from_dict(calibration), params,
                                         masks_params)
        if skeleton is not None:   # the joints move with the mesh
            skeleton.bind = np.asarray(alignment["transform"]) @ skeleton.bind
    # the mesh is in depth-camera coordinates at frame 0: open parts are turned to face that camera
    camera = Calibration.from_dict(calibration).depth if calibration else None
    try:
        result = prepare_template(mesh, params, camera=camera, skeleton=skeleton)
    except (ValueError, RuntimeError) as e:  # name the mesh: the stage's errors speak of faces only
        raise type(e)(f"{scene_path}: template ({origin}): {e}") from e
    attrs = result.pop("attrs")
    attrs["origin"] = origin
    attrs["alignment"] = alignment
    with create_store(out, "template", attrs=attrs, params=params) as store:
        for name, arr in result.items():
            store.write(name, arr)
    log.info("template: wrote %s (%d faces, atlas %d^2)", out, attrs["counts"]["faces"], attrs["atlas_size"])


def _source_skeleton(scene, scene_path, params: dict, mesh: Mesh, origin: str):
    """The skeleton of the source's template: the rig file ``template.rig``, else the one the
    source gave (``template/skeleton/*`` of the scene store), else None. A template not from the
    source (from depth, from a scan) has none: a rig file there is an error, the source's is
    dropped with a note."""
    rig = params.get("rig")
    if origin != "source":
        if rig:
            raise ValueError(f"template.rig {rig}: the rig refers to the source's template mesh, but the template "
                             f"is built from the {origin} (template.from_depth / from_scan); drop one of them")
        if "template/skeleton/parents" in scene:
            log.info("template: the source's skeleton refers to its own template mesh, not used for one from the %s",
                     origin)
        return None
    if rig:
        return read_rig(rig, len(mesh.vertices))
    skeleton = skeleton_from_arrays(scene, scene.attrs.get("skeleton_joint_names"), prefix="template/skeleton/")
    if skeleton is not None and len(skeleton.joints) != len(mesh.vertices):
        raise ValueError(f"{scene_path}: the source's skeleton weights {len(skeleton.joints)} vertices, its template "
                         f"has {len(mesh.vertices)}")
    return skeleton


def preview_template(template_path, out_png, size: int = 1024) -> None:
    """Write the atlas picture of a ``template`` store to ``out_png``."""
    g = open_store(template_path, "template")
    img = atlas_preview(g["texcoords"][...], g["texcoord_faces"][...], g["face_chart"][...], size)
    c = g.attrs["counts"]
    title = (f"atlas {g.attrs['atlas_size']}^2, {c['charts']} charts, {c['faces']} faces, "
             f"gutter {g.attrs['gutter_px']} px")
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    write_png(out_png, label_image(img, title))
