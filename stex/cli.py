"""The ``stex`` command line: tasks a user runs outside Snakemake.

    stex inspect results/demo/scene.zarr      # what a store holds: kind, frames, arrays, params
"""

from __future__ import annotations

import argparse
import json
import sys

import zarr

from stex.io import ARTIFACTS, StoreError, open_store


def _arrays(group: zarr.Group, prefix: str = ""):
    for name, member in sorted(group.members(), key=lambda m: m[0]):
        path = f"{prefix}{name}"
        if isinstance(member, zarr.Group):
            yield from _arrays(member, path + "/")
        else:
            yield path, member


def inspect_store(path: str) -> str:
    """A human-readable summary of one artifact store."""
    raw = zarr.open_group(path, mode="r")
    kind = raw.attrs.get("stex_artifact")
    if kind not in ARTIFACTS:
        raise StoreError(f"{path}: not a stex artifact store (stex_artifact={kind!r})")
    group = open_store(path, kind)
    lines = [f"{path}: artifact '{kind}' (stex {group.attrs.get('stex_version')})",
             f"  {ARTIFACTS[kind].description}"]
    ids = group.attrs.get("frame_ids")
    if ids:
        lines.append(f"  frames: {len(ids)} ({ids[0]}..{ids[-1]})")
    units = group.attrs.get("units", {})
    for name, arr in _arrays(group):
        lines.append(f"  {name:28s} {str(arr.shape):24s} {str(arr.dtype):8s} {units.get(name, '')}")
    params = group.attrs.get("params")
    if params:
        lines.append("  params: " + json.dumps(params, sort_keys=True)[:400])
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="stex", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("inspect", help="summarise artifact stores")
    p.add_argument("stores", nargs="+")
    args = parser.parse_args(argv)
    status = 0
    for store in args.stores:
        try:
            print(inspect_store(store))
        except (StoreError, FileNotFoundError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
