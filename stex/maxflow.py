"""Boykov–Kolmogorov s-t max-flow / min-cut (PAMI 2004) in numba, the cut of every α-expansion move
of :mod:`stex.mrf`.

Two search trees grown from the terminals, augmenting along the path where they meet, orphans
re-adopted (origin check with time stamps and distances) so the trees are reused between
augmentations, never rebuilt. Capacities are float64 (exact for integer capacities below 2^53).
Nodes not in the source tree after the flow (free or sink tree) are on the sink side, i.e. the
source side is the set reachable from s in the residual graph.

- :func:`min_cut` — the routine on its own (checked arguments).
- :func:`build_arcs`, :func:`bk_maxflow` — the kernels :mod:`stex.mrf` calls from its compiled
  expansion cycle.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["min_cut", "build_arcs", "bk_maxflow", "float_vector"]

_NONE = -1       # BK parent: free node
_TERMINAL = -2   # BK parent: attached to its terminal
_ORPHAN = -3     # BK parent: lost its parent arc, awaiting adoption
_INF_D = 1 << 60



# --------------------------------------------------------------------------------------------
# Boykov–Kolmogorov max-flow on a CSR arc list
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def build_arcs(n, pair_i, pair_j, cap_ij, cap_ji, n_pairs):
    """CSR arcs for ``n_pairs`` node pairs: arc_ptr (n+1,), head, sister, r_cap (2*n_pairs,)."""
    deg = np.zeros(n + 1, np.int64)
    for p in range(n_pairs):
        deg[pair_i[p] + 1] += 1
        deg[pair_j[p] + 1] += 1
    for i in range(n):
        deg[i + 1] += deg[i]
    arc_ptr = deg.copy()
    fill = deg[:n].copy()
    m = 2 * n_pairs
    head = np.empty(m, np.int64)
    sister = np.empty(m, np.int64)
    r_cap = np.empty(m, np.float64)
    for p in range(n_pairs):
        i = pair_i[p]
        j = pair_j[p]
        a = fill[i]
        b = fill[j]
        fill[i] += 1
        fill[j] += 1
        head[a] = j
        head[b] = i
        sister[a] = b
        sister[b] = a
        r_cap[a] = cap_ij[p]
        r_cap[b] = cap_ji[p]
    return arc_ptr, head, sister, r_cap


@njit(cache=True, nogil=True, inline="always")
def _activate(j, nxt, q_first, q_last):
    """Append node j to the active FIFO (nxt links; the last node links to itself)."""
    if q_last >= 0:
        nxt[q_last] = j
    else:
        q_first = j
    nxt[j] = j
    return q_first, j


@njit(cache=True, nogil=True, inline="always")
def _push_orphan(k, orphans, o_head, o_count):
    """Append node k to the circular orphan FIFO; returns the new count."""
    orphans[(o_head + o_count) % orphans.shape[0]] = k
    return o_count + 1


@njit(cache=True, nogil=True)
def bk_maxflow(arc_ptr, head, sister, r_cap, tr_cap, side):
    """Max-flow of the graph given by CSR arcs and terminal residuals ``tr_cap`` (source minus
    sink capacity per node). ``r_cap`` and ``tr_cap`` are updated in place to the residuals.
    Writes ``side[i]`` = 0 for the source side (source tree), 1 otherwise. Returns the flow
    augmented along s-t paths (the caller adds the min(source, sink) already cancelled)."""
    n = arc_ptr.shape[0] - 1
    parent = np.full(n, _NONE, np.int64)
    is_sink = np.zeros(n, np.uint8)
    nxt = np.full(n, -1, np.int64)        # active FIFO link; -1 = not active, self = last
    ts = np.zeros(n, np.int64)
    dist = np.zeros(n, np.int64)
    orphans = np.empty(n, np.int64)       # circular FIFO; a node is in it at most once
    o_head = 0
    o_count = 0
    q_first = -1
    q_last = -1

    for i in range(n):
        if tr_cap[i] > 0.0:
            parent[i] = _TERMINAL
            is_sink[i] = 0
        elif tr_cap[i] < 0.0:
            parent[i] = _TERMINAL
            is_sink[i] = 1
        else:
            continue
        dist[i] = 1
        q_first, q_last = _activate(i, nxt, q_first, q_last)

    flow = 0.0
    time = 0
    cur = -1
    while True:
        i = cur
        if i >= 0:
            nxt[i] = -1
            if parent[i] == _NONE:
                i = -1
        if i < 0:
            # next active node that is still in a tree
            while True:
                i = q_first
                if i < 0:
                    break
                if nxt[i] == i:
                    q_first = -1
                    q_last = -1
                else:
                    q_first = nxt[i]
                nxt[i] = -1
                if parent[i] != _NONE:
                    break
            if i < 0:
                break

        # grow the tree of i; `mid` is an arc from the source tree into the sink tree
        mid = -1
        if is_sink[i] == 0:
            for a in range(arc_ptr[i], arc_ptr[i + 1]):
                if r_cap[a] > 0.0:
                    j = head[a]
                    if parent[j] == _NONE:
                        is_sink[j] = 0
                        parent[j] = sister[a]
                        ts[j] = ts[i]
                        dist[j] = dist[i] + 1
                        if nxt[j] < 0:
                            q_first, q_last = _activate(j, nxt, q_first, q_last)
                    elif is_sink[j]:
                        mid = a
                        break
                    elif ts[j] <= ts[i] and dist[j] > dist[i]:
                        parent[j] = sister[a]
                        ts[j] = ts[i]
                        dist[j] = dist[i] + 1
        else:
            for a in range(arc_ptr[i], arc_ptr[i + 1]):
                s = sister[a]
                if r_cap[s] > 0.0:
                    j = head[a]
                    if parent[j] == _NONE:
                        is_sink[j] = 1
                        parent[j] = s
                        ts[j] = ts[i]
                        dist[j] = dist[i] + 1
                        if nxt[j] < 0:
                            q_first, q_last = _activate(j, nxt, q_first, q_last)
                    elif is_sink[j] == 0:
                        mid = s
                        break
                    elif ts[j] <= ts[i] and dist[j] > dist[i]:
                        parent[j] = s
                        ts[j] = ts[i]
                        dist[j] = dist[i] + 1
        time += 1

        if mid < 0:
            cur = -1
            continue
        nxt[i] = i          # keep i as the current node (active, but not queued)
        cur = i

        # augment: bottleneck along source tree, middle arc, sink tree
        b = r_cap[mid]
        k = head[sister[mid]]
        while parent[k] != _TERMINAL:
            a = parent[k]
            if r_cap[sister[a]] < b:
                b = r_cap[sister[a]]
            k = head[a]
        if tr_cap[k] < b:
            b = tr_cap[k]
        k = head[mid]
        while parent[k] != _TERMINAL:
            a = parent[k]
            if r_cap[a] < b:
                b = r_cap[a]
            k = head[a]
        if -tr_cap[k] < b:
            b = -tr_cap[k]

        r_cap[sister[mid]] += b
        r_cap[mid] -= b
        k = head[sister[mid]]
        while parent[k] != _TERMINAL:
            a = parent[k]
            r_cap[a] += b
            r_cap[sister[a]] -= b
            if r_cap[sister[a]] <= 0.0:
                parent[k] = _ORPHAN
                o_count = _push_orphan(k, orphans, o_head, o_count)
            k = head[a]
        tr_cap[k] -= b
        if tr_cap[k] <= 0.0:
            parent[k] = _ORPHAN
            o_count = _push_orphan(k, orphans, o_head, o_count)
        k = head[mid]
        while parent[k] != _TERMINAL:
            a = parent[k]
            r_cap[sister[a]] += b
            r_cap[a] -= b
            if r_cap[a] <= 0.0:
                parent[k] = _ORPHAN
                o_count = _push_orphan(k, orphans, o_head, o_count)
            k = head[a]
        tr_cap[k] += b
        if tr_cap[k] >= 0.0:
            parent[k] = _ORPHAN
            o_count = _push_orphan(k, orphans, o_head, o_count)
        flow += b

        # adoption
        while o_count > 0:
            o = orphans[o_head]
            o_head = (o_head + 1) % n
            o_count -= 1
            sink = is_sink[o]
            d_min = _INF_D
            a_min = -1
            for a0 in range(arc_ptr[o], arc_ptr[o + 1]):
                # a parent j must be able to push flow towards o (source tree) or take it (sink)
                cap = r_cap[a0] if sink else r_cap[sister[a0]]
                if cap <= 0.0:
                    continue
                j = head[a0]
                if is_sink[j] != sink or parent[j] == _NONE:
                    continue
                d = 0
                while True:       # is j's origin a terminal? (stamped nodes are known to be)
                    if ts[j] == time:
                        d += dist[j]
                        break
                    a = parent[j]
                    d += 1
                    if a == _TERMINAL:
                        ts[j] = time
                        dist[j] = 1
                        break
                    if a == _ORPHAN:
                        d = _INF_D
                        break
                    j = head[a]
                if d < _INF_D:
                    if d < d_min:
                        a_min = a0
                        d_min = d
                    j = head[a0]
                    while ts[j] != time:
                        ts[j] = time
                        dist[j] = d
                        d -= 1
                        j = head[parent[j]]
            if a_min >= 0:
                parent[o] = a_min
                ts[o] = time
                dist[o] = d_min + 1
                continue
            parent[o] = _NONE
            for a0 in range(arc_ptr[o], arc_ptr[o + 1]):
                j = head[a0]
                a = parent[j]
                if is_sink[j] != sink or a == _NONE:
                    continue
                cap = r_cap[a0] if sink else r_cap[sister[a0]]
                if cap > 0.0 and nxt[j] < 0:
                    q_first, q_last = _activate(j, nxt, q_first, q_last)
                if a != _TERMINAL and a != _ORPHAN and head[a] == o:
                    parent[j] = _ORPHAN
                    o_count = _push_orphan(j, orphans, o_head, o_count)

    for i in range(n):
        side[i] = 0 if (parent[i] != _NONE and is_sink[i] == 0) else 1
    return flow


def min_cut(n, source_cap, sink_cap, edge_i, edge_j, cap_ij, cap_ji):
    """Maximum s-t flow and a minimum cut of a graph with terminal and pairwise capacities.

    The cut cost of a node set S (source side) is
    ``sum_{i in T} source_cap[i] + sum_{i in S} sink_cap[i] + sum_{p: i in S, j in T} cap_ij[p]
    + sum_{p: j in S, i in T} cap_ji[p]`` (T = the other nodes); the min cut's cost equals the
    max flow.

    Args:
        n: number of non-terminal nodes.
        source_cap, sink_cap: (n,) float, >= 0, capacities s->i and i->t.
        edge_i, edge_j: (P,) int node ids (parallel pairs allowed, no self-loops).
        cap_ij, cap_ji: (P,) float >= 0, capacities i->j and j->i.

    Returns:
        (flow float, side (n,) uint8): side 0 = source side S (the nodes reachable from s in the
        residual graph), 1 = sink side.
    """
    n = int(n)
    if n < 0:
        raise ValueError(f"min_cut: n must be >= 0, got {n}")
    cs = float_vector(source_cap, "source_cap", n)
    ct = float_vector(sink_cap, "sink_cap", n)
    ei = np.ascontiguousarray(np.asarray(edge_i).reshape(-1))
    ej = np.ascontiguousarray(np.asarray(edge_j).reshape(-1))
    p = ei.shape[0]
    if ej.shape[0] != p:
        raise ValueError(f"min_cut: edge_i has {p} entries but edge_j has {ej.shape[0]}")
    if p and not (np.issubdtype(ei.dtype, np.integer) and np.issubdtype(ej.dtype, np.integer)):
        raise ValueError("min_cut: edge_i and edge_j must be integer arrays")
    cij = float_vector(cap_ij, "cap_ij", p)
    cji = float_vector(cap_ji, "cap_ji", p)
    ei = ei.astype(np.int64)
    ej = ej.astype(np.int64)
    if p:
        bad = (ei < 0) | (ei >= n) | (ej < 0) | (ej >= n)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"min_cut: pair {k} = ({ei[k]}, {ej[k]}) is outside 0..{n - 1}")
        loop = ei == ej
        if loop.any():
            k = int(np.flatnonzero(loop)[0])
            raise ValueError(f"min_cut: pair {k} is a self-loop on node {ei[k]}")
    for name, c in (("source_cap", cs), ("sink_cap", ct), ("cap_ij", cij), ("cap_ji", cji)):
        if c.size and c.min() < 0:
            k = int(np.argmin(c))
            raise ValueError(f"min_cut: {name}[{k}] = {c[k]} is negative")
    base = float(np.minimum(cs, ct).sum())
    side = np.zeros(n, np.uint8)
    if n == 0:
        return base, side
    arc_ptr, head, sister, r_cap = build_arcs(n, ei, ej, cij, cji, p)
    tr = cs - ct
    flow = bk_maxflow(arc_ptr, head, sister, r_cap, tr, side)
    return base + flow, side


def float_vector(x, name, length):
    """``x`` as a contiguous (length,) float64 vector; ValueError naming ``name`` if it has another
    length or a non-finite entry."""
    a = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1))
    if a.shape[0] != length:
        raise ValueError(f"{name} must have {length} entries, got {a.shape[0]}")
    if not np.isfinite(a).all():
        k = int(np.flatnonzero(~np.isfinite(a))[0])
        raise ValueError(f"{name}[{k}] = {a[k]} is not finite")
    return a
