"""Ingest stage, artifact side: the ``scene`` store of a source (:func:`stex.ingest.open_source`)
and one ``frames`` store (and, for synthetic scenes, ``truth`` store) per block of frames.

Later stages never touch the source files again."""


from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path

import numpy as np

from stex.ingest import FolderSource, SyntheticSource, frame_blocks, open_source
from stex.io import create_store
from stex.readers.images import check_mask
from stex.skeleton import skeleton_arrays, skeleton_from_skin

log = logging.getLogger("stex.ingest")


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
        skin = src.scene.skeleton(0) if isinstance(src, SyntheticSource) and tmpl is not None else None
        if skin is not None:   # a skinned object: its skeleton at the template's pose (frame 0)
            skeleton = skeleton_from_skin(*skin)
            for name, arr in skeleton_arrays(skeleton, prefix="template/skeleton/").items():
                store.write(name, arr)
            store.attrs["skeleton_joint_names"] = skeleton.names
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
