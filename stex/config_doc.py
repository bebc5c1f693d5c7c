"""config/README.md from the schema: the settings a user changes, then the research switches.

``python -m stex.config_doc > config/README.md`` writes it; tests/test_docs.py checks that the
committed file is what this prints, so the page cannot drift from stex/schema.yaml.

A setting's tier is the schema's custom keyword ``tier`` (``user`` or ``research``) on the
setting, or else on its nearest section that has one, or else ``user``. JSON Schema ignores
keywords it does not know, so ``tier`` changes neither validation nor the defaults.
"""
from __future__ import annotations

import json
import sys
from collections.abc import Iterator

from stex.config import load_schema

TIERS = ("user", "research")

HEADER = """\
# Configuration

Every setting of the workflow, generated from `stex/schema.yaml` by
`python -m stex.config_doc > config/README.md` (do not edit by hand; a test compares the two).
Put the settings you change in a scene file and run `snakemake --cores 2 --configfile
my_scene.yaml`; everything left out takes the default below. `config/config.yaml` is the default
scene (`demo`), `config/scenes/` holds the others (`paper.yaml` is paper scale), and
`config/datasets/` runs several scenes at once (docs/datasets.md). `config/recipes/` holds settings
to give after a scene file: `paper_tables.yaml` adds what the paper's tables need and the default
run leaves out, the sampling table (`snakemake --cores 2 --configfile config/scenes/paper.yaml
config/recipes/paper_tables.yaml`; docs/running.md).

Threads are not a setting: `--cores N` caps the run, and each rule asks for its own (most 1, the
poses, texture-coordinate and labeling jobs 2; `workflow/rules/*.smk`). Why each tuned default is
what it is, with the measurements: `docs/decisions/config-<section>.md`.
"""


def settings(schema: dict, prefix: str = "", inherited: str = "user") -> Iterator[tuple[str, dict, str]]:
    """(dotted path, schema node, tier) of every setting, depth first in the schema's order.

    A setting is a property that has no ``properties`` of its own (sections are walked, not
    listed). ValueError naming the key for a ``tier`` other than ``user`` or ``research``.
    """
    for key, node in (schema.get("properties") or {}).items():
        path = f"{prefix}.{key}" if prefix else key
        tier = node.get("tier", inherited)
        if tier not in TIERS:
            raise ValueError(f"schema: {path}: tier {tier!r} is not one of {', '.join(TIERS)}")
        if "properties" in node:
            yield from settings(node, path, tier)
        else:
            yield path, node, tier


def _cell(text: str) -> str:
    # one table row per setting: a newline or a bar would end the cell
    return " ".join(str(text).split()).replace("|", "\\|")


def _default(node: dict) -> str:
    if "default" not in node:
        return ""
    return "`" + json.dumps(node["default"], ensure_ascii=False) + "`"


def table(rows: list[tuple[str, dict, str]]) -> list[str]:
    """Markdown table lines (setting, default, what it does) of ``settings()`` rows."""
    out = ["| setting | default | what it does |", "|---|---|---|"]
    out += [f"| `{path}` | {_default(node)} | {_cell(node.get('description', ''))} |"
            for path, node, _ in rows]
    return out


def markdown(schema: dict | None = None) -> str:
    """The whole of config/README.md for ``schema`` (default: stex/schema.yaml)."""
    rows = list(settings(schema or load_schema()))
    user = [r for r in rows if r[2] == "user"]
    research = [r for r in rows if r[2] == "research"]
    lines = [HEADER, "## The settings you change", "",
             "Where the frames come from, the masks, the template, the tracking mode, the sizes and",
             "what the evaluation scores.", "", *table(user), "",
             "## Research and ablation switches", "",
             "The method's parameters and the paper's ablations (`tier: research` in the schema).",
             "Their defaults were tuned on the demo and checked on the Fox",
             "(docs/decisions/config-*.md); change them to study the method, not to run a capture.", "",
             *table(research)]
    return "\n".join(lines) + "\n"


def main() -> None:
    sys.stdout.write(markdown())


if __name__ == "__main__":
    main()
