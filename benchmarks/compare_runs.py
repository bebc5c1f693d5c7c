"""Whether two finished runs of one scene made the same results: every array of every store equal
(NaN equal to NaN), the evaluation's ``evaluation.json`` equal but for its timings, and
``per_frame.csv`` equal. Used to check that a change meant to move code only (a restructure)
changed nothing a user gets.

    python benchmarks/compare_runs.py results/demo /elsewhere/results/demo
    python benchmarks/compare_runs.py OLD NEW --rename tables=data_term   # a store folder renamed

Exit 0 when they agree, 1 otherwise; every difference is printed, with the store and array.
Store attributes that record when, where and with which library versions a store was written,
and every duration (``seconds``, ``*_s``, ``time_*``, speed-ups), are not compared; nor is the
artifact kind of a store whose folder ``--rename`` maps.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import zarr

# attrs that say how a store was made, not what it holds
PROVENANCE_ATTRS = {"written", "versions", "library_versions", "created", "host", "elapsed_s", "timing",
                    "seconds", "stex_version", "complete"}
# evaluation.json keys that hold the run's times
TIMING_KEYS = {"timing", "timings", "stage_timings", "seconds", "elapsed_s"}


def _stores(run: Path) -> list[Path]:
    return sorted(p.relative_to(run) for p in run.rglob("*.zarr") if (p / "zarr.json").exists()
                  and not any(q.suffix == ".zarr" for q in p.relative_to(run).parents if str(q) != "."))


def _timing(key: str) -> bool:
    """Keys that hold a duration or a ratio of durations: they differ from run to run."""
    return key.startswith("time_") or key.endswith("_s") or key in ("seconds", "speedup", "timings_s")


def _strip(doc, keys):
    if isinstance(doc, dict):
        return {k: _strip(v, keys) for k, v in doc.items() if k not in keys and not _timing(k)}
    if isinstance(doc, list):
        return [_strip(v, keys) for v in doc]
    return doc


def _compare_group(a, b, where: str, out: list, renamed: bool = False) -> int:
    n = 0
    attrs_a, attrs_b = _strip(dict(a.attrs), PROVENANCE_ATTRS), _strip(dict(b.attrs), PROVENANCE_ATTRS)
    if renamed:
        attrs_a.pop("stex_artifact", None)
        attrs_b.pop("stex_artifact", None)
    if attrs_a != attrs_b:
        diff = sorted(k for k in set(attrs_a) | set(attrs_b) if attrs_a.get(k) != attrs_b.get(k))
        out.append(f"{where}: attrs differ: {diff}")
    names_a, names_b = dict(a.members()), dict(b.members())
    for name in sorted(set(names_a) ^ set(names_b)):
        out.append(f"{where}/{name}: only in {'first' if name in names_a else 'second'} run")
    for name in sorted(set(names_a) & set(names_b)):
        x, y = names_a[name], names_b[name]
        if isinstance(x, zarr.Group):
            n += _compare_group(x, y, f"{where}/{name}", out, renamed)
            continue
        n += 1
        if _timing(name):
            continue
        u, v = x[...], y[...]
        if u.shape != v.shape or u.dtype != v.dtype:
            out.append(f"{where}/{name}: {u.shape} {u.dtype} against {v.shape} {v.dtype}")
        elif not np.array_equal(u, v, equal_nan=u.dtype.kind in "fc"):
            bad = np.count_nonzero(~((u == v) | (np.isnan(u) & np.isnan(v)) if u.dtype.kind in "fc" else (u == v)))
            out.append(f"{where}/{name}: {bad} of {u.size} values differ")
    return n


def compare_runs(first: Path, second: Path, renames: dict | None = None) -> list[str]:
    """Every difference between two runs' results, as lines (empty when they agree).
    ``renames`` maps a top-level folder of the first run to its name in the second."""
    out: list[str] = []
    renames = renames or {}
    stores_b = _stores(second)
    originals = {Path(renames.get(s.parts[0], s.parts[0]), *s.parts[1:]): s for s in _stores(first)}
    stores_a = list(originals)
    for s in sorted(set(stores_a) ^ set(stores_b)):
        out.append(f"{s}: only in {'first' if s in stores_a else 'second'} run")
    arrays = 0
    for s in sorted(set(stores_a) & set(stores_b)):
        arrays += _compare_group(zarr.open_group(first / originals[s], mode="r"), zarr.open_group(second / s, mode="r"),
                                 str(s), out, renamed=originals[s] != s)
    for name in ("evaluation/evaluation.json", "evaluation/per_frame.csv"):
        pa, pb = first / name, second / name
        if pa.exists() != pb.exists():
            out.append(f"{name}: only in {'first' if pa.exists() else 'second'} run")
        elif pa.exists():
            if name.endswith(".json"):
                da, db = (_strip(json.loads(p.read_text()), TIMING_KEYS) for p in (pa, pb))
                if da != db:
                    keys = sorted(k for k in set(da) | set(db) if da.get(k) != db.get(k))
                    out.append(f"{name}: differs in {keys}")
            elif pa.read_bytes() != pb.read_bytes():
                out.append(f"{name}: differs")
    print(f"compared {len(set(stores_a) & set(stores_b))} stores, {arrays} arrays", file=sys.stderr)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("first", type=Path)
    ap.add_argument("second", type=Path)
    ap.add_argument("--rename", action="append", default=[], metavar="OLD=NEW",
                    help="a top-level folder of the first run that the second names NEW")
    args = ap.parse_args(argv)
    diffs = compare_runs(args.first, args.second, dict(r.split("=", 1) for r in args.rename))
    print("\n".join(diffs) if diffs else "the two runs agree")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
