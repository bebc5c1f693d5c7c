"""The workflow's SLURM profile, run through the real snakemake-executor-plugin-slurm against a
stand-in cluster on this machine (tests/fake_slurm.py): the jobs are submitted with their
rule's threads as CPUs, the profile's memory and time, and they produce the stores."""
import re
import subprocess
import sys

import pytest
import yaml

from conftest import REPO, TINY_SYNTHETIC
from stex.io import open_store

pytest.importorskip("snakemake_executor_plugin_slurm")

import fake_slurm  # noqa: E402


def rule_threads_and_runtime():
    """threads declared by each rule of the workflow (1 where none is declared), and the wall time
    (minutes) of the rules that declare one (``runtime=SEQUENCE_RUNTIME_MIN``)."""
    rules = REPO / "workflow" / "rules"
    sequence_minutes = int(re.search(r"^SEQUENCE_RUNTIME_MIN = (\d+)$", (rules / "common.smk").read_text(), re.M)[1])
    threads, runtime = {}, {}
    for smk in rules.glob("*.smk"):
        for block in re.split(r"^\s*rule ", smk.read_text(), flags=re.M)[1:]:
            name = block.split(":", 1)[0].strip()
            m = re.search(r"^\s+threads:\s*(\d+)", block, flags=re.M)
            threads[name] = int(m.group(1)) if m else 1
            if re.search(r"^\s+runtime=SEQUENCE_RUNTIME_MIN,", block, flags=re.M):
                runtime[name] = sequence_minutes
    return threads, runtime


def stand_in_run(tmp_path, *targets):
    """The tiny scene in ``tmp_path``/wf and snakemake's command line with the slurm profile on the
    stand-in cluster (installed in ``tmp_path``), building ``targets`` (paths relative to its
    results/tiny). Returns (command, environment, results/tiny, the profile's settings)."""
    work = tmp_path / "wf"
    work.mkdir()
    # one frame block and the jobs up to the poses (two threads, after the sequence-long tracking):
    # each job is a snakemake of its own on the stand-in nodes, so the job count is the test's time
    cfg = {"scene": "tiny", "results": str(work / "results"), "frame_block": 6,
           "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC},
           "template": {"atlas_size": 256}, "tracking": {"mode": "given"}}
    (work / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    env = fake_slurm.install(tmp_path / "bin", tmp_path / "slurm")
    res = work / "results" / "tiny"
    profile = REPO / "workflow" / "profiles" / "slurm"
    settings = yaml.safe_load((profile / "config.yaml").read_text())
    defaults = settings["default-resources"]
    # snakemake's command line, its slurm status checks at most 2 s apart (fake_slurm's __main__)
    cmd = [sys.executable, fake_slurm.__file__, *[str(res / t) for t in targets],
           "--snakefile", str(REPO / "Snakefile"),
           "--workflow-profile", str(profile),
           "--directory", str(work), "--configfile", str(work / "tiny.yaml"),
           "--slurm-init-seconds-before-status-checks", "1",
           # account and partition as the profile and the README say: a command-line
           # --default-resources replaces the profile's list, so its values are repeated
           "--default-resources", *[f"{k}={v}" for k, v in defaults.items()],
           "slurm_account=acct", "slurm_partition=part"]
    return cmd, env, res, settings


def test_slurm_profile_submits_each_rule_with_its_threads(tmp_path):
    cmd, env, res, settings = stand_in_run(tmp_path, "poses.zarr")
    defaults = settings["default-resources"]
    # per-rule resources live in the rules, so that they also hold for workflow/dataset.smk's
    # prefixed rule names, which a profile's set-resources would not reach
    assert "set-resources" not in settings
    assert "cpus_per_task" not in defaults  # it would replace every rule's threads
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-4000:]

    submitted = {}
    for args in fake_slurm.submissions(tmp_path / "slurm"):
        rule = args[args.index("--comment") + 1].removeprefix("rule_").split("_wildcards_")[0]
        cpus = [a for a in args if a.startswith("--cpus-per-task=")]
        submitted[rule] = (cpus, args[args.index("--mem") + 1], args[args.index("-t") + 1],
                           args[args.index("-A") + 1], args[args.index("-p") + 1])
    threads, runtime = rule_threads_and_runtime()
    expected = {"ingest_scene", "ingest_block", "masks", "template", "tracking", "projection", "poses"}
    assert expected <= set(submitted), submitted
    assert threads["poses"] == 2 and threads["template"] == 1
    assert runtime["tracking"] > defaults["runtime"]  # a sequence-long job
    for rule, (cpus, mem, minutes, account, partition) in submitted.items():
        assert cpus == [f"--cpus-per-task={threads[rule]}"], (rule, cpus)
        assert (int(mem), int(minutes)) == (defaults["mem_mb"], runtime.get(rule, defaults["runtime"])), rule
        assert (account, partition) == ("acct", "part"), rule
    # the jobs ran on the stand-in nodes and wrote complete stores
    assert open_store(res / "poses.zarr", "poses")["neighbours"].shape[0] == 6
    assert open_store(res / "tracking.zarr", "tracking")["vertices"].shape[0] == 6


def test_a_cluster_without_accounting_whose_squeue_cannot_follow_the_jobs_is_an_error_at_once(tmp_path):
    """sacct fails (no accounting) and the controller does not say how long squeue lists ended
    jobs (the stand-in's scontrol prints nothing): the run stops before it submits a job, instead
    of waiting for ever (workflow/rules/hooks.smk, stex.slurm)."""
    cmd, env, res, _ = stand_in_run(tmp_path, "scene.zarr")
    run = subprocess.run(cmd, env=dict(env, FAKE_SLURM_SACCT_ANSWERS="0"), capture_output=True, text=True, timeout=300)
    out = run.stdout + run.stderr
    assert run.returncode != 0
    assert ("this cluster has no job accounting (sacct: Slurm accounting storage is disabled), and squeue "
            "forgets a finished job after MinJobAge = unknown") in out, out[-4000:]
    assert fake_slurm.submissions(tmp_path / "slurm") == []
    assert not (res / ".stex-run.lock").exists()  # released as the run ended


def test_a_status_command_that_keeps_failing_ends_the_run_with_its_error(tmp_path):
    """sacct answers at the start, then fails at every status check: the run ends with that
    error once the failures have lasted STEX_SLURM_STATUS_FAILURE_LIMIT_S (4 s here), naming the
    command and how to find the run's jobs."""
    cmd, env, res, _ = stand_in_run(tmp_path, "scene.zarr")
    env = dict(env, FAKE_SLURM_SACCT_ANSWERS="1", STEX_SLURM_STATUS_FAILURE_LIMIT_S="4")
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    out = run.stdout + run.stderr
    assert run.returncode != 0
    assert len(fake_slurm.submissions(tmp_path / "slurm")) == 1
    failed = re.search(r"the job status command has failed (\d+) times over (\d+) s \(sacct .*--name (\S+): "
                       r"Slurm accounting storage is disabled\)", out)
    assert failed, out[-4000:]
    assert int(failed[1]) >= 2 and 4 <= int(failed[2]) < 60, failed[0]
    assert f"scancel --name {failed[3]}" in out


def test_what_the_hooks_rely_on_in_the_slurm_plugin():
    """workflow/rules/hooks.smk wraps the plugin's ``query_job_status`` and reads its settings;
    stex.slurm knows its longest wait between checks and its own threshold for squeue. These
    fail when a plugin release changes any of it: then update the hooks (docs/cluster.md)."""
    import inspect

    import snakemake_executor_plugin_slurm as plugin
    from snakemake_executor_plugin_slurm import job_status_query

    from stex.slurm import PLUGIN_MAX_CHECK_INTERVAL_S

    check = inspect.getsource(plugin.Executor.check_active_jobs)
    # looked up in the plugin's module at every call: the wrapper replaces it there
    assert "= await query_job_status(" in check and plugin.query_job_status is job_status_query.query_job_status
    # a failed query is (None, None), and a check whose queries all fail yields none of its jobs
    assert "return None, None" in inspect.getsource(job_status_query.query_job_status)
    assert "if status_of_jobs is None and sacct_query_duration is None:" in check
    assert f"max_sleep_time = {PLUGIN_MAX_CHECK_INTERVAL_S}" in check
    assert "dynamic_check_threshold = 3 * initial_interval" in check
    assert 'if status_command_name == "sacct":\n            status_command = query_job_status_sacct(self.run_uuid)' in check
    fields = plugin.ExecutorSettings.__dataclass_fields__
    assert {"status_command", "init_seconds_before_status_checks"} <= set(fields)
    assert "--name" in job_status_query.query_job_status_sacct("run-id").split()
