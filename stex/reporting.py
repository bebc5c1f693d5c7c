"""Report helpers: stage timings from Snakemake benchmark files, RST tables as HTML."""

from __future__ import annotations

import csv
from pathlib import Path

__all__ = ["stage_timings", "write_tables_html"]


def stage_timings(benchmark_dir) -> dict:
    """Wall time per stage (s): the sum over a stage's jobs of Snakemake's ``benchmark:`` files
    ``<dir>/<rule>[_<block>].tsv`` (column ``s``; block suffixes are summed into one stage).
    Missing directory: {}."""
    out: dict[str, float] = {}
    d = Path(benchmark_dir)
    if not d.is_dir():
        return out
    for path in sorted(d.glob("*.tsv")):
        stem = path.stem
        head, _, tail = stem.rpartition("_")
        stage = head if tail.isdigit() and head else stem
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh, delimiter="\t"))
        if rows:
            out[stage] = out.get(stage, 0.0) + float(rows[-1]["s"])
    return out


def write_tables_html(rst_path, html_path) -> None:
    """The reStructuredText tables of the evaluation as a standalone HTML page (docutils), for
    the Snakemake report (which embeds HTML results)."""
    from docutils.core import publish_string

    html = publish_string(Path(rst_path).read_text(), writer="html5",
                          settings_overrides={"report_level": 4, "embed_stylesheet": True,
                                               "title": "stex evaluation tables"})
    Path(html_path).write_bytes(html)
