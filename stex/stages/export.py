"""Exports of a run's stores: the texture volume under ``results/<scene>/`` as PNG slices, an
MP4, OBJ or glTF meshes (:func:`export_results`, ``stex export``) and the preview video
(:func:`preview_results`, ``stex preview`` and the workflow's ``preview_video`` rule). The
writers over arrays are :mod:`stex.export`'s."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stex.camera import Calibration
from stex.export import (EXPORT_KINDS, SOURCES, Progress, output_file, output_folder, parse_frame_range,
                         select_frames, write_gltf_sequence, write_obj_sequence, write_png_slices,
                         write_preview_video, write_texture_video)
from stex.io import FrameSequence, StoreError, open_store, run_block_paths
from stex.stages.template import check_atlas

__all__ = ["RunResults", "export_results", "preview_results"]


class RunResults:
    """The stores of one ``results/<scene>`` folder that the exports read: the texture slices of
    ``source`` (``volume`` or ``corrected``), the template's atlas, and on demand the tracked
    vertices, colour images and frame rate, each read one frame at a time."""

    def __init__(self, results_dir, source: str = "corrected"):
        if source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
        self.dir = Path(results_dir)
        if not self.dir.is_dir():
            raise StoreError(f"{self.dir}: no such results folder")
        if (self.dir / "zarr.json").exists():
            raise StoreError(f"{self.dir}: a store, not a results folder; give the results/<scene> folder "
                             f"that holds the run's stores")
        self.scene = open_store(self.dir / "scene.zarr", "scene")
        self.textures = FrameSequence(self._blocks(source), source)
        template = open_store(self.dir / "template.zarr", "template")
        check_atlas(zip(self.textures.paths, self.textures.groups), template, self.dir / "template.zarr")
        self.n_vertices = template["vertices"].shape[0]
        self.faces = template["faces"][...]
        self.texcoords = template["texcoords"][...]
        self.texcoord_faces = template["texcoord_faces"][...]
        self._tracking = None
        self._frames = None

    def _blocks(self, kind: str) -> list[Path]:
        return run_block_paths(self.dir, kind, self.scene)

    @property
    def frame_ids(self) -> list[int]:
        return self.textures.frame_ids

    def texture(self, fid: int) -> np.ndarray:
        return self.textures.read("texture", fid)

    def vertices(self, fid: int) -> np.ndarray:
        if self._tracking is None:
            g = open_store(self.dir / "tracking.zarr", "tracking")
            rows = {int(i): k for k, i in enumerate(g.attrs["frame_ids"])}
            if g["vertices"].shape[1] != self.n_vertices:
                raise StoreError(f"{self.dir / 'tracking.zarr'}: {g['vertices'].shape[1]} vertices per "
                                 f"frame, template.zarr has {self.n_vertices}")
            self._tracking = (g, rows)
        g, rows = self._tracking
        if fid not in rows:
            raise StoreError(f"{self.dir / 'tracking.zarr'}: no vertices for frame {fid}")
        vertices = g["vertices"][rows[fid]]
        if not np.isfinite(vertices).all():
            # the tracking writes finite vertices: a store written before chunk checksums, damaged
            # in place, decodes to garbage (a damaged chunk of a newer store does not decode)
            raise StoreError(f"{self.dir / 'tracking.zarr'}: the vertices of frame {fid} are not finite; "
                             f"the store is damaged: re-run the stage that writes it")
        return vertices

    def color(self, fid: int) -> np.ndarray:
        if self._frames is None:
            self._frames = FrameSequence(self._blocks("frames"), "frames")
        if fid not in self._frames.frame_ids:
            raise StoreError(f"{self.dir / 'frames'}: no colour image for frame {fid}")
        return self._frames.read("color", fid)

    @property
    def calibration(self) -> Calibration:
        return Calibration.from_dict(self.scene.attrs["calibration"])

    def fps(self, default: float = 30.0) -> float:
        """Frame rate from the frames' timestamps (median step), else ``default``."""
        seq = FrameSequence(self._blocks("frames"), "frames")
        stamps = np.concatenate([g["timestamps"][...] for g in seq.groups])
        steps = np.diff(stamps)
        steps = steps[steps > 0]
        return float(1.0 / np.median(steps)) if steps.size else default


def export_results(results_dir, what: str, out, frames: str | None = None,
                   source: str = "corrected", fps: float | None = None, crf: int = 18,
                   pix_fmt: str = "yuv420p", progress: Progress | None = None) -> list[Path]:
    """Export the texture volume under ``results_dir`` (= results/<scene>).

    Args:
        results_dir: folder holding ``scene.zarr`` (its ``frame_blocks`` name the blocks),
            ``<source>/block_*.zarr``, ``template.zarr`` and, for meshes, ``tracking.zarr``
            (and ``frames/`` for the video frame rate).
        what: 'png' (``out/texture_00012.png``), 'mp4' (``out/texture.mp4``), 'obj'
            (``out/frame_00012.{obj,mtl,png}``) or 'gltf' (``out/frame_00012.glb``).
        out: output folder.
        frames: frame-id range as in :func:`parse_frame_range` (None = all).
        source: 'corrected' or 'volume' (before colour correction).
        fps: video frame rate; None = from the frames' timestamps (30 if unavailable).
        crf, pix_fmt: video quality and chroma layout (:func:`write_video`).
        progress: called as ``progress(done, total)`` per frame.

    Returns:
        The written files (for obj: the .obj files).

    Raises:
        StoreError: a store is missing, incomplete or inconsistent.
        ValueError: bad ``what``, ``source`` or frame range.
    """
    if what not in EXPORT_KINDS:
        raise ValueError(f"what must be one of {EXPORT_KINDS}, got {what!r}")
    out = output_folder(out)
    res = RunResults(results_dir, source)
    ids = select_frames(res.frame_ids, *parse_frame_range(frames))
    textures = (res.texture(i) for i in ids)
    if what == "png":
        return write_png_slices(textures, ids, out, progress=progress)
    if what == "mp4":
        if fps is None:
            try:
                fps = res.fps()
            except StoreError:
                fps = 30.0
        path = out / "texture.mp4"
        write_texture_video(textures, path, fps=fps, crf=crf, pix_fmt=pix_fmt, total=len(ids),
                            progress=progress)
        return [path]
    res.vertices(ids[0])  # fail on a missing tracking store before writing anything
    verts = (res.vertices(i) for i in ids)
    if what == "obj":
        return write_obj_sequence(verts, res.faces, res.texcoords, res.texcoord_faces, textures,
                                  ids, out, progress=progress)
    return write_gltf_sequence(verts, res.faces, res.texcoords, res.texcoord_faces, textures,
                               ids, out, progress=progress)


def preview_results(results_dir, out_mp4, frames: str | None = None, source: str = "corrected",
                    fps: float | None = None, size: int = 360,
                    progress: Progress | None = None) -> tuple[int, int, int]:
    """:func:`write_preview_video` of the stores under ``results_dir`` (= results/<scene>):
    colour images from ``frames/``, vertices from ``tracking.zarr``, textures from
    ``<source>/``, calibration from ``scene.zarr``. Returns (frames, width, height)."""
    out_mp4 = output_file(out_mp4, ".mp4")
    res = RunResults(results_dir, source)
    ids = select_frames(res.frame_ids, *parse_frame_range(frames))
    calibration = res.calibration
    res.color(ids[0]), res.vertices(ids[0])  # fail on missing stores before encoding starts
    if fps is None:
        fps = res.fps()
    return write_preview_video((res.color(i) for i in ids), (res.vertices(i) for i in ids),
                               res.faces, res.texcoords, res.texcoord_faces,
                               (res.texture(i) for i in ids), calibration, out_mp4, fps=fps,
                               size=size, frame_ids=ids, progress=progress)
