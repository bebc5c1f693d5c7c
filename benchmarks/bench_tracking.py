"""Tracking accuracy and speed on synthetic scenes with ground truth.

    python benchmarks/bench_tracking.py --scene demo            # accuracy, every frame
    python benchmarks/bench_tracking.py --scene fox
    python benchmarks/bench_tracking.py --scene fox --skeleton      # skeleton-driven (also biped, biped_turning, fox_run)
    python benchmarks/bench_tracking.py --scene paper --frames 12   # speed at paper scale
    python benchmarks/bench_tracking.py --start 60 --frames 40 --params '{"w_silhouette": 0.25}'
    python benchmarks/bench_tracking.py --scene demo --ceiling model --capture-error   # where the error comes from
    python benchmarks/bench_tracking.py --scene demo --ceiling rigid --lower-half

Renders the scene's frames in memory (true masks, the scene's depth and colour degradations),
runs the template stage on the true frame-0 mesh (as the workflow does), tracks it and prints,
per frame, the mean vertex error against the truth carried to the template's topology (exact:
template vertices lie on the true surface) over the vertices visible in the depth camera and
over all vertices, and the solve time; beside them, what the tracking stage records without any
truth (stex.frame_fit.silhouette_iou against the true mask, and the clipped depth fit), to see
how well those track the true error.

``--ceiling`` replaces one input of the tracker by the truth, to measure how much of the error
each one causes (diagnostics only: the tracker itself never sees the truth):

- ``flow``: the flow term's targets are the true projections of the same vertices (its
  vertex set unchanged): a perfect appearance model and a perfect optical flow;
- ``flow-all``: the same, for every vertex visible in the depth camera at the predicted mesh;
- ``model``: the appearance model captures each texel at the true mesh (the optical flow is
  still DIS on the images): a model free of the mesh's drift at capture;
- ``rigid``: the rigid stage's motion is the scene's true object motion from the previous frame
  (exact for the demo's rigid lower half; the non-rigid stage runs as usual on top).

``--lower-half`` (procedural scenes) prints, per printed frame, the mean signed error along the
body's turn about its vertical axis (mm; + = towards increasing yaw) of the body's lower half,
which is rigid in the truth, over its vertices the depth camera sees and those it does not: how
far the tracked body twists there although the true one does not.

``--prior-floor`` tracks nothing: per frame it fits the tracker's rest-shape warp
(:func:`stex.tracking.fit_rest_warp`: the same graph, priors and L0 step) to the true positions
of the vertices the depth camera sees, starting from the rest shape's rigid (Kabsch) fit to the
truth, and prints how far every vertex then is from the truth, seen and unseen: the error of the
hidden side that perfect data on the seen side still leaves to the deformation prior.

``--capture-error`` prints, at each printed frame, the median misregistration (colour px) of the
texels the appearance model captured then (new / captured again): where the texel's surface
point truly projects minus where the tracked mesh put it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stex.config import load_config  # noqa: E402
from stex.render import rasterize, vertex_visibility  # noqa: E402
from stex.readers.meshes import Mesh  # noqa: E402
from stex.synth.scene import SyntheticScene  # noqa: E402
from stex.template import prepare_template  # noqa: E402
from stex.mesh import transfer_vertices  # noqa: E402
from stex.frame_fit import silhouette_iou  # noqa: E402
from stex.tracking import Observation, TrackParams, depth_target, track_sequence  # noqa: E402
from stex.camera import mask_in_depth  # noqa: E402
from stex.articulated import ArticulatedParams, ArticulatedTracker  # noqa: E402
from stex.skeleton import carry_skeleton, skeleton_from_skin  # noqa: E402

SCENES = {"demo": [], "fox": ["config/scenes/fox.yaml"], "biped": ["config/scenes/biped.yaml"],
          "biped_turning": ["config/scenes/biped_turning.yaml"], "fox_run": ["config/scenes/fox_run.yaml"],
          "paper": ["config/scenes/paper.yaml"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="demo")
    ap.add_argument("--frames", type=int, default=None, help="track only the first N frames")
    ap.add_argument("--params", default="{}", help="JSON overrides of the tracking settings (any stex.tracking.TrackParams field)")
    ap.add_argument("--start", type=int, default=0,
                    help="start at this frame from the true mesh carried to the template (the graph and the "
                         "appearance model then start there too): short experiments on a late stretch")
    ap.add_argument("--every", type=int, default=1, help="print every k-th frame")
    ap.add_argument("--configfile", action="append", default=[], help="extra config files (applied last)")
    ap.add_argument("--ceiling", choices=["flow", "flow-all", "model", "rigid"], default=None,
                    help="replace one input of the tracker by the truth (see the module docstring)")
    ap.add_argument("--lower-half", action="store_true",
                    help="procedural scenes: print the rigid lower half's error along the turn (mm), seen / unseen")
    ap.add_argument("--prior-floor", action="store_true",
                    help="no tracking: the rest-shape warp fitted to the true seen vertices, per frame (see the module docstring)")
    ap.add_argument("--skeleton", action="store_true",
                    help="skinned scenes: track with the object's skeleton (carried to the template as the "
                         "template stage does), the articulated solve before the graph")
    ap.add_argument("--capture-error", action="store_true",
                    help="print the appearance model's capture misregistration (px) per printed frame")
    args = ap.parse_args()
    overrides = json.loads(args.params)
    unknown = sorted(set(overrides) - set(TrackParams.__dataclass_fields__) - {"mode"}
                     - {f"skeleton_{k}" for k in ArticulatedParams.__dataclass_fields__})
    if unknown:
        raise ValueError(f"--params: {unknown} are not tracking settings (stex.tracking.TrackParams)")
    cfg = load_config(REPO / "config" / "config.yaml", *[REPO / f for f in SCENES[args.scene]], *args.configfile)
    if cfg["source"]["synthetic"]["object"] == "gltf":   # the scene file's path is relative to the repository
        cfg["source"]["synthetic"]["gltf"]["path"] = str((REPO / cfg["source"]["synthetic"]["gltf"]["path"]).resolve())
    scene = SyntheticScene(cfg["source"]["synthetic"])
    cal = scene.calibration
    if not 0 <= args.start < scene.n_frames:
        raise ValueError(f"--start {args.start} outside the scene's 0..{scene.n_frames - 1}")
    frames = range(args.start, min(args.start + (args.frames or scene.n_frames), scene.n_frames))
    tmpl = prepare_template(Mesh(scene.true_vertices(0), scene.faces), cfg["template"])
    F = tmpl["faces"].astype(np.int64)
    emb = (tmpl["embedding/face"], tmpl["embedding/bary"])
    V_start = transfer_vertices(scene.true_vertices(args.start), scene.faces, *emb)

    lower = None
    if args.lower_half:
        if not hasattr(scene.body, "vertex_h"):
            raise SystemExit("--lower-half needs a procedural scene (its body's lower half is rigid)")
        # height parameter of each template vertex on the source mesh; the lower half stays rigid
        # below h = 0.5 (procedural.py), 0.45 keeps clear of the nose's and the belly's tails
        h = (tmpl["embedding/bary"] * scene.body.vertex_h[scene.faces[tmpl["embedding/face"]]]).sum(1)
        lower = h < 0.45
    # --params go straight to the tracker, so settings not (yet) in the schema can be tried
    cfg["tracking"].update(overrides)
    params = TrackParams.from_dict(cfg["tracking"])
    if args.prior_floor:
        return _prior_floor(scene, frames, F, emb, params, args.every)
    articulated = None
    if args.skeleton:
        if scene.skeleton() is None or args.start:
            raise SystemExit("--skeleton needs a skinned scene (fox, biped) and --start 0")
        skel = carry_skeleton(skeleton_from_skin(*scene.skeleton(0)), scene.faces, *emb)
        articulated = ArticulatedTracker(skel, V_start, F, params, ArticulatedParams.from_dict(cfg["tracking"]))
    truth = {}          # the true mesh of the frame being tracked, for --ceiling / --capture-error
    capture_log = {}    # frame position -> (new texels' median px, re-captured texels' median px)
    _patch_tracker(args.ceiling, args.capture_error, truth, capture_log)

    def observations():
        for t in frames:
            truth["V"] = transfer_vertices(scene.true_vertices(t), scene.faces, *emb)
            # the object's true rigid motion since the previous tracked frame (--ceiling rigid)
            truth["rigid_step"] = (np.eye(4) if t == frames.start else
                                   scene.object_to_depth(scene.time_of(t))
                                   @ np.linalg.inv(scene.object_to_depth(scene.time_of(t - 1))))
            r = scene.render_frame(t)
            truth["mask"] = r.true_mask
            fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
            yield Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg), r.color, cal, r.true_mask)

    print(f"scene {args.scene}: frames {frames.start}..{frames.stop - 1}; template {len(tmpl['vertices'])} vertices, {len(F)} faces "
          f"(source mesh {len(scene.faces)} faces); params {json.dumps(cfg['tracking'])}")
    rows = []
    for pos, V, st in track_sequence(V_start, F, observations(), params, progress=False,
                                     texcoords=tmpl["texcoords"], texcoord_faces=tmpl["texcoord_faces"],
                                     articulated=articulated):
        t = frames[pos]
        Vt = truth["V"]   # frame t: the observations generator has just set it
        vis = _seen_by_depth(Vt, F, cal)
        err = np.linalg.norm(V - Vt, axis=1)
        iou = silhouette_iou(V, F, truth["mask"], cal)
        rows.append((err[vis].mean(), err.mean(), st["seconds"], st.get("lm_rejected", 0), st.get("lm_failed", 0),
                     st.get("frame_fallback", 0), iou, st.get("depth_residual_m", np.nan),
                     st.get("rigid_coarse_to_fine", 0)))
        if pos % args.every == 0:
            cap = ""
            if args.capture_error and pos in capture_log:
                cap = "  captured texels off by {:.2f} px new / {:.2f} px again".format(*capture_log[pos])
            if lower is not None:
                cap += "  lower half along the turn {:+.2f} mm seen / {:+.2f} mm unseen".format(
                    *_along_turn(scene, t, V[lower], Vt[lower], vis[lower]))
            print(f"frame {t:4d}: visible {1000 * err[vis].mean():5.1f} mm  all {1000 * err.mean():5.1f} mm  "
                  f"max {1000 * err.max():6.1f} mm  silhouette IoU {iou:.3f}  depth fit {1000 * rows[-1][7]:5.1f} mm  "
                  f"{st['seconds']:.2f} s{cap}", flush=True)
    r = np.array(rows)
    if args.ceiling:
        print(f"ceiling: {args.ceiling} (truth in place of one input of the tracker)")
    print(f"worst frame visible: {1000 * r[:, 0].max():.2f} mm (frame {frames[r[:, 0].argmax()]}); "
          f"worst frame all: {1000 * r[:, 1].max():.2f} mm (frame {frames[r[:, 1].argmax()]}); "
          f"frames within 5 / 15 mm: {(r[:, 0] <= 0.005).mean() * 100:.0f} % / {(r[:, 1] <= 0.015).mean() * 100:.0f} % "
          f"(visible within 15 mm: {(r[:, 0] <= 0.015).mean() * 100:.0f} %); "
          f"median {np.median(r[:, 2]):.2f} s per frame (first frame excluded: {np.median(r[1:, 2]) if len(r) > 1 else float('nan'):.2f} s); "
          f"step guard: {int(r[:, 3].sum())} steps re-solved with damping, {int(r[:, 4].sum())} rounds stopped, {int(r[:, 5].sum())} frames fell back; "
          f"the rigid stage went coarse to fine at {int(r[:, 8].sum())} frames")
    return 0


def _seen_by_depth(V, F, calibration) -> np.ndarray:
    """(V,) bool: the vertices of the mesh V (V, 3) / F (F, 3) that the depth camera sees."""
    K = calibration.depth.K
    return vertex_visibility(V, F, K, rasterize(V, F, K, *calibration.depth.size).depth)[0]


def _prior_floor(scene, frames, F, emb, params, every) -> int:
    """``--prior-floor``: per frame, the rest-shape warp fitted to the true seen vertices."""
    from stex.deformation import build_graph, compose_rigid, deform, identity_params, rigid_fit
    from stex.tracking import fit_rest_warp

    cal = scene.calibration
    rest = transfer_vertices(scene.true_vertices(0), scene.faces, *emb)
    graph = build_graph(rest, F, params.node_spacing_m, params.k_nodes, volume_links=params.volume_links,
                        volume_range=params.volume_link_range)
    nodes = rest[graph.nodes]
    rows = []
    for t in frames:
        Vt = transfer_vertices(scene.true_vertices(t), scene.faces, *emb)
        vis = _seen_by_depth(Vt, F, cal)
        # start where the tracker's rigid stage would at best: the rest's rigid fit to the truth
        R, tr = rigid_fit(rest, Vt)
        seen = np.flatnonzero(vis)
        x = fit_rest_warp(rest, graph, compose_rigid(identity_params(len(nodes)), nodes, R, tr), seen, Vt[seen], params)
        err = 1000 * np.linalg.norm(deform(rest, nodes, graph, x) - Vt, axis=1)
        rigid = 1000 * np.linalg.norm(rest @ R.T + tr - Vt, axis=1).mean()
        rows.append((err[vis].mean(), err[~vis].mean() if (~vis).any() else np.nan, err.mean()))
        if (t - frames.start) % every == 0:
            print(f"frame {t:4d}: seen {rows[-1][0]:5.2f} mm  unseen {rows[-1][1]:6.2f} mm  all {rows[-1][2]:6.2f} mm  "
                  f"({len(seen)} vertices seen; the rigid fit alone {rigid:5.1f} mm)", flush=True)
    r = np.array(rows)
    print(f"prior floor: worst frame seen {r[:, 0].max():.2f} mm; unseen {np.nanmax(r[:, 1]):.2f} mm; "
          f"all {r[:, 2].max():.2f} mm (frame {frames[int(r[:, 2].argmax())]}); frames within 15 mm on all "
          f"vertices: {(r[:, 2] <= 15).mean() * 100:.0f} %")
    return 0


def _along_turn(scene, t, V, Vt, seen):
    """Mean of (tracked - true) along the object's turn about its vertical axis at frame t, in mm,
    over ``seen`` and the rest; + = towards increasing yaw (the turn's direction over frames 0-30
    and 90-120 of the demo, against it over 30-90). V, Vt (n, 3) depth-camera metres, seen (n,)."""
    M = scene.object_to_depth(scene.time_of(t))
    tangent = np.cross(M[:3, 1], Vt - M[:3, 3])
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True) + 1e-12
    along = 1000 * ((V - Vt) * tangent).sum(1)
    return tuple(float(along[m].mean()) if m.any() else float("nan") for m in (seen, ~seen))


def _patch_tracker(ceiling, capture_error, truth, capture_log):
    """Wrap stex.tracking's flow targets and the appearance model's capture for ``--ceiling`` and
    ``--capture-error``; ``truth["V"]`` holds the current frame's true vertices (V, 3)."""
    import stex.tracking as tracking
    from stex.camera import project_points, transform_points

    flow_constraints = tracking.flow_constraints
    capture = tracking.AppearanceModel.capture
    solve_rigid = tracking._solve_rigid

    def colour_px(X, calibration):  # (n, 3) points in the depth camera -> (n, 2) colour pixels
        return project_points(transform_points(calibration.depth_to_color, X), calibration.color.K)[0]

    def oracle_flow(pred, faces, model, image, mask, calibration, *a, **k):
        if ceiling == "flow-all":
            fid = np.flatnonzero(_seen_by_depth(pred, faces, calibration))
        else:
            fid, _ = flow_constraints(pred, faces, model, image, mask, calibration, *a, **k)
        return fid, colour_px(truth["V"][fid], calibration)

    def logged_capture(model, vertices, image, calibration, min_cos=0.5, frame=0, refresh_margin=None):
        before = model.captured_at.copy()
        filled = model.texture[..., -1].ravel() > 0
        out = capture(model, truth["V"] if ceiling == "model" else vertices, image, calibration, min_cos, frame,
                      refresh_margin)
        if capture_error:
            sel = model.captured_at[model.texels] != before[model.texels]   # captured just now
            corners, bary = model.faces[model.texel_face[sel]], model.texel_bary[sel][:, :, None]
            off = np.linalg.norm(colour_px((bary * truth["V"][corners]).sum(1), calibration)
                                 - colour_px((bary * vertices[corners]).sum(1), calibration), axis=1)
            again = filled[model.texels[sel]]
            capture_log[frame] = tuple(float(np.median(off[m])) if m.any() else float("nan") for m in (~again, again))
        return out

    def true_rigid_stage(*a, **k):   # the rigid stage's (R, t, stats): x' = R x + t
        _, _, stats = solve_rigid(*a, **k)
        return truth["rigid_step"][:3, :3], truth["rigid_step"][:3, 3], stats

    if ceiling in ("flow", "flow-all"):
        tracking.flow_constraints = oracle_flow
    if ceiling == "rigid":
        tracking._solve_rigid = true_rigid_stage
    if ceiling == "model" or capture_error:
        tracking.AppearanceModel.capture = logged_capture


if __name__ == "__main__":
    sys.exit(main())
