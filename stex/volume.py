"""Texture volume: one W x W slice of the fixed atlas per frame, from the labelled source frames.

What it computes
----------------
- :func:`volume_slice` — the slice of one target frame t: every covered texel of the atlas takes
  the colour of the source frame its face is labelled with at t, looked up at that frame's
  texture coordinates ξ (:class:`stex.sampling.TexelSampler`, which also says how), and the
  texels left without colour and ``gutter_px`` rings around the charts are filled
  (:func:`stex.sampling.fill_gutter`). The stage (:mod:`stex.stages.volume`) samples a pass of
  slices at once and colours never-seen faces from the nearest seen texels
  (:func:`stex.sampling.nearest_seen_texels`), then, with ``volume.fill`` harmonic, by a
  seam-aware screened harmonic fill over the atlas texel graph (:class:`stex.fill.SeamFill`).

Label map
---------
The returned ``label_map`` (W, W) int32 holds the source frame each texel was sampled from;
-1 in the gutter, on empty texels, on texels of unlabelled faces and where ξ was not finite
(those are filled colours, not observations).
"""

from __future__ import annotations

from stex.sampling import TexelSampler

__all__ = ["volume_slice"]


def volume_slice(texel_face, texel_bary, faces, labels_t, coords, images, gutter_px: int = 4,
                 interpolation: str = "bicubic"):
    """The texture-volume slice of one target frame.

    Args:
        texel_face: (W, W) int32 face per texel, -1 = empty. texel_bary: (W, W, 3) float32.
        faces: (F, 3) int vertex indices.
        labels_t: (F,) int32 source frame of each face at this target frame, -1 = none. Labels
            index ``coords`` and ``images`` (local frame indices of the sequence).
        coords: ξ, per source frame s an (V, 2) float array of colour-pixel coordinates of the
            vertices (integer = pixel centre; NaN = not available): anything ``coords[s]`` works
            on (a (T, V, 2) array, a zarr array, a dict) or a callable ``coords(s)``.
        images: source frame s -> (Hc, Wc, 3) uint8 RGB colour image, likewise indexable or
            callable. Only the frames that occur in ``labels_t`` are read, each once.
        gutter_px: rings of empty texels around the charts to fill (see :func:`stex.sampling.fill_gutter`).
        interpolation: "bicubic" or "bilinear" (see :class:`stex.sampling.TexelSampler`).

    Returns:
        (slice (W, W, 3) uint8, label_map (W, W) int32; -1 where the colour is not sampled).

    For many slices of one atlas, build a :class:`stex.sampling.TexelSampler` once and call its ``slice``.
    """
    return TexelSampler(texel_face, texel_bary, faces, interpolation).slice(labels_t, coords, images,
                                                                          gutter_px)
