"""Gradient-domain colour correction of texture-volume slices (Kim et al. 2021 §5, after
Prada et al. 2018, the authors' ``TextureStitching``).

What it computes
----------------
A slice stitches texels sampled from different source frames (its label map), and their
exposure / white balance / shading differ: steps appear along label boundaries, and along atlas
chart seams (one 3-D edge, two places in the atlas). :class:`CorrectionSystem` removes them with
a screened Poisson solve over the covered texels, per colour channel:

    minimise  Σ_(p,q) w (f_p − f_q − g_pq)²  +  λ Σ_p (f_p − f0_p)²  [ +  μ Σ_(p borrowed) (f_p − f_prev,p)² ]

- f0 is the slice, f the result.
- (p, q) runs over two kinds of pairs:
  1. 4-neighbour texel pairs inside one chart, with g_pq = f0_p − f0_q when p and q have the same
     source label (gradient copied). Across a label boundary or where a texel has no label,
     ``boundary_gradient`` decides:
     - ``'zero'``: g_pq = 0, as ``TextureStitching`` does (``official_code_notes.md`` §2.6). The
       step between the two sources goes, but so does the texture's own slope there: a colour
       ramp or an edge of the object's appearance that crosses the boundary is flattened on the
       pair and, by the spread of the solve, around it.
     - ``'one_sided'`` (default): g_pq = the mean of the same-label gradients along the same axis
       just before p and just after q (those that exist and are not themselves across a
       boundary), 0 if neither does. The ramp continues through the boundary and only the step
       between the sources is removed (measured in docs/decisions/correction.md);
  2. seam couplings: each 3-D edge shared by two faces whose UV edges differ is sampled at about
     one point per texel of its UV length; each sample gives a row (bilinear value of f at the
     point in chart 1) − (bilinear value at the same 3-D point in chart 2) with target 0
     (continuity) and weight ``seam_weight``. Bilinear stencils use only covered texels of the
     edge's own chart (weights renormalised).
- λ (screening) sets how far a correction spreads: a step decays over about 1/√λ texels.
  It is given resolution-independently as ``screen_length`` (fraction of the atlas side;
  λ = 1 / (screen_length · W)²; default 1/64, i.e. 64 texels at 4096², 4 at 256²).
- The matrix A = Gᵀ W G + λ I (+ seam rows) depends only on the atlas, never on the labels or
  colours, so it is built and its pyamg classical (Ruge-Stüben) AMG hierarchy set up **once per
  atlas** and reused for every channel and slice (set up on first use: with ``keep_own_frame``
  a slice with texels of its own frame solves a smaller system of its own, below). Classical rather than smoothed aggregation:
  its setup is deterministic (smoothed aggregation estimates a spectral radius from a random
  vector, so two runs differ), and it is faster to set up and per solve
  (docs/decisions/correction.md).
  Per slice only the right-hand side changes: the solve is for the correction c = f − f0,
  ``A c = −Gᵀ d_cross − w_s SᵀS f0`` (d_cross the colour differences of boundary pairs minus
  their guidance g_pq), warm-started at 0, CG-accelerated V-cycles to a relative residual
  ``tol``, the three channels together (:func:`stex.multigrid.cg_solve`: pyamg's solutions bit
  for bit, each sparse product reading the matrix once for the three).
- Texels without a label (covered, but their face had no source frame) keep no gradients: they
  are screened towards their (filled) value and otherwise interpolated smoothly from their
  surroundings.

Reduced resolution (``factor`` k > 1)
-------------------------------------
The correction c is smooth *inside* each label region but jumps at label boundaries, so a plain
upsampling would put back the steps. With k > 1 the system is built on the atlas rasterised at
W/k (the same texcoords, :func:`stex.template.texel_map`, with its own seams), and per slice:

1. each coarse texel takes the **majority label** of the fine texels of its chart in its k×k
   block and the mean colour of those fine texels (so coarse gradients are never mixed across
   a label boundary);
2. the coarse correction is solved (λ, μ scaled by k² so the spread in fine texels is the same);
3. each fine texel takes the bilinear interpolation of the coarse correction over the (up to 4)
   nearest coarse texels of **its own chart and label** (weights renormalised), falling back to
   its chart's texels of any label, then to the nearest same-chart texel within 2 coarse texels.

So the jump lands on the fine label boundary. Slivers of a label narrower than ~k texels borrow
a neighbouring label's correction (a residual step there). Measured in
``benchmarks/bench_volume.py`` and ``tests/test_correction.py``.

Keeping the observed texels (``keep_own_frame``, default)
---------------------------------------------------------
Slice t is the texture at time t, and where frame t itself saw the surface it is that
observation. With ``correct(..., frame=t)`` the texels labelled t are held at c = 0 (a Dirichlet
boundary instead of the screening towards f0 alone) and only the borrowed texels are solved for,
so each step at a boundary of the own frame's region goes entirely to the borrowed side. The free
texels change with every slice, so their system gets an AMG hierarchy of its own per slice. At
k > 1 a coarse texel is kept when its majority label is t, and every fine texel labelled t is
skipped by the upsampling. The screened solve of both sides (the paper's) pulled the observed
texels half-way towards their borrowed neighbours; keeping them raised the input-view PSNR
(docs/decisions/correction.md). Slices whose frame is not a source (held-out frames) have no own texels
and are solved as before.

Temporal coupling (option)
--------------------------
``correct(..., previous=prev, frame=t)`` adds μ Σ (f_p − prev_p)² on *borrowed* texels (label ≥ 0
and ≠ t, i.e. colours taken from another frame; all labelled texels if ``frame`` is None),
``prev`` being the previous frame's corrected slice. The low frequencies of borrowed regions then
follow the previous output (decay length 1/√μ texels) while their details still come from the
current gradients: this damps the frame-to-frame flicker of regions re-borrowed from changing
source frames (the paper's stated limitation). The diagonal μ term makes the matrix
label-dependent, so this solve runs scipy CG on (A + D) preconditioned by the *fixed* AMG
hierarchy of A (still no per-slice setup). Default μ: ``temporal_length`` = 1/256 of the atlas
side; ``temporal_length=None`` disables it.

After the solve the gutter is re-filled from the corrected texels (:func:`stex.sampling.fill_gutter`).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp
from numba import njit

from stex.sampling import fill_gutter
from stex.atlas import texel_map, uv_charts
from stex.mesh import face_adjacency
from stex.multigrid import cg_solve, supported
from stex.texel_graph import texel_graph

log = logging.getLogger("stex.correction")

__all__ = ["CorrectionSystem", "label_boundary_step", "interior_change", "seam_step"]


BOUNDARY_GRADIENTS = ("zero", "one_sided")


# --------------------------------------------------------------------------------------------
# the texel graph of one atlas resolution
# --------------------------------------------------------------------------------------------

class _Graph:
    """Unknowns, pairs, seam rows (:func:`stex.texel_graph.texel_graph`), matrix and AMG
    hierarchy of one atlas rasterisation."""

    def __init__(self, texel_face, face_chart, texcoords, texcoord_faces, faces, pairs, edges,
                 lam, seam_weight, amg_kwargs):
        t0 = time.perf_counter()
        tg = texel_graph(texel_face, face_chart, texcoords, texcoord_faces, faces, pairs, edges)
        self.W, self.covered, self.index, self.idx, self.chart_tex = tg.W, tg.covered, tg.index, tg.idx, tg.chart_tex
        self.n = tg.n
        self.p, self.q, self.before, self.after = tg.p, tg.q, tg.before, tg.after
        self.S, self.n_seam_edges, self.n_seam_dropped = tg.S, tg.n_seam_edges, tg.n_seam_dropped
        self.seam_weight = float(seam_weight)
        self.lam = float(lam)
        self.A = tg.laplacian(self.seam_weight, self.lam)
        t1 = time.perf_counter()
        self.amg_kwargs = dict(amg_kwargs or {})
        self._ml = None
        self.timings = {"graph_s": t1 - t0}
        log.info("correction: %d^2 atlas, %d unknowns, %d pairs, %d seam rows; graph %.1f s",
                 self.W, self.n, len(self.p), self.S.shape[0], t1 - t0)

    @property
    def ml(self):
        """A's AMG hierarchy, set up on first use: slices with texels kept at their own frame
        solve a system of their own, so a block of such slices never needs it."""
        if self._ml is None:
            # pyamg is slow to import; only the solve needs it
            import pyamg

            t0 = time.perf_counter()
            self._ml = pyamg.ruge_stuben_solver(self.A, **self.amg_kwargs)
            self.timings["amg_setup_s"] = time.perf_counter() - t0
            log.info("correction: AMG setup of the whole system %.1f s (%d levels)",
                     self.timings["amg_setup_s"], len(self._ml.levels))
        return self._ml

    def solve(self, f0, lab, prev=None, borrowed=None, mu=0.0, tol=1e-4, maxiter=50,
              boundary_gradient="one_sided", kept=None):
        """Correction c (n, 3) for values f0 (n, 3) float64 and labels lab (n,); ``kept`` (n,)
        bool: unknowns held at c = 0 (Dirichlet), the others solved with them as boundary."""
        n = self.n
        lp, lq = lab[self.p], lab[self.q]
        cross = (lp != lq) | (lp < 0) | (lq < 0)
        pc, qc = self.p[cross], self.q[cross]
        d = f0[pc] - f0[qc]                                   # (m, 3) differences to remove
        if boundary_gradient == "one_sided":
            # the guidance across a label boundary continues the same-label gradients on either
            # side (the mean of those that exist) instead of being 0: a colour ramp of the texture
            # that crosses the boundary is kept, the step between the two sources still removed
            side, count = np.zeros_like(d), np.zeros(len(pc))
            for nb in (self.before[cross], self.after[cross]):
                at = np.flatnonzero(nb >= 0)
                at = at[~cross[nb[at]]]                   # that neighbour lies inside one label
                side[at] += f0[self.p[nb[at]]] - f0[self.q[nb[at]]]
                count[at] += 1.0
            d -= side / np.maximum(count, 1.0)[:, None]
        rhs = np.empty((n, 3))
        for ch in range(3):
            rhs[:, ch] = np.bincount(qc, d[:, ch], n) - np.bincount(pc, d[:, ch], n)
        if self.S.shape[0]:
            rhs -= self.seam_weight * (self.S.T @ (self.S @ f0))
        c = np.zeros((n, 3))
        iters = []
        use_prev = prev is not None and mu > 0 and borrowed is not None and borrowed.any()
        D = np.where(borrowed, mu, 0.0) if use_prev else None
        if kept is not None and kept.any():
            # c = 0 on the kept unknowns: the system of the free ones (their coupling to the kept
            # ones only leaves the diagonal), with an AMG hierarchy of its own, since which
            # unknowns are free changes with every slice (pyamg is imported here: slow to import)
            import pyamg

            idx = np.flatnonzero(~kept)
            if len(idx) == 0:
                return c, iters
            A = self.A if D is None else self.A + sp.diags(D)
            ml = pyamg.ruge_stuben_solver(A[idx][:, idx].tocsr(), **self.amg_kwargs)
        elif D is not None:
            # the diagonal makes the matrix label-dependent: CG preconditioned by A's hierarchy
            from scipy.sparse.linalg import cg

            A2 = (self.A + sp.diags(D)).tocsr()
            M = self.ml.aspreconditioner(cycle="V")
            for ch in range(3):
                b = rhs[:, ch] + D * (prev[:, ch] - f0[:, ch])
                if not b.any():
                    continue
                count = [0]

                def cb(_x, count=count):
                    count[0] += 1

                c[:, ch], _ = cg(A2, b, x0=np.zeros(n), rtol=tol, maxiter=maxiter, M=M, callback=cb)
                iters.append(count[0])
            return c, iters
        else:
            idx, ml = slice(None), self.ml
        bs = {}
        for ch in range(3):
            b = rhs[idx, ch] if D is None else rhs[idx, ch] + D[idx] * (prev[idx, ch] - f0[idx, ch])
            if b.any():
                bs[ch] = b
        if bs and supported(ml):
            # the channels in one block: the same solution as one ml.solve per channel, bit for bit
            x, its = cg_solve(ml, np.stack(list(bs.values())), tol, maxiter)
            for k, ch in enumerate(bs):
                c[idx, ch] = x[k]
            return c, [int(i) for i in its]
        for ch, b in bs.items():
            res = []
            c[idx, ch] = ml.solve(b, x0=np.zeros(len(b)), tol=tol, accel="cg", maxiter=maxiter,
                                  residuals=res)
            iters.append(len(res) - 1)
        return c, iters


# --------------------------------------------------------------------------------------------
# coarse <-> fine (reduced resolution)
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _downsample(k, c_cov_r, c_cov_c, c_chart, f_chart, f_lab, img, prev, has_prev):
    """Per coarse covered texel: majority label of the same-chart fine texels of its k x k block,
    mean colour of those texels (of the whole block if it has none), same for prev."""
    n = c_cov_r.shape[0]
    W = f_chart.shape[0]
    lab = np.full(n, -1, np.int32)
    f0 = np.zeros((n, 3))
    pv = np.zeros((n, 3))
    labs = np.empty(k * k, np.int32)
    for i in range(n):
        R = c_cov_r[i]
        C = c_cov_c[i]
        ch = c_chart[i]
        m = 0
        for r in range(R * k, min(R * k + k, W)):
            for c in range(C * k, min(C * k + k, W)):
                if f_chart[r, c] == ch and f_lab[r, c] >= 0:
                    labs[m] = f_lab[r, c]
                    m += 1
        best = -1
        bestn = 0
        for a in range(m):
            cnt = 0
            for b in range(m):
                if labs[b] == labs[a]:
                    cnt += 1
            if cnt > bestn or (cnt == bestn and labs[a] < best):
                bestn = cnt
                best = labs[a]
        lab[i] = best
        # Mean over the block's fine texels of this chart with that label; if there are none,
        # over the whole block.
        for whole in range(2):
            cnt = 0
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            q0 = 0.0
            q1 = 0.0
            q2 = 0.0
            for r in range(R * k, min(R * k + k, W)):
                for c in range(C * k, min(C * k + k, W)):
                    if whole == 1 or (f_chart[r, c] == ch and f_lab[r, c] == best):
                        s0 += img[r, c, 0]
                        s1 += img[r, c, 1]
                        s2 += img[r, c, 2]
                        if has_prev:
                            q0 += prev[r, c, 0]
                            q1 += prev[r, c, 1]
                            q2 += prev[r, c, 2]
                        cnt += 1
            if cnt > 0:
                break
        f0[i, 0] = s0 / cnt
        f0[i, 1] = s1 / cnt
        f0[i, 2] = s2 / cnt
        pv[i, 0] = q0 / cnt
        pv[i, 1] = q1 / cnt
        pv[i, 2] = q2 / cnt
    return lab, f0, pv


@njit(cache=True, nogil=True)
def _upsample_apply(k, f_rows, f_cols, f_chart_v, f_lab, c_idx, c_chart, c_lab, corr, img, kept_label):
    """Add the coarse correction to the fine covered texels of ``img`` (uint8, in place, rounded
    and clamped): bilinear over same-chart same-label coarse texels, then same-chart any label,
    then nearest same-chart within 2 coarse texels (else no change). Fine texels labelled
    ``kept_label`` stay as they are (-2: none), also inside a coarse texel of another majority
    label."""
    n = f_rows.shape[0]
    Wc = c_idx.shape[0]
    cv = np.zeros(3)
    for i in range(n):
        r = f_rows[i]
        c = f_cols[i]
        ch = f_chart_v[i]
        l = f_lab[r, c]
        if l == kept_label:
            continue
        cv[0] = 0.0
        cv[1] = 0.0
        cv[2] = 0.0
        x = (c + 0.5) / k - 0.5
        y = (r + 0.5) / k - 0.5
        c0 = int(np.floor(x))
        r0 = int(np.floor(y))
        a = x - c0
        b = y - r0
        done = False
        for mode in range(2):
            ws = 0.0
            v0 = 0.0
            v1 = 0.0
            v2 = 0.0
            for dr in range(2):
                for dc in range(2):
                    rr = r0 + dr
                    cc = c0 + dc
                    if rr < 0 or rr >= Wc or cc < 0 or cc >= Wc:
                        continue
                    j = c_idx[rr, cc]
                    if j < 0 or c_chart[j] != ch:
                        continue
                    if mode == 0 and c_lab[j] != l:
                        continue
                    w = (a if dc == 1 else 1.0 - a) * (b if dr == 1 else 1.0 - b)
                    ws += w
                    v0 += w * corr[j, 0]
                    v1 += w * corr[j, 1]
                    v2 += w * corr[j, 2]
            if ws > 1e-6:
                cv[0] = v0 / ws
                cv[1] = v1 / ws
                cv[2] = v2 / ws
                done = True
                break
        best = -1
        bd = 1e30
        if done:
            rc = -100  # skip the search
        else:
            rc = int(np.floor(y + 0.5))
        cc0 = int(np.floor(x + 0.5))
        for rr in range(rc - 2, rc + 3):
            for cc in range(cc0 - 2, cc0 + 3):
                if rr < 0 or rr >= Wc or cc < 0 or cc >= Wc:
                    continue
                j = c_idx[rr, cc]
                if j < 0 or c_chart[j] != ch:
                    continue
                d = (rr - y) ** 2 + (cc - x) ** 2
                if d < bd:
                    bd = d
                    best = j
        if best >= 0:
            cv[0] = corr[best, 0]
            cv[1] = corr[best, 1]
            cv[2] = corr[best, 2]
        for q in range(3):
            x = np.floor(img[r, c, q] + cv[q] + 0.5)
            img[r, c, q] = np.uint8(min(max(x, 0.0), 255.0))


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------

class CorrectionSystem:
    """The colour-correction solver of one atlas (built once, reused for every slice).

    Args:
        texel_face: (W, W) int32 face per texel, -1 = empty (template ``texel/face_id``).
        texcoords: (Vt, 2) float texcoords, texcoord_faces: (F, 3) int (template).
        faces: (F, 3) int vertex indices (template ``faces``).
        adjacency_pairs, adjacency_edges: template ``adjacency/pairs`` and ``adjacency/edges``
            ((E, 2) each); computed with :func:`stex.template.face_adjacency` when None.
        face_chart: (F,) chart of each face (template ``face_chart``); computed when None.
        factor: solve at W / factor (1 = full resolution; W must be divisible by it).
        screen_length: spread of a correction, fraction of the atlas side (λ = 1/(screen_length·W)²).
        seam_weight: weight of a seam-continuity sample relative to a texel pair.
        temporal_length: spread of the temporal coupling, fraction of the atlas side
            (μ = 1/(temporal_length·W)²); None = no temporal coupling.
        tol: relative residual of the solve; maxiter: iteration cap per channel.
        gutter_px: rings of gutter re-filled from the corrected texels.
        amg_kwargs: extra arguments for ``pyamg.ruge_stuben_solver``.
        boundary_gradient: guidance of a texel pair across a label boundary: ``'one_sided'``
            (ours, default) continues the same-label gradients on either side; ``'zero'`` (the
            authors' ``TextureStitching``) flattens it.
        keep_own_frame: texels sampled from the slice's own frame (``correct(..., frame=t)``)
            keep their colour (c = 0 there) and only borrowed texels are corrected, towards
            them.
    """

    def __init__(self, texel_face, texcoords, texcoord_faces, faces, adjacency_pairs=None,
                 adjacency_edges=None, face_chart=None, *, factor: int = 1,
                 screen_length: float = 1 / 64, seam_weight: float = 1.0,
                 temporal_length: float | None = 1 / 256, tol: float = 1e-4, maxiter: int = 50,
                 gutter_px: int = 4, amg_kwargs: dict | None = None,
                 boundary_gradient: str = "one_sided", keep_own_frame: bool = True):
        tf = np.asarray(texel_face)
        if tf.ndim != 2 or tf.shape[0] != tf.shape[1]:
            raise ValueError(f"texel_face must be (W, W), got {tf.shape}")
        W = tf.shape[0]
        factor = int(factor)
        if factor < 1 or W % factor:
            raise ValueError(f"factor must be a positive divisor of W={W}, got {factor}")
        self.W, self.factor = W, factor
        self.texel_face = tf
        self.covered = tf >= 0
        faces = np.asarray(faces)
        tfaces = np.asarray(texcoord_faces)
        if face_chart is None:
            face_chart = uv_charts(tfaces, len(texcoords))
        self.face_chart = np.asarray(face_chart, np.int32)
        if adjacency_pairs is None or adjacency_edges is None:
            adjacency_pairs, adjacency_edges = face_adjacency(faces)
        self.chart_tex = np.where(self.covered, self.face_chart[np.maximum(tf, 0)], -1).astype(np.int32)
        Wg = W // factor
        self.lam = 1.0 / (screen_length * W) ** 2 * factor ** 2
        self.mu = 0.0 if temporal_length is None else 1.0 / (temporal_length * W) ** 2 * factor ** 2
        self.tol, self.maxiter, self.gutter_px = float(tol), int(maxiter), int(gutter_px)
        if boundary_gradient not in BOUNDARY_GRADIENTS:
            raise ValueError(f"boundary_gradient must be one of {BOUNDARY_GRADIENTS}, got {boundary_gradient!r}")
        self.boundary_gradient = boundary_gradient
        self.keep_own_frame = bool(keep_own_frame)
        grid_face = tf if factor == 1 else texel_map(texcoords, tfaces, Wg)[0]
        self.graph = _Graph(grid_face, self.face_chart, texcoords, tfaces, faces, adjacency_pairs,
                            adjacency_edges, self.lam, seam_weight, amg_kwargs)
        self.timings = self.graph.timings   # the same dict: the AMG setup is added on first use
        if factor > 1:
            g = self.graph
            self._c_rows, self._c_cols = np.divmod(g.index, Wg)
            self._c_chart = g.chart_tex.ravel()[g.index].astype(np.int32)
            f_index = np.flatnonzero(self.covered.ravel())
            self._f_rows, self._f_cols = (a.astype(np.int32) for a in np.divmod(f_index, W))
            self._f_chart = self.chart_tex.ravel()[f_index]
        self.last_stats: dict = {}

    @property
    def n_unknowns(self) -> int:
        return self.graph.n

    def correct(self, slice_, label_map, previous=None, frame: int | None = None):
        """Colour-correct one slice.

        Args:
            slice_: (W, W, 3) uint8 slice (:func:`stex.volume.volume_slice`).
            label_map: (W, W) int32 source frame per texel, -1 = none.
            previous: optional (W, W, 3) uint8, the previous frame's corrected slice, for the
                temporal coupling (ignored when the system has no temporal coupling).
            frame: this slice's own frame index (texels labelled with it are not borrowed).

        Returns:
            (W, W, 3) uint8 corrected slice; gutter re-filled. ``self.last_stats`` holds the
            iteration counts and timings of the call.
        """
        t0 = time.perf_counter()
        W = self.W
        img = np.asarray(slice_)
        lm = np.asarray(label_map, np.int32)
        if img.shape != (W, W, 3) or lm.shape != (W, W):
            raise ValueError(f"expected slice ({W}, {W}, 3) and label map ({W}, {W}), got "
                             f"{img.shape}, {lm.shape}")
        g = self.graph
        use_prev = previous is not None and self.mu > 0
        if use_prev:
            prev = np.asarray(previous)
            if prev.shape != (W, W, 3):
                raise ValueError(f"previous must be ({W}, {W}, 3), got {prev.shape}")
        if self.factor == 1:
            flat = img.reshape(-1, 3)
            f0 = flat[g.index].astype(np.float64)
            lab = lm.ravel()[g.index]
            pv = prev.reshape(-1, 3)[g.index].astype(np.float64) if use_prev else None
        else:
            lab, f0, pv = _downsample(self.factor, self._c_rows, self._c_cols, self._c_chart,
                                      self.chart_tex, lm, np.ascontiguousarray(img),
                                      np.ascontiguousarray(prev) if use_prev else img, use_prev)
            if not use_prev:
                pv = None
        borrowed = None
        if use_prev:
            borrowed = (lab >= 0) & ((lab != frame) if frame is not None else True)
        keep = self.keep_own_frame and frame is not None
        t1 = time.perf_counter()
        corr, iters = g.solve(f0, lab, pv, borrowed, self.mu, self.tol, self.maxiter,
                              self.boundary_gradient, kept=(lab == frame) if keep else None)
        t2 = time.perf_counter()
        out = np.array(img, dtype=np.uint8, order="C", copy=True)
        if self.factor == 1:
            out.reshape(-1, 3)[g.index] = np.clip(np.floor(f0 + corr + 0.5), 0, 255).astype(np.uint8)
        else:
            _upsample_apply(self.factor, self._f_rows, self._f_cols, self._f_chart, lm, g.idx,
                            self._c_chart, lab, corr, out, frame if keep else -2)
        fill_gutter(out, self.covered, self.covered, self.gutter_px)
        t3 = time.perf_counter()
        self.last_stats = {"iterations": iters, "prepare_s": t1 - t0, "solve_s": t2 - t1,
                           "finish_s": t3 - t2, "total_s": t3 - t0}
        return out


# --------------------------------------------------------------------------------------------
# measures (acceptance figures)
# --------------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _boundary_step_sum(im, lm, texel_face, face_chart, use_chart):
    """Sum and count, over right and down 4-neighbour texel pairs with two different labels (both
    >= 0; with ``use_chart`` both inside one chart), of the channel-mean |difference|."""
    H, W = lm.shape
    C = im.shape[2]
    total = 0.0
    n = 0
    for r in range(H):
        for c in range(W):
            la = lm[r, c]
            if la < 0:
                continue
            ca = 0
            if use_chart:
                if texel_face[r, c] < 0:
                    continue
                ca = face_chart[texel_face[r, c]]
            for step in range(2):
                rr = r + step
                cc = c + 1 - step
                if rr >= H or cc >= W:
                    continue
                lb = lm[rr, cc]
                if lb < 0 or lb == la:
                    continue
                if use_chart and (texel_face[rr, cc] < 0 or face_chart[texel_face[rr, cc]] != ca):
                    continue
                d = 0.0
                for k in range(C):
                    d += abs(np.float64(im[r, c, k]) - np.float64(im[rr, cc, k]))
                total += d / C
                n += 1
    return total, n


def label_boundary_step(image, label_map, texel_face=None, face_chart=None) -> float:
    """Mean colour step across label boundaries: mean over 4-neighbour texel pairs with two
    different labels (both >= 0, same chart when ``texel_face``/``face_chart`` are given) of
    the channel-mean |difference| (grey levels). NaN if there is no such pair.

    image (H, W, C) uint8 or float; label_map (H, W) int; texel_face (H, W) int (-1 empty);
    face_chart (F,) int (None: one chart)."""
    im = np.asarray(image)
    if im.dtype != np.uint8:
        im = np.asarray(im, np.float64)
    lm = np.ascontiguousarray(label_map)
    if lm.dtype.kind not in "iu":
        lm = lm.astype(np.int64)
    if im.ndim != 3 or im.shape[:2] != lm.shape:
        raise ValueError(f"image {im.shape} must be (H, W, C) over the label map {lm.shape}")
    if texel_face is None:
        tf, fc, use = np.full((1, 1), -1, np.int64), np.zeros(1, np.int64), False
    else:
        tf = np.ascontiguousarray(texel_face)
        n_faces = int(tf.max(initial=-1)) + 1
        fc = (np.zeros(max(n_faces, 1), np.int64) if face_chart is None
              else np.ascontiguousarray(face_chart, dtype=np.int64))
        use = True
    total, n = _boundary_step_sum(np.ascontiguousarray(im), lm, tf, fc, use)
    return float(total / n) if n else float("nan")


def interior_change(before, after, label_map, margin: int) -> float:
    """Mean absolute change (grey levels, channel mean) over labelled texels farther than
    ``margin`` texels (chessboard) from any label boundary (a 4-neighbour of another label,
    including -1: unlabelled texels, gutter). NaN if there is none."""
    from scipy import ndimage  # only this metric needs scipy.ndimage, slow to import

    lm = np.asarray(label_map)
    bnd = np.zeros(lm.shape, bool)
    d = lm[:, :-1] != lm[:, 1:]
    bnd[:, :-1] |= d
    bnd[:, 1:] |= d
    d = lm[:-1, :] != lm[1:, :]
    bnd[:-1, :] |= d
    bnd[1:, :] |= d
    near = ndimage.binary_dilation(bnd, np.ones((3, 3), bool), iterations=int(margin)) if margin > 0 else bnd
    m = (lm >= 0) & ~near
    if not m.any():
        return float("nan")
    diff = np.abs(np.asarray(after, np.float64)[m] - np.asarray(before, np.float64)[m])
    return float(diff.mean())


def seam_step(image, system: CorrectionSystem) -> float:
    """Mean channel-mean |difference| of the image's bilinear values on the two sides of the
    atlas seams (the full-resolution seam rows of ``system``, which must have factor 1)."""
    if system.factor != 1:
        raise ValueError("seam_step needs a factor-1 system")
    g = system.graph
    if g.S.shape[0] == 0:
        return float("nan")
    f = np.asarray(image, np.float64).reshape(-1, 3)[g.index]
    return float(np.abs(g.S @ f).mean())
