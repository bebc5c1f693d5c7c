"""Labeling speed at paper scale: the whole block-coordinate descent on synthetic tables.

The issue target (issue 5): labeling ≤ 1.5 s per frame per BCD round (median) on the paper scene
(265 frames, ~20k faces) on this 2-core machine. This benchmark builds paper-sized inputs for
:func:`stex.labeling.label_sequence` without rendering a scene: the bumpy sphere of
``stex.synth.shapes`` (20,480 faces, its face adjacency), 265 frames, each face visible in a
window of frames that drifts smoothly over the surface (a turning object), K = 20 candidates per
(target, face) drawn from the visible frames nearest in time, unary = a quality step plus a
smooth similarity term plus noise, grey face/edge samples from a per-face base texture plus
per-frame exposure and noise (so E_spa and E_temp are realistic in scale). Prints the seconds of
the initial per-frame solves and of every round, per frame, and the peak RSS.

    python benchmarks/bench_bcd.py [--frames 265] [--rounds 2] [--threads 2]
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex.labeling import label_sequence
from stex.synth.shapes import bumpy_sphere
from stex.mesh import face_adjacency


def synthetic_inputs(T: int, K: int = 20, seed: int = 0):
    rng = np.random.default_rng(seed)
    V, F = bumpy_sphere()
    pairs, _ = face_adjacency(F)
    nF = len(F)
    c = V[F].mean(axis=1)
    azim = np.arctan2(c[:, 1], c[:, 0])                       # each face's angle on the "turn"
    phase = (azim / (2 * np.pi) + 0.5) * T
    t = np.arange(T)[:, None]
    visible = np.abs(((t - phase[None]) + T / 2) % T - T / 2) < T / 6   # seen ~1/3 of the time
    cand = np.full((T, nF, K), -1, np.int16)
    unary = np.zeros((T, nF, K), np.float32)
    for k in range(T):
        d = np.where(visible, np.abs(np.arange(T)[:, None] - k), 10**6)   # (T, F)
        best = np.argsort(d, axis=0, kind="stable")[:K].T                   # (F, K)
        ok = np.take_along_axis(d.T, best, axis=1) < 10**6
        best = np.where(ok, best, -1)
        best.sort(axis=1)
        best = np.where(best >= 0, best, -1)
        cand[k] = best
        unary[k] = np.where(best >= 0, (rng.random((nF, K)) < 0.2) + 0.3 * np.abs(best - k) / T
                            + 0.05 * rng.random((nF, K)), 0)
    base = rng.integers(30, 220, (nF, 15))
    gain = 1 + 0.1 * np.sin(np.arange(T) / 20.0)
    face_samples = np.clip(base[None] * gain[:, None, None] + rng.normal(0, 3, (T, nF, 15)), 0, 255).astype(np.uint8)
    ebase = rng.integers(30, 220, (len(pairs), 9))
    edge_samples = np.clip(ebase[None] * gain[:, None, None] + rng.normal(0, 3, (T, len(pairs), 9)), 0, 255).astype(np.uint8)
    return dict(cand=cand, unary=unary, pairs=pairs, pair_weight=np.full(len(pairs), 10.0),
                edge_samples=edge_samples, face_samples=face_samples)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=265)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    P = synthetic_inputs(args.frames)
    print(f"inputs: {args.frames} frames, {P['cand'].shape[1]} faces, {len(P['pairs'])} adjacent pairs, "
          f"{(P['cand'] >= 0).sum(-1).mean():.1f} candidates per (target, face) "
          f"(built in {time.perf_counter() - t0:.1f} s)", flush=True)
    res = label_sequence(**P, omega_t=2.0, max_rounds=args.rounds, rel_tol=0.0, threads=args.threads,
                         progress=lambda m: print(m, flush=True))
    T = args.frames
    for r in res["rounds"]:
        print(f"round {r['round']}: {r['seconds']:.1f} s, {r['seconds'] / T:.3f} s per frame, "
              f"energy {r['energy']:.1f}, {r['changed']} labels changed")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GB")


if __name__ == "__main__":
    main()
