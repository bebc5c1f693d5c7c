"""The xatlas work of :func:`stex.atlas.build_atlas`: charting, the chart fix and the repack
search, run in a child process (:func:`stex.isolated.call_in_child`).

This module imports nothing of stex and loads xatlas only inside its functions, so the child
starts quickly and the calling process never loads xatlas. UV conventions as in :mod:`stex.atlas`.
"""

from __future__ import annotations

import time

import numpy as np


# --------------------------------------------------------------------------------------------
# UV atlas
# --------------------------------------------------------------------------------------------

def uv_signed_area(texcoords, texcoord_faces) -> np.ndarray:
    """(F,) float64 signed area of each UV triangle, in texcoord units (u right, v down).

    Negative = front-facing in stex's convention (see the module docstring), positive = mirrored.
    """
    p = np.asarray(texcoords, np.float64)[np.asarray(texcoord_faces)]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]


def _xatlas_pack_options(resolution, gutter_px, rotate, texels_per_unit=0.0):
    import xatlas  # loaded in the child process only (stex.isolated)

    po = xatlas.PackOptions()
    po.resolution = int(resolution)
    po.padding = int(gutter_px)
    po.bilinear = True
    po.rotate_charts = bool(rotate)
    po.texels_per_unit = float(texels_per_unit)
    return po


def _repack(positions, tfaces, uv, resolution, gutter_px, texels_per_unit):
    """xatlas pack of given UV charts into one resolution^2 atlas; None if they do not fit."""
    import xatlas  # loaded in the child process only (stex.isolated)

    a = xatlas.Atlas()
    a.add_mesh(positions.astype(np.float32), tfaces.astype(np.uint32), None, uv.astype(np.float32))
    co = xatlas.ChartOptions()
    co.use_input_mesh_uvs = True
    a.generate(co, _xatlas_pack_options(resolution, gutter_px, False, texels_per_unit))
    if a.atlas_count != 1:
        return None
    if (a.width, a.height) != (resolution, resolution):
        raise RuntimeError(f"xatlas packed into {a.width}x{a.height}, expected {resolution}^2")
    vmap, idx, out_uv = a[0]
    return np.asarray(vmap, np.int64), np.asarray(idx, np.int64), np.asarray(out_uv, np.float64), a.utilization


def xatlas_layout(V, F, resolution, gutter_px, pack_search_steps):
    """xatlas' part of :func:`build_atlas` (steps 1-3 of the module docstring), run in a child
    process by :func:`stex.isolated.call_in_child`.

    Args:
        V: (V, 3) float64 vertices at the working scale; F: (F, 3) int64 faces.
        resolution, gutter_px, pack_search_steps: as :func:`build_atlas`.

    Returns:
        dict: ``vmap`` (Vt,) int64 and ``idx`` (F, 3) int64 (pass 1's texcoord -> vertex map and
        texcoord faces, folded faces split off), ``best``
        (vmap2, idx2, uv2 in [0, 1] of the inner square, xatlas utilisation) of the densest
        repack that fitted, or None, ``best_tpu`` its texel density (per working-scale unit),
        ``hi`` the lowest density that did not fit, ``info`` (flipped_xatlas, flipped_charts,
        fold_faces, time_chart_s, time_pack_s).
    """
    import xatlas  # loaded in the child process only (stex.isolated)

    inner = resolution - 2 * gutter_px
    info: dict = {}
    t0 = time.perf_counter()
    a = xatlas.Atlas()
    a.add_mesh(V.astype(np.float32), F.astype(np.uint32))
    co = xatlas.ChartOptions()
    co.fix_winding = True
    a.generate(co, _xatlas_pack_options(resolution, gutter_px, True))
    vmap, idx, uv = (np.asarray(x) for x in a[0])
    vmap, idx = vmap.astype(np.int64), idx.astype(np.int64)
    if idx.shape != F.shape or not np.array_equal(vmap[idx], F):
        raise RuntimeError("xatlas changed the faces (degenerate faces? run clean_mesh first)")
    w1, h1, tpu1 = a.width, a.height, float(a.texels_per_unit)
    info["time_chart_s"] = time.perf_counter() - t0

    # xatlas' uv have v growing with its image rows, and front-facing = positive area in them
    # (before its packer transposes charts). Work in texel units.
    px = uv.astype(np.float64) * [w1, h1]
    area = uv_signed_area(px, idx)
    info["flipped_xatlas"] = int((area < 0).sum())
    # each texcoord's chart, from xatlas (the same partition as uv_charts, without importing
    # scipy into the child, which would take most of its start; faces xatlas ignored share its
    # "no chart" label and have no UV area, so they are never mirrored either way)
    t_chart = np.unique(np.asarray(a.get_mesh_vertex_assignment(0)[1], np.int64), return_inverse=True)[1]
    t_chart = t_chart.reshape(-1)
    mirrored = np.bincount(t_chart[idx[:, 0]], area, int(t_chart.max()) + 1) < 0
    info["flipped_charts"] = int(mirrored.sum())
    px[mirrored[t_chart], 0] *= -1.0
    fold = uv_signed_area(px, idx) < 0
    info["fold_faces"] = int(fold.sum())
    if fold.any():  # each folded face becomes a chart of its own, mirrored
        fi = np.flatnonzero(fold)
        new = px[idx[fi]].reshape(-1, 2).copy()
        new[:, 0] *= -1.0
        base = len(px)
        px = np.concatenate([px, new])
        vmap = np.concatenate([vmap, vmap[idx[fi]].ravel()])
        idx = idx.copy()
        idx[fi] = base + np.arange(3 * len(fi)).reshape(-1, 3)

    # Repack into exactly inner^2: largest texel density (texels per metre) that fits.
    t1 = time.perf_counter()
    positions = V[vmap]
    uv_in = (px - px.min(0)) / max(float(np.ptp(px, axis=0).max()), 1e-12)
    tpu = tpu1 * inner / max(w1, h1)  # pass 1's density scaled to fill the atlas
    best, lo, hi, tries = None, None, None, 0
    while tries < pack_search_steps or best is None:
        if tries >= pack_search_steps + 30:
            break
        r = _repack(positions, idx, uv_in, inner, gutter_px, tpu)
        tries += 1
        if r is not None:
            best, lo = r, tpu
        else:
            hi = tpu
        if lo is not None and hi is not None and hi / lo < 1.01:
            break
        tpu = 0.92 * tpu if lo is None else 1.08 * tpu if hi is None else 0.5 * (lo + hi)
    info["time_pack_s"] = time.perf_counter() - t1
    return dict(vmap=vmap, idx=idx, best=best, best_tpu=lo, hi=hi, info=info)
