"""Benchmark stex.similarity at paper scale: E_glo rows, SHOT descriptors, E_loc.

Scene: the paper-scale synthetic scene (config/scenes/paper.yaml: 265 frames, the procedural
body with 9,938 vertices / 19,872 faces, 640x576 depth camera, fx = 504), true vertices from
``SyntheticScene.true_vertices`` stored as float32 (as tracking.zarr), true rigid poses
K_{t→l} = obj2depth(l) · inv(obj2depth(t)) (the cost of E_glo does not depend on the poses).

Measures (single process; first calls that JIT-compile / load the numba cache are excluded;
wall-clock and process CPU time, the latter less sensitive to other jobs on a shared machine):

1. E_glo: seconds per target row (all T sources) at render scale 1 and 0.5 (median over
   ``--rows`` rows, one call per row, own-render setup timed separately) and the difference
   between the two scales' values; then, unless
   ``--no-full``, the whole (T, T) table at ``--full-scale`` with ``--threads`` threads.
2. Geodesic neighbourhoods (once, template = frame 0) and SHOT seconds per frame (median over
   all frames); descriptors of all frames kept as float16 (the storage type), 1.9 GB.
3. E_loc: ``local_similarity_faces`` for every target × ``--sources`` candidate source frames
   (every (T/sources)-th frame from t on, spread over the sequence), in target blocks of
   ``--block`` frames (as the workflow's target blocks); and ``local_similarity_triples`` for
   ``--triple-targets`` targets with ``--per-face`` random candidates per face among 40 sources.
4. float16 vs float32 descriptor storage: max |ΔE_loc| over a few pairs.
5. Peak RSS (ru_maxrss) after each step.

    python benchmarks/bench_similarity.py [--frames 265] [--rows 3] [--full-scale 0.5] [--threads 1]
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex import shot
    from stex import similarity as S
    from stex.config import load_config
    from stex.poses import invert_rigid
    from stex.synth.scene import SyntheticScene
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stex import shot
    from stex import similarity as S
    from stex.config import load_config
    from stex.poses import invert_rigid
    from stex.synth.scene import SyntheticScene

REPO = Path(__file__).resolve().parents[1]


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB (Linux)


def scene(n_frames: int):
    cfg = load_config(REPO / "config" / "scenes" / "paper.yaml",
                      overrides={"source": {"synthetic": {"n_frames": n_frames}}})["source"]["synthetic"]
    s = SyntheticScene(cfg)
    X = np.stack([s.true_vertices(t) for t in range(n_frames)]).astype(np.float32)
    M = np.stack([s.object_to_depth(s.time_of(t)) for t in range(n_frames)])
    poses = M[None, :] @ invert_rigid(M)[:, None]  # [t, l] = M[l] inv(M[t])
    return s, X, poses


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=265)
    ap.add_argument("--rows", type=int, default=3, help="E_glo rows timed per scale")
    ap.add_argument("--full-scale", type=float, default=0.5, help="scale of the whole E_glo table")
    ap.add_argument("--no-full", action="store_true", help="skip the whole E_glo table")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sources", type=int, default=40, help="E_loc candidate sources per target")
    ap.add_argument("--block", type=int, default=16, help="targets per local_similarity_faces call")
    ap.add_argument("--triple-targets", type=int, default=4)
    ap.add_argument("--per-face", type=int, default=20)
    ap.add_argument("--radius-res", type=float, default=5.0, help="SHOT radius in mesh resolutions")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    s, X, poses = scene(args.frames)
    T, V = X.shape[:2]
    F = s.faces
    d = s.calibration.depth
    print(f"scene: {T} frames, {V} vertices, {F.shape[0]} faces, depth {d.width}x{d.height} "
          f"(built in {time.perf_counter() - t0:.1f} s)")

    # warm-up: compile / load the numba cache
    S.global_similarity(X[:2], F, poses[:2, :2], d.K, d.width, d.height)

    # 1. E_glo ----------------------------------------------------------------------------
    rows = np.linspace(0, T - 1, args.rows).round().astype(int)
    row_values = {}
    for scale in (1.0, 0.5):
        wall, cpu = [], []
        for r in rows:
            w0, c0 = time.perf_counter(), time.process_time()
            row_values[scale, r] = S.global_similarity(X, F, poses, d.K, d.width, d.height,
                                                       targets=[r], scale=scale)[0]
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
        # the own renders shared by all rows of a call: an empty target list costs just those
        w0, c0 = time.perf_counter(), time.process_time()
        S.global_similarity(X, F, poses, d.K, d.width, d.height, targets=np.zeros(0, int), scale=scale)
        setup_w, setup_c = time.perf_counter() - w0, time.process_time() - c0
        print(f"E_glo scale {scale}: one-row call (own renders of all {T} frames + one row of {T} "
              f"sources) median wall {np.median(wall):.2f} s, CPU {np.median(cpu):.2f} s over {len(wall)} "
              f"rows (wall {', '.join(f'{x:.2f}' for x in wall)}); own renders alone wall {setup_w:.2f} s, "
              f"CPU {setup_c:.2f} s -> per row wall {np.median(wall) - setup_w:.2f} s, CPU "
              f"{np.median(cpu) - setup_c:.2f} s")
    dev = np.abs(np.stack([row_values[0.5, r] - row_values[1.0, r] for r in rows]))
    print(f"E_glo scale 0.5 vs 1.0 on rows {rows.tolist()}: max |diff| {dev.max():.4f}, median "
          f"{np.median(dev):.4f} (values up to {max(v.max() for v in row_values.values()):.3f})")
    print(f"peak RSS {rss_gb():.2f} GiB")
    if not args.no_full:
        w0, c0 = time.perf_counter(), time.process_time()
        G = S.global_similarity(X, F, poses, d.K, d.width, d.height, scale=args.full_scale,
                                threads=args.threads)
        full, full_c = time.perf_counter() - w0, time.process_time() - c0
        off = ~np.eye(T, dtype=bool)
        print(f"E_glo whole {T}x{T} table at scale {args.full_scale}, {args.threads} thread(s): "
              f"wall {full:.1f} s, CPU {full_c:.1f} s (1 run); off-diagonal min {G[off].min():.3f} median "
              f"{np.median(G[off]):.3f} max {G[off].max():.3f}; peak RSS {rss_gb():.2f} GiB")

    # 2. neighbourhoods + SHOT ----------------------------------------------------------------
    res = shot.mesh_resolution(X[0], F)
    radius = args.radius_res * res
    shot.geodesic_neighbourhoods(X[0, :3], [[0, 1, 2]], radius)  # warm-up on a tiny piece
    t1 = time.perf_counter()
    nbh = shot.geodesic_neighbourhoods(X[0], F, radius)
    t_nbh = time.perf_counter() - t1
    print(f"geodesic neighbourhoods: R = {radius * 100:.2f} cm ({args.radius_res} x mesh resolution "
          f"{res * 100:.2f} cm), {np.diff(nbh.ptr).mean():.1f} neighbours per vertex, {t_nbh:.3f} s (once)")
    shot.shot_descriptors(X[0], F, nbh, radius_m=radius)  # warm-up
    desc = np.empty((T, V, shot.SHOT_DIM), np.float16)
    times, ctimes = [], []
    for t in range(T):
        w0, c0 = time.perf_counter(), time.process_time()
        dt = shot.shot_descriptors(X[t], F, nbh, radius_m=radius)
        times.append(time.perf_counter() - w0)
        ctimes.append(time.process_time() - c0)
        desc[t] = dt
    times = np.asarray(times)
    print(f"SHOT: median wall {np.median(times):.3f} s, CPU {np.median(ctimes):.3f} s per frame (wall min "
          f"{times.min():.3f}, max {times.max():.3f}), wall {times.sum():.1f} s, CPU {np.sum(ctimes):.1f} s "
          f"for {T} frames; float16 table {desc.nbytes / 2**30:.2f} GiB; "
          f"peak RSS {rss_gb():.2f} GiB")

    # 3. E_loc ---------------------------------------------------------------------------------
    K_src = min(args.sources, T)
    # candidate sources of target t: K_src frames spread over the sequence (every T/K-th, shifted by t)
    src = (np.arange(T)[:, None] + np.round(np.arange(K_src) * T / K_src).astype(int)[None]) % T
    rings = S.vertex_rings(F, V, 2)
    S.local_similarity_faces(desc, F, [[0, 1]], rings=rings)  # warm-up
    w0, c0 = time.perf_counter(), time.process_time()
    check = 0.0
    for b0 in range(0, T, args.block):
        tg = np.arange(b0, min(T, b0 + args.block))
        pairs = np.stack([np.repeat(tg, K_src), src[tg].ravel()], axis=1)
        E = S.local_similarity_faces(desc, F, pairs, rings=rings, target_chunk=args.block)
        check += float(E.sum())
    t_loc, c_loc = time.perf_counter() - w0, time.process_time() - c0
    print(f"E_loc faces: {T} targets x {K_src} sources = {T * K_src} pairs x {F.shape[0]} faces in "
          f"wall {t_loc:.1f} s, CPU {c_loc:.1f} s (1 run, blocks of {args.block} targets; "
          f"{1e3 * t_loc / (T * K_src):.2f} ms wall, {1e3 * c_loc / (T * K_src):.2f} ms CPU per pair); "
          f"mean E_loc {check / (T * K_src * F.shape[0]):.3f}; peak RSS {rss_gb():.2f} GiB")

    rng = np.random.default_rng(0)
    tg = np.linspace(0, T - 1, args.triple_targets).round().astype(int)
    n_face = F.shape[0]
    kk = min(args.per_face, K_src)
    times, ctimes = [], []
    for t in tg:
        cand = src[t][np.argsort(rng.random((n_face, K_src)), axis=1)[:, :kk]]  # (F, kk)
        w0, c0 = time.perf_counter(), time.process_time()
        S.local_similarity_triples(desc, F, np.full(cand.size, t), np.repeat(np.arange(n_face), kk),
                                   cand.ravel(), rings=rings)
        times.append(time.perf_counter() - w0)
        ctimes.append(time.process_time() - c0)
    print(f"E_loc triples: {kk} random candidates per face among {K_src} sources ({n_face * kk} triples "
          f"per target): median wall {np.median(times):.2f} s, CPU {np.median(ctimes):.2f} s per target "
          f"over {len(times)} targets")

    # 4. float16 vs float32 storage -----------------------------------------------------------
    pairs = np.stack([np.repeat(np.arange(0, T, max(1, T // 8)), 4),
                      np.tile([1, 17, 60, 131], len(range(0, T, max(1, T // 8))))], axis=1) % T
    d32 = {int(t): shot.shot_descriptors(X[t], F, nbh, radius_m=radius) for t in np.unique(pairs)}

    class Lazy:  # float32 descriptors of the needed frames only
        shape = (T, V, shot.SHOT_DIM)

        def __getitem__(self, t):
            return d32[int(t)]

    e32 = S.local_similarity_faces(Lazy(), F, pairs, rings=rings)
    e16 = S.local_similarity_faces(desc, F, pairs, rings=rings)
    sim32 = np.concatenate([S.vertex_similarity(d32[int(t)], d32[int(l)]) for t, l in pairs])
    sim16 = np.concatenate([S.vertex_similarity(desc[t], desc[l]) for t, l in pairs])
    print(f"float16 storage vs float32 over {len(pairs)} pairs: E_loc max |diff| "
          f"{np.abs(e16 - e32).max():.2e}, median {np.median(np.abs(e16 - e32)):.2e}; per-vertex "
          f"similarity max |diff| {np.abs(sim16 - sim32).max():.2e} (E_loc range of these pairs "
          f"{e32.min():.3f}..{e32.max():.3f})")
    print(f"peak RSS {rss_gb():.2f} GiB")


if __name__ == "__main__":
    main()
