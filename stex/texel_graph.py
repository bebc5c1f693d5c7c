"""The texel graph of one atlas rasterisation: what couples the covered texels of a UV atlas.

Solvers over a texture slice (the colour correction, :mod:`stex.correction`; the fill of
never-seen faces, :mod:`stex.fill`) need to know which texels are neighbours on the surface:

1. 4-neighbour texel pairs inside one chart (two texels side by side in the atlas but in two
   charts are not neighbours on the surface);
2. seam couplings: each 3-D edge shared by two faces whose UV edges differ (the two sides of a
   chart seam, two places in the atlas) is sampled at about one point per texel of its UV
   length; each sample is a row (bilinear value at the point in chart 1) − (bilinear value at
   the same 3-D point in chart 2), which is 0 where the texture is continuous across the seam.
   Bilinear stencils use only covered texels of the edge's own chart (weights renormalised);
   samples with no such texel on one side are dropped.

:func:`texel_graph` builds both once per atlas (they depend on the atlas only, never on a
slice); :meth:`TexelGraph.laplacian` is the graph Laplacian Gᵀ G + w SᵀS of the two kinds
together, the operator of a harmonic or screened-Poisson solve that respects the seams.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["TexelGraph", "texel_graph", "bilinear_stencil"]


def bilinear_stencil(px, chart_tex, chart_want, idx):
    """Bilinear stencils of points restricted to one chart's covered texels.

    Args:
        px: (N, 2) float texel coordinates (x = column, y = row; texel centres at integers).
        chart_tex: (W, W) int chart of each texel (-1 empty).
        chart_want: (N,) int chart the stencil of each point may use.
        idx: (W, W) int64 unknown id of each texel (-1 = not an unknown).

    Returns:
        (ids (N, 4) int64 unknown ids, -1 unused; w (N, 4) float64 weights renormalised to sum
        1; ok (N,) bool: the point has at least one usable texel).
    """
    W = chart_tex.shape[0]
    x, y = px[:, 0], px[:, 1]
    c0 = np.floor(x).astype(np.int64)
    r0 = np.floor(y).astype(np.int64)
    a, b = x - c0, y - r0
    ids = np.full((len(px), 4), -1, np.int64)
    w = np.zeros((len(px), 4))
    for j, (dr, dc, wt) in enumerate([(0, 0, (1 - a) * (1 - b)), (0, 1, a * (1 - b)),
                                      (1, 0, (1 - a) * b), (1, 1, a * b)]):
        r, c = r0 + dr, c0 + dc
        inside = (r >= 0) & (r < W) & (c >= 0) & (c < W)
        rr, cc = np.clip(r, 0, W - 1), np.clip(c, 0, W - 1)
        good = inside & (chart_tex[rr, cc] == chart_want) & (idx[rr, cc] >= 0)
        ids[:, j] = np.where(good, idx[rr, cc], -1)
        w[:, j] = np.where(good, wt, 0.0)
    s = w.sum(1)
    ok = s > 1e-9
    w[ok] /= s[ok, None]
    return ids, w, ok


@dataclass
class TexelGraph:
    """Pairs and seam rows over the covered texels of one (W, W) atlas rasterisation.

    Attributes:
        W: atlas side (texels).
        covered: (W, W) bool, texels of some face.
        index: (n,) int64 flat texel index of each unknown (the covered texels, row-major).
        idx: (W, W) int64 unknown id of each texel, -1 where not covered.
        chart_tex: (W, W) int32 chart of each texel, -1 where not covered.
        p, q: (m,) int32 unknown ids of the 4-neighbour pairs inside one chart (horizontal
            pairs first, q right of / below p).
        before, after: (m,) int32 per pair, the pair just before p / just after q along the
            same axis (-1 at a chart edge).
        S: (R, n) float64 CSR seam rows (chart-1 stencil − chart-2 stencil).
        n_seam_edges: 3-D edges that are seams; n_seam_dropped: their samples dropped.
    """

    W: int
    covered: np.ndarray
    index: np.ndarray
    idx: np.ndarray
    chart_tex: np.ndarray
    p: np.ndarray
    q: np.ndarray
    before: np.ndarray
    after: np.ndarray
    S: sp.csr_matrix
    n_seam_edges: int
    n_seam_dropped: int

    @property
    def n(self) -> int:
        """Number of unknowns (covered texels)."""
        return len(self.index)

    def laplacian(self, seam_weight: float = 1.0, screen: float = 0.0) -> sp.csr_matrix:
        """(n, n) float64 CSR graph Laplacian Gᵀ G + screen · I + seam_weight · SᵀS:
        symmetric positive semi-definite (definite with screen > 0), each pair and seam sample
        a squared difference."""
        n, m = self.n, len(self.p)
        deg = np.bincount(self.p, minlength=n) + np.bincount(self.q, minlength=n)
        L = sp.coo_matrix((np.concatenate([-np.ones(m), -np.ones(m), deg + float(screen)]),
                           (np.concatenate([self.p, self.q, np.arange(n)]),
                            np.concatenate([self.q, self.p, np.arange(n)]))), shape=(n, n)).tocsr()
        if self.S.shape[0] and seam_weight:
            L = L + float(seam_weight) * (self.S.T @ self.S).tocsr()
        L = L.tocsr()
        L.sum_duplicates()
        return L


def _pairs(covered, chart_tex, idx):
    """4-neighbour pairs inside one chart and each pair's neighbours along its own axis."""
    W = covered.shape[0]
    ps, qs = [], []
    same_h = covered[:, :-1] & covered[:, 1:] & (chart_tex[:, :-1] == chart_tex[:, 1:])
    ps.append(idx[:, :-1][same_h]); qs.append(idx[:, 1:][same_h])
    same_v = covered[:-1, :] & covered[1:, :] & (chart_tex[:-1, :] == chart_tex[1:, :])
    ps.append(idx[:-1, :][same_v]); qs.append(idx[1:, :][same_v])
    p = np.concatenate(ps).astype(np.int32)
    q = np.concatenate(qs).astype(np.int32)
    # (p's predecessor, p) and (q, q's successor), -1 where there is none (chart edge)
    nh = int(same_h.sum())
    hid = np.full((W, W), -1, np.int32)
    hid[:, :-1][same_h] = np.arange(nh)
    vid = np.full((W, W), -1, np.int32)
    vid[:-1, :][same_v] = nh + np.arange(int(same_v.sum()))
    pad_h = np.pad(hid, ((0, 0), (1, 1)), constant_values=-1)
    pad_v = np.pad(vid, ((1, 1), (0, 0)), constant_values=-1)
    before = np.concatenate([pad_h[:, :-3][same_h], pad_v[:-3, :][same_v]])
    after = np.concatenate([pad_h[:, 2:-1][same_h], pad_v[2:-1, :][same_v]])
    return p, q, before, after


def _seam_rows(W, n, texcoords, tfaces, faces, pairs, edges, face_chart, chart_tex, idx):
    """(seam rows (R, n) CSR, seam edges, dropped samples)."""
    tc = np.asarray(texcoords, np.float64)
    TF = np.asarray(tfaces, np.int64)
    Fv = np.asarray(faces, np.int64)
    pr = np.asarray(pairs, np.int64).reshape(-1, 2)
    ed = np.asarray(edges, np.int64).reshape(-1, 2)
    if len(pr) == 0:
        return sp.csr_matrix((0, n)), 0, 0

    def corner_uv(f, v):
        k = np.argmax(Fv[f] == v[:, None], axis=1)
        return tc[TF[f, k]]

    f1, f2 = pr[:, 0], pr[:, 1]
    a, b = ed[:, 0], ed[:, 1]
    u1a, u1b = corner_uv(f1, a), corner_uv(f1, b)
    u2a, u2b = corner_uv(f2, a), corner_uv(f2, b)
    seam = (np.abs(u1a - u2a).max(1) > 1e-7) | (np.abs(u1b - u2b).max(1) > 1e-7)
    n_edges = int(seam.sum())
    if not seam.any():
        return sp.csr_matrix((0, n)), 0, 0
    f1, f2, u1a, u1b, u2a, u2b = f1[seam], f2[seam], u1a[seam], u1b[seam], u2a[seam], u2b[seam]
    length = np.maximum(np.linalg.norm(u1b - u1a, axis=1), np.linalg.norm(u2b - u2a, axis=1)) * W
    ns = np.maximum(1, np.ceil(length)).astype(np.int64)
    e = np.repeat(np.arange(len(ns)), ns)
    k = np.arange(len(e)) - np.repeat(np.cumsum(ns) - ns, ns)
    t = ((k + 0.5) / ns[e])[:, None]
    p1 = (u1a[e] + t * (u1b[e] - u1a[e])) * W - 0.5
    p2 = (u2a[e] + t * (u2b[e] - u2a[e])) * W - 0.5
    id1, w1, ok1 = bilinear_stencil(p1, chart_tex, face_chart[f1[e]], idx)
    id2, w2, ok2 = bilinear_stencil(p2, chart_tex, face_chart[f2[e]], idx)
    ok = ok1 & ok2
    id1, w1, id2, w2 = id1[ok], w1[ok], id2[ok], w2[ok]
    R = len(id1)
    rows = np.repeat(np.arange(R), 8)
    cols = np.concatenate([id1, id2], 1).ravel()
    vals = np.concatenate([w1, -w2], 1).ravel()
    keep = cols >= 0
    S = sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(R, n))
    return S, n_edges, int((~ok).sum())


def texel_graph(texel_face, face_chart, texcoords, texcoord_faces, faces, pairs, edges) -> TexelGraph:
    """The :class:`TexelGraph` of one atlas rasterisation.

    Args:
        texel_face: (W, W) int face per texel, -1 = empty (:func:`stex.atlas.texel_map`).
        face_chart: (F,) int chart of each face (:func:`stex.atlas.uv_charts`).
        texcoords: (Vt, 2) float texcoords in [0, 1]; texcoord_faces: (F, 3) int.
        faces: (F, 3) int vertex indices.
        pairs, edges: (E, 2) int faces sharing a 3-D edge and that edge's two vertices
            (:func:`stex.mesh.face_adjacency`).
    """
    tfc = np.asarray(texel_face)
    if tfc.ndim != 2 or tfc.shape[0] != tfc.shape[1]:
        raise ValueError(f"texel_face must be (W, W), got {tfc.shape}")
    W = tfc.shape[0]
    face_chart = np.asarray(face_chart)
    covered = tfc >= 0
    index = np.flatnonzero(covered.ravel())
    n = len(index)
    idx = np.full(W * W, -1, np.int64)
    idx[index] = np.arange(n)
    idx = idx.reshape(W, W)
    chart_tex = np.where(covered, face_chart[np.maximum(tfc, 0)], -1).astype(np.int32)
    p, q, before, after = _pairs(covered, chart_tex, idx)
    S, n_edges, n_dropped = _seam_rows(W, n, texcoords, texcoord_faces, faces, pairs, edges,
                                       face_chart, chart_tex, idx)
    return TexelGraph(W, covered, index, idx, chart_tex, p, q, before, after, S, n_edges, n_dropped)
