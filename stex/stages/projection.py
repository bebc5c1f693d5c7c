"""Projection stage, artifact side: :func:`stex.projection.project_frame` over the tracked frames
into the ``projection`` store, and the preview of each frame's visible vertices over its colour."""


from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from stex.camera import Calibration
from stex.io import FrameSequence, create_store, open_store, short_ids
from stex.preview import label_image, montage, write_png
from stex.projection import project_frame, projection_params

log = logging.getLogger("stex.projection")


def write_projection(tracking_path, template_path, scene_path, masks_paths, params: dict, out,
                     frames=None) -> None:
    """Projection stage: write the ``projection`` store for the tracked frames.

    Args:
        tracking_path: the ``tracking`` store (vertices [T, V, 3], depth-camera coordinates).
        template_path: the ``template`` store (faces).
        scene_path: the ``scene`` store (calibration attr).
        masks_paths: the ``masks`` frame-block stores (read one frame at a time); may be empty
            when ``params['use_mask']`` is false.
        params: the ``projection`` config section.
        out: path of the store to write.
        frames: optional list of global frame ids to project (default: every tracked frame), in
            increasing order.

    Streams frame by frame: memory is one frame's mesh, raster and mask. No colour image is read.
    """
    p = projection_params(params)
    scene = open_store(scene_path, "scene")
    template = open_store(template_path, "template")
    tracking = open_store(tracking_path, "tracking")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    F = np.asarray(template["faces"][...], np.int64)
    track_ids = list(tracking.attrs["frame_ids"])
    scene_ids = list(scene.attrs["frame_ids"])
    if track_ids != scene_ids:
        raise ValueError(f"{tracking_path}: tracks frames {short_ids(track_ids)}, but {scene_path} has frames "
                         f"{short_ids(scene_ids)}: a tracking store of another run? Re-run the tracking stage")
    verts = tracking["vertices"]
    if F.size and verts.shape[1] <= int(F.max()):
        raise ValueError(f"{tracking_path}: {verts.shape[1]} vertices per frame but {template_path} "
                         f"faces index vertex {int(F.max())}")
    ids = track_ids if frames is None else [int(f) for f in frames]
    missing = [f for f in ids if f not in track_ids]
    if missing:
        raise ValueError(f"{tracking_path}: frames {missing[:5]} are not tracked (tracked: "
                         f"{track_ids[0]}..{track_ids[-1]})")
    if ids != sorted(set(ids)):
        raise ValueError(f"frames must be increasing and distinct, got {ids[:10]}...")
    pos = {f: i for i, f in enumerate(track_ids)}
    masks = None
    if p["use_mask"]:
        if not masks_paths:
            raise ValueError("projection.use_mask is set but no masks stores were given")
        masks = FrameSequence(list(masks_paths), "masks")
        have = set(masks.frame_ids)
        absent = [f for f in ids if f not in have]
        if absent:
            raise ValueError(f"masks stores hold no mask for frames {absent[:5]}")
    T, V, nF = len(ids), verts.shape[1], F.shape[0]
    Wc, Hc = cal.color.width, cal.color.height
    vis_area = np.zeros(T)
    t0 = time.perf_counter()
    attrs = {"frame_ids": ids, "color_size": [Wc, Hc], "cos_mode": p["cos_mode"]}
    with create_store(out, "projection", attrs=attrs, params=p) as store:
        a_phi = store.create("phi", (T, V, 2))
        a_vvis = store.create("vertex_visible", (T, V))
        a_vcos = store.create("vertex_cos", (T, V))
        a_fvis = store.create("face_visible", (T, nF))
        a_fcos = store.create("face_cos", (T, nF))
        a_fgl = store.create("face_glimpsed", (T, nF))
        for k, fid in enumerate(ids):
            Vd = np.asarray(verts[pos[fid]], np.float64)
            mask = masks.read("mask", fid) if masks is not None else None
            try:
                r = project_frame(Vd, F, cal, p, mask)
            except ValueError as exc:
                raise ValueError(f"{tracking_path}: frame {fid}: {exc}") from exc
            a_phi[k] = r["phi"]
            a_vvis[k] = r["vertex_visible"]
            a_vcos[k] = r["vertex_cos"]
            a_fvis[k] = r["face_visible"]
            a_fcos[k] = r["face_cos"]
            a_fgl[k] = r["face_glimpsed"]
            area = 0.5 * np.linalg.norm(np.cross(Vd[F[:, 1]] - Vd[F[:, 0]], Vd[F[:, 2]] - Vd[F[:, 0]]), axis=1)
            vis_area[k] = area[r["face_visible"]].sum() / max(area.sum(), 1e-30)
            if (k + 1) % 10 == 0 or k + 1 == T:
                log.info("projection: frame %d (%d/%d, %.1f frames/s), %.1f %% of the surface visible",
                         fid, k + 1, T, (k + 1) / (time.perf_counter() - t0), 100 * vis_area[k])
        store.attrs["visible_area_fraction"] = [round(float(x), 5) for x in vis_area]


# --------------------------------------------------------------------------------------------
# preview
# --------------------------------------------------------------------------------------------

def projection_overlay(color: np.ndarray, phi: np.ndarray, visible: np.ndarray, cos: np.ndarray,
                       size: int = 480, title: str = "") -> np.ndarray:
    """(size, size, 3) uint8 RGB picture: the colour image cropped to the visible vertices (square,
    with a margin), dimmed, and each visible vertex's Φ drawn as a dot coloured by its cosine
    (colormap viridis: dark blue 0 -> yellow 1)."""
    H, W = color.shape[:2]
    pts = phi[visible]
    if len(pts):
        lo, hi = pts.min(0), pts.max(0)
        c = (lo + hi) / 2
        half = max(hi - lo) / 2 * 1.15 + 8
    else:
        c, half = np.array([W / 2, H / 2]), min(W, H) / 2
    x0, y0 = int(round(c[0] - half)), int(round(c[1] - half))
    side = max(int(round(2 * half)), 8)
    # crop with zero padding outside the image
    crop = np.zeros((side, side, 3), np.uint8)
    sx0, sy0 = max(x0, 0), max(y0, 0)
    sx1, sy1 = min(x0 + side, W), min(y0 + side, H)
    if sx1 > sx0 and sy1 > sy0:
        crop[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = color[sy0:sy1, sx0:sx1]
    s = size / side
    img = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    img = (img.astype(np.float32) * 0.6).astype(np.uint8)
    if len(pts):
        lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0, ::-1]
        col = lut[np.clip(np.round(cos[visible] * 255), 0, 255).astype(int)]
        q = (pts - [x0, y0] + 0.5) * s - 0.5
        radius = 1 if len(pts) > 3000 else 2
        for (x, y), cc in zip(np.round(q).astype(int), col):  # a few thousand dots: preview only
            cv2.circle(img, (int(x), int(y)), radius, tuple(int(t) for t in cc), -1, cv2.LINE_AA)
    return label_image(img, title) if title else img


def preview_projection(frames_paths: list, projection_path, out, n_show: int = 6) -> None:
    """Write a PNG montage: for ``n_show`` frames spread over the sequence, the visible vertices'
    Φ over the colour image, coloured by cosine (:func:`projection_overlay`)."""
    frames = FrameSequence(list(frames_paths), "frames")
    proj = open_store(projection_path, "projection")
    ids = list(proj.attrs["frame_ids"])
    frac = proj.attrs.get("visible_area_fraction", [None] * len(ids))
    pick = np.unique(np.linspace(0, len(ids) - 1, min(n_show, len(ids))).round().astype(int))
    tiles = []
    for k in pick:
        fid = ids[k]
        vis = proj["vertex_visible"][k]
        title = f"frame {fid}: {int(vis.sum())} vertices"
        if frac[k] is not None:
            title += f", {100 * frac[k]:.0f}% area"
        tiles.append(projection_overlay(frames.read("color", fid), proj["phi"][k], vis,
                                        proj["vertex_cos"][k], title=title))
    write_png(out, montage(tiles))
