"""Observations stage's artifacts: the ``observations`` store, one pass over the colour frames
(:mod:`stex.observations`), and :func:`open_coordinates`, the texture coordinates the later stages
read (ξ of the ``texcoords`` store or Φ of the ``projection`` store)."""

from __future__ import annotations

import logging
import time

import numpy as np
import zarr

from stex.config import section_params
from stex.dynamism import face_ssim, partial_texture
from stex.image import grey_float32
from stex.io import FrameSequence, create_store, open_store
from stex.observations import (EDGE_SAMPLES, blur_cost, edge_samples, face_centroids, face_motion,
                               face_samples, slanted_faces, theta_b_for_width)
from stex.sampling import TexelSampler
from stex.shot import geodesic_neighbourhoods, mesh_resolution, shot_descriptors
from stex.similarity import face_strain
from stex.atlas import texel_map
from stex.texcoords import SAMPLE_BARY

log = logging.getLogger("stex.observations")

__all__ = ["open_coordinates", "write_observations"]


def open_coordinates(path):
    """The texture coordinates the later stages use: ``(coords, valid, kind)``.

    ``coords`` (T, V, 2) px and ``valid`` (T, V) bool are zarr arrays (read per frame): ξ and
    ``valid`` of a ``texcoords`` store, or Φ and ``vertex_visible`` of a ``projection`` store.
    """
    kind = zarr.open_group(str(path), mode="r").attrs.get("stex_artifact")
    if kind == "texcoords":
        g = open_store(path, "texcoords")
        return g["xi"], g["valid"], kind
    if kind == "projection":
        g = open_store(path, "projection")
        return g["phi"], g["vertex_visible"], kind
    raise ValueError(f"{path}: expected a 'texcoords' or 'projection' store, found {kind!r}")


def write_observations(template_path, tracking_path, projection_path, coords_path, frames_paths,
                       params: dict, out) -> None:
    """Observations stage: write the ``observations`` store (one pass over the colour frames).

    Args:
        template_path: ``template`` store (faces, adjacency, atlas).
        tracking_path: ``tracking`` store (vertices [T, V, 3], for the SHOT descriptors and the
            strain).
        projection_path: ``projection`` store (face visibility and cosines).
        coords_path: ``texcoords`` store (ξ) or the ``projection`` store itself (Φ).
        frames_paths: ``frames`` block stores (colour images, read one frame at a time).
        params: the ``observations`` config section.
        out: path of the store to write.
    """
    p = section_params("observations", params)
    template = open_store(template_path, "template")
    projection = open_store(projection_path, "projection")
    faces = np.asarray(template["faces"][...], np.int64)
    edges = np.asarray(template["adjacency/edges"][...], np.int64)
    ids = list(projection.attrs["frame_ids"])
    coords, valid, kind = open_coordinates(coords_path)
    if coords.shape[0] != len(ids):
        raise ValueError(f"{coords_path}: {coords.shape[0]} frames, {projection_path}: {len(ids)}")
    frames = FrameSequence(list(frames_paths), "frames")
    missing = [f for f in ids if f not in frames._where]
    if missing:
        raise ValueError(f"frames stores hold no colour image for frames {missing[:5]}")
    T, nF, nE = len(ids), faces.shape[0], edges.shape[0]
    face_visible = np.asarray(projection["face_visible"][...], bool)
    face_cos = np.asarray(projection["face_cos"][...], np.float32)
    centroids = np.empty((T, nF, 2))
    verts = open_store(tracking_path, "tracking")["vertices"]
    if verts.shape[0] != T:
        raise ValueError(f"{tracking_path}: {verts.shape[0]} frames, {projection_path}: {T}")
    t0 = time.perf_counter()
    rest = np.asarray(template["vertices"][...], np.float64)
    radius = float(p["shot_radius"]) * mesh_resolution(rest, faces)
    nbh = geodesic_neighbourhoods(rest, faces, radius)      # fixed topology: once per sequence
    small = texel_map(template["texcoords"][...], template["texcoord_faces"][...], int(p["ssim_size"]))
    ssim_sampler = TexelSampler(small[0], small[1], faces)
    log.info("observations: SHOT radius %.1f mm (%d neighbours per vertex on average), SSIM at "
             "%d², set up in %.1f s", 1000 * radius, len(nbh[1]) // max(len(rest), 1),
             int(p["ssim_size"]), time.perf_counter() - t0)
    previous = None
    attrs = {"frame_ids": ids, "coordinates": kind}
    with create_store(out, "observations", attrs=attrs, params=p) as store:
        a_face = store.create("face_samples", (T, nF, len(SAMPLE_BARY)))
        a_edge = store.create("edge_samples", (T, nE, EDGE_SAMPLES))
        a_dyn = store.create("dynamism", (T, nF))
        a_desc = store.create("descriptors", (T, verts.shape[1], 352))
        for k, fid in enumerate(ids):
            xy = np.asarray(coords[k], np.float64)
            ok = np.asarray(valid[k], bool)
            color = frames.read("color", fid)
            width = color.shape[1]
            g = grey_float32(color)
            a_face[k] = face_samples(g, xy, faces, face_visible[k])
            a_edge[k] = edge_samples(g, xy, edges, ok)
            centroids[k] = face_centroids(xy, faces)
            current = partial_texture(ssim_sampler, xy, face_visible[k], color)
            if previous is not None:
                a_dyn[k] = face_ssim(*previous, *current, small[0], nF)
                if k == 1:          # frame 0 has no predecessor: its row copies row 1
                    a_dyn[0] = a_dyn[1]
            elif T == 1:
                a_dyn[0] = np.full(nF, np.nan, np.float32)
            previous = current
            a_desc[k] = shot_descriptors(np.asarray(verts[k], np.float64), faces, nbh, radius).astype(np.float16)
            if (k + 1) % 20 == 0 or k + 1 == T:
                log.info("observations: frame %d (%d/%d, %.1f frames/s)", fid, k + 1, T,
                         (k + 1) / (time.perf_counter() - t0))
        theta_b = theta_b_for_width(p["theta_b_px"], width)
        motion = face_motion(centroids, face_visible, p["unseen_neighbours"])
        blurred = blur_cost(motion, face_visible, theta_b, "step") > 0   # for its fraction only
        slanted = slanted_faces(face_cos, p["theta_n"], p["angle_rule"]) & face_visible
        store.write("strain", face_strain(verts[...], rest, faces, int(p["strain_rings"])))
        store.write("face_visible", face_visible)
        store.create("motion", motion.shape)[...] = motion      # NaN = unknown, by design
        store.write("blur_cost", blur_cost(motion, face_visible, theta_b, p["blur_rule"],
                                           p["blur_cap"]))
        store.write("slanted", slanted)
        n_vis = max(int(face_visible.sum()), 1)
        store.attrs["theta_b_px"] = theta_b
        store.attrs["fractions"] = {"blurred": round(float(blurred.sum()) / n_vis, 5),
                                    "slanted": round(float(slanted.sum()) / n_vis, 5)}
