"""Labeling stage's artifacts: the ``labels`` store (:mod:`stex.labeling`) and its preview."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from stex.config import section_params
from stex.dynamism import (label_set_min, spatial_edge_weight, spatial_face_weight, ssim_map_image,
                           temporal_gate)
from stex.io import FrameSequence, create_store, open_store, short_ids
from stex.labeling import TableRows, glimpse_sources, label_sequence
from stex.preview import label_image, montage, write_png
from stex.sampling import label_colors

log = logging.getLogger("stex.labeling")

__all__ = ["labeling_inputs", "write_labels", "preview_labels"]


def labeling_inputs(observations_path, data_term_paths, template_path, params: dict) -> dict:
    """Read what :func:`stex.labeling.label_sequence` needs from the stores and apply the config switches.

    Returns a dict of keyword arguments for :func:`stex.labeling.label_sequence` plus ``frame_ids`` and
    ``never_seen`` (F,) bool.
    """
    p = section_params("labeling", params)
    obs = open_store(observations_path, "observations")
    template = open_store(template_path, "template")
    pairs = np.asarray(template["adjacency/pairs"][...], np.int64)
    ids = list(obs.attrs["frame_ids"])
    blocks = [open_store(path, "data_term") for path in data_term_paths]
    got = [fid for b in blocks for fid in b.attrs["frame_ids"]]
    if got != ids:
        raise ValueError(f"data_term blocks cover frames {got[:3]}..{got[-3:]} but the observations "
                         f"hold {ids[:3]}..{ids[-3:]} (every frame exactly once, in order)")
    tp = blocks[0].attrs["params"]            # the data term is weighted as it was ranked
    # read a frame at a time while solving: the (T, F, K) rows are what grows with the sequence
    cand, unary = TableRows(blocks, "candidates"), TableRows(blocks, "unary", tp)
    first = np.concatenate([b["candidates"][:, :, 0] for b in blocks])   # (T, F)
    face_visible = np.asarray(obs["face_visible"][...], bool)
    has_dyn = "dynamism" in obs
    S = np.asarray(obs["dynamism"][...], np.float32) if has_dyn else None
    if (p["temporal"] == "selective" or p["spatial_selective"]) and S is None:
        raise ValueError(f"{observations_path}: no dynamism table, needed by labeling.temporal="
                         f"selective / spatial_selective")
    gates = temporal_gate(S, p["theta_omega"]) if p["temporal"] == "selective" else None
    omega_t = 0.0 if p["temporal"] == "off" else float(p["omega_t"])
    w = (spatial_edge_weight(spatial_face_weight(S, face_visible, p["theta_omega"]), pairs)
         if p["spatial_selective"] else np.ones(len(pairs), np.float32))
    return {"cand": cand, "unary": unary, "pairs": pairs,
            "pair_weight": (p["omega_s"] * w).astype(np.float64),
            "edge_samples": obs["edge_samples"][...], "face_samples": obs["face_samples"][...],
            "omega_t": omega_t, "gates": gates, "max_rounds": p["max_rounds"],
            "rel_tol": p["rel_tol"], "seed": p["seed"], "frame_ids": ids,
            "never_seen": (first < 0).all(axis=0)}   # no source frame sees them


def write_labels(observations_path, data_term_paths, template_path, params: dict, out,
                 threads: int = 2, projection_path=None) -> None:
    """Labeling stage: write the ``labels`` store.

    With ``projection_path``, never-seen faces glimpsed by a source frame are labelled with it
    at every frame (:func:`stex.labeling.glimpse_sources`); ``never_seen`` then holds the faces left without
    any source."""
    p = section_params("labeling", params)
    args = labeling_inputs(observations_path, data_term_paths, template_path, p)
    ids, never = args.pop("frame_ids"), args.pop("never_seen")
    log.info("labeling: %d frames, %d faces (%d never seen), %d candidates per face",
             len(ids), never.size, int(never.sum()), args["cand"].shape[2])
    res = label_sequence(**args, threads=threads, progress=log.info)
    labels = res["labels"]
    seen = ~never
    coverage = [float((labels[t, seen] >= 0).mean()) if seen.any() else 1.0 for t in range(len(ids))]
    glimpse = np.full(never.size, -1, np.int32)
    if projection_path is not None and never.any():
        proj = open_store(projection_path, "projection")
        if list(proj.attrs["frame_ids"]) != ids:
            raise ValueError(f"{projection_path} holds frames {short_ids(proj.attrs['frame_ids'])}, "
                             f"the observations {short_ids(ids)}")
        # the held-out protocol's source frames, as the data term ranked them
        sources = set(open_store(data_term_paths[0], "data_term").attrs.get("source_frames", ids))
        is_source = np.array([i in sources for i in ids])
        glimpse = glimpse_sources(proj["face_glimpsed"][...], proj["face_cos"][...], never, is_source)
        got = glimpse >= 0
        labels[:, got] = glimpse[got]
        never = never & ~got
        log.info("labeling: %d never-seen faces glimpsed by a source frame, labelled with it; "
                 "%d left without a source", int(got.sum()), int(never.sum()))
    attrs = {"frame_ids": ids, "rounds": res["rounds"], "n_never_seen": int(never.sum()),
             "n_glimpsed": int((glimpse >= 0).sum()),
             "coverage_of_seen_faces": [round(c, 6) for c in coverage]}
    with create_store(out, "labels", attrs=attrs, params=p) as store:
        store.write("labels", labels)
        store.write("energy", res["energy"])
        store.write("frame_energy", res["frame_energy"])
        store.write("never_seen", never)
        store.write("glimpse_source", glimpse)


def preview_labels(volume_paths, corrected_paths, observations_path, template_path, out,
                   n_show: int = 4, size: int = 384, theta_omega: float = 0.95) -> None:
    """The label maps of a few frames spread over the sequence, as in the paper's figures.

    One row per frame: the colour-corrected slice, its label map (each source frame its own
    colour, :func:`stex.sampling.label_colors`; black = gutter / never seen), and once, the SSIM
    dynamism S_m(f) = min over the face's frames (dark = dynamic, red below ``theta_omega``,
    the labeling's θ_Ω).
    """
    vol = FrameSequence(list(volume_paths), "volume")
    cor = FrameSequence(list(corrected_paths), "corrected")
    ids = vol.frame_ids
    pick = [ids[int(round(k))] for k in np.linspace(0, len(ids) - 1, min(n_show, len(ids)))]
    obs = open_store(observations_path, "observations")
    tf = open_store(template_path, "template")["texel/face_id"][...]
    s_min = label_set_min(obs["dynamism"][...], np.asarray(obs["face_visible"][...], bool))
    rs = lambda im: cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA)
    dyn = label_image(rs(ssim_map_image(s_min, tf, theta=theta_omega)), "SSIM dynamism (min over frames)")
    tiles = []
    for k, fid in enumerate(pick):
        lm = vol.read("label_map", fid)
        tiles += [label_image(rs(cor.read("texture", fid)), f"frame {fid}: corrected slice"),
                  label_image(rs(label_colors(lm)), f"frame {fid}: labels ({len(np.unique(lm[lm >= 0]))} sources)"),
                  dyn if k == 0 else np.zeros_like(dyn)]
    write_png(out, montage(tiles, columns=3, width=3 * size))
