"""docs/results.md from the recorded runs, so that the figures quoted in the docs cannot go stale.

A finished run's folder (``results/<scene>``) is not committed; its scores and job times are, as
a small record ``docs/runs/<scene>.json``:

    python benchmarks/results_page.py --add results/demo   # record a finished run, rebuild the page
    python benchmarks/results_page.py                      # rebuild docs/results.md from docs/runs/
    python benchmarks/results_page.py --check              # exit 1 when docs/results.md is stale

A record holds the run's summary scores (``evaluation/evaluation.json``: the mean, and how many
frames it is over, of every metric, method and frame subset), the paper's sampling table, the
wall time, job count and peak memory of every stage (``benchmarks/*.tsv``, Snakemake's
``benchmark:`` files), when the evaluation was written, the commit of the checkout the run lives
in, the machine, and the library versions the evaluation recorded.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

from stex.reporting import (benchmark_rows, method_name, nan_for_none, sampling_rows, stage_timings, table_rows,
                            timing_rows)

REPO = Path(__file__).resolve().parents[1]
RUNS = REPO / "docs" / "runs"
PAGE = REPO / "docs" / "results.md"
TITLES = {"reconstruction": "Texture reconstruction error and blurriness", "coverage": "Coverage",
          "ground_truth": "Ground truth (synthetic scenes)"}
KEPT = ("mean", "n", "n_total")  # of each metric's summary: what the tables show


def _blocks(run: Path) -> int | None:
    # the scene store lists the run's frame blocks; benchmark files of higher blocks are left
    # over from an earlier run of the scene with more frames
    try:
        return len(json.loads((run / "scene.zarr" / "zarr.json").read_text())["attributes"]["frame_blocks"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def stage_jobs(benchmark_dir: Path, n_blocks: int | None = None) -> dict:
    """``{stage: {"jobs": count, "max_rss_mb": peak over its jobs}}`` from the Snakemake benchmark
    files (:func:`stex.reporting.benchmark_rows`, column ``max_rss``, MB)."""
    out: dict[str, dict] = {}
    for name, _, row in benchmark_rows(benchmark_dir, n_blocks):
        stage = out.setdefault(name, {"jobs": 0, "max_rss_mb": None})
        stage["jobs"] += 1
        try:
            rss = float(row["max_rss"])
        except (KeyError, TypeError, ValueError):  # "-" where psutil could not measure
            continue
        stage["max_rss_mb"] = rss if stage["max_rss_mb"] is None else max(stage["max_rss_mb"], rss)
    return out


def _commit(run: Path) -> str:
    try:
        out = subprocess.run(["git", "-C", str(run), "rev-parse", "--short=10", "HEAD"],
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(run), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out + (" (with uncommitted changes)" if dirty else "")


def this_machine() -> str:
    """The CPU model, its logical cores and the memory of this machine, in one line."""
    model = platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1024 ** 3
        memory = f", {mem:.0f} GB"
    except (ValueError, OSError, AttributeError):
        memory = ""
    return f"{model}, {os.cpu_count()} cores{memory}, {platform.system()}"


def _trim(summary: dict) -> dict:
    return {subset: ({method: {metric: {k: s[k] for k in KEPT if k in s} for metric, s in metrics.items()}
                      for method, metrics in methods.items()} if isinstance(methods, dict) else methods)
            for subset, methods in summary.items()}


def record(run: str | Path, machine: str | None = None, commit: str | None = None) -> dict:
    """The record of one finished run folder ``results/<scene>`` (see the module docstring).

    FileNotFoundError naming the file for a folder without ``evaluation/evaluation.json`` (the
    run has not finished), ValueError for an evaluation.json without a summary.
    """
    run = Path(run)
    path = run / "evaluation" / "evaluation.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no evaluation in {run} (a finished run's results/<scene> folder)")
    doc = json.loads(path.read_text())
    if not isinstance(doc.get("summary"), dict) or "all" not in doc["summary"]:
        raise ValueError(f"{path}: not an evaluation.json (no summary scores)")
    n = _blocks(run)
    finished = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc)
    return {"scene": str(doc.get("scene") or run.name),
            "evaluated": finished.strftime("%Y-%m-%d %H:%M UTC"),
            "commit": commit or _commit(run),
            "machine": machine or this_machine(),
            "summary": _trim(doc["summary"]),
            "sampling": doc.get("sampling"),
            "stage_seconds": stage_timings(run / "benchmarks", n),
            "stage_jobs": stage_jobs(run / "benchmarks", n),
            "libraries": doc.get("libraries")}


def _cell(x) -> str:
    return str(x).replace("|", "\\|")


def markdown_table(rows: list[list[str]]) -> list[str]:
    """Lines of a Markdown table from rows, the first the header."""
    out = ["| " + " | ".join(map(_cell, rows[0])) + " |", "|" + "---|" * len(rows[0])]
    return out + ["| " + " | ".join(map(_cell, r)) + " |" for r in rows[1:]]


def load_records(runs_dir: Path = RUNS) -> list[dict]:
    """Every ``<scene>.json`` record in ``runs_dir``, in file-name order."""
    return [json.loads(p.read_text()) for p in sorted(Path(runs_dir).glob("*.json"))]


TEST_SET = REPO / "config" / "datasets" / "test_set.yaml"
#: the headline's rows: (label, metric) of the evaluation's summary, every frame
HEADLINE_ROWS = (("novel view, borrowed (unseen at t, seen by another frame), dB", "gt_novel_psnr_borrowed"),
                 ("novel view, never seen, dB", "gt_novel_psnr_never_seen"),
                 ("input view, unseen at t, dB", "gt_input_psnr_unseen"),
                 ("blur (inputs: the input images)", "blur"),
                 ("face coverage, %", "coverage_faces"),
                 ("flicker in borrowed regions, grey levels", "flicker"),
                 ("change in borrowed regions, grey levels (truth: its own)", "flicker_change"))
HEADLINE_METHODS = ("global", "ours", "oracle", "no_temporal")


def test_scenes(dataset: Path = TEST_SET) -> list[str]:
    """The scene names of the test set's scene files (their ``scene:``), in its order."""
    import yaml

    try:
        files = yaml.safe_load(dataset.read_text()).get("scene_files") or []
    except (OSError, AttributeError):
        return []
    names = []
    for entry in files:
        name = None
        for f in [entry] if isinstance(entry, str) else entry:
            try:
                name = (yaml.safe_load((REPO / f).read_text()) or {}).get("scene", name)
            except OSError:
                pass
        if name:
            names.append(name)
    return names


def _headline_value(summary: dict, method: str, metric: str):
    if method == "input":
        method, metric = "ours", "blur_input"
    if method == "truth":
        method, metric = "ours", "flicker_true_change"
    try:
        v = summary["all"][method][metric]["mean"]
    except (KeyError, TypeError):
        return None
    return None if v is None else float(v)


def headline(records: list[dict], names: list[str]) -> list[str]:
    """The test set's table (the headline): per region, global / ours / oracle / no temporal term
    for every recorded test scene, and their mean over the scenes."""
    recs = [r for n in names for r in records if r["scene"] == n]
    if not recs:
        return []
    rows = [["Quantity", "Method"] + [r["scene"] for r in recs] + ["mean"]]
    for label, metric in HEADLINE_ROWS:
        methods = list(HEADLINE_METHODS) + (["input"] if metric == "blur" else []) + (
            ["truth"] if metric == "flicker_change" else [])
        first = True
        for m in methods:
            vals = [_headline_value(r["summary"], m, metric) for r in recs]
            if all(v is None for v in vals):
                continue
            scale, digits = (100.0, 1) if metric == "coverage_faces" else ((1.0, 4) if metric == "blur" else (1.0, 2))
            fin = [v for v in vals if v is not None]
            cells = ["–" if v is None else f"{v * scale:.{digits}f}" for v in vals]
            mean = f"{sum(fin) / len(fin) * scale:.{digits}f}" if len(fin) == len(vals) else "–"
            name = {"input": "Input images", "truth": "the truth's own change"}.get(m, method_name(m))
            rows.append([label if first else "", name] + cells + [mean])
            first = False
    return ["## The test set (headline)", "",
            "Scenes never used to choose a default (config/datasets/test_set.yaml; docs/datasets.md, \"Dev and",
            "test scenes\"), every frame, against the truth. The oracle is the bound of the labeling and no",
            "temporal term the flicker ablation (docs/metrics.md, \"Reference methods\"). Run:",
            "`python benchmarks/bench_test_set.py --record`. The other runs below are dev scenes (the demo,",
            "dev_body, dev_body_twist) and the paper scene. "
            + (f"Recorded: {len(recs)} of the set's {len(names)} scenes; the mean is over the recorded ones."
               if len(recs) < len(names) else "The mean is over the scenes."), "",
            *markdown_table(rows), ""]


def page(records: list[dict]) -> str:
    """The whole of docs/results.md for ``records`` (one column per run)."""
    lines = ["# Results", "",
             "Generated by `python benchmarks/results_page.py` from the recorded runs in `docs/runs/`",
             "(do not edit by hand; a test compares the two). Record a finished run with",
             "`python benchmarks/results_page.py --add results/<scene>`. What each score measures:",
             "[metrics.md](metrics.md); why the defaults are what they are: [decisions/](decisions/README.md);",
             "older measurements, kept as history: [paper_scale.md](paper_scale.md), [tracking.md](tracking.md).", ""]
    if not records:
        return "\n".join(lines + ["No run has been recorded yet.", ""])
    lines += headline(records, test_scenes())
    names = [r["scene"] for r in records]
    lines += ["## The runs", "", *markdown_table(
        [["run", "evaluated", "commit", "machine", "frames scored (held out)"]]
        + [[r["scene"], r["evaluated"], r["commit"], r["machine"],
            f"{r['summary'].get('n_frames', '–')} ({r['summary'].get('n_held_out', 0)})"] for r in records]), ""]
    for name, rows in table_rows({r["scene"]: nan_for_none(r["summary"]) for r in records}).items():
        lines += [f"## {TITLES.get(name, name)}", "", *markdown_table(rows), ""]
    lines += ["## Time per stage", "",
              "The sum of the wall times of a stage's jobs (Snakemake's benchmark files; two jobs run at",
              "once on two cores, so this is core time, not the run's wall time), and the peak memory of",
              "its largest job.", "",
              *markdown_table(timing_rows({r["scene"]: r["stage_seconds"] for r in records})), ""]
    stages = list(dict.fromkeys(s for r in records for s in r["stage_jobs"]))
    rss = [["Stage"] + [f"{n}: jobs, peak RSS (MB)" for n in names]]
    for s in stages:
        cells = []
        for r in records:
            j = r["stage_jobs"].get(s)
            cells.append("–" if j is None else f"{j['jobs']}, " + ("–" if j["max_rss_mb"] is None else f"{j['max_rss_mb']:.0f}"))
        rss.append([s] + cells)
    lines += [*markdown_table(rss), ""]
    sampling = {r["scene"]: r["sampling"] for r in records if r.get("sampling")}
    if sampling:
        lines += ["## Texture-coordinate optimisation: key-frame sampling", "",
                  *markdown_table(sampling_rows(nan_for_none(sampling if len(sampling) > 1 else next(iter(sampling.values()))))), ""]
    libs = list(dict.fromkeys(k for r in records for k in (r.get("libraries") or {})))
    if libs:
        lines += ["## Library versions", "", *markdown_table(
            [["library"] + names] + [[k] + [(r.get("libraries") or {}).get(k, "–") for r in records] for k in libs]), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--add", metavar="RESULTS", action="append", default=[],
                    help="record a finished run folder (results/<scene>) in docs/runs/<scene>.json")
    ap.add_argument("--machine", help="the machine's description (default: this machine's CPU, cores, memory)")
    ap.add_argument("--commit", help="the commit the run was made at (default: its checkout's HEAD)")
    ap.add_argument("--runs", type=Path, default=RUNS, help="folder of the records (default docs/runs)")
    ap.add_argument("--out", type=Path, default=PAGE, help="the page (default docs/results.md)")
    ap.add_argument("--check", action="store_true", help="exit 1 when the page is not what the records give")
    args = ap.parse_args(argv)
    for run in args.add:
        rec = record(run, args.machine, args.commit)
        args.runs.mkdir(parents=True, exist_ok=True)
        (args.runs / f"{rec['scene']}.json").write_text(json.dumps(rec, indent=1, ensure_ascii=False) + "\n")
    text = page(load_records(args.runs))
    if args.check:
        if not args.out.is_file() or args.out.read_text() != text:
            print(f"{args.out} is stale: python benchmarks/results_page.py", file=sys.stderr)
            return 1
        return 0
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
