"""Multi-label MRF energy minimisation for the labeling stage: α-expansion with per-node label
subsets and per-edge L1-metric pairwise costs, on a numba Boykov–Kolmogorov max-flow.

The problem
-----------
N nodes (faces of one target frame), each choosing one label (a global source-frame index
0..L-1) from its own candidate subset; E edges (faces sharing a mesh edge). The energy is

    E(x) = sum_i D_i(x_i) + sum_e w_e * || F_e(x_u) - F_e(x_v) ||_1 ,   e = (u, v)

with one feature vector F_e(l) in R^K per (edge, label): for the paper's E_spa the 9 intensity
and 8 gradient samples along the shared edge, scaled so the L1 distance is
λ(0.5·mean|ΔI_a − ΔI_b| + 0.5·mean|I_a − I_b|). The pairwise cost is a metric on every edge (a
different one per edge), so every expansion move is a submodular binary problem and α-expansion
applies with its usual guarantee (a local minimum w.r.t. all expansion moves, within 2c of the
global minimum for non-negative unaries, c = max/min ratio of the non-zero pairwise costs).

Representation (all functions take exactly these arrays)
---------------------------------------------------------
- ``cand_ptr`` (N+1,) int64, ``cand_label`` (M,) int32, ``cand_cost`` (M,) float64: node i's
  candidate labels are ``cand_label[cand_ptr[i]:cand_ptr[i+1]]`` (strictly increasing) with unary
  costs ``cand_cost[...]``. A node with an empty subset is not part of the MRF: its label is -1
  and it contributes nothing (nor do its edges).
- ``edges`` (E, 2) int32 node ids (no self-loops; parallel edges add up), ``edge_weight`` (E,)
  float64 >= 0.
- ``feat_ptr`` (E+1,) int64, ``feat_label`` (Me,) int32, ``feat`` (Me, K) float32: the features of
  edge e are rows ``feat_ptr[e]:feat_ptr[e+1]`` for labels ``feat_label[...]`` (strictly
  increasing). Every label of either endpoint's subset must be present (a missing one is an
  upstream bug and raises ValueError); extra labels are allowed and ignored.
- ``labels`` (N,) int32: a label of the node's subset, or -1 exactly for empty-subset nodes.

Functions
---------
- :func:`energy` — the true energy of a labeling.
- :func:`icm` — iterated conditional modes (node-order sweeps until no change).
- :func:`alpha_expansion` — α-expansion from the unary argmin or a given labeling.
- :func:`stex.maxflow.min_cut` — the s-t max-flow / min-cut routine on its own.

Algorithm
---------
α-expansion (Boykov, Veksler, Zabih, PAMI 2001). One cycle visits every label present in some
subset once, in a seeded random order. For label α the binary variables are the nodes whose
subset contains α and whose label is not α (x=1: take α, x=0: keep). Nodes without α in their
subset, and nodes already at α, are fixed; their pairwise terms with a variable neighbour become
unary terms of that neighbour. A pairwise term between two variables with costs
A=V(l_i,l_j), B=V(l_i,α), C=V(α,l_j), D=V(α,α)=0 is split into unaries (A, C on i; 0, −C on j)
plus one arc of capacity B+C−A >= 0 (the triangle inequality; rounding below 0 is clamped, which
is harmless because of the next rule). The move found by the min cut is applied only if its
exact energy change (summed from the unaries and pairwise costs of the nodes that switch, not
read off the cut value) is negative, below −1e-12 of the energy's scale, so the energy never
increases, even for rounding or non-metric features; after each cycle the energy is recomputed
from scratch and checked (RuntimeError if it rose). A run stops when a cycle
lowers the energy by less than ``tol`` relative, or after ``max_cycles``. Each cycle is one
compiled call (no per-label Python).

The cut is Boykov–Kolmogorov (PAMI 2004): two search trees grown from the terminals, augmenting
along the path where they meet, orphans re-adopted (origin check with time stamps and
distances) so the trees are reused between augmentations, never rebuilt. Capacities are float64
(exact for integer capacities below 2^53). Nodes not in the source tree after the flow (free or
sink tree) are on the sink side, i.e. the source side is the set reachable from s in the
residual graph; in an expansion move the source side takes α, so ties keep the current label.

Complexity: building the move for α touches the nodes whose subset holds α and their edges,
O((n_α + e_α)·K), so a cycle costs O(N·S̄·deg·K) for S̄ labels per node and degree deg (plus a
one-off O(N·S̄·deg + E·S_e) table of feature rows, S_e labels per edge); the BK cut has no
useful polynomial bound (O(n²·m·|C|)) but is near-linear on these sparse graphs. Memory:
O(N·S̄·deg + E) besides the inputs.

Speed-ups that keep the result exact: the current pairwise cost of every edge and, per incident
slot, the feature row of the neighbour's current label are cached and updated on accepted moves;
the feature row of (candidate, slot) is tabulated once per call (``_Graph``); a label whose nodes
and their neighbours have not changed since it was last tried is skipped (its move would be the
same binary problem). The kernels are serial and release the GIL.

Most of a cycle is memory traffic for the feature rows; the max-flow itself is a small part. The
measured speed is in docs/decisions/labeling.md.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from stex.maxflow import bk_maxflow, build_arcs, float_vector

__all__ = ["energy", "icm", "alpha_expansion"]

# --------------------------------------------------------------------------------------------
# problem checks and derived indices
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _first_unsorted(ptr, lab):
    """First (segment, position) where labels are not strictly increasing, else (-1, -1)."""
    for s in range(ptr.shape[0] - 1):
        for p in range(ptr[s] + 1, ptr[s + 1]):
            if lab[p] <= lab[p - 1]:
                return s, p
    return -1, -1


@njit(cache=True, nogil=True)
def _first_missing_feature(cand_ptr, cand_label, edges, feat_ptr, feat_label):
    """First (edge, label) of an endpoint's subset missing from the edge's features."""
    for e in range(edges.shape[0]):
        for end in range(2):
            u = edges[e, end]
            q = feat_ptr[e]
            q1 = feat_ptr[e + 1]
            for p in range(cand_ptr[u], cand_ptr[u + 1]):
                lab = cand_label[p]
                while q < q1 and feat_label[q] < lab:
                    q += 1
                if q == q1 or feat_label[q] != lab:
                    return e, lab
    return -1, -1


def _check_ptr(ptr, name, n_seg):
    ptr = np.asarray(ptr)
    if ptr.ndim != 1 or ptr.shape[0] != n_seg + 1:
        raise ValueError(f"{name} must have shape ({n_seg + 1},), got {ptr.shape}")
    if not np.issubdtype(ptr.dtype, np.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {ptr.dtype}")
    ptr = np.ascontiguousarray(ptr, dtype=np.int64)
    if ptr[0] != 0:
        raise ValueError(f"{name}[0] must be 0, got {ptr[0]}")
    if n_seg and (np.diff(ptr) < 0).any():
        k = int(np.flatnonzero(np.diff(ptr) < 0)[0])
        raise ValueError(f"{name} must be non-decreasing: {name}[{k}]={ptr[k]} > {name}[{k + 1}]={ptr[k + 1]}")
    return ptr


def _check_labels_array(lab, name, length):
    lab = np.asarray(lab)
    if lab.ndim != 1 or lab.shape[0] != length:
        raise ValueError(f"{name} must have shape ({length},), got {lab.shape}")
    if length and not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {lab.dtype}")
    if length and lab.min() < 0:
        k = int(np.argmin(lab))
        raise ValueError(f"{name}[{k}] = {lab[k]} is negative (labels are frame indices >= 0)")
    if length and lab.max() > np.iinfo(np.int32).max:
        raise ValueError(f"{name} has a label above the int32 range")
    return np.ascontiguousarray(lab, dtype=np.int32)


def _check_problem(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat):
    """Validate and convert a problem to the kernels' dtypes; raises ValueError naming the fault."""
    cand_ptr = np.asarray(cand_ptr)
    if cand_ptr.ndim != 1 or cand_ptr.shape[0] < 1:
        raise ValueError(f"cand_ptr must have shape (N+1,), got {cand_ptr.shape}")
    n = cand_ptr.shape[0] - 1
    cand_ptr = _check_ptr(cand_ptr, "cand_ptr", n)
    m = int(cand_ptr[-1])
    cand_label = _check_labels_array(cand_label, "cand_label", m)
    cand_cost = float_vector(cand_cost, "cand_cost", m)
    s, p = _first_unsorted(cand_ptr, cand_label)
    if s >= 0:
        raise ValueError(f"cand_label of node {s} must be strictly increasing: "
                         f"{cand_label[cand_ptr[s]:cand_ptr[s + 1]].tolist()}")

    edges = np.asarray(edges)
    if edges.size == 0:
        edges = np.zeros((0, 2), np.int32)
    if edges.ndim != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape (E, 2), got {edges.shape}")
    if not np.issubdtype(edges.dtype, np.integer):
        raise ValueError(f"edges must be an integer array, got dtype {edges.dtype}")
    n_edges = edges.shape[0]
    if n_edges:
        bad = ((edges < 0) | (edges >= n)).any(axis=1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"edges[{k}] = {edges[k].tolist()} refers to a node outside 0..{n - 1}")
        loop = edges[:, 0] == edges[:, 1]
        if loop.any():
            k = int(np.flatnonzero(loop)[0])
            raise ValueError(f"edges[{k}] = {edges[k].tolist()} is a self-loop")
    edges = np.ascontiguousarray(edges, dtype=np.int32)
    edge_weight = float_vector(edge_weight, "edge_weight", n_edges)
    if n_edges and edge_weight.min() < 0:
        k = int(np.argmin(edge_weight))
        raise ValueError(f"edge_weight[{k}] = {edge_weight[k]} is negative")

    feat_ptr = _check_ptr(feat_ptr, "feat_ptr", n_edges)
    me = int(feat_ptr[-1])
    feat_label = _check_labels_array(feat_label, "feat_label", me)
    feat = np.asarray(feat)
    if feat.ndim != 2 or feat.shape[0] != me:
        raise ValueError(f"feat must have shape ({me}, K), got {feat.shape}")
    feat = np.ascontiguousarray(feat, dtype=np.float32)
    if not np.isfinite(feat).all():
        k = int(np.flatnonzero(~np.isfinite(feat).all(axis=1))[0])
        raise ValueError(f"feat row {k} (label {feat_label[k]}) is not finite")
    s, p = _first_unsorted(feat_ptr, feat_label)
    if s >= 0:
        raise ValueError(f"feat_label of edge {s} must be strictly increasing: "
                         f"{feat_label[feat_ptr[s]:feat_ptr[s + 1]].tolist()}")
    e, lab = _first_missing_feature(cand_ptr, cand_label, edges, feat_ptr, feat_label)
    if e >= 0:
        raise ValueError(f"edge {e} = {edges[e].tolist()} has no feature for label {lab}, a candidate "
                         f"of one of its nodes (features must cover both nodes' subsets)")
    return cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat


@njit(cache=True, nogil=True)
def _labels_to_pos(labels, cand_ptr, cand_label):
    """Entry index of each node's label in the candidate arrays; (-1, bad node) on a mismatch."""
    n = cand_ptr.shape[0] - 1
    pos = np.full(n, -1, np.int64)
    for i in range(n):
        lo = cand_ptr[i]
        hi = cand_ptr[i + 1]
        lab = labels[i]
        if lo == hi:
            if lab != -1:
                return pos, i
            continue
        while lo < hi:
            mid = (lo + hi) // 2
            if cand_label[mid] < lab:
                lo = mid + 1
            else:
                hi = mid
        if lo == cand_ptr[i + 1] or cand_label[lo] != lab:
            return pos, i
        pos[i] = lo
    return pos, -1


def _positions(labels, cand_ptr, cand_label, name):
    labels = np.asarray(labels)
    n = cand_ptr.shape[0] - 1
    if labels.ndim != 1 or labels.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},), got {labels.shape}")
    if n and not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{name} must be an integer array, got dtype {labels.dtype}")
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    pos, bad = _labels_to_pos(labels, cand_ptr, cand_label)
    if bad >= 0:
        subset = cand_label[cand_ptr[bad]:cand_ptr[bad + 1]].tolist()
        want = "-1 (its subset is empty)" if not subset else f"one of {subset}"
        raise ValueError(f"{name}[{bad}] = {labels[bad]} is not in node {bad}'s label subset: expected {want}")
    return pos


@njit(cache=True, nogil=True)
def _unary_argmin(cand_ptr, cand_cost):
    """Per node the entry with the lowest unary (the first on ties); -1 for empty subsets."""
    n = cand_ptr.shape[0] - 1
    pos = np.full(n, -1, np.int64)
    for i in range(n):
        best = np.inf
        for p in range(cand_ptr[i], cand_ptr[i + 1]):
            if cand_cost[p] < best:
                best = cand_cost[p]
                pos[i] = p
    return pos


class _Graph(NamedTuple):
    """Per-node incidence and feature-row tables shared by the ICM and α-expansion kernels.

    inc_ptr (N+1,) int64: node i's incident edges are slots inc_ptr[i]:inc_ptr[i+1];
    inc_edge (2E,) int64 the edge of each slot, inc_other (2E,) int64 the neighbour across it,
    inc_weight (2E,) float64 the edge weight, inc_twin (2E,) int64 the same edge's slot number
    (0-based) in the neighbour's list;
    ebase (M,) int64 and rowtab: the feature row of candidate entry p on its node's slot s is
    rowtab[ebase[p] + s] (no search in the kernels).
    """

    inc_ptr: np.ndarray
    inc_edge: np.ndarray
    inc_other: np.ndarray
    inc_weight: np.ndarray
    inc_twin: np.ndarray
    ebase: np.ndarray
    rowtab: np.ndarray


@njit(cache=True, nogil=True)
def _row_table(cand_ptr, cand_label, inc_ptr, inc_edge, feat_ptr, feat_label):
    """ebase, rowtab of :class:`_Graph` (features are known to cover every candidate)."""
    n = cand_ptr.shape[0] - 1
    ebase = np.empty(cand_label.shape[0], np.int64)
    total = 0
    for i in range(n):
        deg = inc_ptr[i + 1] - inc_ptr[i]
        for p in range(cand_ptr[i], cand_ptr[i + 1]):
            ebase[p] = total
            total += deg
    rowtab = np.empty(total, np.int64)
    for i in range(n):
        for q in range(inc_ptr[i], inc_ptr[i + 1]):
            s = q - inc_ptr[i]
            e = inc_edge[q]
            r = feat_ptr[e]
            for p in range(cand_ptr[i], cand_ptr[i + 1]):
                while feat_label[r] < cand_label[p]:   # both sorted; the label is present
                    r += 1
                rowtab[ebase[p] + s] = r
    return ebase, rowtab


def _graph(cand_ptr, cand_label, edges, edge_weight, feat_ptr, feat_label) -> _Graph:
    n = cand_ptr.shape[0] - 1
    ends = edges.reshape(-1).astype(np.int64)            # slot k of edge e: end 2e + k
    order = np.argsort(ends, kind="stable")
    inc_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(ends, minlength=n), out=inc_ptr[1:])
    inc_edge = (order // 2).astype(np.int64)
    other_end = order ^ 1                                 # the edge's other end
    inc_other = ends[other_end]
    where = np.empty_like(order)
    where[order] = np.arange(order.size)
    inc_twin = where[other_end] - inc_ptr[inc_other]
    ebase, rowtab = _row_table(cand_ptr, cand_label, inc_ptr, inc_edge, feat_ptr, feat_label)
    return _Graph(inc_ptr, inc_edge, inc_other, np.ascontiguousarray(edge_weight[inc_edge]), inc_twin, ebase, rowtab)


def _by_label(cand_ptr, cand_label):
    """Candidate entries grouped by label: lab_ptr (L+1,), lab_entry (M,), entry_node (M,)."""
    n_lab = int(cand_label.max()) + 1 if cand_label.size else 0
    lab_entry = np.argsort(cand_label, kind="stable").astype(np.int64)
    lab_ptr = np.zeros(n_lab + 1, np.int64)
    np.cumsum(np.bincount(cand_label, minlength=n_lab), out=lab_ptr[1:])
    entry_node = np.repeat(np.arange(cand_ptr.shape[0] - 1, dtype=np.int64), np.diff(cand_ptr))
    return lab_ptr, lab_entry, entry_node


# --------------------------------------------------------------------------------------------
# energy kernels
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _feat_row(feat_ptr, feat_label, e, lab):
    lo = feat_ptr[e]
    hi = feat_ptr[e + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        if feat_label[mid] < lab:
            lo = mid + 1
        else:
            hi = mid
    if lo == feat_ptr[e + 1] or feat_label[lo] != lab:
        raise ValueError("mrf: an (edge, label) feature is missing")
    return lo


# reassociation lets LLVM vectorise the K-term sum; the result differs from the sequential sum
# only by rounding and is the same on every call
@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _l1(feat, r0, r1):
    """sum_k |feat[r0, k] - feat[r1, k]| in float64 (0 when r0 == r1)."""
    if r0 == r1:
        return 0.0
    s = 0.0
    for k in range(feat.shape[1]):
        s += abs(np.float64(feat[r0, k]) - np.float64(feat[r1, k]))
    return s


@njit(cache=True, nogil=True)
def _energy_pos(pos, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat):
    """(energy, scale): the energy of the labeling given by entry indices, and the sum of the
    absolute values of its terms (the scale rounding errors are relative to)."""
    e_tot = 0.0
    scale = 0.0
    for i in range(pos.shape[0]):
        if pos[i] >= 0:
            e_tot += cand_cost[pos[i]]
            scale += abs(cand_cost[pos[i]])
    for e in range(edges.shape[0]):
        pu = pos[edges[e, 0]]
        pv = pos[edges[e, 1]]
        if pu < 0 or pv < 0 or edge_weight[e] == 0.0:
            continue
        a = cand_label[pu]
        b = cand_label[pv]
        if a == b:
            continue
        c = edge_weight[e] * _l1(feat, _feat_row(feat_ptr, feat_label, e, a),
                                 _feat_row(feat_ptr, feat_label, e, b))
        e_tot += c
        scale += c
    return e_tot, scale


def energy(labels, cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat) -> float:
    """True energy of a labeling (see the module docstring for the arrays).

    Args:
        labels: (N,) int, a label of each node's subset, -1 for nodes with an empty subset.

    Returns:
        sum of the chosen unaries plus sum over edges of w_e * ||F_e(a) - F_e(b)||_1 (float).

    Raises:
        ValueError: bad arrays, or a label outside its node's subset.
    """
    prob = _check_problem(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat)
    pos = _positions(labels, prob[0], prob[1], "labels")
    return float(_energy_pos(pos, *prob[1:])[0])


# --------------------------------------------------------------------------------------------
# ICM
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _icm_sweeps(pos, cand_ptr, cand_cost, inc_ptr, inc_other, inc_weight, inc_twin, ebase, rowtab,
                feat, max_sweeps):
    """ICM in node order on entry indices ``pos`` (in place); returns the number of sweeps.

    A node is re-evaluated only if it or a neighbour changed since its last evaluation: the
    others would keep their label anyway (a change needs a strict decrease), so the result is
    that of full sweeps."""
    n = pos.shape[0]
    dirty = np.ones(n, np.uint8)
    max_deg = 0
    for i in range(n):
        max_deg = max(max_deg, inc_ptr[i + 1] - inc_ptr[i])
    nrow = np.empty(max_deg, np.int64)     # neighbour's feature row per slot, -1 = no term
    for sweep in range(max_sweeps):
        changed = 0
        for i in range(n):
            if pos[i] < 0 or dirty[i] == 0:
                continue
            dirty[i] = 0
            q0 = inc_ptr[i]
            deg = inc_ptr[i + 1] - q0
            for s in range(deg):
                j = inc_other[q0 + s]
                if pos[j] < 0 or inc_weight[q0 + s] == 0.0:
                    nrow[s] = -1
                else:
                    nrow[s] = rowtab[ebase[pos[j]] + inc_twin[q0 + s]]
            best_p = pos[i]
            best = np.inf
            cur = np.inf
            for p in range(cand_ptr[i], cand_ptr[i + 1]):
                c = cand_cost[p]
                for s in range(deg):
                    if nrow[s] >= 0:
                        c += inc_weight[q0 + s] * _l1(feat, rowtab[ebase[p] + s], nrow[s])
                if p == pos[i]:
                    cur = c
                if c < best:
                    best = c
                    best_p = p
            # move only on a strict improvement, so ties keep the label and sweeps terminate
            if best_p != pos[i] and best < cur:
                pos[i] = best_p
                changed += 1
                for s in range(deg):
                    dirty[inc_other[q0 + s]] = 1
        if changed == 0:
            return sweep + 1
    return max_sweeps


def icm(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat,
        labels0=None, max_sweeps: int = 1000):
    """Iterated conditional modes: sweep the nodes in index order, giving each the label of its
    subset that minimises its unary plus its pairwise terms with the neighbours' current labels
    (changing only on a strict decrease), until a sweep changes nothing or ``max_sweeps``.
    Deterministic.

    Args:
        cand_ptr ... feat: the problem (module docstring).
        labels0: (N,) int initial labeling; None = per-node unary argmin (lowest label on ties).
        max_sweeps: upper bound on the sweeps.

    Returns:
        labels (N,) int32, -1 for nodes with an empty subset.
    """
    prob = _check_problem(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat)
    cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat = prob
    if int(max_sweeps) < 1:
        raise ValueError(f"max_sweeps must be >= 1, got {max_sweeps}")
    pos = _unary_argmin(cand_ptr, cand_cost) if labels0 is None else _positions(labels0, cand_ptr, cand_label, "labels0")
    g = _graph(cand_ptr, cand_label, edges, edge_weight, feat_ptr, feat_label)
    _icm_sweeps(pos, cand_ptr, cand_cost, g.inc_ptr, g.inc_other, g.inc_weight, g.inc_twin, g.ebase,
                g.rowtab, feat, int(max_sweeps))
    return _pos_to_labels(pos, cand_label)


def _pos_to_labels(pos, cand_label):
    labels = np.full(pos.shape[0], -1, np.int32)
    ok = pos >= 0
    labels[ok] = cand_label[pos[ok]]
    return labels


# --------------------------------------------------------------------------------------------
# α-expansion
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _edge_costs(pos, cand_label, edges, edge_weight, feat_ptr, feat_label, feat):
    """(E,) float64 pairwise cost of every edge under the labeling ``pos`` (0 if a node is out)."""
    out = np.zeros(edges.shape[0], np.float64)
    for e in range(edges.shape[0]):
        pu = pos[edges[e, 0]]
        pv = pos[edges[e, 1]]
        if pu >= 0 and pv >= 0 and edge_weight[e] != 0.0 and cand_label[pu] != cand_label[pv]:
            out[e] = edge_weight[e] * _l1(feat, _feat_row(feat_ptr, feat_label, e, cand_label[pu]),
                                          _feat_row(feat_ptr, feat_label, e, cand_label[pv]))
    return out


@njit(cache=True, nogil=True)
def _neighbour_rows(pos, inc_ptr, inc_other, inc_twin, ebase, rowtab):
    """(2E,) int64 per slot the feature row of the neighbour's current label (-1 if it is out)."""
    out = np.full(inc_other.shape[0], -1, np.int64)
    for i in range(pos.shape[0]):
        for q in range(inc_ptr[i], inc_ptr[i + 1]):
            j = inc_other[q]
            if pos[j] >= 0 and pos[i] >= 0:
                out[q] = rowtab[ebase[pos[j]] + inc_twin[q]]
    return out


@njit(cache=True, nogil=True)
def _expansion_cycle(order, pos, cand_cost, lab_ptr, lab_entry, entry_node, inc_ptr, inc_edge, inc_other,
                     inc_weight, inc_twin, ebase, rowtab, feat, edge_cost, nbr_row, accept_eps, changed_at,
                     last_tried, move):
    """One α-expansion cycle over the labels in ``order``, updating in place the entry indices
    ``pos``, the current pairwise cost per edge ``edge_cost`` and, per slot, the feature row of
    the neighbour's current label ``nbr_row`` (kept so the kernel reads slots sequentially
    instead of chasing the neighbour's tables).

    ``changed_at[i]`` is the move number at which node i last changed, ``last_tried[α]`` the
    move number at which α was last tried (-1 never); both persist across cycles. A label is
    skipped when no node holding it, nor a neighbour of one, changed since it was last tried:
    its move would be the same binary problem again (and after an accepted move every expansion
    of the new labeling is an expansion of the old one, so it cannot improve either).

    Returns (moves tried, moves accepted, summed energy change, next move number).
    """
    n = pos.shape[0]
    var_of = np.full(n, -1, np.int64)
    var_node = np.empty(n, np.int64)
    var_entry = np.empty(n, np.int64)
    e0 = np.empty(n, np.float64)
    e1 = np.empty(n, np.float64)
    n_slots = inc_other.shape[0]
    slot_new = np.empty(n_slots, np.float64)   # pairwise cost if this slot's node alone takes α
    n_pairs_max = n_slots // 2
    pair_i = np.empty(n_pairs_max, np.int64)
    pair_j = np.empty(n_pairs_max, np.int64)
    cap_ij = np.zeros(n_pairs_max, np.float64)
    cap_ji = np.empty(n_pairs_max, np.float64)
    side = np.empty(n, np.uint8)
    n_tried = 0
    n_acc = 0
    total = 0.0
    for oi in range(order.shape[0]):
        alpha = order[oi]
        if alpha + 1 >= lab_ptr.shape[0]:
            continue
        if last_tried[alpha] >= 0:
            stale = True
            for q in range(lab_ptr[alpha], lab_ptr[alpha + 1]):
                i = entry_node[lab_entry[q]]
                if changed_at[i] > last_tried[alpha]:
                    stale = False
                    break
                for k in range(inc_ptr[i], inc_ptr[i + 1]):
                    if changed_at[inc_other[k]] > last_tried[alpha]:
                        stale = False
                        break
                if not stale:
                    break
            if stale:
                continue
        move += 1
        n_tried += 1
        last_tried[alpha] = move

        nv = 0
        for q in range(lab_ptr[alpha], lab_ptr[alpha + 1]):
            p = lab_entry[q]
            i = entry_node[p]
            if pos[i] == p:
                continue
            var_of[i] = nv
            var_node[nv] = i
            var_entry[nv] = p
            e0[nv] = cand_cost[pos[i]]
            e1[nv] = cand_cost[p]
            nv += 1
        if nv == 0:
            continue

        npair = 0
        for v in range(nv):
            i = var_node[v]
            bi = ebase[pos[i]]
            ba = ebase[var_entry[v]]
            q0 = inc_ptr[i]
            for q in range(q0, inc_ptr[i + 1]):
                j = inc_other[q]
                w = inc_weight[q]
                if pos[j] < 0 or w == 0.0:
                    continue
                vj = var_of[j]
                if vj >= 0 and vj < v:
                    continue           # the pair was built from j's side, its slots filled
                ra = rowtab[ba + q - q0]
                rj = nbr_row[q]
                a_ = edge_cost[inc_edge[q]]     # both keep
                c_ = w * _l1(feat, ra, rj)      # i takes α, j keeps
                slot_new[q] = c_
                if vj < 0:
                    e0[v] += a_
                    e1[v] += c_
                else:
                    b_ = w * _l1(feat, rowtab[bi + q - q0], ra)  # i keeps, j takes α
                    slot_new[inc_ptr[j] + inc_twin[q]] = b_
                    # E = A(1-x_i) + C x_i - C x_j + (B+C-A)(1-x_i) x_j  (x = 1: take α)
                    e0[v] += a_
                    e1[v] += c_
                    e1[vj] -= c_
                    pair_i[npair] = v
                    pair_j[npair] = vj
                    # x_j = 1 (j on the source side), x_i = 0 (sink side) cuts arc j -> i
                    cap_ji[npair] = max(b_ + c_ - a_, 0.0)
                    npair += 1

        arc_ptr, head, sister, r_cap = build_arcs(nv, pair_i, pair_j, cap_ij, cap_ji, npair)
        tr = np.empty(nv, np.float64)
        for v in range(nv):
            tr[v] = e0[v] - e1[v]     # source cap (paid if x=0) minus sink cap (paid if x=1)
        bk_maxflow(arc_ptr, head, sister, r_cap, tr, side[:nv])

        # true energy change of the proposed move, from the pairwise costs computed above
        delta = 0.0
        n_sw = 0
        for v in range(nv):
            if side[v] != 0:
                continue
            n_sw += 1
            i = var_node[v]
            delta += cand_cost[var_entry[v]] - cand_cost[pos[i]]
            for q in range(inc_ptr[i], inc_ptr[i + 1]):
                j = inc_other[q]
                if pos[j] < 0 or inc_weight[q] == 0.0:
                    continue
                vj = var_of[j]
                if vj >= 0 and side[vj] == 0:       # both take α: the term becomes 0
                    if vj > v:
                        delta -= edge_cost[inc_edge[q]]
                else:
                    delta += slot_new[q] - edge_cost[inc_edge[q]]
        if n_sw > 0 and delta < -accept_eps:
            for v in range(nv):
                if side[v] != 0:
                    continue
                i = var_node[v]
                pos[i] = var_entry[v]
                changed_at[i] = move
                ba = ebase[var_entry[v]]
                for q in range(inc_ptr[i], inc_ptr[i + 1]):
                    j = inc_other[q]
                    nbr_row[inc_ptr[j] + inc_twin[q]] = rowtab[ba + q - inc_ptr[i]]
                    if pos[j] < 0 or inc_weight[q] == 0.0:
                        continue
                    vj = var_of[j]
                    edge_cost[inc_edge[q]] = 0.0 if (vj >= 0 and side[vj] == 0) else slot_new[q]
            n_acc += 1
            total += delta
        for v in range(nv):
            var_of[var_node[v]] = -1
    return n_tried, n_acc, total, move


def alpha_expansion(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat,
                    labels0=None, max_cycles: int = 10, tol: float = 1e-3, seed: int = 0):
    """Minimise the MRF energy by α-expansion (see the module docstring).

    Args:
        cand_ptr ... feat: the problem (module docstring).
        labels0: (N,) int initial labeling (a label of each node's subset, -1 for empty subsets);
            None = per-node unary argmin (lowest label on ties).
        max_cycles: at most this many cycles over the labels.
        tol: stop after a cycle that lowers the energy by less than ``tol * |E|`` (E = energy
            before the cycle); 0 runs until a cycle changes nothing (or ``max_cycles``).
        seed: seeds the label order of every cycle (a new permutation per cycle); the result is
            a deterministic function of the inputs and the seed.

    Returns:
        labels (N,) int32 (-1 for nodes with an empty subset) and energies (C+1,) float64: the
        energy of the initial labeling and after each of the C cycles run (non-increasing).
    """
    prob = _check_problem(cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat)
    cand_ptr, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat = prob
    if int(max_cycles) < 0:
        raise ValueError(f"max_cycles must be >= 0, got {max_cycles}")
    if isinstance(tol, (str, bytes)) or not (np.isscalar(tol) and np.isreal(tol)) or not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0 (0 runs until a cycle changes nothing), got {tol!r}")
    n = cand_ptr.shape[0] - 1
    pos = _unary_argmin(cand_ptr, cand_cost) if labels0 is None else _positions(labels0, cand_ptr, cand_label, "labels0")
    g = _graph(cand_ptr, cand_label, edges, edge_weight, feat_ptr, feat_label)
    lab_ptr, lab_entry, entry_node = _by_label(cand_ptr, cand_label)
    present = np.flatnonzero(np.diff(lab_ptr)).astype(np.int32)
    changed_at = np.zeros(n, np.int64)
    last_tried = np.full(lab_ptr.shape[0] - 1, -1, np.int64)
    move = 0
    rng = np.random.default_rng(seed)

    e_cur, scale = _energy_pos(pos, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat)
    edge_cost = _edge_costs(pos, cand_label, edges, edge_weight, feat_ptr, feat_label, feat)
    nbr_row = _neighbour_rows(pos, g.inc_ptr, g.inc_other, g.inc_twin, g.ebase, g.rowtab)
    energies = [e_cur]
    for _ in range(int(max_cycles)):
        order = rng.permutation(present).astype(np.int32)
        # a move must beat the rounding noise of the energy sums to count as a decrease
        eps = 1e-12 * max(scale, 1.0)
        n_tried, n_acc, _, move = _expansion_cycle(
            order, pos, cand_cost, lab_ptr, lab_entry, entry_node, g.inc_ptr, g.inc_edge, g.inc_other,
            g.inc_weight, g.inc_twin, g.ebase, g.rowtab, feat, edge_cost, nbr_row, eps, changed_at, last_tried,
            move)
        e_new, scale = _energy_pos(pos, cand_label, cand_cost, edges, edge_weight, feat_ptr, feat_label, feat)
        if e_new > e_cur + 1e-9 * max(scale, 1.0):
            raise RuntimeError(f"alpha_expansion: energy rose from {e_cur!r} to {e_new!r} in a cycle (bug)")
        energies.append(e_new)
        done = n_acc == 0 or (e_cur - e_new) < tol * abs(e_cur)
        e_cur = e_new
        if done:
            break
    return _pos_to_labels(pos, cand_label), np.asarray(energies, dtype=np.float64)
