"""Texture-coordinate stage's artifacts: the ``texcoords`` store (:mod:`stex.texcoords`), the
paper's sampling table as JSON, and the displacement previews."""

from __future__ import annotations

import time

import cv2
import numpy as np

from stex.camera import Calibration
from stex.files import write_json
from stex.io import FrameSequence, create_store, open_store
from stex.preview import label_image, montage, write_png
from stex.texcoords import optimize_texcoords, sampling_table, texcoords_params

__all__ = ["stage_inputs", "write_texcoords", "write_sampling_table", "displacement_picture",
           "preview_texcoords"]


def stage_inputs(scene, template, projection, frames_paths, masks_paths) -> dict:
    """What :func:`stex.texcoords.optimize_texcoords` reads, from a run's stores.

    Args:
        scene: the ``scene`` store (calibration: colour image size).
        template: the ``template`` store (faces).
        projection: the ``projection`` store (phi, vertex_visible, face_visible, face_cos, frame_ids).
        frames_paths: the ``frames`` block stores (colour images, read one frame at a time).
        masks_paths: the ``masks`` block stores (foreground masks for the proxy weights); empty =
            every pixel counts as foreground.

    Returns:
        dict with the keyword arguments of :func:`stex.texcoords.optimize_texcoords` (``load``, ``phi``,
        ``vertex_visible``, ``face_visible``, ``face_weight``, ``faces``, ``image_size``) and
        ``frame_ids``.
    """
    sc = open_store(scene, "scene")
    cal = Calibration.from_dict(sc.attrs["calibration"])
    W, H = cal.color.width, cal.color.height
    proj = open_store(projection, "projection")
    ids = [int(i) for i in proj.attrs["frame_ids"]]
    frames = FrameSequence(list(frames_paths), "frames")
    masks = FrameSequence(list(masks_paths), "masks") if masks_paths else None

    def load(t):
        fid = ids[t]
        grey = cv2.cvtColor(np.asarray(frames.read("color", fid)), cv2.COLOR_RGB2GRAY)
        m = np.asarray(masks.read("mask", fid), bool) if masks is not None else np.ones((H, W), bool)
        return grey, m

    return {"load": load, "phi": np.asarray(proj["phi"][...], np.float64),
            "vertex_visible": np.asarray(proj["vertex_visible"][...], bool),
            "face_visible": np.asarray(proj["face_visible"][...], bool),
            "face_weight": np.asarray(proj["face_cos"][...], np.float64),
            "faces": np.asarray(open_store(template, "template")["faces"][...], np.int64),
            "image_size": (W, H), "frame_ids": ids}


def write_texcoords(scene, template, projection, frames_paths, masks_paths, params: dict, out) -> None:
    """Texture-coordinate stage: write the ``texcoords`` store (arguments: :func:`stage_inputs`;
    ``params``: the ``texcoords`` config section; ``out``: path of the store to write)."""
    p = texcoords_params(params)
    inputs = stage_inputs(scene, template, projection, frames_paths, masks_paths)
    ids = inputs.pop("frame_ids")
    t0 = time.perf_counter()
    r = optimize_texcoords(params=p, **inputs)
    seconds = time.perf_counter() - t0
    attrs = {"frame_ids": ids, "keyframes": [ids[k] for k in r["keyframes"]],
             "color_size": list(inputs["image_size"]), "stages": r["stages"], "seconds": round(seconds, 2),
             "energy_rows": [s["name"] for s in r["stages"]]}
    with create_store(out, "texcoords", attrs=attrs, params=p) as store:
        a = store.create("xi", r["xi"].shape)
        for k in range(len(ids)):
            a[k] = r["xi"][k]
        store.write("valid", r["valid"])
        e = store.create("energy", r["energy"].shape)
        e[...] = r["energy"]


def write_sampling_table(scene, template, projection, frames_paths, masks_paths, params: dict,
                         steps, out_json) -> None:
    """:func:`stex.texcoords.sampling_table` of a run's stores (:func:`stage_inputs`), written as JSON
    ``{"steps": [rows], "params": the texcoords settings}`` to ``out_json`` (written under a
    temporary name and renamed when complete: :func:`stex.files.write_json`)."""
    inputs = stage_inputs(scene, template, projection, frames_paths, masks_paths)
    rows = sampling_table(inputs, params, steps)
    write_json(out_json, {"steps": rows, "params": texcoords_params(params)})


# --------------------------------------------------------------------------------------------
# picture
# --------------------------------------------------------------------------------------------

def displacement_picture(color: np.ndarray, phi, xi, valid, scale: float = 10.0,
                         spacing_px: float = 12.0, max_px: float | None = None) -> np.ndarray:
    """The optimised displacements ξ − Φ of one frame as arrows over its colour image.

    Each drawn vertex gets an arrow from Φ to Φ + ``scale`` · (ξ − Φ), coloured by |ξ − Φ|
    (colormap turbo: dark blue 0 → dark red ``max_px``); the image is dimmed so the arrows
    read. At most one vertex per ``spacing_px`` × ``spacing_px`` cell is drawn (the first
    visible one in vertex order), so dense meshes do not turn into a smear.

    Args:
        color: (Hc, Wc, 3) uint8 RGB colour image of the frame.
        phi: (V, 2) float Φ, colour px (u = column, v = row; integer = pixel centre).
        xi: (V, 2) float ξ, colour px.
        valid: (V,) bool vertices to draw (visible in the frame).
        scale: arrow magnification (1 = true length).
        spacing_px: side of the cells that thin the arrows out (colour px; 0 = every vertex).
        max_px: displacement (px) at the top of the colormap; None = the largest drawn one.

    Returns:
        (Hc, Wc, 3) uint8 RGB picture with a caption giving ``scale`` and ``max_px``.
    """
    color = np.asarray(color)
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"displacement_picture: color must be (H, W, 3) uint8, got {color.shape} {color.dtype}")
    phi = np.asarray(phi, np.float64)
    xi = np.asarray(xi, np.float64)
    valid = np.asarray(valid, bool)
    if phi.ndim != 2 or phi.shape[1] != 2 or xi.shape != phi.shape or valid.shape != phi.shape[:1]:
        raise ValueError(f"displacement_picture: phi {phi.shape}, xi {xi.shape}, valid {valid.shape}: "
                         "expected (V, 2), (V, 2), (V,)")
    if not scale > 0:
        raise ValueError(f"displacement_picture: scale must be > 0, got {scale}")
    H, W = color.shape[:2]
    ok = valid & np.isfinite(phi).all(1) & np.isfinite(xi).all(1)
    ok &= (phi[:, 0] >= 0) & (phi[:, 0] <= W - 1) & (phi[:, 1] >= 0) & (phi[:, 1] <= H - 1)
    idx = np.flatnonzero(ok)
    if spacing_px > 0 and len(idx):
        cell = np.floor(phi[idx] / spacing_px).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        idx = idx[np.sort(first)]
    d = xi[idx] - phi[idx]
    mag = np.linalg.norm(d, axis=1)
    top = float(max_px) if max_px is not None else float(mag.max()) if len(mag) else 1.0
    top = top if top > 0 else 1.0
    img = (color.astype(np.float32) * 0.5).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    col = lut[np.clip(np.round(mag / top * 255), 0, 255).astype(int)]
    a = np.round(phi[idx]).astype(int)
    b = np.round(phi[idx] + scale * d).astype(int)
    thick = max(1, round(min(H, W) / 600))
    for p0, p1, c in zip(a, b, col):  # a few thousand arrows at most: preview only
        cv2.arrowedLine(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])),
                        tuple(int(t) for t in c), thick, cv2.LINE_AA, tipLength=0.3)
    return label_image(img, f"xi - phi x{scale:g}, colour 0..{top:.2f} px, {len(idx)} vertices")


def preview_texcoords(frames_paths, projection_path, texcoords_path, out, n_show: int = 3) -> None:
    """:func:`displacement_picture` of a few frames spread over the sequence, cropped to the
    object, side by side (the paper's figure of displacements)."""
    frames = FrameSequence(list(frames_paths), "frames")
    proj = open_store(projection_path, "projection")
    tc = open_store(texcoords_path, "texcoords")
    ids = list(tc.attrs["frame_ids"])
    tiles = []
    for k in np.linspace(0, len(ids) - 1, min(n_show, len(ids))).round().astype(int):
        valid = np.asarray(tc["valid"][k], bool)
        phi, xi = np.asarray(proj["phi"][k]), np.asarray(tc["xi"][k])
        img = displacement_picture(frames.read("color", ids[k]), phi, xi, valid)
        pts = phi[valid]
        if len(pts):
            (u0, v0), (u1, v1) = np.floor(pts.min(0)).astype(int) - 40, np.ceil(pts.max(0)).astype(int) + 40
            img = img[max(v0, 0):v1, max(u0, 0):u1]
        med = float(np.median(np.linalg.norm(xi[valid] - phi[valid], axis=1))) if valid.any() else 0.0
        tiles.append(label_image(cv2.resize(img, (360, 360), interpolation=cv2.INTER_AREA),
                            f"frame {ids[k]}: median |xi - phi| {med:.2f} px"))
    write_png(out, montage(tiles, columns=len(tiles), width=360 * len(tiles)))
