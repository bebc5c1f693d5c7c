"""The oracle bound of the labeling on synthetic scenes: for every (t, face) the camera does not see
at t, the source frame whose true appearance of the face is closest to the truth at t.

The paper borrows the surface frame t does not see from the frame of most similar shape. Whether
the labels it finds are far from what the frames could give (the labeling's fault) or the frames
hold nothing better (the scene's) is answered by this bound: the same volume and correction
from labels chosen with the truth, scored by the same evaluation (``evaluation.references:
[oracle]``, :mod:`stex.stages.oracle`).

Pure functions over numpy arrays:

- :func:`sample_points_uv` — where the 15 barycentric samples of every template face lie in the
  true appearance's atlas (the scene's own texcoords), through the closest points on the scene's
  template mesh (seam-safe: each sample takes the texcoords of the true face it lies on).
- :func:`truth_samples` — the true appearance of a frame at those points (F, S, 3).
- :func:`oracle_labels` — the labels: for each (t, f) not seen at t, the argmin over the source
  frames that saw f of the mean squared difference of the true colours; the rest keep the
  given labels.
"""

from __future__ import annotations

import numpy as np

from stex.mesh import embed_vertices
from stex.render import sample_bilinear

__all__ = ["sample_points_uv", "truth_samples", "oracle_labels"]

#: added per frame of distance |s - t| to the squared colour difference (grey levels²): among
#: equally good source frames (static surface) the nearest in time, as the temporal term prefers
TIME_TIE_BREAK = 1e-6


def sample_points_uv(vertices, faces, bary, true_vertices, true_faces, true_texcoords,
                     true_texcoord_faces) -> np.ndarray:
    """(F, S, 2) float64 texture coordinates in the true atlas ([0, 1], v down) of the samples.

    Args:
        vertices: (V, 3) float template vertices (m); faces: (F, 3) int.
        bary: (S, 3) float barycentric samples of a face (e.g. :data:`stex.texcoords.SAMPLE_BARY`).
        true_vertices: (V0, 3) float, the scene's template mesh in the same frame (m);
            true_faces: (F0, 3) int; true_texcoords: (N, 2) float; true_texcoord_faces: (F0, 3) int.
    """
    V = np.asarray(vertices, np.float64)
    Fc = np.asarray(faces, np.int64)
    b = np.asarray(bary, np.float64)
    pts = np.einsum("sk,fkd->fsd", b, V[Fc]).reshape(-1, 3)
    face, fb, _, _ = embed_vertices(pts, true_vertices, true_faces)
    tc = np.asarray(true_texcoords, np.float64)[np.asarray(true_texcoord_faces, np.int64)[face]]
    uv = np.einsum("nk,nkd->nd", fb.astype(np.float64), tc)
    return uv.reshape(len(Fc), len(b), 2)


def truth_samples(appearance, uv) -> np.ndarray:
    """(F, S, 3) float32 true colours (grey levels 0..255) of ``appearance`` ((W, W, 3) uint8, the
    true texture of one frame) at ``uv`` ((F, S, 2) from :func:`sample_points_uv`), bilinear."""
    app = np.asarray(appearance)
    W = app.shape[0]
    flat = np.asarray(uv, np.float64).reshape(-1, 2) * W - 0.5
    out = sample_bilinear(app, flat)
    return np.asarray(out, np.float32).reshape(*np.shape(uv)[:2], 3)


def oracle_labels(truth, face_visible, is_source, labels, candidates=None) -> np.ndarray:
    """(T, F) int16 labels: the oracle's source frame where the face is not seen at t.

    Args:
        truth: (T, F, S, 3) float true colours of every face at every frame
            (:func:`truth_samples`).
        face_visible: (T, F) bool, the face is visible in frame t (a label candidate).
        is_source: (T,) bool, frame t may texture (the held-out protocol's source frames).
        labels: (T, F) int, the labels to start from (the labeling's); kept where frame t is a
            source that sees the face, and where no source frame saw it.
        candidates: optional (T, F, K) int, the data term's candidates (-1 = none): the oracle
            chooses among them only (what the labeling could have chosen), else among every
            source frame that saw the face.

    Returns:
        the labels, the (t, f) not seen at t set to argmin over source frames s that saw f of
        mean((truth[s, f] - truth[t, f])²) (ties: the nearest s in time). Faces no candidate
        saw keep their label.
    """
    X = np.asarray(truth, np.float32)
    vis = np.asarray(face_visible, bool)
    src = np.asarray(is_source, bool)
    T, F = vis.shape
    if X.shape[:2] != (T, F) or np.shape(labels) != (T, F) or src.shape != (T,):
        raise ValueError(f"oracle_labels: truth {X.shape}, face_visible {vis.shape}, labels "
                         f"{np.shape(labels)} and is_source {src.shape} do not agree on (T, F)")
    out = np.array(labels, np.int16, copy=True)
    seen_by = vis & src[:, None]                            # (T, F) frames that may texture f
    frames = np.arange(T)
    for t in range(T):
        need = ~(vis[t] & src[t])
        if candidates is not None:
            c = np.asarray(candidates[t])
            allowed = np.zeros((T, F), bool)
            ok = c >= 0
            allowed[c[ok], np.nonzero(ok)[0]] = True
            allowed &= seen_by
        else:
            allowed = seen_by
        need &= allowed.any(axis=0)
        if not need.any():
            continue
        f = np.flatnonzero(need)
        d = X[:, f] - X[t, f][None]                         # (T, n, S, 3)
        err = (d * d).mean(axis=(2, 3)) + TIME_TIE_BREAK * np.abs(frames - t)[:, None]
        err[~allowed[:, f]] = np.inf
        out[t, f] = np.argmin(err, axis=0)
    return out
