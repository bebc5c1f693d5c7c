"""The README's SLURM command on a real one-node cluster (tests/real_slurm.py: Debian's slurm-wlm
and munge, started here as root), once without job accounting and once with slurmdbd + MariaDB.

Without accounting ``sacct`` exists but fails, and the slurm plugin, which asks it whenever it
exists, used to wait for ever for jobs that had long ended; workflow/rules/hooks.smk finds that
out at the start and has the plugin ask ``squeue`` (stex.slurm). The jobs the cluster saw
(sacct's or squeue's list) are printed at the end of the test run (tests/conftest.py).

The tiny scene up to the projection (six jobs); the plugin's first status check 2 s after a
submission instead of 40, so that the test waits less for jobs of a few seconds."""
import re
import subprocess
import time

import pytest
import yaml

from conftest import REPO, tiny_workflow_config
from real_slurm import ACCOUNT, PARTITION, Cluster, unavailable
from stex.io import open_store

pytest.importorskip("snakemake_executor_plugin_slurm")

RULES = ["ingest_scene", "ingest_block", "masks", "template", "tracking", "projection"]


@pytest.fixture(scope="module", params=[False, True], ids=["no-accounting", "accounting"])
def cluster(request, tmp_path_factory):
    reason = unavailable(accounting=request.param)
    if reason:
        pytest.skip(f"no real SLURM cluster here: {reason}")
    cluster = Cluster(tmp_path_factory.mktemp("slurm")).start(accounting=request.param)
    yield cluster
    cluster.stop()


def readme_slurm_command(work, *targets):
    """The README's SLURM command (its profile, and on the command line the profile's memory and
    time with an account and a partition), for the tiny scene in ``work``."""
    (work / "tiny.yaml").write_text(yaml.safe_dump(tiny_workflow_config(work / "results")))
    return ["snakemake", "--workflow-profile", str(REPO / "workflow" / "profiles" / "slurm"),
            "--snakefile", str(REPO / "Snakefile"), "--directory", str(work),
            "--configfile", str(work / "tiny.yaml"),
            "--default-resources", "mem_mb=1000", "runtime=10", f"slurm_account={ACCOUNT}",
            f"slurm_partition={PARTITION}",
            "--slurm-init-seconds-before-status-checks", "2", *targets]


def test_the_readme_slurm_command_runs_the_workflow(cluster, tmp_path, record_property):
    res = tmp_path / "results" / "tiny"
    start = time.monotonic()
    run = subprocess.run(readme_slurm_command(tmp_path, str(res / "projection.zarr")),
                         capture_output=True, text=True, timeout=900)
    seconds = time.monotonic() - start
    log = run.stdout + run.stderr
    assert run.returncode == 0, log[-4000:]
    if cluster.accounting:
        assert "job status from" not in log  # sacct answers: the plugin's own choice stands
    else:
        assert "stex: job status from squeue, not sacct (sacct: Slurm accounting storage is disabled)" in log, log[-4000:]

    submitted = dict(re.findall(r"has been submitted with SLURM jobid (\d+) \(log: \S*/rule_(\w+?)[/.]", log))
    jobs = {job["id"]: job for job in cluster.jobs()}
    table = "\n".join(f"  {job['id']:>4}  {job['comment']:<40} {job['state']}"
                      for job in sorted(jobs.values(), key=lambda j: int(j["id"])))
    kind = "with accounting: sacct" if cluster.accounting else "without accounting: squeue --states=all"
    record_property("summary", f"real SLURM, {kind} lists {len(jobs)} jobs of the README's SLURM command "
                               f"({seconds:.0f} s, {len(submitted)} submitted):\n{table}")
    assert sorted(submitted.values()) == sorted(RULES), submitted
    for jobid, rule in submitted.items():
        assert jobs[jobid]["state"] == "COMPLETED", (rule, jobs.get(jobid))
        assert jobs[jobid]["comment"].startswith(f"rule_{rule}"), jobs[jobid]
    assert open_store(res / "projection.zarr", "projection")["phi"].shape[0] == 6
    assert not (res / ".stex-run.lock").exists()


@pytest.mark.parametrize("cluster", [False], ids=["no-accounting"], indirect=True)
def test_a_cluster_that_cannot_see_its_jobs_end_is_an_error_at_the_start(cluster, tmp_path):
    """No accounting and a controller that forgets ended jobs after 60 s, before the plugin's
    next check may come: the run stops at once saying so, before it submits anything."""
    cluster.reconfigure(min_job_age_s=60)
    try:
        start = time.monotonic()
        run = subprocess.run(readme_slurm_command(tmp_path), capture_output=True, text=True, timeout=300)
        seconds = time.monotonic() - start
    finally:
        cluster.reconfigure(min_job_age_s=300)
    log = run.stdout + run.stderr
    assert run.returncode != 0
    assert "this cluster has no job accounting (sacct: Slurm accounting storage is disabled)" in log, log[-4000:]
    assert "MinJobAge = 60 s, less than the 180 s" in log and "MinJobAge >= 180" in log, log[-4000:]
    assert "has been submitted" not in log
    assert seconds < 60, seconds
