"""Does the tracking-quality signal (stex.tracking_quality) tell lost frames from good ones?

    NUMBA_NUM_THREADS=1 nice -n 5 python benchmarks/bench_tracking_quality.py            # everything
    python benchmarks/bench_tracking_quality.py --only dev                               # the dev set
    python benchmarks/bench_tracking_quality.py --cache /tmp/q --rejudge                 # judge again, no tracking
    python benchmarks/bench_tracking_quality.py --template-ratios                        # the scale cue only

A labelled set of tracked frames from small synthetic scenes (reduced image size, motion blur
off, a coarse procedural body): each track is the tracker as it is (``good``) or a track made to
fail: ``few_rigid`` (one fine rigid step, one coarse step, every 3rd frame), ``wrong_pose`` (the
template turned 25 degrees about the body's axis and moved 3 cm at the first frame),
``dropped`` (runs of 12 frames dropped, every 2nd frame between them), ``jumps`` (every 10th
frame), ``rigid_only`` (no graph: the body's deformation is not followed), failures that stay
failed: ``rigid_noflow`` (rigid only, no colour term: a slow slide), ``few_noflow`` (one
Gauss-Newton step a stage, no colour term, every 4th frame), ``scaled`` (the template 10 %
too large), ``skip`` (every 15th frame, a crippled rigid stage), and on the Fox the walk tracked
without a skeleton (the ``good`` track's frames). A frame is lost where the mean error
of the vertices the depth camera sees, against the truth, exceeds 15 mm (``LOST_M``); a vertex
where its own error does.

The thresholds (stex.tracking_quality.THRESHOLDS) were chosen on the dev set only (``--grid``):
the demo scene (config/config.yaml's synthetic source at this size), procedural body 1, and the
tracks made to fail on them. The headline is the test set: two other procedural bodies (other
seeds, shapes and motion) and the Fox, each with its failing tracks. Printed: per set the frames, lost frames, precision and recall of
"lost" per frame and per vertex; false alarms (share of good frames / seen vertices judged lost)
on the demo's good track and on the real frame pairs (tests/conftest.py real_tracking_pairs;
DeepDeform with its colour and the appearance model captured at the first frame).
``--cache DIR`` keeps each track's per-frame signals and meshes; the cues of this tree
(stex.tracking_quality.QualityMonitor) are judged again from the cached meshes, the frames
rendered again (``*.sig.npz``, ``--no-replay`` to skip), so a new cue needs no new tracking;
``--rejudge`` reads the cache only, to try thresholds. On the loaded 2-core machine every track together took
about an hour and a half in four processes (15-37 s wall a frame).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(1, str(REPO / "tests"))

from conftest import data_samples, real_tracking_pairs  # noqa: E402
from stex.camera import mask_in_depth  # noqa: E402
from stex.config import load_config  # noqa: E402
from stex.mesh import transfer_vertices  # noqa: E402
from stex.readers.meshes import Mesh  # noqa: E402
from stex.render import rasterize, vertex_visibility  # noqa: E402
from stex.synth.scene import SyntheticScene  # noqa: E402
from stex.template import prepare_template, template_from_depth  # noqa: E402
from stex.tracking import Observation, TrackParams, depth_target, track_sequence  # noqa: E402
from stex.flow import AppearanceModel, flow_image  # noqa: E402
from stex.tracking_quality import THRESHOLDS, QualityMonitor, QualityThresholds, judge, template_area_ratio  # noqa: E402

LOST_M = 0.015
SIGNAL_KEYS = ("seen", "depth_m", "outside_px", "flow_px", "flow_fail", "m_per_px")
SMALL = {"color": {"width": 320, "height": 240, "fx": 280.0}, "depth": {"width": 160, "height": 144, "fx": 126.0},
         "texture_size": 256, "procedural": {"n_around": 48, "n_rings": 24},
         "degradations": {"motion_blur": {"enabled": False}}}
# the scenes: name -> (set, source.synthetic overrides on top of SMALL, frames)
SCENES = {
    "demo": ("dev", {}, 120),
    "body_s1": ("dev", {"seed": 1, "procedural": {"radius_m": 0.12, "height_m": 0.45, "twist_rad": 0.6}}, 120),
    "body_s2": ("test", {"seed": 2, "procedural": {"radius_m": 0.17, "height_m": 0.55, "bend_rad": 0.8,
                                                    "bulge": 0.25}, "yaw_period_s": 5.0}, 120),
    "body_s3": ("test", {"seed": 3, "procedural": {"radius_m": 0.14, "bend_period_s": 3.0, "squash": 0.12}}, 120),
    "fox": ("test", "fox", 40),
}
# the tracks: name -> (frame positions from the scene's frames, tracking overrides, template turn deg, shift m)
TRACKS = {
    "good": (lambda n: list(range(0, n, 3)), {}, 0.0, 0.0),
    "few_rigid": (lambda n: list(range(0, n, 4)),
                  {"rigid_iterations": 1, "rigid_max_iterations": 1, "gn_iterations": 2}, 0.0, 0.0),
    "wrong_pose": (lambda n: list(range(0, n, 3)), {}, 25.0, 0.03),
    "dropped": (lambda n: [t for t in range(0, n, 2) if (t // 12) % 2 == 0], {}, 0.0, 0.0),
    "jumps": (lambda n: list(range(0, n, 10)), {}, 0.0, 0.0),
    "rigid_only": (lambda n: list(range(0, n, 3)), {"rigid_only": True}, 0.0, 0.0),
    # failures that stay failed: no colour term to pull a slid mesh back, a crippled solve, a
    # template of the wrong size, long skips
    "rigid_noflow": (lambda n: list(range(0, n, 3)), {"rigid_only": True, "w_flow": 0.0, "rigid_w_flow": 0.0},
                     0.0, 0.0),
    "few_noflow": (lambda n: list(range(0, n, 4)), {"rigid_iterations": 1, "rigid_max_iterations": 1,
                                                    "gn_iterations": 1, "w_flow": 0.0, "rigid_w_flow": 0.0},
                   0.0, 0.0),
    "scaled": (lambda n: list(range(0, n, 3)), {}, 0.0, 0.0),
    "skip": (lambda n: list(range(0, n, 15)), {"rigid_iterations": 2, "rigid_max_iterations": 4}, 0.0, 0.0),
}
TEMPLATE_SCALE = {"scaled": 1.1}   # the template grown about its centre: a template that does not fit


def _merge(a: dict, b: dict) -> dict:
    out = copy.deepcopy(a)
    for k, v in b.items():
        out[k] = _merge(out.get(k, {}), v) if isinstance(v, dict) else v
    return out


def scene_config(name: str) -> tuple[dict, dict]:
    """(source.synthetic, the whole config) of a scene of SCENES."""
    _, extra, _ = SCENES[name]
    if extra == "fox":
        cfg = load_config(REPO / "config" / "config.yaml", REPO / "config" / "scenes" / "fox.yaml")
        syn = cfg["source"]["synthetic"]
        syn["gltf"]["path"] = str((REPO / syn["gltf"]["path"]).resolve())
        syn = _merge(syn, {k: v for k, v in SMALL.items() if k != "procedural"})
    else:
        cfg = load_config(REPO / "config" / "config.yaml")
        syn = _merge(_merge(cfg["source"]["synthetic"], SMALL), extra)
    return syn, cfg


def seen_by_depth(V, F, K, size) -> np.ndarray:
    return vertex_visibility(V, F, K, rasterize(V, F, K, *size).depth)[0]


def initial_template(scene, cfg: dict, track: str, t0: int):
    """(template, faces, embedding, the template's vertices at frame ``t0`` as the track starts:
    turned, shifted or grown where TRACKS / TEMPLATE_SCALE say)."""
    _, _, turn_deg, shift = TRACKS[track]
    # the body as it is (no splitting): small scenes, quick tracks
    tmpl = prepare_template(Mesh(scene.true_vertices(0), scene.faces), {**cfg["template"], "min_faces": 0})
    F = tmpl["faces"].astype(np.int64)
    emb = (tmpl["embedding/face"], tmpl["embedding/bary"])
    V0 = transfer_vertices(scene.true_vertices(t0), scene.faces, *emb)
    if turn_deg or shift:
        axis = scene.object_to_depth(scene.time_of(t0))[:3, 1]   # the body's vertical axis
        c = V0.mean(0)
        V0 = (V0 - c) @ Rotation.from_rotvec(np.deg2rad(turn_deg) * axis).as_matrix().T + c + [shift, 0.0, 0.0]
    if track in TEMPLATE_SCALE:
        V0 = (V0 - V0.mean(0)) * TEMPLATE_SCALE[track] + V0.mean(0)
    return tmpl, F, emb, V0


def template_area(scene_name: str, track: str, tracked: dict) -> dict:
    """The scale cue (stex.tracking_quality.template_area_ratio) of a cached track: its starting
    template against its first frame rendered again; per frame (the same value)."""
    syn, cfg = scene_config(scene_name)
    syn["n_frames"] = SCENES[scene_name][2]
    scene = SyntheticScene(syn)
    t0 = int(tracked["frames"][0])
    _, F, _, V0 = initial_template(scene, cfg, track, t0)
    r = scene.render_frame(t0)
    target = depth_target(r.depth_mm / 1000.0, scene.calibration.depth.K,
                          mask_in_depth(r.true_mask, r.depth_mm, scene.calibration))
    return {"template_area_ratio": np.full(len(tracked["frames"]), template_area_ratio(V0, F, target))}


def print_template_ratios(names: list[str], samples: Path | None) -> None:
    """The scale cue of each scene's starting templates (as it is, turned, grown), and of templates
    from the real pairs' first depth at strides 1, 2, 4 (``samples``: None leaves them out); no
    tracking."""
    print("| scene | set | " + " | ".join(f"{tr} template" for tr in ("good", "wrong_pose", "scaled")) + " |")
    print("|---|---|---|---|---|")
    for s in names:
        cells = [f"{template_area(s, tr, {'frames': [0]})['template_area_ratio'][0]:.3f}"
                 for tr in ("good", "wrong_pose", "scaled")]
        print(f"| {s} | {SCENES[s][0]} | " + " | ".join(cells) + " |", flush=True)
    if samples is None:
        return
    print("\n| real pair, template from depth | stride 1 | stride 2 | stride 4 |\n|---|---|---|---|")
    for name, K, depths, masks in real_tracking_pairs(samples):
        target = depth_target(depths[0], K, masks[0])
        cells = [f"{template_area_ratio(*template_from_depth(depths[0], K, masks[0], stride=k), target):.3f}"
                 for k in (1, 2, 4)]
        print(f"| {name} | " + " | ".join(cells) + " |")


def run_track(scene_name: str, track: str) -> dict:
    """Track one (scene, track) pair; per frame the signals, the truth's errors, the time."""
    syn, cfg = scene_config(scene_name)
    n = SCENES[scene_name][2]
    syn["n_frames"] = n
    scene = SyntheticScene(syn)
    cal = scene.calibration
    pick, overrides, _, _ = TRACKS[track]
    frames = pick(n)
    tmpl, F, emb, V0 = initial_template(scene, cfg, track, frames[0])
    params = TrackParams.from_dict({**cfg["tracking"], "mode": "track", **overrides})
    truth = {}

    def observations():
        for t in frames:
            truth["V"] = transfer_vertices(scene.true_vertices(t), scene.faces, *emb)
            r = scene.render_frame(t)
            fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
            yield Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg), r.color, cal, r.true_mask)

    rows = {k: [] for k in (*SIGNAL_KEYS, "err", "true_seen", "V")}
    secs = []
    for _, V, st in track_sequence(V0, F, observations(), params, progress=False, texcoords=tmpl["texcoords"],
                                   texcoord_faces=tmpl["texcoord_faces"]):
        q = st["quality"]
        for k in SIGNAL_KEYS:
            rows[k].append(q[k])
        rows["err"].append(np.linalg.norm(V - truth["V"], axis=1).astype(np.float32))
        rows["V"].append(V.astype(np.float32))   # the tracked mesh: new cues are judged again from it
        rows["true_seen"].append(seen_by_depth(truth["V"], F, cal.depth.K, cal.depth.size))
        secs.append(st["seconds"])
    out = {k: np.stack(v) for k, v in rows.items()}
    out["frames"] = np.array(frames)
    out["seconds"] = np.array(secs)
    return out


REPLAY_KEYS = (*SIGNAL_KEYS, "ref_flow_px", "ref_fail")
SIGNAL_KEYS_ALL = (*REPLAY_KEYS, "template_area_ratio")


def replay_signals(scene_name: str, track: str, tracked: dict) -> dict:
    """The signals of :class:`stex.tracking_quality.QualityMonitor` (this tree's cues) for a cached
    track's meshes (``tracked["V"]``): the frames rendered again, the tracker's appearance model
    captured again from the same meshes as the tracker did (so its signals are the tracker's)."""
    syn, cfg = scene_config(scene_name)
    syn["n_frames"] = SCENES[scene_name][2]
    scene = SyntheticScene(syn)
    cal = scene.calibration
    tmpl = prepare_template(Mesh(scene.true_vertices(0), scene.faces), {**cfg["template"], "min_faces": 0})
    F = tmpl["faces"].astype(np.int64)
    params = TrackParams.from_dict({**cfg["tracking"], "mode": "track", **TRACKS[track][1]})
    monitor = QualityMonitor(F, tmpl["texcoords"], tmpl["texcoord_faces"], params, rest=tracked["V"][0])
    model = None
    rows = {k: [] for k in REPLAY_KEYS}
    for pos, (t, V) in enumerate(zip(tracked["frames"], tracked["V"].astype(np.float64))):
        r = scene.render_frame(int(t))
        fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
        obs = Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg), r.color, cal, r.true_mask)
        use_flow = params.w_flow > 0
        image = flow_image(r.color, params.flow_channels)
        q = monitor.frame(pos, V, obs, model if use_flow else None, image if use_flow else None)
        for k in REPLAY_KEYS:
            rows[k].append(q[k])
        if use_flow:
            if model is None:
                model = AppearanceModel(tmpl["texcoords"], tmpl["texcoord_faces"], F, params.model_size, image.shape[2])
            model.capture(V, image, cal, params.model_min_cos, pos, params.model_refresh_cos)
    return {k: np.stack(v) for k, v in rows.items()}


def real_pair_tracks(samples: Path) -> list[dict]:
    """The real pairs tracked (template from the first frame's depth; DeepDeform with its colour,
    aligned with its depth): per pair the signals of both frames (no truth: all good tracks)."""
    import cv2
    from stex.camera import Calibration
    out = []
    dd = samples / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017" / "color"
    for name, K, depths, masks in real_tracking_pairs(samples):
        V, F = template_from_depth(depths[0], K, masks[0], stride=2)
        colour = None
        if name.startswith("DeepDeform"):
            colour = [cv2.cvtColor(cv2.imread(str(dd / f"000{i}.jpg")), cv2.COLOR_BGR2RGB) for i in (300, 600)]
        H, W = depths[0].shape
        cam = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "width": W, "height": H}
        cal = Calibration.from_dict({"depth": cam, "color": cam, "depth_to_color": np.eye(4).tolist()}) if colour else None
        obs = [Observation(depth_target(d, K, m), colour[i] if colour else None, cal, m if colour else None)
               for i, (d, m) in enumerate(zip(depths, masks))]
        p = TrackParams(**{"gn_iterations": 8, "w_flow": 0.25 if colour else 0.0})
        rows = {k: [] for k in REPLAY_KEYS}
        for _, _, st in track_sequence(V, F, obs, p, progress=False):
            for k in REPLAY_KEYS:
                rows[k].append(st["quality"][k])
        out.append({"name": name, **{k: np.stack(v) for k, v in rows.items()}})
    return out


def signals_of(track: dict, i: int) -> dict:
    return {k: track[k][i] for k in SIGNAL_KEYS_ALL if k in track}


def judged(track: dict, th: QualityThresholds) -> list:
    """:func:`judge` frame by frame along the track, with the memory of the last frame's decision."""
    out, was = [], False
    for i in range(len(track["seen"])):
        res = judge(signals_of(track, i), th, was)
        was = res[1]
        out.append(res)
    return out


def truth_lost(track: dict) -> np.ndarray:
    return np.array([e[v].mean() > LOST_M if v.any() else True for e, v in zip(track["err"], track["true_seen"])])


def scores(tracks: list[dict], th: QualityThresholds) -> dict:
    """Frame and vertex confusion counts of the judge against the truth over ``tracks``."""
    c = {"frames": 0, "lost": 0, "tp": 0, "fp": 0, "fn": 0, "v_tp": 0, "v_fp": 0, "v_fn": 0, "v_seen": 0}
    for tr in tracks:
        for i, (vlost, lost, _) in enumerate(judged(tr, th)):
            sig = signals_of(tr, i)
            truth = truth_lost(tr)[i]
            c["frames"] += 1
            c["lost"] += truth
            c["tp"] += lost and truth
            c["fp"] += lost and not truth
            c["fn"] += truth and not lost
            seen = sig["seen"]
            vt = tr["err"][i] > LOST_M
            c["v_tp"] += int((vlost & vt & seen).sum())
            c["v_fp"] += int((vlost & ~vt & seen).sum())
            c["v_fn"] += int((~vlost & vt & seen).sum())
            c["v_seen"] += int(seen.sum())
    return c


GRID = {"frame_share": [0.1, 0.15, 0.2, 0.25, 0.3, 0.4], "frame_flow_m": [0.004, 0.006, 0.008, 0.012, 1.0],
        "frame_fail_share": [0.3, 0.5, 0.7, 1.0], "frame_depth_m": [0.003, 0.004, 0.005, 0.006, 1.0],
        "frame_ref_flow_m": [0.003, 0.004, 0.005, 0.006, 0.008, 0.012, 1.0],
        "frame_ref_fail_share": [0.3, 0.5, 0.7, 1.0], "reacquire_share": [0.02, 0.05, 0.1, 0.2],
        "reacquire_flow_m": [0.003, 0.004, 1.0], "reacquire_depth_m": [0.003, 0.004, 1.0],
        "template_area_ratio": [1.015]}
# reacquire_share 0 (a track once lost stays lost) is left out on purpose: one false alarm would
# then take every later frame from the labeling, and a track the tracker recovers would never count again.
SUMMARY_OF = {"frame_share": "share", "frame_flow_m": "flow_m", "frame_fail_share": "fail_share",
              "frame_depth_m": "depth_mean_m", "frame_ref_flow_m": "ref_flow_m", "frame_ref_fail_share": "ref_fail_share", "template_area_ratio": "template_area_ratio"}


def choose_thresholds(tracks: list[dict], th: QualityThresholds) -> None:
    """``--grid``: the frame thresholds of GRID (every combination; the vertex thresholds as
    ``th``) on ``tracks`` (the dev set), with the memory of the last frame's decision: those with
    false alarms on at most 5 % of the good frames (the acceptance's bound), ranked by the smaller
    of precision and recall, then F1; prints the best ten."""
    import itertools
    off = QualityThresholds(**{**th.__dict__, **{k: np.inf for k in SUMMARY_OF}})
    combos = np.array(list(itertools.product(*GRID.values())), np.float64)   # (n, len(GRID))
    names = list(GRID)
    tp, fp, fn = (np.zeros(len(combos), np.int64) for _ in range(3))
    n_good = n_lost = 0
    for tr in tracks:
        truth = truth_lost(tr)
        was = np.zeros(len(combos), bool)
        for i in range(len(tr["frames"])):
            _, _, s = judge(signals_of(tr, i), off)
            lost = np.full(len(combos), s["no_data"])
            for j, k in enumerate(names):
                if k in SUMMARY_OF:
                    lost |= np.nan_to_num(s[SUMMARY_OF[k]], nan=0.0) > combos[:, j]
            reacquired = ((s["share"] < combos[:, names.index("reacquire_share")])
                          & ~(np.nan_to_num(s["ref_flow_m"], nan=0.0) >= combos[:, names.index("reacquire_flow_m")])
                          & (np.nan_to_num(s["depth_mean_m"], nan=np.inf) < combos[:, names.index("reacquire_depth_m")]))
            lost |= was & ~reacquired
            was = lost
            tp += lost & truth[i]
            fp += lost & ~truth[i]
            fn += ~lost & truth[i]
        n_good += int((~truth).sum())
        n_lost += int(truth.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        p, r = tp / (tp + fp), tp / (tp + fn)
        f1 = 2 * tp / (2 * tp + fp + fn)
    ok = fp <= 0.05 * n_good
    order = np.lexsort((fp, -np.nan_to_num(f1), -np.nan_to_num(np.minimum(p, r))))
    order = order[ok[order]]
    print(f"dev set: {n_good + n_lost} frames, {n_lost} lost")
    print("| min(P, R) | F1 | precision | recall | false alarms | " + " | ".join(GRID) + " |")
    print("|" + "---|" * (5 + len(GRID)))
    for i in order[:10]:
        print(f"| {min(p[i], r[i]):.3f} | {f1[i]:.3f} | {p[i]:.3f} | {r[i]:.3f} | {fp[i]} | "
              + " | ".join(f"{x:g}" for x in combos[i]) + " |")


def _ratio(a, b):
    return a / b if b else float("nan")


def _cached_real(args) -> list[dict]:
    """:func:`real_pair_tracks`, through the cache when there is one ([] without the samples)."""
    path = args.cache / "real.npz" if args.cache else None
    if path is not None and path.exists():
        flat = dict(np.load(path))
        return [{k.split("/", 1)[1]: (str(v) if k.endswith("/name") else v) for k, v in flat.items()
                 if k.startswith(f"{i}/")} for i in range(int(flat["n"]))]
    if args.rejudge or not (args.samples / "killingfusion_snoopy").is_dir():
        return []
    pairs = real_pair_tracks(args.samples)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, n=len(pairs), **{f"{i}/{k}": v for i, r in enumerate(pairs) for k, v in r.items()})
    return pairs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["dev", "test", "all"], default="all")
    ap.add_argument("--no-real", action="store_true", help="leave out the real pairs")
    ap.add_argument("--scenes", nargs="+", default=None, help="these scenes of SCENES only")
    ap.add_argument("--tracks", nargs="+", default=list(TRACKS), help="these tracks of TRACKS only")
    ap.add_argument("--cache", type=Path, default=None, help="keep / read each track's signals here (npz)")
    ap.add_argument("--rejudge", action="store_true", help="read the cache only (no tracking)")
    ap.add_argument("--thresholds", default="{}", help="JSON overrides of stex.tracking_quality.THRESHOLDS")
    ap.add_argument("--samples", type=Path, default=data_samples())
    ap.add_argument("--replay", action=argparse.BooleanOptionalAction, default=True,
                    help="judge the cached meshes with this tree's cues (cached as *.sig.npz)")
    ap.add_argument("--template-ratios", action="store_true",
                    help="print the scale cue of each scene's starting templates only (no tracking)")
    ap.add_argument("--grid", action="store_true", help="search GRID for the thresholds on the dev set (from --cache)")
    args = ap.parse_args()
    th = QualityThresholds(**{**THRESHOLDS.__dict__, **json.loads(args.thresholds)})
    names = args.scenes or [s for s, (role, _, _) in SCENES.items() if args.only in ("all", role)]
    if args.template_ratios:
        print_template_ratios(names, None if args.no_real else args.samples)
        return 0
    tracks = {}
    t0, c0 = time.perf_counter(), time.process_time()
    for s in names:
        for tr in args.tracks:
            if s == "fox" and tr != "good":
                continue        # the Fox's walk without a skeleton is the failing track there
            path = args.cache / f"{s}_{tr}.npz" if args.cache else None
            if path is not None and path.exists():
                tracks[(s, tr)] = dict(np.load(path))
                continue
            if args.rejudge:
                continue
            tracks[(s, tr)] = run_track(s, tr)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(path, **tracks[(s, tr)])
            r = tracks[(s, tr)]
            err = [e[v].mean() for e, v in zip(r["err"], r["true_seen"])]
            print(f"tracked {s}/{tr}: {len(r['frames'])} frames, {int((np.array(err) > LOST_M).sum())} lost, "
                  f"median {np.median(r['seconds']):.2f} s a frame", flush=True)
    for (s, tr), r in tracks.items():
        if args.replay and "V" in r:    # the cues of this tree, from the cached meshes
            path = args.cache / f"{s}_{tr}.sig.npz" if args.cache else None
            if path is not None and path.exists():
                r.update(dict(np.load(path)))
            elif not args.rejudge:
                r.update(replay_signals(s, tr, r))
                if path is not None:
                    np.savez_compressed(path, **{k: r[k] for k in REPLAY_KEYS})
        if "V" in r:    # the scale cue: the starting template against the first frame
            path = args.cache / f"{s}_{tr}.scale.npz" if args.cache else None
            if path is not None and path.exists():
                r.update(dict(np.load(path)))
            else:
                r.update(template_area(s, tr, r))
                if path is not None:
                    np.savez_compressed(path, **{"template_area_ratio": r["template_area_ratio"]})
    if args.grid:
        choose_thresholds([v for (s, _), v in tracks.items() if SCENES[s][0] == "dev"], th)
        return 0
    print(f"thresholds: {json.dumps(th.__dict__)}")
    print("| set | tracks | frames | lost (truth) | precision | recall | vertex precision | vertex recall |")
    print("|---|---|---|---|---|---|---|---|")
    for role in ("dev", "test"):
        sel = [v for (s, _), v in tracks.items() if SCENES[s][0] == role]
        if not sel:
            continue
        c = scores(sel, th)
        print(f"| {role} | {len(sel)} | {c['frames']} | {c['lost']} | {_ratio(c['tp'], c['tp'] + c['fp']):.3f} | "
              f"{_ratio(c['tp'], c['tp'] + c['fn']):.3f} | {_ratio(c['v_tp'], c['v_tp'] + c['v_fp']):.3f} | "
              f"{_ratio(c['v_tp'], c['v_tp'] + c['v_fn']):.3f} |")
    print("\n| track | frames | lost (truth) | judged lost | false alarms (good frames) | false alarms (seen vertices) |")
    print("|---|---|---|---|---|---|")
    for (s, tr), v in tracks.items():
        c = scores([v], th)
        good = c["frames"] - c["lost"]
        name = f"{s}/{'walk without a skeleton, every 3rd frame' if s == 'fox' else tr}"
        print(f"| {name} | {c['frames']} | {c['lost']} | {c['tp'] + c['fp']} | "
              f"{c['fp']}/{good} ({100 * _ratio(c['fp'], good):.1f} %) | {100 * _ratio(c['v_fp'], c['v_seen']):.2f} % |")
    if args.only != "dev" and not args.no_real:
        for r in _cached_real(args):
            res = judged(r, th)
            vl = sum(int((x[0] & r["seen"][i]).sum()) for i, x in enumerate(res))
            print(f"| real: {r['name']} | {len(res)} | (good) | {sum(x[1] for x in res)} | "
                  f"{sum(x[1] for x in res)}/{len(res)} | {100 * vl / max(int(r['seen'].sum()), 1):.2f} % |")
    print(f"\nwall {time.perf_counter() - t0:.0f} s, CPU {time.process_time() - c0:.0f} s (machine shared, loaded)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
