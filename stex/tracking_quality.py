"""Tracking quality without ground truth: per vertex and per frame, has the tracker lost the object?

A mesh that slides along the surface still fits the depth, and a loose mask (one that also holds
an arm) lowers the silhouette IoU of a perfect track (docs/tracking.md), so neither alone tells a
good frame from a lost one. Each frame's mesh is scored here from four things the user has
(:func:`vertex_signals`), per vertex the depth camera sees:

- depth: |observed - mesh| depth along the ray at the vertex's depth pixel, away from depth
  discontinuities (the pixel and its 8 neighbours foreground depth without a jump);
- silhouette: how far (colour px) the vertex projects outside the frame's mask; one-sided, so a
  mask that includes extra things costs nothing;
- appearance: optical flow from the tracker's appearance model (texels captured at earlier
  frames, :class:`stex.flow.AppearanceModel`) rendered at the mesh to the colour frame
  (:func:`stex.flow.flow_constraints`): where the mesh is right the model sits on the image and
  the flow is about zero; where it has slid, the flow shows how far (px);
- flow consistency: a vertex whose texel is known and seen squarely enough but whose flow fails
  the forward-backward check in every channel: model and image disagree there.

The same flow against a reference model captured at the first frames only (:class:`QualityMonitor`)
sees a slow slide that the tracker's own model, drifting with the mesh, follows.
:func:`judge` turns them into a lost/ok decision per vertex and per frame with the thresholds
of :data:`THRESHOLDS`, chosen on the dev scenes (the demo, a procedural body) and tracks made to
fail on them, with the memory of the last frame's decision
(docs/decisions/tracking_quality.md; benchmarks/bench_tracking_quality.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from stex.camera import project_points, transform_points
from stex.atlas import build_atlas
from stex.flow import AppearanceModel, flow_constraints, flow_image
from stex.render import rasterize, vertex_visibility

__all__ = ["QualityThresholds", "THRESHOLDS", "vertex_signals", "judge", "frame_quality", "QualityMonitor",
           "template_area_ratio"]

DEPTH_CLIP_M = 0.1         # a depth difference counts at most this much (m): beyond, the pixel is another surface
REFERENCE_FRAMES = 3      # the first frames' appearance is the reference (QualityMonitor): before any drift
APPEARANCE_MAX_SIDE = 640  # the appearance flow runs on colour images downscaled to this longer side (px) at most


@dataclass(frozen=True)
class QualityThresholds:
    """When a vertex and a frame count as lost (see :func:`judge`).

    vertex_depth_m: a vertex's depth difference beyond this (m) marks it.
    vertex_outside_px: a vertex this far outside the mask (colour px) marks it.
    vertex_flow_m: a vertex whose appearance flow moves it this far (m on the surface: px times
        its metres per colour pixel) marks it.
    frame_share: a frame is lost where more than this share of its seen vertices is marked.
    frame_flow_m: ... or where the median appearance flow of its measured vertices exceeds this (m).
    frame_fail_share: ... or where more than this share of the vertices the flow could measure
        fails its forward-backward check.
    frame_depth_m: ... or where the mean depth difference of its seen vertices exceeds this (m): a
        mesh that no longer follows the surface's deformation.
    frame_ref_flow_m, frame_ref_fail_share: as frame_flow_m and frame_fail_share, against the
        first frames' appearance (:class:`QualityMonitor`).
    reacquire_share, reacquire_flow_m, reacquire_depth_m: after a lost frame, a frame is ok again
        only under this share of lost seen vertices, this median flow against the first frames (m)
        and this mean depth difference (m).
    template_area_ratio: every frame is lost where the template, at the first frame, covers more
        than this many times the first frame's foreground depth pixels (:func:`template_area_ratio`):
        a template too large for the object, which the tracker squeezes onto the depth.
    """

    vertex_depth_m: float = 0.015
    vertex_outside_px: float = 3.0
    vertex_flow_m: float = 0.01
    frame_share: float = 0.15
    frame_flow_m: float = 0.008
    frame_fail_share: float = 0.3
    frame_depth_m: float = 0.006
    frame_ref_flow_m: float = 0.008
    frame_ref_fail_share: float = 0.5
    reacquire_share: float = 0.1
    reacquire_flow_m: float = 0.003
    reacquire_depth_m: float = 0.004
    template_area_ratio: float = 1.015


THRESHOLDS = QualityThresholds()


def _outside_distance(mask: np.ndarray, uv: np.ndarray, margin_px: int = 8) -> np.ndarray:
    """Distance (px) from each pixel position ``uv`` (n, 2) to the nearest pixel of ``mask`` (H, W)
    bool, 0 inside it; over the box of the mask and the points only (exact there: the nearest mask
    pixel lies inside the mask's box)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return np.full(len(uv), np.inf)
    H, W = mask.shape
    px = np.rint(uv).astype(np.int64)
    x0 = max(min(cols[0], px[:, 0].min(initial=cols[0])) - margin_px, 0)
    y0 = max(min(rows[0], px[:, 1].min(initial=rows[0])) - margin_px, 0)
    x1 = min(max(cols[-1], px[:, 0].max(initial=cols[-1])) + margin_px + 1, W)
    y1 = min(max(rows[-1], px[:, 1].max(initial=rows[-1])) + margin_px + 1, H)
    dist = cv2.distanceTransform((~mask[y0:y1, x0:x1]).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    inside = (px[:, 0] >= x0) & (px[:, 0] < x1) & (px[:, 1] >= y0) & (px[:, 1] < y1)
    out = np.full(len(uv), np.inf, np.float32)       # off the image: as far out as it gets
    out[inside] = dist[px[inside, 1] - y0, px[inside, 0] - x0]
    return out


def _resized(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """An image (H, W[, C]) uint8 or a mask (H, W) bool at ``size`` (W, H): area-averaged, masks nearest."""
    if a.dtype == bool:
        return cv2.resize(a.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    out = cv2.resize(np.ascontiguousarray(a), size, interpolation=cv2.INTER_AREA)
    return out.reshape(size[1], size[0], *a.shape[2:])


def vertex_signals(vertices, faces, target, mask=None, calibration=None, model: AppearanceModel | None = None,
                   image=None, prev_image=None, consistency_px: float = 1.0, min_cos: float = 0.15,
                   erode_px: int = 1, reference: AppearanceModel | None = None) -> dict:
    """The quality signals of one frame's mesh, per vertex (see the module docstring).

    Args:
        vertices: (V, 3) float the frame's mesh (m, depth-camera coordinates); faces (F, 3) int.
        target: the frame's foreground depth (:class:`stex.tracking.DepthTarget`: ``points``
            (H, W, 3) m, ``valid`` (H, W) bool, ``K`` (3, 3)).
        mask: (Hc, Wc) bool the frame's object mask in the colour camera, or None (no silhouette).
        calibration: :class:`stex.camera.Calibration` (needed with ``mask`` or ``model``).
        model: the tracker's appearance model before this frame's capture, or None (no appearance).
        image: (Hc, Wc, C) uint8 the frame's flow channels (:func:`stex.flow.flow_image`, the
            model's), with ``model``; prev_image the previous frame's, or None.
        consistency_px, min_cos, erode_px: the flow term's settings (``tracking.flow_*``).
        reference: an appearance model captured at the first frames only (:class:`QualityMonitor`),
            or None: the same flow against it gives ``ref_flow_px`` and ``ref_fail``.

    Returns a dict of (V,) arrays: ``seen`` bool (the depth camera sees the vertex), ``depth_m``
    float32 (|observed - mesh| depth along the ray, clipped at DEPTH_CLIP_M; NaN where not seen or
    without clean depth), ``outside_px`` float32 (distance outside the mask; NaN where not seen
    or without a mask), ``flow_px`` float32 (the smallest appearance flow over the channels that
    pass; NaN where none), ``flow_fail`` bool (measurable, but no channel passes), ``m_per_px``
    float32 (metres per colour pixel at the vertex; NaN without a calibration); ``ref_flow_px``
    and ``ref_fail`` as ``flow_px`` and ``flow_fail`` against ``reference``.
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    n = len(V)
    H, W = target.valid.shape
    nan = np.full(n, np.nan, np.float32)
    out = {"seen": np.zeros(n, bool), "depth_m": nan.copy(), "outside_px": nan.copy(), "flow_px": nan.copy(),
           "flow_fail": np.zeros(n, bool), "m_per_px": nan.copy(), "ref_flow_px": nan.copy(),
           "ref_fail": np.zeros(n, bool)}
    if not np.isfinite(V).all():
        return out
    seen = vertex_visibility(V, F, target.K, rasterize(V, F, target.K, W, H).depth)[0]
    out["seen"] = seen
    ids = np.flatnonzero(seen)
    if not len(ids):
        return out
    # depth, away from discontinuities: the pixel and its neighbours all clean foreground depth
    clean = cv2.erode(target.valid.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    uv, z = project_points(V[ids], target.K)
    px = np.rint(uv).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    ok[ok] = clean[px[ok, 1], px[ok, 0]]
    out["depth_m"][ids[ok]] = np.minimum(np.abs(target.points[px[ok, 1], px[ok, 0], 2] - z[ok]), DEPTH_CLIP_M)
    if calibration is None:
        return out
    c = calibration.color
    Vc = transform_points(calibration.depth_to_color, V)
    out["m_per_px"] = (Vc[:, 2] / c.K[0, 0]).astype(np.float32)
    if mask is not None:
        out["outside_px"][ids] = _outside_distance(np.asarray(mask, bool), project_points(Vc[ids], c.K)[0])
    models = {"flow": model, "ref_flow": reference}
    if image is not None and any(m is not None for m in models.values()):
        # Why downscaled: at a paper-scale colour camera the flow costs as much as half a frame's
        # tracking; a vertex off by a centimetre is still pixels off at the smaller size.
        factor = min(1.0, APPEARANCE_MAX_SIDE / max(c.width, c.height))
        if factor < 1.0:
            calibration = replace(calibration, color=c.scaled(factor))
            c = calibration.color
            image, prev_image, mask = (None if a is None else _resized(a, c.size) for a in (image, prev_image, mask))
        uv_c = project_points(transform_points(calibration.depth_to_color, V), c.K)[0]
        # measurable: seen squarely enough in the colour camera
        Vs = transform_points(calibration.depth_to_color, V)
        cvis, ccos = vertex_visibility(Vs, F, c.K, rasterize(Vs, F, c.K, c.width, c.height).depth)
        for key, m in models.items():
            if m is None:
                continue
            fid, u1 = flow_constraints(V, F, m, image, mask, calibration, consistency_px, min_cos, erode_px=erode_px,
                                       prev_image=prev_image)
            if len(fid):
                d = np.linalg.norm(u1 - uv_c[fid], axis=1) / factor   # full-size px
                best = np.full(n, np.inf)
                np.minimum.at(best, fid, d)
                got = np.isfinite(best)
                out[f"{key}_px"][got] = best[got]
            # ... and with a known texel
            known = m.texture.reshape(-1, m.channels + 1)[m.vertex_texel, -1] > 0
            out[f"{key}_fail"] = cvis & (ccos > min_cos) & known & seen & ~np.isfinite(out[f"{key}_px"])
    return out


def template_area_ratio(vertices, faces, target) -> float:
    """The template's silhouette in the depth camera over the first frame's foreground depth pixels;
    both count only pixels with depth (``target.measured``, ``target.foreground``: depth edges
    included, so the ratio does not grow as the depth image shrinks; ``target.valid`` where not
    given).

    Why: a template too large for the object is pulled onto the depth by the tracker, so neither the
    depth fit nor the one-sided silhouette sees it; its own extent, before tracking, does, where it
    covers measured background. Pixels without depth say nothing (a template from depth fills the
    object's holes). A right template scores about 1, one 10 % too large about its square. NaN
    without foreground depth or with a non-finite template.
    """
    V = np.asarray(vertices, np.float64)
    H, W = target.valid.shape
    fg = target.valid if target.foreground is None else target.foreground
    n_fg = int(np.count_nonzero(fg))
    if not n_fg or not np.isfinite(V).all():
        return float("nan")
    d = rasterize(V, np.asarray(faces, np.int64), target.K, W, H).depth
    cover = np.isfinite(d) & (d > 0)
    if target.measured is not None:
        cover &= target.measured
    return float(np.count_nonzero(cover) / n_fg)


def judge(signals: dict, th: QualityThresholds = THRESHOLDS, was_lost: bool = False) -> tuple[np.ndarray, bool, dict]:
    """Lost or ok, per vertex and for the frame, from :func:`vertex_signals`.

    A seen vertex is lost where its depth difference exceeds ``th.vertex_depth_m``, it lies more
    than ``th.vertex_outside_px`` outside the mask, or its appearance flow (against the tracker's
    model or the first frames' reference) exceeds ``th.vertex_flow_m`` (px times its metres per
    pixel). The frame is lost where the depth camera sees none of the mesh (no data), or more
    than ``th.frame_share`` of its seen vertices are lost, or the median appearance flow exceeds
    ``th.frame_flow_m`` (the reference's ``th.frame_ref_flow_m``), or more than
    ``th.frame_fail_share`` of the measurable vertices fail the flow's forward-backward check, or
    the mean depth difference exceeds ``th.frame_depth_m``, or the template's first-frame
    ``signals["template_area_ratio"]`` (where given) exceeds ``th.template_area_ratio``. With ``was_lost`` (the previous
    frame was lost) the frame also stays lost until it is re-acquired: under
    ``th.reacquire_share`` of its seen vertices lost, the reference's median flow (where
    measured) under ``th.reacquire_flow_m`` and the mean depth difference under
    ``th.reacquire_depth_m``. Why: a drifted mesh can fit the depth again while
    still sliding; without this memory a slow drift flickers between lost and ok.

    Returns (vertex lost (V,) bool, frame lost, summary: ``share`` of seen vertices lost,
    ``flow_m`` and ``ref_flow_m`` median appearance flow (m, NaN without), ``fail_share``,
    ``ref_fail_share``, ``depth_mean_m`` mean depth difference (m), ``template_area_ratio`` (the
    signals', NaN without), ``no_data`` bool, ``why`` str naming
    what decided, "" where ok).
    """
    seen = signals["seen"]
    depth, outside = signals["depth_m"], signals["outside_px"]
    flow_m = signals["flow_px"] * signals["m_per_px"]
    ref_m = signals.get("ref_flow_px", np.full(len(seen), np.nan)) * signals["m_per_px"]
    with np.errstate(invalid="ignore"):
        lost = seen & ((depth > th.vertex_depth_m) | (outside > th.vertex_outside_px) | (flow_m > th.vertex_flow_m)
                       | (ref_m > th.vertex_flow_m))
    n_seen = int(seen.sum())

    def median_and_fail(f, fail):
        measured = np.isfinite(f)
        med = float(np.median(f[measured])) if measured.any() else float("nan")
        n_meas = int(measured.sum() + fail.sum())
        return med, float(fail.sum() / n_meas) if n_meas else 0.0

    flow_med, fail_share = median_and_fail(flow_m, signals["flow_fail"])
    ref_med, ref_fail_share = median_and_fail(ref_m, signals.get("ref_fail", np.zeros(len(seen), bool)))
    share = float(lost.sum() / n_seen) if n_seen else 1.0
    no_data = n_seen == 0 or not np.isfinite(depth).any()
    why = []
    if no_data:
        why.append("no depth of the object under the mesh")
    if share > th.frame_share:
        why.append(f"{100 * share:.0f} % of the seen vertices off the depth, the mask or the appearance")
    if flow_med > th.frame_flow_m:
        why.append(f"the appearance model sits {1000 * flow_med:.1f} mm (median) from the image")
    if ref_med > th.frame_ref_flow_m:
        why.append(f"the first frames' appearance sits {1000 * ref_med:.1f} mm (median) from the image")
    if fail_share > th.frame_fail_share:
        why.append(f"{100 * fail_share:.0f} % of the appearance flow inconsistent")
    if ref_fail_share > th.frame_ref_fail_share:
        why.append(f"{100 * ref_fail_share:.0f} % of the flow from the first frames' appearance inconsistent")
    depth_mean = float(np.nanmean(depth)) if not no_data else float("nan")
    area = float(signals.get("template_area_ratio", np.nan))
    if area > th.template_area_ratio:
        why.append(f"the template covers {area:.2f} times the first frame's depth of the object: too large")
    if depth_mean > th.frame_depth_m:
        why.append(f"the mesh is {1000 * depth_mean:.1f} mm off the depth (mean)")
    if was_lost and not why and not (share < th.reacquire_share and not ref_med >= th.reacquire_flow_m
                                     and depth_mean < th.reacquire_depth_m):
        why.append("not re-acquired since the last lost frame")
    summary = {"share": share, "flow_m": flow_med, "fail_share": fail_share, "ref_flow_m": ref_med,
               "ref_fail_share": ref_fail_share, "depth_mean_m": depth_mean, "template_area_ratio": area, "no_data": no_data, "why": "; ".join(why)}
    return lost, bool(why), summary


def frame_quality(vertices, faces, target, mask=None, calibration=None, model=None, image=None, prev_image=None,
                  th: QualityThresholds = THRESHOLDS, **flow_settings) -> dict:
    """:func:`vertex_signals` then :func:`judge`: a dict with the signals, ``vertex_lost`` (V,) bool,
    ``lost`` bool and the summary's keys."""
    sig = vertex_signals(vertices, faces, target, mask, calibration, model, image, prev_image, **flow_settings)
    vertex_lost, lost, summary = judge(sig, th)
    return {**sig, "vertex_lost": vertex_lost, "lost": lost, **summary}


class QualityMonitor:
    """The tracker's per-frame judgement with memory (:func:`judge` with ``was_lost``) and a
    reference appearance model captured at the first ``REFERENCE_FRAMES`` frames only.

    Why a reference: the tracker's own model captures new texels where the mesh already is, so it
    drifts with the mesh and cannot see a slow slide; the first frames' texture, captured before
    any drift, can. It is judged even where the tracker's flow term is off (``w_flow`` 0), from the
    frame's colour image.
    """

    def __init__(self, faces, texcoords=None, texcoord_faces=None, params=None, th: QualityThresholds = THRESHOLDS,
                 reference_frames: int = REFERENCE_FRAMES, rest=None):
        self.faces, self.rest = np.asarray(faces, np.int64), rest
        self.texcoords, self.texcoord_faces = texcoords, texcoord_faces
        g = (lambda k, d: getattr(params, k, d))
        self.channels, self.size = g("flow_channels", "grey+chroma"), g("model_size", 1024)
        self.capture_cos = g("model_min_cos", 0.3)
        self.flow = {"consistency_px": g("flow_consistency_px", 1.0), "min_cos": g("flow_min_cos", 0.15),
                     "erode_px": g("flow_erode_px", 1)}
        self.th, self.reference_frames = th, reference_frames
        self.reference, self.prev_image, self.was_lost = None, None, False
        self.area_ratio = float("nan")

    def atlas(self, vertices=None) -> tuple[np.ndarray, np.ndarray]:
        """The atlas (texcoords, texcoord faces) given, or built once (from ``rest`` where given) and
        shared with the tracker's model."""
        if self.texcoords is None:
            self.texcoords, self.texcoord_faces = build_atlas(self.rest if self.rest is not None else vertices,
                                                              self.faces, self.size, 2)
        return self.texcoords, self.texcoord_faces

    def frame(self, pos: int, vertices, obs, model=None, image=None) -> dict:
        """Judge frame position ``pos``'s mesh (V, 3) against the observation ``obs`` (``target``,
        ``image``, ``mask``, ``calibration``), the tracker's ``model`` before this frame's capture
        and its flow ``image`` (None: made from ``obs.image``); as :func:`frame_quality`."""
        if image is None and obs.image is not None and obs.calibration is not None:
            image = flow_image(obs.image, self.channels)
        captured = self.reference is not None and pos > 0
        if pos == 0:
            self.area_ratio = template_area_ratio(self.rest if self.rest is not None else vertices, self.faces,
                                                  obs.target)
        sig = vertex_signals(vertices, self.faces, obs.target, obs.mask, obs.calibration, model, image,
                             self.prev_image, reference=self.reference if captured else None, **self.flow)
        sig["template_area_ratio"] = self.area_ratio
        vertex_lost, lost, summary = judge(sig, self.th, self.was_lost)
        if image is not None and pos < self.reference_frames and not lost and np.isfinite(vertices).all():
            if self.reference is None:
                self.reference = AppearanceModel(*self.atlas(vertices), self.faces, self.size, image.shape[2])
            self.reference.capture(vertices, image, obs.calibration, self.capture_cos, pos)
        self.was_lost, self.prev_image = lost, image
        return {**sig, "vertex_lost": vertex_lost, "lost": lost, **summary}
