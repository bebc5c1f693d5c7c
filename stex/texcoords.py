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
  kernel (:func:`_face_blocks_kernel`) and are summed into one CSC matrix per frame through a
  pattern built once per level; (H + λ (diag H + mean diag H) + 1e-4 I) δ = −g is solved by
  SuperLU (:class:`_SparseSystems`). Levenberg–Marquardt: λ starts at ``lm_lambda`` each level,
  follows Nielsen's rule on the gain ratio (actual / model decrease) after an accepted step and
  doubles (×2, ×4, ...) after a rejected one, up to ``backtracks`` re-solves. The step is clamped,
  gauge-projected and kept in the crop as above, and accepted only if neither E nor the objective
  it minimises, O = E + edge term (/ 255²), rises. Measured (bench_texcoords): the same or a lower
  O in 3-8x fewer steps, each 4-8x dearer (one LU per frame and trial: ≈ 7 ms at 3 000 unknowns,
  ≈ 75 ms at 7 000), the same accuracy — the stage is not convergence-limited — so 'jacobi'
  stays the default.
- **Monotone energy**: a level stops when no halving / re-solve helps, when the relative decrease
  is below ``rel_tol`` (the authors: 1e-5; default 1e-4, same accuracy, half the time), or after
  ``iterations`` steps (the authors: 300). The recorded E is non-increasing within every level
  for both solvers (and O for 'sparse').
- **Gauge** (``gauge`` 'weighted'): Eq. 1 only sees where the frames disagree: moving every frame's
  ξ of a vertex the same way (sliding the texture over the surface) leaves it unchanged, so the
  per-vertex mean of ξ − Φ over the stage's frames (where the vertex has a visible face) is
  unobserved. Without a rule for it (``gauge`` 'none', the authors) it random-walks under the
  small biases of the data term (noise, appearance changing in time, the silhouette): on the
  drift-free demo, 300 iterations per level moved ξ 0.39 px (median) off the truth in this mean
  alone. 'mean' holds it at 0 by subtracting it from every candidate ξ (image px, over the
  frames where the vertex is a corner of a visible face): ξ keeps tracking's average placement
  and takes only the frame-to-frame corrections. 'weighted' (default) holds the mean weighted by
  the proxy weights (the mean cosine of the vertex's visible faces at that frame) instead: the
  proxy colour is the cosine-weighted average of the frames, so this is where the proxy puts the
  texture, and a frame that sees the vertex frontally places it better than one at a grazing
  angle. Demo, 120 frames (bench_texcoords): 70.1 % median drift reduction against 68.2 % with
  'mean': the pairs at cosine 0.2-0.4 come from 0.66 to 0.62 px, 0.6-0.8 from 0.53 to 0.48 px,
  the frontal ones (0.8-1.0) give a little (0.47 → 0.50 px).
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
``face_photometric`` 'affine' ['none'] and ``solver`` 'sparse' ['jacobi', the default]. Measured
with ``benchmarks/bench_texcoords.py`` (median |ξ − truth| relative to |Φ − truth|): demo, 120
frames with the current degradations (exposure drift, wrinkles): 46.7 % reduction with gain
'none', robust_grey 0 and face_photometric 'none'; 65.0 % with gain and robust weights; 68.2 %
with face_photometric 'affine' (stage 71 s instead of ~130 s: the levels converge in fewer
steps); 70.1 % with the defaults (gauge 'weighted'; stage 42 s on a quiet core); paper scale, all
265 frames: 93.9 % with the defaults (92.8 % with gauge 'mean', 91.7 % before the face model;
the consensus of the plain-mean gauge, the truth slid by its mean drift over the visible
frames, is at 81.2 % on the demo and 94.5 % there). All measured with the synthetic camera looking
from below; from above (35a5f98, the camera's fix) the demo gives 71.7 % (|Φ − truth| 1.845 →
|ξ − truth| 0.522 px; consensus 83.0 %) and Table 3's ratios 1.0034 / 1.0075 / 1.0096 /
0.9959 for key frames every 2nd-5th frame. On the demo the wrinkled frames stay the
limit: their shading is not affine inside a face, so they are down-weighted rather than
explained.

Those figures are for the synthetic drift, which averages out over time by design. The tracker's
own error mostly does not: in the workflow's runs (``benchmarks/bench_registration.py RESULTS``,
every 5th frame, visible vertices) Φ lies 2.42 px from the truth (paper scene; demo 0.77), and
the per-vertex mean of the tracker's error over the frames that see the vertex, which Eq. 1
cannot observe, alone puts it 2.15 px off (demo 0.66: the consensus). ξ removes about half of
what varies between frames (|Φ − consensus| 0.55 → |ξ − consensus| 0.30 px; demo 0.26 → 0.19)
and ends 2.12 px from the truth (demo 0.72), at that bound. With exact meshes there is nothing to
remove, and ξ moves 0.12 px off the truth on the demo (``bench_texcoords.py --drift 0``) and
0.39 px on the Fox (given meshes; its photos have motion blur).
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

log = logging.getLogger("stex.texcoords")

__all__ = ["SAMPLE_BARY", "CropStack", "build_stack", "keyframe_positions",
           "interpolate_displacements", "photometric_energy", "optimize_level",
           "optimize_texcoords", "write_texcoords", "texcoords_params", "displacement_picture",
           "stage_inputs", "final_energy", "sampling_table", "write_sampling_table"]

#: the authors' 15 barycentric samples per face (Optimizer.cu L5-7), rows (w0, w1, w2)
SAMPLE_BARY = np.array([
    (.5, .25, .25), (.25, .5, .25), (.25, .25, .5), (.8, .1, .1), (.1, .8, .1), (.1, .1, .8),
    (.5, .5, 0), (0, .5, .5), (.5, 0, .5), (.2, .2, .6), (.6, .2, .2), (.2, .6, .2),
    (.1, .5, .4), (.5, .4, .1), (.4, .1, .5)], dtype=np.float64)

#: texcoords.face_photometric modes, in the order of the kernels' integer code
FACE_PHOTOMETRIC = ("none", "offset", "affine")


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
def _gn_kernel(buf, off, hh, ww, x0, y0, xi, phi, faces, fvis, omega, gain, bary, proxy, C, qs,
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
def _face_blocks_kernel(buf, off, hh, ww, x0, y0, xi, phi, faces, pk, pf, omega, gain, bary, proxy,
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


class _Photometric:
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

    def __init__(self, stack: CropStack, faces, fvis, fw, bary, params):
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
        estimates and decays slowly (demo, 120 frames with exposure drift: 1.8 % RMS gain error
        after 2 rounds, converged after ~45; bench_texcoords drift reduction 55.7 % -> 63.5 %,
        and 65.0 % with the mode instead of the median)."""
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


def photometric_energy(stack: CropStack, xi, faces, face_visible, face_weight, params=None):
    """The photometric energy of the stage's frames at ``xi``, with the proxy recomputed there.

    Args:
        stack: the frames' crops (``blur`` is used: call ``stack.set_blur`` first).
        xi: (K, V, 2) float texture coordinates (colour px) of the stack's frames.
        faces: (F, 3) int; face_visible: (K, F) bool; face_weight: (K, F) float (cosines).
        params: ``texcoords`` section (samples_per_face, background_weight, robust_grey, gain).

    Returns:
        (E, proxy): E float = Σ ((C − P)/255)² over visible faces and samples (Eq. 1; its robust,
        gain-compensated form if ``robust_grey`` > 0 / ``gain`` 'frame', see :class:`_Photometric`);
        proxy (F, S) grey levels.
    """
    p = texcoords_params(params)
    bary = np.ascontiguousarray(SAMPLE_BARY[: int(p["samples_per_face"])])
    xi = np.ascontiguousarray(xi, np.float64)
    faces = np.ascontiguousarray(faces, np.int64)
    fvis = np.ascontiguousarray(face_visible, np.bool_)
    fw = np.ascontiguousarray(face_weight, np.float64)
    ph = _Photometric(stack, faces, fvis, fw, bary, p)
    ph.set_gain(xi)
    P, E, _, _ = ph.evaluate(xi)
    return E, P


def _vertex_used(fvis, faces, n_vertices):
    """(K, V) bool: the vertex is a corner of a face visible at that frame."""
    used = np.zeros((fvis.shape[0], n_vertices), bool)
    for j in range(3):
        for k in range(fvis.shape[0]):
            used[k, faces[fvis[k], j]] = True
    return used


def _gauge_weights(fvis, fw, faces, used, gauge: str) -> np.ndarray:
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


def _edge_energy(xi, phi, faces, fvis, edge_w, edge_vec) -> float:
    """The edge term of the Gauss-Newton kernels, / 255² (:func:`_edge_energy_kernel`)."""
    out = np.zeros(xi.shape[0])
    if faces.shape[0] and xi.shape[0] and edge_w > 0:
        _edge_energy_kernel(xi, phi, faces, fvis, float(edge_w), bool(edge_vec), out)
    return float(out.sum())


class _SparseSystems:
    """Per-frame sparse Gauss-Newton systems of one level (fixed pattern, values per step).

    Frame k's unknowns are the (u, v) of the vertices used at k (corner of a visible face), in
    vertex order: unknown 2·loc[k, v] + c. The (frame, face) blocks of :func:`_face_blocks_kernel`
    are summed into one CSC matrix per frame through a pattern built once per level.
    """

    def __init__(self, faces, pk, pf, qs, used):
        K = used.shape[0]
        self.pk, self.pf, self.qs = pk, pf, qs   # the visible pairs, frame-major (_Photometric)
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
        singularity guard). Hq (Q, 6, 6), gq (Q, 6): :func:`_face_blocks_kernel`. Direct sparse
        LU (SuperLU, symmetric mode, minimum-degree ordering on A + Aᵀ), one frame at a time:
        reusing a frame's factors as the preconditioner of later solves needed fewer
        factorisations but kept K factors in memory (≈ 3.6 GB at 64 paper-scale frames) and did
        not make the stage faster."""
        from scipy.sparse import csc_matrix
        from scipy.sparse.linalg import splu

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
    # ξ stays inside each frame's crop (and so inside the image)
    lo = np.stack([stack.x0, stack.y0], 1).astype(np.float64)[:, None, :]
    hi = (np.stack([stack.x0 + stack.w, stack.y0 + stack.h], 1) - 1).astype(np.float64)[:, None, :]
    hi = np.minimum(hi, np.array([width - 1.0, height - 1.0]))
    gauge = p["gauge"] != "none"
    edge_vec = p["edge_mode"] == "vector"
    edge_w = float(p["edge_weight"])
    clamp = float(p["step_clamp_px"])
    sparse = p.get("solver", "jacobi") == "sparse"
    used = _vertex_used(fvis, faces, xi.shape[1])
    gauge_w = _gauge_weights(fvis, fw, faces, used, p["gauge"])
    gauge_norm = np.maximum(gauge_w.sum(0), 1e-12)[:, None]

    def finish(step_xi):
        cand = step_xi
        if gauge:
            # hold every vertex's (weighted) mean displacement over its frames: Eq. 1 cannot see it
            dsp = gauge_w[..., None] * (cand - phi)
            cand = cand - used[..., None] * (dsp.sum(0) / gauge_norm)[None]
        return np.clip(cand, lo, hi)

    photo = _Photometric(stack, faces, fvis, fw, bary, p)
    photo.set_gain(xi)

    def evaluate(x):
        Px, Ex, om, Cx = photo.evaluate(x)
        return Px, Ex, Ex + _edge_energy(x, phi, faces, fvis, edge_w, edge_vec), om, Cx

    P, E, J, omega, C = evaluate(xi)
    energies, objectives = [E], [J]
    step = np.zeros_like(xi)
    if sparse:
        systems = _SparseSystems(faces, photo.pk, photo.pf, photo.qs, used)
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
            _face_blocks_kernel(stack.blur, stack.off, stack.h, stack.w, stack.x0, stack.y0, xi,
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
            _gn_kernel(stack.blur, stack.off, stack.h, stack.w, stack.x0, stack.y0, xi, phi,
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


def stage_inputs(scene, template, projection, frames_paths, masks_paths) -> dict:
    """What :func:`optimize_texcoords` reads, from a run's stores.

    Args:
        scene: the ``scene`` store (calibration: colour image size).
        template: the ``template`` store (faces).
        projection: the ``projection`` store (phi, vertex_visible, face_visible, face_cos, frame_ids).
        frames_paths: the ``frames`` block stores (colour images, read one frame at a time).
        masks_paths: the ``masks`` block stores (foreground masks for the proxy weights); empty =
            every pixel counts as foreground.

    Returns:
        dict with the keyword arguments of :func:`optimize_texcoords` (``load``, ``phi``,
        ``vertex_visible``, ``face_visible``, ``face_weight``, ``faces``, ``image_size``) and
        ``frame_ids``.
    """
    from stex.camera import Calibration
    from stex.io import FrameSequence, open_store

    sc = open_store(scene, "scene")
    cal = Calibration.from_dict(sc.attrs["calibration"])
    W, H = cal.color.width, cal.color.height
    proj = open_store(projection, "projection")
    ids = [int(i) for i in proj.attrs["frame_ids"]]
    frames = FrameSequence(list(frames_paths), "frames")
    masks = FrameSequence(list(masks_paths), "masks") if masks_paths else None

    def load(t):
        fid = ids[t]
        grey = cv2.cvtColor(np.asarray(frames.read("color", fid)), cv2.COLOR_RGB2GRAY)
        m = np.asarray(masks.read("mask", fid), bool) if masks is not None else np.ones((H, W), bool)
        return grey, m

    return {"load": load, "phi": np.asarray(proj["phi"][...], np.float64),
            "vertex_visible": np.asarray(proj["vertex_visible"][...], bool),
            "face_visible": np.asarray(proj["face_visible"][...], bool),
            "face_weight": np.asarray(proj["face_cos"][...], np.float64),
            "faces": np.asarray(open_store(template, "template")["faces"][...], np.int64),
            "image_size": (W, H), "frame_ids": ids}


def write_texcoords(scene, template, projection, frames_paths, masks_paths, params: dict, out) -> None:
    """Texture-coordinate stage: write the ``texcoords`` store (arguments: :func:`stage_inputs`;
    ``params``: the ``texcoords`` config section; ``out``: path of the store to write)."""
    from stex.io import create_store

    p = texcoords_params(params)
    inputs = stage_inputs(scene, template, projection, frames_paths, masks_paths)
    ids = inputs.pop("frame_ids")
    t0 = time.perf_counter()
    r = optimize_texcoords(params=p, **inputs)
    seconds = time.perf_counter() - t0
    attrs = {"frame_ids": ids, "keyframes": [ids[k] for k in r["keyframes"]],
             "color_size": list(inputs["image_size"]), "stages": r["stages"], "seconds": round(seconds, 2),
             "energy_rows": [s["name"] for s in r["stages"]]}
    with create_store(out, "texcoords", attrs=attrs, params=p) as store:
        a = store.create("xi", r["xi"].shape)
        for k in range(len(ids)):
            a[k] = r["xi"][k]
        store.write("valid", r["valid"])
        e = store.create("energy", r["energy"].shape)
        e[...] = r["energy"]


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
        inputs: :func:`stage_inputs` (``frame_ids`` ignored).
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


def write_sampling_table(scene, template, projection, frames_paths, masks_paths, params: dict,
                         steps, out_json) -> None:
    """:func:`sampling_table` of a run's stores (:func:`stage_inputs`), written as JSON
    ``{"steps": [rows], "params": the texcoords settings}`` to ``out_json`` (written under a
    temporary name and renamed when complete: :func:`stex.io.write_json`)."""
    from stex.io import write_json

    inputs = stage_inputs(scene, template, projection, frames_paths, masks_paths)
    rows = sampling_table(inputs, params, steps)
    write_json(out_json, {"steps": rows, "params": texcoords_params(params)})


# --------------------------------------------------------------------------------------------
# picture
# --------------------------------------------------------------------------------------------

def displacement_picture(color: np.ndarray, phi, xi, valid, scale: float = 10.0,
                         spacing_px: float = 12.0, max_px: float | None = None) -> np.ndarray:
    """The optimised displacements ξ − Φ of one frame as arrows over its colour image.

    Each drawn vertex gets an arrow from Φ to Φ + ``scale`` · (ξ − Φ), coloured by |ξ − Φ|
    (colormap turbo: dark blue 0 → dark red ``max_px``); the image is dimmed so the arrows
    read. At most one vertex per ``spacing_px`` × ``spacing_px`` cell is drawn (the first
    visible one in vertex order), so dense meshes do not turn into a smear.

    Args:
        color: (Hc, Wc, 3) uint8 RGB colour image of the frame.
        phi: (V, 2) float Φ, colour px (u = column, v = row; integer = pixel centre).
        xi: (V, 2) float ξ, colour px.
        valid: (V,) bool vertices to draw (visible in the frame).
        scale: arrow magnification (1 = true length).
        spacing_px: side of the cells that thin the arrows out (colour px; 0 = every vertex).
        max_px: displacement (px) at the top of the colormap; None = the largest drawn one.

    Returns:
        (Hc, Wc, 3) uint8 RGB picture with a caption giving ``scale`` and ``max_px``.
    """
    from stex.preview import _label

    color = np.asarray(color)
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"displacement_picture: color must be (H, W, 3) uint8, got {color.shape} {color.dtype}")
    phi = np.asarray(phi, np.float64)
    xi = np.asarray(xi, np.float64)
    valid = np.asarray(valid, bool)
    if phi.ndim != 2 or phi.shape[1] != 2 or xi.shape != phi.shape or valid.shape != phi.shape[:1]:
        raise ValueError(f"displacement_picture: phi {phi.shape}, xi {xi.shape}, valid {valid.shape}: "
                         "expected (V, 2), (V, 2), (V,)")
    if not scale > 0:
        raise ValueError(f"displacement_picture: scale must be > 0, got {scale}")
    H, W = color.shape[:2]
    ok = valid & np.isfinite(phi).all(1) & np.isfinite(xi).all(1)
    ok &= (phi[:, 0] >= 0) & (phi[:, 0] <= W - 1) & (phi[:, 1] >= 0) & (phi[:, 1] <= H - 1)
    idx = np.flatnonzero(ok)
    if spacing_px > 0 and len(idx):
        cell = np.floor(phi[idx] / spacing_px).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        idx = idx[np.sort(first)]
    d = xi[idx] - phi[idx]
    mag = np.linalg.norm(d, axis=1)
    top = float(max_px) if max_px is not None else float(mag.max()) if len(mag) else 1.0
    top = top if top > 0 else 1.0
    img = (color.astype(np.float32) * 0.5).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    col = lut[np.clip(np.round(mag / top * 255), 0, 255).astype(int)]
    a = np.round(phi[idx]).astype(int)
    b = np.round(phi[idx] + scale * d).astype(int)
    thick = max(1, round(min(H, W) / 600))
    for p0, p1, c in zip(a, b, col):  # a few thousand arrows at most: preview only
        cv2.arrowedLine(img, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])),
                        tuple(int(t) for t in c), thick, cv2.LINE_AA, tipLength=0.3)
    return _label(img, f"xi - phi x{scale:g}, colour 0..{top:.2f} px, {len(idx)} vertices")


def preview_texcoords(frames_paths, projection_path, texcoords_path, out, n_show: int = 3) -> None:
    """:func:`displacement_picture` of a few frames spread over the sequence, cropped to the
    object, side by side (the paper's figure of displacements)."""
    from stex.io import FrameSequence, open_store
    from stex.preview import _label, montage, write_png

    frames = FrameSequence(list(frames_paths), "frames")
    proj = open_store(projection_path, "projection")
    tc = open_store(texcoords_path, "texcoords")
    ids = list(tc.attrs["frame_ids"])
    tiles = []
    for k in np.linspace(0, len(ids) - 1, min(n_show, len(ids))).round().astype(int):
        valid = np.asarray(tc["valid"][k], bool)
        phi, xi = np.asarray(proj["phi"][k]), np.asarray(tc["xi"][k])
        img = displacement_picture(frames.read("color", ids[k]), phi, xi, valid)
        pts = phi[valid]
        if len(pts):
            (u0, v0), (u1, v1) = np.floor(pts.min(0)).astype(int) - 40, np.ceil(pts.max(0)).astype(int) + 40
            img = img[max(v0, 0):v1, max(u0, 0):u1]
        med = float(np.median(np.linalg.norm(xi[valid] - phi[valid], axis=1))) if valid.any() else 0.0
        tiles.append(_label(cv2.resize(img, (360, 360), interpolation=cv2.INTER_AREA),
                            f"frame {ids[k]}: median |xi - phi| {med:.2f} px"))
    write_png(out, montage(tiles, columns=len(tiles), width=360 * len(tiles)))
