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
stage, or Φ of the ``projection`` store otherwise (:func:`open_coordinates`).

Angle rule. The paper writes χ_θn(1 − n·c) with θ_n = 0.3, i.e. a face is slanted when
cos ≤ 0.7; the authors' code tests cos ≤ 0.3 (``official_code_notes.md`` §2.4). Both are offered
(``angle_rule: paper | authors``); the default is the authors' rule: on the demo scene the paper's
flags 67 % of the visible (frame, face) pairs as slanted, which drives labels away from the target
frame and raised the ground-truth error of the labeling from 3.14 to 4.38 grey levels
(``benchmarks/bench_labeling.py``).
"""

from __future__ import annotations

import logging
import time

import numpy as np
from numba import njit

from stex.render import bilinear_taps
from stex.texcoords import SAMPLE_BARY

log = logging.getLogger("stex.observations")

__all__ = ["EDGE_SAMPLES", "PAPER_COLOR_WIDTH", "BLUR_RULES", "UNSEEN_NEIGHBOURS",
           "theta_b_for_width", "grey", "face_samples", "edge_samples", "face_motion",
           "blurred_faces", "blur_cost",
           "slanted_faces", "open_coordinates", "write_observations"]

#: samples along a shared edge (the authors' e_samnum = 9, at s/8)
EDGE_SAMPLES = 9
ANGLE_RULES = ("paper", "authors")


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 luma (ITU-R 601 weights, 0..255) of an (H, W, 3) uint8 RGB image."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3) RGB, got shape {img.shape}")
    return (0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]).astype(np.float32)


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
        grey_image: (H, W) float grey image (0..255), e.g. :func:`grey`.
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


def open_coordinates(path):
    """The texture coordinates the later stages use: ``(coords, valid, kind)``.

    ``coords`` (T, V, 2) px and ``valid`` (T, V) bool are zarr arrays (read per frame): ξ and
    ``valid`` of a ``texcoords`` store, or Φ and ``vertex_visible`` of a ``projection`` store.
    """
    import zarr

    from stex.io import open_store

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
    from stex.config import section_params
    from stex.dynamism import face_ssim, partial_texture
    from stex.io import FrameSequence, create_store, open_store
    from stex.similarity import face_strain, geodesic_neighbourhoods, mesh_resolution, shot_descriptors
    from stex.atlas import texel_map
    from stex.volume import TexelSampler

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
            g = grey(color)
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
