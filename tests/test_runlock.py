"""stex.runlock: one writer per results folder, stale locks taken over, others' locks left alone;
and stex.slurm's choice of the status command and its failure limit."""
import dataclasses
import json
import os
import socket
import subprocess
import sys

import pytest

from stex import runlock
from stex.runlock import LOCK_NAME, RunLocked, acquire, is_stale, read_holder, release
from stex.slurm import (SlurmStatusError, StatusFailures, choose_status_command, parse_min_job_age,
                        squeue_needs_min_job_age_s)


def write_lock(folder, **fields):
    folder.mkdir(parents=True, exist_ok=True)
    record = {**dataclasses.asdict(runlock.this_process("other run")), **fields}
    (folder / LOCK_NAME).write_text(json.dumps(record))
    return runlock.Holder(**record)


@pytest.fixture
def live_process():
    """A child process that lives while the test runs: (pid, its start in clock ticks)."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc.pid, runlock.process_start(proc.pid)
    proc.kill()
    proc.wait()


def dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_acquire_records_this_process_and_release_removes_it(tmp_path):
    folder = tmp_path / "results" / "tiny"  # created by acquire
    assert acquire([folder], command="snakemake --cores 2") == [folder / LOCK_NAME]
    holder = read_holder(folder)
    assert (holder.host, holder.pid, holder.cwd) == (socket.gethostname(), os.getpid(), os.getcwd())
    assert holder.command == "snakemake --cores 2" and holder.process_start == runlock.process_start(os.getpid())
    assert list(folder.iterdir()) == [folder / LOCK_NAME]  # no private file left behind
    assert acquire([folder]) == [folder / LOCK_NAME]  # this process holds it already
    release([folder])
    assert not (folder / LOCK_NAME).exists()


def test_a_live_holder_refuses_another_run_naming_it(tmp_path, live_process):
    pid, start = live_process
    holder = write_lock(tmp_path, pid=pid, process_start=start, cwd="/elsewhere")
    assert not is_stale(holder)
    with pytest.raises(RunLocked) as e:
        acquire([tmp_path])
    assert e.value.holder == holder
    message = str(e.value)
    assert f"{tmp_path} is being written by another stex run: pid {pid} on host {socket.gethostname()}" in message
    assert "in /elsewhere (other run)" in message and str(tmp_path / LOCK_NAME) in message
    release([tmp_path])  # not ours: left alone
    assert read_holder(tmp_path) == holder


def test_a_holder_that_has_ended_or_whose_pid_was_reused_is_stale_and_taken_over(tmp_path, live_process):
    gone = write_lock(tmp_path / "a", pid=dead_pid())
    pid, start = live_process
    reused = write_lock(tmp_path / "b", pid=pid, process_start=start - 1)  # another process had the pid
    assert is_stale(gone) and is_stale(reused)
    acquire([tmp_path / "a", tmp_path / "b"])
    assert read_holder(tmp_path / "a").pid == read_holder(tmp_path / "b").pid == os.getpid()


def test_a_holder_on_another_host_is_never_stale(tmp_path):
    holder = write_lock(tmp_path, host="login2.elsewhere", pid=dead_pid())
    assert not is_stale(holder)
    with pytest.raises(RunLocked, match="pid .* on host login2.elsewhere.*another host: whether it still runs cannot be checked"):
        acquire([tmp_path])


def test_a_refused_folder_releases_the_ones_taken_before_it(tmp_path, live_process):
    pid, start = live_process
    write_lock(tmp_path / "b", pid=pid, process_start=start)
    with pytest.raises(RunLocked):
        acquire([tmp_path / "a", tmp_path / "b"])
    assert not (tmp_path / "a" / LOCK_NAME).exists()


def test_a_lock_file_that_is_not_a_record_is_named(tmp_path):
    (tmp_path / LOCK_NAME).write_text("not json")
    with pytest.raises(ValueError, match=f"{tmp_path / LOCK_NAME} is not a stex run lock"):
        acquire([tmp_path])


def test_process_start_reads_proc_stat_with_spaces_and_parentheses_in_the_command_name():
    # the child reads its own start while its name is plain, then renames itself "a) b (c"
    code = ("import ctypes, sys, time\n"
            "print(open('/proc/self/stat').read().split()[21], flush=True)\n"
            "ctypes.CDLL(None).prctl(15, b'a) b (c', 0, 0, 0)\n"
            "print('renamed', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        start = int(proc.stdout.readline())
        assert proc.stdout.readline() == "renamed\n"
        assert "(a) b (c)" in open(f"/proc/{proc.pid}/stat").read()
        assert runlock.process_start(proc.pid) == start
    finally:
        proc.kill()
        proc.wait()
    assert runlock.process_start(dead_pid()) is None


def test_min_job_age_from_scontrol():
    assert parse_min_job_age("MaxJobCount             = 10000\nMinJobAge               = 300 sec\n") == 300
    assert parse_min_job_age("MaxJobCount = 10000\n") is None


def test_status_command_choice():
    need = squeue_needs_min_job_age_s(40)
    assert need == 180 and squeue_needs_min_job_age_s(100) == 300
    # accounting answers: the plugin's setting stands, unless squeue cannot follow the jobs
    assert choose_status_command("sacct", None, 10, 40) == "sacct"
    assert choose_status_command("squeue", None, 300, 40) == "squeue"
    assert choose_status_command("squeue", None, 60, 40) == "sacct"
    # no accounting: squeue where MinJobAge allows, else an error saying what to change
    assert choose_status_command("sacct", "Slurm accounting storage is disabled", 300, 40) == "squeue"
    with pytest.raises(SlurmStatusError, match=r"MinJobAge = 120 s, less than the 180 s .* MinJobAge >= 180"):
        choose_status_command("sacct", "Slurm accounting storage is disabled", 120, 40)
    with pytest.raises(SlurmStatusError, match="MinJobAge = unknown"):
        choose_status_command("squeue", "disabled", None, 40)


def test_status_failures_raise_once_they_have_lasted_the_limit():
    failures = StatusFailures(30)
    failures.failed(100.0, "squeue --name run1", "no controller")
    failures.failed(120.0, "squeue --name run1", "no controller")
    failures.answered()  # the controller came back: the count starts afresh
    failures.failed(140.0, "squeue --name run1", "no controller")
    failures.failed(169.0, "squeue --name run1", "no controller")
    with pytest.raises(SlurmStatusError, match=r"failed 3 times over 30 s \(squeue --name run1: no controller\).*"
                                               r"`scancel --name run1` ends them"):
        failures.failed(170.0, "squeue --name run1", "no controller")
    with pytest.raises(ValueError, match="> 0 s"):
        StatusFailures(0)
