"""CPU time of the colour correction per slice on a run's atlas, to compare two checkouts.

Reads a results folder's ``template.zarr`` (never writes into it) and corrects ``--slices``
slices of a smooth colour ramp with a per-label exposure step, labels by chart (six sources, the
slice's own frame one of them), with the default correction settings at ``--solve-size``.
Reported: CPU seconds per slice (process time, so that a loaded machine inflates it less than wall
time), the iterations, and the slices are saved to ``--out`` (``.npy``) so that two checkouts'
results can be compared for equality (``--compare``):

    PYTHONPATH=<before> python benchmarks/bench_correction_speed.py --results results/demo --out /tmp/a.npy
    PYTHONPATH=<after>  python benchmarks/bench_correction_speed.py --results results/demo --out /tmp/b.npy --compare /tmp/a.npy
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # source checkout without install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/demo")
    ap.add_argument("--slices", type=int, default=4, help="slices corrected (the first is not timed)")
    ap.add_argument("--solve-size", type=int, default=1024)
    ap.add_argument("--out", default=None, help="save the corrected slices here (.npy)")
    ap.add_argument("--compare", default=None, help="slices saved by another run: report equality")
    a = ap.parse_args(argv)

    from stex.correction import CorrectionSystem
    from stex.io import open_store

    t = open_store(Path(a.results) / "template.zarr", "template")
    tf = t["texel/face_id"][...]
    fc = t["face_chart"][...]
    W = tf.shape[0]
    c0 = time.process_time()
    system = CorrectionSystem(tf, t["texcoords"][...], t["texcoord_faces"][...], t["faces"][...],
                              t["adjacency/pairs"][...], t["adjacency/edges"][...], fc,
                              factor=max(1, W // a.solve_size), temporal_length=None,
                              gutter_px=int(t.attrs["gutter_px"]))
    build = time.process_time() - c0
    yy, xx = np.mgrid[0:W, 0:W] / W
    base = np.stack([128 + 60 * np.sin(6 * xx), 128 + 60 * np.cos(5 * yy), 128 + 40 * np.sin(4 * (xx + yy))], -1)
    steps = np.array([[0, 0, 0], [10, -5, 3], [-8, 6, 0], [5, 5, 5], [-10, 0, 8], [3, -9, -4]], float)
    rng = np.random.default_rng(0)
    outs, cpu, iters = [], [], []
    for k in range(a.slices):
        lm = np.where(tf >= 0, ((fc * 7 + k) % 6)[np.maximum(tf, 0)], -1).astype(np.int32)
        img = np.clip(base + steps[np.maximum(lm, 0)] + rng.normal(0, 2, base.shape), 0, 255).astype(np.uint8)
        img[tf < 0] = 0
        c1 = time.process_time()
        outs.append(system.correct(img, lm, frame=0))
        cpu.append(time.process_time() - c1)
        iters.append(system.last_stats["iterations"])
    timed = cpu[1:] or cpu
    print("| atlas | solve grid | unknowns | build, s CPU | slices timed | median s CPU per slice | iterations |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {W} | {system.graph.W} | {system.n_unknowns} | {build:.2f} | {len(timed)} | "
          f"{statistics.median(timed):.2f} | {iters[-1]} |")
    result = np.stack(outs)
    if a.out:
        np.save(a.out, result)
    if a.compare:
        other = np.load(a.compare)
        same = other.shape == result.shape and np.array_equal(other, result)
        diff = "" if same or other.shape != result.shape else (
            f"; max |difference| {np.abs(other.astype(int) - result).max()} grey levels")
        print(f"slices equal to {a.compare}: {same}{diff}")


if __name__ == "__main__":
    main()
