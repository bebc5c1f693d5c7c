# Local runs schedule without Snakemake's job rate limiter (--max-jobs-per-timespan, default
# 100/1s). With it, every scheduling round that leaves a ready job waiting for a core starts a
# timer for another round 1 s later, and every finished job starts a round of its own: the
# rounds multiply with the jobs finished while others wait (snakemake 9.27; upstream PR 3744).
# Four tiny scenes over 2 cores (117 jobs): 14,499 rounds and 71 s of the snakemake process's CPU
# in a 278 s run, against 115 rounds, 18 s and 235 s without (docs/datasets.md, "Scheduling";
# benchmarks/bench_scheduling.py). Locally a new job can only start when one
# ends, and each end starts a round, so the limiter has nothing to do there; a cluster run
# (the slurm profile) keeps it to pace its submissions. Included by ../../Snakefile and
# ../dataset.smk; Snakemake runs the onstart of the top-level workflow only.
onstart:
    _scheduler = getattr(workflow, "scheduler", None)  # set just before onstart (snakemake >= 8)
    if getattr(workflow, "local_exec", False) and getattr(_scheduler, "job_rate_limiter", None) is not None:
        _scheduler.job_rate_limiter = None
