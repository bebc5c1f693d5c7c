"""Benchmark stex.mrf: one frame's labeling MRF at the paper scene's size.

Problem (built here, seeded): the faces of the bumpy icosphere (``stex.synth.shapes.bumpy_sphere``,
subdivisions 5: 20,480 faces) joined by ``stex.mesh.face_adjacency`` (30,720 edges); labels
are frames 0..264; each face's subset is ~20 frames (the authors prune to the top-20 candidates):
a window of 13 frames around a per-face centre that varies smoothly over the sphere (plus a
jitter of +-2 frames) and 7 frames around a second, also smooth, centre (a "similar shape"
elsewhere in the sequence). Unary 10·(1 - cos) + U(0, 2) with cos falling off away from the first
centre. Features K = 17 per (edge, frame): 9 intensities along the shared edge (smooth albedo +
a frame-dependent shading wave + N(0, 0.02) noise) and their 8 differences, scaled by 10·0.5/9 and
10·0.5/8 so the L1 distance is E_spa = 10(0.5·mean|ΔI_a − ΔI_b| + 0.5·mean|I_a − I_b|).

Cases (each timed ``--runs`` times after one untimed compile/cache-load call, median reported):
- cold: α-expansion from the unary argmin to convergence (``--tol``);
- warm: α-expansion from the cold solution with perturbed unaries (+U(0, 1) per candidate, as the
  temporal term of a block-coordinate-descent round changes them);
- ICM from the unary argmin, and ICM from the same warm start.

    python benchmarks/bench_mrf.py [--runs 5] [--tol 1e-3] [--max-cycles 10] [--seed 0]
                                   [--window 13 --second 7] [--frames 265] [--subdivisions 5]

The numbers measured on the shared 2-core project machine are in the module docstring of
``stex/mrf.py``. The table prints the wall time and the process CPU time: on a busy shared
machine the CPU time is the steadier one.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex import mrf
    from stex.synth.shapes import bumpy_sphere
    from stex.mesh import face_adjacency
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stex import mrf
    from stex.synth.shapes import bumpy_sphere
    from stex.mesh import face_adjacency


def make_problem(n_frames: int = 265, window: int = 13, second: int = 7, subdivisions: int = 5, seed: int = 0):
    """The benchmark MRF (see the module docstring). Returns the 8 problem arrays of
    :mod:`stex.mrf` in its order."""
    rng = np.random.default_rng(seed)
    V, F = bumpy_sphere(subdivisions=subdivisions)
    edges, _ = face_adjacency(F)
    c = V[F].mean(axis=1) - np.array([0.0, 0.0, 1.5])
    d = c / np.linalg.norm(c, axis=1, keepdims=True)
    n = F.shape[0]
    t = np.arange(n_frames)

    smooth1 = np.sin(2.0 * d[:, 0] + 1.0 * d[:, 1]) * np.cos(1.5 * d[:, 2])
    centre1 = np.round((n_frames - 1) / 2 + 0.42 * (n_frames - window) * smooth1) + rng.integers(-2, 3, n)
    centre1 = np.clip(centre1, window // 2, n_frames - 1 - window // 2).astype(np.int64)
    smooth2 = np.cos(2.5 * d[:, 1] - 0.5 * d[:, 2])
    centre2 = np.clip(np.round((n_frames - 1) / 2 + 0.45 * (n_frames - second) * smooth2),
                      second // 2, n_frames - 1 - second // 2).astype(np.int64)
    mask = np.abs(t[None, :] - centre1[:, None]) <= window // 2
    mask |= np.abs(t[None, :] - centre2[:, None]) <= second // 2
    node, lab = np.nonzero(mask)
    cand_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(mask.sum(axis=1), out=cand_ptr[1:])
    cos = np.clip(np.cos(0.5 * np.pi * (lab - centre1[node]) / (window + 2.0)), 0.05, 1.0)
    cand_cost = 10.0 * (1.0 - cos) + rng.uniform(0.0, 2.0, lab.size)

    emask = mask[edges[:, 0]] | mask[edges[:, 1]]
    fe, flab = np.nonzero(emask)
    feat_ptr = np.zeros(edges.shape[0] + 1, np.int64)
    np.cumsum(emask.sum(axis=1), out=feat_ptr[1:])
    ce = c[edges].mean(axis=1)
    s = np.linspace(0.0, 1.0, 9)
    albedo = 0.5 + 0.2 * np.sin(9.0 * ce[:, :1] + 4.0 * s[None, :]) * np.cos(7.0 * ce[:, 1:2])   # (E, 9)
    phase = 3.0 * ce[:, 2] + 2.0 * ce[:, 0]
    shade = 0.15 * np.sin(2.0 * np.pi * flab / 80.0 + phase[fe])
    inten = albedo[fe] + shade[:, None] + rng.normal(0.0, 0.02, (fe.size, 9))
    grad = np.diff(inten, axis=1)
    feat = np.concatenate([inten * (10.0 * 0.5 / 9.0), grad * (10.0 * 0.5 / 8.0)], axis=1).astype(np.float32)
    return (cand_ptr, lab.astype(np.int32), cand_cost, edges.astype(np.int32),
            np.ones(edges.shape[0]), feat_ptr, flab.astype(np.int32), feat)


def _timed(fn, runs):
    """(last result, wall seconds (runs,), process CPU seconds (runs,)). On a shared machine the
    CPU time is the steadier number; the wall time is what a job waits."""
    fn()  # compile / load the numba cache
    out, wall, cpu = None, [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return out, np.asarray(wall), np.asarray(cpu)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="timed runs per case")
    ap.add_argument("--tol", type=float, default=1e-3, help="alpha_expansion relative tolerance per cycle")
    ap.add_argument("--max-cycles", type=int, default=10)
    ap.add_argument("--frames", type=int, default=265)
    ap.add_argument("--subdivisions", type=int, default=5, help="icosphere subdivisions (5: 20,480 faces)")
    ap.add_argument("--window", type=int, default=13, help="frames around the first centre (odd)")
    ap.add_argument("--second", type=int, default=7, help="frames around the second centre (odd)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    prob = make_problem(n_frames=args.frames, window=args.window, second=args.second,
                        subdivisions=args.subdivisions, seed=args.seed)
    t_build = time.perf_counter() - t0
    cand_ptr = prob[0]
    sizes = np.diff(cand_ptr)
    print(f"problem: {cand_ptr.size - 1} nodes, {prob[3].shape[0]} edges, {args.frames} labels, "
          f"{sizes.mean():.1f} labels/node (min {sizes.min()}, max {sizes.max()}), "
          f"{np.diff(prob[5]).mean():.1f} labels/edge, K={prob[7].shape[1]}; built in {t_build:.2f} s")
    print(f"{args.runs} timed runs per case after one untimed call; tol={args.tol}, "
          f"max_cycles={args.max_cycles}")

    rng = np.random.default_rng(args.seed + 1)
    warm_cost = prob[2] + rng.uniform(0.0, 1.0, prob[2].size)
    warm_prob = (prob[0], prob[1], warm_cost) + prob[3:]

    rows = []
    (lab_c, en_c), t_c, c_c = _timed(lambda: mrf.alpha_expansion(*prob, max_cycles=args.max_cycles,
                                                            tol=args.tol, seed=args.seed), args.runs)
    rows.append(("alpha-expansion, cold (unary argmin)", t_c, c_c, en_c[0], en_c[-1], len(en_c) - 1))
    (lab_w, en_w), t_w, c_w = _timed(lambda: mrf.alpha_expansion(*warm_prob, labels0=lab_c,
                                                            max_cycles=args.max_cycles, tol=args.tol,
                                                            seed=args.seed), args.runs)
    rows.append(("alpha-expansion, warm (perturbed unaries)", t_w, c_w, en_w[0], en_w[-1], len(en_w) - 1))
    lab_i, t_i, c_i = _timed(lambda: mrf.icm(*prob), args.runs)
    rows.append(("ICM, cold (unary argmin)", t_i, c_i, en_c[0], mrf.energy(lab_i, *prob), None))
    lab_iw, t_iw, c_iw = _timed(lambda: mrf.icm(*warm_prob, labels0=lab_c), args.runs)
    rows.append(("ICM, warm (perturbed unaries)", t_iw, c_iw, en_w[0], mrf.energy(lab_iw, *warm_prob), None))
    (lab_f, en_f), t_f, c_f = _timed(lambda: mrf.alpha_expansion(*prob, max_cycles=100, tol=0.0,
                                                            seed=args.seed), 1)
    rows.append(("alpha-expansion, cold, tol=0 (1 run)", t_f, c_f, en_f[0], en_f[-1], len(en_f) - 1))

    print(f"\n{'case':<44s} {'wall med':>9s} {'min':>6s} {'max':>6s} {'CPU med':>8s} {'E init':>10s} "
          f"{'E final':>10s} {'cycles':>6s}")
    for name, t, c, e0, e1, cyc in rows:
        print(f"{name:<44s} {np.median(t):8.3f}s {t.min():6.3f} {t.max():6.3f} {np.median(c):7.3f}s "
              f"{e0:10.1f} {e1:10.1f} {'' if cyc is None else cyc:>6}")
    print(f"\ncold energies per cycle: {np.round(en_c, 1).tolist()}")
    print(f"warm energies per cycle: {np.round(en_w, 1).tolist()}")
    print(f"labels changed by the warm run: {int((lab_w != lab_c).sum())} of {lab_c.size}")


if __name__ == "__main__":
    main()
