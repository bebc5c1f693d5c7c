# Local runs schedule without Snakemake's job rate limiter (--max-jobs-per-timespan, default
# 100/1s). With it, every scheduling round that leaves a ready job waiting for a core starts a
# timer for another round a timespan later, and every finished job starts a round of its own, so
# the rounds multiply with the jobs that finish while others wait. Locally a new job can only
# start when one ends, and each end starts a round, so the limiter has nothing to do there; a
# cluster run (the slurm profile) keeps it to pace its submissions. Snakemake has no supported
# setting that turns the limiter off (every --max-jobs-per-timespan value builds one, and a
# timespan long enough to be harmless leaves timer threads that keep the process alive), so this
# sets the scheduler's attribute; tests/test_scheduling.py fails when Snakemake changes what it
# relies on. Why and what it was measured to cost: docs/decisions/scheduling.md. Included by
# ../../Snakefile and ../dataset.smk; called from the onstart in hooks.smk (Snakemake runs the
# onstart of the top-level workflow only, and one of them).


def local_scheduling_without_rate_limiter():
    _scheduler = getattr(workflow, "scheduler", None)  # set just before onstart (snakemake >= 8)
    if getattr(workflow, "local_exec", False) and getattr(_scheduler, "job_rate_limiter", None) is not None:
        _scheduler.job_rate_limiter = None
