"""What candidate pruning (``poses.nearest_frames``) loses against the full tables.

Two measurements:

1. **Labels, for several k** (``--k``): on a finished run, re-run the poses, data-term and
   labeling writers with each k into a scratch folder (the run's own settings otherwise) and
   compare the labels with the full tables' on every (frame, face): the fraction that agree, the
   pairs posed, the sources per target and the three stages' time. The full tables' labels are
   the run's own when it was made with ``poses: {nearest_frames: 0}``, else k = 0 is run into
   the scratch folder first. Cheap (no volume, correction or evaluation): the sweep to choose k.
2. **Scores** (``--pruned RUN``): a second finished run of the same scene made with pruning;
   the labels' agreement and every PSNR score of the evaluation (dB) of ours and ours
   uncorrected, side by side, with the largest difference.

3. **The labeling's own floor** (``--seeds N``): the run's own tables labelled again with
   ``labeling.seed`` 1..N (the α-expansion's label order) and compared with the run's labels the
   same way. Pruning cannot be asked to agree with the full tables better than the full tables
   agree with themselves under another label order.

    python benchmarks/bench_pruning.py RESULTS --k 10:3,20:3,20:3:cover [--scratch DIR] [--pruned RESULTS_K]
    python benchmarks/bench_pruning.py RESULTS --seeds 2

The issue's acceptance (paper scene family, T = 265): labels agree on >= 99 % of (t, face) and
the evaluation's scores move by <= 0.05 dB.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _stored_params(path, kind) -> dict:
    from stex.io import open_store
    return dict(open_store(path, kind).attrs.get("params", {}))


def run_k(results: Path, scratch: Path, k: int, reference: Path | None = None,
          coverage: int | None = None, mode: str | None = None) -> dict:
    """Poses, data term and labels of ``results`` with nearest_frames = k (and coverage_frames
    = coverage, coverage_mode = mode, default the schema's), into ``scratch``."""
    from stex.io import open_store
    from stex.stages.data_term import write_data_term
    from stex.stages.labeling import write_labels
    from stex.stages.poses import write_pose_table

    R = results
    d = scratch / ((f"k{k}" if coverage is None else f"k{k}_c{coverage}") + (f"_{mode}" if mode else ""))
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    blocks = sorted((R / "data_term").glob("block_*.zarr"))
    dt = _stored_params(blocks[0], "data_term")
    pp = dict(_stored_params(R / "poses.zarr", "poses"), nearest_frames=k)
    if coverage is not None:
        pp["coverage_frames"] = coverage
    if mode:
        pp["coverage_mode"] = mode
    row = {"k": k, "coverage": pp.get("coverage_frames"), "mode": pp.get("coverage_mode", "walk")}
    t0 = time.perf_counter()
    write_pose_table(R / "tracking.zarr", d / "poses.zarr", pp, faces=R / "template.zarr",
                     visibility=R / "projection.zarr", source_stride=dt["source_stride"], threads=2)
    row["poses_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    out = []
    for b in blocks:
        ids = open_store(b, "data_term").attrs["frame_ids"]
        seq = open_store(b, "data_term").attrs["sequence_frame_ids"]
        start = seq.index(ids[0])
        out.append(d / b.name)
        write_data_term(R / "scene.zarr", R / "template.zarr", R / "tracking.zarr", d / "poses.zarr",
                        R / "observations.zarr", [start, start + len(ids)], dt, out[-1])
    row["data_term_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    write_labels(R / "observations.zarr", out, R / "template.zarr",
                 _stored_params(R / "labels.zarr", "labels"), d / "labels.zarr", threads=2,
                 projection_path=R / "projection.zarr")
    row["labeling_s"] = round(time.perf_counter() - t0, 1)
    g = open_store(d / "poses.zarr", "poses")
    T = g["neighbours"].shape[0]
    nb = g["neighbours"][...]
    row["pairs"] = int(g["pairs"].shape[0])
    row["pairs_of_all_%"] = round(100 * row["pairs"] / max(1, T * (T - 1) // 2), 1)
    row["sources_per_target"] = round(float((nb >= 0).sum(axis=1).mean()), 1)
    row.update(agreement(reference or R / "labels.zarr", d / "labels.zarr"))
    return row


def seed_floor(results: Path, scratch: Path, n_seeds: int) -> list[dict]:
    """The run's own data-term blocks labelled with ``labeling.seed`` 1..n_seeds into
    ``scratch`` (bench_labeling's relabel): per seed the agreement with the run's labels and the
    labeling's time."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_labeling import relabel
    scratch.mkdir(parents=True, exist_ok=True)
    seed0 = _stored_params(results / "labels.zarr", "labels").get("seed", 0)
    rows = []
    for seed in range(1, n_seeds + 1):
        t0 = time.perf_counter()
        out = relabel(results, scratch, {"seed": seed})
        rows.append({"seed": seed, "from seed": seed0, "labeling_s": round(time.perf_counter() - t0, 1),
                     **agreement(results / "labels.zarr", out)})
    return rows


def pair_counts(results: Path, specs: str) -> None:
    """Sources per target and pairs kept for each k[:coverage] on the run's tracking and
    visibility, without computing poses (the cheap look at how much pruning keeps)."""
    from stex.io import open_store
    from stex.pruning import nearest_sources, pose_pairs, shape_descriptors
    X = np.asarray(open_store(results / "tracking.zarr", "tracking")["vertices"][...], np.float64)
    vis = np.asarray(open_store(results / "projection.zarr", "projection")["face_visible"][...], bool)
    D = shape_descriptors(X)
    T = len(X)
    print("k | coverage | mode | sources per target (mean, max) | pairs | of all pairs")
    for spec in specs.split(","):
        k, c, m = parse_spec(spec)
        nb = nearest_sources(D, vis, k, coverage=c, mode=m or "walk")
        n = (nb >= 0).sum(axis=1)
        print(f"{k} | {c if c is not None else k} | {m or 'walk'} | {n.mean():.1f}, {n.max()} | "
              f"{len(pose_pairs(nb))} | {T * (T - 1) // 2}")


def parse_spec(spec: str):
    """``k[:coverage[:mode]]`` -> (k, coverage or None, mode or None)."""
    parts = spec.split(":")
    if not 1 <= len(parts) <= 3 or not parts[0]:
        raise ValueError(f"--k / --pairs entry {spec!r}: expected k[:coverage[:walk|cover]]")
    c = int(parts[1]) if len(parts) > 1 and parts[1] else None
    return int(parts[0]), c, (parts[2] if len(parts) > 2 and parts[2] else None)


def agreement(full_labels, other_labels) -> dict:
    from stex.io import open_store
    a = open_store(full_labels, "labels")["labels"][...]
    b = open_store(other_labels, "labels")["labels"][...]
    if a.shape != b.shape:
        raise ValueError(f"{full_labels} and {other_labels} label different (T, F): {a.shape}, {b.shape}")
    return {"labels_agree_%": round(100 * float((a == b).mean()), 3),
            "labelled_full_%": round(100 * float((a >= 0).mean()), 3),
            "labelled_pruned_%": round(100 * float((b >= 0).mean()), 3)}


def psnr_scores(results: Path) -> dict:
    """{(region, method, metric): mean} of every PSNR score (dB) of ours and ours uncorrected."""
    ev = json.loads((results / "evaluation" / "evaluation.json").read_text())
    out = {}
    for region, methods in ev["summary"].items():
        if not isinstance(methods, dict):     # the summary's counts beside the regions
            continue
        for method in ("ours", "ours_uncorrected"):
            for metric, v in methods.get(method, {}).items():
                if "psnr" in metric and isinstance(v, dict) and v.get("mean") is not None:
                    out[(region, method, metric)] = float(v["mean"])
    return out


def compare_runs(full: Path, pruned: Path) -> None:
    a, b = psnr_scores(full), psnr_scores(pruned)
    keys = sorted(set(a) & set(b))
    print(f"{'region':<10} {'method':<17} {'metric':<34} {'full dB':>8} {'pruned dB':>9} {'diff':>7}")
    for key in keys:
        print(f"{key[0]:<10} {key[1]:<17} {key[2]:<34} {a[key]:8.3f} {b[key]:9.3f} {b[key] - a[key]:+7.3f}")
    worst = max(keys, key=lambda k: abs(b[k] - a[k]))
    print(f"largest |difference|: {abs(b[worst] - a[worst]):.3f} dB ({' / '.join(worst)}), over {len(keys)} scores")
    print("labels:", json.dumps(agreement(full / "labels.zarr", pruned / "labels.zarr")))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="a finished run (with the full tables or pruned)")
    ap.add_argument("--k", default="", help="comma-separated nearest_frames[:coverage_frames] values to sweep")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/stex_bench_pruning"))
    ap.add_argument("--pairs", default="", help="k[:coverage] values: only count the pairs kept")
    ap.add_argument("--seeds", type=int, default=0, help="label the run's own tables again with "
                    "labeling.seed 1..N: the labeling's own agreement floor")
    ap.add_argument("--pruned", type=Path, help="a finished run of the same scene with pruning "
                    "(RESULTS then must be the full tables' run)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from stex.logs import setup_logging
    setup_logging(None)
    R = args.results.resolve()
    if args.pairs:
        pair_counts(R, args.pairs)
    k0 = _stored_params(R / "poses.zarr", "poses").get("nearest_frames", 0)
    from stex.io import open_store
    g = open_store(R / "poses.zarr", "poses")
    T = len(g.attrs["frame_ids"])
    if "pairs" in g and g["pairs"].shape[0] == T * (T - 1) // 2:
        k0 = 0  # pruning kept every pair: the run's tables are the full ones
    if args.k:
        ref = None
        if k0:  # the run was pruned: the full tables' labels first
            ref_row = run_k(R, args.scratch, 0, reference=R / "labels.zarr")
            print("full tables (k = 0), against the run's own labels (k = %d): %s" % (k0, ref_row))
            ref = args.scratch / "k0" / "labels.zarr"
        rows = []
        for spec in args.k.split(","):
            k, c, m = parse_spec(spec)
            if k or not k0:
                rows.append(run_k(R, args.scratch, k, ref, c, m))
        cols = list(rows[0])
        print(" | ".join(cols))
        for r in rows:
            print(" | ".join(str(r[c]) for c in cols))
    if args.seeds:
        rows = seed_floor(R, args.scratch, args.seeds)
        print(" | ".join(rows[0]))
        for r in rows:
            print(" | ".join(str(v) for v in r.values()))
    if args.pruned:
        compare_runs(R, args.pruned.resolve())


if __name__ == "__main__":
    main()
