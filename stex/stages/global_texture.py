"""Global-texture stage's artifacts: the ``global_texture`` store the evaluation compares with
(:mod:`stex.global_texture`)."""

from __future__ import annotations

import logging
import time

import numpy as np

from stex.data_term import source_mask
from stex.global_texture import global_texture, global_texture_params
from stex.io import FrameSequence, create_store, open_store
from stex.sampling import TexelSampler
from stex.stages.observations import open_coordinates
from stex.stages.template import template_atlas_digest

log = logging.getLogger("stex.global_texture")

__all__ = ["write_global_texture"]


def write_global_texture(scene_path, frames_paths, template_path, projection_path, coords_path,
                         out, params: dict | None = None) -> None:
    """Global-texture stage: Kim et al. 2019's single texture over the source frames, written to
    a ``global_texture`` store.

    Source frames are the sequence positions 0, k, 2k, ... (k = ``params['source_stride']``, the
    data-term stage's setting, :func:`stex.data_term.source_mask`). Each source frame t blends into the atlas with
    weight w_t(f) = projection ``face_cos[t, f]`` where ``face_visible[t, f]``; (t, f) with
    w_t(f) <= ``params['min_weight']`` are left out (:func:`stex.global_texture.global_texture`). Colours are sampled
    at the texture coordinates of ``coords_path`` (ξ or Φ, as the volume). Chart gutters are
    filled over the template's ``gutter_px`` rings.

    Args:
        scene_path: ``scene`` store (frame ids, in sequence order).
        frames_paths: ``frames`` block stores (colour images (Hc, Wc, 3) uint8, one read per
            source frame).
        template_path: ``template`` store (faces (F, 3), texel map (W, W), attr gutter_px).
        projection_path: ``projection`` store (face_visible, face_cos [T, F]; rows of the source
            frames are read).
        coords_path: ``texcoords`` store (ξ [T, V, 2] px) or the ``projection`` store (Φ).
        out: path of the ``global_texture`` store.
        params: :func:`stex.global_texture.global_texture_params` (``min_weight``, ``source_stride``).

    Writes ``texture`` (W, W, 3) uint8 sRGB, ``weight_sum`` (W, W) float32 (Σ_t w_t(f) of each
    texel's face, 0 where nothing was observed), ``face_textured`` (F,) bool (faces with at least
    one used observation) and attrs ``source_frames`` (global frame ids of the source frames),
    ``sequence_frame_ids`` (every frame id of the scene), ``seconds`` (wall time of the blend, s).

    Attr ``atlas_digest``: the template's atlas (:func:`stex.atlas.atlas_digest`).

    Raises:
        ValueError naming the store when frame counts, frame ids, face or vertex counts disagree.
    """
    p = global_texture_params(params)
    min_weight = float(p["min_weight"])
    scene = open_store(scene_path, "scene")
    ids = [int(i) for i in scene.attrs["frame_ids"]]
    T = len(ids)
    template = open_store(template_path, "template")
    faces = np.asarray(template["faces"][...], np.int64)
    F, V = len(faces), int(template["vertices"].shape[0])
    projection = open_store(projection_path, "projection")
    if [int(i) for i in projection.attrs["frame_ids"]] != ids:
        raise ValueError(f"projection store {projection_path} holds {len(projection.attrs['frame_ids'])} "
                         f"frames, the scene {scene_path} has {T} (or other frame ids)")
    face_visible, face_cos = projection["face_visible"], projection["face_cos"]
    if face_visible.shape[1] != F:
        raise ValueError(f"projection store {projection_path} has {face_visible.shape[1]} faces, "
                         f"the template {template_path} has {F}")
    coords, _, _ = open_coordinates(coords_path)
    if coords.shape[0] != T:
        raise ValueError(f"texture coordinates {coords_path} hold {coords.shape[0]} frames, the "
                         f"scene {scene_path} has {T}")
    if coords.shape[1] != V:
        raise ValueError(f"texture coordinates {coords_path} hold {coords.shape[1]} vertices, the "
                         f"template {template_path} has {V}")
    photos = FrameSequence(list(frames_paths), "frames")
    if photos.frame_ids != ids:
        raise ValueError(f"frames stores {', '.join(str(x) for x in frames_paths)} hold "
                         f"{len(photos.frame_ids)} frames, the scene {scene_path} has {T} "
                         f"(or other frame ids)")
    tf = template["texel/face_id"][...]
    W = int(template.attrs["atlas_size"])
    if tf.shape != (W, W):
        raise ValueError(f"template {template_path}: texel map {tf.shape}, atlas_size {W}")
    sampler = TexelSampler(tf, template["texel/bary"][...], faces)

    src = np.flatnonzero(source_mask(T, p["source_stride"]))
    t0 = time.perf_counter()
    vis = np.stack([np.asarray(face_visible[int(t)], bool) for t in src])          # (S, F)
    cos = np.stack([np.asarray(face_cos[int(t)], np.float32) for t in src])        # (S, F)

    def load(k):
        t = int(src[k])
        return photos.read("color", ids[t]), np.asarray(coords[t], np.float64), vis[k]

    texture, weight_sum = global_texture(load, len(src), sampler, face_weight=cos,
                                         min_weight=min_weight,
                                         gutter_px=int(template.attrs["gutter_px"]),
                                         progress=True)
    # the (t, f) global_texture used: visible with weight above min_weight
    face_textured = (vis & (cos > min_weight)).any(axis=0)
    seconds = time.perf_counter() - t0
    log.info("global texture: %d source frames (stride %d) in %.1f s; %d/%d faces textured",
             len(src), p["source_stride"], seconds, int(face_textured.sum()), F)
    attrs = {"source_frames": [ids[int(t)] for t in src], "sequence_frame_ids": ids,
             "seconds": float(seconds), "atlas_digest": template_atlas_digest(template)}
    with create_store(out, "global_texture", attrs=attrs, params=p) as store:
        store.write("texture", texture)
        store.write("weight_sum", weight_sum)
        store.write("face_textured", face_textured)
