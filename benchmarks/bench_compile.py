"""Benchmark the first-run numba compilation of a stage's kernels.

A fresh install compiles stex's numba kernels on their first call and caches them (docs/benchmarks.md, "The
numba kernels' first compile"). This times that first call, in a new interpreter with an empty
``NUMBA_CACHE_DIR`` each run, so nothing is loaded from a cache: ``--runs`` runs, median.

- ``poses``: :func:`stex.poses.pose_table` on 3 frames of 200 random points (RANSAC, the inlier
  refit and ICP; the work itself takes milliseconds).

    python benchmarks/bench_compile.py [--runs 3] [--stage poses]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SNIPPETS = {
    "poses": """
import time
import numpy as np
from stex import poses
X = np.random.default_rng(0).normal(size=(3, 200, 3))
F = np.array([[i, i + 1, i + 2] for i in range(0, 198, 3)])
t0 = time.perf_counter()
poses.pose_table(X, F, {"ransac_iterations": 20}, seed=0, threads=1)
print(time.perf_counter() - t0)
""",
}


def first_call_seconds(stage: str) -> float:
    """Seconds of the stage's first call in a new interpreter with an empty numba cache."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache,
               "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        run = subprocess.run([sys.executable, "-c", SNIPPETS[stage]], env=env, capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"{stage}: the first call failed:\n{run.stderr[-2000:]}")
        return float(run.stdout.split()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--stage", choices=sorted(SNIPPETS), default="poses")
    args = ap.parse_args(argv)
    times = []
    for i in range(args.runs):
        times.append(first_call_seconds(args.stage))
        print(f"run {i + 1}: {times[-1]:.1f} s", flush=True)
    print(f"{args.stage}: first call with an empty numba cache, median {np.median(times):.1f} s "
          f"(min {min(times):.1f}, max {max(times):.1f}, n={len(times)})")


if __name__ == "__main__":
    main()
