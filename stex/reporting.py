"""Report helpers: the paper-style tables (rows, reStructuredText, HTML) of evaluation
summaries, stage timings from Snakemake benchmark files, the tables over several runs, and the
NaN <-> null mapping of ``evaluation.json``."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["METHODS", "METHOD_NAMES", "method_name", "table_rows", "timing_rows", "sampling_rows",
           "rst_tables", "finite_or_none", "nan_for_none", "stage_timings", "tables_html",
           "runs_tables", "library_differences"]


#: Methods scored by :func:`write_evaluation`, in table order.
METHODS = ("ours", "ours_uncorrected", "global", "projection")


#: Their names in tables and plots.
METHOD_NAMES = {"input": "Input images", "ours": "Ours", "ours_uncorrected": "Ours, uncorrected",
                "global": "Kim et al. 2019 (global)", "projection": "Per-frame projection",
                # evaluation.references (built by the workflow, scored as other methods)
                "oracle": "Oracle labels (bound)", "oracle_candidates": "Oracle among our candidates",
                "no_temporal": "Ours, no temporal term"}


def method_name(method: str) -> str:
    """The name tables and figures show for a method (an other method's own name)."""
    return METHOD_NAMES.get(method, method)


def _fmt(x, digits=2, scale=1.0):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x * scale:.{digits}f}"


def _grid(header: list[str], rows: list[list[str]]) -> str:
    """A reStructuredText grid table."""
    cols = list(zip(*([header] + rows)))
    widths = [max(len(c) for c in col) for col in cols]
    line = "+" + "+".join("-" * (w + 2) for w in widths) + "+"
    head = "+" + "+".join("=" * (w + 2) for w in widths) + "+"

    def row(cells):
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    return "\n".join([line, row(header), head] + [x for r in rows for x in (row(r), line)]) + "\n"


def _mean(summary, subset, method, metric):
    try:
        return summary[subset][method][metric]["mean"]
    except KeyError:
        return math.nan


def table_rows(summaries: dict) -> dict:
    """The paper-style tables as lists of rows (header first) over scenes ``{scene: summary}``,
    where a summary is ``evaluation.json``'s ``summary`` (plus its ``held_out_label`` and
    ``blur_interior_px``).

    Returns ``{table name: [header, row, ...]}`` for ``reconstruction``, ``coverage`` and
    ``ground_truth`` (the last only when some scene has ground truth).
    """
    scenes = list(summaries)
    rec = [["Metric", "Method"] + scenes]
    # the pipeline's methods, then other methods scored beside them (stex evaluate --texture)
    others = list(dict.fromkeys(m for s in scenes for m in summaries[s].get("all", {})
                                if m not in METHODS))
    methods = list(METHODS) + others

    def add(table, label, method, subset, metric, digits=2, scale=1.0, name=None, count=False):
        vals = [_mean(summaries[s], subset, method, metric) for s in scenes]
        if all(not math.isfinite(v) for v in vals):
            return
        first = "" if any(r[0] == label for r in table[1:]) else label   # group label once
        cells = [_fmt(v, digits, scale) for v in vals]
        if count:  # a region absent from most frames (e.g. seen at t, from behind): say over how many
            for k, s in enumerate(scenes):
                got = summaries[s].get(subset, {}).get(method, {}).get(metric, {})
                if math.isfinite(vals[k]) and got.get("n", 0) < got.get("n_total", 0):
                    cells[k] += f" ({got['n']} of {got['n_total']} frames)"
        table.append([first, name or method_name(method)] + cells)

    for m in methods:
        add(rec, "PSNR, dB (every frame)", m, "all", "psnr")
    for s in scenes:
        if summaries[s].get("n_held_out", 0):
            for m in ["global", "ours", "ours_uncorrected"] + others:
                label = summaries[s].get("held_out_label", "")
                add(rec, "PSNR, dB (held-out frames)", m, "held_out", "psnr",
                    name=method_name(m) + (f" {label}" if m in ("ours", "ours_uncorrected") else ""))
            break
    for m in methods:
        add(rec, "Plain PSNR, dB (every frame)", m, "all", "psnr_plain")
    for m in methods:
        add(rec, "SSIM (every frame)", m, "all", "ssim", digits=4)
    add(rec, "Blurriness (Crete et al.)", "ours", "all", "blur_input", digits=4, name=METHOD_NAMES["input"])
    add(rec, "Blurriness (Crete et al.)", "ours", "all", "blur_truth", digits=4,
        name="true appearance, rendered")
    for m in ["global", "ours", "ours_uncorrected", "projection"] + others:
        add(rec, "Blurriness (Crete et al.)", m, "all", "blur", digits=4)
    # the same without the silhouette band, where a photo mixes object and background
    bands = sorted({summaries[s].get("blur_interior_px") for s in scenes} - {None})
    inner = ("Blurriness, object interior (mask eroded by "
             + " / ".join(str(b) for b in bands) + " px)")
    add(rec, inner, "ours", "all", "blur_input_interior", digits=4, name=METHOD_NAMES["input"])
    add(rec, inner, "ours", "all", "blur_truth_interior", digits=4, name="true appearance, rendered")
    for m in ["global", "ours", "ours_uncorrected", "projection"] + others:
        add(rec, inner, m, "all", "blur_interior", digits=4)
    # the blur metric reads noise as sharpness: how noisy the inputs are belongs beside it
    add(rec, "Noise, grey levels (Immerkær)", "ours", "all", "noise_input", digits=2,
        name=METHOD_NAMES["input"])

    cov = [["Coverage (mean over frames)", "Method"] + scenes]
    for metric, label in (("coverage_faces", "faces, %"), ("coverage_area", "surface area, %"),
                          ("coverage_seen", "of the faces seen by some frame, %")):
        for m in methods:
            add(cov, label, m, "all", metric, digits=1, scale=100.0)
    out = {"reconstruction": rec, "coverage": cov}

    gt = [["Ground truth (novel view unless stated)", "Method"] + scenes]
    for metric, label, digits in (("gt_novel_psnr_all", "PSNR, dB, whole object", 2),
                                  ("gt_novel_psnr_seen", "PSNR, dB, seen at t", 2),
                                  ("gt_novel_psnr_unseen", "PSNR, dB, unseen at t", 2),
                                  ("gt_novel_psnr_borrowed", "PSNR, dB, unseen at t, seen by another frame", 2),
                                  ("gt_novel_psnr_never_seen", "PSNR, dB, never seen", 2),
                                  ("gt_novel_ssim_unseen", "SSIM, unseen at t", 4),
                                  ("gt_input_psnr_all", "PSNR, dB, input view", 2),
                                  ("gt_input_psnr_seen", "PSNR, dB, input view, seen at t", 2),
                                  ("gt_input_psnr_unseen", "PSNR, dB, input view, unseen at t", 2),
                                  ("gt_truegeom_psnr_unseen", "on the true surface: PSNR, dB, unseen at t", 2),
                                  ("gt_truegeom_psnr_borrowed", "on the true surface: PSNR, dB, unseen at t, seen by another frame", 2),
                                  ("gt_truegeom_psnr_never_seen", "on the true surface: PSNR, dB, never seen", 2),
                                  ("gt_truegeom_input_psnr_all", "on the true surface: PSNR, dB, input view", 2),
                                  ("gt_truegeom_input_psnr_seen", "on the true surface: PSNR, dB, input view, seen at t", 2),
                                  ("gt_truegeom_input_psnr_unseen", "on the true surface: PSNR, dB, input view, unseen at t", 2),
                                  ("flicker", "flicker in borrowed regions, grey levels", 2)):
        for m in methods:
            add(gt, label, m, "all", metric, digits=digits, count=True)
    if len(gt) > 1:
        out["ground_truth"] = gt
    return out


def timing_rows(timing: dict) -> list[list[str]]:
    """Rows (header first) of the timing table from ``{stage: seconds}`` or
    ``{scene: {stage: seconds}}``."""
    if timing and all(isinstance(v, dict) for v in timing.values()):
        scenes = list(timing)
        stages = list(dict.fromkeys(k for v in timing.values() for k in v))
    else:
        scenes, stages, timing = ["time"], list(timing or {}), {"time": dict(timing or {})}
    rows = [["Stage"] + [f"{s} (min)" for s in scenes]]
    for st in stages:
        rows.append([st] + [_fmt(timing[s].get(st, math.nan), 2, 1 / 60) for s in scenes])
    return rows


def sampling_rows(steps) -> list[list[str]]:
    """Rows (header first) of the paper's sampling table from :func:`stex.texcoords.sampling_table`'s
    rows of one run (a list), or of several runs (``{run: rows}``: a row per run and measure, and
    the error ratio averaged over the runs, as the paper averages its datasets): per key-frame
    sampling 1/n, the error ratio (final all-frame Eq. 1 energy over that with every frame a key
    frame), the key frames, the stage time and the speed-up."""
    runs = steps if isinstance(steps, dict) else {"": steps}
    order = sorted({int(r["step"]) for rows in runs.values() for r in rows})
    rows = [["Texture-coordinate optimisation"] + [f"1/{n}" for n in order]]

    def row(label, rs, key, digits):
        by = {int(r["step"]): r for r in rs}
        return [label] + [str(by[n][key]) if digits is None and n in by else
                          _fmt(by[n][key] if n in by else math.nan, digits) for n in order]

    for name, rs in runs.items():
        prefix = f"{name}: " if name else ""
        rows.append(row(prefix + "error ratio", rs, "error_ratio", 4))
        rows.append(row(prefix + "key frames", rs, "keyframes", None))
        rows.append(row(prefix + "stage time, s", rs, "seconds", 1))
        rows.append(row(prefix + "speed-up", rs, "speedup", 2))
    if len(runs) > 1:
        mean = [float(np.nanmean([next((r["error_ratio"] for r in rs if int(r["step"]) == n), math.nan)
                                  for rs in runs.values()])) for n in order]
        rows.append(["mean error ratio over the runs"] + [_fmt(v, 4) for v in mean])
    return rows


def rst_tables(summaries: dict, timing: dict | None = None, sampling=None) -> str:
    """reStructuredText (no HTML) tables like the paper's, over scenes ``{scene: summary}``.

    Sections: reconstruction error and blur per method (the paper's Table 3: PSNR every frame,
    PSNR on held-out frames, blur), coverage, ground truth (synthetic scenes) and timing per
    stage (``{stage: seconds}`` or ``{scene: {stage: seconds}}``, shown in minutes as the
    paper's Table 1), and the sampling table of one run or several (:func:`sampling_rows`).
    """
    titles = {"reconstruction": "Texture reconstruction error and blurriness",
              "coverage": "Coverage",
              "ground_truth": "Ground truth (synthetic scenes)",
              "timing": "Computation time",
              "sampling": "Texture-coordinate optimisation: key-frame sampling"}
    notes = {
        "reconstruction": "PSNR inside the object mask between input photos and renders of the "
                          "texture on the tracked mesh; the patch-shift PSNR translates 32 x 32 "
                          "patches by up to 4 px (docs/metrics.md). Blur: Crete et al. 2007 "
                          "(skimage, h_size 11), smaller is sharper; 'object interior' "
                          "leaves out a band along the silhouette, where a photo's pixels mix "
                          "the object with the background.",
        "coverage": "Faces (or area) with texture per frame, averaged over the scored frames.",
        "ground_truth": "Renders of the texture on our tracked mesh against the true appearance "
                        "on the true mesh, from the opposite side (novel view), split into the "
                        "surface the camera sees at t and the rest. 'On the true surface': the "
                        "same texture rendered on the true geometry (the template carried onto "
                        "the true mesh), so that only the texture's own error remains; in the "
                        "input view the tracked mesh forgives a frame's own texels the tracker's "
                        "error at that frame (they come back to the pixels they were read from), "
                        "the true surface does not.",
        "timing": "Wall time per stage.",
        "sampling": "The texture-coordinate stage run with key frames every n-th frame (1/n) and "
                    "the displacements interpolated between them, then refined over all frames "
                    "(Kim et al. 2021 §4). Error ratio: the final all-frame Eq. 1 energy divided "
                    "by that with every frame a key frame (1/1). The runs ran one after another "
                    "in one job (rule texcoords_sampling).",
    }
    tabs = table_rows(summaries)
    if timing:
        tabs["timing"] = timing_rows(timing)
    if sampling:
        tabs["sampling"] = sampling_rows(sampling)
    parts = []
    for name, rows in tabs.items():
        t = titles[name]
        parts.append(f"{t}\n{'-' * len(t)}\n\n{notes[name]}\n\n{_grid(rows[0], rows[1:])}")
    return "\n".join(parts)


def finite_or_none(x):
    """``x`` (nested dicts, lists, numpy scalars) with every NaN or infinity as None, for JSON:
    ``evaluation.json`` holds null where a score is undefined."""
    if isinstance(x, dict):
        return {str(k): finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_none(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def nan_for_none(x):
    """The inverse of ``finite_or_none`` for what ``evaluation.json`` files hold: every null
    (in nested dicts and lists) back to NaN, so that records and summaries read from JSON score
    and summarise as the ones computed in-process."""
    if isinstance(x, dict):
        return {k: nan_for_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [nan_for_none(v) for v in x]
    return math.nan if x is None else x


def benchmark_rows(benchmark_dir, n_blocks: int | None = None):
    """``(stage, path, last row)`` of every Snakemake ``benchmark:`` file
    ``<dir>/<rule>[_<block>].tsv`` that has a row, block suffixes folded into the stage. With
    ``n_blocks``, files of blocks ``>= n_blocks`` are left out: they are left over from a run of
    the scene with more frames. Missing directory: nothing."""
    d = Path(benchmark_dir)
    if not d.is_dir():
        return
    for path in sorted(d.glob("*.tsv")):
        stem = path.stem
        head, _, tail = stem.rpartition("_")
        stage = head if tail.isdigit() and head else stem
        if stage == head and n_blocks is not None and int(tail) >= n_blocks:
            continue
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh, delimiter="\t"))
        if rows:
            yield stage, path, rows[-1]


def stage_timings(benchmark_dir, n_blocks: int | None = None) -> dict:
    """Wall time per stage (s): the sum over a stage's jobs of column ``s`` of their
    :func:`benchmark_rows`. Missing directory: {}."""
    out: dict[str, float] = {}
    for stage, path, row in benchmark_rows(benchmark_dir, n_blocks):
        try:
            out[stage] = out.get(stage, 0.0) + float(row["s"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{path}: not a Snakemake benchmark file (no seconds in column 's')") from None
    return out


def _block_count(scene_store) -> int | None:
    """The number of frame blocks a run's scene store lists (attr ``frame_blocks``); None when
    it cannot be read (a folder ``stex evaluate`` wrote has no scene)."""
    try:
        return len(json.loads((Path(scene_store) / "zarr.json").read_text())["attributes"]["frame_blocks"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def tables_html(rst: str) -> bytes:
    """reStructuredText tables as a standalone HTML page (docutils), for the Snakemake report,
    which embeds HTML results (the evaluation folder's ``tables.html``)."""
    from docutils.core import publish_string  # docutils loads slowly; only the HTML tables need it

    return publish_string(rst, writer="html5",
                          settings_overrides={"report_level": 4, "embed_stylesheet": True,
                                              "title": "stex evaluation tables"})


def runs_tables(run_dirs) -> str:
    """The paper-style tables (:func:`rst_tables`) over several runs, one column
    per run, as the paper lays out its scenes: each ``results/<scene>`` folder's
    ``evaluation/evaluation.json`` summary and its jobs' wall times (``benchmarks/``).

    A held-out run (e.g. ``results/demo_heldout``) is a column of its own, with the held-out
    rows. Raises FileNotFoundError for a folder without an evaluation, ValueError for two runs
    of one scene name.
    """
    summaries, timing, sampling, libraries = {}, {}, {}, {}
    for d in map(Path, run_dirs):
        # a run's folder, or an evaluation folder itself (as ``stex evaluate --out`` writes)
        path = d / "evaluation.json" if (d / "evaluation.json").is_file() else d / "evaluation" / "evaluation.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no evaluation in {d} (run the workflow on that "
                                    f"scene first, or give a folder 'stex evaluate' wrote)")
        try:
            doc = json.loads(path.read_text())
            # an evaluation folder of its own is named by its folder (it re-scores some run's scene)
            own = path.parent == d
            name, summary = (d.resolve().name if own else str(doc.get("scene") or d.name)), doc["summary"]
            if not isinstance(summary, dict) or "all" not in summary:
                raise ValueError("its summary has no scores")
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{path}: not an evaluation.json ({e})") from e
        if name in summaries:
            raise ValueError(f"{path}: a second run of scene {name!r}; give each scene once")
        summaries[name] = nan_for_none(summary)
        libraries[name] = doc.get("libraries")
        timing[name] = stage_timings(d / "benchmarks", _block_count(d / "scene.zarr"))
        if doc.get("sampling"):
            sampling[name] = nan_for_none(doc["sampling"])
    if not summaries:
        raise ValueError("no runs given")
    rst = rst_tables(summaries, timing if any(timing.values()) else None, sampling or None)
    note = library_differences(libraries)
    return rst + ("\n" + note + "\n" if note else "")


def library_differences(libraries: dict) -> str:
    """A sentence naming the libraries whose versions differ between runs, or "" when they agree.

    Args:
        libraries: run name -> its ``evaluation.json`` ``libraries`` (None for a run scored
            before they were recorded).

    A newer numba, scipy or pyamg moves a figure in its last digits, so figures compared across
    runs made on different installs are read with that in mind.
    """
    if len(libraries) < 2:
        return ""
    unknown = sorted(n for n, v in libraries.items() if not v)
    known = {n: v for n, v in libraries.items() if v}
    parts = []
    for lib in sorted({k for v in known.values() for k in v}):
        got = {n: v.get(lib, "not installed") for n, v in known.items()}
        if len(set(got.values())) > 1:
            parts.append(f"{lib} " + ", ".join(f"{ver} ({n})" for n, ver in got.items()))
    if unknown:
        parts.append("not recorded for " + ", ".join(unknown))
    if not parts:
        return ""
    return ("The runs were scored with different library versions, which can move a figure in "
            "its last digits: " + "; ".join(parts) + ".")
