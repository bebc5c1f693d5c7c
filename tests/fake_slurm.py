"""A stand-in for a SLURM cluster on this one machine, to run the workflow's slurm profile
through the real ``snakemake-executor-plugin-slurm`` in a test.

``install(bin_dir, state_dir)`` writes executables that the plugin calls:

- ``sbatch``: records its arguments (one JSON list per line in ``state_dir/sbatch.log``), prints
  a job id and runs the ``--wrap`` command in the background, in ``-D``, with its output in
  ``--output`` and its CPU affinity cut to ``--cpus-per-task`` CPUs (as a cgroup would);
- ``sacct``: every job's state (``RUNNING`` until its command ends, then ``COMPLETED`` or
  ``FAILED``), as ``sacct --parsable2 --format=JobIdRaw,State`` prints them; after
  ``$FAKE_SLURM_SACCT_ANSWERS`` calls (when set) it fails as on a cluster without accounting;
- ``srun``: runs its command (options dropped);
- ``sinfo``, ``scontrol``, ``sacctmgr``, ``sshare``: know nothing (no partitions, no
  configuration, no accounts to check a given account against).

Returns the environment to run snakemake in (``PATH`` first through ``bin_dir``).
"""
from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path

SBATCH = r'''#!{python}
import json, os, shlex, subprocess, sys

state = os.environ["FAKE_SLURM_STATE"]
args = sys.argv[1:]
log = os.path.join(state, "sbatch.log")
with open(log, "a") as f:
    f.write(json.dumps(args) + "\n")
with open(log) as f:
    jobid = str(1000 + sum(1 for _ in f))


def value(name):
    for i, a in enumerate(args):
        if a.startswith(name + "="):
            return a[len(name) + 1:]
        if a == name and i + 1 < len(args):
            return args[i + 1]
    return None


wrap = value("--wrap")
out = value("--output").replace("%j", jobid)
os.makedirs(os.path.dirname(out), exist_ok=True)
available = sorted(os.sched_getaffinity(0))
# CPUs handed out in turn from the job id on, as a cluster gives jobs running side by side
# different CPUs (all from the first, two one-CPU jobs would share one core)
cpus = sorted({available[(int(jobid) + i) % len(available)] for i in range(int(value("--cpus-per-task") or 1))})
jobs = os.path.join(state, "jobs")
with open(jobs, "a") as f:
    f.write(jobid + "|RUNNING\n")
pin = "import os, sys; os.sched_setaffinity(0, %r); os.execvp('sh', ['sh', '-c', sys.argv[1]])" % (cpus,)
run = (shlex.join([sys.executable, "-c", pin, wrap]) + " > " + shlex.quote(out) + " 2>&1; "
       "if [ $? -eq 0 ]; then s=COMPLETED; else s=FAILED; fi; "
       "echo " + jobid + "'|'$s >> " + shlex.quote(jobs))
env = dict(os.environ, SLURM_JOB_ID=jobid, SLURM_CPUS_PER_TASK=str(len(cpus)))
subprocess.Popen(["/bin/sh", "-c", run], cwd=value("-D") or os.getcwd(), env=env,
                 start_new_session=True, stdin=subprocess.DEVNULL,
                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
print(jobid)
'''

SACCT = r'''#!{python}
import os, sys

state = os.environ["FAKE_SLURM_STATE"]
with open(os.path.join(state, "sacct.calls"), "a+") as f:
    f.write("x")
    f.seek(0)
    calls = len(f.read())
if calls > int(os.environ.get("FAKE_SLURM_SACCT_ANSWERS", "1000000")):
    sys.exit("Slurm accounting storage is disabled")
states = {}
path = os.path.join(state, "jobs")
if os.path.exists(path):
    with open(path) as f:
        for line in f:
            jobid, state = line.strip().split("|")
            states[jobid] = state
for jobid, state in states.items():
    print(jobid + "|" + state)
'''

SRUN = r'''#!/bin/sh
while [ $# -gt 0 ]; do
  case "$1" in -*) shift ;; *) break ;; esac
done
exec "$@"
'''

NOTHING = "#!/bin/sh\nexit 0\n"


def install(bin_dir: Path, state_dir: Path) -> dict:
    bin_dir.mkdir(parents=True, exist_ok=True)
    state_dir.mkdir(parents=True, exist_ok=True)
    scripts = {"sbatch": SBATCH.replace("{python}", sys.executable),
               "sacct": SACCT.replace("{python}", sys.executable), "srun": SRUN,
               "sinfo": NOTHING, "scontrol": NOTHING, "sacctmgr": NOTHING, "sshare": NOTHING}
    for name, text in scripts.items():
        path = bin_dir / name
        path.write_text(text)
        path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
                FAKE_SLURM_STATE=str(state_dir))


def submissions(state_dir: Path) -> list[list[str]]:
    """The argument lists sbatch was called with, in order."""
    log = state_dir / "sbatch.log"
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


def run_snakemake_polling_every(seconds: float) -> None:
    """Run snakemake's command line (``sys.argv``) with the remote executors' status checks at
    most ``seconds`` apart. The slurm plugin adds 10 s to its interval at every check that finds
    no job finished (a real cluster's accounting is slow to ask); the stand-in's ``sacct`` is
    instant, and jobs of a few seconds would otherwise wait tens of seconds each to be seen."""
    from snakemake.cli import main
    from snakemake_interface_executor_plugins.executors import remote

    interval = remote.RemoteExecutor.next_seconds_between_status_checks
    remote.RemoteExecutor.next_seconds_between_status_checks = interval.setter(
        lambda self, value: interval.fset(self, min(value, seconds)))
    main()


if __name__ == "__main__":  # python fake_slurm.py SNAKEMAKE-ARGS...
    run_snakemake_polling_every(2.0)
