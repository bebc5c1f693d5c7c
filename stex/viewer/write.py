"""``stex view``: write a finished run as a self-contained viewer folder.

The folder (any static file server serves it; nothing is fetched from elsewhere)::

    index.html  viewer.js  viewer.css        the page (stex/viewer/static)
    three/                                   three.js, vendored, with its LICENSE
    view.json                                what the page reads first (see below)
    data/mesh.bin                            GPU vertices: template vertex (uint32), uv (float32 x 2);
                                             triangles (uint32 x 3)
    data/positions.bin                       (T, V, 3) uint16 vertex positions per shown frame
    data/texture/00012.jpg                   the frame's texture slice (or .png)
    data/color/00012.jpg                     the frame's input colour image
    data/labels/00012.png                    the frame's label map in colour (stex.sampling.label_colors)

``view.json`` holds the frame ids, playback rate, the byte layout of the two .bin files, the
position code's offset and step (:func:`stex.viewer.pack.quantize_positions`), the colour
camera's intrinsics, and each frame's image files.
"""

from __future__ import annotations

import io
import json
import logging
import shutil
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from PIL import Image

from stex.export import output_folder, parse_frame_range, select_frames
from stex.files import move_into_place, partial_path
from stex.io import StoreError
from stex.sampling import label_colors
from stex.stages.export import RunResults
from stex.viewer.pack import corner_buffers, quantize_positions, viewer_positions

__all__ = ["write_view", "STATIC", "IMAGE_FORMATS"]

log = logging.getLogger(__name__)

#: the page and the vendored three.js, copied into every viewer folder
STATIC = Path(__file__).with_name("static")
IMAGE_FORMATS = ("jpg", "png")
#: a folder with this file was written by write_view, and may be replaced by it
MANIFEST = "view.json"


def _encode(rgb: np.ndarray, fmt: str, quality: int = 90) -> bytes:
    """(H, W, 3) uint8 RGB -> JPEG or PNG file bytes."""
    args = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpg" else []
    ok, buf = cv2.imencode(f".{fmt}", np.ascontiguousarray(rgb[..., ::-1]), args)
    if not ok:
        raise OSError(f"cannot encode a {rgb.shape[1]}x{rgb.shape[0]} image as {fmt}")
    return buf.tobytes()


def _resized(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    if rgb.shape[:2] == (height, width):
        return rgb
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _label_png(label_map: np.ndarray, side: int) -> bytes:
    """A (W, W) label map as a (side, side) PNG of its colours (:func:`stex.sampling.label_colors`),
    resized nearest first (the colours of a W = 2048 map took longer than everything else of a
    frame). A frame's texels come from few source frames: an indexed PNG of those colours, less
    than half the bytes of RGB; RGB when more than 256 labels."""
    lm = np.asarray(label_map)
    if lm.shape[0] != side:
        lm = cv2.resize(lm, (side, side), interpolation=cv2.INTER_NEAREST)
    labels, index = np.unique(lm, return_inverse=True)
    colors = label_colors(labels[None, :])[0]
    if len(labels) > 256:
        return _encode(colors[index.reshape(lm.shape)], "png")
    img = Image.fromarray(index.reshape(lm.shape).astype(np.uint8), "P")
    img.putpalette(colors.reshape(-1).tolist())
    buf = io.BytesIO()
    img.save(buf, "PNG", compress_level=6)
    return buf.getvalue()


def _check_out(out: Path) -> None:
    """Refuse an existing folder that holds files and is not an earlier viewer folder: the
    folder is replaced as a whole, which must not take a user's other files with it."""
    if out.is_dir() and any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise ValueError(f"--out {out}: a folder that holds other files (no {MANIFEST} of an earlier "
                         f"'stex view'); give a new or empty folder")


def _write_frames(stage: Path, res: RunResults, ids: list[int], image_format: str, quality: int,
                  tex_side: int, color_size: tuple[int, int], labels: bool, progress):
    """Each frame's texture, colour image and label map into ``stage/data``; returns the frames'
    (V, 3) page positions and their ``view.json`` entries."""
    for sub in ("texture", "color") + (("labels",) if labels else ()):
        (stage / "data" / sub).mkdir(parents=True)
    cal = res.calibration
    positions, entries = [], []
    for k, fid in enumerate(ids):
        positions.append(viewer_positions(res.vertices(fid), cal.depth_to_color))
        entry = {"id": fid, "texture": f"data/texture/{fid:05d}.{image_format}",
                 "color": f"data/color/{fid:05d}.{image_format}"}
        tex = _resized(res.texture(fid), tex_side, tex_side)
        (stage / entry["texture"]).write_bytes(_encode(tex, image_format, quality))
        color = _resized(res.color(fid), *color_size)
        (stage / entry["color"]).write_bytes(_encode(color, image_format, quality))
        if labels:
            entry["labels"] = f"data/labels/{fid:05d}.png"
            (stage / entry["labels"]).write_bytes(_label_png(res.label_map(fid), tex_side))
        entries.append(entry)
        if progress:
            progress(k + 1, len(ids))
    return positions, entries


def _write_buffers(data: Path, res: RunResults, positions: list[np.ndarray]) -> dict:
    """``data/mesh.bin`` and ``data/positions.bin``; returns their ``view.json`` entries and
    where the object is at the first frame (centre, radius; m)."""
    code, offset, step = quantize_positions(np.stack(positions))
    layout, at = {}, 0
    with open(data / "mesh.bin", "wb") as fh:
        for name, arr in zip(("vertex_index", "uv", "index"),
                             corner_buffers(res.faces, res.texcoords, res.texcoord_faces)):
            fh.write(arr.tobytes())  # every part is 4-byte items: each starts aligned
            layout[name] = {"offset": at, "count": int(arr.size)}
            at += arr.nbytes
    (data / "positions.bin").write_bytes(code.tobytes())
    first = offset + code[0].astype(np.float64) * step
    return {"n_vertices": int(code.shape[1]),
            "mesh": {"file": "data/mesh.bin", **layout},
            "positions": {"file": "data/positions.bin", "dtype": "uint16", "shape": list(code.shape),
                          "offset": offset.tolist(), "step": step.tolist()},
            "center": first.mean(axis=0).tolist(),
            "radius": float(np.linalg.norm(first - first.mean(axis=0), axis=1).max())}


def write_view(results_dir, out, frames: str | None = None, every: int = 1,
               source: str = "corrected", image_format: str = "jpg", quality: int = 90,
               texture_size: int | None = 1024, color_height: int = 480, labels: bool = True,
               progress: Callable[[int, int | None], None] | None = None) -> Path:
    """Write the viewer folder of the run under ``results_dir`` (= results/<scene>) to ``out``.

    Args:
        results_dir: a finished run's folder: ``scene.zarr``, ``template.zarr``,
            ``tracking.zarr``, ``frames/``, ``<source>/`` (``global_texture.zarr`` for 'global')
            and, for the label overlay, ``volume/``.
        out: output folder: new, empty, or an earlier viewer folder (replaced as a whole, once
            the new one is complete).
        frames: frame-id range as in :func:`stex.export.parse_frame_range` (None = all).
        every: frame step: every ``every``-th frame of the range; playback keeps the capture's
            pace (the frame rate from the timestamps divided by ``every``).
        source: texture shown: 'corrected', 'volume' or 'global' (see :class:`stex.stages.export.RunResults`).
        image_format: 'jpg' or 'png' for the texture and colour images (label maps are PNG).
        quality: JPEG quality, 1..100.
        texture_size: largest texture side written (px); larger atlases are downscaled (area
            average), smaller ones kept. None = the atlas size.
        color_height: height of the colour images written (px; the camera's own when smaller).
        labels: write the label maps (from ``volume/``) for the page's overlay; off for 'global'.
        progress: called as ``progress(done, total)`` per frame.

    Returns:
        The folder's ``index.html``.

    Raises:
        StoreError: a store is missing, incomplete or inconsistent.
        ValueError: a bad option, or ``out`` holds other files.
    """
    if image_format not in IMAGE_FORMATS:
        raise ValueError(f"image format must be one of {IMAGE_FORMATS}, got {image_format!r}")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"JPEG quality must be 1..100, got {quality}")
    if texture_size is not None and int(texture_size) < 16:
        raise ValueError(f"texture size must be at least 16 px, got {texture_size}")
    if int(color_height) < 16:
        raise ValueError(f"colour image height must be at least 16 px, got {color_height}")
    out = output_folder(out)
    _check_out(out)
    res = RunResults(results_dir, source)
    ids = select_frames(res.frame_ids, *parse_frame_range(frames), every=every)
    labels = labels and source != "global"
    cam = res.calibration.color
    res.vertices(ids[0]), res.color(ids[0])  # fail on missing stores before writing anything
    if labels:
        res.label_map(ids[0])
    try:
        fps = res.fps() / every
    except StoreError:
        fps = 30.0 / every
    atlas = res.texture(ids[0]).shape[0]
    tex_side = atlas if texture_size is None else min(atlas, int(texture_size))
    c_h = min(cam.height, int(color_height))
    c_w = max(1, round(cam.width * c_h / cam.height))

    stage = partial_path(out)
    try:
        shutil.copytree(STATIC, stage, ignore=shutil.ignore_patterns("VENDORED.txt"))
        positions, entries = _write_frames(stage, res, ids, image_format, quality, tex_side,
                                           (c_w, c_h), labels, progress)
        manifest = {"format": "stex-view 1", "scene": Path(results_dir).resolve().name,
                    "source": source, "fps": fps, "atlas_size": int(atlas),
                    "texture_size": int(tex_side),
                    # the input colour camera at its own pixel size: the page scales it as
                    # stex.camera.Intrinsics.scaled does
                    "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                               "width": cam.width, "height": cam.height},
                    **_write_buffers(stage / "data", res, positions),
                    "labels": labels, "frames": entries}
        (stage / MANIFEST).write_text(json.dumps(manifest, indent=1))
        move_into_place(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    log.info("view: %d frames written to %s", len(ids), out)
    return out / "index.html"
