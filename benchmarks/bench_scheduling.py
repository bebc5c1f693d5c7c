"""Benchmark the snakemake process's own work in a dataset run, with and without the job rate limiter.

Runs ``workflow/dataset.smk`` over ``--scenes`` tiny synthetic scenes (the tiny scene of the
tests, ``--frames`` frames each, given meshes, 2 cores) from empty results, ``--runs`` times
each way, alternating:

- **limiter off**: the workflow as shipped (``workflow/rules/scheduling.smk`` turns Snakemake's
  job rate limiter off in its ``onstart``);
- **limiter on**: the same with ``--no-hooks``, which skips that ``onstart``: Snakemake's own
  scheduling (the workflow's other hooks, the results folder's run lock and a SLURM run's
  status checks, workflow/rules/hooks.smk, do not touch the scheduling).

Reports per run the scheduling rounds (``--verbose``'s "Resources before job selection" lines),
the jobs finished, the CPU time of the snakemake process itself (user + system, from
/proc/<pid>/stat sampled every 0.2 s, not its jobs'), its most threads, and the wall time; then
the medians of each way.

    python benchmarks/bench_scheduling.py [--runs 3] [--scenes 4] [--frames 12] [--work /tmp/bench_scheduling]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
TINY_SYNTHETIC = yaml.safe_load((REPO / "tests" / "tiny_synthetic.yaml").read_text())  # the tests' tiny scene

COMMON = {"frame_block": 6, "template": {"atlas_size": 256}, "tracking": {"mode": "given"},
          "texcoords": {"levels": 2, "iterations": 10, "refine_iterations": 10}, "sampling_table": {"steps": []}}


def write_dataset(work: Path, n_scenes: int, n_frames: int) -> Path:
    """Scene files s0..s{n-1} (seeds 0..n-1) and the dataset file in ``work``; returns the latter."""
    files = []
    for i in range(n_scenes):
        path = work / f"s{i}.yaml"
        path.write_text(yaml.safe_dump({"scene": f"s{i}", "source": {
            "kind": "synthetic", "synthetic": {**TINY_SYNTHETIC, "n_frames": n_frames, "seed": i}}}))
        files.append(str(path))
    (work / "config").mkdir(exist_ok=True)
    # the scenes' wall stands at 2.2 m (tests/test_dataset.py)
    (work / "config" / "config.yaml").write_text(yaml.safe_dump({"masks": {"depth_far_m": 1.8}}))
    dataset = work / "dataset.yaml"
    dataset.write_text(yaml.safe_dump({"scene_files": files, "common": {**COMMON, "results": str(work / "results")}}))
    return dataset


def _cpu_seconds(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def run_once(work: Path, dataset: Path, limiter: bool) -> dict:
    """One dataset run from empty results; its rounds, jobs, snakemake CPU, threads and wall time."""
    shutil.rmtree(work / "results", ignore_errors=True)
    shutil.rmtree(work / ".snakemake", ignore_errors=True)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "workflow" / "dataset.smk"),
           "--directory", str(work), "--configfile", str(dataset), "--cores", "2", "--verbose"]
    if limiter:
        cmd.append("--no-hooks")
    log = work / f"log_{'on' if limiter else 'off'}.txt"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
        cpu, threads = 0.0, 0
        while proc.poll() is None:
            cpu = _cpu_seconds(proc.pid) or cpu
            try:
                threads = max(threads, len(os.listdir(f"/proc/{proc.pid}/task")))
            except OSError:
                pass
            time.sleep(0.2)
    wall = time.perf_counter() - t0
    text = log.read_text()
    if proc.returncode != 0:
        raise RuntimeError(f"dataset run failed (exit {proc.returncode}); see {log}:\n{text[-2000:]}")
    return {"rounds": text.count("Resources before job selection"),
            "jobs": len(re.findall(r"^Finished jobid", text, flags=re.M)),
            "cpu_s": cpu, "threads": threads, "wall_s": wall}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_scheduling"))
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    dataset = write_dataset(args.work, args.scenes, args.frames)
    results = {"off": [], "on": []}
    for i in range(args.runs):
        for way in ("on", "off"):
            r = run_once(args.work, dataset, limiter=way == "on")
            results[way].append(r)
            print(f"run {i + 1} limiter {way:>3s}: {r['rounds']:6d} rounds, {r['jobs']} jobs, "
                  f"snakemake CPU {r['cpu_s']:6.1f} s, {r['threads']:3d} threads at most, wall {r['wall_s']:6.1f} s",
                  flush=True)
    for way in ("on", "off"):
        rs = results[way]
        med = {k: float(np.median([r[k] for r in rs])) for k in ("rounds", "cpu_s", "threads", "wall_s")}
        print(f"median limiter {way:>3s} (n={len(rs)}): {med['rounds']:.0f} rounds, snakemake CPU "
              f"{med['cpu_s']:.1f} s, {med['threads']:.0f} threads at most, wall {med['wall_s']:.1f} s")


if __name__ == "__main__":
    main()
