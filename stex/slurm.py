"""How a SLURM run learns that its jobs have ended, on clusters with and without job accounting.

snakemake-executor-plugin-slurm asks ``sacct`` whenever the program exists. On a cluster without
accounting (``AccountingStorageType=accounting_storage/none``, as many small clusters run) the
program exists but every call fails ("Slurm accounting storage is disabled"); the plugin logs
the failure at debug level and never hears of its jobs again, so the run waits for ever.
``squeue --states=all`` works there, but only for ``MinJobAge`` seconds after a job ends (the
controller forgets it then), and the plugin itself goes back to ``sacct`` when ``MinJobAge`` is
below three times its first wait (``init-seconds-before-status-checks``).

The workflow (workflow/rules/hooks.smk) asks once at the start which command answers
(:func:`choose_status_command`), and counts the plugin's failed queries while it runs
(:class:`StatusFailures`): a status command that keeps failing ends the run with its error
instead of a silent wait. Nothing here imports Snakemake or the plugin.
"""
from __future__ import annotations

import shlex
import subprocess

# The plugin's longest wait between two status checks (it adds 10 s after each check that sees no
# job end, up to this): squeue must still list a job this long after it ended.
PLUGIN_MAX_CHECK_INTERVAL_S = 180


class SlurmStatusError(RuntimeError):
    """The cluster cannot tell this run when its jobs end."""


def command_error(command: str, timeout_s: float = 60) -> str | None:
    """Run ``command`` (a shell-quoted string, no shell); None when it exits 0, else what it
    printed on stderr (or how it failed) in one line."""
    try:
        run = subprocess.run(shlex.split(command), capture_output=True, text=True, timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as e:
        return str(e)
    if run.returncode == 0:
        return None
    return " ".join((run.stderr or run.stdout).split()) or f"exit status {run.returncode}"


def parse_min_job_age(scontrol_config: str) -> int | None:
    """``MinJobAge`` in seconds from ``scontrol show config`` output (``MinJobAge = 300 sec``),
    None when it is not there."""
    for line in scontrol_config.splitlines():
        key, _, value = line.partition("=")
        if key.strip() == "MinJobAge":
            number = value.split()[0] if value.split() else ""
            return int(number) if number.isdigit() else None
    return None


def min_job_age_s() -> int | None:
    """The controller's ``MinJobAge`` (s), or None when ``scontrol`` does not answer."""
    try:
        run = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return parse_min_job_age(run.stdout) if run.returncode == 0 else None


def squeue_needs_min_job_age_s(init_seconds: int) -> int:
    """The ``MinJobAge`` (s) below which squeue cannot follow a run whose first status check
    comes ``init_seconds`` after a submission: the plugin's own threshold (3 x that) and its
    longest wait between checks."""
    return max(3 * init_seconds, PLUGIN_MAX_CHECK_INTERVAL_S)


def choose_status_command(wanted: str, sacct_error: str | None, min_job_age: int | None,
                          init_seconds: int) -> str:
    """The status command (``"sacct"`` or ``"squeue"``) that follows this cluster's jobs.

    ``wanted`` is the plugin's setting, ``sacct_error`` what a ``sacct`` query printed when it
    failed (None: accounting answers), ``min_job_age`` the controller's ``MinJobAge`` (s, None if
    unknown), ``init_seconds`` the plugin's wait before its first check. Keeps ``wanted`` where it
    works; without accounting, squeue where ``MinJobAge`` allows it, else SlurmStatusError
    saying what to change."""
    need = squeue_needs_min_job_age_s(init_seconds)
    squeue_works = min_job_age is not None and min_job_age >= need
    if sacct_error is None:
        return wanted if wanted == "sacct" or squeue_works else "sacct"
    if squeue_works:
        return "squeue"
    age = "unknown (scontrol show config does not answer)" if min_job_age is None else f"{min_job_age} s"
    raise SlurmStatusError(
        f"this cluster has no job accounting (sacct: {sacct_error}), and squeue forgets a finished "
        f"job after MinJobAge = {age}, less than the {need} s the slurm plugin may wait between "
        f"two status checks, so the run could not see its jobs end. Ask the administrators for "
        f"job accounting (slurmdbd) or MinJobAge >= {need} in slurm.conf (docs/cluster.md)")


class StatusFailures:
    """Consecutive failures of the status queries of one run: :meth:`failed` raises
    SlurmStatusError once they have gone on for ``limit_s`` seconds, :meth:`answered` starts
    the count afresh. A controller that restarts answers again within that time."""

    def __init__(self, limit_s: float):
        if limit_s <= 0:
            raise ValueError(f"the time status queries may fail must be > 0 s, got {limit_s}")
        self.limit_s = limit_s
        self.first_failure = None
        self.count = 0

    def answered(self) -> None:
        self.first_failure, self.count = None, 0

    def failed(self, now: float, command: str, error: str) -> None:
        """Record a failed query at time ``now`` (s, monotonic)."""
        if self.first_failure is None:
            self.first_failure = now
        self.count += 1
        if now - self.first_failure >= self.limit_s:
            words = shlex.split(command)
            name = words[words.index("--name") + 1] if "--name" in words[:-1] else None
            jobs = (f"`squeue --name {name}` lists them, `scancel --name {name}` ends them" if name
                    else "squeue lists them")
            raise SlurmStatusError(
                f"the job status command has failed {self.count} times over "
                f"{now - self.first_failure:.0f} s ({command}: {error}); stopping instead of "
                f"waiting for jobs whose end cannot be seen. Jobs of this run may still be queued "
                f"or running: {jobs}")
