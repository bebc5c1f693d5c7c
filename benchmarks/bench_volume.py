"""Benchmark the texture-volume slice and the colour correction at paper scale (4096^2).

Acceptance (issue 6): volume <= 1 s per slice, correction <= 6 s per slice (median), peak RSS
<= 4 GB per job, on the 2-core machine.

Synthetic data (untimed): the bumpy sphere of ``stex.synth.shapes`` (20,480 faces) unwrapped by
:func:`stex.atlas.build_atlas` at ``--size`` with ``--gutter``; ``--frames`` source frames,
each a smooth random colour image (2048 x 1536) with its own exposure offset and ξ an orthographic
view of the vertices from a per-frame direction; labels in coherent patches (each face takes the
frame of the nearest of ``--patches`` random seed points on the surface; patch->frame random,
re-drawn per slice).

Each correction factor runs in its own subprocess so that its peak RSS (resource.getrusage) is
its own. Reported per factor: system build (graph + pyamg setup, once per atlas), per-slice
median, iterations, the mean colour step across label boundaries before/after, the mean absolute
change away from boundaries (> 16 texels), and for factor > 1 the mean |difference| to the
factor-1 result when this run has one.

The atlas is cached in ``/tmp/stex_bench_volume`` under a digest of the code that builds it
(``stex/atlas.py``, ``stex/mesh.py``, ``stex/charting.py``, ``stex/synth/shapes.py``, xatlas's
version), so a changed atlas is built again; the slice and the corrected results go from job to job through a folder of this run only.

    python benchmarks/bench_volume.py [--size 4096] [--runs 3] [--factors 4,2] [--tol 1e-4]
                                      [--interpolation bicubic|bilinear]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # source checkout without install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CACHE = Path("/tmp/stex_bench_volume")


def _rss_gb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def _atlas_digest() -> str:
    """Digest of what the cached atlas depends on besides its size and gutter."""
    import stex.atlas
    import stex.mesh
    import stex.synth.shapes
    import stex.charting

    h = hashlib.sha1(version("xatlas").encode())
    for module in (stex.atlas, stex.mesh, stex.charting, stex.synth.shapes):
        h.update(Path(module.__file__).read_bytes())
    return h.hexdigest()[:12]


def _atlas(size, gutter):
    from stex.atlas import build_atlas, texel_map, uv_charts
    from stex.mesh import face_adjacency
    from stex.synth.shapes import bumpy_sphere

    CACHE.mkdir(exist_ok=True)
    f = CACHE / f"atlas_{size}_{gutter}_{_atlas_digest()}.npz"
    if f.exists():
        d = np.load(f)
        return {k: d[k] for k in d.files}
    V, F = bumpy_sphere(subdivisions=5)
    tc, tf = build_atlas(V, F, size, gutter)
    face, bary = texel_map(tc, tf, size)
    pairs, edges = face_adjacency(F)
    d = dict(V=V, F=F.astype(np.int32), tc=tc, tf=tf, face=face, bary=bary, pairs=pairs, edges=edges,
             chart=uv_charts(tf, len(tc)))
    np.savez(f, **d)
    return d


def _sources(V, n_frames, rng, hc=1536, wc=2048):
    import cv2

    images, coords = {}, {}
    c = V.mean(0)
    r = np.abs(V - c).max()
    for s in range(n_frames):
        small = rng.uniform(30, 220, (24, 32, 3)).astype(np.float32)
        img = cv2.resize(small, (wc, hc), interpolation=cv2.INTER_CUBIC) + rng.uniform(-25, 25)
        images[s] = np.clip(img, 0, 255).astype(np.uint8)
        a = rng.normal(size=3)
        Q, _ = np.linalg.qr(np.column_stack([a, rng.normal(size=3), rng.normal(size=3)]))
        P = (V - c) @ Q[:, :2] / r
        coords[s] = np.column_stack([wc / 2 + 0.45 * hc * P[:, 0], hc / 2 + 0.45 * hc * P[:, 1]])
    return images, coords


def _labels(V, F, n_patches, n_frames, rng):
    from scipy.spatial import cKDTree

    cent = V[F].mean(1)
    seeds = cent[rng.choice(len(F), n_patches, replace=False)]
    _, near = cKDTree(seeds).query(cent)
    return rng.integers(0, n_frames, n_patches)[near].astype(np.int32)


def run_volume(args):
    from stex.sampling import TexelSampler
    from stex.volume import volume_slice

    d = _atlas(args.size, args.gutter)
    rng = np.random.default_rng(0)
    images, coords = _sources(d["V"], args.frames, rng)
    t0 = time.perf_counter()
    sampler = TexelSampler(d["face"], d["bary"], d["F"], args.interpolation)
    t_pre = time.perf_counter() - t0
    labels = [_labels(d["V"], d["F"], args.patches, args.frames, rng) for _ in range(args.runs + 1)]
    sampler.slice(labels[-1], coords, images, args.gutter)  # warm-up (numba cache)
    times = []
    for lab in labels[:args.runs]:
        t0 = time.perf_counter()
        sl, lm = sampler.slice(lab, coords, images, args.gutter)
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    volume_slice(d["face"], d["bary"], d["F"], labels[0], coords, images, args.gutter)
    t_once = time.perf_counter() - t0
    np.savez(Path(args.workdir) / "slice.npz", slice=sl, label_map=lm)
    return {"stage": "volume", "interpolation": args.interpolation, "size": args.size, "faces": int(len(d["F"])),
            "covered_texels": int((d["face"] >= 0).sum()), "labels_in_slice": int(len(np.unique(lab))),
            "sampler_precompute_s": t_pre, "slice_median_s": float(np.median(times)),
            "slice_times_s": times, "volume_slice_oneshot_s": t_once, "peak_rss_gb": _rss_gb()}


def run_correction(args, factor):
    from stex.correction import CorrectionSystem, interior_change, label_boundary_step

    d = _atlas(args.size, args.gutter)
    s = np.load(Path(args.workdir) / "slice.npz")
    sl, lm = s["slice"], s["label_map"]
    t0 = time.perf_counter()
    cs = CorrectionSystem(d["face"], d["tc"], d["tf"], d["F"], d["pairs"], d["edges"], d["chart"],
                          factor=factor, gutter_px=args.gutter, tol=args.tol)
    t_build = time.perf_counter() - t0
    times, stats = [], []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        out = cs.correct(sl, lm)
        times.append(time.perf_counter() - t0)
        stats.append(cs.last_stats)
    np.save(Path(args.workdir) / f"corrected_{factor}.npy", out)
    res = {"stage": f"correction factor {factor}", "unknowns": cs.n_unknowns,
           "build_s": t_build, **{k: float(v) for k, v in cs.timings.items()},
           "slice_median_s": float(np.median(times)), "slice_times_s": times,
           "iterations": stats[-1]["iterations"], "solve_s": stats[-1]["solve_s"],
           "step_before": label_boundary_step(sl, lm, d["face"], d["chart"]),
           "step_after": label_boundary_step(out, lm, d["face"], d["chart"]),
           "interior_change_16px": interior_change(sl, out, lm, 16),
           "peak_rss_gb": _rss_gb()}
    ref = Path(args.workdir) / "corrected_1.npy"  # factor 1 of this run only
    if factor > 1 and ref.exists():
        cov = d["face"] >= 0
        res["mean_abs_diff_to_factor1"] = float(np.abs(np.load(ref)[cov].astype(float) - out[cov]).mean())
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--gutter", type=int, default=4)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--patches", type=int, default=60)
    ap.add_argument("--factors", default="4,2")
    ap.add_argument("--interpolation", choices=["bicubic", "bilinear"], default="bicubic",
                    help="the volume's image lookup (volume.interpolation)")
    ap.add_argument("--tol", type=float, default=1e-4, help="relative residual of the correction solve")
    ap.add_argument("--only", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--workdir", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.only is not None:
        if args.workdir is None:
            ap.error("--only is one job of a run: it needs the run's --workdir")
        res = run_volume(args) if args.only == "volume" else run_correction(args, int(args.only))
        print("RESULT " + json.dumps(res))
        return 0
    _atlas(args.size, args.gutter)  # build (and cache) the atlas outside the measured jobs
    workdir = tempfile.mkdtemp(prefix="run_", dir=CACHE)
    base = [sys.executable, __file__, "--size", str(args.size), "--gutter", str(args.gutter),
            "--runs", str(args.runs), "--frames", str(args.frames), "--patches", str(args.patches), "--tol", str(args.tol),
            "--interpolation", args.interpolation, "--workdir", workdir]
    try:
        return _run_jobs(base, ["volume"] + [f for f in args.factors.split(",") if f])
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def _run_jobs(base, jobs):
    ok = True
    for job in jobs:
        p = subprocess.run(base + ["--only", job], capture_output=True, text=True)
        line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
        if p.returncode or not line:
            print(f"{job}: failed (rc {p.returncode})\n{p.stderr[-2000:]}")
            ok = False
            continue
        r = json.loads(line[0][7:])
        target = 1.0 if job == "volume" else 6.0
        verdict = "OK" if r["slice_median_s"] <= target and r["peak_rss_gb"] <= 4 else "MISSED"
        print(f"{r['stage']}: median {r['slice_median_s']:.2f} s/slice (target {target:.0f} s), "
              f"peak RSS {r['peak_rss_gb']:.2f} GB (target 4) -> {verdict}")
        print("   " + json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
