"""Template stage: clean, decimate and UV-unwrap the template mesh once for the whole sequence.

What it computes (:func:`prepare_template`, a mesh in, the ``template`` store's arrays out; the
store itself is written by :func:`stex.stages.template.write_template`):

- :func:`stex.mesh.clean_mesh` — merges exactly duplicated vertices, drops degenerate and
  duplicated faces and unreferenced vertices, turns round the coherently wound parts that face
  the wrong way (closed parts by signed volume and nesting, open parts towards the depth camera),
  and reports non-manifold and boundary edges and faces of opposite winding (reported, not fixed).
- :func:`stex.mesh.decimate` — pymeshlab quadric edge collapse to a target face count (the
  paper's templates have 10-30k faces; default 20k). A no-op when the mesh is already small enough.
- :func:`stex.atlas.build_atlas` — a UV atlas from xatlas in one square ``resolution`` x
  ``resolution`` texture with ``gutter_px`` empty texels between charts, and **no mirrored UV
  triangles**; or :func:`stex.atlas.keep_layout` (``template.uv: mesh``): the mesh's own texture
  coordinates, carried through cleaning, decimation and subdivision.
- :func:`stex.mesh.face_adjacency`, :func:`stex.atlas.texel_map` — the faces' neighbours and each
  texel's face and barycentrics.
- :func:`stex.mesh.embed_vertices` — where each template vertex lies on the *original* template
  surface, so per-frame meshes of the original topology can be carried to the decimated one.

Sources without a template get one from the first frame's depth (:func:`template_from_frame`,
:func:`template_from_depth`).

Conventions
-----------
Vertices are metres in depth-camera coordinates (never recentred; the depth camera sits at the
origin looking along +z); faces are counter-clockwise seen from outside. Texcoords follow stex
(see :mod:`stex.render` and :mod:`stex.atlas`): u right, v **down**, origin at the texture's
top-left corner.
"""

from __future__ import annotations

import colorsys
import logging
import time

import cv2
import numpy as np
from scipy import ndimage

from stex.atlas import (
    border_gap, build_atlas, faces_without_texel, gutter_conflicts, keep_layout, texel_map, uv_charts,
    uv_signed_area)
from stex.camera import backproject_depth, depth_pixels_in_color, mask_in_depth
from stex.config import section_params
from stex.skeleton import carry_skeleton, skeleton_arrays
from stex.mesh import clean_mesh, decimate, drop_small_parts, embed_vertices, face_adjacency, subdivide_midpoint

log = logging.getLogger("stex.template")


# --------------------------------------------------------------------------------------------
# the stage
# --------------------------------------------------------------------------------------------

#: Fraction of the faces that may hold no texel centre without a warning. Tiny faces legitimately
#: miss every centre, but at the default 2048^2 none did on the fox (2304 faces after subdivision,
#: 0.6 m and 1.5 m), the demo's procedural body (9024), a KillingFusion template from depth (20k
#: after decimation) and a bumpy 82k-face sphere decimated to 20k; the 1.5 m fox at 256^2 has
#: 3.2 %, at 128^2 55 %.
MAX_FACES_WITHOUT_TEXEL = 0.01


def _warn_faces_without_texel(face_id, uv_area, size: int, gutter: int, keep_uv: bool) -> int:
    """Count the faces without a texel centre in ``face_id`` (W, W); warn, naming the settings,
    when those with UV area (``uv_area`` (F,) signed; collapsed ones are warned about where they
    collapse) exceed :data:`MAX_FACES_WITHOUT_TEXEL` of the faces."""
    n_faces = len(uv_area)
    missing = faces_without_texel(face_id, n_faces)
    n = int((uv_area[missing] != 0).sum())
    if n > MAX_FACES_WITHOUT_TEXEL * n_faces:
        fix = ("raise template.atlas_size (the mesh's own layout is read at that size)" if keep_uv else
               f"raise template.atlas_size (or lower template.gutter_px, now {gutter})")
        log.warning("template: %d of the %d faces (%.1f %%) hold no texel centre of the %d^2 atlas, so they get no "
                    "texture of their own (lookups on them read neighbouring texels): the atlas is too small for "
                    "the mesh; %s", n, n_faces, 100.0 * n / n_faces, size, fix)
    return int(len(missing))


def prepare_template(mesh, params: dict, camera=None, skeleton=None) -> dict:
    """Run the template stage on a mesh.

    Args:
        mesh: :class:`stex.readers.meshes.Mesh` (original template, depth-camera coordinates, m).
        params: the ``template`` config section: ``target_faces``, ``decimate``, ``atlas_size``,
            ``gutter_px``, ``uv`` (``xatlas``: a new atlas; ``mesh``: the mesh's own texture
            coordinates, carried through cleaning, decimation and subdivision, see
            :func:`keep_layout`); completed with the schema's defaults and validated
            (:func:`stex.config.section_params`: unknown keys and bad values raise ValueError).
        camera: the scene's depth camera (:class:`stex.camera.Intrinsics`, e.g.
            ``Calibration.depth``): open parts of the mesh (a single-view scan) are turned to face
            what it sees of them (:func:`clean_mesh`). Its centre is the origin of the mesh's
            coordinates, looking along +z. None (default): a pinhole at the origin looking along
            +z that frames the open parts.
        skeleton: the mesh's :class:`stex.skeleton.Skeleton` (weights for ``mesh``'s vertices) or
            None; carried to the template's vertices through the embedding
            (:func:`stex.skeleton.carry_skeleton`) as the ``skeleton/*`` arrays.

    Returns:
        dict with the ``template`` store's arrays (keys as in :data:`stex.artifacts.ARTIFACTS`) and
        ``"attrs"``: a JSON-able dict of the stage's report.

    A warning names faces that hold no texel centre of the atlas when they are more than
    :data:`MAX_FACES_WITHOUT_TEXEL` of the faces (an atlas too small for the mesh).
    """
    params = section_params("template", params)
    t0 = time.perf_counter()
    keep_uv = params["uv"] == "mesh"
    corner_uv = None
    if keep_uv:
        if mesh.texcoords is None or mesh.texcoord_faces is None:
            raise ValueError("template.uv is 'mesh' but the template mesh has no texture coordinates (OBJ vt, "
                             "glTF TEXCOORD_0); use template.uv: xatlas")
        corner_uv = np.asarray(mesh.texcoords, np.float64)[np.asarray(mesh.texcoord_faces, np.int64)]
    V, F, report, corners = clean_mesh(mesh.vertices, mesh.faces, return_corners=True, camera=camera)
    V, F, parts, kept = drop_small_parts(V, F, int(params["min_part_faces"]), return_kept=True)
    if keep_uv:  # the corners' coordinates follow the faces that stay, turned round or not
        corner_uv = corner_uv.reshape(-1, 2)[corners][kept]
    report.update(parts)
    if parts["dropped_parts"]:
        log.info("template: dropped %d of %d parts with fewer than %d faces (%d faces)", parts["dropped_parts"],
                 parts["parts"], int(params["min_part_faces"]), parts["dropped_faces"])
    extent = float(np.ptp(V, axis=0).max())
    if extent > 5.0:  # the tracking stage refuses it at the first frame; say why here already
        log.warning("template: the mesh is %.3g m across: an object one RGB-D camera films is under a few metres; "
                    "is it in millimetres or centimetres? (it must be in metres)", extent)
    log.info("template: cleaned %d -> %d faces (%s)", report["faces_in"], report["faces_out"],
             {k: report[k] for k in ("duplicate_vertices", "degenerate_faces", "duplicate_faces",
                                     "unreferenced_vertices", "nonmanifold_edges", "nonmanifold_vertices",
                                     "boundary_edges")})
    t1 = time.perf_counter()
    decimated = bool(params["decimate"]) and len(F) > int(params["target_faces"])
    if decimated and keep_uv:
        V, F, corner_uv = decimate(V, F, int(params["target_faces"]), corner_uv=corner_uv)
        log.info("template: decimated to %d faces, %d vertices (UV layout kept)", len(F), len(V))
    elif decimated:
        V, F = decimate(V, F, int(params["target_faces"]))
        log.info("template: decimated to %d faces, %d vertices", len(F), len(V))
    # Low-poly assets (e.g. game models) are split until they have enough vertices to carry the
    # tracker's data term; midpoint splits leave the shape exactly as it was.
    subdivided = 0
    while not decimated and len(F) * 4 <= int(params["min_faces"]):
        if keep_uv:
            V, F, corner_uv = subdivide_midpoint(V, F, corner_uv)
        else:
            V, F = subdivide_midpoint(V, F)
        subdivided += 1
    if subdivided:
        log.info("template: subdivided %d times to %d faces", subdivided, len(F))
    t2 = time.perf_counter()
    # Keep the template on the original surface so that transfer_vertices reproduces it exactly.
    emb_face, emb_bary, closest, dist = embed_vertices(V, mesh.vertices, mesh.faces)
    V = closest
    t3 = time.perf_counter()
    size, gutter = int(params["atlas_size"]), int(params["gutter_px"])
    if keep_uv:
        tc, tf, info = keep_layout(corner_uv, size)
        face_id, bary = texel_map(tc, tf, size)
    else:
        tc, tf, info, (face_id, bary) = build_atlas(V, F, size, gutter, return_info=True, return_texels=True)
    t4 = time.perf_counter()
    pairs, edges = face_adjacency(F)
    info["faces_without_texel"] = _warn_faces_without_texel(face_id, uv_signed_area(tc, tf), size, gutter, keep_uv)
    chart = uv_charts(tf, len(tc))
    conflicts = gutter_conflicts(face_id, chart, gutter)
    whose = " in the mesh's own UV layout (bilinear lookups there mix in the neighbour)" if keep_uv else ""
    if conflicts:
        log.warning("template: %d texels closer than %d texels to another chart%s", conflicts, gutter, whose)
    to_border = border_gap(face_id)
    if to_border < gutter:
        log.warning("template: a chart %d texels from the atlas border (gutter %d)%s", to_border, gutter, whose)
    t5 = time.perf_counter()
    attrs = {
        "atlas_size": size, "gutter_px": gutter,
        "counts": {"vertices": len(V), "faces": len(F), "texcoords": len(tc), "charts": info["charts"],
                   "adjacent_pairs": len(pairs), "covered_texels": int((face_id >= 0).sum()),
                   "faces_in": int(len(mesh.faces))},
        "clean_report": report,
        "decimated": decimated,
        "subdivided": subdivided,
        "uv": "mesh" if keep_uv else "xatlas",
        "flipped_fixed": info.get("flipped_xatlas", 0),
        "atlas": {k: v for k, v in info.items()},
        "gutter_conflicts": conflicts,
        "border_gap_px": to_border,
        "embedding_max_distance_m": float(dist.max()) if len(dist) else 0.0,
        "skeleton_joint_names": None if skeleton is None else list(skeleton.names),
        "timings_s": {"clean": t1 - t0, "decimate": t2 - t1, "embed": t3 - t2, "atlas": t4 - t3,
                      "adjacency_texels": t5 - t4},
    }
    carried = {} if skeleton is None else skeleton_arrays(carry_skeleton(skeleton, mesh.faces, emb_face, emb_bary))
    return carried | {
        "vertices": V.astype(np.float32), "faces": F.astype(np.int32),
        "texcoords": tc, "texcoord_faces": tf, "face_chart": chart,
        "adjacency/pairs": pairs, "adjacency/edges": edges,
        "texel/face_id": face_id, "texel/bary": bary,
        "embedding/face": emb_face, "embedding/bary": emb_bary,
        "attrs": attrs,
    }


def hidden_from_color(depth_m, calibration, select, tolerance_m: float = 0.05) -> np.ndarray:
    """(Hd, Wd) bool: depth pixels in ``select`` that the colour camera cannot see, because a
    selected point more than ``tolerance_m`` nearer lands within a depth pixel's footprint of them
    in the colour image.

    The two cameras are a few centimetres apart, so background just beside the object in the depth
    image can land behind the object in the colour image, inside its mask. The tolerance keeps the
    object's own receding sides, which a tighter one drops (docs/decisions/template.md).
    """
    out = np.zeros(depth_m.size, bool)
    idx, px, z = depth_pixels_in_color(depth_m, calibration, select)
    if idx.size == 0:
        return out.reshape(depth_m.shape)
    c = calibration.color
    zbuf = np.full((c.height, c.width), np.inf, np.float32)
    np.minimum.at(zbuf, (px[:, 1], px[:, 0]), z.astype(np.float32))
    # a depth pixel covers about this many colour pixels: the nearest surface over that footprint
    k = 2 * int(np.ceil(c.fx / calibration.depth.fx)) + 1
    zbuf = cv2.erode(zbuf, np.ones((k, k), np.uint8))
    out[idx] = z > zbuf[px[:, 1], px[:, 0]] + tolerance_m
    return out.reshape(depth_m.shape)


def template_from_frame(depth_mm, mask_color, calibration, stride: int = 2, max_jump_m: float = 0.05):
    """A template from one frame: the surface its depth image sees inside its colour mask.

    The mask is carried into the depth image (:func:`stex.camera.mask_in_depth`), without the
    points the colour camera cannot see (:func:`hidden_from_color`: background behind the object
    that lands in its mask); depth pixels without a value are carried into the colour image at the
    object's median depth and kept where they land in the mask; the region is closed and its holes
    filled. Pixels without a value in it get the depth of their nearest valid pixel in the mask,
    then a 5-px median smooths the result.
    :func:`template_from_depth` turns it into triangles (``stride`` depth px apart; no triangle
    across a depth jump of ``max_jump_m``, e.g. a nose in front of a chest).

    Args:
        depth_mm: (Hd, Wd) uint16 depth, millimetres, 0 = invalid. mask_color: (Hc, Wc) bool.
        calibration: :class:`stex.camera.Calibration`.

    Returns:
        (vertices (V, 3) float64 depth-camera metres, faces (F, 3) int32), faces towards the camera.
    """
    mask_color = np.asarray(mask_color, bool)
    d = np.asarray(depth_mm).astype(np.float64) / 1000.0
    seen = mask_in_depth(mask_color, np.asarray(depth_mm), calibration)
    seen &= ~hidden_from_color(d, calibration, seen)
    if not seen.any():
        raise ValueError("template_from_frame: no valid depth inside the mask")
    # depth pixels without a value cannot be carried into the colour image by their own depth:
    # they are carried at the object's median depth (the parallax error is small at its distance)
    idx, px, _ = depth_pixels_in_color(np.full(d.shape, float(np.median(d[seen]))), calibration)
    no_depth = np.zeros(d.size, bool)
    no_depth[idx] = mask_color[px[:, 1], px[:, 0]]
    no_depth = no_depth.reshape(d.shape) & (d <= 0)
    k = 2 * stride + 1
    region = ndimage.binary_fill_holes(cv2.morphologyEx((seen | no_depth).astype(np.uint8), cv2.MORPH_CLOSE,
                                                        np.ones((k, k), np.uint8)) > 0)
    # every pixel takes its nearest object depth before the median, so that the median at the
    # silhouette does not mix in the background or zeros
    nearest = ndimage.distance_transform_edt(~seen, return_distances=False, return_indices=True)
    filled = np.where(region, cv2.medianBlur(d[tuple(nearest)].astype(np.float32), 5), 0.0)
    return template_from_depth(filled, calibration.depth.K, region, stride=stride, max_jump_m=max_jump_m)


# --------------------------------------------------------------------------------------------
# preview
# --------------------------------------------------------------------------------------------

def atlas_preview(texcoords, texcoord_faces, face_chart, size: int = 1024) -> np.ndarray:
    """(size, size, 3) uint8 RGB picture of the atlas: each chart in its own colour (the same
    hue family, lighter towards higher face ids inside a chart), empty texels dark grey."""
    face_id, _ = texel_map(texcoords, texcoord_faces, size)
    chart = np.asarray(face_chart)
    n = int(chart.max()) + 1 if len(chart) else 0
    golden = 0.618033988749895
    palette = np.array([colorsys.hsv_to_rgb((k * golden) % 1.0, 0.55 + 0.35 * ((k * 7) % 3) / 2, 0.95)
                        for k in range(max(n, 1))]) * 255
    img = np.full((size, size, 3), 40, np.uint8)
    hit = face_id >= 0
    img[hit] = palette[chart[face_id[hit]]].astype(np.uint8)
    return img


# --------------------------------------------------------------------------------------------
# a template from one depth image
# --------------------------------------------------------------------------------------------

def template_from_depth(depth_m, K, mask=None, stride: int = 2, max_jump_m: float = 0.02):
    """A triangle mesh of the surface one depth image sees (for sources without a template).

    Pixels on a grid of ``stride`` that have valid depth (and lie in ``mask``) become vertices;
    each grid square whose corners are valid and whose depth range is below ``max_jump_m``
    becomes two triangles, oriented so that their normals face the camera (the outside).

    Args:
        depth_m: (H, W) float depth in metres, 0 = invalid. K: (3, 3) depth camera matrix.
        mask: (H, W) bool foreground, or None.

    Returns:
        (vertices (V, 3) float64 camera-space metres, faces (F, 3) int32).
    """
    d = np.asarray(depth_m, np.float64)
    if not np.isfinite(d).all():
        raise ValueError("depth has non-finite values")
    ok = d > 0
    if mask is not None:
        ok &= np.asarray(mask, bool)
    P = backproject_depth(d, K)[::stride, ::stride]
    ok = ok[::stride, ::stride]
    z = d[::stride, ::stride]
    h, w = ok.shape
    index = np.full((h, w), -1, np.int64)
    index[ok] = np.arange(ok.sum())
    a, b, c, e = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    zs = np.stack([z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]])
    good = (a >= 0) & (b >= 0) & (c >= 0) & (e >= 0) & (zs.max(0) - zs.min(0) < max_jump_m)
    # Image x right, y down, camera looking along +z: (a, c, b) winds towards the camera.
    t1 = np.stack([a[good], c[good], b[good]], 1)
    t2 = np.stack([b[good], c[good], e[good]], 1)
    faces = np.concatenate([t1, t2])
    if len(faces) == 0:
        raise ValueError("no valid depth surface to build a template from (empty mask or depth?)")
    V = P[ok]
    used = np.unique(faces)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[faces].astype(np.int32)
