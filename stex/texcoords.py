"""Texture-coordinate optimisation (Kim et al. 2019, accelerated as in Kim et al. 2021 §4).

Tracking and calibration errors make one surface point land on different pixels in different
frames. For every vertex v and every frame t where it is visible, the stage optimises its texture
coordinate ξ_t(v) on that frame's colour image (colour pixels, integer = pixel centre; starting
from Φ, the ``projection`` store) so that the textures of each face taken from all frames agree
with a proxy colour (the paper's Eq. 1):

    E(ξ, P) = Σ_{t} Σ_{f visible at t} Σ_{s<S} ((C_t(p_tfs) − P_fs) / 255)²,
    p_tfs   = Σ_k β_sk ξ_t(F_fk)        (S fixed barycentric samples β per face)

What follows mirrors the authors' code (``TextureMappingNonRigid``, ``official_code_notes.md``
§2.2); the differences — several of them options that are ours — are listed at the end.

- **Colour**: grey (OpenCV RGB→grey, 0..255), as the authors. C_t is bilinear in the grey image
  blurred for the current level; its gradient (for Gauss-Newton) is the central difference of
  bilinear lookups 1 px apart. Every energy evaluation samples the crops once per visible
  (frame, face) pair and sample (C and the mask test, float32 / bool, Q × S each); proxies,
  errors and the Gauss-Newton residuals reuse those samples.
- **Samples**: the authors' 15 barycentric triples (:data:`SAMPLE_BARY`); ``samples_per_face``
  takes the first S of them.
- **Proxy colour** of sample s of face f: weighted mean of g_t·C_t(p_tfs) over the stage's frames
  t where f is visible, weight = face cosine (``projection`` face_cos) × mask weight × robust
  weight ω_tf (below), the mask weight being 1 when the bilinearly interpolated foreground mask at
  p is ≥ 0.999 and ``background_weight`` (0.001, the authors' GrabCut weighting) otherwise. It is
  recomputed after every step (alternation, as the authors).
- **Gain** (``gain`` 'frame', ours; 'none' = the authors, g_t = 1): a per-frame factor g_t on
  the grey samples, the half-sample mode over the frame's faces (all samples inside the mask) of
  Σ_s P_fs / Σ_s C_t(p_tfs), set at each level's start by alternating with the face sums of the
  proxy until it converges (normalised to geometric mean 1; warm-started from the previous
  stage): auto exposure / white balance otherwise looks like motion to Eq. 1; the mode ignores
  local changes of appearance, even on a large minority of the faces. A fixed two rounds (the
  last stop) left 1.8 % RMS gain error on the demo, which Eq. 1 turned into drift.
- **Robust weights** (``robust_grey`` c > 0, ours; 0 = Eq. 1, the authors): with e_tf =
  Σ_s (g_t C_t − P_fs)² (grey levels²) the energy is Σ ρ(e_tf) / 255², ρ(e) = S c² e / (S c² + e)
  (Geman-McClure: ≈ e while the face's RMS residual is well under c, bounded above), so the
  residuals of a (frame, face) pair enter the steps and the proxy with weight ω_tf = ρ'(e_tf) =
  (1 + e_tf / (S c²))⁻². The proxy is the weighted mean after one reweighting pass (ω from the
  residuals against the unweighted proxy), so E is a function of ξ. A face whose appearance
  changes (the demo's wrinkles and tint patch; real folds, specularities) then stops dragging ξ:
  with Eq. 1 the demo's wrinkle stripes pulled whole regions 10-40 px off (p99 |ξ − Φ| 23 px for
  a drift whose p99 is 5 px), and E at the true coordinates was 3.7x E at the optimum.
- **Local photometric model** (``face_photometric``, ours; 'none' = Eq. 1, the authors): each
  (t, f) pair's residuals are taken after removing their mean over the face's samples ('offset')
  and, with 'affine' (default), after fitting the contrast a_tf of its samples to the proxy's
  (least squares, clamped to [0.5, 2]): r_s = a_tf g_t C_t(p_s) − P_fs − m_tf, m_tf their mean.
  Wrinkle shading and a changing tint change a face's brightness and contrast at some frames, and
  a single static proxy per sample can explain that only by moving ξ. The 2×2 steps then use the
  exact Gauss-Newton blocks of the mean-removed residuals (corner j's Jacobian a β_sj ∇C_s − M_j,
  M_j its mean over the samples; a_tf held at its value for the step, refitted by the energy).
  Demo, 120 frames (harness of bench_texcoords, gauge 'mean'): 65.0 % median drift reduction
  with 'none', 67.0 % with 'offset', 68.2 % with 'affine'. Not with solver 'sparse'.
- **Gauss-Newton, solver 'jacobi'** (the authors' scheme): every (t, v) takes a 2×2 step from
  its own normal equations with its neighbours held fixed. Photometric residuals
  r = g_t C_t(p) − P over the samples of the faces around v visible at t, weighted by ω_tf, and
  2 edge residuals per such face: with ``edge_mode`` 'length' (the authors) ``edge_weight`` ·
  (|ξ_v − ξ_k| − |Φ_v − Φ_k|) (grey levels; keeps ξ's triangles close to Φ's lengths), with
  'vector' the 2-vector ``edge_weight`` · ((ξ_v − ξ_k) − (Φ_v − Φ_k)), i.e. the displacement
  ξ − Φ is smooth over the mesh, which carries the displacement of textured vertices to
  untextured ones (tracking drift is smooth) instead of only keeping lengths. Each photometric
  residual enters v's equations with weight β (v's barycentric) and Jacobian g_t ∇C (the sample
  moves with v): with the plain Jacobian β∇C every corner of a uniformly shifted face would step
  ≈ 2.5× the shift when all three move at once. If det(A) < 1e-4, 1e-4 is added to the diagonal
  (as the authors); NaN steps become 0; each component is clamped to ±``step_clamp_px``; ξ stays
  inside the frame's working crop (below) and the image. A step of all unknowns is accepted only
  if E (proxy and weights recomputed at the new ξ) does not rise; otherwise it is halved up to
  ``backtracks`` times (the length carries over to the next step and doubles, up to 1, after each
  accepted one).
- **Gauss-Newton, solver 'sparse'** (ours): per frame, with the proxy, gains and weights of the
  current ξ held fixed, the full normal equations of all the frame's vertices — the same
  residuals and weights as 'jacobi', but each photometric residual with its true Jacobian
  β_k g_t ∇C for every corner k, so corners j, k of a face are coupled by β_j β_k g_t² ∇C∇Cᵀ; the
  edge term adds the graph-Laplacian-like blocks. Per (frame, face) 6×6 blocks come from a numba
  kernel (:func:`stex.photometric.face_blocks_kernel`) and are summed into one CSC matrix per frame through a
  pattern built once per level; (H + λ (diag H + mean diag H) + 1e-4 I) δ = −g is solved by
  SuperLU (:class:`stex.photometric.SparseSystems`). Levenberg–Marquardt: λ starts at ``lm_lambda`` each level,
  follows Nielsen's rule on the gain ratio (actual / model decrease) after an accepted step and
  doubles (×2, ×4, ...) after a rejected one, up to ``backtracks`` re-solves. The step is clamped,
  gauge-projected and kept in the crop as above, and accepted only if neither E nor the objective
  it minimises, O = E + edge term (/ 255²), rises. It reaches the same accuracy in fewer but
  dearer steps (the stage is not convergence-limited), so 'jacobi' stays the default
  (docs/decisions/texcoords.md).
- **Monotone energy**: a level stops when no halving / re-solve helps, when the relative decrease
  is below ``rel_tol`` (the authors: 1e-5; default 1e-4, same accuracy, half the time), or after
  ``iterations`` steps (the authors: 300). The recorded E is non-increasing within every level
  for both solvers (and O for 'sparse').
- **Gauge** (``gauge`` 'weighted'): Eq. 1 only sees where the frames disagree: moving every frame's
  ξ of a vertex the same way (sliding the texture over the surface) leaves it unchanged, so the
  per-vertex mean of ξ − Φ over the stage's frames (where the vertex has a visible face) is
  unobserved. Without a rule for it (``gauge`` 'none', the authors) it random-walks under the
  small biases of the data term (noise, appearance changing in time, the silhouette)
  (docs/decisions/texcoords.md). 'mean' holds it at 0 by subtracting it from every candidate ξ (image px, over the
  frames where the vertex is a corner of a visible face): ξ keeps tracking's average placement
  and takes only the frame-to-frame corrections. 'weighted' (default) holds the mean weighted by
  the proxy weights (the mean cosine of the vertex's visible faces at that frame) instead: the
  proxy colour is the cosine-weighted average of the frames, so this is where the proxy puts the
  texture, and a frame that sees the vertex frontally places it better than one at a grazing
  angle (docs/decisions/texcoords.md).
- **Hierarchy**: ``levels`` coarse-to-fine levels over an *image* pyramid: level l (0 = coarsest)
  uses the grey image blurred by ``levels − l`` successive 3×3 Gaussian blurs (the authors'
  ``blur_vec``: 6 blurs on the coarsest, 1 on the finest), always at full resolution. **The
  authors' mesh hierarchy (deformation-oriented decimation, ⌊F/2⌋ faces per coarser level) is
  not built**: every level optimises the full mesh's vertices (the 'sparse' solver is the other
  way to move smooth displacements across the mesh in few steps).
- **Schedule** (``main.cpp``): key frames are the frames at positions ``i % keyframe_step == 0``
  of the sequence; they are optimised jointly coarse-to-fine; the displacements ξ − Φ are then
  linearly interpolated to the other frames (:func:`interpolate_displacements`, the authors'
  ``InterpKeytoAll``: per vertex, per run of consecutive frames where it is visible, held constant
  before the first / after the last key frame of the run, 0 in a run without a key frame); last,
  ``refine_iterations`` iterations over all frames with 1 blur.
- **Memory**: colour frames are streamed from the store, one at a time, converted to grey and
  cropped to the bounding box of the frame's visible ξ plus ``crop_margin_px``. A stage holds,
  for each of its frames, the unblurred grey crop, the blurred crop of the level and the mask
  crop, all uint8 (3 B per cropped pixel). Paper scale (265 frames of 2048×1536, object ≈ 1/4 of
  the image): ≈ 265 × 0.8 Mpx × 3 B ≈ 0.6 GB, worst case (object filling every frame)
  265 × 3.1 Mpx × 3 B = 2.5 GB; plus ξ/Φ/visibility tables (T·V·(2·8·3) B ≈ 0.5 GB at V = 10k,
  T = 265 in float64 work arrays) and the samples of the current and the candidate ξ (Q·S·5 B
  each, Q ≈ 7k faces × T: ≈ 0.14 GB each at T = 265) — under the 4 GB target ('sparse' adds
  Q·(36 + 6)·8 B of blocks, ≈ 0.6 GB at T = 265, and one frame's LU at a time).

Differences from the authors' code, deliberately: the mesh hierarchy above (not built); the
proxy and the energy use the *level's* blurred image (the authors: the GN step on the blurred
image, proxy and energy on the unblurred one) so that accepting steps on E is consistent; edge
rest lengths come from Φ (the authors: the current ξ at the start of each level); bilinear
interpolation instead of their non-standard 2×2 blend; steps are accepted only when E does not
rise (the authors accept every step); the mask test is made on the proxy weights only (the
``projection`` stage already dropped masked-out vertices and faces); ``rel_tol`` 1e-4 (theirs
1e-5). Options that are ours (the authors' behaviour in brackets): ``gauge`` 'weighted' ['none'],
``edge_mode`` 'vector' ['length'], ``gain`` 'frame' ['none'], ``robust_grey`` 4 [0],
``face_photometric`` 'affine' ['none'] and ``solver`` 'sparse' ['jacobi', the default]. Each of
ours lowered the error against the truth in ``benchmarks/bench_texcoords.py``; on the workflow's
runs ξ is bounded by the part of the tracker's error that Eq. 1 cannot observe (its per-vertex
mean over the frames). The measurements are in docs/decisions/texcoords.md.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, prange

from stex.config import section_params
from stex.photometric import (PhotometricTerm, SparseSystems, edge_energy, face_blocks_kernel,
                              gauge_weights, jacobi_step_kernel, vertex_used)

log = logging.getLogger("stex.texcoords")

__all__ = ["SAMPLE_BARY", "CropStack", "build_stack", "keyframe_positions",
           "interpolate_displacements", "photometric_energy", "optimize_level",
           "optimize_texcoords", "texcoords_params", "final_energy", "sampling_table"]

#: the authors' 15 barycentric samples per face (Optimizer.cu L5-7), rows (w0, w1, w2)
SAMPLE_BARY = np.array([
    (.5, .25, .25), (.25, .5, .25), (.25, .25, .5), (.8, .1, .1), (.1, .8, .1), (.1, .1, .8),
    (.5, .5, 0), (0, .5, .5), (.5, 0, .5), (.2, .2, .6), (.6, .2, .2), (.2, .6, .2),
    (.1, .5, .4), (.5, .4, .1), (.4, .1, .5)], dtype=np.float64)



def texcoords_params(params: dict | None) -> dict:
    """``params`` (the ``texcoords`` config section) completed with the schema defaults, checked."""
    p = section_params("texcoords", params)
    if p["solver"] == "sparse" and p["face_photometric"] != "none":
        raise ValueError("texcoords.solver 'sparse' needs texcoords.face_photometric 'none' "
                         f"(got {p['face_photometric']!r}): its blocks are the plain residuals'")
    if not 1 <= int(p["samples_per_face"]) <= len(SAMPLE_BARY):
        raise ValueError(f"texcoords.samples_per_face must be in 1..{len(SAMPLE_BARY)}")
    if int(p["levels"]) < 1 or int(p["keyframe_step"]) < 1:
        raise ValueError("texcoords.levels and texcoords.keyframe_step must be >= 1")
    return p


# --------------------------------------------------------------------------------------------
# images: per-frame crops in one flat buffer
# --------------------------------------------------------------------------------------------

@dataclass
class CropStack:
    """Per-frame image crops of one stage, concatenated.

    ``grey`` / ``blur`` / ``mask``: flat uint8 buffers (grey levels 0..255, mask 0/1); frame k's
    crop is ``buf[off[k]:off[k] + h[k]*w[k]].reshape(h[k], w[k])`` and covers image pixels
    x0[k]..x0[k]+w[k]-1 (columns) × y0[k]..y0[k]+h[k]-1 (rows). ``blur`` holds ``grey`` after
    ``n_blur`` 3×3 Gaussian blurs (see :meth:`set_blur`).
    """

    grey: np.ndarray
    blur: np.ndarray
    mask: np.ndarray
    off: np.ndarray   # (K,) int64
    h: np.ndarray     # (K,) int64
    w: np.ndarray     # (K,) int64
    x0: np.ndarray    # (K,) int64
    y0: np.ndarray    # (K,) int64
    n_blur: int = 0
    gain: np.ndarray | None = None  # (K,) float64 per-frame gain of the last stage (warm start)

    @property
    def nbytes(self) -> int:
        return self.grey.nbytes + self.blur.nbytes + self.mask.nbytes

    def crop(self, k: int, which: str = "blur") -> np.ndarray:
        buf = getattr(self, which)
        o, h, w = int(self.off[k]), int(self.h[k]), int(self.w[k])
        return buf[o:o + h * w].reshape(h, w)

    def set_blur(self, n_blur: int) -> None:
        """Fill ``blur`` with ``grey`` after ``n_blur`` successive 3×3 Gaussian blurs (float, one
        rounding at the end), as the authors' image pyramid."""
        if n_blur == self.n_blur and n_blur > 0:
            return
        for k in range(len(self.off)):
            g = self.crop(k, "grey").astype(np.float32)
            for _ in range(n_blur):
                g = cv2.GaussianBlur(g, (3, 3), 0, borderType=cv2.BORDER_REPLICATE)
            self.crop(k, "blur")[...] = np.clip(np.rint(g), 0, 255).astype(np.uint8)
        self.n_blur = n_blur


def _box(points: np.ndarray, margin: int, width: int, height: int):
    if len(points) == 0:
        return 0, 0, 1, 1
    lo = np.floor(points.min(0)).astype(int) - margin
    hi = np.ceil(points.max(0)).astype(int) + margin
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], width - 1), min(hi[1], height - 1)
    if x1 < x0 or y1 < y0:
        return 0, 0, 1, 1
    return x0, y0, x1 - x0 + 1, y1 - y0 + 1


def build_stack(load, frames, xi, valid, margin: int, width: int, height: int) -> CropStack:
    """Stream frames and crop them around their visible texture coordinates.

    Args:
        load: callable ``load(t) -> (grey (H, W) uint8, mask (H, W) bool)`` for sequence position
            t (called once per frame; only one frame is held at a time).
        frames: sequence positions of the stage's frames (K,).
        xi: (T, V, 2) float texture coordinates (colour px) of the whole sequence.
        valid: (T, V) bool vertex visible.
        margin: crop margin around the visible coordinates (px).
        width, height: colour image size (px).
    """
    boxes = [_box(xi[t][valid[t]], margin, width, height) for t in frames]
    sizes = np.array([bw * bh for _, _, bw, bh in boxes], np.int64)
    off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    total = int(sizes.sum())
    grey = np.zeros(total, np.uint8)
    mask = np.zeros(total, np.uint8)
    for k, t in enumerate(frames):
        x0, y0, bw, bh = boxes[k]
        g, m = load(int(t))
        if g.shape != (height, width) or m.shape != (height, width):
            raise ValueError(f"frame {t}: grey {g.shape} / mask {m.shape}, expected {(height, width)}")
        grey[off[k]:off[k] + sizes[k]] = g[y0:y0 + bh, x0:x0 + bw].ravel()
        mask[off[k]:off[k] + sizes[k]] = m[y0:y0 + bh, x0:x0 + bw].ravel()
    arr = np.array(boxes, np.int64).reshape(-1, 4)
    return CropStack(grey, grey.copy(), mask, off, arr[:, 3].copy(), arr[:, 2].copy(),
                     arr[:, 0].copy(), arr[:, 1].copy(), 0)


@njit(cache=True, nogil=True, parallel=True)
def _interp_kernel(delta_key, key_pos, valid, out):
    T, V = valid.shape
    nK = key_pos.shape[0]
    for v in prange(V):
        t = 0
        while t < T:
            if not valid[t, v]:
                out[t, v, 0] = 0.0
                out[t, v, 1] = 0.0
                t += 1
                continue
            t1 = t
            while t1 < T and valid[t1, v]:
                t1 += 1
            # run [t, t1): key frames inside it
            prev = -1     # index into key_pos
            for tt in range(t, t1):
                # next key frame index at or after tt inside the run
                nxt = -1
                for q in range(nK):
                    if key_pos[q] >= tt and key_pos[q] < t1:
                        nxt = q
                        break
                if nxt >= 0 and key_pos[nxt] == tt:
                    prev = nxt
                    out[tt, v, 0] = delta_key[nxt, v, 0]
                    out[tt, v, 1] = delta_key[nxt, v, 1]
                elif prev >= 0 and nxt >= 0:
                    a = (tt - key_pos[prev]) / (key_pos[nxt] - key_pos[prev])
                    out[tt, v, 0] = (1 - a) * delta_key[prev, v, 0] + a * delta_key[nxt, v, 0]
                    out[tt, v, 1] = (1 - a) * delta_key[prev, v, 1] + a * delta_key[nxt, v, 1]
                elif prev >= 0:
                    out[tt, v, 0] = delta_key[prev, v, 0]
                    out[tt, v, 1] = delta_key[prev, v, 1]
                elif nxt >= 0:
                    out[tt, v, 0] = delta_key[nxt, v, 0]
                    out[tt, v, 1] = delta_key[nxt, v, 1]
                else:
                    out[tt, v, 0] = 0.0
                    out[tt, v, 1] = 0.0
            t = t1


# --------------------------------------------------------------------------------------------
# pure functions
# --------------------------------------------------------------------------------------------

def keyframe_positions(n_frames: int, step: int) -> np.ndarray:
    """Sequence positions of the key frames: i % step == 0 (the authors' ``ExtractKeyframes``)."""
    return np.arange(0, n_frames, max(int(step), 1), dtype=np.int64)


def interpolate_displacements(delta_key, key_pos, valid) -> np.ndarray:
    """Linear interpolation of key-frame displacements to every frame (``InterpKeytoAll``).

    Args:
        delta_key: (K, V, 2) float displacements ξ − Φ at the key frames (px).
        key_pos: (K,) int increasing sequence positions of the key frames.
        valid: (T, V) bool vertex visible at each frame.

    Returns:
        (T, V, 2) float64 displacements: per vertex and per run of consecutive frames where it is
        visible, linear between the run's key frames at which it is visible, constant before the
        first / after the last of them, 0 in a run without one, and 0 where not visible.
    """
    valid = np.ascontiguousarray(valid, dtype=np.bool_)
    key_pos = np.asarray(key_pos, np.int64)
    delta_key = np.ascontiguousarray(delta_key, np.float64)
    if delta_key.shape != (len(key_pos), valid.shape[1], 2):
        raise ValueError(f"delta_key has shape {delta_key.shape}, expected {(len(key_pos), valid.shape[1], 2)}")
    out = np.zeros(valid.shape + (2,), np.float64)
    if valid.size and len(key_pos):
        _interp_kernel(delta_key, key_pos, valid, out)
    return out


def photometric_energy(stack: CropStack, xi, faces, face_visible, face_weight, params=None):
    """The photometric energy of the stage's frames at ``xi``, with the proxy recomputed there.

    Args:
        stack: the frames' crops (``blur`` is used: call ``stack.set_blur`` first).
        xi: (K, V, 2) float texture coordinates (colour px) of the stack's frames.
        faces: (F, 3) int; face_visible: (K, F) bool; face_weight: (K, F) float (cosines).
        params: ``texcoords`` section (samples_per_face, background_weight, robust_grey, gain).

    Returns:
        (E, proxy): E float = Σ ((C − P)/255)² over visible faces and samples (Eq. 1; its robust,
        gain-compensated form if ``robust_grey`` > 0 / ``gain`` 'frame', see :class:`stex.photometric.PhotometricTerm`);
        proxy (F, S) grey levels.
    """
    p = texcoords_params(params)
    bary = np.ascontiguousarray(SAMPLE_BARY[: int(p["samples_per_face"])])
    xi = np.ascontiguousarray(xi, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    fvis = np.ascontiguousarray(face_visible, np.bool_)
    fw = np.ascontiguousarray(face_weight, np.float64)
    ph = PhotometricTerm(stack, faces, fvis, fw, bary, p)
    ph.set_gain(xi)
    P, E, _, _ = ph.evaluate(xi)
    return E, P


def _crop_bounds(stack: CropStack, width: int, height: int):
    """(lo, hi) (K, 1, 2) float64 bounds of ξ: it stays inside each frame's crop (and so inside
    the image)."""
    lo = np.stack([stack.x0, stack.y0], 1).astype(np.float64)[:, None, :]
    hi = (np.stack([stack.x0 + stack.w, stack.y0 + stack.h], 1) - 1).astype(np.float64)[:, None, :]
    hi = np.minimum(hi, np.array([width - 1.0, height - 1.0]))
    return lo, hi


def _step_finisher(gauge: bool, gauge_w, used, phi, lo, hi):
    """The map from a stepped ξ (K, V, 2) to the candidate: with ``gauge``, every vertex's
    (``gauge_w``-weighted) mean displacement over its frames removed, then clipped to [lo, hi]."""
    gauge_norm = np.maximum(gauge_w.sum(0), 1e-12)[:, None]

    def finish(step_xi):
        cand = step_xi
        if gauge:
            # hold every vertex's (weighted) mean displacement over its frames: Eq. 1 cannot see it
            dsp = gauge_w[..., None] * (cand - phi)
            cand = cand - used[..., None] * (dsp.sum(0) / gauge_norm)[None]
        return np.clip(cand, lo, hi)

    return finish


def optimize_level(stack: CropStack, xi0, phi, faces, face_visible, face_weight, params,
                   iterations: int, width: int, height: int):
    """Gauss-Newton iterations of one level on the frames of ``stack``.

    Args:
        stack: crops of the K frames, ``blur`` set to the level's image.
        xi0: (K, V, 2) float64 starting texture coordinates (colour px).
        phi: (K, V, 2) float Φ (edge rest lengths).
        faces: (F, 3) int; face_visible (K, F) bool; face_weight (K, F) float cosines.
        params: completed ``texcoords`` section (``solver`` picks the step, see the module
            docstring).
        iterations: maximum number of accepted steps.
        width, height: colour image size (px).

    Returns:
        (xi (K, V, 2) float64, energies list[float], objectives list[float]): Eq. 1 E and the
        objective E + edge term (both dimensionless, grey levels / 255 squared) at the start and
        after every accepted step. The accepted quantity — E for 'jacobi', E + edge term for
        'sparse' — is non-increasing.
    """
    p = params
    bary = np.ascontiguousarray(SAMPLE_BARY[: int(p["samples_per_face"])])
    xi = np.array(xi0, np.float64, order="C")
    phi = np.ascontiguousarray(phi, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    fvis = np.ascontiguousarray(face_visible, np.bool_)
    fw = np.ascontiguousarray(face_weight, np.float64)
    K = xi.shape[0]
    lo, hi = _crop_bounds(stack, width, height)
    gauge = p["gauge"] != "none"
    edge_vec = p["edge_mode"] == "vector"
    edge_w = float(p["edge_weight"])
    clamp = float(p["step_clamp_px"])
    sparse = p.get("solver", "jacobi") == "sparse"
    used = vertex_used(fvis, faces, xi.shape[1])
    gauge_w = gauge_weights(fvis, fw, faces, used, p["gauge"])
    finish = _step_finisher(gauge, gauge_w, used, phi, lo, hi)

    photo = PhotometricTerm(stack, faces, fvis, fw, bary, p)
    photo.set_gain(xi)

    def evaluate(x):
        Px, Ex, om, Cx = photo.evaluate(x)
        return Px, Ex, Ex + edge_energy(x, phi, faces, fvis, edge_w, edge_vec), om, Cx

    P, E, J, omega, C = evaluate(xi)
    energies, objectives = [E], [J]
    step = np.zeros_like(xi)
    if sparse:
        systems = SparseSystems(faces, photo.pk, photo.pf, photo.qs, used)
        Q = len(systems.pk)
        Hq = np.zeros((Q, 6, 6))
        gq = np.zeros((Q, 6))
        lam = float(p["lm_lambda"])
        nu = 2.0
    alpha = 1.0
    for _ in range(int(iterations)):
        if E <= 0 or K == 0:
            break
        accepted = False
        if sparse:
            # full Gauss-Newton of every frame (proxy and weights fixed), Levenberg-Marquardt
            # damped; λ follows the gain ratio (Nielsen's rule: shrinks when the model predicted
            # the decrease well, grows ×2, ×4, ... on each rise)
            face_blocks_kernel(stack.blur, stack.off, stack.h, stack.w, stack.x0, stack.y0, xi,
                                phi, faces, systems.pk, systems.pf, omega, photo.gain, bary, P,
                                C, edge_w, edge_vec, Hq, gq)
            for _b in range(int(p["backtracks"]) + 1):
                step[...] = 0.0
                systems.solve(Hq, gq, lam, step)
                np.nan_to_num(step, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
                np.clip(step, -clamp, clamp, out=step)
                pred = systems.model_decrease(Hq, gq, faces, step)
                cand = finish(xi + step)
                Pc, Ec, Jc, omc, Cc = evaluate(cand)
                log.debug("sparse λ %.3g: J %.6g -> %.6g (model %.6g), E %.6g -> %.6g, |step| max %.3g",
                          lam, J, Jc, J - pred, E, Ec, np.abs(step).max())
                if Jc <= J and Ec <= E:
                    accepted = True
                    gain_ratio = (J - Jc) / pred if pred > 0 else 0.0
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * gain_ratio - 1.0) ** 3)
                    nu = 2.0
                    break
                lam = max(lam, 1e-6) * nu
                nu *= 2.0
            if not accepted:
                break
            rel = (J - Jc) / J
        else:
            jacobi_step_kernel(stack.blur, stack.off, stack.h, stack.w, stack.x0, stack.y0, xi, phi,
                       faces, fvis, omega, photo.gain, bary, P, C, photo.qs, edge_w, edge_vec, clamp,
                       photo.face_model, step)
            # the step length adapts: halved on a rise, doubled (up to 1) after an accepted step
            for _b in range(int(p["backtracks"]) + 1):
                cand = finish(xi + alpha * step)
                Pc, Ec, Jc, omc, Cc = evaluate(cand)
                if Ec <= E:
                    accepted = True
                    break
                alpha *= 0.5
            if not accepted:
                break
            alpha = min(1.0, 2.0 * alpha)
            rel = (E - Ec) / E
        xi, P, E, J, omega, C = cand, Pc, Ec, Jc, omc, Cc
        energies.append(E)
        objectives.append(J)
        if rel < float(p["rel_tol"]):
            break
    if sparse:
        log.debug("sparse solver: %d accepted steps, %d factorisations of %d frames",
                  len(energies) - 1, systems.factorisations, K)
    return xi, energies, objectives


def optimize_texcoords(load, phi, vertex_visible, face_visible, face_weight, faces,
                       image_size, params: dict | None = None, progress: bool = True) -> dict:
    """The whole stage in memory, frames streamed through ``load``.

    Args:
        load: callable ``load(t) -> (grey (H, W) uint8, mask (H, W) bool)`` for sequence position
            t in 0..T-1 (grey = the colour image in grey levels, mask = the foreground mask).
        phi: (T, V, 2) float Φ (colour px). vertex_visible: (T, V) bool.
        face_visible: (T, F) bool. face_weight: (T, F) float proxy weights (face cosines).
        faces: (F, 3) int. image_size: (W, H) colour image size (px).
        params: the ``texcoords`` config section (missing keys: the schema defaults).

    Returns:
        dict: ``xi`` (T, V, 2) float32 (Φ where not visible), ``valid`` (T, V) bool,
        ``energy`` (levels + 1, max(iterations, refine_iterations) + 1) float64 — row l < levels is
        key-frame level l (0 coarsest), the last row the all-frame refinement; column 0 the energy
        E at the start of the stage, column i after accepted step i, NaN after the stage stopped —,
        ``objective`` the same for E + edge term (what the 'sparse' solver minimises),
        ``keyframes`` (K,) int positions, ``stages`` list of dicts (name, frames, blurs,
        iterations, seconds, crop_mb, energy_start, energy_end).
    """
    p = texcoords_params(params)
    W, H = int(image_size[0]), int(image_size[1])
    phi = np.asarray(phi, np.float64)
    valid = np.asarray(vertex_visible, bool)
    fvis_all = np.asarray(face_visible, bool)
    fw_all = np.asarray(face_weight, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    T, V = valid.shape
    L = int(p["levels"])
    n_it = max(int(p["iterations"]), int(p["refine_iterations"]))
    energy = np.full((L + 1, n_it + 1), np.nan)
    objective = np.full((L + 1, n_it + 1), np.nan)
    stages = []
    margin = int(p["crop_margin_px"])

    keys = keyframe_positions(T, p["keyframe_step"])
    xi_key = phi[keys].copy()
    t0 = time.perf_counter()
    stack = build_stack(load, keys, phi, valid, margin, W, H)
    for lev in range(L):
        ts = time.perf_counter()
        nb = L - lev
        stack.set_blur(nb)
        xi_key, en, ob = optimize_level(stack, xi_key, phi[keys], faces, fvis_all[keys],
                                        fw_all[keys], p, int(p["iterations"]), W, H)
        energy[lev, :len(en)] = en
        objective[lev, :len(ob)] = ob
        stages.append({"name": f"level {lev}", "frames": len(keys), "blurs": nb,
                       "iterations": len(en) - 1, "seconds": round(time.perf_counter() - ts, 3),
                       "crop_mb": round(stack.nbytes / 2**20, 1),
                       "energy_start": en[0], "energy_end": en[-1]})
        if progress:
            log.info("texcoords: key frames, level %d/%d (%d blurs): %d iterations, E %.4g -> %.4g (%.1f s)",
                     lev + 1, L, nb, len(en) - 1, en[0], en[-1], time.perf_counter() - ts)
    key_gain = stack.gain
    del stack
    # displacements to every frame
    delta_key = np.where(valid[keys][..., None], xi_key - phi[keys], 0.0)
    delta = interpolate_displacements(delta_key, keys, valid)
    xi = phi + delta
    xi[..., 0] = np.clip(xi[..., 0], 0, W - 1)
    xi[..., 1] = np.clip(xi[..., 1], 0, H - 1)
    # refinement over all frames at the finest image
    ts = time.perf_counter()
    allf = np.arange(T)
    if int(p["refine_iterations"]) >= 0:
        stack = build_stack(load, allf, xi, valid, margin, W, H)
        if key_gain is not None:  # warm start of the gain alternation
            stack.gain = np.exp(np.interp(allf, keys, np.log(key_gain)))
        stack.set_blur(1)
        xi, en, ob = optimize_level(stack, xi, phi, faces, fvis_all, fw_all, p,
                                    int(p["refine_iterations"]), W, H)
        energy[L, :len(en)] = en
        objective[L, :len(ob)] = ob
        stages.append({"name": "refine", "frames": T, "blurs": 1, "iterations": len(en) - 1,
                       "seconds": round(time.perf_counter() - ts, 3),
                       "crop_mb": round(stack.nbytes / 2**20, 1),
                       "energy_start": en[0], "energy_end": en[-1]})
        if progress:
            log.info("texcoords: all %d frames: %d iterations, E %.4g -> %.4g (%.1f s; %.1f s in all)",
                     T, len(en) - 1, en[0], en[-1], time.perf_counter() - ts, time.perf_counter() - t0)
        del stack
    xi = np.where(valid[..., None], xi, phi)
    return {"xi": xi.astype(np.float32), "valid": valid.copy(), "energy": energy,
            "objective": objective, "keyframes": keys, "stages": stages}


# --------------------------------------------------------------------------------------------
# the paper's sampling table
# --------------------------------------------------------------------------------------------

def final_energy(energy) -> float:
    """The stage's final all-frame energy: the last finite value of ``energy``'s last row (the
    all-frame refinement; :func:`optimize_texcoords`)."""
    row = np.asarray(energy, np.float64)[-1]
    row = row[np.isfinite(row)]
    return float(row[-1]) if len(row) else math.nan


def sampling_table(inputs: dict, params: dict | None, steps) -> list[dict]:
    """The paper's sampling table (Kim et al. 2021, "error ratio ... depending on the sampling
    ratio"): the stage run once per key-frame step n in ``steps`` (the other settings as
    ``params``), one after another in this process so that their times compare.

    The error of a run is its final all-frame Eq. 1 energy (:func:`final_energy`); its ratio is
    that error divided by the error with every frame a key frame (n = 1, the original Kim et al.
    2019 scheme, which ``steps`` must hold), and its speed-up the stage time with n = 1 divided
    by its own.

    Args:
        inputs: :func:`stex.stages.texcoords.stage_inputs` (``frame_ids`` ignored).
        params: the ``texcoords`` config section. steps: key-frame steps (ints >= 1).

    Returns:
        one dict per step, in ``steps``' order: ``step``, ``keyframes`` (count), ``energy``,
        ``seconds``, ``error_ratio``, ``speedup``.
    """
    steps = [int(n) for n in steps]
    if 1 not in steps or min(steps) < 1:
        raise ValueError(f"sampling steps {steps}: need 1 (every frame a key frame, the reference) and no step below 1")
    p = texcoords_params(params)
    kw = {k: v for k, v in inputs.items() if k != "frame_ids"}
    rows = []
    for n in steps:
        t0 = time.perf_counter()
        r = optimize_texcoords(params=dict(p, keyframe_step=n), progress=False, **kw)
        rows.append({"step": n, "keyframes": int(len(r["keyframes"])), "energy": final_energy(r["energy"]),
                     "seconds": round(time.perf_counter() - t0, 2)})
        log.info("texcoords sampling: key frames every %d frame(s): final E %.6g, %.1f s",
                 n, rows[-1]["energy"], rows[-1]["seconds"])
    ref = rows[steps.index(1)]
    for row in rows:
        row["error_ratio"] = row["energy"] / ref["energy"] if ref["energy"] > 0 else math.nan
        row["speedup"] = ref["seconds"] / row["seconds"] if row["seconds"] > 0 else math.nan
    return rows
