"""Baselines for the evaluation: Kim et al. 2019's single global texture, and the naive per-frame
projection.

What it computes
----------------
- :func:`global_texture` — the paper's comparison method (Kim, Kim, Park, Lee, PG 2019, "Global
  Texture Mapping for Dynamic Objects"): **one** texture for the whole sequence. Every texel
  blends all frames where its face is visible, sampled at the optimised texture coordinates ξ_t
  (the same ξ as the spatiotemporal volume), with normalised per-face visibility weights:

      C(x) = Σ_t w_t(f) C_t(ξ_t(x)) / Σ_t w_t(f),   f = face of texel x, w_t(f) = 0 if f not seen at t.

  Weight choice: the authors' code (``GenAtlas_UVAtlas`` → ``multi.png``, official_code_notes.md
  §2.2/§2.5) uses w_t(f) = cos θ between the face normal and the camera's optical axis, over the
  frames that pass visibility and background subtraction, normalised to sum 1 per face. Here the
  weights are whatever ``face_weight`` holds — pass the projection store's ``face_cos`` [T, F]
  (its attr ``cos_mode`` says view ray or optical axis; ``'optical_axis'`` is the authors'
  variant) — and the visibility is the projection's ``face_visible`` (depth test, facing, eroded
  foreground mask: the counterpart of the authors' background subtraction). The normalisation
  is per texel (Σ_t w_t(f) of its face), so normalising per face first changes nothing.
- :func:`write_global_texture` — the ``global_texture`` pipeline stage: :func:`global_texture`
  over the source frames of the held-out protocol (sequence positions 0, k, 2k, ... with
  k = ``data_term.source_stride``, :func:`source_mask`), weighted by the projection's ``face_cos``,
  written to a ``global_texture`` store that the evaluation reads.
- :func:`projection_texture` — the naive per-frame projection: only what frame t sees, the rest
  black and uncovered (:func:`stex.dynamism.partial_texture`).

Cost
----
:func:`global_texture` streams: ``load(t)`` once per frame, one colour image in memory at a time,
and two float32 accumulators (W² x 4 texel sums: 256 MB at W = 4096). O(T · covered texels).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np
from numba import njit

from stex.dynamism import _as_sampler, _load_checked, partial_texture
from stex.data_term import source_mask
from stex.volume import fill_gutter

log = logging.getLogger("stex.global_texture")

__all__ = ["global_texture", "projection_texture", "write_global_texture"]


@njit(cache=True, nogil=True)
def _accumulate(index, tex_face, w, tex, covered, acc, wsum):
    """acc[i] += w[f] * tex[index[i]] and wsum[i] += w[f] for the compact covered texels i of the
    atlas (face f = tex_face[i]) that this frame covered. tex (W*W, 3) uint8, covered (W*W,) bool."""
    for i in range(index.shape[0]):
        p = index[i]
        if not covered[p]:
            continue
        wt = w[tex_face[i]]
        for k in range(3):
            acc[i, k] += wt * np.float32(tex[p, k])
        wsum[i] += wt


def _weights_row(face_weight, t: int, F: int) -> np.ndarray | None:
    if face_weight is None:
        return None
    w = face_weight(t) if callable(face_weight) else face_weight[t]
    w = np.asarray(w, np.float32)
    if w.shape != (F,):
        raise ValueError(f"face_weight row {t} must have shape ({F},), got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"face_weight row {t} must be finite and >= 0")
    return w


def global_texture(load: Callable, n_frames: int, sampler_or_maps, face_weight=None,
                   min_weight: float = 0.0, gutter_px: int = 4, progress: bool = False):
    """Kim et al. 2019's single global texture: every frame blended into one atlas.

    Args:
        load: ``load(t) -> (image (Hc, Wc, 3) uint8 RGB, xi_t (V, 2) float px (integer = pixel
            centre), face_visible_t (F,) bool)``, called once per frame, t = 0 .. T-1.
        n_frames: T.
        sampler_or_maps: the atlas, a :class:`stex.volume.TexelSampler` or (texel_face (W, W),
            texel_bary (W, W, 3), faces (F, 3)).
        face_weight: per-frame, per-face blending weight w_t(f) >= 0: a (T, F) array (numpy or
            zarr, e.g. projection ``face_cos``, read one row per frame) or a callable
            ``t -> (F,)``; None = 1 for every visible face (plain average).
        min_weight: a (t, f) with w_t(f) <= min_weight is left out (e.g. 0.3 to drop grazing
            views, θ_n); with the default 0 only zero weights are left out.
        gutter_px: rings of empty texels around the charts to fill (:func:`stex.volume.fill_gutter`);
            covered texels of faces never seen are filled from their neighbours first.
        progress: log frames done / total and the rate.

    Returns:
        (texture (W, W, 3) uint8 RGB; weight_sum (W, W) float32, Σ_t w_t(f) of each texel,
        0 where nothing was observed — those texels hold filled colours, not observations).
    """
    sampler = _as_sampler(sampler_or_maps)
    T = int(n_frames)
    if T < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    F, W = len(sampler.faces), sampler.W
    idx, tface = sampler.index, sampler.face
    acc = np.zeros((len(idx), 3), np.float32)
    wsum = np.zeros(len(idx), np.float32)
    t0 = time.perf_counter()
    for t in range(T):
        image, xi, vis = _load_checked(load, t, F)
        w = _weights_row(face_weight, t, F)
        w = vis.astype(np.float32) if w is None else np.where(vis, w, np.float32(0))
        use = w > float(min_weight)
        if use.any():
            tex, cov = partial_texture(sampler, xi, use, image)
            _accumulate(idx, tface, w, tex.reshape(-1, 3), cov.ravel(), acc, wsum)
        if progress and ((t + 1) % 10 == 0 or t + 1 == T):
            dt = time.perf_counter() - t0
            log.info("global texture: %d/%d frames (%.1f frames/s)", t + 1, T, (t + 1) / max(dt, 1e-9))
    seen = wsum > 0
    out = np.zeros((W * W, 3), np.uint8)
    out[idx[seen]] = np.clip(np.floor(acc[seen] / wsum[seen, None] + 0.5), 0, 255).astype(np.uint8)
    weight_sum = np.zeros(W * W, np.float32)
    weight_sum[idx] = wsum
    texture = out.reshape(W, W, 3)
    weight_sum = weight_sum.reshape(W, W)
    fill_gutter(texture, weight_sum > 0, sampler.covered, int(gutter_px))
    return texture, weight_sum


def projection_texture(sampler_or_maps, xi_t, face_visible_t, image_t):
    """The naive per-frame projection baseline: frame t's image copied into the atlas on the
    faces it sees, at the texture coordinates ξ_t; every other texel black and uncovered (no
    borrowing from other frames, no gutter).

    Same arguments as :func:`stex.dynamism.partial_texture`.

    Returns:
        (texture (W, W, 3) uint8, covered (W, W) bool).
    """
    return partial_texture(sampler_or_maps, xi_t, face_visible_t, image_t)


def global_texture_params(params: dict | None = None) -> dict:
    """The settings of :func:`write_global_texture`: the schema's ``global_texture`` section
    (``min_weight``) completed with its defaults, plus ``source_stride`` (frames; not a key of
    that section: the workflow passes ``data_term.source_stride`` so that the baseline uses the
    data term's source frames; default the ``data_term`` section's default). Unknown keys and bad values
    raise ValueError."""
    from stex.config import section_params

    params = dict(params or {})
    stride = params.pop("source_stride", None)
    p = section_params("global_texture", params)
    if stride is None:
        stride = section_params("data_term", {})["source_stride"]
    p["source_stride"] = section_params("data_term", {"source_stride": stride})["source_stride"]
    return p


def write_global_texture(scene_path, frames_paths, template_path, projection_path, coords_path,
                         out, params: dict | None = None) -> None:
    """Global-texture stage: Kim et al. 2019's single texture over the source frames, written to
    a ``global_texture`` store.

    Source frames are the sequence positions 0, k, 2k, ... (k = ``params['source_stride']``, the
    data-term stage's setting, :func:`source_mask`). Each source frame t blends into the atlas with
    weight w_t(f) = projection ``face_cos[t, f]`` where ``face_visible[t, f]``; (t, f) with
    w_t(f) <= ``params['min_weight']`` are left out (:func:`global_texture`). Colours are sampled
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
        params: :func:`global_texture_params` (``min_weight``, ``source_stride``).

    Writes ``texture`` (W, W, 3) uint8 sRGB, ``weight_sum`` (W, W) float32 (Σ_t w_t(f) of each
    texel's face, 0 where nothing was observed), ``face_textured`` (F,) bool (faces with at least
    one used observation) and attrs ``source_frames`` (global frame ids of the source frames),
    ``sequence_frame_ids`` (every frame id of the scene), ``seconds`` (wall time of the blend, s).

    Attr ``atlas_digest``: the template's atlas (:func:`stex.template.atlas_digest`).

    Raises:
        ValueError naming the store when frame counts, frame ids, face or vertex counts disagree.
    """
    from stex.io import FrameSequence, create_store, open_store
    from stex.observations import open_coordinates
    from stex.stages.template import template_atlas_digest
    from stex.volume import TexelSampler

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
