"""Ingest stage: the sources a run reads (synthetic scene, folder dataset, Azure Kinect .mkv),
behind one interface (:class:`Source`, :func:`open_source`), and the split into frame blocks.

:mod:`stex.stages.ingest` writes them into stores: the ``scene`` store once per scene
(:func:`stex.stages.ingest.write_scene`: calibration, frame list, frame blocks, the template mesh
and, when the source has them, per-frame meshes and, for synthetic scenes, the true per-frame
vertices), and one ``frames`` (and ``truth``) store per block of frames
(:func:`stex.stages.ingest.write_frames_block`). Later stages never touch the source files again.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from stex.camera import Calibration
from stex.readers.folder import FolderDataset
from stex.readers.kinect_calibration import Undistorter
from stex.readers.kinect_mkv import open_kinect_mkv
from stex.readers.meshes import Mesh, check_same_topology, load_mesh
from stex.synth.scene import SyntheticScene


def frame_blocks(n_frames: int, block: int) -> list[tuple[int, int]]:
    """Split positions 0..n_frames-1 into [start, stop) blocks of at most ``block`` frames."""
    if n_frames < 1 or block < 1:
        raise ValueError(f"need n_frames >= 1 and block >= 1, got {n_frames}, {block}")
    return [(s, min(s + block, n_frames)) for s in range(0, n_frames, block)]


# -- sources ------------------------------------------------------------------------------------

class Source:
    """What ingest needs from any source. ``frame_ids`` are absolute frame indices."""

    calibration: Calibration
    frame_ids: list[int]
    description: dict

    def template(self) -> Mesh | None: ...
    def given_vertices(self, position: int) -> np.ndarray | None: ...

    def files(self, start: int | None = None, stop: int | None = None) -> list[Path]:
        """The files ingest reads: with no range, those :func:`write_scene` reads (calibration,
        template, per-frame meshes); else those :func:`write_frames_block` reads for the frame
        positions [start, stop). The workflow makes them the ingest rules' inputs, so a dataset
        file changed after a run (a frame replaced, the calibration fixed) re-runs what read it."""
        ...

    def frames(self, start: int, stop: int):
        """Yield (position, color uint8 RGB, depth uint16 mm, mask bool or None, timestamp s)."""
        ...


class SyntheticSource(Source):
    def __init__(self, cfg: dict):
        self.cfg = cfg
        self.frame_ids = list(range(int(cfg["n_frames"])))
        if not self.frame_ids:
            raise ValueError(f"synthetic scene needs n_frames >= 1, got {cfg['n_frames']}")
        self.description = {"kind": "synthetic", "object": cfg["object"]}
        if cfg["object"] != "procedural":
            # a glTF asset is read now, so that a bad one is named before any job runs; the
            # procedural body cannot fail, and the workflow (parsed again by every cluster job)
            # needs only its frame count: its renderer is not imported until a frame is asked for
            self.scene

    @functools.cached_property
    def scene(self):
        return SyntheticScene(self.cfg)

    @property
    def calibration(self):
        return self.scene.calibration

    def template(self) -> Mesh:
        # The true mesh at frame 0, or the undeformed rest shape in frame 0's place; both with the
        # object's own atlas.
        if self.cfg["template"] == "rest":
            V = self.scene.rest_shape_vertices(0)
        else:
            V = self.scene.true_vertices(0)
        return Mesh(V, self.scene.faces, self.scene.texcoords, self.scene.texcoord_faces)

    def given_vertices(self, position: int) -> np.ndarray:
        return self.scene.given_vertices(position)

    def files(self, start: int | None = None, stop: int | None = None) -> list[Path]:
        # a glTF asset is read by every job; the procedural body reads nothing
        return [Path(self.cfg["gltf"]["path"])] if self.cfg["object"] == "gltf" else []

    def true_vertices(self, position: int) -> np.ndarray:
        return self.scene.true_vertices(position)

    def frames(self, start: int, stop: int):
        for i in range(start, stop):
            r = self.scene.render_frame(i)
            yield i, r.color, r.depth_mm, None, r.timestamp, r


class FolderSource(Source):
    def __init__(self, cfg: dict):
        if not cfg.get("path"):
            raise ValueError("source.folder.path must name the dataset folder")
        self.cfg = cfg
        self.ds = FolderDataset(cfg["path"], cfg["layout"], cfg["start"], cfg["stop"])
        self.calibration = self.ds.calibration
        self.frame_ids = self.ds.frame_ids
        self.description = {"kind": "folder", "path": str(cfg["path"]), "layout": cfg["layout"]}
        self._template: Mesh | None = None

    def template(self) -> Mesh | None:
        if self._template is None:
            p = self.ds.template_path(self.cfg.get("template"))
            self._template = None if p is None else load_mesh(p)
        return self._template

    def given_vertices(self, position: int) -> np.ndarray | None:
        fid = self.frame_ids[position]
        mesh = self.ds.load_given_mesh(fid)
        if mesh is None:
            return None
        tmpl = self.template()
        if tmpl is not None:
            check_same_topology(tmpl.faces, len(tmpl.vertices), mesh, str(self.ds.mesh_path(fid)))
        return mesh.vertices

    def files(self, start: int | None = None, stop: int | None = None) -> list[Path]:
        out = [self.ds.calibration_path]
        if start is None:
            template = self.ds.template_path(self.cfg.get("template"))
            meshes = [self.ds.mesh_path(fid) for fid in self.frame_ids]
            # dict: the stex layout's default template is the first given mesh, listed once
            return list(dict.fromkeys(out + ([template] if template else []) + [p for p in meshes if p]))
        for fid in self.frame_ids[start:stop]:
            out += self.ds.frame_files(fid)
        return out

    def frames(self, start: int, stop: int):
        for pos in range(start, stop):
            fid = self.frame_ids[pos]
            mask = self.ds.mask(fid) if self.ds.has_masks else None
            yield pos, self.ds.color(fid), self.ds.depth(fid), mask, pos / self.cfg["fps"], None


class MkvSource(Source):
    def __init__(self, cfg: dict):
        if not cfg.get("path"):
            raise ValueError("source.mkv.path must name the .mkv recording")
        self.cfg = cfg
        self.path = Path(cfg["path"])
        self._open = dict(allow_truncated=bool(cfg.get("allow_truncated", False)),
                          skip_damaged_color=bool(cfg.get("skip_damaged_color", False)))
        with open_kinect_mkv(self.path, **self._open) as rec:
            raw_cal = rec.calibration
            n = rec.n_frames
            damaged = rec.damaged_color_captures
            skipped = rec.n_damaged_color_skipped
        stop = n if cfg["stop"] is None else min(cfg["stop"], n)
        if cfg["start"] >= stop:
            raise ValueError(f"{self.path}: no captures in [{cfg['start']}, {cfg['stop']}) (recording has {n})")
        self.frame_ids = list(range(cfg["start"], stop))
        # refused here, before any frame block is read, and all of them at once
        damaged = [i for i in damaged if cfg["start"] <= i < stop]
        if damaged:
            raise ValueError(f"{self.path}: the colour images of {len(damaged)} captures are cut short (no JPEG end "
                             f"marker; their lower rows would be invented): captures {damaged[:10]}"
                             f"{' ...' if len(damaged) > 10 else ''}. Set source.mkv.skip_damaged_color: true to "
                             f"leave them out, or read around them with source.mkv.start / stop")
        self._undistort = Undistorter(raw_cal) if cfg["undistort"] else None
        self.calibration = self._undistort.calibration if self._undistort else raw_cal
        self.description = {"kind": "mkv", "path": str(self.path), "undistorted": bool(cfg["undistort"]),
                            "damaged_color_skipped": skipped}

    def template(self) -> Mesh | None:
        return load_mesh(self.cfg["template"]) if self.cfg.get("template") else None

    def given_vertices(self, position: int) -> None:
        return None

    def files(self, start: int | None = None, stop: int | None = None) -> list[Path]:
        template = [Path(self.cfg["template"])] if start is None and self.cfg.get("template") else []
        return [self.path] + template

    def frames(self, start: int, stop: int):
        first = self.frame_ids[0]
        with open_kinect_mkv(self.path, **self._open) as rec:
            for idx, ts_us, color, depth in rec.frames(first + start, first + stop):
                if self._undistort is not None:
                    color, depth = self._undistort(color, depth)
                yield idx - first, color, depth, None, ts_us * 1e-6, None


def open_source(source_cfg: dict) -> Source:
    """The source named by the validated ``source`` config section."""
    kind = source_cfg["kind"]
    if kind == "synthetic":
        return SyntheticSource(source_cfg["synthetic"])
    if kind == "folder":
        return FolderSource(source_cfg["folder"])
    if kind == "mkv":
        return MkvSource(source_cfg["mkv"])
    raise ValueError(f"unknown source kind {kind!r}")


def count_frames(source_cfg: dict) -> int:
    """Number of frames the source provides (cheap: reads no images)."""
    return len(open_source(source_cfg).frame_ids)
