"""The README's SLURM command on a real one-node cluster, without and with job accounting.

Starts the cluster of tests/real_slurm.py (Debian's slurm-wlm and munge; slurmdbd + MariaDB for
accounting; as root, config in /etc/slurm, removed afterwards), runs

    snakemake --workflow-profile workflow/profiles/slurm --configfile tiny.yaml
      --default-resources mem_mb=1000 runtime=10 slurm_account=stexci slurm_partition=debug

on the tiny scene (tests' tiny_workflow_config: every stage, one frame block) from empty results,
with the profile as shipped (the plugin's first status check 40 s after a submission; ``--init
2`` for 2 s), and prints per way the wall time, the jobs submitted, the status command used and
the jobs as sacct or squeue list them. ``--until`` stops at a store (e.g. projection.zarr).

    python benchmarks/bench_slurm.py [--ways no-accounting accounting] [--init 40] [--until STORE] [--work DIR]
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
from conftest import tiny_workflow_config  # noqa: E402
from real_slurm import ACCOUNT, PARTITION, Cluster, unavailable  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ways", nargs="+", default=["no-accounting", "accounting"], choices=["no-accounting", "accounting"])
    ap.add_argument("--init", type=int, default=None, help="--slurm-init-seconds-before-status-checks (default: the plugin's)")
    ap.add_argument("--until", default=None, help="a store of results/tiny to stop at (default: the whole workflow)")
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    base = args.work or Path(tempfile.mkdtemp(prefix="bench_slurm_"))
    for way in args.ways:
        accounting = way == "accounting"
        reason = unavailable(accounting)
        if reason:
            sys.exit(f"{way}: {reason}")
        work = base / way
        work.mkdir(parents=True)
        (work / "tiny.yaml").write_text(yaml.safe_dump(tiny_workflow_config(work / "results")))
        cmd = ["snakemake", "--workflow-profile", str(REPO / "workflow" / "profiles" / "slurm"),
               "--snakefile", str(REPO / "Snakefile"), "--directory", str(work),
               "--configfile", str(work / "tiny.yaml"), "--default-resources", "mem_mb=1000", "runtime=10",
               f"slurm_account={ACCOUNT}", f"slurm_partition={PARTITION}"]
        if args.init is not None:
            cmd += ["--slurm-init-seconds-before-status-checks", str(args.init)]
        if args.until:
            cmd.append(str(work / "results" / "tiny" / args.until))
        cluster = Cluster(work / "slurm").start(accounting=accounting)
        try:
            start = time.monotonic()
            run = subprocess.run(cmd, capture_output=True, text=True)
            seconds = time.monotonic() - start
            jobs = cluster.jobs()
        finally:
            cluster.stop()
        log = run.stdout + run.stderr
        (work / "snakemake.log").write_text(log)
        chosen = re.search(r"stex: job status from (\w+)", log)
        submitted = len(re.findall(r"has been submitted with SLURM jobid", log))
        steps = re.findall(r"(\d+) of (\d+) steps", log)
        print(f"{way}: exit {run.returncode}, {seconds:.0f} s, {submitted} jobs submitted, "
              f"{steps[-1][0] + ' of ' + steps[-1][1] if steps else 'no'} steps done, status from "
              f"{chosen[1] if chosen else 'sacct (the plugin default)'}; log {work / 'snakemake.log'}")
        states = {}
        for job in jobs:
            states[job["state"]] = states.get(job["state"], 0) + 1
        print(f"  {'sacct' if accounting else 'squeue --states=all'}: {len(jobs)} jobs, {states}")
        for job in sorted(jobs, key=lambda j: int(j["id"])):
            print(f"    {job['id']:>4} {job['comment']:<45} {job['state']}")


if __name__ == "__main__":
    main()
