"""Correction stage's artifacts: the ``corrected`` store of one block (:mod:`stex.correction`)."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.config import section_params
from stex.correction import CorrectionSystem, label_boundary_step
from stex.io import create_store, open_store
from stex.stages.template import check_atlas

log = logging.getLogger("stex.correction")

__all__ = ["write_corrected"]


def write_corrected(template_path, volume_path, params: dict, out, previous_path=None) -> None:
    """Correction stage for one block: write a ``corrected`` store from a ``volume`` store.

    Args:
        template_path: ``template`` store (atlas, adjacency, charts).
        volume_path: the block's ``volume`` store (texture, label_map).
        params: the ``correction`` config section.
        out: path of the store.
        previous_path: the previous block's ``corrected`` store; with the temporal coupling on,
            its last slice is the first slice's ``previous`` (blocks then run in sequence).
    """
    p = section_params("correction", params)
    template = open_store(template_path, "template")
    volume = open_store(volume_path, "volume")
    digest = check_atlas([(volume_path, volume)], template, template_path)
    ids = list(volume.attrs["frame_ids"])
    temporal = p["temporal_length"] if p["temporal"] else None
    W = int(template.attrs["atlas_size"])
    factor = max(1, W // int(p["solve_size"]))
    if W % factor:
        raise ValueError(f"correction.solve_size {p['solve_size']}: atlas side {W} is not divisible "
                         f"by the factor {factor}")
    t0 = time.perf_counter()
    system = CorrectionSystem(
        template["texel/face_id"][...], template["texcoords"][...],
        template["texcoord_faces"][...], template["faces"][...],
        template["adjacency/pairs"][...], template["adjacency/edges"][...],
        template["face_chart"][...], factor=factor, screen_length=p["screen_length"],
        seam_weight=p["seam_weight"], temporal_length=temporal, tol=p["tol"],
        boundary_gradient=p["boundary_gradient"], keep_own_frame=p["keep_own_frame"],
        gutter_px=int(volume.attrs["gutter_px"]))
    log.info("correction: system of %d unknowns built in %.1f s", system.n_unknowns,
             time.perf_counter() - t0)
    prev = None
    if temporal is not None and previous_path is not None:
        previous = open_store(previous_path, "corrected")
        check_atlas([(previous_path, previous)], template, template_path)
        prev = previous["texture"][-1]
    W = system.W
    attrs = {"frame_ids": ids, "gutter_px": int(volume.attrs["gutter_px"]),
             "atlas_digest": digest}
    first = int(volume.attrs["first_position"])
    chart = (system.texel_face, system.face_chart)
    steps = []
    with create_store(out, "corrected", attrs=attrs, params=p) as store:
        a_tex = store.create("texture", (len(ids), W, W, 3))
        for k, fid in enumerate(ids):
            tex = volume["texture"][k]
            lm = np.asarray(volume["label_map"][k], np.int32)
            # labels are sequence positions: texels labelled with the slice's own are not borrowed
            res = system.correct(tex, lm, previous=prev, frame=first + k)
            a_tex[k] = res
            prev = res if temporal is not None else None
            steps.append([round(label_boundary_step(tex, lm, *chart), 4),
                          round(label_boundary_step(res, lm, *chart), 4)])
            log.info("correction: slice %d (%d/%d) %.2f s, label-boundary step %.2f -> %.2f",
                     fid, k + 1, len(ids), system.last_stats["total_s"], steps[-1][0], steps[-1][1])
        store.attrs["label_boundary_step"] = steps
