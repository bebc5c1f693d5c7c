"""Run a dataset of synthetic scenes (default: the test set, config/datasets/test_set.yaml) and print
its table: per scene, the global texture, ours and the reference methods (the oracle bound of the
labeling, ours without the temporal term: evaluation.references) against the truth.

    python benchmarks/bench_test_set.py [--dataset config/datasets/test_set.yaml] [--cores 2]
        [--no-run] [--record] [--json out.json]

Runs ``nice -n 5 snakemake --snakefile workflow/dataset.smk --configfile DATASET --cores N
--keep-going`` on the scenes' ``evaluation`` folders only (no previews, video or viewer), then
reads each ``results/<scene>/evaluation/evaluation.json``. Rows, all means over the scored frames:

- novel view (180°), surface unseen at t that another frame saw (borrowed), and surface no frame
  saw (never seen): PSNR against the truth (dB);
- input view, surface unseen at t: PSNR against the truth (dB);
- patch-shift PSNR against the photos (dB), every frame;
- blur (Crete et al.) of the method's render and of the inputs;
- face coverage (%);
- flicker in borrowed regions of the novel view (mean |d_rec - d_true|, grey levels), and the
  frame-to-frame change of the render against the truth's own change.

Then, per scene: oracle - global on the borrowed region (a scene whose oracle gains less than
1 dB cannot show the method), ours - global and the fraction of the oracle's gain ours reaches.
``--record`` writes each finished run's record into docs/runs/ and regenerates docs/results.md
(benchmarks/results_page.py).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from stex.config import dataset_scene_configs  # noqa: E402

#: (label, metric, methods' metric or None for the method's own) in the table's order
ROWS = (
    ("novel view, borrowed (dB)", "gt_novel_psnr_borrowed"),
    ("novel view, never seen (dB)", "gt_novel_psnr_never_seen"),
    ("input view, unseen at t (dB)", "gt_input_psnr_unseen"),
    ("patch-shift PSNR, photos (dB)", "psnr"),
    ("blur", "blur"),
    ("face coverage (%)", "coverage_faces"),
    ("flicker, borrowed (grey levels)", "flicker"),
    ("change, borrowed (grey levels)", "flicker_change"),
)
METHOD_ORDER = ("global", "ours", "oracle", "oracle_candidates", "no_temporal")


def _mean(summary, method, metric, subset="all"):
    try:
        v = summary[subset][method][metric]["mean"]
    except (KeyError, TypeError):
        return math.nan
    return math.nan if v is None else float(v)


def _f(x, d=2):
    return "–" if x is None or not math.isfinite(x) else f"{x:.{d}f}"


def scene_rows(name: str, summary: dict) -> list[list[str]]:
    """Rows ``[scene, quantity, method values...]`` of one scene's summary."""
    methods = [m for m in METHOD_ORDER if m in summary.get("all", {})]
    rows = []
    for label, metric in ROWS:
        digits = 4 if metric == "blur" else 2
        scale = 100.0 if metric == "coverage_faces" else 1.0
        cells = [_f(_mean(summary, m, metric) * scale, digits) for m in methods]
        if metric == "blur":
            cells.append(f"inputs {_f(_mean(summary, 'ours', 'blur_input'), 4)}")
        if metric == "flicker_change":
            cells.append(f"truth {_f(_mean(summary, 'ours', 'flicker_true_change'))}")
        rows.append([name, label, *cells])
    return rows, methods


def verdicts(name: str, summary: dict) -> dict:
    """The issue-56 figures of one scene (borrowed region, novel view; input view; flicker)."""
    g, o = _mean(summary, "global", "gt_novel_psnr_borrowed"), _mean(summary, "ours", "gt_novel_psnr_borrowed")
    orc = _mean(summary, "oracle", "gt_novel_psnr_borrowed")
    gain = orc - g
    return {"scene": name, "ours_minus_global": o - g, "oracle_minus_global": gain,
            "shows_method": bool(math.isfinite(gain) and gain >= 1.0),
            "fraction_of_oracle_gain": (o - g) / gain if math.isfinite(gain) and gain > 0 else math.nan,
            "input_unseen_ours_minus_global": _mean(summary, "ours", "gt_input_psnr_unseen")
            - _mean(summary, "global", "gt_input_psnr_unseen"),
            "flicker_ours": _mean(summary, "ours", "flicker"),
            "flicker_no_temporal": _mean(summary, "no_temporal", "flicker"),
            "change_ours": _mean(summary, "ours", "flicker_change"),
            "change_truth": _mean(summary, "ours", "flicker_true_change"),
            "blur_ours": _mean(summary, "ours", "blur"), "blur_inputs": _mean(summary, "ours", "blur_input"),
            "coverage_ours": _mean(summary, "ours", "coverage_faces")}


def print_table(results: dict) -> str:
    """The table of every scene with a summary, then the per-scene verdicts."""
    out, methods_all = [], []
    for name, summary in results.items():
        rows, methods = scene_rows(name, summary)
        methods_all = methods if len(methods) > len(methods_all) else methods_all
        out += rows
    head = ["scene", "quantity", *methods_all, "reference"]
    rows = [head] + out
    w = [max(len(r[i]) if i < len(r) else 0 for r in rows) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)) for r in rows]
    lines += ["", "borrowed region, novel view (dB); input view unseen at t (dB); flicker (grey levels):"]
    vs = [verdicts(n, s) for n, s in results.items()]
    for v in vs:
        lines.append(
            f"{v['scene']}: ours-global {_f(v['ours_minus_global'])}, oracle-global "
            f"{_f(v['oracle_minus_global'])} ({'can' if v['shows_method'] else 'cannot'} show the method), "
            f"ours reaches {_f(100 * v['fraction_of_oracle_gain'], 0)} % of the oracle's gain; input view "
            f"unseen ours-global {_f(v['input_unseen_ours_minus_global'])}; flicker ours "
            f"{_f(v['flicker_ours'])} / no temporal {_f(v['flicker_no_temporal'])}; change ours "
            f"{_f(v['change_ours'])} / truth {_f(v['change_truth'])}")
    fin = [v["ours_minus_global"] for v in vs if math.isfinite(v["ours_minus_global"])]
    if fin:
        lines.append(f"mean over {len(fin)} scenes: ours-global (borrowed, novel view) {_f(sum(fin) / len(fin))} dB")
    text = "\n".join(lines)
    print(text)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, default=REPO / "config" / "datasets" / "test_set.yaml")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--no-run", action="store_true", help="only read the finished runs' evaluations")
    ap.add_argument("--prioritize", action="append", default=[], metavar="SCENE",
                    help="make this scene's evaluation first (snakemake --prioritize; repeatable), so that "
                         "on a loaded machine some scenes finish early rather than all late")
    ap.add_argument("--record", action="store_true",
                    help="record each finished run in docs/runs/ and regenerate docs/results.md")
    ap.add_argument("--json", type=Path, help="also write the summaries and verdicts to this file")
    args = ap.parse_args(argv)
    dataset = yaml.safe_load(args.dataset.read_text())
    os.chdir(REPO)  # the scene files' paths are relative to the repository, as for snakemake
    scenes = dataset_scene_configs(dataset, where=str(args.dataset))
    folders = {name: Path(c["results"]) / name for name, c in scenes.items()}
    if not args.no_run:
        cmd = ["nice", "-n", "5", sys.executable, "-m", "snakemake", "--snakefile", "workflow/dataset.smk",
               "--configfile", str(args.dataset), "--cores", str(args.cores), "--keep-going",
               *[str(f / "evaluation") for f in folders.values()]]
        if args.prioritize:
            cmd += ["--prioritize", *[str(folders[n] / "evaluation") for n in args.prioritize]]
        print(" ".join(cmd), flush=True)
        t0 = time.perf_counter()
        rc = subprocess.run(cmd).returncode
        print(f"snakemake exit {rc} after {time.perf_counter() - t0:.0f} s wall", flush=True)
    results = {}
    for name, folder in folders.items():
        path = folder / "evaluation" / "evaluation.json"
        if not path.is_file():
            print(f"{name}: no {path} (its run failed or has not run: see {folder / 'logs'})", file=sys.stderr)
            continue
        results[name] = json.loads(path.read_text())["summary"]
    if not results:
        return 1
    text = print_table(results)
    if args.json:
        args.json.write_text(json.dumps({"dataset": str(args.dataset), "summaries": results, "table": text,
                                         "verdicts": [verdicts(n, s) for n, s in results.items()]}, indent=1))
    if args.record:
        from results_page import main as results_page
        adds = [a for f in folders.values() if (f / "evaluation" / "evaluation.json").is_file()
                for a in ("--add", str(f))]
        results_page(adds)
    return 0 if len(results) == len(folders) else 1


if __name__ == "__main__":
    sys.exit(main())
