"""The photometric term of the texture-coordinate optimisation (:mod:`stex.texcoords`): the numba
kernels that sample the frames' crops at ξ, the proxy colours, the per-(frame, face) errors and
robust weights (:class:`PhotometricTerm`), the Gauss-Newton steps and blocks, and the sparse
per-frame systems of the 'sparse' solver (:class:`SparseSystems`). Conventions as in
:mod:`stex.texcoords`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from scipy.sparse import csc_matrix
from scipy.sparse.linalg import splu

__all__ = ["FACE_PHOTOMETRIC", "PhotometricTerm", "SparseSystems", "jacobi_step_kernel",
           "face_blocks_kernel", "vertex_used", "gauge_weights", "edge_energy"]

#: texcoords.face_photometric modes, in the order of the kernels' integer code
FACE_PHOTOMETRIC = ("none", "offset", "affine")


# --------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _bilerp(buf, off, h, w, x, y):
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    c0 = int(x)
    r0 = int(y)
    c1 = min(c0 + 1, w - 1)
    r1 = min(r0 + 1, h - 1)
    a = x - c0
    b = y - r0
    return ((1.0 - a) * (1.0 - b) * buf[off + r0 * w + c0] + a * (1.0 - b) * buf[off + r0 * w + c1]
            + (1.0 - a) * b * buf[off + r1 * w + c0] + a * b * buf[off + r1 * w + c1])


@njit(cache=True, nogil=True, inline="always")
def _grad(buf, off, h, w, u, v, g):
    """g · ∇C at (u, v): central differences of bilinear lookups 1 px apart (grey levels / px)."""
    gx = 0.5 * g * (_bilerp(buf, off, h, w, u + 1.0, v) - _bilerp(buf, off, h, w, u - 1.0, v))
    gy = 0.5 * g * (_bilerp(buf, off, h, w, u, v + 1.0) - _bilerp(buf, off, h, w, u, v - 1.0))
    return gx, gy


@njit(cache=True, nogil=True, inline="always")
def _edge_vectors(xi, phi, k, va, vb):
    """(ξ_a − ξ_b, Φ_a − Φ_b) components (ex, ey, px, py) of the edge (va, vb) at frame k."""
    return (xi[k, va, 0] - xi[k, vb, 0], xi[k, va, 1] - xi[k, vb, 1],
            phi[k, va, 0] - phi[k, vb, 0], phi[k, va, 1] - phi[k, vb, 1])


@njit(cache=True, nogil=True, inline="always")
def _sample_pos(bary, s, xi, k, faces, f, x0, y0):
    """Crop-pixel position (u, v) of sample ``s`` of face ``f`` in frame ``k`` (through ξ)."""
    a = faces[f, 0]
    b = faces[f, 1]
    c = faces[f, 2]
    u = bary[s, 0] * xi[k, a, 0] + bary[s, 1] * xi[k, b, 0] + bary[s, 2] * xi[k, c, 0] - x0[k]
    v = bary[s, 0] * xi[k, a, 1] + bary[s, 1] * xi[k, b, 1] + bary[s, 2] * xi[k, c, 1] - y0[k]
    return u, v


@njit(cache=True, nogil=True, parallel=True)
def _sample_kernel(buf, mbuf, off, hh, ww, x0, y0, xi, faces, pk, pf, bary, C, inside):
    """C[q, s] = C_k(p) (grey levels, float32) and inside[q, s] = foreground mask ≥ 0.999 at p, for
    every visible (frame, face) pair q = (pk[q], pf[q]) and sample s (bilinear in the crops)."""
    Q = pk.shape[0]
    S = bary.shape[0]
    for q in prange(Q):
        k = pk[q]
        f = pf[q]
        o = off[k]
        h = hh[k]
        w = ww[k]
        for s in range(S):
            u, v = _sample_pos(bary, s, xi, k, faces, f, x0, y0)
            C[q, s] = _bilerp(buf, o, h, w, u, v)
            inside[q, s] = _bilerp(mbuf, o, h, w, u, v) >= 0.999


@njit(cache=True, nogil=True, parallel=True)
def _proxy_kernel(C, inside, order, fstart, pk, wq, gain, bg_weight, proxy):
    """proxy[f, s] = Σ_q w·g_k·C[q, s] / Σ_q w over the pairs q = order[fstart[f]:fstart[f + 1]] of
    face f (0 if none), w = wq[q] (face cosine × robust weight) × (1 inside the mask, bg_weight
    outside), g_k = gain[pk[q]]."""
    nF = proxy.shape[0]
    S = proxy.shape[1]
    for f in prange(nF):
        num = np.zeros(S)
        den = np.zeros(S)
        for i in range(fstart[f], fstart[f + 1]):
            q = order[i]
            w = wq[q]
            gw = w * gain[pk[q]]
            for s in range(S):
                if inside[q, s]:
                    num[s] += gw * C[q, s]
                    den[s] += w
                else:
                    num[s] += bg_weight * gw * C[q, s]
                    den[s] += bg_weight * w
        for s in range(S):
            proxy[f, s] = num[s] / den[s] if den[s] > 0 else 0.0


@njit(cache=True, nogil=True, parallel=True)
def _face_err_kernel(C, pk, pf, gain, proxy, face_model, out):
    """out[q] = Σ_s (a·g_k·C[q, s] − P[pf[q], s] − m)² (grey levels²), (a, m) the pair's fit by
    ``face_model`` (:func:`_face_fit`; (1, 0) for 'none')."""
    Q = C.shape[0]
    S = C.shape[1]
    for q in prange(Q):
        g = gain[pk[q]]
        f = pf[q]
        a, m = _face_fit(C, q, f, g, proxy, face_model)
        e = 0.0
        for s in range(S):
            r = a * g * C[q, s] - proxy[f, s] - m
            e += r * r
        out[q] = e


@njit(cache=True, nogil=True, inline="always")
def _face_fit(C, q, f, g, proxy, face_model):
    """(a, m) of the residuals a·g·C_s − P_s − m of pair q (face f) by ``face_photometric``
    (index in FACE_PHOTOMETRIC): none (1, 0); offset: m their mean; affine: also a, the
    least-squares contrast of the face's samples to the proxy's, clamped to [0.5, 2]."""
    S = C.shape[1]
    if face_model == 0:
        return 1.0, 0.0
    a = 1.0
    if face_model == 2:
        xm = 0.0
        ym = 0.0
        for s in range(S):
            xm += g * C[q, s]
            ym += proxy[f, s]
        xm /= S
        ym /= S
        sxy = 0.0
        sxx = 0.0
        for s in range(S):
            dx = g * C[q, s] - xm
            sxy += dx * (proxy[f, s] - ym)
            sxx += dx * dx
        if sxx > 1e-9:
            a = min(max(sxy / sxx, 0.5), 2.0)
    m = 0.0
    for s in range(S):
        m += a * g * C[q, s] - proxy[f, s]
    return a, m / S


@njit(cache=True, nogil=True, parallel=True)
def jacobi_step_kernel(buf, off, hh, ww, x0, y0, xi, phi, faces, fvis, omega, gain, bary, proxy, C, qs,
               edge_w, edge_vec, clamp, face_model, step):
    """step[k, v] = the clamped 2×2 Gauss-Newton step of every vertex (neighbours fixed); the
    photometric residuals g_k·C_k(p) − P of face f at frame k (with ``face_model`` > 0, the
    face's fitted residuals, :func:`_face_fit`) are weighted by omega[k, f].
    C (Q, S): the samples at ``xi`` of the visible pairs, frame-major (:func:`_sample_kernel`),
    frame k's pairs at qs[k]..qs[k + 1] in face order."""
    K, V = xi.shape[0], xi.shape[1]
    nF = faces.shape[0]
    S = bary.shape[0]
    for k in prange(K):
        A = np.zeros((V, 3))   # a11, a12, a22
        g = np.zeros((V, 2))
        M = np.zeros((3, 2))   # a face's mean corner Jacobians (face_model > 0)
        o = off[k]
        h = hh[k]
        w = ww[k]
        gk = gain[k]
        q = qs[k] - 1
        for f in range(nF):
            if not fvis[k, f]:
                continue
            q += 1
            om = omega[k, f]
            if face_model:
                # residuals a·g·C_s − P_s − m (:func:`_face_fit`): exact Gauss-Newton blocks of
                # the corners, whose Jacobians are a β_sj ∇C_s − M_j, M_j = mean_s a β_sj ∇C_s
                # (a held fixed for the step)
                a, m = _face_fit(C, q, f, gk, proxy, face_model)
                M[...] = 0.0
                for s in range(S):
                    u, v = _sample_pos(bary, s, xi, k, faces, f, x0, y0)
                    gx, gy = _grad(buf, o, h, w, u, v, a * gk)
                    r = a * gk * C[q, s] - proxy[f, s] - m
                    for j in range(3):
                        b = bary[s, j]
                        vi = faces[f, j]
                        A[vi, 0] += om * b * b * gx * gx
                        A[vi, 1] += om * b * b * gx * gy
                        A[vi, 2] += om * b * b * gy * gy
                        g[vi, 0] += om * b * gx * r
                        g[vi, 1] += om * b * gy * r
                        M[j, 0] += b * gx / S
                        M[j, 1] += b * gy / S
                for j in range(3):
                    vi = faces[f, j]
                    A[vi, 0] -= om * S * M[j, 0] * M[j, 0]
                    A[vi, 1] -= om * S * M[j, 0] * M[j, 1]
                    A[vi, 2] -= om * S * M[j, 1] * M[j, 1]
            else:
                for s in range(S):
                    u, v = _sample_pos(bary, s, xi, k, faces, f, x0, y0)
                    r = gk * C[q, s] - proxy[f, s]
                    gx, gy = _grad(buf, o, h, w, u, v, gk)
                    for j in range(3):
                        bj = om * bary[s, j]
                        if bj <= 0.0:
                            continue
                        vi = faces[f, j]
                        A[vi, 0] += bj * gx * gx
                        A[vi, 1] += bj * gx * gy
                        A[vi, 2] += bj * gy * gy
                        g[vi, 0] += bj * gx * r
                        g[vi, 1] += bj * gy * r
            if edge_w > 0.0:
                for j in range(3):
                    vi = faces[f, j]
                    for dj in range(1, 3):
                        vk = faces[f, (j + dj) % 3]
                        ex, ey, px, py = _edge_vectors(xi, phi, k, vi, vk)
                        if edge_vec:
                            # edge vectors: the displacement ξ − Φ is smooth over the mesh
                            A[vi, 0] += edge_w * edge_w
                            A[vi, 2] += edge_w * edge_w
                            g[vi, 0] += edge_w * edge_w * (ex - px)
                            g[vi, 1] += edge_w * edge_w * (ey - py)
                            continue
                        L = np.sqrt(ex * ex + ey * ey)
                        if L < 1e-9:
                            continue
                        L0 = np.sqrt(px * px + py * py)
                        re = edge_w * (L - L0)
                        jx = edge_w * ex / L
                        jy = edge_w * ey / L
                        A[vi, 0] += jx * jx
                        A[vi, 1] += jx * jy
                        A[vi, 2] += jy * jy
                        g[vi, 0] += jx * re
                        g[vi, 1] += jy * re
        for vi in range(V):
            a11 = A[vi, 0]
            a12 = A[vi, 1]
            a22 = A[vi, 2]
            det = a11 * a22 - a12 * a12
            if det < 1e-4:
                a11 += 1e-4
                a22 += 1e-4
                det = a11 * a22 - a12 * a12
            dx = -(a22 * g[vi, 0] - a12 * g[vi, 1]) / det
            dy = -(-a12 * g[vi, 0] + a11 * g[vi, 1]) / det
            if not (dx == dx):
                dx = 0.0
            if not (dy == dy):
                dy = 0.0
            step[k, vi, 0] = min(max(dx, -clamp), clamp)
            step[k, vi, 1] = min(max(dy, -clamp), clamp)


@njit(cache=True, nogil=True, parallel=True)
def face_blocks_kernel(buf, off, hh, ww, x0, y0, xi, phi, faces, pk, pf, omega, gain, bary, proxy,
                        C, edge_w, edge_vec, Hq, gq):
    """Full Gauss-Newton blocks of every visible (frame, face) pair q = (pk[q], pf[q]).

    The unknowns of face f at frame k are its corners' (u, v), ordered (u0, v0, u1, v1, u2, v2).
    Hq[q] (6, 6) = JᵀJ and gq[q] (6,) = Jᵀr of the residuals that live on that face: its S
    photometric residuals g_k·C_k(p) − P_fs (grey levels, weighted by omega[k, f]; corner a's
    Jacobian β_a g_k ∇C, so corners a, b are coupled by β_a β_b g_k² ∇C∇Cᵀ) and its 3 edge
    residuals, each edge (a, b) with the weight the Jacobi kernel gives it (vector: edge_w ·
    ((ξ_a − ξ_b) − (Φ_a − Φ_b)); length: edge_w · (|ξ_a − ξ_b| − |Φ_a − Φ_b|)). Summed over the faces this is the normal matrix of E·255² +
    edge term (:func:`_edge_energy_kernel`).
    """
    Q = pk.shape[0]
    S = bary.shape[0]
    for q in prange(Q):
        k = pk[q]
        f = pf[q]
        o = off[k]
        h = hh[k]
        w = ww[k]
        gk = gain[k]
        om = omega[k, f]
        for i in range(6):
            gq[q, i] = 0.0
            for j in range(6):
                Hq[q, i, j] = 0.0
        for s in range(S):
            u, v = _sample_pos(bary, s, xi, k, faces, f, x0, y0)
            r = gk * C[q, s] - proxy[f, s]
            gx, gy = _grad(buf, o, h, w, u, v, gk)
            for a in range(3):
                ba = om * bary[s, a]
                if ba == 0.0:
                    continue
                gq[q, 2 * a] += ba * gx * r
                gq[q, 2 * a + 1] += ba * gy * r
                for b in range(3):
                    bb = ba * bary[s, b]
                    if bb == 0.0:
                        continue
                    Hq[q, 2 * a, 2 * b] += bb * gx * gx
                    Hq[q, 2 * a, 2 * b + 1] += bb * gx * gy
                    Hq[q, 2 * a + 1, 2 * b] += bb * gy * gx
                    Hq[q, 2 * a + 1, 2 * b + 1] += bb * gy * gy
        if edge_w <= 0.0:
            continue
        w2 = edge_w * edge_w
        for a in range(3):
            b = (a + 1) % 3
            va = faces[f, a]
            vb = faces[f, b]
            ex, ey, px, py = _edge_vectors(xi, phi, k, va, vb)
            if edge_vec:
                dx = ex - px
                dy = ey - py
                for c in range(2):
                    Hq[q, 2 * a + c, 2 * a + c] += w2
                    Hq[q, 2 * b + c, 2 * b + c] += w2
                    Hq[q, 2 * a + c, 2 * b + c] -= w2
                    Hq[q, 2 * b + c, 2 * a + c] -= w2
                gq[q, 2 * a] += w2 * dx
                gq[q, 2 * a + 1] += w2 * dy
                gq[q, 2 * b] -= w2 * dx
                gq[q, 2 * b + 1] -= w2 * dy
                continue
            L = np.sqrt(ex * ex + ey * ey)
            if L < 1e-9:
                continue
            L0 = np.sqrt(px * px + py * py)
            re = edge_w * (L - L0)
            jj = (edge_w * ex / L, edge_w * ey / L)
            for c in range(2):
                gq[q, 2 * a + c] += jj[c] * re
                gq[q, 2 * b + c] -= jj[c] * re
                for d in range(2):
                    t = jj[c] * jj[d]
                    Hq[q, 2 * a + c, 2 * a + d] += t
                    Hq[q, 2 * b + c, 2 * b + d] += t
                    Hq[q, 2 * a + c, 2 * b + d] -= t
                    Hq[q, 2 * b + c, 2 * a + d] -= t


@njit(cache=True, nogil=True, parallel=True)
def _edge_energy_kernel(xi, phi, faces, fvis, edge_w, edge_vec, out):
    """out[k] = Σ_{f visible at k} Σ_{edges (a, b) of f} |edge residual / 255|² (the residuals
    of the Gauss-Newton kernels: 3 per visible face, an edge shared by two visible faces counts
    twice, as it does in the Jacobi kernel)."""
    K = xi.shape[0]
    nF = faces.shape[0]
    for k in prange(K):
        e = 0.0
        for f in range(nF):
            if not fvis[k, f]:
                continue
            for a in range(3):
                va = faces[f, a]
                vb = faces[f, (a + 1) % 3]
                ex, ey, px, py = _edge_vectors(xi, phi, k, va, vb)
                if edge_vec:
                    r2 = (ex - px) ** 2 + (ey - py) ** 2
                else:
                    r2 = (np.sqrt(ex * ex + ey * ey) - np.sqrt(px * px + py * py)) ** 2
                e += r2 * (edge_w / 255.0) ** 2
        out[k] = e


class PhotometricTerm:
    """The photometric term of one level: samples, proxy colours, per-(frame, face) errors, weights.

    E(ξ) = Σ_{k, f visible at k} ρ(e_kf) / 255², e_kf = Σ_s (g_k·C_k(p_kfs) − P_fs)² (grey
    levels²), with the proxy P recomputed at ξ. ``robust_grey`` c = 0: ρ(e) = e and every weight
    is 1 — Eq. 1 exactly. c > 0: ρ(e) = S c² e / (S c² + e) (Geman-McClure on the face's
    residuals; ≈ e while their RMS is well under c, bounded by S c² above), and both the
    Gauss-Newton residuals and the proxy are weighted by ω_kf = ρ'(e_kf) = (1 + e_kf / (S c²))⁻²
    — a face whose appearance at k disagrees with the other frames (a wrinkle, a tint, a
    specularity) stops pulling ξ and stops colouring the proxy; the proxy is the weighted mean
    after one reweighting pass (weights from the residuals against the unweighted proxy), so E
    stays a function of ξ. g_k = ``gain`` [k] (1 unless ``gain`` 'frame', see :meth:`set_gain`).

    Each evaluation samples the crops once (C and the mask test for every visible pair and
    sample, :func:`_sample_kernel`); proxies and errors are reductions of those samples.
    """

    def __init__(self, stack, faces, fvis, fw, bary, params):
        self.stack, self.faces, self.fvis, self.bary = stack, faces, fvis, bary
        self.bg = float(params["background_weight"])
        c = float(params.get("robust_grey", 0.0))
        self.c2 = c * c * bary.shape[0]
        self.gain_mode = params.get("gain", "none")
        self.face_model = FACE_PHOTOMETRIC.index(params.get("face_photometric", "none"))
        self.gain = np.ones(fvis.shape[0])
        # visible (frame, face) pairs, frame-major; and the same pairs grouped by face
        self.pk, self.pf = (a.astype(np.int64) for a in np.nonzero(fvis))
        self.qs = np.searchsorted(self.pk, np.arange(fvis.shape[0] + 1)).astype(np.int64)  # frame k's
        self.order = np.argsort(self.pf, kind="stable").astype(np.int64)
        self.fstart = np.searchsorted(self.pf[self.order], np.arange(faces.shape[0] + 1)).astype(np.int64)
        self.fw = np.ascontiguousarray(fw[self.pk, self.pf], np.float64)
        self.ones = np.ones(len(self.pk))

    def samples(self, xi):
        """(C (Q, S) float32 grey levels, inside (Q, S) bool) at ``xi`` (K, V, 2)."""
        st = self.stack
        Q, S = len(self.pk), self.bary.shape[0]
        C = np.zeros((Q, S), np.float32)
        inside = np.zeros((Q, S), np.bool_)
        if Q:
            _sample_kernel(st.blur, st.mask, st.off, st.h, st.w, st.x0, st.y0, xi, self.faces,
                           self.pk, self.pf, self.bary, C, inside)
        return C, inside

    def proxy(self, C, inside, omega_q) -> np.ndarray:
        P = np.zeros((self.faces.shape[0], self.bary.shape[0]))
        if len(self.pk):
            _proxy_kernel(C, inside, self.order, self.fstart, self.pk, self.fw * omega_q, self.gain,
                          self.bg, P)
        return P

    def face_err(self, C, P) -> np.ndarray:
        e = np.zeros(len(self.pk))
        if len(self.pk):
            _face_err_kernel(C, self.pk, self.pf, self.gain, P, self.face_model, e)
        return e

    def weights(self, e) -> np.ndarray:
        """(Q,) robust weights of the pairs from their errors e (Q,)."""
        return self.ones if self.c2 <= 0 else 1.0 / (1.0 + e / self.c2) ** 2

    def dense(self, omega_q) -> np.ndarray:
        """(K, F) weights (0 where the face is not visible) from the (Q,) pair weights."""
        out = np.zeros(self.fvis.shape)
        out[self.pk, self.pf] = omega_q
        return out

    def evaluate(self, xi):
        """(P (F, S) proxy, E float, omega (K, F) weights, C (Q, S) samples) at ``xi`` (K, V, 2)."""
        C, inside = self.samples(xi)
        P = self.proxy(C, inside, self.ones)
        if self.c2 > 0:
            P = self.proxy(C, inside, self.weights(self.face_err(C, P)))
        e = self.face_err(C, P)
        rho = e if self.c2 <= 0 else self.c2 * e / (self.c2 + e)
        return P, float(rho.sum()) / 255.0**2, self.dense(self.weights(e)), C

    def set_gain(self, xi, max_iterations: int = 100, tol: float = 1e-5) -> None:
        """``gain`` 'frame': alternate g_k = the half-sample mode over the frame's visible faces
        (all samples inside the foreground mask) of Σ_s P_fs / Σ_s C_k(p) with the face sums
        Σ_s P_fs recomputed from the new gains (weighted mean of g_k Σ_s C_k over those pairs),
        normalised to geometric mean 1 over the frames (frames with fewer than 10 such faces
        take 1 before that normalisation, so they share its factor), until no gain moves by more
        than ``tol``. An exposure /
        white-balance change of the whole frame then stops looking like motion, while a local
        change of appearance (a wrinkle, a tint: a minority of the faces) does not move the mode.
        Starts from ``stack.gain`` when it holds one per frame and stores the result there.

        Run to convergence, not a fixed two rounds: each face's proxy averages the frames that
        see it, which are neighbours in time, so a gain error spreads to the neighbouring frames'
        estimates and decays slowly (docs/decisions/texcoords.md)."""
        K = self.fvis.shape[0]
        g0 = self.stack.gain
        if self.gain_mode != "frame" or not len(self.pk):
            self.gain = np.ones(K)
            return
        self.gain = np.array(g0, np.float64) if g0 is not None and len(g0) == K else np.ones(K)
        C, inside = self.samples(xi)
        a = C.sum(1, dtype=np.float64)
        use = inside.all(1) & (a > 0)
        # face-level sums: Σ_s P_fs over the fully inside pairs, so one round costs O(pairs)
        wq = np.where(use, self.fw, 0.0)
        F = self.faces.shape[0]
        den = np.bincount(self.pf, wq, F)
        for _ in range(int(max_iterations)):
            b = (np.bincount(self.pf, wq * self.gain[self.pk] * a, F) / np.maximum(den, 1e-300))[self.pf]
            ok = use & (b > 0)
            g = np.ones(K)
            ratio = np.where(ok, b / np.where(a > 0, a, 1.0), np.nan)
            for k in range(K):
                r = ratio[self.qs[k]:self.qs[k + 1]]
                r = r[np.isfinite(r)]
                if len(r) >= 10:
                    g[k] = _half_sample_mode(r)
            g /= np.exp(np.mean(np.log(g)))
            change = float(np.abs(g - self.gain).max())
            self.gain = g
            if change < tol:
                break
        self.stack.gain = self.gain.copy()


def _half_sample_mode(x) -> float:
    """Half-sample mode (Bickel & Frühwirth 2006) of a 1-D sample, the densest value: the shortest
    half of the sorted sample, halved again until 3 values remain, averaged. Unlike the median it
    is not dragged by a large minority that moved one way (wrinkles darkening a third of the
    visible faces)."""
    v = np.sort(np.asarray(x, np.float64))
    while len(v) > 3:
        h = (len(v) + 1) // 2
        i = int(np.argmin(v[h - 1:] - v[:len(v) - h + 1]))
        v = v[i:i + h]
    return float(v.mean())


def vertex_used(fvis, faces, n_vertices):
    """(K, V) bool: the vertex is a corner of a face visible at that frame."""
    used = np.zeros((fvis.shape[0], n_vertices), bool)
    for j in range(3):
        for k in range(fvis.shape[0]):
            used[k, faces[fvis[k], j]] = True
    return used


def gauge_weights(fvis, fw, faces, used, gauge: str) -> np.ndarray:
    """(K, V) float64 weight of each (frame, vertex) in the gauge's mean displacement: 1 where
    the vertex is ``used`` (a corner of a visible face; 'mean'), or the mean proxy weight (cosine)
    of its visible faces ('weighted'); 0 elsewhere."""
    if gauge != "weighted":
        return used.astype(np.float64)
    K, V = used.shape
    num = np.zeros((K, V))
    cnt = np.zeros((K, V))
    w = np.where(fvis, fw, 0.0)
    for j in range(3):
        for k in range(K):
            num[k] += np.bincount(faces[:, j], w[k], V)
            cnt[k] += np.bincount(faces[:, j], fvis[k], V)
    return num / np.maximum(cnt, 1)


def edge_energy(xi, phi, faces, fvis, edge_w, edge_vec) -> float:
    """The edge term of the Gauss-Newton kernels, / 255² (:func:`_edge_energy_kernel`)."""
    out = np.zeros(xi.shape[0])
    if faces.shape[0] and xi.shape[0] and edge_w > 0:
        _edge_energy_kernel(xi, phi, faces, fvis, float(edge_w), bool(edge_vec), out)
    return float(out.sum())


class SparseSystems:
    """Per-frame sparse Gauss-Newton systems of one level (fixed pattern, values per step).

    Frame k's unknowns are the (u, v) of the vertices used at k (corner of a visible face), in
    vertex order: unknown 2·loc[k, v] + c. The (frame, face) blocks of :func:`face_blocks_kernel`
    are summed into one CSC matrix per frame through a pattern built once per level.
    """

    def __init__(self, faces, pk, pf, qs, used):
        K = used.shape[0]
        self.pk, self.pf, self.qs = pk, pf, qs   # the visible pairs, frame-major (PhotometricTerm)
        self.verts = [np.flatnonzero(used[k]) for k in range(K)]
        loc = np.full(used.shape, -1, np.int64)
        for k in range(K):
            loc[k, self.verts[k]] = np.arange(len(self.verts[k]))
        corner = loc[self.pk[:, None], faces[self.pf]]                       # (Q, 3)
        rows6 = (2 * corner[:, :, None] + np.arange(2)).reshape(-1, 6)       # (Q, 6)
        self.pattern = []
        for k in range(K):
            n = 2 * len(self.verts[k])
            r6 = rows6[self.qs[k]:self.qs[k + 1]]
            rr = np.broadcast_to(r6[:, :, None], (len(r6), 6, 6)).ravel()
            cc = np.broadcast_to(r6[:, None, :], (len(r6), 6, 6)).ravel()
            key, inv = np.unique(cc * max(n, 1) + rr, return_inverse=True)   # column-major
            indices = (key % max(n, 1)).astype(np.int32)
            indptr = np.searchsorted(key // max(n, 1), np.arange(n + 1)).astype(np.int32)
            diag = np.flatnonzero(indices == (key // max(n, 1)))
            self.pattern.append((n, inv, indices, indptr, diag, r6.ravel()))
        self.factorisations = 0

    def solve(self, Hq, gq, lam: float, out) -> None:
        """out[k, verts[k]] = −(H_k + lam·(D_k + mean(D_k)·I) + 1e-4·I)⁻¹ g_k for every frame k,
        D_k = diag(H_k) (Levenberg-Marquardt damping; the mean term also damps vertices whose
        own diagonal is tiny — untextured, barely constrained; 1e-4 as the Jacobi kernel's
        singularity guard). Hq (Q, 6, 6), gq (Q, 6): :func:`face_blocks_kernel`. Direct sparse
        LU (SuperLU, symmetric mode, minimum-degree ordering on A + Aᵀ), one frame at a time:
        reusing a frame's factors as the preconditioner of later solves needed fewer
        factorisations but kept K factors in memory and did not make the stage faster
        (docs/decisions/texcoords.md)."""
        for k, (n, inv, indices, indptr, diag, r6) in enumerate(self.pattern):
            if n == 0:
                continue
            q0, q1 = self.qs[k], self.qs[k + 1]
            data = np.bincount(inv, weights=Hq[q0:q1].ravel(), minlength=len(indices))
            b = -np.bincount(r6, weights=gq[q0:q1].ravel(), minlength=n)
            d = data[diag]
            data[diag] = d + lam * (d + d.mean()) + 1e-4
            A = csc_matrix((data, indices, indptr), shape=(n, n))
            lu = splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
            self.factorisations += 1
            out[k, self.verts[k]] = lu.solve(b).reshape(-1, 2)

    def model_decrease(self, Hq, gq, faces, step) -> float:
        """−(2 gᵀs + sᵀHs) / 255²: the decrease of the objective Σ r² / 255² that the Gauss-Newton
        model r + Js (proxy and weights fixed; g = Jᵀr, H = JᵀJ) predicts for ``step`` (K, V, 2)."""
        sq = step[self.pk[:, None], faces[self.pf]].reshape(-1, 6)
        d = -(2.0 * np.einsum("qi,qi->", gq, sq) + np.einsum("qi,qij,qj->", sq, Hq, sq))
        return float(d) / 255.0**2


