"""Scan stage, artifact side (``template.from_scan``): read the scan capture (a folder or .mkv
through :mod:`stex.ingest`'s sources, or the synthetic turntable), compute each frame's mask as
the masks stage does (:func:`stex.masks.compute_mask`), fuse them (:func:`stex.scan.fuse_scan`)
and write the ``scan`` store."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.camera import mask_in_depth
from stex.config import section_params
from stex.ingest import open_source
from stex.io import create_store
from stex.masks import compute_mask
from stex.scan import fuse_scan
from stex.synth.turntable import TurntableScene

log = logging.getLogger("stex.scan")


def scan_capture(scan: dict, source_cfg: dict | None = None):
    """The scan capture named by the validated ``template.scan`` section.

    Returns (calibration, n_frames, frames, description), where ``frames(start, stop)`` yields
    (position, colour (Hc, Wc, 3) uint8, depth (Hd, Wd) uint16 mm, mask (Hc, Wc) bool or None).
    Kind synthetic turns ``source_cfg``'s synthetic object (the schema's defaults when the main
    source is not synthetic) on a turntable.
    """
    kind = scan["kind"]
    if kind == "synthetic":
        src = section_params("source", source_cfg if source_cfg and source_cfg.get("kind") == "synthetic" else {})
        synth = dict(src["synthetic"], n_frames=int(scan["n_frames"]))
        if scan.get("depth"):  # the scan's own depth mode; the colour camera stays the source's
            synth["depth"] = dict(scan["depth"])
        scene = TurntableScene(synth, scan["elevation_deg"])

        def frames(start, stop):
            for k in range(start, stop):
                r = scene.render_frame(k)
                yield k, r.color, r.depth_mm, None

        return scene.calibration, scene.n_frames, frames, {"kind": "synthetic", "object": synth["object"]}
    if not scan.get("path"):
        raise ValueError(f"template.scan.path must name the scan's {'dataset folder' if kind == 'folder' else '.mkv file'}"
                         f" (template.scan.kind {kind})")
    sub = {"path": scan["path"], "start": scan["start"], "stop": scan["stop"]}
    if kind == "folder":
        sub["layout"] = scan["layout"]
    src = open_source(section_params("source", {"kind": kind, kind: sub}))

    def frames(start, stop):
        for pos, color, depth, mask, _ts, _extra in src.frames(start, stop):
            yield pos, color, depth, mask

    return src.calibration, len(src.frame_ids), frames, dict(src.description)


def scan_masks(masks_params: dict | None, scan: dict) -> dict:
    """The validated ``masks`` section the scan's masks use: the main one, GrabCut on images of at
    most ``scan['mask_max_pixels']`` pixels."""
    masks = section_params("masks", masks_params)
    return dict(masks, max_pixels=min(masks["max_pixels"], scan["mask_max_pixels"]))


def masked_frames(frames, calibration, masks: dict, step: int = 1, where: str = "the scan"):
    """Every ``step``-th frame of ``frames`` (from :func:`scan_capture`) with its object mask in
    the depth image, as :func:`stex.scan.fuse_scan` takes them: (position, colour, depth, mask
    (Hd, Wd) bool or None when the frame shows no object). ``masks`` is the validated masks
    section; with ``use_given`` the capture's own masks are used."""
    t0 = time.perf_counter()
    for pos, color, depth, given in frames:
        if pos % step:
            continue
        if masks["use_given"] and given is None:
            raise ValueError(f"{where}: masks.use_given is set but the scan supplies no masks")
        try:
            m = given if masks["use_given"] else compute_mask(color, depth, calibration, masks, seed=pos)[0]
        except ValueError as e:  # no object depth: an empty frame, counted by fuse_scan
            log.warning("scan: %s frame %d: no mask (%s)", where, pos, e)
            m = None
        # only the depth range's pixels can join the model: the rest (the wall, most of the image)
        # is left out before it is carried into the colour image
        d = depth.astype(np.float64) / 1000.0
        in_range = np.where((d >= masks["depth_near_m"]) & (d <= masks["depth_far_m"]), depth, 0)
        md = None if m is None or not m.any() else mask_in_depth(m, in_range, calibration)
        if pos % 25 == 0:
            log.info("scan: frame %d (%.1f s)", pos, time.perf_counter() - t0)
        yield pos, color, depth, md


def write_scan(template_params: dict, source_cfg: dict, masks_params: dict, out) -> None:
    """Fuse the scan capture of ``template_params['scan']`` and write the ``scan`` store to ``out``.

    ``source_cfg`` is the main capture's ``source`` section (the synthetic turntable turns its
    object); ``masks_params`` the ``masks`` section, whose settings the scan's masks use.
    """
    params = section_params("template", template_params)
    scan = params["scan"]
    masks = scan_masks(masks_params, scan)
    cal, n, frames, description = scan_capture(scan, source_cfg)
    where = scan.get("path") or "the synthetic turntable"
    t0 = time.perf_counter()
    try:
        result = fuse_scan(masked_frames(frames(0, n), cal, masks, scan["step"], where), cal, scan,
                           masks["depth_near_m"], masks["depth_far_m"])
    except ValueError as e:
        raise ValueError(f"{where}: template.from_scan: {e}") from e
    if result["n_empty"]:
        log.warning("scan: %d frames without object in their mask were left out", result["n_empty"])
    attrs = {"calibration": cal.to_dict(), "frame_ids": result["frame_ids"].tolist(), "source": description,
             "turned_deg": result["turned_deg"], "fused_frames": int(result["fused"].sum()),
             "empty_frames": result["n_empty"], "seconds": time.perf_counter() - t0}
    with create_store(out, "scan", attrs=attrs, params={"template": params, "masks": masks}) as store:
        for name in ("vertices", "faces", "poses", "fitness", "fused"):
            store.write(name, result[name])
    log.info("scan: wrote %s (%d faces, %d of %d frames fused, turned %.0f degrees, %.1f s)", out,
             len(result["faces"]), attrs["fused_frames"], len(result["frame_ids"]), result["turned_deg"],
             attrs["seconds"])
