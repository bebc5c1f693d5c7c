"""Embedded deformation (Sumner et al. 2007): the deformation graph over the template, the warp,
and the normal equations of the tracker's Gauss-Newton steps.

- A deformation graph of nodes sampled over the template with geodesic spacing; each vertex is
  bound to its k geodesically nearest nodes with weights (1 - d/d_max)^2, normalised. Nodes are
  linked to their geodesic neighbours and, on a closed template, also through the solid (ours:
  links whose midpoint is inside the mesh, :func:`volume_links_through_solid`), so the side the
  camera does not see follows the side it sees.
- Per node an affine A_j and translation t_j (12 parameters, :data:`PARAMS_PER_NODE`),
  x'_i = sum_j w_ij (A_j (x_i - g_j) + g_j + t_j) (:func:`deform`); the rotation term
  ||A^T A - I||^2 (:func:`rotation_terms`).
- J^T J assembled directly as 12x12 node-pair blocks (every data-like residual of a vertex folds
  into one 3x3 matrix first; :func:`normal_equations`), not as a sparse Jacobian times its
  transpose.

Vertices are metres in depth-camera coordinates. The solve itself is :mod:`stex.tracking`'s.
"""


from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse import csgraph
from scipy.sparse.linalg import LinearOperator
from scipy.spatial import cKDTree

from stex.mesh import is_closed, points_inside

log = logging.getLogger("stex.tracking")


PARAMS_PER_NODE = 12  # A (3x3, row-major) then t (3)


# -- deformation graph -------------------------------------------------------------------------

@dataclass
class DeformationGraph:
    """Nodes over a mesh and each vertex's binding.

    nodes: (N,) int32 vertex index of each node; vertex_nodes (V, k) int32; vertex_weights (V, k)
    float64 (rows sum to 1; padding entries have weight 0); edges (E, 2) int32 node pairs j < k;
    normal_pattern: the block pattern of the tracker's normal equations, built on first use.
    """

    nodes: np.ndarray
    vertex_nodes: np.ndarray
    vertex_weights: np.ndarray
    edges: np.ndarray
    normal_pattern: object = field(default=None, repr=False, compare=False)


def edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(V, V) sparse symmetric matrix of mesh edge lengths (metres)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    w = np.maximum(w, 1e-9)  # zero-length edges would vanish from the sparse matrix
    n = len(vertices)
    g = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    return g.tocsr()


def build_graph(vertices: np.ndarray, faces: np.ndarray, spacing_m: float, k: int = 4,
                node_neighbours: int = 6, volume_links: int = 0,
                volume_range: float = 9.0) -> DeformationGraph:
    """Sample nodes with geodesic spacing ``spacing_m`` and bind each vertex to ``k`` nodes.

    Greedy covering in vertex order (deterministic): a vertex not within ``spacing_m`` (geodesic,
    along mesh edges) of an existing node becomes a node. Vertices are bound to their k
    geodesically nearest nodes within 2.5 spacings (Euclidean nearest if none, e.g. on a tiny
    island); nodes are linked to up to ``node_neighbours`` nearest nodes within that range, and,
    with ``volume_links`` > 0 on a closed mesh, through the solid to up to that many nodes within
    ``volume_range`` spacings (:func:`volume_links_through_solid`).
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    G = edge_graph(V, F)
    n = len(V)
    covered = np.zeros(n, bool)
    nodes = []
    # Vertices not on any face are skipped (they cannot be reached along edges).
    used = np.zeros(n, bool)
    used[F.ravel()] = True
    covered[~used] = True
    order = np.flatnonzero(~covered)
    pos = 0
    while pos < len(order):
        v = order[pos]
        if covered[v]:
            pos += 1
            continue
        nodes.append(v)
        d = csgraph.dijkstra(G, indices=v, limit=spacing_m)
        covered |= np.isfinite(d)
        pos += 1
    nodes = np.asarray(nodes, np.int32)
    reach = 2.5 * spacing_m
    D = csgraph.dijkstra(G, indices=nodes, limit=reach)  # (N, V)
    Dt = D.T  # (V, N)
    kk = min(k + 1, len(nodes))
    idx = np.argsort(Dt, axis=1, kind="stable")[:, :kk]
    dist = np.take_along_axis(Dt, idx, axis=1)
    dmax = dist[:, -1] if kk > k else np.full(n, reach)
    dmax = np.where(np.isfinite(dmax), dmax, reach)
    vn, vd = idx[:, :k], dist[:, :k]
    w = np.where(np.isfinite(vd), np.clip(1 - vd / np.maximum(dmax[:, None], 1e-12), 0, 1) ** 2, 0.0)
    # A vertex whose nearest node sits at d_max gets weight 0 everywhere: keep the nearest.
    lonely = w.sum(1) <= 1e-12
    if lonely.any():
        _, nn = cKDTree(V[nodes]).query(V[lonely], k=1)
        vn[lonely] = 0
        vn[lonely, 0] = nn
        w[lonely] = 0
        w[lonely, 0] = 1
    w /= w.sum(1, keepdims=True)
    # Node-node links from geodesic distances between nodes.
    DN = D[:, nodes]
    np.fill_diagonal(DN, np.inf)
    nb = min(node_neighbours, max(len(nodes) - 1, 0))
    pairs = []
    if nb > 0:
        near = np.argsort(DN, axis=1, kind="stable")[:, :nb]
        for j in range(len(nodes)):  # N is a few hundred; vectorising buys nothing here
            for kq in near[j]:
                if np.isfinite(DN[j, kq]):
                    pairs.append((min(j, kq), max(j, kq)))
    edges = np.unique(np.asarray(pairs, np.int32).reshape(-1, 2), axis=0)
    if volume_links > 0:
        edges = volume_links_through_solid(V, F, nodes, edges, volume_links, volume_range * spacing_m)
    return DeformationGraph(nodes, vn.astype(np.int32), w, edges)


def volume_links_through_solid(vertices: np.ndarray, faces: np.ndarray, nodes: np.ndarray,
                               edges: np.ndarray, k: int, max_distance_m: float) -> np.ndarray:
    """``edges`` (E, 2) int32 plus links from every node to its ``k`` Euclidean nearest nodes
    within ``max_distance_m`` whose midpoint lies inside the closed mesh.

    Why: along the surface, a closed body's far side is linked to the side the camera sees only
    around the silhouette, so while it is unseen the regularisers carry the seen side's bend and
    twist over to it late and weakly; a link through the solid ties the two sides directly (the
    volumetric idea of VolumeDeform / DynamicFusion's Euclidean graph). A link whose midpoint is
    outside (between two legs, across a concavity) is not made, and neither is any on an open
    mesh (a template from one depth frame has no inside): (E', 2) is then ``edges`` unchanged.
    """
    V = np.asarray(vertices, np.float64)
    if len(nodes) < 2:
        return edges
    if not is_closed(V, faces):
        log.info("deformation graph: mesh not closed, no links through the solid")
        return edges
    P = V[nodes]
    d, idx = cKDTree(P).query(P, k=min(k + 1, len(P)))
    j = np.repeat(np.arange(len(P)), idx.shape[1] - 1)
    q = idx[:, 1:].ravel()
    near = d[:, 1:].ravel() <= max_distance_m
    cand = np.unique(np.sort(np.stack([j[near], q[near]], 1), axis=1), axis=0)
    if len(edges):
        known = set(map(tuple, np.asarray(edges).tolist()))
        cand = cand[[tuple(c) not in known for c in cand.tolist()]]
    if not len(cand):
        return edges
    # ray parity, any winding (trimesh's contains took most of the graph's time; same links)
    inside = points_inside(V, faces, 0.5 * (P[cand[:, 0]] + P[cand[:, 1]]))
    log.info("deformation graph: %d links through the solid (of %d candidates)", int(inside.sum()), len(cand))
    out = np.concatenate([np.asarray(edges, np.int32).reshape(-1, 2), cand[inside].astype(np.int32)])
    return np.unique(out, axis=0)


# -- deformation ----------------------------------------------------------------------------------

def identity_params(n_nodes: int) -> np.ndarray:
    """(N, 12) parameters of the identity warp."""
    x = np.zeros((n_nodes, PARAMS_PER_NODE))
    x[:, [0, 4, 8]] = 1.0
    return x


def deform(vertices: np.ndarray, node_pos: np.ndarray, graph: DeformationGraph, x: np.ndarray) -> np.ndarray:
    """Apply the ED warp ``x`` (N, 12) to (V, 3) vertices bound as in ``graph``."""
    A = x[:, :9].reshape(-1, 3, 3)
    t = x[:, 9:]
    g = node_pos[graph.vertex_nodes]                      # (V, k, 3)
    local = vertices[:, None, :] - g                      # (V, k, 3)
    moved = np.einsum("vkab,vkb->vka", A[graph.vertex_nodes], local) + g + t[graph.vertex_nodes]
    return (graph.vertex_weights[..., None] * moved).sum(1)


def rotation_terms(x: np.ndarray):
    """Residuals (6N,) and Jacobian blocks for ||A^T A - I|| per node."""
    N = len(x)
    A = x[:, :9].reshape(N, 3, 3)
    c = [A[:, :, i] for i in range(3)]  # columns
    pairs = [(0, 1), (0, 2), (1, 2), (0, 0), (1, 1), (2, 2)]
    res = np.empty((N, 6))
    J = np.zeros((N, 6, 9))
    for m, (a, b) in enumerate(pairs):
        res[:, m] = (c[a] * c[b]).sum(1) - (1.0 if a == b else 0.0)
        # d(c_a . c_b)/dA[r, a] = c_b[r]; d/dA[r, b] += c_a[r]; A[r, col] is index 3r + col
        for rr in range(3):
            J[:, m, 3 * rr + a] += c[b][:, rr]
            J[:, m, 3 * rr + b] += c[a][:, rr]
    return res, J


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion (Kabsch) taking points ``src`` (n, 3) to ``dst`` (n, 3):
    (R (3, 3), t (3,)) with dst ~ src @ R.T + t."""
    a, b = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or len(a) < 3:
        raise ValueError(f"rigid_fit needs two (n >= 3, 3) point sets of one shape, got {a.shape} and {b.shape}")
    ca, cb = a.mean(0), b.mean(0)
    U, _, Wt = np.linalg.svd((b - cb).T @ (a - ca))
    U[:, 2] *= np.linalg.det(U @ Wt)
    R = U @ Wt
    return R, cb - ca @ R.T


# -- normal equations ---------------------------------------------------------------------------
#
# Every data-like residual (depth, point, flow, silhouette) has the form sw * D . x'_i for one
# vertex i, and x'_i depends on a node j's 12 parameters through w_ij [A_j row r] . [local; 1].
# So a vertex's residuals fold into one 3x3 information matrix M_i = sum sw^2 D D^T and a 3-vector
# b_i = sum sw^2 r D, and J^T J gains G_a^T M_i G_b = w_a w_b M[r, s] h_a[c] h_b[d] between node
# slots a, b (h = [local; 1]). The graph-smoothness residuals have the same shape (two slots,
# h = [g_k - g_j; 1] and [0; -1], M = w I). Accumulating these 12x12 node-pair blocks directly
# (numba) replaces building the sparse Jacobian and the sparse product J^T J, a large part of a
# paper-scale solve (docs/decisions/tracking.md).

@njit(cache=True, nogil=True)
def _vertex_information(n_vertices, vid, Dw, rw):
    """Fold weighted residuals rw (n,) with rows Dw (n, 3) per vertex vid (n,) into
    M (V, 3, 3) = sum Dw Dw^T and b (V, 3) = sum rw Dw."""
    M = np.zeros((n_vertices, 3, 3))
    b = np.zeros((n_vertices, 3))
    for i in range(len(vid)):
        v = vid[i]
        for a in range(3):
            b[v, a] += rw[i] * Dw[i, a]
            for c in range(3):
                M[v, a, c] += Dw[i, a] * Dw[i, c]
    return M, b


@njit(cache=True, nogil=True)
def _accumulate_normal(blocks, grad, nodes, h, M, b, bidx):
    """blocks (nb, 12, 12) += G^T M G and grad (N, 12) += G^T b for points (n,) with slots
    nodes (n, s), h (n, s, 4) (the slot weight folded in), M (n, 3, 3), b (n, 3), and bidx
    (n, s, s) the block of each slot pair."""
    n, s = nodes.shape
    for i in range(n):
        for a in range(s):
            ja = nodes[i, a]
            for r in range(3):
                for c in range(4):
                    pa = 3 * r + c if c < 3 else 9 + r
                    grad[ja, pa] += h[i, a, c] * b[i, r]
            for q in range(s):
                blk = bidx[i, a, q]
                for r in range(3):
                    for c in range(4):
                        hac = h[i, a, c]
                        if hac == 0.0:
                            continue
                        pa = 3 * r + c if c < 3 else 9 + r
                        for r2 in range(3):
                            m = M[i, r, r2] * hac
                            if m == 0.0:
                                continue
                            for d in range(4):
                                pb = 3 * r2 + d if d < 3 else 9 + r2
                                blocks[blk, pa, pb] += m * h[i, q, d]


class NormalPattern:
    """Block-sparse (BSR, 12x12 blocks) pattern of J^T J for one deformation graph: a block for
    every pair of nodes sharing a vertex or a graph edge, and the diagonal."""

    def __init__(self, graph: DeformationGraph, n_nodes: int):
        N = n_nodes
        vn = graph.vertex_nodes.astype(np.int64)
        ends = graph.edges.astype(np.int64).reshape(-1, 2)
        keys = np.concatenate([(vn[:, :, None] * N + vn[:, None, :]).ravel(),
                               (ends[:, :, None] * N + ends[:, None, :]).ravel(),
                               np.arange(N) * (N + 1)])
        self.keys = np.unique(keys)
        rows = self.keys // N
        self.indices = (self.keys % N).astype(np.int32)
        self.indptr = np.searchsorted(rows, np.arange(N + 1)).astype(np.int32)
        self.vertex_blocks = np.searchsorted(self.keys, vn[:, :, None] * N + vn[:, None, :])
        self.edge_blocks = np.searchsorted(self.keys, ends[:, :, None] * N + ends[:, None, :])
        self.diag = np.searchsorted(self.keys, np.arange(N) * (N + 1))
        self.n_nodes = N


def normal_equations(pattern: NormalPattern, graph: DeformationGraph, local, vid, Dw, rw,
                      rot_res, rot_jac, smooth_res, smooth_weight, d_jk, damping=0.0):
    """J^T J (BSR, 12N x 12N) and J^T r (12N,) of the weighted residuals of one GN step.

    vid (n,) vertex of each data-like residual, Dw (n, 3) its row d r / d x'_i, rw (n,) its
    value (weights folded in); rot_res (N, 6) / rot_jac (N, 6, 9) the rotation residuals and their
    Jacobian w.r.t. A (weight folded in); smooth_res (E, 3) the graph residuals r_jk - s_jk, with
    weight smooth_weight (scalar or (E,); its square root scales each residual), d_jk (E, 3) = g_k - g_j;
    damping is added to the diagonal. Also returns the (N, 12, 12) diagonal blocks.
    """
    N = pattern.n_nodes
    blocks = np.zeros((len(pattern.keys), 12, 12))
    grad = np.zeros((N, 12))
    if len(vid):
        M, b = _vertex_information(len(local), vid, Dw, rw)
        act = np.unique(vid)
        w = graph.vertex_weights[act]
        h = np.concatenate([local[act] * w[..., None], w[..., None]], axis=2)
        _accumulate_normal(blocks, grad, graph.vertex_nodes[act].astype(np.int64), h, M[act], b[act],
                           pattern.vertex_blocks[act])
    E = len(smooth_res)
    if E:
        h = np.zeros((E, 2, 4))
        h[:, 0, :3] = d_jk
        h[:, 0, 3] = 1.0
        h[:, 1, 3] = -1.0
        sw = np.broadcast_to(np.asarray(smooth_weight, np.float64), (E,))
        M = np.eye(3)[None] * sw[:, None, None]
        _accumulate_normal(blocks, grad, graph.edges.astype(np.int64), h, M, smooth_res * sw[:, None],
                           pattern.edge_blocks)
    blocks[pattern.diag, :9, :9] += np.einsum("nmi,nmj->nij", rot_jac, rot_jac)
    grad[:, :9] += np.einsum("nmi,nm->ni", rot_jac, rot_res)
    blocks[pattern.diag] += np.eye(12) * damping
    JtJ = sp.bsr_matrix((blocks, pattern.indices, pattern.indptr), shape=(12 * N, 12 * N))
    return JtJ, grad.ravel(), blocks[pattern.diag]


def compose_rigid(x: np.ndarray, node_pos: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """ED parameters (N, 12) of the warp ``x`` (nodes at ``node_pos`` (N, 3)) followed by the rigid
    motion y = R y + t: deform(V, node_pos, graph, result) == deform(V, node_pos, graph, x) @ R.T + t."""
    out = np.array(x, np.float64, copy=True)
    N = len(out)
    out[:, :9] = (R[None] @ out[:, :9].reshape(N, 3, 3)).reshape(N, 9)
    out[:, 9:] = (node_pos + out[:, 9:]) @ R.T + t - node_pos
    return out


def block_jacobi(blocks):
    """The 12x12 block-Jacobi preconditioner of the (N, 12, 12) diagonal blocks, for scipy's cg.

    A node whose data are degenerate (a few points on a line, one limb's last pixels) has a
    rank-deficient block; with large entries the tiny ridge is lost to rounding and the block is
    singular in floating point, so such a set of blocks is pseudo-inverted instead."""
    N = len(blocks)
    ridged = blocks + np.eye(12) * 1e-12
    try:
        inv = np.linalg.inv(ridged)
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(ridged, hermitian=True)
    return LinearOperator((12 * N, 12 * N), matvec=lambda v: np.einsum("nab,nb->na", inv, v.reshape(N, 12)).ravel())
