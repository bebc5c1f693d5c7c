"""The paper's ablations, scored end to end by the evaluation code (issue 7, protocol 3).

On a finished synthetic run (``snakemake --cores 2`` → results/demo) every variant re-runs the
stages it changes into a scratch folder — tables (similarity global-only / local-only, the
strain term E_str off),
labeling (temporal off / constant / selective, spatial selective weighting on), then the volume
of every frame — and is scored by :func:`stex.stages.evaluation.write_evaluation` on every
``--stride``-th frame, exactly as the workflow scores ``ours_uncorrected``: the variant's volume
is passed as the uncorrected volume (the variants are not colour-corrected; the main run's
``ours`` row against its ``ours_uncorrected`` row gives the correction's own effect).

Reported per variant:
- input view: patch-shift PSNR (dB) against the photos;
- ground truth, novel view (180°): PSNR in the region unseen at t, split into surface another
  frame saw (borrowed) and surface no frame saw (filled); temporal flicker excess in borrowed
  regions (frame-to-frame change of the render minus the true change, grey levels);
- labels against the true appearance (as ``bench_labeling``): error and label switches per face,
  split into *dynamic* faces (their true colour changes over the sequence: temporal std of the
  face's true colour above ``--dynamic-std`` grey levels) and *static* faces. The paper's claim
  for the selective weighting: dynamic regions stay dynamic (switch labels and follow the true
  change: low error) while static regions do not flicker (few switches).

    python benchmarks/bench_ablations.py results/demo [--stride 6] [--scratch /tmp/stex_ablations]
        [--only "temporal off" --only "spatial selective on" ...]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_labeling import gt_error, true_face_colours  # noqa: E402
from stex.io import open_store  # noqa: E402
from stex.stages.data_term import write_data_term  # noqa: E402
from stex.stages.evaluation import EvaluationInputs, write_evaluation  # noqa: E402
from stex.stages.labeling import write_labels  # noqa: E402
from stex.stages.volume import write_volume  # noqa: E402

# name -> (tables overrides, labeling overrides); the first is the main run's configuration
VARIANTS = {
    "ours (selective temporal, both similarities)": ({}, {}),
    "without E_str (the paper's data term)": ({"omega_str": 0.0}, {}),
    "temporal off": ({}, {"temporal": "off"}),
    "temporal constant": ({}, {"temporal": "constant"}),
    "spatial selective on": ({}, {"spatial_selective": True}),
    "global similarity only": ({"similarity": "global"}, {}),
    "local similarity only": ({"similarity": "local"}, {}),
}


def _blocks(R: Path, kind: str) -> list[str]:
    return sorted(str(p) for p in (R / kind).glob("block_*.zarr"))


def run_variant(R: Path, out: Path, tables_over: dict, labels_over: dict, stride: int) -> dict:
    """Re-run tables (if changed), labeling and volume for one variant into ``out``; score it."""
    out.mkdir(parents=True, exist_ok=True)
    scene = open_store(R / "scene.zarr", "scene")
    blocks = scene.attrs["frame_blocks"]
    timing = {}
    tables = _blocks(R, "data_term")
    if tables_over:
        t0 = time.perf_counter()
        base = dict(open_store(tables[0], "data_term").attrs["params"])
        tables = []
        for b, (s, e) in enumerate(blocks):
            p = out / "data_term" / f"block_{b:04d}.zarr"
            shutil.rmtree(p, ignore_errors=True)
            write_data_term(R / "scene.zarr", R / "template.zarr", R / "tracking.zarr", R / "poses.zarr",
                         R / "observations.zarr", [s, e], dict(base, **tables_over), p)
            tables.append(str(p))
        timing["tables_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    labels = out / "labels.zarr"
    shutil.rmtree(labels, ignore_errors=True)
    base = dict(open_store(R / "labels.zarr", "labels").attrs["params"])
    write_labels(R / "observations.zarr", tables, R / "template.zarr", dict(base, **labels_over), labels,
                 projection_path=R / "projection.zarr")
    timing["labeling_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    coords = R / "texcoords.zarr" if (R / "texcoords.zarr").exists() else R / "projection.zarr"
    vparams = dict(open_store(_blocks(R, "volume")[0], "volume").attrs["params"])
    volume = []
    for b, (s, e) in enumerate(blocks):
        p = out / "volume" / f"block_{b:04d}.zarr"
        shutil.rmtree(p, ignore_errors=True)
        write_volume(R / "template.zarr", labels, coords, _blocks(R, "frames"), [s, e], vparams, p)
        volume.append(str(p))
    timing["volume_s"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    ids = [int(i) for i in scene.attrs["frame_ids"]]
    inputs = EvaluationInputs(
        scene=R / "scene.zarr", frames=_blocks(R, "frames"), masks=_blocks(R, "masks"), template=R / "template.zarr",
        tracking=R / "tracking.zarr", projection=R / "projection.zarr", labels=labels, volume=volume,
        corrected=_blocks(R, "corrected"), global_texture=R / "global_texture.zarr", truth=_blocks(R, "truth"),
        coords=coords, data_term=tables)
    ev = write_evaluation(inputs, out / "evaluation", {"stride": stride}, frames=ids[::stride])
    timing["evaluation_s"] = round(time.perf_counter() - t0, 1)
    return {"labels": str(labels), "summary": ev["summary"], "timing": timing}


def label_scores(labels, colours, vis, dynamic) -> dict:
    """Ground-truth label error and switches, on all / dynamic / static faces."""
    L = np.asarray(labels)
    out = {}
    for name, sel in (("all", np.ones(L.shape[1], bool)), ("dynamic", dynamic), ("static", ~dynamic)):
        out[name] = gt_error(L[:, sel], colours[:, sel], vis[:, sel])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path)
    ap.add_argument("--stride", type=int, default=6, help="score every N-th frame (default 6)")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/stex_ablations"))
    ap.add_argument("--dynamic-std", type=float, default=4.0,
                    help="a face is dynamic when its true colour's temporal std exceeds this (grey levels)")
    # repeated rather than comma-separated: the main variant's name holds a comma
    ap.add_argument("--only", action="append", default=None,
                    help="a variant's name; repeat for several (default: all)")
    args = ap.parse_args(argv)
    R = args.results
    if not (R / "truth").is_dir():
        sys.exit(f"{R}: no truth stores — ablations are scored against the synthetic ground truth")
    args.scratch.mkdir(parents=True, exist_ok=True)
    obs = open_store(R / "observations.zarr", "observations")
    vis = np.asarray(obs["face_visible"][...], bool)
    colours = true_face_colours(R)
    dynamic = colours.std(axis=0).mean(-1) > float(args.dynamic_std)
    res = {"results": str(R), "stride": args.stride, "dynamic_std": args.dynamic_std,
           "dynamic_faces": int(dynamic.sum()), "faces": int(dynamic.size), "variants": {}}
    print(f"{dynamic.sum()} of {dynamic.size} faces dynamic (true colour std > {args.dynamic_std})", flush=True)
    names = list(VARIANTS) if args.only is None else [n.strip() for n in args.only]
    for k, name in enumerate(names):
        if name not in VARIANTS:
            sys.exit(f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")
        t_over, l_over = VARIANTS[name]
        t0 = time.perf_counter()
        r = run_variant(R, args.scratch / f"variant_{list(VARIANTS).index(name)}", t_over, l_over, args.stride)
        s = r["summary"]["all"]["ours_uncorrected"]   # the variant's volume ("ours" = the main run's)
        L = open_store(r["labels"], "labels")["labels"][...]
        row = {"input_psnr": s["psnr"]["mean"],
               "gt_novel_psnr_seen": s.get("gt_novel_psnr_seen", {}).get("mean"),
               "gt_novel_psnr_unseen": s.get("gt_novel_psnr_unseen", {}).get("mean"),
               "gt_novel_psnr_borrowed": s.get("gt_novel_psnr_borrowed", {}).get("mean"),
               "gt_novel_psnr_never_seen": s.get("gt_novel_psnr_never_seen", {}).get("mean"),
               "flicker_excess": s.get("flicker_excess", {}).get("mean"),
               "labels": label_scores(L, colours, vis, dynamic),
               "timing": r["timing"], "seconds": round(time.perf_counter() - t0, 1)}
        res["variants"][name] = row
        print(name, json.dumps(row), flush=True)
        (args.scratch / "bench_ablations.json").write_text(json.dumps(res, indent=1))
    print(table(res))


def _f(x, d=2):
    return "n/a" if x is None else f"{x:.{d}f}"


def table(res: dict) -> str:
    """A plain-text table of the variants."""
    head = ("variant", "input PSNR", "GT unseen", "GT borrowed", "GT never seen", "flicker exc.",
            "err dyn", "err static", "switch dyn", "switch static")
    rows = [head]
    for name, r in res["variants"].items():
        lab = r["labels"]
        rows.append((name, _f(r["input_psnr"]), _f(r["gt_novel_psnr_unseen"]), _f(r["gt_novel_psnr_borrowed"]),
                     _f(r["gt_novel_psnr_never_seen"]),
                     _f(r["flicker_excess"], 3), _f(lab["dynamic"]["all"], 3), _f(lab["static"]["all"], 3),
                     _f(lab["dynamic"]["label_switches_per_face"], 1),
                     _f(lab["static"]["label_switches_per_face"], 1)))
    w = [max(len(r[i]) for r in rows) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r)) for r in rows)


if __name__ == "__main__":
    main()
