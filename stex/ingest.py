"""Ingest stage: turn a source (synthetic scene, folder dataset, Azure Kinect .mkv) into stores.

- :func:`write_scene` writes the ``scene`` store once per scene: calibration, frame list, frame
  blocks, the template mesh and, when the source has them, per-frame meshes (and, for synthetic
  scenes, the true per-frame vertices).
- :func:`write_frames_block` writes one ``frames`` store per block of frames (and, for synthetic
  scenes, the matching ``truth`` store). Blocks are independent jobs.

Later stages never touch the source files again.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from pathlib import Path

import numpy as np

from stex.camera import Calibration
from stex.io import create_store
from stex.readers.meshes import Mesh, check_same_topology, load_mesh

log = logging.getLogger("stex.ingest")


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
        from stex.synth.scene import SyntheticScene
        return SyntheticScene(self.cfg)

    @property
    def calibration(self):
        return self.scene.calibration

    def template(self) -> Mesh:
        # The template is the true mesh at frame 0 (with the object's own atlas).
        return Mesh(self.scene.true_vertices(0), self.scene.faces, self.scene.texcoords, self.scene.texcoord_faces)

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
        from stex.readers.folder import FolderDataset
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
        from stex.readers.kinect_mkv import Undistorter, open_kinect_mkv
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
        from stex.readers.kinect_mkv import open_kinect_mkv
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


# -- writers ------------------------------------------------------------------------------------

def write_scene(source_cfg: dict, block: int, out: str | Path) -> None:
    """Write the ``scene`` store of the configured source to ``out``."""
    src = open_source(source_cfg)
    T = len(src.frame_ids)
    blocks = frame_blocks(T, block)
    with create_store(out, "scene", attrs={
        "calibration": src.calibration.to_dict(), "frame_ids": src.frame_ids,
        "frame_blocks": blocks, "source": src.description,
    }, params={"source": source_cfg, "frame_block": block}) as store:
        tmpl = src.template()
        if tmpl is not None:
            store.write("template/vertices", tmpl.vertices)
            store.write("template/faces", tmpl.faces)
            if tmpl.texcoords is not None:
                store.write("template/texcoords", tmpl.texcoords)
                store.write("template/texcoord_faces", tmpl.texcoord_faces)
        store.attrs["has_template"] = tmpl is not None
        first = src.given_vertices(0)
        if first is None and isinstance(src, FolderSource):
            # meshes for later frames but not the first would be dropped without a word
            having = [fid for fid in src.frame_ids if src.ds.mesh_path(fid) is not None]
            if having:
                base = (f" (the authors' layout numbers them from frame {src.ds.mesh_base}: mesh/Frame_000)"
                        if src.ds.layout == "authors" else "")
                raise ValueError(f"{src.description['path']}: given meshes exist for {len(having)} of the "
                                 f"{T} frames, from frame {having[0]}, but not for the first frame "
                                 f"{src.frame_ids[0]}{base}: every frame needs one, or none (source.folder.start "
                                 f"selects where the sequence begins)")
        if first is not None:
            if tmpl is not None and first.shape != tmpl.vertices.shape:
                raise ValueError(f"given mesh of frame {src.frame_ids[0]} has {len(first)} vertices, template has {len(tmpl.vertices)}")
            arr = store.create("given/vertices", (T,) + first.shape)
            arr[0] = first
            for pos in range(1, T):
                v = src.given_vertices(pos)
                if v is None:
                    where = src.description.get("path", "the source")
                    raise ValueError(f"{where}: given mesh missing for frame {src.frame_ids[pos]} "
                                     f"(frame {src.frame_ids[0]} has one: every frame needs one, or none)")
                if v.shape != first.shape:
                    raise ValueError(f"given mesh of frame {src.frame_ids[pos]} has {len(v)} vertices, frame {src.frame_ids[0]} has {len(first)}")
                if not np.isfinite(v).all():
                    raise ValueError(f"given mesh of frame {src.frame_ids[pos]} has non-finite vertices")
                arr[pos] = v
        if isinstance(src, SyntheticSource):
            arr = store.create("truth/vertices", (T, len(src.scene.body.rest_vertices), 3))
            for pos in range(T):
                arr[pos] = src.true_vertices(pos)


def write_frames_block(source_cfg: dict, start: int, stop: int, out_frames: str | Path,
                       out_truth: str | Path | None = None) -> None:
    """Write frames at positions [start, stop) to a ``frames`` store (and ``truth`` if synthetic)."""
    from stex.readers.images import check_mask  # here: cv2 is not imported when the workflow is parsed

    src = open_source(source_cfg)
    T = len(src.frame_ids)
    if not 0 <= start < stop <= T:
        raise ValueError(f"frame block [{start}, {stop}) outside the source's {T} frames")
    n = stop - start
    cal = src.calibration
    ids = src.frame_ids[start:stop]
    synthetic = isinstance(src, SyntheticSource)
    if synthetic and out_truth is None:
        raise ValueError("a synthetic source needs out_truth for its ground truth")
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        store = stack.enter_context(create_store(
            out_frames, "frames", attrs={"frame_ids": ids, "calibration": cal.to_dict()},
            params={"source": source_cfg}))
        truth = stack.enter_context(create_store(
            out_truth, "truth", attrs={"frame_ids": ids}, params={"source": source_cfg})) if synthetic else None
        color = store.create("color", (n, cal.color.height, cal.color.width, 3))
        depth = store.create("depth", (n, cal.depth.height, cal.depth.width))
        stamps = np.zeros(n)
        mask_arr = None
        no_depth = []
        k = -1
        for k, (pos, c, d, m, ts, extra) in enumerate(src.frames(start, stop)):
            fid = src.frame_ids[pos]
            if c.shape != (cal.color.height, cal.color.width, 3):
                raise ValueError(f"frame {fid}: colour shape {c.shape} does not match the calibration")
            if d.shape != (cal.depth.height, cal.depth.width):
                raise ValueError(f"frame {fid}: depth shape {d.shape} does not match the calibration")
            if d.dtype != np.uint16:  # a float array would be cast silently: NaN to 0, metres to 0/1 mm
                raise ValueError(f"frame {fid}: depth must be uint16 millimetres, got {d.dtype}")
            if not d.any():
                no_depth.append(fid)
            color[k] = c
            depth[k] = d
            stamps[k] = ts
            if m is not None:
                if mask_arr is None:
                    mask_arr = store.create("mask", (n, cal.color.height, cal.color.width))
                check_mask(m, f"frame {fid} (the source's mask)")  # empty, all foreground, or inverted
                mask_arr[k] = m
            if truth is not None:
                if k == 0:
                    W = extra.appearance.shape[0]
                    t_app = truth.create("appearance", (n, W, W, 3))
                    t_mask = truth.create("mask", (n, cal.color.height, cal.color.width))
                    t_depth = truth.create("depth", (n, cal.depth.height, cal.depth.width))
                t_app[k] = extra.appearance
                t_mask[k] = extra.true_mask
                t_depth[k] = extra.true_depth
            rate = (k + 1) / max(time.perf_counter() - t0, 1e-9)
            log.info("ingest: frame %d (%d/%d in block, %.1f frames/s)", fid, k + 1, n, rate)
        if k + 1 != n:
            raise ValueError(f"source delivered {k + 1} of the {n} frames of block [{start}, {stop})")
        if no_depth:  # a dropped depth frame: the masks stage refuses it, given masks and the tracker coast
            log.warning("ingest: frame(s) %s have no valid depth pixel (all 0): a dropped depth frame?", no_depth)
        store.write("timestamps", stamps)
