"""Labeling stage: the spatiotemporal MRF of the paper (Eq. 2), one source frame per (face, frame).

For every frame t and face f the stage chooses l_{f,t}, the frame whose colour image textures f
at time t, minimising

    E = Σ_t Σ_f U(t, f, l_{f,t})                                   data term (stex.data_term)
      + ω_s Σ_t Σ_{(f,f')} w_{ff'} E_spa(l_{f,t}, l_{f',t})         spatial smoothness
      + ω_t Σ_t Σ_f g_f(l_{f,t}, l_{f,t+1}) E_temp(l_{f,t}, l_{f,t+1})   temporal smoothness

- U = E_qual + ω_g E_glo + (1 − ω_g) E_loc over the face's candidate frames (``data_term`` store;
  ``similarity: global | local`` keep one of the two geometric terms, as ablations).
- E_spa(a, b) = 0.5·mean|I_a − I_b| + 0.5·mean|ΔI_a − ΔI_b| over the 9 grey samples along the
  shared edge (``observations`` edge_samples, /255; ΔI = differences of consecutive samples, the
  authors' gradient along the edge). The paper sums both terms; the authors weight each 0.5
  (``calEdgeImdiff``), which stex follows. It is an L1 distance between per-(edge, frame)
  feature vectors, so it is a metric on every edge and every α-expansion move is submodular.
- E_temp(a, b) = mean|I_a − I_b| over the 15 grey samples of the face (/255), the authors'
  ``calFaceImdiff``.
- Selective weighting (θ_Ω = 0.95, S = ``observations`` dynamism): ``temporal: selective`` gates
  E_temp with χ(min(S(f, a), S(f, b)) ≥ θ_Ω) — source frames a and b, as the paper's Eq.
  revised_temp and the authors' code; ``constant`` uses weight 1; ``off`` drops the term.
  ``spatial_selective`` multiplies E_spa on an edge by 2 − (χ(S_m(f)) + χ(S_m(f')))/2 with
  S_m(f) = min over the face's visible frames of S(f, ·) — the paper's rule, which the authors'
  code intends but never applies (a by-value loop, ``official_code_notes.md`` §2.4); off by
  default, since on the demo ground truth it made the labeling slightly worse
  (docs/decisions/labeling.md). NaN
  dynamism (face not seen in two consecutive frames) gives no evidence of change and counts as
  static (χ = 1).

Optimisation (the authors' schedule, made a descent method): every frame's spatial MRF is first
solved on its own (temporal term absent), then block coordinate descent: all even frames with
their odd neighbours' labels fixed, then all odd frames, repeated until a round lowers the total
energy by less than ``rel_tol`` or ``max_rounds``. With the neighbours fixed, the temporal terms
of frame t are unary terms of its MRF (the authors fold them the same way), so each frame is one
α-expansion (:func:`stex.mrf.alpha_expansion`: per-node label subsets, moves accepted only when
the frame's energy falls) warm-started from its current labels: the total energy never rises.
Frames of one parity do not interact, so they are solved in parallel threads (numba releases the
GIL). A frame's candidates and data term are read from the data_term stores when it is solved
(:class:`TableRows`), not held for every frame: the stage's peak memory falls for a little more
time and the same labels (docs/decisions/labeling.md).

Faces never visible have no candidate. Those that some source frame glimpses (``projection``
``face_glimpsed``: the face's own test passes there, but a corner fails the vertex rule, e.g. on
a silhouette) take, at every frame, the source frame that glimpses them at the largest cosine
(:func:`glimpse_sources`; stex's addition, outside the MRF and its energy). The rest stay -1
(``never_seen``); the volume stage fills their texels in texture space from the nearest labelled
surface.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from stex import mrf
from stex.data_term import unary_terms

__all__ = ["spatial_features", "EdgeFeatures", "FrameProblem",
           "frame_problem", "temporal_cost", "label_sequence", "total_energy", "TableRows",
           "glimpse_sources"]

TEMPORAL_MODES = ("selective", "constant", "off")
SIMILARITY_MODES = ("both", "global", "local")


def spatial_features(edge_samples) -> np.ndarray:
    """Per-(edge, frame) features whose L1 distance is E_spa.

    Args:
        edge_samples: (..., n) uint8 grey samples along the edges (n >= 2).

    Returns:
        (..., 2n − 1) float32: 0.5/n · I/255 then 0.5/(n−1) · ΔI/255, so that
        ‖F_a − F_b‖₁ = 0.5·mean|I_a − I_b| + 0.5·mean|ΔI_a − ΔI_b| (grey / 255).
    """
    s = np.asarray(edge_samples, dtype=np.float32) / 255.0
    n = s.shape[-1]
    if n < 2:
        raise ValueError("edge_samples need at least 2 samples per edge")
    return np.concatenate([s * (0.5 / n), np.diff(s, axis=-1) * (0.5 / (n - 1))], axis=-1)


def temporal_cost(face_samples, cand, faces_idx, other_labels, gates=None) -> np.ndarray:
    """E_temp between every candidate label of some faces and a fixed label of each face.

    Args:
        face_samples: (T, F, S) uint8 grey samples per (frame, face).
        cand: (n, K) int candidate labels of faces ``faces_idx`` (-1 = padding).
        faces_idx: (n,) int face ids.
        other_labels: (n,) int the neighbouring frame's label of each face (-1 = none: cost 0).
        gates: optional (T, F) float32 selective gates; the cost is multiplied by
            min(gate[a, f], gate[b, f]).

    Returns:
        (n, K) float32 mean |I_a − I_b| / 255 over the face's samples (0 at padding).
    """
    cand = np.asarray(cand)
    f = np.asarray(faces_idx, np.int64)
    b = np.asarray(other_labels, np.int64)
    ok = (cand >= 0) & (b >= 0)[:, None]
    a = np.where(ok, cand, 0).astype(np.int64)
    bb = np.where(b >= 0, b, 0)
    sa = face_samples[a, f[:, None]].astype(np.int16)             # (n, K, S)
    sb = face_samples[bb, f].astype(np.int16)[:, None, :]         # (n, 1, S)
    cost = np.abs(sa - sb).mean(axis=-1).astype(np.float32) / 255.0
    if gates is not None:
        cost *= np.minimum(gates[a, f[:, None]], gates[bb, f][:, None])
    return np.where(ok, cost, 0.0).astype(np.float32)


class EdgeFeatures:
    """:func:`spatial_features` computed on demand: ``EdgeFeatures(samples)[labels, edges]``.

    A frame's MRF needs the features of a few (label, edge) pairs; the full (T, E, 17) float32
    table would be 0.5 GB on the paper scene, the uint8 samples are 72 MB."""

    def __init__(self, edge_samples):
        self.samples = np.asarray(edge_samples)

    def __getitem__(self, idx):
        return spatial_features(self.samples[idx])


class FrameProblem:
    """One frame's spatial MRF in the form :mod:`stex.mrf` takes (nodes = faces with candidates).

    Attributes: ``faces`` (N,) face id of each node; ``cand`` (N, K) candidate labels (-1 pad);
    ``unary`` (N, K) float64 data term; CSR arrays of :func:`stex.mrf.alpha_expansion`
    (``cand_ptr``, ``cand_label``), ``edges`` (M, 2) node pairs, ``edge_weight`` (M,),
    ``feat_ptr``, ``feat_label``, ``feat``.
    """

    def __init__(self, faces, cand, unary, cand_ptr, cand_label, slot, edges, edge_weight,
                 feat_ptr, feat_label, feat):
        self.faces, self.cand, self.unary = faces, cand, unary
        self.cand_ptr, self.cand_label, self.slot = cand_ptr, cand_label, slot
        self.edges, self.edge_weight = edges, edge_weight
        self.feat_ptr, self.feat_label, self.feat = feat_ptr, feat_label, feat

    def costs(self, extra=None) -> np.ndarray:
        """(M,) float64 unary cost per CSR entry, plus ``extra`` (N, K) if given."""
        u = self.unary if extra is None else self.unary + extra
        return np.ascontiguousarray(u[self.slot[:, 0], self.slot[:, 1]], dtype=np.float64)

    def solve(self, extra=None, labels0=None, seed=0, max_cycles=10, tol=1e-4):
        args = (self.cand_ptr, self.cand_label, self.costs(extra), self.edges, self.edge_weight,
                self.feat_ptr, self.feat_label, self.feat)
        return mrf.alpha_expansion(*args, labels0=labels0, max_cycles=max_cycles, tol=tol, seed=seed)

    def energy(self, labels, extra=None) -> float:
        return mrf.energy(labels, self.cand_ptr, self.cand_label, self.costs(extra), self.edges,
                          self.edge_weight, self.feat_ptr, self.feat_label, self.feat)

    def icm(self, extra=None, labels0=None):
        return mrf.icm(self.cand_ptr, self.cand_label, self.costs(extra), self.edges,
                       self.edge_weight, self.feat_ptr, self.feat_label, self.feat, labels0=labels0)


def frame_problem(cand, unary, pairs, pair_weight, edge_features) -> FrameProblem:
    """Build frame t's MRF.

    Args:
        cand: (F, K) int candidate labels of every face at t (ascending, -1 = padding).
        unary: (F, K) float data term of each candidate.
        pairs: (E, 2) adjacent face pairs; pair_weight: (E,) ω_s times the selective weight.
        edge_features: (T, E, D) float32 :func:`spatial_features` of every frame, or an
            :class:`EdgeFeatures` indexed the same way.

    Only faces with at least one candidate are nodes; only pairs of two nodes are edges.
    """
    cand = np.asarray(cand)
    has = cand[:, 0] >= 0
    faces = np.flatnonzero(has)
    node_of = np.full(cand.shape[0], -1, np.int64)
    node_of[faces] = np.arange(faces.size)
    c = cand[faces].astype(np.int32)
    valid = c >= 0
    counts = valid.sum(axis=1)
    cand_ptr = np.zeros(faces.size + 1, np.int64)
    np.cumsum(counts, out=cand_ptr[1:])
    rows, cols = np.nonzero(valid)                   # row-major: ascending labels per node
    cand_label = np.ascontiguousarray(c[rows, cols], dtype=np.int32)
    slot = np.stack([rows, cols], axis=1)
    P = np.asarray(pairs, np.int64)
    keep = has[P[:, 0]] & has[P[:, 1]]
    ek = np.flatnonzero(keep)
    edges = np.stack([node_of[P[ek, 0]], node_of[P[ek, 1]]], axis=1).astype(np.int32)
    weight = np.ascontiguousarray(np.asarray(pair_weight, np.float64)[ek])
    # features over the union of the two faces' candidate labels, ascending, no repeats
    both = np.concatenate([cand[P[ek, 0]], cand[P[ek, 1]]], axis=1).astype(np.int64)
    both.sort(axis=1)
    keepl = both >= 0
    keepl[:, 1:] &= both[:, 1:] != both[:, :-1]
    fcounts = keepl.sum(axis=1)
    feat_ptr = np.zeros(ek.size + 1, np.int64)
    np.cumsum(fcounts, out=feat_ptr[1:])
    er, ec = np.nonzero(keepl)
    feat_label = np.ascontiguousarray(both[er, ec], dtype=np.int32)
    feat = np.ascontiguousarray(edge_features[feat_label, ek[er]], dtype=np.float32)
    return FrameProblem(faces, cand[faces], np.asarray(unary, np.float64)[faces], cand_ptr,
                        cand_label, slot, edges, weight, feat_ptr, feat_label, feat)


def _links(face_samples, L_prev, L_cur, gates) -> float:
    """Σ_f gate·E_temp(L_prev[f], L_cur[f]) over faces labelled in both frames."""
    ok = (L_prev >= 0) & (L_cur >= 0)
    f = np.flatnonzero(ok)
    if f.size == 0:
        return 0.0
    c = temporal_cost(face_samples, L_cur[f][:, None], f, L_prev[f], gates)
    return float(c.sum())


def label_sequence(cand, unary, pairs, pair_weight, edge_samples, face_samples, omega_t: float,
                   gates=None, max_rounds: int = 4, rel_tol: float = 1e-3, seed: int = 0,
                   max_cycles: int = 10, threads: int = 2, progress=None) -> dict:
    """Solve the spatiotemporal labeling by per-frame α-expansion and even/odd BCD.

    Args:
        cand: (T, F, K) int16 candidate labels per (target frame, face), -1 = padding.
        unary: (T, F, K) float32 data term of each candidate. Either may be a
            :class:`TableRows`, which reads a frame's row when it is solved.
        pairs: (E, 2) adjacent face pairs; pair_weight: (E,) ω_s·selective weight.
        edge_samples: (T, E, n) uint8 grey samples along every shared edge per frame.
        face_samples: (T, F, S) uint8 grey samples per (frame, face).
        omega_t: temporal weight ω_t (0 or ``gates`` all 0 drops the term).
        gates: optional (T, F) float32 selective gates (None: constant weight 1).
        max_rounds: BCD rounds (each: one even sweep, one odd sweep) after the initial solves.
        rel_tol: stop when a round lowers the total energy by less than this fraction.
        seed: α-expansion label order seed (frame t uses seed + t): fixed seed, same result.
        threads: frames of one parity solved in parallel.
        progress: optional callable(str) for progress messages.

    Returns:
        dict with ``labels`` (T, F) int16 (-1 where a face has no candidate), ``energy`` (R,)
        total energy after the initial solves and after every round, ``frame_energy`` (R, T),
        ``rounds`` list of dicts (energy, seconds, changed faces).
    """
    T, nF = cand.shape[:2]    # cand, unary: arrays, or per-frame readers (TableRows)
    features = EdgeFeatures(edge_samples)

    def problem(t):
        return frame_problem(cand[t], unary[t], pairs, pair_weight, features)

    L = np.full((T, nF), -1, np.int32)
    spa = np.zeros(T)
    link = np.zeros(T)           # link[t]: temporal energy between t-1 and t (link[0] = 0)

    def extra_for(t, pr):
        if omega_t == 0:
            return None
        ex = np.zeros(pr.cand.shape, np.float32)
        for nb in (t - 1, t + 1):
            if 0 <= nb < T:
                ex += temporal_cost(face_samples, pr.cand, pr.faces, L[nb, pr.faces], gates)
        return omega_t * ex

    def solve(t, temporal):
        pr = problem(t)
        ex = extra_for(t, pr) if temporal else None
        cur = L[t, pr.faces] if temporal else None
        lab, _ = pr.solve(ex, labels0=cur, seed=seed + t, max_cycles=max_cycles)
        return t, pr, lab

    def store(t, pr, lab):
        changed = int(np.count_nonzero(L[t, pr.faces] != lab))
        L[t, pr.faces] = lab
        spa[t] = pr.energy(lab)
        return changed

    def relink():
        for t in range(1, T):
            link[t] = omega_t * _links(face_samples, L[t - 1], L[t], gates) if omega_t else 0.0

    def total():
        return float(spa.sum() + link.sum())

    say = progress or (lambda msg: None)
    history, frame_hist, rounds = [], [], []
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max(1, threads)) as pool:
        for t, pr, lab in pool.map(lambda t: solve(t, False), range(T)):
            store(t, pr, lab)
        relink()
        history.append(total())
        frame_hist.append(spa + link)
        rounds.append({"round": 0, "energy": history[-1], "seconds": time.perf_counter() - t0,
                       "changed": int((L >= 0).sum())})
        say(f"labeling: initial per-frame solves, energy {history[-1]:.4f} "
            f"({rounds[-1]['seconds']:.1f} s)")
        if omega_t > 0:
            for r in range(1, max_rounds + 1):
                t1 = time.perf_counter()
                changed = 0
                for parity in (0, 1):
                    for t, pr, lab in pool.map(lambda t: solve(t, True), range(parity, T, 2)):
                        changed += store(t, pr, lab)
                relink()
                e = total()
                if e > history[-1] + 1e-6 * max(1.0, abs(history[-1])):
                    raise RuntimeError(f"labeling energy rose in round {r}: {history[-1]} -> {e}")
                history.append(e)
                frame_hist.append(spa + link)
                rounds.append({"round": r, "energy": e, "seconds": time.perf_counter() - t1,
                               "changed": changed})
                say(f"labeling: round {r}, energy {e:.4f}, {changed} labels changed "
                    f"({rounds[-1]['seconds']:.1f} s, {rounds[-1]['seconds'] / T:.2f} s per frame)")
                if history[-2] - e <= rel_tol * abs(history[-2]):
                    break
    return {"labels": L.astype(np.int16), "energy": np.array(history),
            "frame_energy": np.array(frame_hist), "rounds": rounds}


def total_energy(labels, cand, unary, pairs, pair_weight, edge_samples, face_samples, omega_t,
                 gates=None) -> float:
    """Eq. 2 for a given labeling (T, F), computed from scratch (for tests and comparisons)."""
    L = np.asarray(labels, np.int32)
    T = L.shape[0]
    e = 0.0
    features = EdgeFeatures(edge_samples)
    for t in range(T):
        pr = frame_problem(cand[t], unary[t], pairs, pair_weight, features)
        e += pr.energy(L[t, pr.faces])
    if omega_t:
        for t in range(1, T):
            e += omega_t * _links(face_samples, L[t - 1], L[t], gates)
    return float(e)


class TableRows:
    """The candidates or the data term of every frame, read from the data_term blocks one frame at a
    time (their arrays are chunked by frame), so that the labeling does not hold all frames'
    (T, F, K) rows: ``rows[t]`` is frame t's (F, K) array, ``rows.shape`` (T, F, K).

    Args:
        blocks: the ``data_term`` block stores, in frame order.
        what: ``'candidates'`` (int16) or ``'unary'`` (float32, :func:`stex.data_term.unary_terms`
            of the block's E_qual, E_glo, E_loc and E_str with the weights the data term ranked
            them with, ``params``).
    """

    def __init__(self, blocks, what: str, params: dict | None = None):
        if what not in ("candidates", "unary") or (what == "unary" and params is None):
            raise ValueError(f"TableRows reads 'candidates', or 'unary' with the data term's params; "
                             f"got {what!r}")
        self.blocks, self.what, self.params = blocks, what, params
        sizes = [b["candidates"].shape[0] for b in blocks]
        self.start = np.cumsum([0] + sizes)
        self.shape = (int(self.start[-1]),) + tuple(blocks[0]["candidates"].shape[1:])

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, t: int) -> np.ndarray:
        if not 0 <= t < self.shape[0]:
            raise IndexError(f"frame position {t} outside 0..{self.shape[0] - 1}")
        k = int(np.searchsorted(self.start, t, side="right")) - 1
        b, i = self.blocks[k], t - int(self.start[k])
        if self.what == "candidates":
            return b["candidates"][i]
        tp = self.params
        return unary_terms(b["e_qual"][i], b["e_glo"][i], b["e_loc"][i], tp["omega_g"],
                           tp["similarity"], b["e_str"][i] if "e_str" in b else None,
                           tp.get("omega_str", 0.0)).astype(np.float32)


def glimpse_sources(face_glimpsed, face_cos, never_seen, is_source) -> np.ndarray:
    """The source frame of each face that no frame sees but some source frame glimpses.

    Args:
        face_glimpsed: (T, F) bool (``projection`` store). face_cos: (T, F) float viewing cosine.
        never_seen: (F,) bool, faces without any label candidate.
        is_source: (T,) bool, the frames allowed to texture (held-out protocol).

    Returns:
        (F,) int32: for never-seen faces glimpsed by a source frame, the one with the largest
        ``face_cos`` (earliest on ties); -1 elsewhere.
    """
    g = np.asarray(face_glimpsed, bool) & np.asarray(is_source, bool)[:, None]
    g &= np.asarray(never_seen, bool)[None, :]
    score = np.where(g, np.asarray(face_cos, np.float32), -1.0)
    best = np.argmax(score, axis=0)
    return np.where(g.any(axis=0), best, -1).astype(np.int32)
