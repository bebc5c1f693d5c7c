"""Poses stage, artifact side: read per-frame vertices from a store, write the ``poses`` store.

The poses themselves are :func:`stex.poses.pair_poses` (arrays in, arrays out), for the frame
pairs :mod:`stex.pruning` chooses (``poses.nearest_frames``; 0 = every pair). The vertices are
read from the array the caller names (the ``tracking`` store's ``vertices`` by default), never
from the ground truth unless asked for by name: the evaluation may ask for ``truth/vertices``,
a library user who does not is not handed the truth in place of the tracking.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import zarr

from stex.data_term import source_mask
from stex.io import create_store, open_store
from stex.poses import pair_poses, pose_params
from stex.pruning import nearest_sources, pose_pairs, shape_descriptors

log = logging.getLogger("stex.poses")


def read_vertices(source, array: str = "vertices"):
    """Per-frame vertices (T, V, 3) float64, faces (F, 3) or None, frame ids and the array name
    read, from a store.

    ``source`` is a zarr store path. ``array`` names the (T, V, 3) array, and only that array is
    read: ``vertices`` (a ``tracking`` store) by default, ``given/vertices`` or
    ``truth/vertices`` of a ``scene`` store when asked for by name. Faces come from
    ``template/faces`` or ``faces`` in the same store (or None).
    """
    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such store")
    g = _open_vertices_store(path)
    if array not in g:
        raise ValueError(f"{path}: no array {array!r} (read_vertices reads only the array it is given)")
    X = np.asarray(g[array][...], dtype=np.float64)
    faces = None
    for name in ("template/faces", "faces"):
        if name in g:
            faces = np.asarray(g[name][...])
            break
    frame_ids = g.attrs.get("frame_ids", list(range(X.shape[0])))
    return X, faces, list(frame_ids), array


def _open_vertices_store(path: Path):
    """A stex store through :func:`stex.io.open_store` (its kind read from it: a damaged chunk
    is then named), or a plain zarr group holding vertices."""
    g = zarr.open_group(str(path), mode="r")
    kind = g.attrs.get("stex_artifact")
    if kind:
        return open_store(path, kind)
    if g.attrs.get("complete") is False:
        raise ValueError(f"{path}: store is incomplete (its writer did not finish)")
    return g


def write_pose_table(vertices_source, out, params: dict | None = None, array: str = "vertices",
                     faces=None, threads: int | None = None, visibility=None,
                     source_stride: int = 1) -> None:
    """Choose the frame pairs, compute their poses and write the ``poses`` store.

    Args:
        vertices_source: store path holding (T, V, 3) per-frame vertices (see
            :func:`read_vertices`; the ``tracking`` store in the pipeline).
        out: output store path (``poses.zarr``), written atomically.
        params: the ``poses`` config section.
        array: name of the vertices array in the store (default ``vertices``, the ``tracking``
            store's; see :func:`read_vertices`).
        faces: (F, 3) int faces, or a store path holding ``template/faces`` or ``faces`` (a
            ``scene`` or ``template`` store); default: the vertices store's own faces.
        threads: worker threads.
        visibility: ``projection`` store path: its face_visible decides which frames can serve a
            face (:func:`stex.pruning.nearest_sources`); None = the k nearest frames overall.
        source_stride: ``data_term.source_stride``: only those frames are chosen as sources.
    """
    p = pose_params(params)
    X, own_faces, frame_ids, array = read_vertices(vertices_source, array)
    if faces is None:
        faces = own_faces
    elif isinstance(faces, (str, os.PathLike)):
        g = _open_vertices_store(Path(faces))
        name = next((n for n in ("template/faces", "faces") if n in g), None)
        if name is None:
            raise ValueError(f"{faces}: no template/faces or faces array")
        faces = np.asarray(g[name][...])
    if faces is None:
        if p["icp_iterations"] > 0:
            raise ValueError(f"{vertices_source}: no faces found for the point-to-plane ICP "
                             "(pass faces=, or set poses.icp_iterations: 0)")
        faces = np.zeros((0, 3), np.int32)
    vis = None
    if visibility is not None:
        proj = open_store(visibility, "projection")
        if list(proj.attrs["frame_ids"]) != list(frame_ids):
            raise ValueError(f"{visibility} and {vertices_source} hold different frames")
        vis = np.asarray(proj["face_visible"][...], bool)
    desc = shape_descriptors(X, p["sample_vertices"], seed=p["seed"])
    nb = nearest_sources(desc, vis, p["nearest_frames"], source_mask(len(X), source_stride),
                         coverage=p["coverage_frames"], mode=p["coverage_mode"])
    pairs = pose_pairs(nb)
    log.info("poses: %d frames, up to %d sources per frame (nearest_frames %d), %d pairs of %d",
             len(X), nb.shape[1], p["nearest_frames"], len(pairs), len(X) * (len(X) - 1) // 2)
    poses, ratio = pair_poses(X, faces, pairs.reshape(-1, 2), p, threads=threads)
    with create_store(out, "poses", attrs={"frame_ids": frame_ids,
                                           "vertices_source": str(vertices_source),
                                           "vertices_array": array,
                                           "source_stride": int(source_stride)}, params=p) as s:
        s.write("pairs", pairs.reshape(-1, 2))
        s.write("poses", poses.reshape(-1, 4, 4))
        s.write("inlier_ratio", ratio)
        s.write("neighbours", nb)
        s.write("descriptors", desc)


def read_pose_table(path) -> dict:
    """The ``poses`` store as arrays: ``pairs`` (P, 2) int64, ``poses`` (P, 4, 4) float64,
    ``inlier_ratio`` (P,) float32, ``neighbours`` (T, N) int64, ``frame_ids``."""
    g = open_store(path, "poses")
    if "pairs" not in g:
        raise ValueError(f"{path}: a pose table of every frame pair in the layout before candidate "
                         f"pruning (no 'pairs' array); re-run the poses stage")
    return {"pairs": np.asarray(g["pairs"][...], np.int64),
            "poses": np.asarray(g["poses"][...], np.float64),
            "inlier_ratio": np.asarray(g["inlier_ratio"][...], np.float32),
            "neighbours": np.asarray(g["neighbours"][...], np.int64),
            "frame_ids": list(g.attrs["frame_ids"]),
            "source_stride": int(g.attrs.get("source_stride", 1))}
