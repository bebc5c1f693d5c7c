"""Benchmark stex.poses.pose_table: rigid poses K_{t→t'} for every frame pair of a long sequence.

Scene: the paper-scale synthetic scene (config/scenes/paper.yaml: 265 frames at 30 fps, the
procedural body with n_around=144, n_rings=70, i.e. 9,938 vertices / 19,872 faces), vertices
from ``SyntheticScene.true_vertices``. Times the whole table (T(T−1)/2 = 34,980 estimated pairs
plus the inverted half): the median of ``--runs`` runs when the first run takes ≤ 60 s, else that
one run; the first (JIT-compiling / cache-loading) call on a 3-frame table is excluded.

Accuracy against the true rigid motion K_true[t, t'] = obj2depth(t') · inv(obj2depth(t)), over
all pairs t ≠ t': rotation error (angle of R_estᵀ R_true), translation error at the object,
‖K_est c − K_true c‖ with c frame t's vertex centroid, and ‖t_est − t_true‖ (the transforms' own
translations, at the depth-camera origin ~1 m away: ~17 mm per degree of rotation error). Two
deformations:

- ``full``: the scene as configured (bend, twist, squash and belly bulge);
- ``core``: bend, twist and squash switched off, only the local belly bulge deforms — a body with
  a genuinely rigid core, where "the rigid part of the motion" is well defined.

    python benchmarks/bench_poses.py [--frames 265] [--runs 3] [--threads N] [--threshold 0.01]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex import poses
    from stex.config import load_config
    from stex.synth.procedural import ProceduralBody
    from stex.synth.scene import SyntheticScene
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stex import poses
    from stex.config import load_config
    from stex.synth.procedural import ProceduralBody
    from stex.synth.scene import SyntheticScene

REPO = Path(__file__).resolve().parents[1]


def scene_vertices(n_frames: int, variant: str):
    cfg = load_config(REPO / "config" / "scenes" / "paper.yaml",
                      overrides={"source": {"synthetic": {"n_frames": n_frames}}})["source"]["synthetic"]
    s = SyntheticScene(cfg)
    if variant == "core":
        s.body = ProceduralBody(dataclasses.replace(s.body.p, bend=0.0, twist=0.0, squash=0.0))
    X = np.stack([s.true_vertices(t) for t in range(n_frames)])
    M = np.stack([s.object_to_depth(s.time_of(t)) for t in range(n_frames)])
    K_true = M[None, :] @ poses.invert_rigid(M)[:, None]  # [t, t'] = M[t'] inv(M[t])
    return s, X, K_true


def accuracy(P, K_true, X):
    n = P.shape[0]
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    rot, trans = poses.pose_error(P[i, j], K_true[i, j])
    _, ce = poses.pose_error(P[i, j], K_true[i, j], center=X.mean(1)[i])
    ok = (rot <= 1.0) & (ce <= 0.005)
    return (f"rotation median {np.median(rot):.3f}° p95 {np.percentile(rot, 95):.3f}° max {rot.max():.3f}°; "
            f"translation at the object centroid median {1e3 * np.median(ce):.2f} mm max {1e3 * ce.max():.2f} mm "
            f"(at the camera origin median {1e3 * np.median(trans):.2f} mm max {1e3 * trans.max():.2f} mm); "
            f"pairs within 1° and 5 mm at the centroid: {100 * ok.mean():.1f} %")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=265)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="default: all CPUs")
    ap.add_argument("--threshold", type=float, default=None, help="poses.inlier_threshold_m (and icp_threshold_m)")
    ap.add_argument("--verbose", action="store_true", help="log progress")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(message)s")

    params = load_config()["poses"]
    if args.threshold is not None:
        params.update(inlier_threshold_m=args.threshold, icp_threshold_m=args.threshold)
    print(f"poses params: {params}")

    t0 = time.perf_counter()
    s, X, K_true = scene_vertices(args.frames, "full")
    print(f"scene: {X.shape[0]} frames, {X.shape[1]} vertices, {s.faces.shape[0]} faces "
          f"(vertices generated in {time.perf_counter() - t0:.1f} s); "
          f"{X.shape[0] * (X.shape[0] - 1) // 2} pairs estimated")
    poses.pose_table(X[:3], s.faces, params, threads=args.threads)  # compile / load the cache

    times = []
    for r in range(args.runs):
        t0 = time.perf_counter()
        P, ratio = poses.pose_table(X, s.faces, params, threads=args.threads)
        times.append(time.perf_counter() - t0)
        if times[0] > 60.0:
            break
    times = np.asarray(times)
    n_pairs = X.shape[0] * (X.shape[0] - 1) // 2
    label = f"median of {times.size} runs" if times.size > 1 else "1 run"
    print(f"pose table: {np.median(times):.2f} s ({label}; runs {', '.join(f'{t:.2f}' for t in times)} s), "
          f"{1e3 * np.median(times) / n_pairs:.3f} ms per estimated pair")
    off = ~np.eye(X.shape[0], dtype=bool)
    print(f"inlier ratio: median {np.median(ratio[off]):.3f}, min {ratio[off].min():.3f}")
    print(f"accuracy [full deformation]: {accuracy(P, K_true, X)}")

    _, Xc, Kc = scene_vertices(args.frames, "core")
    t0 = time.perf_counter()
    Pc, rc = poses.pose_table(Xc, s.faces, params, threads=args.threads)
    print(f"accuracy [rigid core, bulge only] ({time.perf_counter() - t0:.2f} s, inlier ratio median "
          f"{np.median(rc[off]):.3f}): {accuracy(Pc, Kc, Xc)}")


if __name__ == "__main__":
    main()
