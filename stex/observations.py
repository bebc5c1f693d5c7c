"""Observations stage: what every frame shows of every face, gathered in one pass over the frames.

The labeling (paper §5) compares frames with each other through a handful of per-(frame, face)
and per-(frame, edge) quantities that do not depend on the target time t. They are computed once
here, streaming the colour images one at a time, so that the data-term and labeling stages never
touch an image again:

- **Face samples** (E_temp): the grey value at the authors' 15 barycentric samples of face f,
  looked up bilinearly at the face's texture coordinates on frame l's colour image.
- **Edge samples** (E_spa): 9 grey values along each shared edge of adjacent faces (from
  ``adjacency/edges[e, 0]`` to ``[e, 1]``, at s/8, s = 0..8). The texture coordinates are per
  vertex, so both faces of the edge see the same samples in one frame and the spatial cost
  between labels a and b of the two faces only needs the samples of frames a and b.
- **Quality terms** (E_qual, Eq. quality term): ``motion`` — how far the face's texture
  coordinates move per frame (mean of the moves to frame l-1 and l+1 of the centroid of its three
  coordinates, as the authors' ``Selector.cpp``; :func:`face_motion`, with ``unseen_neighbours``
  saying whether a neighbouring frame that does not see the face still gives a motion); and
  ``blur_cost``, the blur part of E_qual the data term uses (:func:`blur_cost`): the paper's step
  (blurred when the motion exceeds θ_b or is unknown) or, with ``blur_rule: graded``, the motion
  in units of θ_b. ``slanted`` — the view angle is too oblique (rule ``angle_rule``, below).
- **Dynamism** S(f, t) (selective weighting): mean SSIM of face f between the partial texture
  maps of frames t-1 and t (:mod:`stex.dynamism`).
- **SHOT descriptors** of every vertex of the tracked mesh (E_loc; :mod:`stex.similarity`).
- **Strain** of every face of the tracked mesh: smoothed log stretch of its edges against the
  template (E_str; :func:`stex.similarity.face_strain`), once for all frames here rather than in
  every data_term block.

Texture coordinates are the optimised ξ of the ``texcoords`` store when the workflow runs that
stage, or Φ of the ``projection`` store otherwise (:func:`stex.stages.observations.open_coordinates`).

Angle rule. The paper writes χ_θn(1 − n·c) with θ_n = 0.3, i.e. a face is slanted when
cos ≤ 0.7; the authors' code tests cos ≤ 0.3 (``official_code_notes.md`` §2.4). Both are offered
(``angle_rule: paper | authors``); the default is the authors' rule: the paper's flags most
visible (frame, face) pairs of the demo as slanted, which drives labels away from the target
frame (docs/decisions/observations.md).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from stex.render import bilinear_taps
from stex.texcoords import SAMPLE_BARY

__all__ = ["EDGE_SAMPLES", "PAPER_COLOR_WIDTH", "BLUR_RULES", "UNSEEN_NEIGHBOURS",
           "theta_b_for_width", "face_samples", "edge_samples", "face_motion",
           "blurred_faces", "blur_cost", "slanted_faces"]

#: samples along a shared edge (the authors' e_samnum = 9, at s/8)
EDGE_SAMPLES = 9
ANGLE_RULES = ("paper", "authors")


@njit(cache=True, nogil=True)
def _face_samples_kernel(img, coords, faces, visible, bary, out):
    H, W = img.shape
    for f in range(faces.shape[0]):
        if not visible[f]:
            continue
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        for s in range(bary.shape[0]):
            u = bary[s, 0] * coords[a, 0] + bary[s, 1] * coords[b, 0] + bary[s, 2] * coords[c, 0]
            v = bary[s, 0] * coords[a, 1] + bary[s, 1] * coords[b, 1] + bary[s, 2] * coords[c, 1]
            r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(u, v, W, H)
            g = w00 * img[r0, c0] + w01 * img[r0, c1] + w10 * img[r1, c0] + w11 * img[r1, c1]
            out[f, s] = np.uint8(min(255.0, max(0.0, g + 0.5)))


@njit(cache=True, nogil=True)
def _edge_samples_kernel(img, coords, edges, valid, n, out):
    H, W = img.shape
    for e in range(edges.shape[0]):
        i, j = edges[e, 0], edges[e, 1]
        if not (valid[i] and valid[j]):
            continue
        for s in range(n):
            w = s / (n - 1.0)
            u = (1.0 - w) * coords[i, 0] + w * coords[j, 0]
            v = (1.0 - w) * coords[i, 1] + w * coords[j, 1]
            r0, c0, r1, c1, w00, w01, w10, w11 = bilinear_taps(u, v, W, H)
            g = w00 * img[r0, c0] + w01 * img[r0, c1] + w10 * img[r1, c0] + w11 * img[r1, c1]
            out[e, s] = np.uint8(min(255.0, max(0.0, g + 0.5)))


def _check_coords(coords, n_vertices_needed: int, name="coords") -> np.ndarray:
    c = np.ascontiguousarray(coords, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"{name} must be (V, 2) pixel coordinates, got shape {c.shape}")
    if c.shape[0] < n_vertices_needed:
        raise ValueError(f"{name} has {c.shape[0]} vertices but the mesh indexes {n_vertices_needed}")
    return c


def face_samples(grey_image, coords, faces, face_visible, n_samples: int = 15) -> np.ndarray:
    """Grey values at the 15 barycentric samples of every visible face.

    Args:
        grey_image: (H, W) float grey image (0..255), e.g. :func:`stex.image.grey_float32`.
        coords: (V, 2) texture coordinates of the vertices on that image (px, u column, v row,
            integer = pixel centre), ξ or Φ.
        faces: (F, 3) int triangles.
        face_visible: (F,) bool; invisible faces get 0 (their samples are meaningless).
        n_samples: the first n of the authors' 15 barycentric triples.

    Returns:
        (F, n_samples) uint8, bilinear lookups (clamp-to-edge) rounded to the nearest grey level.
    """
    img = np.ascontiguousarray(grey_image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"grey_image must be (H, W), got shape {img.shape}")
    F = np.ascontiguousarray(faces, dtype=np.int64)
    vis = np.ascontiguousarray(face_visible, dtype=np.bool_)
    if vis.shape != (F.shape[0],):
        raise ValueError(f"face_visible must be ({F.shape[0]},), got {vis.shape}")
    c = _check_coords(coords, int(F.max()) + 1 if F.size else 0)
    if not 1 <= n_samples <= len(SAMPLE_BARY):
        raise ValueError(f"n_samples must be in 1..{len(SAMPLE_BARY)}")
    out = np.zeros((F.shape[0], n_samples), np.uint8)
    _face_samples_kernel(img, c, F, vis, np.ascontiguousarray(SAMPLE_BARY[:n_samples]), out)
    return out


def edge_samples(grey_image, coords, edges, vertex_valid, n_samples: int = EDGE_SAMPLES) -> np.ndarray:
    """Grey values at ``n_samples`` evenly spaced points along every edge (both ends included).

    Args:
        grey_image: (H, W) float grey image (0..255).
        coords: (V, 2) texture coordinates on that image (px).
        edges: (E, 2) int vertex pairs (the shared edge of each adjacent face pair).
        vertex_valid: (V,) bool; an edge is sampled only when both its vertices are valid,
            otherwise its row is 0.

    Returns:
        (E, n_samples) uint8, sample s at (1 − s/(n−1))·coords[e0] + s/(n−1)·coords[e1].
    """
    img = np.ascontiguousarray(grey_image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"grey_image must be (H, W), got shape {img.shape}")
    E = np.ascontiguousarray(edges, dtype=np.int64).reshape(-1, 2)
    c = _check_coords(coords, int(E.max()) + 1 if E.size else 0)
    valid = np.ascontiguousarray(vertex_valid, dtype=np.bool_)
    if valid.shape != (c.shape[0],):
        raise ValueError(f"vertex_valid must be ({c.shape[0]},), got {valid.shape}")
    if n_samples < 2:
        raise ValueError("n_samples must be >= 2")
    out = np.zeros((E.shape[0], n_samples), np.uint8)
    _edge_samples_kernel(img, c, E, valid, n_samples, out)
    return out


def face_centroids(coords, faces) -> np.ndarray:
    """(..., F, 2) centroid of each face's three texture coordinates, for (..., V, 2) coords."""
    c = np.asarray(coords, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    return c[..., F, :].mean(axis=-2)


PAPER_COLOR_WIDTH = 4096
"""Width (px) of the colour images behind the paper's θ_b = 20 px (Azure Kinect, 3072p)."""


def theta_b_for_width(theta_b_px, width: int) -> float:
    """θ_b in px per frame for colour images ``width`` px wide: ``theta_b_px`` itself, or, when it
    is None, the paper's 20 px at its 4096-px-wide images scaled to ``width`` (3.125 px at 640):
    the same motion blur as a fraction of the picture."""
    if theta_b_px is not None:
        return float(theta_b_px)
    return 20.0 * float(width) / PAPER_COLOR_WIDTH


BLUR_RULES = ("step", "graded")
UNSEEN_NEIGHBOURS = ("unknown", "measured")


def face_motion(centroids, face_visible, unseen_neighbours: str = "unknown") -> np.ndarray:
    """How far each face's texture coordinates move per frame, the measure behind E_qual's blur.

    Args:
        centroids: (T, F, 2) centroid of each face's texture coordinates per frame (px); defined
            in every frame, seen or not (the projection of the tracked mesh).
        face_visible: (T, F) bool.
        unseen_neighbours: ``'unknown'`` (the authors' ``Selector.cpp``): the motion needs the
            face visible at l−1, l and l+1 and is NaN otherwise, and at the first/last frame.
            ``'measured'`` (ours): the image motion of a surface point, and so its motion blur,
            does not depend on whether the neighbouring frames see it: the moves to l−1 and
            l+1 are measured from the centroids whatever their visibility, and the first/last
            frame uses its one neighbour.

    Returns:
        (T, F) float32 px per frame: the mean of |c̄(l−1) − c̄(l)| and |c̄(l+1) − c̄(l)|; NaN where
        unknown, and always where the face is not visible at l.
    """
    c = np.asarray(centroids, dtype=np.float64)
    vis = np.asarray(face_visible, dtype=bool)
    if c.ndim != 3 or c.shape[2] != 2 or vis.shape != c.shape[:2]:
        raise ValueError(f"centroids (T, F, 2) and face_visible (T, F) disagree: {c.shape}, {vis.shape}")
    if unseen_neighbours not in UNSEEN_NEIGHBOURS:
        raise ValueError(f"unseen_neighbours must be one of {UNSEEN_NEIGHBOURS}, got {unseen_neighbours!r}")
    T = c.shape[0]
    out = np.full(vis.shape, np.nan)
    moves = np.linalg.norm(np.diff(c, axis=0), axis=-1)        # (T-1, F): |c̄(l+1) − c̄(l)|
    if unseen_neighbours == "measured" and T >= 2:
        out[1:-1] = 0.5 * (moves[:-1] + moves[1:])
        out[0], out[-1] = moves[0], moves[-1]
    elif T >= 3:
        known = vis[:-2] & vis[1:-1] & vis[2:]
        out[1:-1] = np.where(known, 0.5 * (moves[:-1] + moves[1:]), np.nan)
    out[~vis] = np.nan
    return out.astype(np.float32)


def blurred_faces(centroids, face_visible, theta_b_px: float) -> np.ndarray:
    """The blur step of E_qual for every (frame, face).

    Args:
        centroids: (T, F, 2) centroid of each face's texture coordinates per frame (px).
        face_visible: (T, F) bool.
        theta_b_px: motion threshold θ_b (px per frame; the paper: 20).

    Returns:
        (T, F) bool: :func:`face_motion` exceeds θ_b, or a neighbouring frame does not see the
        face (or l is the first/last frame): a missing neighbour counts as blurred, as in the
        authors' code. False where the face is not visible at l.
    """
    return blur_cost(face_motion(centroids, face_visible), face_visible, theta_b_px, "step") > 0


def blur_cost(motion, face_visible, theta_b_px: float, rule: str = "step",
              cap: float = 2.0) -> np.ndarray:
    """The blur part of E_qual: (T, F) float32, from :func:`face_motion` (px per frame; NaN =
    unknown) and face_visible (T, F) bool.

    ``rule='step'`` (the paper): 1 where the motion exceeds θ_b or is unknown (a missing
    neighbour counts as blurred, as in the authors' code), else 0.
    ``rule='graded'`` (ours): motion / θ_b, capped at ``cap``; unknown motion costs ``cap``. It
    is 1 at θ_b like the step, but also ranks the frames on either side: when most frames move
    faster than θ_b (a walk that never pauses) the step makes them all equally bad and cannot
    prefer the sharpest.
    0 where the face is not visible (not a candidate).
    """
    m = np.asarray(motion, dtype=np.float64)
    vis = np.asarray(face_visible, dtype=bool)
    if vis.shape != m.shape:
        raise ValueError(f"motion {m.shape} and face_visible {vis.shape} disagree")
    unknown = np.isnan(m)
    if rule == "step":
        out = (m > theta_b_px) | unknown
    elif rule == "graded":
        if not theta_b_px > 0 or not cap > 0:
            raise ValueError(f"graded blur cost needs θ_b > 0 and cap > 0, got {theta_b_px}, {cap}")
        out = np.where(unknown, cap, np.minimum(m / theta_b_px, cap))
    else:
        raise ValueError(f"blur_rule must be one of {BLUR_RULES}, got {rule!r}")
    return np.where(vis, out, 0).astype(np.float32)


def slanted_faces(face_cos, theta_n: float = 0.3, rule: str = "paper") -> np.ndarray:
    """The view-angle step of E_qual: (T, F) bool, True where the face is seen too obliquely.

    ``rule='paper'``: χ_θn(1 − cos) = 1, i.e. cos ≤ 1 − θ_n (0.7 at θ_n = 0.3).
    ``rule='authors'``: cos ≤ θ_n, as ``Selector.cpp`` computes it.
    """
    cos = np.asarray(face_cos, dtype=np.float32)
    if rule == "paper":
        return cos <= 1.0 - theta_n
    if rule == "authors":
        return cos <= theta_n
    raise ValueError(f"angle_rule must be one of {ANGLE_RULES}, got {rule!r}")
