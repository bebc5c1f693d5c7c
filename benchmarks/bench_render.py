"""Benchmark stex.render: rasterisation and visibility of a deforming 20k-face mesh.

Mesh: a bumpy icosphere (trimesh icosphere, subdivisions=5: 20,480 faces, 10,242 vertices),
radius ~0.4 m, 1.5 m in front of the camera — mesh A of
``reference/building_blocks_measured.md`` §1. Every run gets a new vertex buffer (small random
jitter), as for a deforming mesh; the first (JIT-compiling / cache-loading) call and ``--warmup``
further runs are excluded.

    python benchmarks/bench_render.py [--runs 50] [--warmup 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex import render
    from stex.synth.shapes import bumpy_sphere
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stex import render
    from stex.synth.shapes import bumpy_sphere





def _stats(name, times_s):
    t = np.asarray(times_s) * 1e3
    print(f"{name:<42s} median {np.median(t):7.2f} ms   min {t.min():7.2f} ms   "
          f"max {t.max():7.2f} ms   (n={t.size})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=50, help="timed runs per case (>= 30 recommended)")
    ap.add_argument("--warmup", type=int, default=3, help="untimed runs after the first call")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jitter", type=float, default=1e-4, help="vertex jitter std, metres")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    V0, F = bumpy_sphere()
    print(f"mesh: {F.shape[0]} faces, {V0.shape[0]} vertices; {args.runs} timed runs, "
          f"{args.warmup} warm-up runs, new vertex buffer per run")

    cameras = {
        "640x576 (fx=504)": (504.0, 640, 576),
        "2048x1536 (fx=980)": (980.0, 2048, 1536),
    }
    for label, (f, W, H) in cameras.items():
        K = np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
        buffers = [(V0 + rng.normal(0.0, args.jitter, V0.shape)).astype(np.float32)
                   for _ in range(args.runs + args.warmup + 1)]
        t_r, t_fv, t_fp, t_vv = [], [], [], []
        for i, V in enumerate(buffers):
            t0 = time.perf_counter()
            ras = render.rasterize(V, F, K, W, H)
            t1 = time.perf_counter()
            render.face_visibility(V, F, K, ras.depth)
            t2 = time.perf_counter()
            render.vertex_visibility(V, F, K, ras.depth)
            t3 = time.perf_counter()
            render.face_visibility(V, F, K, ras.depth, tangent_plane=False)
            t4 = time.perf_counter()
            if i > args.warmup:
                t_r.append(t1 - t0)
                t_fv.append(t2 - t1)
                t_vv.append(t3 - t2)
                t_fp.append(t4 - t3)
        hit = ras.face_id >= 0
        vis, _ = render.face_visibility(V, F, K, ras.depth)
        visp, _ = render.face_visibility(V, F, K, ras.depth, tangent_plane=False)
        print(f"\n{label}: object covers {int(hit.sum())} px, {np.unique(ras.face_id[hit]).size} "
              f"faces own a pixel; visible faces: {int(vis.sum())} (tangent-plane depth test), "
              f"{int(visp.sum())} (plain depth test)")
        _stats("rasterize", t_r)
        _stats("face_visibility", t_fv)
        _stats("face_visibility(tangent_plane=False)", t_fp)
        _stats("vertex_visibility", t_vv)


if __name__ == "__main__":
    main()
