"""Benchmark template.from_scan and template.align on the synthetic turntable (acceptance: the
fused template of the procedural body within 2 mm of the true surface, closed, <= 2 min for 300
frames at 640x576; a template turned 90 degrees and moved 1 m aligned to frame 0 within 5 mm / 2
degrees).

The turntable (:class:`stex.synth.turntable.TurntableScene`, default degradations: Kinect-like
depth noise, holes, edge drop-outs) is rendered first (timed apart: a real scan is read, not
rendered), then masked and fused through the scan stage's own functions
(:func:`stex.stages.scan.masked_frames`, :func:`stex.scan.fuse_scan`); reported: wall and CPU time,
the symmetric mean distance to the true rest mesh, closedness, the pose errors. Then the true
template of the main synthetic scene's frame 0, turned and moved, is aligned to that frame.

    python benchmarks/bench_scan.py [--frames 300] [--depth 640x576] [--fx 504] [--voxel 0.003]
                                    [--object procedural|gltf] [--gltf PATH] [--cache FRAMES.npz] [--no-align]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex.scan import fuse_scan
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from stex.camera import mask_in_depth  # noqa: E402
from stex.config import section_params  # noqa: E402
from stex.masks import compute_mask  # noqa: E402
from stex.mesh import is_closed  # noqa: E402
from stex.scan import align_to_view, frame_points, fuse_scan, rotation_angle_deg, surface_distance  # noqa: E402
from stex.stages.scan import masked_frames, scan_masks  # noqa: E402
from stex.synth.scene import SyntheticScene, rotation  # noqa: E402
from stex.synth.turntable import TurntableScene  # noqa: E402


def synthetic(args, n_frames: int) -> dict:
    w, h = (int(x) for x in args.depth.split("x"))
    synth = {"n_frames": n_frames, "object": args.object, "depth": {"width": w, "height": h, "fx": args.fx}}
    if args.object == "gltf":
        synth["gltf"] = {"path": args.gltf}
    return section_params("source", {"kind": "synthetic", "synthetic": synth})["synthetic"]


def bench_scan(args) -> None:
    scan = section_params("template", {"scan": {"n_frames": args.frames, "voxel_m": args.voxel}})["scan"]
    scene = TurntableScene(synthetic(args, args.frames), scan["elevation_deg"])
    t = time.perf_counter()
    if args.cache and Path(args.cache).is_file():  # the same turntable rendered before: read, not rendered
        z = np.load(args.cache)
        if z["depth"].shape[0] != args.frames or z["depth"].shape[1:] != (scene.calibration.depth.height,
                                                                           scene.calibration.depth.width):
            raise SystemExit(f"{args.cache}: holds {z['depth'].shape} depth frames, not this turntable's")
        frames = [(k, c, d, None) for k, (c, d) in enumerate(zip(z["color"], z["depth"]))]
    else:
        frames = [(k, r.color, r.depth_mm, None) for k, r in ((k, scene.render_frame(k)) for k in range(args.frames))]
        if args.cache:
            np.savez(args.cache, color=np.stack([f[1] for f in frames]), depth=np.stack([f[2] for f in frames]))
    print(f"render: {args.frames} frames in {time.perf_counter() - t:.1f} s (not part of the stage's cost)")
    masks = scan_masks({}, scan)
    load = os.getloadavg()[0]
    t, c = time.perf_counter(), time.process_time()
    result = fuse_scan(masked_frames(iter(frames), scene.calibration, masks), scene.calibration, scan,
                       masks["depth_near_m"], masks["depth_far_m"])
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    V, F = result["vertices"], result["faces"]
    d = surface_distance(V, F, scene.true_vertices(0), scene.faces)
    T0 = scene.object_to_depth(0.0)
    err = [rotation_angle_deg((T0 @ np.linalg.inv(scene.object_to_depth(scene.time_of(k))))[:3, :3].T @ P[:3, :3])
           for k, P in enumerate(result["poses"])]
    print(f"scan: masks + fusion + closing {wall:.1f} s wall, {cpu:.1f} s CPU (load average {load:.1f} at start); "
          f"{len(F)} faces, closed {is_closed(V, F)}, fused {int(result['fused'].sum())}/{args.frames}, "
          f"turned {result['turned_deg']:.0f} degrees")
    print(f"  distance to the true surface: mean {1000 * d['mean']:.2f} mm (fused->true {1000 * d['a_to_b']:.2f}, "
          f"true->fused {1000 * d['b_to_a']:.2f}), p95 {1000 * d['p95']:.2f} mm, max {1000 * d['max']:.1f} mm")
    print(f"  pose rotation error: median {np.median(err):.2f}, max {np.max(err):.2f} degrees")


def bench_align(args) -> None:
    scene = SyntheticScene(synthetic(args, 1))
    r = scene.render_frame(0)
    mask, _ = compute_mask(r.color, r.depth_mm, scene.calibration, section_params("masks", {}))
    P = frame_points(r.depth_mm, mask_in_depth(mask, r.depth_mm, scene.calibration), r.color, scene.calibration,
                     0.3, 1.6)[0]
    V = scene.true_vertices(0)
    G = np.eye(4)
    G[:3, :3] = rotation("y", np.pi / 2)
    G[:3, 3] = [1.0, 0.0, 0.0]
    t = time.perf_counter()
    a = align_to_view(V @ G[:3, :3].T + G[:3, 3], scene.faces, P)
    E = a.transform @ G
    moved = np.linalg.norm(V @ E[:3, :3].T + E[:3, 3] - V, axis=1)
    print(f"align (turned 90 degrees, moved 1 m): rotation error {rotation_angle_deg(E[:3, :3]):.3f} degrees, vertex "
          f"error mean {1000 * moved.mean():.2f} mm, max {1000 * moved.max():.2f} mm, fitness {a.fitness:.3f}, "
          f"{time.perf_counter() - t:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--depth", default="640x576")
    ap.add_argument("--fx", type=float, default=504.0)
    ap.add_argument("--voxel", type=float, default=0.003)
    ap.add_argument("--object", choices=["procedural", "gltf"], default="procedural")
    ap.add_argument("--gltf", default="/work/shared/data_samples/gltf_fox/glTF-Binary/Fox.glb")
    ap.add_argument("--cache", default=None, help="an .npz of the rendered turntable: written when missing, "
                                                   "read when present (the same options must be given)")
    ap.add_argument("--no-align", action="store_true", help="only the scan")
    args = ap.parse_args()
    if not args.no_align:
        bench_align(args)
    bench_scan(args)


if __name__ == "__main__":
    main()
