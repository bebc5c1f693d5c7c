"""Colour of the never-seen surface: a fill in texture space that respects the chart seams.

What it computes
----------------
Faces that no source frame sees (``never_seen`` of the labels) have no data at any frame. The
volume stage first gives each of their texels a blend of the nearest seen surface points in 3-D
(:func:`stex.sampling.nearest_seen_texels`, the ``nearest`` fill), which reaches any chart but
is only piecewise smooth (the set of nearest points jumps) and ignores the texture along the
surface. :class:`SeamFill` (the ``harmonic`` fill) then solves, per slice and colour channel,

    minimise  Σ_(p,q) (f_p − f_q)²  +  w_s Σ_seam (S f)²  +  λ Σ_(p filled) (f_p − n_p)²

over the texels of never-seen faces, the texels of seen faces held at their sampled colour
(a Dirichlet boundary):

- (p, q) are the 4-neighbour texel pairs inside one chart and S the seam rows of the atlas
  (:func:`stex.texel_graph.texel_graph`, the graph the colour correction solves on), so the fill
  is continuous across chart seams and joins the seen texels around it without a step;
- n is the ``nearest`` fill and λ = 1 / (screen_length · W)² a weak screening towards it: far
  from any seen texel (farther than about screen_length · W texels) the fill tends to the
  colour of the nearest seen surface in 3-D, and a chart without any seen texel (no path in the
  graph to the boundary) takes it outright. Near the boundary the fill is harmonic: the smooth
  interpolation of the seen colours around the hole, the least-squares guess of a texture that
  is not there.

The matrix depends only on the atlas and the never-seen faces, not on a slice: it is built and
its pyamg (classical AMG) hierarchy set up once per volume job, and each slice costs three
CG-accelerated V-cycle solves, each started from the previous slice's solution: consecutive
slices differ little, so the solve meets the same relative residual in fewer cycles (the uint8
result equals a cold start's but for rare one-level roundings). The graph is built on the
texels of never-seen faces and of the seen faces around them (sharing a vertex), not on the
whole atlas.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from stex.texel_graph import texel_graph

log = logging.getLogger("stex.fill")

__all__ = ["SeamFill", "FILLS"]

FILLS = ("nearest", "harmonic")


class SeamFill:
    """Screened harmonic fill of the texels of never-seen faces (module docstring).

    Args:
        texel_face: (W, W) int face per texel, -1 = empty (template ``texel/face_id``).
        face_chart: (F,) int chart of each face (template ``face_chart``).
        texcoords: (Vt, 2) float; texcoord_faces: (F, 3) int; faces: (F, 3) int (template).
        adjacency_pairs, adjacency_edges: (E, 2) int template ``adjacency/pairs`` / ``edges``.
        never_seen: (F,) bool faces whose texels are filled.
        screen_length: reach of the boundary colours into the hole, fraction of the atlas side
            (λ = 1/(screen_length·W)²), beyond which the fill tends to the ``nearest`` fill.
        seam_weight: weight of a seam-continuity sample relative to a texel pair.
        tol: relative residual of each solve; maxiter: V-cycle cap per channel.
    """

    def __init__(self, texel_face, face_chart, texcoords, texcoord_faces, faces, adjacency_pairs,
                 adjacency_edges, never_seen, *, screen_length: float = 1 / 64,
                 seam_weight: float = 1.0, tol: float = 1e-6, maxiter: int = 100):
        t0 = time.perf_counter()
        tf = np.asarray(texel_face)
        if tf.ndim != 2 or tf.shape[0] != tf.shape[1]:
            raise ValueError(f"texel_face must be (W, W), got {tf.shape}")
        faces = np.asarray(faces, np.int64)
        ns = np.asarray(never_seen, bool)
        if ns.shape != (len(faces),):
            raise ValueError(f"never_seen must be ({len(faces)},) for the template's faces, got {ns.shape}")
        if not screen_length > 0:
            raise ValueError(f"screen_length must be > 0, got {screen_length}")
        self.W = W = tf.shape[0]
        self.tol, self.maxiter = float(tol), int(maxiter)
        # the never-seen faces and the seen faces that share a vertex with one: every texel
        # neighbour (in a chart or across a seam) of a filled texel lies in one of them
        near_vertex = np.zeros(int(faces.max(initial=-1)) + 1, bool)
        near_vertex[faces[ns].ravel()] = True
        keep = near_vertex[faces].any(axis=1)
        sub = np.where((tf >= 0) & keep[np.maximum(tf, 0)], tf, -1)
        g = texel_graph(sub, face_chart, texcoords, texcoord_faces, faces, adjacency_pairs, adjacency_edges)
        free = ns[np.maximum(sub.ravel()[g.index], 0)]
        self.targets = g.index[free]                      # flat texel ids of the filled texels
        self.boundary = g.index[~free]                    # flat texel ids of the seen ones
        self.lam = 1.0 / (float(screen_length) * W) ** 2
        self._ml = None
        self.timings = {"graph_s": 0.0, "amg_setup_s": 0.0}
        if self.targets.size:
            L = g.laplacian(seam_weight)
            fi, bi = np.flatnonzero(free), np.flatnonzero(~free)
            self.A = (L[fi][:, fi] + sp.diags(np.full(fi.size, self.lam))).tocsr()
            self.B = L[fi][:, bi].tocsr()                 # coupling to the held (seen) texels
            t1 = time.perf_counter()
            self.timings["graph_s"] = t1 - t0
            import pyamg  # slow to import: only a scene with never-seen faces needs it

            # classical AMG: deterministic set-up (as the correction's, docs/decisions/correction.md)
            self._ml = pyamg.ruge_stuben_solver(self.A)
            self.timings["amg_setup_s"] = time.perf_counter() - t1
            log.info("fill: %d texels of never-seen faces, %d held around them; graph %.1f s, AMG %.1f s",
                     self.targets.size, self.boundary.size, self.timings["graph_s"],
                     self.timings["amg_setup_s"])
        self.last_iterations: list = []
        self._previous: list = [None, None, None]   # last slice's change per channel (warm start)

    @property
    def n_filled(self) -> int:
        """Texels the fill solves for."""
        return int(self.targets.size)

    def fill(self, texture, initial=None) -> np.ndarray:
        """Fill one slice in place and return it.

        Args:
            texture: (W, W, 3) uint8 slice; the texels of seen faces are read (and left as they
                are), those of never-seen faces overwritten.
            initial: (n_filled, 3) float colours of the filled texels to screen towards and to
                start from (the ``nearest`` fill, in the order of ``targets``); None = the
                texels' current values.

        Returns:
            ``texture``. ``self.last_iterations`` holds the V-cycles of each channel.
        """
        tex = np.asarray(texture)
        if tex.shape != (self.W, self.W, 3) or tex.dtype != np.uint8:
            raise ValueError(f"texture must be ({self.W}, {self.W}, 3) uint8, got {tex.shape} {tex.dtype}")
        self.last_iterations = []
        if not self.targets.size:
            return texture
        flat = tex.reshape(-1, 3)
        n0 = (flat[self.targets] if initial is None else np.asarray(initial)).astype(np.float64)
        if n0.shape != (self.targets.size, 3):
            raise ValueError(f"initial must be ({self.targets.size}, 3), got {n0.shape}")
        held = flat[self.boundary].astype(np.float64)
        out = np.empty_like(n0)
        for ch in range(3):
            # solved for the change from the start n0: its right-hand side has no part along a
            # never-seen chart's constant (Lᵀ1 = 0), the near-null space of a weak screening
            # where no seen texel is connected, and the tolerance is relative to the change
            r0 = -(self.A @ n0[:, ch] - self.lam * n0[:, ch]) - self.B @ held[:, ch]
            out[:, ch] = n0[:, ch]
            if not r0.any():
                self.last_iterations.append(0)
                continue
            # the tolerance is relative to |r0| whatever the start, so a start from the last
            # slice's change only saves cycles
            x0 = self._previous[ch]
            res = []
            change = self._ml.solve(r0, x0=np.zeros_like(r0) if x0 is None else x0, tol=self.tol,
                                    accel="cg", maxiter=self.maxiter, residuals=res)
            self._previous[ch] = change
            out[:, ch] += change
            self.last_iterations.append(len(res) - 1)
        flat[self.targets] = np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8)
        return texture
