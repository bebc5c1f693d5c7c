"""Report helpers: stage timings from Snakemake benchmark files, RST tables as HTML, the
paper-style tables over several runs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

__all__ = ["stage_timings", "tables_html", "runs_tables"]


def stage_timings(benchmark_dir, n_blocks: int | None = None) -> dict:
    """Wall time per stage (s): the sum over a stage's jobs of Snakemake's ``benchmark:`` files
    ``<dir>/<rule>[_<block>].tsv`` (column ``s``; block suffixes are summed into one stage).
    With ``n_blocks``, files of blocks ``>= n_blocks`` are left out: they are left over from a
    run of the scene with more frames. Missing directory: {}."""
    out: dict[str, float] = {}
    d = Path(benchmark_dir)
    if not d.is_dir():
        return out
    for path in sorted(d.glob("*.tsv")):
        stem = path.stem
        head, _, tail = stem.rpartition("_")
        stage = head if tail.isdigit() and head else stem
        if stage == head and n_blocks is not None and int(tail) >= n_blocks:
            continue
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh, delimiter="\t"))
        if rows:
            try:
                out[stage] = out.get(stage, 0.0) + float(rows[-1]["s"])
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
    from docutils.core import publish_string

    return publish_string(rst, writer="html5",
                          settings_overrides={"report_level": 4, "embed_stylesheet": True,
                                              "title": "stex evaluation tables"})


def runs_tables(run_dirs) -> str:
    """The paper-style tables (:func:`stex.evaluation.rst_tables`) over several runs, one column
    per run, as the paper lays out its scenes: each ``results/<scene>`` folder's
    ``evaluation/evaluation.json`` summary and its jobs' wall times (``benchmarks/``).

    A held-out run (e.g. ``results/demo_heldout``) is a column of its own, with the held-out
    rows. Raises FileNotFoundError for a folder without an evaluation, ValueError for two runs
    of one scene name.
    """
    from stex.evaluation import nan_for_none, rst_tables

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
