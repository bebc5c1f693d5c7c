"""Masks stage, artifact side: one ``masks`` store per frame block (:func:`stex.masks.compute_mask`
per frame, or the source's own masks), and the montage of masks over colour."""


from __future__ import annotations

import logging
import time
import warnings

import numpy as np

from stex.camera import Calibration
from stex.config import section_params
from stex.io import FrameSequence, create_store, open_store
from stex.masks import GC_BGD, GC_FGD, compute_mask, mask_iou, plane_in_color, why_no_object_depth
from stex.preview import label_image, mask_overlay, montage, write_png
from stex.readers.folder import FolderDataset

log = logging.getLogger("stex.masks")


def _unread_mask_files(source_cfg: dict | None) -> str:
    """For the error of masks.use_given without masks: the folder dataset's mask files that match
    no selected frame (``FolderDataset.mask_note``), read again from the source; '' when there are
    none, the source is no folder, or it cannot be read any more."""
    if not isinstance(source_cfg, dict) or source_cfg.get("kind") != "folder":
        return ""
    try:
        cfg = source_cfg["folder"]
        with warnings.catch_warnings():  # ingest has warned already
            warnings.simplefilter("ignore")
            note = FolderDataset(cfg["path"], cfg["layout"], cfg["start"], cfg["stop"]).mask_note
    except Exception:  # the dataset moved or changed since ingest: the error stands without it
        return ""
    return f": {note}" if note else ""


def write_masks_block(scene_path, frames_path, params: dict, out) -> None:
    """Masks stage for one frame block: read ``frames``, write a ``masks`` store to ``out``.

    With ``params['use_given']`` the source's own masks are copied (error if it has none).
    """
    log = logging.getLogger("stex.masks")
    params = section_params("masks", params)
    scene = open_store(scene_path, "scene")
    frames = open_store(frames_path, "frames")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    ids = list(frames.attrs["frame_ids"])
    n = len(ids)
    if params["use_given"] and "mask" not in frames:
        raise ValueError(f"{frames_path}: masks.use_given is set but the source supplied no masks"
                         + _unread_mask_files(frames.attrs.get("params", {}).get("source")))
    t0 = time.perf_counter()
    planes = []
    with create_store(out, "masks", attrs={"frame_ids": ids}, params=params) as store:
        mask = store.create("mask", (n, cal.color.height, cal.color.width))
        seed = store.create("seed", (n, cal.color.height, cal.color.width))
        for k, fid in enumerate(ids):
            depth = frames["depth"][k]
            if params["use_given"]:
                m = frames["mask"][k]
                s = np.where(m, GC_FGD, GC_BGD).astype(np.uint8)
            else:
                info = {}
                try:
                    m, s = compute_mask(frames["color"][k], depth, cal, params, seed=fid, info=info)
                except ValueError as e:
                    raise ValueError(f"{frames_path}: frame {fid}: {e}") from e
                if "support_plane" in info:
                    planes.append(info["support_plane"])
            if not m.any():
                raise ValueError(f"{frames_path}: frame {fid}: empty mask: "
                                 f"{why_no_object_depth(depth, cal, params)}")
            mask[k] = m
            seed[k] = s
            log.info("masks: frame %d (%d/%d, %.2f frames/s)", fid, k + 1, n, (k + 1) / (time.perf_counter() - t0))
        if planes:
            store.attrs["support_planes"] = planes
            missing = [fid for fid, pl in zip(ids, planes) if pl is None]
            if missing:
                log.warning("masks: no support plane at %d of %d frames (%s): no plane of their in-range depth has "
                            "the object on its camera side, so the depth range alone seeded GrabCut there",
                            len(missing), n, ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else ""))


def preview_masks(frames_paths: list, masks_paths: list, truth_paths: list | None, out, n_show: int = 6,
                  scene_path=None) -> None:
    """Write a PNG montage of masks over colour for ``n_show`` frames spread over the sequence.

    With ``scene_path`` (for the calibration), the support plane each frame's mask left out
    (masks' ``support_planes``) is tinted blue."""
    frames = FrameSequence(frames_paths, "frames")
    masks = FrameSequence(masks_paths, "masks")
    truth = FrameSequence(truth_paths, "truth") if truth_paths else None
    cal = Calibration.from_dict(open_store(scene_path, "scene").attrs["calibration"]) if scene_path else None
    ids = frames.frame_ids
    pick = [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, min(n_show, len(ids))).round().astype(int))]
    tiles = []
    for fid in pick:
        m = masks.read("mask", fid)
        title = f"frame {fid}"
        if truth is not None:
            title += f"  IoU {mask_iou(m, truth.read('mask', fid)):.3f}"
        tile = mask_overlay(frames.read("color", fid), m)
        plane = masks.frame_attr("support_planes", fid)
        if cal is not None and plane is not None:
            tol = masks.attrs["params"]["support_plane_tolerance_m"]
            blue = plane_in_color(frames.read("depth", fid), cal, plane, tol) & ~m
            tile[blue] = (0.5 * tile[blue] + [0, 40, 120]).astype(np.uint8)
            title += "  support plane (blue) left out"
        tiles.append(label_image(tile, title))
    write_png(out, montage(tiles))
