"""Time the texture stages (observations, tables, labeling, volume, correction) on a finished run.

Re-runs each stage writer on the stores of an existing ``results/<scene>`` (made by
``snakemake --cores 2 [--configfile config/scenes/paper.yaml]``) into a scratch folder, one
stage per subprocess so that the peak RSS of each is its own, and prints wall time, per-unit time
(per frame / slice / BCD round) and peak RSS. The issue targets on the paper scene (2 cores):
tables ≤ 5 min in all, labeling ≤ 1.5 s per frame per round, volume ≤ 1 s and correction ≤ 6 s
per 4096² slice, peak RSS ≤ 4 GB per job.

    python benchmarks/bench_stages.py results/paper [--stages tables,labeling,volume,correction]
        [--block 0] [--scratch /tmp/stex_bench_stages]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CODE = {
    "observations": "from stex.observations import write_observations as w; w(R/'template.zarr', R/'tracking.zarr', R/'projection.zarr', C, F, cfg['observations'], O/'observations.zarr')",
    "data_term": "from stex.data_term import write_data_term as w; w(R/'scene.zarr', R/'template.zarr', R/'tracking.zarr', R/'poses.zarr', R/'observations.zarr', B, cfg['tables'], O/'data_term.zarr')",
    "labeling": "from stex.labeling import write_labels as w; w(R/'observations.zarr', T, R/'template.zarr', cfg['labeling'], O/'labels.zarr', threads=2)",
    "volume": "from stex.volume import write_volume as w; w(R/'template.zarr', R/'labels.zarr', C, F, B, cfg['volume'], O/'volume.zarr')",
    "correction": "from stex.correction import write_corrected as w; w(R/'template.zarr', V, cfg['correction'], O/'corrected.zarr')",
}


def run_stage(stage: str, results: Path, out: Path, block: int) -> dict:
    prelude = f"""
import sys, json, shutil
from pathlib import Path
sys.path.insert(0, {str(REPO)!r})
from stex.io import open_store
R = Path({str(results)!r}); O = Path({str(out)!r})
params = open_store(R / 'labels.zarr', 'labels').attrs if (R / 'labels.zarr').exists() else {{}}
scene = open_store(R / 'scene.zarr', 'scene')
blocks = scene.attrs['frame_blocks']
B = blocks[{block}]
F = sorted(str(p) for p in (R / 'frames').glob('block_*.zarr'))
T = sorted(str(p) for p in (R / 'tables').glob('block_*.zarr'))
V = sorted(str(p) for p in (R / 'volume').glob('block_*.zarr'))[{block}]
obs = open_store(R / 'observations.zarr', 'observations')
C = R / ('texcoords.zarr' if obs.attrs['coordinates'] == 'texcoords' else 'projection.zarr')
def stored(path, kind):
    return dict(open_store(path, kind).attrs.get('params', {{}}))
cfg = {{'observations': stored(R / 'observations.zarr', 'observations'),
       'tables': stored(T[0], 'tables'),
       'labeling': stored(R / 'labels.zarr', 'labels') if (R / 'labels.zarr').exists() else {{}},
       'volume': stored(V, 'volume'),
       'correction': stored(sorted((R / 'corrected').glob('block_*.zarr'))[{block}], 'corrected')}}
for name in ('observations.zarr', 'tables.zarr', 'labels.zarr', 'volume.zarr', 'corrected.zarr'):
    shutil.rmtree(O / name, ignore_errors=True)
"""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", prelude + CODE[stage]], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"stage": stage, "wall_s": round(time.perf_counter() - t0, 2),
            "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 2),
            "peak_rss_gb": round(after.ru_maxrss / 2**20, 3)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path)
    ap.add_argument("--stages", default="tables,labeling,volume,correction")
    ap.add_argument("--block", type=int, default=0)
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/stex_bench_stages"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from stex.io import open_store

    rows = []
    for stage in args.stages.split(","):
        r = run_stage(stage, args.results.resolve(), args.scratch, args.block)
        out = args.scratch
        if stage == "data_term":
            g = open_store(out / "tables.zarr", "data_term")
            r["per_target_s"] = round(r["wall_s"] / len(g.attrs["frame_ids"]), 3)
            r["blocks"] = len(open_store(args.results / "scene.zarr", "scene").attrs["frame_blocks"])
        if stage == "labeling":
            g = open_store(out / "labels.zarr", "labels")
            T = len(g.attrs["frame_ids"])
            r["rounds"] = [{"round": x["round"], "s_per_frame": round(x["seconds"] / T, 3),
                            "energy": round(x["energy"], 3)} for x in g.attrs["rounds"]]
        if stage in ("volume", "correction"):
            name = "volume.zarr" if stage == "volume" else "corrected.zarr"
            g = open_store(out / name, stage if stage == "volume" else "corrected")
            r["per_slice_s"] = round(r["wall_s"] / len(g.attrs["frame_ids"]), 3)
        rows.append(r)
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
