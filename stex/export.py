"""Exports of a reconstructed texture volume: PNG slices, H.264 videos, textured meshes, previews.

What it writes
--------------
- :func:`write_png_slices` — one lossless PNG per texture slice.
- :func:`write_video` / :func:`write_texture_video` — an H.264 MP4 (yuv420p) through PyAV.
- :func:`write_obj_frame` / :func:`write_obj_sequence` — Wavefront OBJ + MTL (+ PNG) per frame.
- :func:`write_gltf_frame` / :func:`write_gltf_sequence` — one binary glTF 2.0 (.glb) per frame,
  texture embedded as PNG.
- :func:`preview_frame` / :func:`write_preview_video` — the input image beside the textured mesh
  rendered from the input camera and from the opposite side.
- :func:`parse_frame_range`, :func:`select_frames`, :func:`output_folder`,
  :func:`output_file` — the command line's frame ranges and output checks.

:func:`stex.stages.export.export_results` / :func:`stex.stages.export.preview_results` do the
same reading the artifact stores under ``results/<scene>/`` (what ``stex export`` and
``stex preview`` run).

Conventions at the boundary (stex itself: see :mod:`stex.camera` and :mod:`stex.render`)
--------------------------------------------------------------------------------------
- **Axes.** stex meshes live in OpenCV depth-camera coordinates (x right, y down, z forward, m).
  Mesh viewers (glTF 2.0, Blender/MeshLab OBJ import) expect y up and look down -z, so mesh
  exports use ``(x, -y, -z)`` (:func:`opencv_to_viewer`): a 180 degree rotation about x, which
  keeps handedness and the counter-clockwise winding, and puts the side the camera saw at +z,
  facing a viewer's default camera. Units stay metres.
- **Texture v.** stex texcoords have v down from the top row of the image (glTF's convention),
  so glTF gets them unchanged; OBJ's ``vt`` has v up from the bottom row, so OBJ gets
  ``1 - v``. Texture images are written as stored (row 0 = v 0 = top).
- **Video sizes.** H.264 in yuv420p needs even widths and heights: an odd-sized image is padded
  by repeating its last column / row (the content keeps its pixel coordinates); the padded size
  is returned.

Writers stream: they take iterables and hold one frame at a time. Files that take long to write
(videos) are written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
from fractions import Fraction
from pathlib import Path
from typing import Callable, Iterable, Iterator

import cv2
import numpy as np

from stex.camera import Calibration, transform_points
from stex.files import partial_path
from stex.metrics import novel_view, render_texture
from stex.render import vertex_normals

__all__ = [
    "opencv_to_viewer",
    "write_png",
    "write_png_slices",
    "write_video",
    "write_texture_video",
    "write_obj_frame",
    "write_obj_sequence",
    "split_seams",
    "write_gltf_frame",
    "write_gltf_sequence",
    "preview_frame",
    "write_preview_video",
    "parse_frame_range",
    "select_frames",
    "output_folder",
    "output_file",
]

log = logging.getLogger(__name__)

Progress = Callable[[int, "int | None"], None]  # (frames done, total or None)

EXPORT_KINDS = ("png", "mp4", "obj", "gltf")
SOURCES = ("volume", "corrected", "global")
PIX_FMTS = ("yuv420p", "yuv444p")


# --------------------------------------------------------------------------------------------
# checks and small helpers
# --------------------------------------------------------------------------------------------

def _rgb_image(img, what: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"{what} must be an (H, W, 3) uint8 RGB image, got shape {a.shape} dtype {a.dtype}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{what} is empty (shape {a.shape})")
    return a


def _mesh(vertices, faces, texcoords, texcoord_faces):
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise ValueError(f"vertices must be finite with shape (V, 3), got shape {v.shape}")
    f = np.asarray(faces)
    tc = np.asarray(texcoords, dtype=np.float64)
    tf = np.asarray(texcoord_faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integer with shape (F, 3), got shape {f.shape} dtype {f.dtype}")
    if tc.ndim != 2 or tc.shape[1] != 2 or not np.isfinite(tc).all():
        raise ValueError(f"texcoords must be finite with shape (Vt, 2), got shape {tc.shape}")
    if tf.shape != f.shape or not np.issubdtype(tf.dtype, np.integer):
        raise ValueError(f"texcoord_faces must be integer with the shape of faces {f.shape}, got {tf.shape}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices out of range 0..{len(v) - 1} (min {f.min()}, max {f.max()})")
    if tf.size and (tf.min() < 0 or tf.max() >= len(tc)):
        raise ValueError(f"texcoord_faces index texcoords out of range 0..{len(tc) - 1} (min {tf.min()}, max {tf.max()})")
    return v, f.astype(np.int64), tc, tf.astype(np.int64)


def opencv_to_viewer(points) -> np.ndarray:
    """(..., 3) OpenCV camera coordinates (x right, y down, z forward) -> viewer coordinates
    (x right, y up, z toward the viewer): ``(x, -y, -z)``, float64, same units."""
    p = np.array(points, dtype=np.float64)
    p[..., 1:] *= -1.0
    return p


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.stem}.partial{path.suffix}")


@contextlib.contextmanager
def _written_whole(path):
    """Yield a hidden temporary path next to ``path``; rename it to ``path`` when the block
    completes, remove it when the block fails or is interrupted: an exported file under its
    final name is always complete."""
    path = Path(path)
    tmp = _tmp_name(path)
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


@contextlib.contextmanager
def _written_as_a_set(out_dir: Path):
    """Yield a hidden folder inside ``out_dir`` for a sequence of files; move them into
    ``out_dir`` when the block completes, remove them when it fails or is interrupted: a killed
    export of 265 slices used to leave the slices it had reached, each whole, with nothing to say
    that the set was not. A dead writer's left-over folder is removed by the next export there."""
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = partial_path(out_dir / ".stex-export")
    stage.mkdir()
    try:
        yield stage
        for f in sorted(stage.iterdir()):
            os.replace(f, out_dir / f.name)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    stage.rmdir()


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write one (H, W, 3) uint8 RGB image as a lossless PNG at ``path``, whole or not at all
    (written beside it, then moved into place)."""
    # cv2 takes BGR. Its default PNG settings were the fastest (docs/decisions/export.md).
    with _written_whole(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"cannot write image {path}")


# --------------------------------------------------------------------------------------------
# images and videos
# --------------------------------------------------------------------------------------------

#: File name of a texture slice exported as PNG (also what ``stex evaluate --texture`` reads).
PNG_SLICE_NAME = "texture_{frame:05d}.png"


def write_png_slices(textures: Iterable, frame_ids: Iterable[int], out_dir,
                     pattern: str = PNG_SLICE_NAME,
                     progress: Progress | None = None) -> list[Path]:
    """Write each texture slice as a lossless PNG.

    Args:
        textures: iterable of (W, W, 3) uint8 RGB slices (row 0 = v 0, as stored).
        frame_ids: the global frame id of each slice (same length as ``textures``).
        out_dir: directory, created if missing.
        pattern: file name with a ``{frame}`` field.
        progress: called as ``progress(done, total)`` after each file.

    Returns:
        The written paths, in order.
    """
    def write_one(folder, name, rgb):
        write_png(folder / name, rgb)
        return folder / name

    return _per_frame(None, textures, frame_ids, Path(out_dir), pattern, write_one, progress)


def _even(img: np.ndarray) -> np.ndarray:
    """Pad an (H, W, 3) image to even H and W by repeating its last row / column."""
    H, W = img.shape[:2]
    if H % 2 == 0 and W % 2 == 0:
        return img
    return np.pad(img, ((0, H % 2), (0, W % 2), (0, 0)), mode="edge")


def _rate(fps) -> Fraction:
    try:
        if not isinstance(fps, (int, float, Fraction, np.integer, np.floating)):
            raise TypeError  # Fraction("30") parses text, which the range check cannot compare
        rate = Fraction(fps).limit_denominator(1001) if not isinstance(fps, Fraction) else fps
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"fps must be a positive finite number, got {fps!r}") from None
    if not (rate > 0 and 0.01 <= fps <= 1000):  # the encoder's time base takes no more
        raise ValueError(f"fps must be 0.01 .. 1000, got {fps!r}")
    return rate


def write_video(images: Iterable, out_mp4, fps: float = 30.0, crf: int = 18, preset: str = "medium",
                pix_fmt: str = "yuv420p", total: int | None = None,
                progress: Progress | None = None) -> tuple[int, int, int]:
    """Encode RGB images into an H.264 MP4 (libx264) with PyAV, streaming.

    Args:
        images: iterable of (H, W, 3) uint8 RGB images, all the same size. For yuv420p, odd H or
            W are padded to even by repeating the last row / column (chroma is subsampled 2x2).
        out_mp4: output path; written as a hidden temporary file and renamed when complete.
        fps: frames per second (float or Fraction; 29.97 -> 2997/100).
        crf: x264 constant rate factor, 0 .. 51 (lower: better and larger).
        preset: x264 speed/size preset.
        pix_fmt: 'yuv420p' (plays everywhere) or 'yuv444p' (full-resolution chroma, High 4:4:4
            profile, which many browsers and hardware decoders refuse). yuv420p's subsampled
            chroma alone caps the fidelity of sharp colour detail (docs/decisions/export.md).
        total: number of images if known (for ``progress``).
        progress: called as ``progress(done, total)`` after each encoded frame.

    Returns:
        (frames written, encoded width, encoded height).
    """
    import av  # PyAV (FFmpeg) is loaded only when a video is written

    rate = _rate(fps)
    if pix_fmt not in PIX_FMTS:
        raise ValueError(f"pix_fmt must be one of {PIX_FMTS}, got {pix_fmt!r}")
    even = pix_fmt == "yuv420p"
    if not 0 <= int(crf) <= 51:
        raise ValueError(f"crf must be in 0..51, got {crf}")
    out = Path(out_mp4)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    # closed before the rename, and on failure before the temporary file is removed
    with _written_whole(out) as tmp, contextlib.closing(av.open(str(tmp), mode="w", format="mp4")) as container:
        stream, size = None, None
        for img in images:
            img = _rgb_image(img, f"video frame {n}")
            if size is None:
                size = img.shape[:2]
                if even and (size[0] % 2 or size[1] % 2):
                    log.info("%s: odd frame size %dx%d padded to even for yuv420p",
                             out, size[1], size[0])
                padded = _even(img) if even else img
                stream = container.add_stream("libx264", rate=rate)
                stream.width, stream.height = padded.shape[1], padded.shape[0]
                stream.pix_fmt = pix_fmt
                stream.options = {"crf": str(int(crf)), "preset": preset}
            elif img.shape[:2] != size:
                raise ValueError(f"video frame {n} has size {img.shape[1]}x{img.shape[0]}, "
                                 f"the first frame {size[1]}x{size[0]}")
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(_even(img) if even else img),
                                               format="rgb24")
            frame.pts = n
            frame.time_base = 1 / rate
            container.mux(stream.encode(frame))
            n += 1
            if progress:
                progress(n, total)
        if stream is None:
            raise ValueError(f"{out}: no frames to write")
        container.mux(stream.encode(None))
        W, H = stream.width, stream.height
    return n, W, H


def write_texture_video(textures: Iterable, out_mp4, fps: float = 30.0, crf: int = 18,
                        pix_fmt: str = "yuv420p", total: int | None = None,
                        progress: Progress | None = None) -> tuple[int, int, int]:
    """The texture volume as a video: one (W, W, 3) uint8 slice per video frame, row 0 at the
    top (v 0). See :func:`write_video` (in yuv420p an odd W is padded to W + 1; a 4096^2 atlas
    encodes at H.264 level 6.0, which some players refuse). Returns (frames, width, height)."""
    return write_video(textures, out_mp4, fps=fps, crf=crf, pix_fmt=pix_fmt, total=total,
                       progress=progress)


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------

def write_obj_frame(path_obj, vertices, faces, texcoords, texcoord_faces, texture_png_name: str,
                    material: str = "texture", viewer_axes: bool = True) -> tuple[Path, Path]:
    """Write one textured mesh as Wavefront OBJ plus its MTL (``path_obj`` with suffix .mtl).

    The PNG named ``texture_png_name`` (relative to the OBJ's folder) is not written here.

    Args:
        path_obj: output .obj path.
        vertices: (V, 3) float, OpenCV camera coordinates, metres.
        faces: (F, 3) int, counter-clockwise seen from outside.
        texcoords: (Vt, 2) float stex texcoords (u right, v down from the top row).
        texcoord_faces: (F, 3) int indices into ``texcoords`` (UV seams are kept as OBJ ``vt``
            indices; nothing is split).
        texture_png_name: file name of the texture, written into the MTL's ``map_Kd``.
        viewer_axes: write ``(x, -y, -z)`` (y up; see the module docstring); False keeps OpenCV axes.

    Returns:
        (obj path, mtl path). ``vt`` rows hold ``(u, 1 - v)`` (OBJ: v up from the bottom row).
    """
    v, f, tc, tf = _mesh(vertices, faces, texcoords, texcoord_faces)
    path_obj = Path(path_obj)
    path_mtl = path_obj.with_suffix(".mtl")
    if viewer_axes:
        v = opencv_to_viewer(v)
    vt = np.column_stack([tc[:, 0], 1.0 - tc[:, 1]])
    corners = np.empty((len(f), 6), dtype=np.int64)  # OBJ indices are 1-based: v/vt per corner
    corners[:, 0::2] = f + 1
    corners[:, 1::2] = tf + 1
    axes = ("x right, y up, z toward the viewer = OpenCV camera (x, -y, -z)" if viewer_axes
            else "OpenCV camera: x right, y down, z forward")
    # the .obj last: it names the .mtl (which names the texture), so an .obj on disk is whole
    with _written_whole(path_mtl) as tmp, open(tmp, "w") as fh:
        fh.write(f"newmtl {material}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
                 f"map_Kd {texture_png_name}\n")
    with _written_whole(path_obj) as tmp, open(tmp, "w") as fh:
        fh.write(f"# stex textured mesh; metres; axes: {axes}\n")
        fh.write(f"mtllib {path_mtl.name}\n")
        np.savetxt(fh, v, fmt="v %.7g %.7g %.7g")
        np.savetxt(fh, vt, fmt="vt %.8f %.8f")
        fh.write(f"usemtl {material}\n")
        np.savetxt(fh, corners, fmt="f %d/%d %d/%d %d/%d")
    return path_obj, path_mtl


def _refuse_other_frames(out_dir: Path, pattern: str, ids: list[int]) -> None:
    """Refuse (ValueError) an ``out_dir`` that holds files of ``pattern`` (any extension) for
    frames other than ``ids``: an export of frames 2-3 into a folder of an earlier export of
    0-5 would leave a mixed set that reads as one (``stex evaluate --texture`` scores whatever
    file a frame has). Files of the same frames are replaced, as a re-export should."""
    if "{frame" not in pattern or not Path(out_dir).is_dir():
        return
    head, tail = pattern.split("{frame", 1)[0], pattern.split("}", 1)[1]
    form = re.compile(re.escape(head) + r"(\d+)" + re.escape(tail) + r"(\.\w+)*")
    want = set(ids)
    other = sorted(f.name for f in Path(out_dir).iterdir()
                   if (m := form.fullmatch(f.name)) and int(m.group(1)) not in want)
    if other:
        raise ValueError(f"{out_dir} already holds {len(other)} file(s) of other frames ({', '.join(other[:3])}"
                         f"{', ...' if len(other) > 3 else ''}), which this export would leave beside its "
                         f"own as if one set: give a new or empty folder, or remove them")


def _per_frame(vertices_seq, textures, frame_ids, out_dir: Path, pattern: str, write_one,
               progress) -> list[Path]:
    """Call ``write_one(folder, pattern.format(frame=id), [vertices,] rgb) -> path`` for every
    frame (without vertices when ``vertices_seq`` is None), all in one :func:`_written_as_a_set`
    folder; returns the paths under ``out_dir``."""
    ids = [int(i) for i in frame_ids]
    names = [pattern.format(frame=i) for i in ids]
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"frames would share the file names {twice[:3]} (frame ids repeated, or a "
                         f"pattern {pattern!r} without {{frame}})")
    _refuse_other_frames(out_dir, pattern, ids)
    paths = []
    with _written_as_a_set(out_dir) as stage:
        frames = zip(textures) if vertices_seq is None else zip(vertices_seq, textures, strict=True)
        for k, (*verts, tex) in enumerate(frames):
            if k >= len(ids):
                raise ValueError(f"more frames than frame_ids ({len(ids)})")
            p = write_one(stage, pattern.format(frame=ids[k]), *verts,
                          _rgb_image(tex, f"texture of frame {ids[k]}"))
            paths.append(out_dir / p.name)
            if progress:
                progress(k + 1, len(ids))
        if len(paths) != len(ids):
            raise ValueError(f"{len(ids)} frame_ids but {len(paths)} frames")
    return paths


def write_obj_sequence(vertices_seq: Iterable, faces, texcoords, texcoord_faces, textures: Iterable,
                       frame_ids: Iterable[int], out_dir, pattern: str = "frame_{frame:05d}",
                       viewer_axes: bool = True, progress: Progress | None = None,
                       shared_png: str | None = None) -> list[Path]:
    """One OBJ + MTL + PNG per frame: ``out_dir/frame_00012.{obj,mtl,png}``.

    Args:
        vertices_seq: iterable of (V, 3) float per-frame vertices (OpenCV camera coords, m).
        faces, texcoords, texcoord_faces: the fixed template topology and atlas.
        textures: iterable of (W, W, 3) uint8 slices, one per frame.
        frame_ids: global frame id of each frame (names the files).
        pattern: file stem with a ``{frame}`` field.
        viewer_axes, progress: as in :func:`write_obj_frame` / :func:`write_png_slices`.
        shared_png: the frames share one texture (e.g. the global texture): the first frame's
            is written once under this file name, which every MTL names, instead of a PNG per
            frame (the others are not read back).

    Returns:
        The OBJ paths, in order.
    """
    def write_one(folder, stem, verts, rgb):
        png = shared_png or f"{stem}.png"
        if not (shared_png and (folder / png).exists()):
            write_png(folder / png, rgb)
        return write_obj_frame(folder / f"{stem}.obj", verts, faces, texcoords, texcoord_faces,
                               png, viewer_axes=viewer_axes)[0]

    out_dir = Path(out_dir)
    return _per_frame(vertices_seq, textures, frame_ids, out_dir, pattern, write_one, progress)


def split_seams(faces, texcoord_faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-corner attribute layout (glTF, GPUs): one output vertex per distinct (vertex, texcoord) pair.

    Args:
        faces: (F, 3) int position indices. texcoord_faces: (F, 3) int texcoord indices.

    Returns:
        vertex_index: (N,) int64, the position of each output vertex.
        texcoord_index: (N,) int64, its texcoord.
        new_faces: (F, 3) int64 triangles into the N output vertices (same corner order).
    """
    f = np.asarray(faces, dtype=np.int64)
    tf = np.asarray(texcoord_faces, dtype=np.int64)
    if f.shape != tf.shape:
        raise ValueError(f"faces {f.shape} and texcoord_faces {tf.shape} must have the same shape")
    pairs = np.stack([f.ravel(), tf.ravel()], axis=1)
    uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uniq[:, 1], inverse.reshape(f.shape)


def write_gltf_frame(path, vertices, faces, texcoords, texcoord_faces, texture,
                     viewer_axes: bool = True) -> None:
    """Write one textured mesh as binary glTF 2.0 (.glb) with its texture embedded as PNG.

    Vertices are split where the atlas has seams (:func:`split_seams`), so the .glb has one
    vertex per distinct (position, texcoord) corner pair; smooth normals are computed on the
    unsplit mesh so seams do not show in shading. ``TEXCOORD_0`` holds the stex texcoords
    unchanged (glTF's v is down from the top row, as stex's). The material is unlit-looking PBR
    (metallic 0, roughness 1), double-sided so open templates show their inside.

    Args:
        path: output .glb path.
        vertices: (V, 3) float, OpenCV camera coordinates, metres (written as ``(x, -y, -z)``,
            glTF's y up / +z front, unless ``viewer_axes`` is False).
        faces: (F, 3) int. texcoords: (Vt, 2) float. texcoord_faces: (F, 3) int.
        texture: (H, W, 3) uint8 RGB, row 0 = v 0.
    """
    import trimesh  # trimesh loads slowly; only glTF exports need it
    from PIL import Image  # with trimesh: it embeds the texture as a PIL image
    from trimesh.visual import TextureVisuals  # trimesh's, as above
    from trimesh.visual.material import PBRMaterial  # trimesh's, as above

    v, f, tc, tf = _mesh(vertices, faces, texcoords, texcoord_faces)
    tex = _rgb_image(texture, "texture")
    if viewer_axes:
        v = opencv_to_viewer(v)
    vi, ti, new_faces = split_seams(f, tf)
    normals = vertex_normals(v, f)[vi]
    # trimesh keeps UVs with v up (OBJ) and writes 1 - v into glTF: hand it 1 - v_stex.
    uv = np.column_stack([tc[ti, 0], 1.0 - tc[ti, 1]])
    material = PBRMaterial(name="texture", baseColorTexture=Image.fromarray(tex),
                           metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True)
    mesh = trimesh.Trimesh(v[vi], new_faces, vertex_normals=normals,
                           visual=TextureVisuals(uv=uv, material=material), process=False)
    data = trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), include_normals=True)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _written_whole(path) as tmp:
        tmp.write_bytes(data)


def write_gltf_sequence(vertices_seq: Iterable, faces, texcoords, texcoord_faces, textures: Iterable,
                        frame_ids: Iterable[int], out_dir, pattern: str = "frame_{frame:05d}.glb",
                        viewer_axes: bool = True, progress: Progress | None = None) -> list[Path]:
    """One .glb per frame (:func:`write_gltf_frame`): ``out_dir/frame_00012.glb``.

    Arguments as in :func:`write_obj_sequence`. Returns the written paths, in order.
    """
    def write_one(folder, name, verts, rgb):
        write_gltf_frame(folder / name, verts, faces, texcoords, texcoord_faces, rgb,
                         viewer_axes=viewer_axes)
        return folder / name

    out_dir = Path(out_dir)
    return _per_frame(vertices_seq, textures, frame_ids, out_dir, pattern, write_one, progress)


# --------------------------------------------------------------------------------------------
# previews
# --------------------------------------------------------------------------------------------

def _label(img: np.ndarray, text: str) -> np.ndarray:
    h = max(12, img.shape[0] // 18)
    scale = h / 28.0
    cv2.rectangle(img, (0, 0), (img.shape[1], h + 6), (0, 0, 0), -1)
    cv2.putText(img, text, (4, h), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def preview_frame(color_t, vertices_t, faces, texcoords, texcoord_faces, texture_t,
                  calibration: Calibration, size: int = 360, frame_id: int | None = None,
                  background: int = 48) -> np.ndarray:
    """One preview image: the input colour image, the textured mesh rendered from the input
    camera, and from the opposite side, side by side and labelled.

    The opposite side is the mesh rotated by 180 degrees about the colour camera's vertical (y)
    axis through the vertex centroid (:func:`stex.metrics.novel_view`), seen by the same camera.
    Renders use the colour camera's intrinsics scaled to the panel height (no supersampling).

    Args:
        color_t: (Hc, Wc, 3) uint8 RGB input image of the frame.
        vertices_t: (V, 3) float vertices at the frame, depth-camera coordinates, metres.
        faces, texcoords, texcoord_faces: template topology and atlas (stex texcoords).
        texture_t: (W, W, 3) uint8 texture slice of the frame.
        calibration: the sensor (colour intrinsics, depth_to_color).
        size: panel height in pixels (rounded up to even).
        frame_id: written into the input panel's label.
        background: grey level behind the rendered mesh.

    Returns:
        (H, 3 * W', 3) uint8 RGB with H = ``size`` (even) and W' the scaled colour width
        (the total width is made even).
    """
    color = _rgb_image(color_t, "color_t")
    cam = calibration.color
    if color.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"color_t is {color.shape[1]}x{color.shape[0]} but the calibrated colour "
                         f"camera is {cam.width}x{cam.height}")
    tex = _rgb_image(texture_t, "texture_t")
    v, f, tc, tf = _mesh(vertices_t, faces, texcoords, texcoord_faces)
    size = int(size)
    if size < 16:
        raise ValueError(f"preview size must be at least 16 px, got {size}")
    size += size % 2
    small = cam.scaled(size / cam.height)
    w, h = small.width, size
    vc = transform_points(calibration.depth_to_color, v)
    panels = [cv2.resize(color, (w, h), interpolation=cv2.INTER_AREA)]
    for verts in (vc, transform_points(novel_view(vc, 180.0), vc)):
        img, mask = render_texture(verts, f, tc, tf, tex, small.K, w, h)
        out = np.full((h, w, 3), background, np.uint8)
        out[mask] = img[mask].astype(np.uint8)
        panels.append(out)
    labels = ["input" if frame_id is None else f"input, frame {frame_id}",
              "texture, input view", "texture, opposite side"]
    panels = [_label(np.ascontiguousarray(p), t) for p, t in zip(panels, labels)]
    return _even(np.concatenate(panels, axis=1))


def write_preview_video(colors: Iterable, vertices_seq: Iterable, faces, texcoords, texcoord_faces,
                        textures: Iterable, calibration: Calibration, out_mp4, fps: float = 30.0,
                        size: int = 360, frame_ids: Iterable[int] | None = None, crf: int = 20,
                        total: int | None = None, progress: Progress | None = None) -> tuple[int, int, int]:
    """Stream :func:`preview_frame` of every frame into an MP4 (:func:`write_video`).

    ``colors``, ``vertices_seq`` and ``textures`` are parallel iterables (one item per frame);
    ``frame_ids`` (optional) label the frames. Returns (frames, width, height).
    """
    ids = None if frame_ids is None else [int(i) for i in frame_ids]

    def frames() -> Iterator[np.ndarray]:
        for k, (c, vt, tex) in enumerate(zip(colors, vertices_seq, textures, strict=True)):
            yield preview_frame(c, vt, faces, texcoords, texcoord_faces, tex, calibration,
                                size=size, frame_id=None if ids is None else ids[k])

    if total is None and ids is not None:
        total = len(ids)
    return write_video(frames(), out_mp4, fps=fps, crf=crf, total=total, progress=progress)


# --------------------------------------------------------------------------------------------
# the command line's frame ranges and outputs (stex export / stex preview)
# --------------------------------------------------------------------------------------------

def parse_frame_range(text: str | None) -> tuple[int | None, int | None]:
    """``"10:20"`` -> (10, 20) (frame ids 10..19), ``"12"`` -> (12, 13), ``"10:"``, ``":20"``,
    ``None`` / ``":"`` -> all. Raises ValueError on anything else."""
    if text is None or text.strip() in ("", ":"):
        return None, None
    parts = text.split(":")
    try:
        if len(parts) == 1:
            a = int(parts[0])
            return a, a + 1
        if len(parts) == 2:
            return (int(parts[0]) if parts[0].strip() else None,
                    int(parts[1]) if parts[1].strip() else None)
    except ValueError:
        pass
    raise ValueError(f"frame range {text!r}: expected START:STOP (frame ids, STOP excluded), "
                     f"START:, :STOP or one frame id")


def select_frames(frame_ids, start: int | None, stop: int | None, every: int = 1) -> list[int]:
    """The frame ids ``start <= id < stop`` of a sequence, then every ``every``-th of them from
    the first; ValueError when the range is empty or reaches outside the sequence's ids."""
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"frame step must be an integer of 1 or more, got {every!r}")
    ids = [int(i) for i in frame_ids]
    if not ids:
        raise ValueError("the sequence has no frames")
    lo, hi = ids[0], ids[-1]
    a = lo if start is None else start
    b = hi + 1 if stop is None else stop
    if not (lo <= a < b <= hi + 1):
        raise ValueError(f"frame range {a}:{b} is outside the sequence (frames {lo}..{hi}) or empty")
    return [i for i in ids if a <= i < b][::every]


def _check_writable(folder: Path, what: str, text) -> None:
    """Refuse (ValueError naming ``text``) an output whose nearest existing folder cannot take a
    new file, before any work is done: a probe file is created there and removed."""
    base = folder
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise ValueError(f"{what} {text}: {base} is a file, not a folder")
    try:
        with tempfile.NamedTemporaryFile(dir=base, prefix=".stex-probe-"):
            pass
    except OSError as exc:
        raise ValueError(f"{what} {text}: cannot write into {base} ({exc.strerror or exc})") from None


def output_folder(out, what: str = "--out") -> Path:
    """``out`` as an output folder: refused (ValueError) when it is an existing file or cannot be
    written, before any work is done."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what} {out}: is a file; give a folder")
    _check_writable(out, what, out)
    return out


def output_file(out, suffix: str, what: str = "--out") -> Path:
    """``out`` as an output file with ``suffix`` (e.g. '.mp4'): refused (ValueError) when it is a
    folder, ends in a slash or has another suffix, before any work is done; its folder is created."""
    text = str(out)
    out = Path(out)
    if text.endswith(("/", os.sep)) or out.is_dir():
        raise ValueError(f"{what} {text}: is a folder; give a {suffix} file name")
    if out.suffix.lower() != suffix:
        raise ValueError(f"{what} {text}: give a {suffix} file name")
    _check_writable(out.parent, what, text)
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


