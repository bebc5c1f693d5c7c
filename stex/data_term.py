"""Data-term stage: the data term of the labeling and each face's candidate source frames.

For a block of target frames t and every face f, the candidates are the frames l in which f is
visible (``observations`` face_visible), scored by the data term of the paper's Eq. 2

    U(t, f, l) = E_qual(f, l) + ω_g E_glo(t, l) + (1 − ω_g) E_loc(t, f, l)
                 + ω_str E_str(t, f, l)

- E_qual(f, l) = blur_cost + slanted (``observations``; with the paper's blur step 0, 1 or 2),
  weighted down on the faces t does not see (``borrowed_qual_weight``): there the shape terms
  say which frame's texture to borrow, and blur only breaks near ties.
- E_glo(t, l) ∈ [0, 1]: the clipped depth difference of K_{t→l}(M_t) and M_l over the union of
  their silhouettes, divided by the clip (:func:`stex.similarity.global_similarity`). The authors'
  table is in metres with a 0.1 m clip, so 0.9·E_glo ≤ 0.09 never competes with the 0/1 quality
  steps (``official_code_notes.md`` §2.3); dividing by the clip gives it the weight the paper's
  ω_g = 0.9 implies.
- E_loc(t, f, l) = −(1/3) Σ_j τ_j(t)·τ_j(l) ∈ [−1, 0] over the face's three vertices, SHOT
  descriptors of the tracked meshes (``observations`` descriptors).
- E_str(t, f, l) ∈ [0, 1]: the difference of the local strain (smoothed log edge stretch) of f
  at t and at l on the tracked meshes, less a tolerance for the tracking's own drift on the
  faces t does not see (by default a multiple of the measured strain noise,
  :func:`stex.similarity.strain_noise`; ``observations`` strain,
  :func:`stex.similarity.strain_similarity`). Not in the paper (ω_str = 0 is the paper's data
  term): SHOT sees the surface's orientation, the strain
  sees whether it is compressed (folds, wrinkles) or stretched.

Pruning, as the authors' top-20 (``sel_label``): the full E_loc table is V·T² (2.8 GB at 10k
vertices and 265 frames), so E_loc is computed only for the ``prefilter`` best frames by the
other terms (E_qual, E_glo, E_str), and the ``candidates`` best of those by the full U are kept.
E_loc ≥ −1, so a frame left out by the prefilter (pre-score ≥ P, the worst pre-score kept) scores
at least P − (1 − ω_g); when the K-th best full score is below that, the pruning is provably exact
for the face. The stage records the fraction of (target, face) pairs where this holds (attr
``prefilter_exact``), and ``tests/test_data_term.py`` checks that wherever it holds the pruned
candidates equal those of the full ranking (``test_pruned_candidates_equal_full_ranking_where_exact``).

Candidate pruning (:mod:`stex.pruning`, ``poses.nearest_frames``) comes first: a target's
candidates are drawn only from its source frames in the ``poses`` store (each face's k nearest
in shape that see it), so E_glo, the prefilter and E_loc cost the same per target whatever T is.

``similarity: global | local`` keeps only one geometric term (the paper's ablation): U = E_qual
+ E_glo, or U = E_qual + (1 + E_loc) (shifted to [0, 1] so its scale matches E_glo's). E_str is a
local term: 'local' keeps it, 'global' drops it.
"""

from __future__ import annotations

import numpy as np

from stex.similarity import local_similarity_triples, strain_similarity, vertex_rings

__all__ = ["prefilter_candidates", "select_candidates", "finish_candidates", "block_candidates",
           "unary_terms", "source_mask", "lost_sources"]

SIMILARITY_MODES = ("both", "global", "local")


def select_candidates(score, k: int) -> np.ndarray:
    """The k lowest-scoring columns of every row, ascending by column index.

    Args:
        score: (F, L) float, +inf where the column is not allowed.
        k: number of candidates.

    Returns:
        (F, k) int32 column indices, -1 where a row has fewer than k finite scores.
    """
    s = np.asarray(score, dtype=np.float64)
    F, L = s.shape
    k_eff = min(k, L)
    if k_eff < L:
        part = np.argpartition(s, k_eff - 1, axis=1)[:, :k_eff]
    else:
        part = np.broadcast_to(np.arange(L), (F, L)).copy()
    ok = np.isfinite(np.take_along_axis(s, part, axis=1))
    cols = np.where(ok, part, L + 1)
    cols.sort(axis=1)
    out = np.full((F, k), -1, np.int32)
    out[:, :k_eff] = np.where(cols <= L, cols, -1)
    return out


def prefilter_candidates(glo_row, face_visible, e_qual, omega_g: float, similarity: str,
                         prefilter: int, str_row=None, omega_str: float = 0.0):
    """First cut of the candidates of one target frame, before E_loc is known.

    Args:
        glo_row: (T,) E_glo(t, ·) of the target t.
        face_visible: (T, F) bool.
        e_qual: (T, F) float32 E_qual of every (frame, face).
        omega_g, similarity: the data-term weighting (module docstring).
        prefilter: number of frames kept per face.

    Returns:
        (F, prefilter) int32 candidate frames (ascending, -1 padding) and (F, T) float64 pre-score
        (+inf where not visible).
    """
    vis = np.asarray(face_visible, bool).T                      # (F, T)
    q = np.asarray(e_qual, np.float64).T
    if similarity == "both":
        pre = q + omega_g * np.asarray(glo_row, np.float64)[None, :]
    elif similarity == "global":
        pre = q + np.asarray(glo_row, np.float64)[None, :]
    elif similarity == "local":
        pre = q.copy()
    else:
        raise ValueError(f"similarity must be one of {SIMILARITY_MODES}, got {similarity!r}")
    if str_row is not None and omega_str and similarity != "global":
        pre = pre + omega_str * np.asarray(str_row, np.float64).T
    pre = np.where(vis, pre, np.inf)
    return select_candidates(pre, prefilter), pre


def unary_terms(e_qual, e_glo, e_loc, omega_g: float, similarity: str, e_str=None,
                omega_str: float = 0.0) -> np.ndarray:
    """U = E_qual + ω_g E_glo + (1 − ω_g) E_loc + ω_str E_str (or one geometric term: module
    docstring). ``e_str`` None (stores written without it) counts as 0."""
    strain = 0.0 if e_str is None or not omega_str else omega_str * e_str
    if similarity == "both":
        return e_qual + omega_g * e_glo + (1.0 - omega_g) * e_loc + strain
    if similarity == "global":
        return e_qual + e_glo
    if similarity == "local":
        return e_qual + (1.0 + e_loc) + strain
    raise ValueError(f"similarity must be one of {SIMILARITY_MODES}, got {similarity!r}")


def finish_candidates(pre_c, pre, glo_row, face_visible, e_qual, loc, omega_g: float,
                      similarity: str, n_candidates: int, str_row=None, omega_str: float = 0.0):
    """The final candidates of one target frame from its prefilter and the E_loc of those frames.

    Args:
        pre_c, pre: :func:`prefilter_candidates` of the target ((F, P) frames, (F, T) pre-score).
        glo_row: (T,) E_glo(t, ·). face_visible: (T, F) bool. e_qual: (T, F) float32.
        loc: (F, P) float32 E_loc(t, f, pre_c[f, k]) (ignored for ``similarity='global'``).
        str_row: (T, F) E_str(t, ·, ·) or None (0); omega_str: its weight.

    Returns:
        dict of (F, K) arrays ``candidates`` int16 (ascending, -1 padding), ``e_glo``,
        ``e_loc``, ``e_qual``, ``e_str`` float32, and ``exact`` (F,) bool (the pruning bound
        holds).
    """
    ok = pre_c >= 0
    safe = np.where(ok, pre_c, 0)
    rows = np.arange(pre_c.shape[0])[:, None]
    q = np.asarray(e_qual, np.float32).T[rows, safe]
    g = np.asarray(glo_row, np.float32)[safe]
    loc = np.zeros(pre_c.shape, np.float32) if similarity == "global" else np.asarray(loc, np.float32)
    st = (np.zeros(pre_c.shape, np.float32) if str_row is None else
          np.asarray(str_row, np.float32).T[rows, safe])
    u = np.where(ok, unary_terms(q, g, loc, omega_g, similarity, st, omega_str), np.inf)
    pick = select_candidates(u, n_candidates)                    # columns into pre_c, ascending
    okp = pick >= 0
    sp = np.where(okp, pick, 0)
    cand = np.where(okp, pre_c[rows, sp], -1)                    # ascending: pre_c is
    # the K-th best full score against the best a left-out frame could reach
    kth = np.where(okp, u[rows, sp], -np.inf).max(axis=1)
    worst_pre = np.where(ok, pre[rows, safe], -np.inf).max(axis=1)
    n_vis = np.asarray(face_visible, bool).sum(axis=0)
    # how far E_loc can lower a left-out frame's score below its pre-score ('local' adds 1 + E_loc >= 0)
    loc_gain = 1.0 - omega_g if similarity == "both" else 0.0
    exact = (n_vis <= pre_c.shape[1]) | (kth <= worst_pre - loc_gain)

    def take(a):
        return np.where(okp, a[rows, sp], 0).astype(np.float32)

    return {"candidates": cand.astype(np.int16), "e_glo": take(g), "e_loc": take(loc),
            "e_qual": take(q), "e_str": take(st), "exact": exact}


def block_candidates(targets, glo, face_visible, e_qual, descriptors, faces, omega_g: float,
                     similarity: str, n_candidates: int, prefilter: int, median_hops: int = 2,
                     target_group: int = 4, strain=None, omega_str: float = 0.0,
                     str_clip: float = 0.1, sources=None, str_tolerance: float = 0.0,
                     borrowed_qual_weight: float = 1.0):
    """Candidates of a block of target frames (E_loc for the prefiltered frames of
    ``target_group`` targets at once: the descriptors stream through memory once per group, and
    the (target, face, source) triples of a group — F · prefilter per target, 0.8 M at paper
    scale — bound the memory; docs/decisions/data_term.md).

    Args:
        targets: (n,) target frames (sequence positions); glo: (n, N) their E_glo rows over
            ``sources`` (N = T without them).
        face_visible: (T, F) bool; e_qual: (T, F) float32.
        descriptors: (T, V, D) SHOT descriptors (numpy or zarr; unused for 'global').
        faces: (F, 3) int. median_hops: median filter of the vertex similarities.
        strain: (T, F, 3) :func:`stex.similarity.face_strain` of the tracked meshes, or None
            (E_str = 0); omega_str, str_clip, str_tolerance: its weight, clip and tolerance
            (:func:`stex.similarity.strain_similarity`). The tolerance applies to the faces
            the target does not see (``face_visible``'s row of the target): their texture is
            borrowed, and only a real deformation should rank it. On a face the target sees,
            every difference counts: the frames whose tracked mesh is most like the target's
            there carry texture registered like the target's photo.
        borrowed_qual_weight: E_qual's weight on the faces the target does not see (their
            texture is borrowed, so the frames most like the target in shape should win and blur
            only break near ties); the candidates' ``e_qual`` carries it, so the labeling
            weighs them as they were ranked.
        sources: (n, N) int, the source frames each target is compared with (candidate pruning,
            :func:`stex.pruning.nearest_sources`; ascending, -1 padding); None = every frame.

    Returns:
        list of :func:`finish_candidates` dicts, one per target (candidates as frames).
    """
    use_str = strain is not None and omega_str > 0 and similarity != "global"
    T = np.asarray(face_visible).shape[0]
    cols = (np.broadcast_to(np.arange(T), (len(targets), T)) if sources is None
            else np.asarray(sources, np.int64))
    if cols.shape != np.shape(glo):
        raise ValueError(f"glo rows {np.shape(glo)} and sources {cols.shape} differ in shape")

    def columns(k):  # the target's sources' rows of the (T, F) tables
        if sources is None:
            return face_visible, e_qual
        safe = np.where(cols[k] >= 0, cols[k], 0)
        return face_visible[safe] & (cols[k] >= 0)[:, None], e_qual[safe]

    def borrowed(k, value, seen_value):  # (F,): ``value`` on the faces target k does not see
        return np.where(np.asarray(face_visible[targets[k]], bool), seen_value, value)

    def qual(k):  # E_qual as the target weighs it: borrowed faces ranked by shape first
        vis, q = columns(k)
        return vis, (q * borrowed(k, float(borrowed_qual_weight), 1.0)[None, :]).astype(np.float32)

    def str_row(k):  # (N, F), made twice per target rather than held for the block (21 MB each)
        if not use_str:
            return None
        return strain_similarity(strain, targets[k], str_clip, None if sources is None else cols[k],
                                 borrowed(k, float(str_tolerance), 0.0))

    pres = [prefilter_candidates(glo[k], *qual(k), omega_g, similarity,
                                 max(prefilter, n_candidates), str_row(k), omega_str)
            for k in range(len(targets))]
    locs = [None] * len(targets)
    if similarity != "global":
        rings = vertex_rings(faces, descriptors.shape[1], median_hops)
        group = max(1, int(target_group))
        for g0 in range(0, len(targets), group):
            ks = range(g0, min(g0 + group, len(targets)))
            tt, ff, ll, where = [], [], [], []
            for k in ks:
                f, j = np.nonzero(pres[k][0] >= 0)
                tt.append(np.full(f.size, targets[k], np.int64))
                ff.append(f)
                ll.append(cols[k][pres[k][0][f, j]].astype(np.int64))
                where.append((f, j))
            vals = local_similarity_triples(descriptors, faces, np.concatenate(tt), np.concatenate(ff),
                                            np.concatenate(ll), rings=rings)
            n0 = 0
            for k, (f, j) in zip(ks, where):
                loc = np.zeros(pres[k][0].shape, np.float32)
                loc[f, j] = vals[n0:n0 + f.size]
                n0 += f.size
                locs[k] = loc
    out = []
    for k in range(len(targets)):
        res = finish_candidates(pres[k][0], pres[k][1], glo[k], *qual(k), locs[k], omega_g,
                                similarity, n_candidates, str_row(k), omega_str)
        c = res["candidates"]
        res["candidates"] = np.where(c >= 0, cols[k][np.maximum(c, 0)], -1).astype(np.int16)
        out.append(res)
    return out


def lost_sources(frame_lost, vertex_lost, faces) -> np.ndarray:
    """(T, F) bool: the (frame, face) pairs that may not be a source because the tracking lost
    them, the whole frame (``frame_lost`` (T,) bool) or a vertex of the face there
    (``vertex_lost`` (T, V) bool; ``faces`` (F, 3) int), from the ``tracking`` store.
    Why: a mesh that has lost the object projects the face onto something else, so its texture
    would land in the wrong place."""
    lost_v = np.asarray(vertex_lost, bool)
    F = np.asarray(faces, np.int64)
    return lost_v[:, F].any(axis=2) | np.asarray(frame_lost, bool)[:, None]


def source_mask(n_frames: int, stride: int) -> np.ndarray:
    """The frames that may texture anything under the held-out protocol: (T,) bool, True at the
    sequence positions 0, k, 2k, ... (k = ``stride`` >= 1, the ``data_term.source_stride`` setting;
    used by :func:`stex.stages.data_term.write_data_term` and the global-texture baseline)."""
    k = int(stride)
    if k < 1:
        raise ValueError(f"source_stride must be >= 1, got {stride}")
    return np.arange(int(n_frames)) % k == 0
