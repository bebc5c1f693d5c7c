"""Large motion between two frames: the tracker taken from frame 0 straight to frame k.

    python benchmarks/bench_tracking_jumps.py --scene demo            # k = 5, 10, 20, 30
    python benchmarks/bench_tracking_jumps.py --scene fox --ks 5 10
    python benchmarks/bench_tracking_jumps.py --scene real            # the real frame pairs
    python benchmarks/bench_tracking_jumps.py --scene demo --params '{"rigid_only": true}'

Synthetic scenes (``demo``: config/config.yaml's synthetic source; ``fox``: the skinned Fox of
config/scenes/fox.yaml): the frames are rendered in memory (true masks, the scene's depth and
colour degradations), the template stage runs on the true frame-0 mesh, and the tracker sees
two observations, frame 0 and frame k (the appearance model of the flow term is captured at
frame 0). Printed per k: the object's true motion between the two frames (mean vertex
displacement, mm, and the turn, degrees), the mean vertex error at frame k against the truth
over the vertices visible in the depth camera and over all vertices (mm), what the rigid stage
did (its Gauss-Newton steps, and whether it went on coarse to fine), and the clipped depth fit.

``real``: the real frame pairs of the tracking tests (tests/conftest.py real_tracking_pairs), a
template from the first frame's depth tracked to the second without flow; per pair, left where
it is, rigidly tracked and fully tracked: the mean clipped depth difference where mesh and depth
both cover the image (mm) and, where the pair has colour aligned with its depth (DeepDeform), a
photometric check: the mean absolute difference (grey levels, 0-255) between each vertex's
colour in the first frame and the colour where the mesh puts it in the second, over the vertices
the camera sees in both.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(1, str(REPO / "tests"))   # the real pairs are the tests' own (conftest)

from conftest import data_samples, real_tracking_pairs  # noqa: E402  (the tests' own reading of the samples)
from stex.camera import mask_in_depth, project_points  # noqa: E402
from stex.config import load_config  # noqa: E402
from stex.deformation import rigid_fit  # noqa: E402
from stex.mesh import transfer_vertices  # noqa: E402
from stex.readers.meshes import Mesh  # noqa: E402
from stex.render import rasterize, vertex_visibility  # noqa: E402
from stex.synth.scene import SyntheticScene  # noqa: E402
from stex.template import prepare_template, template_from_depth  # noqa: E402
from stex.frame_fit import depth_residual  # noqa: E402
from stex.tracking import Observation, TrackParams, depth_target, track_sequence  # noqa: E402

SCENES = {"demo": [], "fox": ["config/scenes/fox.yaml"]}


def seen_by_depth(V, F, K, size) -> np.ndarray:
    """(V,) bool: the vertices of the mesh V (V, 3) / F (F, 3) a camera K of ``size`` (W, H) sees."""
    return vertex_visibility(V, F, K, rasterize(V, F, K, *size).depth)[0]


def synthetic_jumps(scene_name: str, ks, overrides: dict) -> None:
    cfg = load_config(REPO / "config" / "config.yaml", *[REPO / f for f in SCENES[scene_name]])
    if scene_name == "fox":
        cfg["source"]["synthetic"]["gltf"]["path"] = str((REPO / cfg["source"]["synthetic"]["gltf"]["path"]).resolve())
    scene = SyntheticScene(cfg["source"]["synthetic"])
    cal = scene.calibration
    tmpl = prepare_template(Mesh(scene.true_vertices(0), scene.faces), cfg["template"])
    F = tmpl["faces"].astype(np.int64)
    emb = (tmpl["embedding/face"], tmpl["embedding/bary"])
    cfg["tracking"].update(overrides)
    params = TrackParams.from_dict(cfg["tracking"])
    truth = {t: transfer_vertices(scene.true_vertices(t), scene.faces, *emb) for t in [0, *ks]}

    def observation(t):
        r = scene.render_frame(t)
        fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
        return Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg), r.color, cal, r.true_mask)

    print(f"scene {scene_name}: template {len(truth[0])} vertices; overrides {json.dumps(overrides)}")
    print("| k | true motion | tracked: visible | all | rigid steps | coarse to fine | depth fit |\n|---|---|---|---|---|---|---|")
    first = observation(0)
    for k in ks:
        if k >= scene.n_frames:
            print(f"| {k} | beyond the scene's {scene.n_frames} frames | | | | | |")
            continue
        *_, (_, V, st) = track_sequence(truth[0], F, [first, observation(k)], params, progress=False,
                                        texcoords=tmpl["texcoords"], texcoord_faces=tmpl["texcoord_faces"])
        Vt = truth[k]
        R, _ = rigid_fit(truth[0], Vt)
        turn = np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()))
        motion = 1000 * np.linalg.norm(Vt - truth[0], axis=1).mean()
        vis = seen_by_depth(Vt, F, cal.depth.K, cal.depth.size)
        err = 1000 * np.linalg.norm(V - Vt, axis=1)
        print(f"| {k} | {motion:.0f} mm, {turn:.1f}° | {err[vis].mean():.2f} mm | {err.mean():.2f} mm | "
              f"{st.get('rigid_steps', '-')} | {'yes' if st.get('rigid_coarse_to_fine') else 'no'} | "
              f"{1000 * st['depth_residual_m']:.2f} mm |", flush=True)


def photometric_error(grey0, grey1, K, V0, V1, F) -> float:
    """Mean |grey1(pi(V1)) - grey0(pi(V0))| over the vertices seen in both frames (grey levels);
    grey0/grey1 (H, W) float32 images aligned with the depth camera K (3, 3), V0/V1 (V, 3) metres."""
    H, W = grey0.shape
    seen = seen_by_depth(V0, F, K, (W, H)) & seen_by_depth(V1, F, K, (W, H))
    u0 = project_points(V0[seen], K)[0].astype(np.float32)
    u1 = project_points(V1[seen], K)[0].astype(np.float32)
    a = cv2.remap(grey0, u0[:, None, 0], u0[:, None, 1], cv2.INTER_LINEAR)[:, 0]
    b = cv2.remap(grey1, u1[:, None, 0], u1[:, None, 1], cv2.INTER_LINEAR)[:, 0]
    return float(np.abs(a - b).mean())


def real_pairs(samples: Path, overrides: dict) -> None:
    dd = samples / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017" / "color"
    greys = {"DeepDeform": [cv2.cvtColor(cv2.imread(str(dd / f"000{i}.jpg")), cv2.COLOR_BGR2GRAY).astype(np.float32)
                            for i in (300, 600)]}
    print(f"real pairs; overrides {json.dumps(overrides)} (gn_iterations 8 as the tests' real_pair_fits)")
    print("| pair | as it is | rigid fit | tracked | rigid steps |\n|---|---|---|---|---|")
    for name, K, depths, masks in real_tracking_pairs(samples):
        V, F = template_from_depth(depths[0], K, masks[0], stride=2)
        targets = [depth_target(d, K, m) for d, m in zip(depths, masks)]
        grey = next((g for key, g in greys.items() if name.startswith(key)), None)
        cells, steps = [], "-"
        for Vb in [V, *[None] * 2]:
            if Vb is None:
                p = TrackParams(**{"gn_iterations": 8, **overrides, "rigid_only": len(cells) == 1, "w_flow": 0.0})
                *_, (_, Vb, st) = track_sequence(V, F, [Observation(t) for t in targets], p, progress=False)
                if len(cells) == 1:
                    steps = f"{st.get('rigid_steps', '-')}{' (coarse to fine)' if st.get('rigid_coarse_to_fine') else ''}"
            cell = f"{1000 * depth_residual(Vb, F, targets[1], union=False):.2f} mm"
            if grey is not None:
                cell += f", {photometric_error(grey[0], grey[1], K, V, Vb, F):.1f} grey"
            cells.append(cell)
        print(f"| {name} | {' | '.join(cells)} | {steps} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=[*SCENES, "real"], default="demo")
    ap.add_argument("--ks", type=int, nargs="+", default=[5, 10, 20, 30])
    ap.add_argument("--params", default="{}", help="JSON overrides of the tracking settings (TrackParams fields)")
    ap.add_argument("--samples", type=Path, default=data_samples())
    args = ap.parse_args()
    overrides = json.loads(args.params)
    unknown = sorted(set(overrides) - set(TrackParams.__dataclass_fields__))
    if unknown:
        raise ValueError(f"--params: {unknown} are not tracking settings (stex.tracking.TrackParams)")
    if args.scene == "real":
        real_pairs(args.samples, overrides)
    else:
        synthetic_jumps(args.scene, args.ks, overrides)
    return 0


if __name__ == "__main__":
    sys.exit(main())
