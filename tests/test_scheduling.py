"""What workflow/rules/scheduling.smk relies on in Snakemake, pinned: it turns the job rate
limiter off by setting a scheduler attribute that Snakemake does not document, because no
supported setting turns it off (docs/decisions/scheduling.md). These fail when a Snakemake
release changes any of it: then look for a supported setting again, or update the patch."""
import inspect
import re

import pytest
import snakemake.api  # noqa: F401  (imports snakemake's modules in the order they need)
from snakemake.scheduling import job_scheduler
from snakemake.settings.types import MaxJobsPerTimespan, SchedulingSettings
from snakemake.workflow import Workflow

from conftest import REPO


def test_the_patch_sets_the_attribute_these_tests_pin():
    text = (REPO / "workflow" / "rules" / "scheduling.smk").read_text()
    # the workflow's one onstart (workflow/rules/hooks.smk) calls it
    hooks = (REPO / "workflow" / "rules" / "hooks.smk").read_text()
    assert re.search(r"^onstart:\n    local_scheduling_without_rate_limiter\(\)$", hooks, flags=re.M)
    assert "def local_scheduling_without_rate_limiter():" in text
    assert '_scheduler = getattr(workflow, "scheduler", None)' in text
    assert 'getattr(workflow, "local_exec", False)' in text
    assert "_scheduler.job_rate_limiter = None" in text


def test_the_scheduler_keeps_its_limiter_in_job_rate_limiter_and_none_means_no_limit():
    init = inspect.getsource(job_scheduler.JobScheduler.__init__)
    assert re.search(r"self\.job_rate_limiter = \(\s*JobRateLimiter\(", init), "the limiter is no longer built in __init__"
    # the job selection: no limiter, no job count limit
    select = inspect.getsource(job_scheduler.JobScheduler.job_selector)
    assert "if self.job_rate_limiter is None:" in select
    # the scheduling loop: the re-evaluation timer only with a limiter
    loop = inspect.getsource(job_scheduler.JobScheduler.schedule)
    assert re.search(r"if self\.job_rate_limiter is not None:\s*\n[^\n]*\n[^\n]*\n\s*self\._schedule_reevalutation\(",
                     loop), "the re-evaluation timer no longer depends on the limiter alone"
    # the limiter is read nowhere else, so None is all it takes
    source = inspect.getsource(job_scheduler)
    assert source.count("job_rate_limiter") == 6, "the scheduler uses job_rate_limiter in a new place"


def test_the_workflow_has_its_scheduler_and_local_exec_when_onstart_runs():
    assert isinstance(inspect.getattr_static(Workflow, "scheduler"), property)
    assert isinstance(inspect.getattr_static(Workflow, "local_exec"), property)
    execute = inspect.getsource(Workflow.execute)
    assert execute.index("self.scheduler = JobScheduler(") < execute.index("self._onstart("), \
        "onstart now runs before the scheduler exists: the patch would find none"


def test_no_value_of_the_option_turns_the_limiter_off():
    """If Snakemake learns to say "no limit" (a value, or a limiter that is falsy), use that in
    workflow/profiles/default/config.yaml instead of the patch."""
    with pytest.raises(Exception):
        MaxJobsPerTimespan.parse_choice("none")
    zero = MaxJobsPerTimespan.parse_choice("0/1s")
    assert zero and zero.max_jobs == 0  # a limiter that lets no job start, not no limiter
    assert bool(MaxJobsPerTimespan.parse_choice("1000000/1d"))
    settings = SchedulingSettings(max_jobs_per_second=5)
    assert settings.max_jobs_per_timespan.max_jobs == 5  # the deprecated option builds the same limiter
