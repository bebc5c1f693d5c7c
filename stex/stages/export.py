"""Exports of a run's stores: the texture volume under ``results/<scene>/`` as PNG slices, an
MP4, OBJ or glTF meshes (:func:`export_results`, ``stex export``) and the preview video
(:func:`preview_results`, ``stex preview`` and the workflow's ``preview_video`` rule). The
writers over arrays are :mod:`stex.export`'s."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stex.camera import Calibration
from stex.export import (EXPORT_KINDS, SOURCES, Progress, output_file, output_folder, parse_frame_range,
                         select_frames, write_gltf_sequence, write_obj_sequence, write_png,
                         write_png_slices, write_preview_video, write_texture_video)
from stex.io import FrameSequence, StoreError, open_store, run_block_paths
from stex.stages.template import check_atlas

__all__ = ["RunResults", "export_results", "preview_results"]


class RunResults:
    """The stores of one finished ``results/<scene>`` folder that the exports and the viewer read.

    ``source`` names the texture of every frame: 'corrected' or 'volume' (the frame-block stores
    of that kind), or 'global' (``global_texture.zarr``: one texture, the same for every frame).
    """

    def __init__(self, results_dir, source: str = "corrected"):
        if source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
        self.dir = Path(results_dir)
        self.source = source
        if not self.dir.is_dir():
            raise StoreError(f"{self.dir}: no such results folder")
        if (self.dir / "zarr.json").exists():
            raise StoreError(f"{self.dir}: a store, not a results folder; give the results/<scene> folder "
                             f"that holds the run's stores")
        self.scene = open_store(self.dir / "scene.zarr", "scene")
        template = open_store(self.dir / "template.zarr", "template")
        if source == "global":
            path = self.dir / "global_texture.zarr"
            store = open_store(path, "global_texture")
            check_atlas([(path, store)], template, self.dir / "template.zarr")
            self._global = np.asarray(store["texture"][...], np.uint8)
            self.textures = None
        else:
            self.textures = FrameSequence(self._blocks(source), source)
            check_atlas(zip(self.textures.paths, self.textures.groups), template, self.dir / "template.zarr")
        self.n_vertices = template["vertices"].shape[0]
        self.faces = template["faces"][...]
        self.texcoords = template["texcoords"][...]
        self.texcoord_faces = template["texcoord_faces"][...]
        self._tracking = None
        self._frames = None
        self._volume = None

    def _blocks(self, kind: str) -> list[Path]:
        return run_block_paths(self.dir, kind, self.scene)

    @property
    def frame_ids(self) -> list[int]:
        """The frames that have a texture: the texture blocks' frames; every frame of the scene
        for the global texture."""
        if self.textures is None:
            return [int(i) for i in self.scene.attrs["frame_ids"]]
        return self.textures.frame_ids

    def texture(self, fid: int) -> np.ndarray:
        """(W, W, 3) uint8 RGB texture of frame ``fid`` (row 0 = v 0)."""
        if self.textures is None:
            return self._global
        return self.textures.read("texture", fid)

    def label_map(self, fid: int) -> np.ndarray:
        """(W, W) int16 label map of frame ``fid`` from the volume blocks: the source frame
        (position in the sequence) each texel was sampled from, -1 = none."""
        if self._volume is None:
            self._volume = FrameSequence(self._blocks("volume"), "volume")
        if fid not in self._volume.frame_ids:
            raise StoreError(f"{self.dir / 'volume'}: no label map for frame {fid}")
        return self._volume.read("label_map", fid)

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
                   pix_fmt: str = "yuv420p", every: int = 1,
                   progress: Progress | None = None) -> list[Path]:
    """Export the texture volume under ``results_dir`` (= results/<scene>).

    Args:
        results_dir: folder holding ``scene.zarr`` (its ``frame_blocks`` name the blocks),
            ``<source>/block_*.zarr`` (``global_texture.zarr`` for 'global'), ``template.zarr``
            and, for meshes, ``tracking.zarr`` (and ``frames/`` for the video frame rate).
        what: 'png' (``out/texture_00012.png``), 'mp4' (``out/texture.mp4``), 'obj'
            (``out/frame_00012.{obj,mtl,png}``) or 'gltf' (``out/frame_00012.glb``).
        out: output folder.
        frames: frame-id range as in :func:`parse_frame_range` (None = all).
        source: 'corrected', 'volume' (before colour correction) or 'global' (the Kim et al. 2019
            baseline: one texture for the whole sequence). For 'global', 'png' writes the one
            image ``out/global_texture.png`` (``frames`` and ``every`` do not apply), 'obj' writes
            it once beside the meshes, whose MTLs all name it, and 'mp4' is refused.
        fps: video frame rate; None = from the frames' timestamps (30 if unavailable), divided
            by ``every``, so that the video keeps the capture's pace.
        crf, pix_fmt: video quality and chroma layout (:func:`write_video`).
        every: frame step: every ``every``-th frame of the range, from its first.
        progress: called as ``progress(done, total)`` per frame.

    Returns:
        The written files (for obj: the .obj files).

    Raises:
        StoreError: a store is missing, incomplete or inconsistent.
        ValueError: bad ``what``, ``source``, frame range or step.
    """
    if what not in EXPORT_KINDS:
        raise ValueError(f"what must be one of {EXPORT_KINDS}, got {what!r}")
    if source == "global" and what == "mp4":
        raise ValueError("the global texture is one image for the whole sequence, not a video: "
                         "export it with --what png (or on the meshes with obj / gltf)")
    if source == "global" and what == "png" and (frames is not None or every != 1):
        raise ValueError("the global texture is one image for the whole sequence: --frames and "
                         "--every do not apply to --what png")
    out = output_folder(out)
    res = RunResults(results_dir, source)
    ids = select_frames(res.frame_ids, *parse_frame_range(frames), every=every)
    if source == "global" and what == "png":
        path = out / "global_texture.png"
        out.mkdir(parents=True, exist_ok=True)
        write_png(path, res.texture(ids[0]))
        if progress:
            progress(1, 1)
        return [path]
    textures = (res.texture(i) for i in ids)
    if what == "png":
        return write_png_slices(textures, ids, out, progress=progress)
    if what == "mp4":
        if fps is None:
            try:
                fps = res.fps() / every
            except StoreError:
                fps = 30.0 / every
        path = out / "texture.mp4"
        write_texture_video(textures, path, fps=fps, crf=crf, pix_fmt=pix_fmt, total=len(ids),
                            progress=progress)
        return [path]
    res.vertices(ids[0])  # fail on a missing tracking store before writing anything
    verts = (res.vertices(i) for i in ids)
    if what == "obj":
        return write_obj_sequence(verts, res.faces, res.texcoords, res.texcoord_faces, textures,
                                  ids, out, progress=progress,
                                  shared_png="global_texture.png" if source == "global" else None)
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
