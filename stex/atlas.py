"""UV layout of the template: building the atlas (xatlas), keeping a mesh's own layout, charts,
the texel map, digests, and the border and gutter checks.

Conventions
-----------
Texcoords follow stex (see :mod:`stex.render`): u right, v **down**, origin at the texture's
top-left corner, texel (r, c) centred at ((c + .5) / W, (r + .5) / W).

**UV orientation.** With v pointing down, a UV triangle is *front-facing* (the texture image shows
the surface as seen from outside, not mirrored) when its signed area

    A = (u1 - u0) (v2 - v0) - (v1 - v0) (u2 - u0)

is **negative**: counter-clockwise on the screen with rows growing downward. (Exported to OBJ,
v -> 1 - v, this becomes the usual positive / counter-clockwise UV winding of OpenGL tools.)
:func:`uv_flipped` marks faces with A > 0; :func:`build_atlas` guarantees there are none.

Why xatlas mirrors charts, and the fix
--------------------------------------
xatlas' packer may "rotate" a chart by 90 degrees to pack it better (``PackOptions.rotate_charts``,
on by default), and it does so by swapping u and v — a *transposition*, i.e. a mirror image.
``ChartOptions.fix_winding`` does not help (it concerns the parameterisation, which is fine).
About half the charts of a mesh can come out mirrored (docs/decisions/template.md).
:func:`build_atlas` therefore

1. charts and packs with xatlas' defaults (pass 1),
2. mirrors every chart whose area-weighted orientation is wrong (u -> -u, turning the
   transposition into a true 90-degree rotation); a face still wrong after that (a fold inside a
   chart; not observed so far) becomes a chart of its own and is mirrored alone,
3. repacks the fixed charts with xatlas (``use_input_mesh_uvs``, ``rotate_charts`` off, so no new
   mirror images) into exactly ``resolution`` x ``resolution`` texels, searching the texel density
   (texels per metre) that just fits one atlas,
4. mirrors back, each inside its own box, the small charts the repack returns wholly mirrored
   (a sliver triangle of a mesh from depth; small fans at the pole of a noisy scan),
   and checks that no triangle is mirrored and all texcoords lie in [0, 1].

xatlas skips faces below an absolute area (:data:`XATLAS_MIN_AREA` in the mesh's units), so a
mesh of tiny faces is scaled up for it (:func:`stex.mesh.working_scale`) and the texel density
scaled back to texels per metre. The scale comes from the median face area, so the faces of a
small part (a 4 mm eye on a 10 cm body) can still fall below the limit: their UVs collapse, and a
warning says how many faces in which parts (scaling further up packs such parts' few-texel
charts closer than the gutter: docs/decisions/template.md).

Steps 1-3 run in a child process (:func:`stex.isolated.call_in_child`,
:func:`stex.charting.xatlas_layout`) that exits without destroying its xatlas atlas:
``xatlas::Destroy`` joins xatlas' worker threads and once waited for them for good.
Which charts the packer transposes depends on the layout, so ``flipped_xatlas`` varies with the
resolution; the result never has mirrored triangles.
"""

from __future__ import annotations

import hashlib
import logging

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from stex.isolated import call_in_child
from stex.mesh import face_areas_quality, mesh_parts, working_scale
from stex.render import rasterize
from stex.charting import uv_signed_area, xatlas_layout

log = logging.getLogger("stex.template")


def uv_flipped(texcoords, texcoord_faces) -> np.ndarray:
    """(F,) bool: UV triangles that are mirrored (signed area > 0 with v pointing down).

    Zero-area UV triangles are not counted as flipped (see :func:`uv_signed_area`).
    """
    return uv_signed_area(texcoords, texcoord_faces) > 0


def uv_charts(texcoord_faces, n_texcoords: int | None = None) -> np.ndarray:
    """(F,) int32 chart id of each face: connected components of faces sharing a texcoord.

    Charts are numbered by their lowest face index (chart 0 holds face 0).
    """
    tf = np.asarray(texcoord_faces, np.int64)
    F = len(tf)
    n_t = int(tf.max()) + 1 if n_texcoords is None else int(n_texcoords)
    # bipartite graph faces <-> texcoords; components restricted to faces
    rows = np.repeat(np.arange(F), 3)
    cols = F + tf.ravel()
    g = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(F + n_t, F + n_t))
    _, lab = connected_components(g, directed=False)
    lab = lab[:F]
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(first)  # component ids in order of first face
    relabel = np.empty(lab.max() + 1, np.int64)
    relabel[np.unique(lab)[order]] = np.arange(len(order))
    return relabel[lab].astype(np.int32)


#: xatlas gives faces of less area than this (in its float32 input units; FLT_EPSILON) no chart.
XATLAS_MIN_AREA = 1.2e-7
#: Faces of at least this quality (:func:`face_areas_quality`) count as well-shaped, not
#: needle-thin, in the warning about faces xatlas collapsed.
WELL_SHAPED_QUALITY = 0.2


def build_atlas(vertices, faces, resolution: int = 2048, gutter_px: int = 4, return_info: bool = False,
                pack_search_steps: int = 7, return_texels: bool = False):
    """A UV atlas of the mesh: xatlas charts packed into one square texture, no mirrored charts.

    See the module docstring for the procedure and why pass 1's charts need fixing.

    Args:
        vertices: (V, 3) float, metres.
        faces: (F, 3) int, counter-clockwise seen from outside; no degenerate faces
            (run :func:`clean_mesh` first).
        resolution: side of the square atlas W, texels.
        gutter_px: empty texels xatlas keeps around every chart (its ``padding``); with its
            bilinear reserve two charts end up at least 2 * gutter_px + 2 texels apart
            (measured with :func:`gutter_conflicts`). The charts are packed into the inner
            (resolution - 2 gutter_px)^2 texels, so that every chart also keeps gutter_px empty
            texels from the atlas border (:func:`border_gap`): xatlas itself packs up to half a
            texel from it, where a viewer's default REPEAT wrap (glTF) and any filter reach across
            to the opposite edge.
        return_info: also return a dict of statistics.
        pack_search_steps: repacks tried when searching the largest texel density that fits
            (bracket, then bisection to 1 %).
        return_texels: also return the atlas' :func:`texel_map` (made anyway for the statistics).

    Returns:
        texcoords (Vt, 2) float32 in [0, 1]^2 (u right, v down), texcoord_faces (F, 3) int32
        (face i of ``faces`` <-> row i), with ``return_info`` a dict: ``flipped_xatlas``
        (mirrored triangles in xatlas' own output), ``flipped_charts`` (charts mirrored back),
        ``fold_faces`` (faces split into their own chart), ``charts``, ``texels_per_unit``
        (texels per metre), ``utilization`` (fraction of the resolution^2 texels whose centre a
        UV triangle holds, as :func:`texel_map` rasterises it), ``xatlas_utilization`` (xatlas'
        own figure for the packed square, which counts its conservative chart rasters: higher),
        ``faces_without_texel`` (faces holding no texel centre), ``degenerate_uv_faces``,
        ``working_scale``, timings in s; and with ``return_texels`` the
        tuple (face_id (W, W) int32, bary (W, W, 3) float32) of :func:`texel_map`.

    Raises:
        RuntimeError: the charts do not fit one atlas even at a tiny texel density (the message
            names ``template.atlas_size`` and ``template.gutter_px``), or xatlas misbehaved.
    """
    F = np.asarray(faces, np.int64)
    scale = working_scale(vertices, F)  # texel densities below are per scaled unit
    V = np.asarray(vertices, np.float64) * scale
    resolution, gutter_px = int(resolution), int(gutter_px)
    if gutter_px < 0 or resolution - 2 * gutter_px < 8:
        raise ValueError(f"need gutter_px >= 0 and resolution - 2 gutter_px >= 8, got {resolution}, {gutter_px}")
    inner = resolution - 2 * gutter_px  # the charts' square: a gutter to the border on every side
    # xatlas runs in a child process that never destroys its atlas (its destructor can hang for
    # good, see stex.isolated)
    lay = call_in_child(xatlas_layout, V, F, resolution, gutter_px, pack_search_steps)
    info = lay["info"]
    vmap, idx = lay["vmap"], lay["idx"]
    if info["fold_faces"]:
        log.warning("template: %d UV triangles folded inside their chart; split into own charts",
                    info["fold_faces"])
    if lay["best"] is None:
        # every chart takes at least a texel plus its padding, whatever the density
        n_charts = int(uv_charts(idx).max()) + 1  # folded faces included
        raise RuntimeError(f"xatlas could not pack the {n_charts} charts into one {inner}^2 "
                           f"atlas ({resolution}^2, template.atlas_size, less template.gutter_px {gutter_px} "
                           f"on each side) even at {lay['hi'] * scale:.3g} texels per metre; raise "
                           f"template.atlas_size or lower template.gutter_px")
    best_tpu = lay["best_tpu"]
    vmap2, idx2, uv2, util = lay["best"]
    if not np.array_equal(vmap[vmap2[idx2]], F):
        raise RuntimeError("xatlas repack changed the faces")
    texcoords = (uv2 * inner + gutter_px) / resolution  # the inner square, a gutter from each border
    texcoords[:, 1] = 1.0 - texcoords[:, 1]  # xatlas rows -> stex v (front-facing: area < 0)
    texcoords = texcoords.astype(np.float32)
    tfaces = idx2.astype(np.int32)
    flipped = uv_flipped(texcoords, tfaces)
    # Small charts can come back from the repack wholly mirrored: a triangle that pass 1 flattened
    # to a sliver (a mesh from depth), fans of 2-4 slivers at the pole of a noisy 500k-face scan.
    # A chart's corners are its own, so mirroring it inside its own box fixes it without moving
    # it or touching any other chart.
    chart2 = uv_charts(tfaces, len(texcoords))
    n2 = int(chart2.max()) + 1
    chart_faces = np.bincount(chart2, minlength=n2)
    whole = (np.bincount(chart2, flipped, n2) == chart_faces) & (chart_faces > 0)
    if whole.any():
        corner_chart = np.empty(len(texcoords), np.int64)
        corner_chart[tfaces.ravel()] = np.repeat(chart2, 3)
        sel = whole[corner_chart]
        lo = np.full(n2, np.inf)
        hi = np.full(n2, -np.inf)
        np.minimum.at(lo, corner_chart[sel], texcoords[sel, 0])
        np.maximum.at(hi, corner_chart[sel], texcoords[sel, 0])
        c = corner_chart[sel]
        texcoords[sel, 0] = (lo[c] + hi[c] - texcoords[sel, 0]).astype(np.float32)
    info["repack_mirrored_charts"] = int(whole.sum())
    flipped = uv_flipped(texcoords, tfaces)
    if flipped.any():
        bad = np.flatnonzero(flipped)
        raise RuntimeError(f"{len(bad)} UV triangles still mirrored after the fix (faces {bad[:10].tolist()}"
                           f"{' ...' if len(bad) > 10 else ''}, in {len(np.unique(chart2[bad]))} charts that are "
                           f"only partly mirrored)")
    if texcoords.min() < 0 or texcoords.max() > 1:
        raise RuntimeError("texcoords outside [0, 1] after packing")
    face_id, bary = texel_map(texcoords, tfaces, resolution)
    collapsed = uv_signed_area(texcoords, tfaces) == 0
    info.update(charts=n2, texels_per_unit=best_tpu * scale,  # mirroring back kept every chart
                utilization=float((face_id >= 0).mean()), xatlas_utilization=float(util),
                faces_without_texel=int(len(faces_without_texel(face_id, len(F)))),
                degenerate_uv_faces=int(collapsed.sum()), working_scale=scale)
    if collapsed.any():
        log.warning("template: %s", _collapsed_message(vertices, F, collapsed, scale))
    log.info("template: atlas %d^2, %d charts (%d mirrored by xatlas, %d triangles), %.1f%% used, "
             "%.1f s charting + %.1f s packing", resolution, info["charts"], info["flipped_charts"],
             info["flipped_xatlas"], 100 * info["utilization"], info["time_chart_s"], info["time_pack_s"])
    out = (texcoords, tfaces) + ((info,) if return_info else ())
    return out + ((face_id, bary),) if return_texels else out


def _collapsed_message(vertices, faces, collapsed, scale) -> str:
    """Why faces got no area in the atlas and where they are: ``collapsed`` (F,) bool, ``scale``
    the working scale xatlas saw the mesh at."""
    area, quality = face_areas_quality(vertices, faces)
    part = mesh_parts(faces)
    hit = np.bincount(part[collapsed], minlength=int(part.max()) + 1)
    sizes = np.bincount(part)
    worst = np.argsort(-hit, kind="stable")[: min(3, int((hit > 0).sum()))]
    where = ", ".join(f"{hit[k]} of the {sizes[k]} faces of part {k}" for k in worst)
    limit = XATLAS_MIN_AREA / scale ** 2  # in m²
    small = int((collapsed & (area * scale ** 2 < XATLAS_MIN_AREA)).sum())
    thin = int((collapsed & (quality < WELL_SHAPED_QUALITY)).sum())
    return (f"{int(collapsed.sum())} faces have no area in the atlas, so each takes the colour of one texel: "
            f"{small} of them are below xatlas' area limit at the working scale x{scale:.3g} (faces under "
            f"{limit:.2g} m²; the scale follows the median face area, so a small part's faces can be under it), "
            f"{thin} are needle-thin; they lie in {int((hit > 0).sum())} of the mesh's {len(sizes)} connected parts "
            f"(numbered in face order: {where}); enlarge, thicken or remove such parts (template.min_part_faces "
            f"drops parts of few faces)")


def faces_without_texel(face_id, n_faces: int) -> np.ndarray:
    """(N,) int64 ids of the faces whose UV triangle holds no texel centre of the texel map
    ``face_id`` (W, W) int (-1 = empty): they have no texture of their own (a lookup on them reads
    neighbouring texels)."""
    has = np.zeros(int(n_faces), bool)
    fid = np.asarray(face_id)
    has[fid[fid >= 0]] = True
    return np.flatnonzero(~has)


def layout_from_corners(corner_uv):
    """Shared texture coordinates from per-corner ones: (texcoords (Vt, 2) float64, the distinct
    rows of ``corner_uv`` (F, 3, 2) in order of first use; texcoord_faces (F, 3) int32)."""
    t = np.asarray(corner_uv, np.float64).reshape(-1, 2)
    uniq, first, inv = np.unique(t, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return uniq[order], rank[inv.reshape(-1)].reshape(-1, 3).astype(np.int32)


def uv_overlaps(texcoords, texcoord_faces, size: int, face_id=None) -> tuple[int, tuple[int, int] | None]:
    """Texel centres that lie inside two or more UV triangles: (their number, (row, col) of one
    of them or None). The layout is rasterised (:func:`texel_map`) with the faces in order (or
    ``face_id``, that raster if already made) and in reverse; where the two disagree, a centre
    has two owners. The rasteriser counts a centre on an edge as inside every triangle that edge
    bounds, so a centre on a shared edge, or on the touching borders of two charts, has two owners
    too: such a centre counts only when it lies strictly inside both (more than 1e-6 texel from
    their edges)."""
    tf = np.asarray(texcoord_faces, np.int64)
    forward = texel_map(texcoords, tf, size)[0] if face_id is None else np.asarray(face_id)
    backward, _ = texel_map(texcoords, tf[::-1], size)
    backward = np.where(backward >= 0, len(tf) - 1 - backward, -1)
    rows, cols = np.nonzero(forward != backward)
    if len(rows):
        tc = np.asarray(texcoords, np.float64) * size - 0.5        # texel units, centres at integers
        centre = np.column_stack([cols, rows]).astype(np.float64)
        inside = np.ones(len(rows), bool)
        for owner in (forward, backward):
            f = owner[rows, cols]
            ok = f >= 0
            inside &= ok
            inside[ok] &= _strictly_inside(centre[ok], tc[tf[f[ok]]], 1e-6)
        rows, cols = rows[inside], cols[inside]
    return int(len(rows)), ((int(rows[0]), int(cols[0])) if len(rows) else None)


def _strictly_inside(p, tri, eps: float) -> np.ndarray:
    """(n, 2) points, (n, 3, 2) triangles -> (n,) bool: the point lies more than ``eps`` inside
    every edge (either winding; a triangle of zero area contains nothing). Signed areas by
    :func:`uv_signed_area`: of the triangle, and of each edge with the point."""
    idx = np.arange(3 * len(p)).reshape(-1, 3)
    sign = np.sign(uv_signed_area(tri.reshape(-1, 2), idx))
    out = sign != 0
    for i in range(3):
        a, b = tri[:, i], tri[:, (i + 1) % 3]
        twice_area = uv_signed_area(np.stack([a, b, p], 1).reshape(-1, 2), idx)
        out &= sign * twice_area / np.maximum(np.linalg.norm(b - a, axis=1), 1e-300) > eps
    return out


def outside_unit_square(uv) -> np.ndarray:
    """(..., 2) texture coordinates -> (...) bool: not finite or outside [0, 1] (a layout that
    tiles or wraps; a texture slice holds the unit square once)."""
    t = np.asarray(uv, np.float64)
    return ~np.isfinite(t).all(-1) | (t < 0).any(-1) | (t > 1).any(-1)


#: :func:`keep_layout` refuses a layout in which more than this fraction of the faces have zero UV
#: area: most faces would then share single texels (a few collapsed faces are only warned about).
MAX_COLLAPSED_UV_FRACTION = 0.5


def _refuse_collapsed_layout(area, texcoords) -> None:
    """Raise ValueError when more than :data:`MAX_COLLAPSED_UV_FRACTION` of the UV triangles
    (signed areas ``area`` (F,)) have zero area; ``texcoords`` (Vt, 2) for the message."""
    zero = int((area == 0).sum())
    if zero > MAX_COLLAPSED_UV_FRACTION * len(area):
        distinct = len(np.unique(np.asarray(texcoords), axis=0))
        raise ValueError(f"template.uv: mesh: {zero} of the {len(area)} faces have zero area in the mesh's texture "
                         f"coordinates (OBJ vt, glTF TEXCOORD_0; {distinct} distinct coordinate pairs): that is no "
                         f"layout that gives faces texels of their own; use template.uv: xatlas")


def keep_layout(corner_uv, resolution: int):
    """The mesh's own UV layout as the atlas (``template.uv: mesh``), checked for what one texture
    per face needs.

    Args:
        corner_uv: (F, 3, 2) float texture coordinates of each face corner, u right, v down.
        resolution: atlas side W, texels (the layout is read at this size; it is not moved).

    Returns:
        texcoords (Vt, 2) float32, texcoord_faces (F, 3) int32 (as :func:`build_atlas`), info
        dict: ``charts``, ``mirrored_faces`` (UV triangles mirrored in stex's convention: a
        layout may be mirrored as a whole, which nothing downstream minds),
        ``degenerate_uv_faces``, ``overlap_texels`` (0), ``utilization``.

    Raises:
        ValueError: coordinates outside [0, 1] (a layout that tiles or wraps), not finite, or
            UV triangles that overlap (several faces sharing texels, e.g. mirrored halves of a
            game asset painted once): a time-varying texture needs texels of its own for every
            face. Also a layout that holds no texel centre at all, or in which more than
            :data:`MAX_COLLAPSED_UV_FRACTION` of the faces have zero UV area (e.g. every
            coordinate (0, 0): an asset exported without a real layout). The message says where.
    """
    t = np.asarray(corner_uv, np.float64)
    bad = outside_unit_square(t).any(axis=1)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise ValueError(f"template.uv: mesh: {int(bad.sum())} faces have texture coordinates outside [0, 1] or not finite "
                         f"(e.g. {np.round(t[f], 4).tolist()}): a layout that tiles or wraps cannot give every "
                         f"face texels of its own; use template.uv: xatlas")
    texcoords, tfaces = layout_from_corners(t)
    area = uv_signed_area(texcoords, tfaces)
    _refuse_collapsed_layout(area, texcoords)
    face_id, _ = texel_map(texcoords, tfaces, resolution)
    if not (face_id >= 0).any():
        raise ValueError(f"template.uv: mesh: the mesh's texture coordinates (OBJ vt, glTF TEXCOORD_0) hold no texel "
                         f"centre of the {resolution}^2 atlas (template.atlas_size): its UV triangles are too small "
                         f"to carry a texture; use template.uv: xatlas")
    overlap, where = uv_overlaps(texcoords, tfaces, resolution, face_id)
    if overlap:
        r, c = where
        raise ValueError(f"template.uv: mesh: UV triangles overlap at {overlap} texels of the {resolution}^2 atlas "
                         f"(e.g. texel row {r}, column {c}: u {(c + .5) / resolution:.4f}, v {(r + .5) / resolution:.4f}, "
                         f"v down): faces sharing texels cannot each get their own texture (mirrored or "
                         f"stacked islands); lay them out apart, or use template.uv: xatlas")
    info = {"source": "mesh", "charts": int(uv_charts(tfaces, len(texcoords)).max()) + 1,
            "mirrored_faces": int((area > 0).sum()), "degenerate_uv_faces": int((area == 0).sum()),
            "overlap_texels": 0, "utilization": float((face_id >= 0).mean())}
    if info["degenerate_uv_faces"]:
        log.warning("template: %d faces have no area in the mesh's own UV layout: they take the colour of one "
                    "texel", info["degenerate_uv_faces"])
    log.info("template: the mesh's own UV layout at %d^2: %d charts, %.1f%% used, %d of %d triangles mirrored",
             resolution, info["charts"], 100 * info["utilization"], info["mirrored_faces"], len(tfaces))
    return texcoords.astype(np.float32), tfaces, info


def texel_map(texcoords, texcoord_faces, size: int):
    """Rasterise a UV layout: which face and where on it each texel centre lies.

    Texel (r, c) of a size x size atlas samples texcoord ((c + .5) / size, (r + .5) / size).
    A centre on a shared edge goes to one face; where UV triangles overlap, the lowest face
    index wins (see :func:`stex.render.rasterize`).

    Args:
        texcoords: (Vt, 2) float, u right, v down.
        texcoord_faces: (F, 3) int.
        size: atlas side W, texels.

    Returns:
        (face_id (size, size) int32, -1 where no face; bary (size, size, 3) float32, weights of
        the face's corners 0, 1, 2, summing to 1; 0 where no face).
    """
    tc = np.asarray(texcoords, np.float64)
    px = np.column_stack([tc[:, 0] * size - 0.5, tc[:, 1] * size - 0.5, np.ones(len(tc))])
    r = rasterize(px, texcoord_faces, np.eye(3), size, size)
    return r.face_id, r.bary


def atlas_digest(texcoords, texcoord_faces, size: int) -> str:
    """A short fingerprint (16 hex digits) of a UV atlas: its texcoords (Vt, 2), texcoord_faces
    (F, 3) and side ``size``. Texture stores record the one of the template they were made in
    (attr ``atlas_digest``), so that a texture of another atlas of the same side, which would
    read as noise on this one, is refused instead of scored (:func:`check_atlas`)."""
    h = hashlib.sha256(str(int(size)).encode())
    # float32: the fingerprint of one layout does not depend on how its floats were stored
    h.update(np.ascontiguousarray(texcoords, np.float32).tobytes())
    h.update(np.ascontiguousarray(texcoord_faces, np.int32).tobytes())
    return h.hexdigest()[:16]


def border_gap(face_id) -> int:
    """Empty texels between the atlas border and the nearest covered texel (face_id (W, W) int,
    -1 = empty, as :func:`texel_map` returns it); W when nothing is covered."""
    rows, cols = np.nonzero(np.asarray(face_id) >= 0)
    if not len(rows):
        return int(np.shape(face_id)[0])
    H, W = np.shape(face_id)
    return int(min(rows.min(), cols.min(), H - 1 - rows.max(), W - 1 - cols.max()))


def gutter_conflicts(face_id, face_chart, gutter_px: int) -> int:
    """Number of covered texels with a texel of *another* chart within ``gutter_px`` texels
    (Chebyshev distance): 0 means every two charts are at least ``gutter_px`` empty texels
    apart (at texel-centre coverage, as rasterised by :func:`texel_map`)."""
    fid = np.asarray(face_id)
    lab = np.where(fid >= 0, np.asarray(face_chart)[np.maximum(fid, 0)], -1).astype(np.int32)
    if gutter_px <= 0:
        return 0
    size = 2 * int(gutter_px) + 1
    big = int(lab.max()) + 1  # (a huge cval would overflow inside ndimage)
    mx = ndimage.maximum_filter(lab, size=size, mode="constant", cval=-1)
    mn = ndimage.minimum_filter(np.where(lab >= 0, lab, big), size=size, mode="constant", cval=big)
    covered = lab >= 0
    return int((covered & ((mx != lab) | (mn != lab))).sum())
