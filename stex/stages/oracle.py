"""Oracle labels (:mod:`stex.oracle`), the artifact layer: read the truth, the visibility and the
labeling's labels of a synthetic run and write a ``labels`` store whose borrowed faces carry the
oracle's source frames. The workflow builds its volume and correction with the same rules as
ours (``references/oracle/``) and the evaluation scores it as the method ``oracle``."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.io import FrameSequence, create_store, open_store, short_ids
from stex.oracle import oracle_labels, sample_points_uv, truth_samples
from stex.texcoords import SAMPLE_BARY

log = logging.getLogger("stex.oracle")

__all__ = ["write_oracle_labels"]


def write_oracle_labels(scene_path, template_path, truth_paths, observations_path, labels_path,
                        data_term_paths, out, *, among_candidates: bool = False) -> None:
    """Write the oracle's ``labels`` store.

    Args:
        scene_path: ``scene`` store of a synthetic scene (template/* with the true atlas).
        template_path: ``template`` store (vertices, faces; in the scene template's frame).
        truth_paths: ``truth`` block stores (appearance of every frame).
        observations_path: ``observations`` store (face_visible: the label candidates).
        labels_path: the labeling's ``labels`` store: kept where frame t is a source that sees
            the face and for faces no source frame saw (never_seen, glimpse_source copied).
        data_term_paths: ``data_term`` block stores (source_frames; the candidates with
            ``among_candidates``).
        out: path of the store.
        among_candidates: choose among the data term's candidates only (what the labeling
            could have chosen) instead of every source frame that saw the face.
    """
    t0 = time.perf_counter()
    scene = open_store(scene_path, "scene")
    if "truth" not in scene:
        raise ValueError(f"{scene_path}: the oracle needs the truth of a synthetic scene (no truth/vertices)")
    template = open_store(template_path, "template")
    obs = open_store(observations_path, "observations")
    ours = open_store(labels_path, "labels")
    ids = [int(i) for i in ours.attrs["frame_ids"]]
    if [int(i) for i in obs.attrs["frame_ids"]] != ids:
        raise ValueError(f"{observations_path} holds frames {short_ids(obs.attrs['frame_ids'])}, "
                         f"the labels {labels_path} {short_ids(ids)}")
    blocks = [open_store(p, "data_term") for p in data_term_paths]
    sources = set(blocks[0].attrs.get("source_frames", ids)) if blocks else set(ids)
    is_source = np.array([i in sources for i in ids])
    uv = sample_points_uv(template["vertices"][...], template["faces"][...], SAMPLE_BARY,
                          scene["template/vertices"][...], scene["template/faces"][...],
                          scene["template/texcoords"][...], scene["template/texcoord_faces"][...])
    truth = FrameSequence(list(truth_paths), "truth")
    X = np.stack([truth_samples(truth.read("appearance", fid), uv) for fid in ids])
    cand = None
    if among_candidates:
        cand = np.concatenate([np.asarray(b["candidates"][...]) for b in blocks])
        if cand.shape[0] != len(ids):
            raise ValueError(f"data_term blocks hold {cand.shape[0]} frames, the labels {len(ids)}")
    labels = np.asarray(ours["labels"][...])
    vis = np.asarray(obs["face_visible"][...], bool)
    new = oracle_labels(X, vis, is_source, labels, candidates=cand)
    changed = int((new != labels).sum())
    log.info("oracle: %d of %d (frame, face) labels differ from the labeling's (%s); %.1f s", changed,
             labels.size, "among its candidates" if among_candidates else "among every source frame",
             time.perf_counter() - t0)
    T = len(ids)
    attrs = {"frame_ids": ids, "rounds": [], "n_never_seen": int(ours.attrs.get("n_never_seen", 0)),
             "n_glimpsed": int(ours.attrs.get("n_glimpsed", 0)),
             "coverage_of_seen_faces": list(ours.attrs.get("coverage_of_seen_faces", [])),
             "oracle": {"among_candidates": bool(among_candidates), "changed": changed,
                        "energy": "not minimised: energy and frame_energy are zeros",
                        "labels_from": str(labels_path)}}
    with create_store(out, "labels", attrs=attrs, params={"oracle": True, "among_candidates": bool(among_candidates)}) as store:
        store.write("labels", new)
        # the oracle minimises no energy (attrs oracle): one row of zeros of the labeling's shape
        store.write("energy", np.zeros(1))
        store.write("frame_energy", np.zeros((1, T)))
        store.write("never_seen", np.asarray(ours["never_seen"][...], bool))
        store.write("glimpse_source", np.asarray(ours["glimpse_source"][...], np.int32))
