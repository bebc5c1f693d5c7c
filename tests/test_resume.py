"""A killed run is resumed by running the same command again, and a results folder has one writer.

The README's command (``snakemake --cores 2``) loads the workflow profile ``profiles/default``
(``rerun-incomplete``), and workflow/rules/hooks.smk clears the Snakemake locks a killed run left
behind, so that neither ``--rerun-incomplete`` nor ``--unlock`` is needed."""
import dataclasses
import glob
import json
import os
import signal
import subprocess
import time
import warnings

import numpy as np
import yaml
import zarr

from conftest import REPO, tiny_workflow_config
from stex.runlock import LOCK_NAME, process_start, read_holder, this_process


def workdir(path, results):
    path.mkdir(parents=True, exist_ok=True)
    (path / "tiny.yaml").write_text(yaml.safe_dump(tiny_workflow_config(results)))
    return path


def command(work, *extra):
    """The README's main command, for the tiny scene in ``work``."""
    return ["snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(work),
            "--configfile", str(work / "tiny.yaml"), "--cores", "2", *extra]


def run(work, *extra, timeout=600):
    return subprocess.run(command(work, *extra), capture_output=True, text=True, timeout=timeout)


def timed(cmd, log):
    """Run ``cmd`` with its output in the file ``log``: (exit status, output, wall time (s), CPU time
    (s, user + system, the process and its children)). The CPU time says how fast a refusal is on
    a machine whose other work stretches the wall time."""
    start = time.monotonic()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, log.read_text(), time.monotonic() - start, usage.ru_utime + usage.ru_stime


def run_and_kill_when(work, pattern, log):
    """Start the command, and kill -9 it and its jobs (the whole process group, as a crash would)
    as soon as a path matching ``pattern`` (a glob) exists. Returns True when it was killed so,
    False when the run ended first."""
    with open(log, "w") as out:
        proc = subprocess.Popen(command(work), stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 600
        while proc.poll() is None and time.monotonic() < deadline:
            if glob.glob(str(pattern)):
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                return True
            time.sleep(0.02)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            raise AssertionError(f"no {pattern} within 600 s")
    return False


def zarr_arrays(results):
    """{(store, array path): array} of every zarr store under ``results`` (partial stores of
    killed jobs, ``*.zarr.partial-*``, are not stores)."""
    arrays = {}
    for store in sorted(results.rglob("*.zarr")):
        group = zarr.open_group(str(store), mode="r")
        with warnings.catch_warnings():  # Snakemake's .snakemake_timestamp in directory outputs
            warnings.filterwarnings("ignore", message=".*snakemake_timestamp is not recognized")
            members = group.members(max_depth=None)
        for name, node in members:
            if isinstance(node, zarr.Array):
                arrays[(str(store.relative_to(results)), name)] = node[...]
    return arrays


def test_kill_9_at_three_stages_then_the_same_command_gives_the_uninterrupted_arrays(tmp_path):
    reference = workdir(tmp_path / "reference", tmp_path / "reference" / "results")
    done = run(reference)
    assert done.returncode == 0, done.stderr[-3000:]

    work = workdir(tmp_path / "killed", tmp_path / "killed" / "results")
    res = work / "results" / "tiny"
    logs = []
    # ingest and the correction killed while their store is written (stores are built at
    # <store>.partial-<host>-<pid> and moved into place when complete); the data term
    # killed once its store is in place, before Snakemake has seen its job end: the store is
    # there, but marked incomplete
    kills = {"ingest": res / "frames" / "block_0000.zarr.partial-*",
             "data_term": res / "data_term" / "block_0000.zarr",
             "correction": res / "corrected" / "block_0000.zarr.partial-*"}
    for stage, pattern in kills.items():
        logs.append(tmp_path / f"killed_in_{stage}.log")
        assert run_and_kill_when(work, pattern, logs[-1]), stage
        holder = read_holder(res)  # the killed run's lock stays, stale
        assert holder is not None and holder.cwd == str(work)
        assert list((work / ".snakemake" / "locks").glob("*.lock")), "Snakemake's locks of the killed run"
    resumed = run(work)
    final = resumed.stdout + resumed.stderr
    assert resumed.returncode == 0, final[-3000:]
    assert not (res / LOCK_NAME).exists()
    # every run after a kill found the killed one's locks and went on without being asked for
    # --unlock or --rerun-incomplete (Snakemake's refusals name them)
    for log in [p.read_text() for p in logs[1:]] + [final]:
        assert "ended without finishing" in log, log[-3000:]
        assert "--unlock" not in log and "--rerun-incomplete" not in log, log[-3000:]
    # the data term store killed in place was redone (marked incomplete), not taken as finished
    assert "rule data_term:" in logs[2].read_text()

    want, got = zarr_arrays(reference / "results" / "tiny"), zarr_arrays(res)
    assert sorted(want) == sorted(got)
    assert len(want) > 40  # every stage's stores
    for key, a in want.items():
        assert a.dtype == got[key].dtype and a.shape == got[key].shape, key
        assert np.array_equal(a, got[key], equal_nan=a.dtype.kind in "fc"), key


def test_a_second_run_on_one_results_folder_from_another_directory_fails_naming_the_first(tmp_path):
    results = tmp_path / "results"
    first, second = workdir(tmp_path / "a", results), workdir(tmp_path / "b", results)
    with open(tmp_path / "first.log", "w") as out:
        proc = subprocess.Popen(command(first), stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        lock = results / "tiny" / LOCK_NAME
        deadline = time.monotonic() + 120
        while not lock.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert lock.exists(), (tmp_path / "first.log").read_text()[-3000:]
        status, log, seconds, cpu = timed(command(second), tmp_path / "second.log")
        assert proc.poll() is None, "the first run ended before the second tried"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert status != 0
    assert f"is being written by another stex run: pid {proc.pid} on host" in log, log[-3000:]
    assert f"in {first} " in log and str(lock) in log
    # refused at the start: no job of its own, a few seconds of Snakemake reading the workflow
    assert "rule " not in log and cpu < 5, (seconds, cpu)
    # a dry run neither takes the lock nor fails on it
    dry = run(second, "-n")
    assert dry.returncode == 0, dry.stderr[-3000:]


def test_a_dataset_run_holds_every_scene_and_a_dry_run_none(tmp_path):
    """workflow/dataset.smk takes the lock of each of its scenes: one held by another live run
    stops it at the start naming that run, and the scene it had taken is let go again."""
    for name in ("a", "b"):
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump({**tiny_workflow_config(tmp_path / "results"), "scene": name}))
    (tmp_path / "dataset.yaml").write_text(yaml.safe_dump({"scene_files": ["a.yaml", "b.yaml"]}))
    other = subprocess.Popen(["sleep", "60"])
    try:
        holder = {**dataclasses.asdict(this_process("the other run")), "pid": other.pid,
                  "process_start": process_start(other.pid)}
        (tmp_path / "results" / "b").mkdir(parents=True)
        (tmp_path / "results" / "b" / LOCK_NAME).write_text(json.dumps(holder))
        cmd = ["snakemake", "--snakefile", str(REPO / "workflow" / "dataset.smk"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "dataset.yaml"), "--cores", "2"]
        dry = subprocess.run(cmd + ["-n"], capture_output=True, text=True, timeout=300)
        assert dry.returncode == 0, dry.stderr[-3000:]
        status, log, seconds, cpu = timed(cmd, tmp_path / "refused.log")
    finally:
        other.kill()
        other.wait()
    assert status != 0
    assert f"{tmp_path / 'results' / 'b'} is being written by another stex run: pid {other.pid}" in log, log[-3000:]
    assert not (tmp_path / "results" / "a" / LOCK_NAME).exists()
    assert "rule " not in log and not (tmp_path / "results" / "a" / "scene.zarr").exists()
    assert cpu < 5, (seconds, cpu)
