"""Volume stage's artifacts: the ``volume`` store of one block of slices (:mod:`stex.volume`)."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.config import section_params
from stex.fill import SeamFill
from stex.io import FrameSequence, create_store, open_store, position_range
from stex.sampling import TexelSampler, fill_gutter, nearest_seen_texels
from stex.stages.observations import open_coordinates
from stex.stages.template import template_atlas_digest

log = logging.getLogger("stex.volume")

__all__ = ["write_volume"]


def write_volume(template_path, labels_path, coords_path, frames_paths, positions, params: dict,
                 out, projection_path=None) -> None:
    """Volume stage for one block of frames: write a ``volume`` store.

    Args:
        template_path: ``template`` store (atlas, texel map).
        labels_path: ``labels`` store (labels [T, F], never_seen).
        coords_path: ``texcoords`` store (ξ) or ``projection`` store (Φ), as the observations.
        frames_paths: ``frames`` block stores (colour images).
        positions: [start, stop) sequence positions of the slices to write.
        params: the ``volume`` config section (gutter_px, slices_per_pass, interpolation,
            own_frame_coordinates, fill, fill_screen_length).
        out: path of the store.
        projection_path: ``projection`` store (Φ); needed when ``own_frame_coordinates`` is
            ``projected`` and ``coords_path`` holds ξ: slice t then reads the texels labelled
            with its own frame at Φ_t, where the tracked mesh at t puts them, and every other
            source frame s at ξ_s.
    """
    p = section_params("volume", params)
    template = open_store(template_path, "template")
    labels_store = open_store(labels_path, "labels")
    ids = list(labels_store.attrs["frame_ids"])
    start, stop = position_range(positions, len(ids), "slice")
    faces = np.asarray(template["faces"][...], np.int64)
    labels = np.asarray(labels_store["labels"][start:stop], np.int32)
    if labels.shape[1] != len(faces):
        raise ValueError(f"{labels_path}: labels for {labels.shape[1]} faces, template has {len(faces)}")
    coords, _, kind = open_coordinates(coords_path)
    own_at_phi = p["own_frame_coordinates"] == "projected" and kind != "projection"
    phi = None
    if own_at_phi:
        if projection_path is None:
            raise ValueError("volume.own_frame_coordinates 'projected' reads each slice's own frame "
                             f"at Φ: give the projection store (the coordinates {coords_path} are ξ)")
        phi, _, _ = open_coordinates(projection_path)
        if phi.shape != coords.shape:
            raise ValueError(f"projection store {projection_path} has Φ of shape {phi.shape}, the "
                             f"coordinates {coords_path} {coords.shape}")
    T = len(ids)
    frames = FrameSequence(list(frames_paths), "frames")
    tf = template["texel/face_id"][...]
    tb = template["texel/bary"][...]
    sampler = TexelSampler(tf, tb, faces, p["interpolation"])
    never = np.asarray(labels_store["never_seen"][...], bool)
    dst, src, weight = nearest_seen_texels(tf, tb, template["vertices"][...], faces, never)
    seam_fill = None
    if dst.size and p["fill"] == "harmonic":
        # solved per slice from the nearest fill, with the seen texels around it held
        seam_fill = SeamFill(tf, template["face_chart"][...], template["texcoords"][...],
                             template["texcoord_faces"][...], faces, template["adjacency/pairs"][...],
                             template["adjacency/edges"][...], never,
                             screen_length=p["fill_screen_length"])
    gutter = int(p["gutter_px"])

    # with own_at_phi, label T + t stands for frame t read at Φ_t (the texels of slice t labelled
    # with its own frame): the sampler reads it as one more source (frame t decoded once more)
    def image(l):
        return frames.read("color", ids[l % T])

    def xi(l):
        return np.asarray(phi[l - T] if l >= T else coords[l], np.float64)

    W = sampler.W
    per_pass = int(p["slices_per_pass"])
    t0 = time.perf_counter()
    attrs = {"frame_ids": ids[start:stop], "first_position": start, "gutter_px": gutter,
             "never_seen_texels": int(dst.size), "fill": p["fill"] if dst.size else "none",
             "atlas_digest": template_atlas_digest(template)}
    with create_store(out, "volume", attrs=attrs, params=p) as store:
        a_tex = store.create("texture", (stop - start, W, W, 3))
        a_lab = store.create("label_map", (stop - start, W, W))
        for k0 in range(0, stop - start, per_pass):
            # the slices of one pass read each of their source frames once
            k1 = min(k0 + per_pass, stop - start)
            rows = labels[k0:k1]
            if own_at_phi:
                own_pos = start + np.arange(k0, k1, dtype=np.int32)[:, None]
                rows = np.where(rows == own_pos, own_pos + T, rows)
            for k, (tex, lm) in enumerate(sampler.slices(rows, xi, image, gutter_px=0), k0):
                if own_at_phi:
                    lm = np.where(lm >= T, lm - T, lm)
                if dst.size:
                    flat = tex.reshape(-1, 3)
                    flat[dst] = np.round(np.einsum("nk,nkc->nc", weight, flat[src].astype(np.float32)))
                    if seam_fill is not None:
                        seam_fill.fill(tex)
                fill_gutter(tex, sampler.covered, sampler.covered, gutter)
                a_tex[k] = tex
                a_lab[k] = lm.astype(np.int16)
                log.info("volume: slice %d (%d/%d), %.2f s per slice", ids[start + k], k + 1,
                         stop - start, (time.perf_counter() - t0) / (k + 1))
