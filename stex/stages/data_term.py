"""Data-term stage's artifacts: the ``data_term`` store of one block of target frames
(:mod:`stex.data_term`)."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.camera import Calibration
from stex.config import section_params
from stex.data_term import block_candidates, lost_sources, source_mask
from stex.io import create_store, open_store, position_range, short_ids
from stex.pruning import directed_poses
from stex.similarity import global_similarity, strain_noise
from stex.stages.poses import read_pose_table

log = logging.getLogger("stex.data_term")

__all__ = ["write_data_term"]


def write_data_term(scene_path, template_path, tracking_path, poses_path, observations_path,
                 positions, params: dict, out) -> None:
    """Data-term stage for one block of target frames: write a ``data_term`` store.

    Args:
        scene_path: ``scene`` store (depth intrinsics). template_path: ``template`` (faces).
        tracking_path: ``tracking`` (vertices [T, V, 3]). poses_path: ``poses`` (K_{t→l}).
        observations_path: ``observations`` (face_visible, blur_cost, slanted, descriptors, strain).
        positions: [start, stop) sequence positions of the target frames.
        params: the ``data_term`` config section.
        out: path of the store.
    """
    p = section_params("data_term", params)
    if p["prefilter"] < p["candidates"]:
        raise ValueError(f"data_term.prefilter ({p['prefilter']}) must be >= data_term.candidates "
                         f"({p['candidates']})")
    scene = open_store(scene_path, "scene")
    template = open_store(template_path, "template")
    obs = open_store(observations_path, "observations")
    ids = list(obs.attrs["frame_ids"])
    start, stop = position_range(positions, len(ids), "target")
    faces = np.asarray(template["faces"][...], np.int64)
    tracking = open_store(tracking_path, "tracking")
    vertices = np.asarray(tracking["vertices"][...], np.float32)
    table = read_pose_table(poses_path)
    if table["frame_ids"] != ids:
        raise ValueError(f"{poses_path} and {observations_path} hold different frames")
    if table["source_stride"] != p["source_stride"] and table["neighbours"].shape[1] < len(ids):
        raise ValueError(f"{poses_path} chose its sources with data_term.source_stride "
                         f"{table['source_stride']}, the data term has {p['source_stride']} "
                         f"(re-run the poses stage)")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    face_visible = np.asarray(obs["face_visible"][...], bool)
    # held-out protocol: only every k-th frame may texture anything, every frame is a target
    sources = source_mask(len(ids), p["source_stride"])
    face_visible = face_visible & sources[:, None]
    frame_lost = np.zeros(len(ids), bool)     # the frames the tracking lost, when they are left out
    lost_frames = np.zeros(len(ids), bool)
    if p["exclude_lost"] and "vertex_lost" in tracking:
        frame_lost = np.asarray(tracking["lost"][...], bool)
        lost = lost_sources(frame_lost, tracking["vertex_lost"][...], faces)
        if not (face_visible & ~lost).any() and face_visible.any():
            raise ValueError(f"{tracking_path}: the tracking lost the object wherever a frame sees it (frames "
                             f"{short_ids(tracking.attrs.get('lost_frames', []))} lost): no frame may texture "
                             f"anything. Look at the tracking's log and previews/tracking_fit.png; or take "
                             f"texture from them anyway with data_term.exclude_lost: false")
        face_visible = face_visible & ~lost
        lost_frames = sources & frame_lost
        sources = sources & ~lost_frames
    if "blur_cost" not in obs:
        raise ValueError(f"{observations_path}: no blur_cost table (written by the observations "
                         f"stage since it offers blur_rule; re-run the observations stage)")
    e_qual = (np.asarray(obs["blur_cost"][...], np.float32)
              + np.asarray(obs["slanted"][...], np.float32))
    descriptors = obs["descriptors"] if "descriptors" in obs else None   # streamed by frame
    strain = None
    if p["omega_str"] > 0 and p["similarity"] != "global":
        if "strain" not in obs:
            raise ValueError(f"{observations_path}: no strain table, needed by data_term.omega_str > 0 "
                             f"(re-run the observations stage)")
        strain = np.asarray(obs["strain"][...], np.float32)
    str_tolerance = p["str_tolerance"]
    if str_tolerance == "auto":
        # every block of the run derives the same tolerance: all frames' strain, lost ones left out
        str_tolerance = 0.0 if strain is None else p["str_noise_multiple"] * strain_noise(strain, ~frame_lost)
        log.info("data_term: strain noise of the tracked meshes gives str_tolerance %.4f", str_tolerance)
    if p["similarity"] != "global" and descriptors is None:
        raise ValueError(f"{observations_path}: no SHOT descriptors, needed by "
                         f"data_term.similarity={p['similarity']!r}")
    t0 = time.perf_counter()
    targets = list(range(start, stop))
    # the sources candidate pruning compares each target with (every frame when not pruned)
    cols = table["neighbours"][start:stop]
    cols = cols[:, :max(1, int((cols >= 0).sum(axis=1).max(initial=1)))]
    tt = np.broadcast_to(np.asarray(targets)[:, None], cols.shape)
    poses = directed_poses(table["pairs"], table["poses"], len(ids), tt, np.where(cols >= 0, cols, tt))
    glo = global_similarity(vertices, faces, poses, cal.depth.K, cal.depth.width,
                            cal.depth.height, targets=targets, clip_m=p["glo_clip_m"],
                            scale=p["glo_scale"], sources=cols)
    log.info("data_term: E_glo rows %d..%d in %.1f s", start, stop - 1, time.perf_counter() - t0)
    K = int(p["candidates"])
    nT, nF = len(targets), len(faces)
    exact = []
    attrs = {"frame_ids": ids[start:stop], "sequence_frame_ids": ids,
             "source_frames": [int(i) for i in np.asarray(ids)[sources]],
             # the held-out protocol's sources that tracking lost: left out, but not held out
             "lost_source_frames": [int(i) for i in np.asarray(ids)[lost_frames]]}
    with create_store(out, "data_term", attrs=attrs, params=p) as store:
        store.write("glo", glo.astype(np.float32))
        store.write("glo_sources", cols)
        arrays = {name: store.create(name, (nT, nF, K))
                  for name in ("candidates", "e_glo", "e_loc", "e_qual", "e_str")}
        results = block_candidates(targets, glo, face_visible, e_qual, descriptors, faces,
                                   p["omega_g"], p["similarity"], K, int(p["prefilter"]),
                                   int(p["median_hops"]), strain=strain,
                                   omega_str=float(p["omega_str"]), str_clip=float(p["str_clip"]),
                                   sources=cols, str_tolerance=float(str_tolerance),
                                   borrowed_qual_weight=float(p["borrowed_qual_weight"]))
        for k, res in enumerate(results):
            for name, arr in arrays.items():
                arr[k] = res[name]
            exact.append(float(res["exact"].mean()))
        store.attrs["prefilter_exact"] = [round(x, 5) for x in exact]
        store.attrs["str_tolerance"] = float(str_tolerance)
        store.attrs["seconds"] = round(time.perf_counter() - t0, 3)
    log.info("data_term: %d targets in %.1f s; pruning provably exact for %.2f %% of (target, face)",
             nT, time.perf_counter() - t0, 100 * float(np.mean(exact)))
