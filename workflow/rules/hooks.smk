# The run's hooks: one writer per results folder (stex.runlock), the status checks of a SLURM run
# (stex.slurm), and local scheduling without the job rate limiter (scheduling.smk). Snakemake runs
# the onstart, onsuccess and onerror of the top-level workflow only, and one of each: included by
# ../../Snakefile and ../dataset.smk, each of which first sets LOCKED_RESULTS, the results
# folders its run writes. Dry runs (-n) and --no-hooks runs (the cluster's jobs) skip the hooks,
# so they neither take nor need the lock.
import asyncio
import atexit
import glob
import os
import sys
import time

from snakemake_interface_executor_plugins.settings import ExecMode

from stex.runlock import acquire, is_stale, read_holder, release
from stex.slurm import StatusFailures, choose_status_command, command_error, min_job_age_s

# How long (s) the slurm status queries may fail in a row before the run stops with their error; a
# controller that restarts answers again well within it. Retried every SLURM_STATUS_RETRY_S.
SLURM_STATUS_FAILURE_LIMIT_S = float(os.environ.get("STEX_SLURM_STATUS_FAILURE_LIMIT_S", 300))
SLURM_STATUS_RETRY_S = min(10.0, SLURM_STATUS_FAILURE_LIMIT_S / 3)


def forget_stale_snakemake_locks(folders):
    """A run killed (kill -9, a lost login node) leaves its stex lock and, in its working
    directory's .snakemake/locks, Snakemake's locks of the files it was writing; Snakemake would
    refuse to start until --unlock. When a folder's stex lock is stale (its run on this host has
    ended) and that run worked in this directory, the Snakemake locks naming files in the folder
    are that run's (no other run may write the folder), and are removed, so that running the
    same command again resumes. Snakemake checks its locks after reading the workflow, so this
    runs while the workflow is read."""
    stale = {}
    for folder in folders:
        try:
            holder = read_holder(folder)
        except ValueError:
            continue
        if holder is not None and is_stale(holder) and holder.cwd == os.getcwd():
            stale[os.path.abspath(folder) + os.sep] = holder
    if not stale:
        return
    removed = 0
    for path in glob.glob(os.path.join(".snakemake", "locks", "*.lock")):
        with open(path) as f:
            names = [os.path.abspath(line.strip()) for line in f if line.strip()]
        if any(name.startswith(folder) for name in names for folder in stale):
            os.remove(path)
            removed += 1
    for folder, holder in stale.items():
        print(
            f"stex: the run that wrote {folder.rstrip(os.sep)} ({holder.describe()}) ended without "
            f"finishing; removed {removed} Snakemake lock file(s) it left here, and this run "
            f"redoes its incomplete jobs",
            file=sys.stderr,
        )


def follow_slurm_jobs():
    """Make the slurm plugin's status checks see this cluster's jobs end, or fail loudly."""
    import snakemake_executor_plugin_slurm as plugin
    from snakemake_executor_plugin_slurm.job_status_query import query_job_status_sacct

    settings = workflow.executor_settings
    # the plugin's own sacct query (a name no job has), so that the probe fails as its checks would
    sacct_error = command_error(query_job_status_sacct("stex-accounting-probe"))
    chosen = choose_status_command(
        settings.status_command, sacct_error, min_job_age_s(), settings.init_seconds_before_status_checks
    )
    if chosen != settings.status_command:
        why = f"sacct: {sacct_error}" if sacct_error else "squeue forgets finished jobs too soon here"
        print(f"stex: job status from {chosen}, not {settings.status_command} ({why})", file=sys.stderr)
        settings.status_command = chosen
    original = getattr(plugin, "query_job_status", None)
    if original is None:
        print(
            "stex: this snakemake-executor-plugin-slurm has no query_job_status: status queries "
            "that keep failing are not caught (docs/cluster.md)",
            file=sys.stderr,
        )
        return
    if getattr(original, "stex_failures", None) is not None:
        return
    failures = StatusFailures(SLURM_STATUS_FAILURE_LIMIT_S)

    async def query_job_status(command, logger):
        # the plugin drops the jobs of a check whose queries all fail and never asks for them
        # again; retrying here until an answer keeps them, and a limit turns a lasting failure
        # into the run's error
        while True:
            status, seconds = await original(command, logger)
            if status is not None:
                failures.answered()
                return status, seconds
            error = await asyncio.to_thread(command_error, command)
            failures.failed(time.monotonic(), command, error or "no answer")
            await asyncio.sleep(SLURM_STATUS_RETRY_S)

    query_job_status.stex_failures = failures
    plugin.query_job_status = query_job_status


if workflow.modifier.is_main_snakefile() and workflow.exec_mode == ExecMode.DEFAULT:
    forget_stale_snakemake_locks(LOCKED_RESULTS)


onstart:
    local_scheduling_without_rate_limiter()
    acquire(LOCKED_RESULTS)
    atexit.register(release, list(LOCKED_RESULTS))  # also when the run ends by an exception
    if workflow.executor_plugin is not None and workflow.executor_plugin.name == "slurm":
        follow_slurm_jobs()


onsuccess:
    release(LOCKED_RESULTS)


onerror:
    release(LOCKED_RESULTS)
