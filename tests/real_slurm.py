"""A real one-node SLURM cluster on this machine, for tests/test_slurm_real.py: Debian's slurm-wlm
(slurmctld, slurmd) and munge, and for job accounting slurmdbd on a MariaDB server of its own.
.ci/run installs the packages; the tests start the daemons as root and stop them afterwards.

``Cluster(state_dir).start(accounting=...)`` writes ``/etc/slurm/slurm.conf`` (and
``slurmdbd.conf``): the path every Slurm command and the jobs' own ``srun`` read, which an
environment variable does not reach through the plugin's job steps. Files there that this module
did not write are never touched (:func:`unavailable` says why the tests skip then). The daemons
run in the foreground as children of the test process, their state and logs in ``state_dir``;
:meth:`Cluster.stop` ends them and removes the configuration files.
"""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

ETC = Path("/etc/slurm")
MARK = "# written by stex tests/real_slurm.py; removed when its tests end\n"
DAEMONS = ("slurmctld", "slurmd", "munged")
ACCOUNTING = ("slurmdbd", "mariadbd", "mariadb-install-db")
ACCOUNT, PARTITION = "stexci", "debug"
DB_PORT = 33061  # MariaDB on localhost TCP: no clash with a system server's socket


def unavailable(accounting: bool) -> str | None:
    """Why the cluster cannot be started here (None: it can)."""
    missing = [d for d in DAEMONS + ("sbatch", "squeue", "sacct", "scontrol")
               + (ACCOUNTING if accounting else ()) if shutil.which(d) is None]
    if missing:
        return f"no {', '.join(missing)} (Debian: apt-get install slurm-wlm munge slurmdbd mariadb-server; .ci/run does)"
    if os.geteuid() != 0:
        return "the test cluster's daemons run as root"
    for name in ("slurm.conf", "slurmdbd.conf"):
        path = ETC / name
        if path.exists() and not path.read_text().startswith(MARK):
            return f"{path} exists (a cluster of this machine's own): not overwritten"
    running = subprocess.run(["pgrep", "-x", "slurmctld|slurmd|slurmdbd"], capture_output=True, text=True).stdout.split()
    if running:
        return f"Slurm daemons already run here (pids {', '.join(running)})"
    return None


def _wait(what: str, check, timeout_s: float = 60, log: Path | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.25)
    tail = log.read_text()[-2000:] if log is not None and log.exists() else ""
    raise RuntimeError(f"{what} not ready after {timeout_s} s\n{tail}")


def _ok(*cmd: str) -> bool:
    try:
        return subprocess.run(cmd, capture_output=True, timeout=30).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def _memory_mb() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) // 1024
    raise RuntimeError("no MemTotal in /proc/meminfo")


class Cluster:
    """One node named after this host, all its CPUs and 3/4 of its memory in partition
    ``debug``; jobs run as the submitting user (root)."""

    def __init__(self, state_dir: Path):
        self.state = Path(state_dir)
        self.node = socket.gethostname().split(".")[0]
        self.procs: dict[str, subprocess.Popen] = {}
        self.accounting = False

    def _spawn(self, name: str, cmd: list[str]) -> None:
        log = open(self.state / f"{name}.out", "ab")
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def _munge(self) -> None:
        if _ok("sh", "-c", "munge -n | unmunge"):
            return  # this machine's munged answers already
        for d in ("/etc/munge", "/run/munge", "/var/lib/munge", "/var/log/munge"):
            os.makedirs(d, exist_ok=True)
            shutil.chown(d, "munge", "munge")
        if not Path("/etc/munge/munge.key").exists():  # the package makes one; an image may lack it
            subprocess.run(["runuser", "-u", "munge", "--", "mungekey", "--create"], check=True, capture_output=True)
        # munged refuses to run as root; in the foreground so that stop() ends it
        self._spawn("munged", ["runuser", "-u", "munge", "--", "munged", "--foreground"])
        _wait("munged", lambda: _ok("sh", "-c", "munge -n | unmunge"))

    def slurm_conf(self, accounting: bool, min_job_age_s: int) -> str:
        spool = self.state / ("spool_accounting" if accounting else "spool")
        lines = [
            "ClusterName=stexci", f"SlurmctldHost={self.node}", "SlurmUser=root", "SlurmdUser=root",
            "AuthType=auth/munge", f"StateSaveLocation={spool}/ctld", f"SlurmdSpoolDir={spool}/d",
            f"SlurmctldPidFile={self.state}/slurmctld.pid", f"SlurmdPidFile={self.state}/slurmd.pid",
            f"SlurmctldLogFile={self.state}/slurmctld.log", f"SlurmdLogFile={self.state}/slurmd.log",
            # no cgroups in a container: processes tracked by their parent, no CPU binding
            "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none",
            "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core_Memory", "ReturnToService=2",
            "MpiDefault=none", f"MinJobAge={min_job_age_s}",
            f"NodeName={self.node} CPUs={os.cpu_count()} RealMemory={_memory_mb() * 3 // 4} State=UNKNOWN",
            f"PartitionName={PARTITION} Nodes={self.node} Default=YES MaxTime=INFINITE State=UP",
        ]
        if accounting:
            lines += ["AccountingStorageType=accounting_storage/slurmdbd", "AccountingStorageHost=localhost",
                      "AccountingStoreFlags=job_comment"]
        for d in ("ctld", "d"):
            (spool / d).mkdir(parents=True, exist_ok=True)
        return MARK + "\n".join(lines) + "\n"

    def _database(self) -> None:
        data = self.state / "mariadb"
        if not data.exists():
            subprocess.run(["mariadb-install-db", "--no-defaults", "--user=root", f"--datadir={data}",
                            "--auth-root-authentication-method=socket"], check=True, capture_output=True)
        sock = self.state / "mariadb.sock"
        self._spawn("mariadbd", ["mariadbd", "--no-defaults", "--user=root", f"--datadir={data}",
                                 f"--socket={sock}", f"--port={DB_PORT}", "--bind-address=127.0.0.1",
                                 f"--pid-file={self.state}/mariadb.pid"])
        client = ["mariadb", "--no-defaults", "-S", str(sock), "-u", "root", "-e"]
        _wait("mariadbd", lambda: _ok(*client, "select 1"), log=self.state / "mariadbd.out")
        subprocess.run(client + ["CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY 'stexci'; "
                                 "GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';"], check=True)
        conf = ETC / "slurmdbd.conf"
        conf.write_text(MARK + "\n".join([
            "AuthType=auth/munge", "DbdHost=localhost", "SlurmUser=root",
            f"PidFile={self.state}/slurmdbd.pid", f"LogFile={self.state}/slurmdbd.log",
            "StorageType=accounting_storage/mysql", "StorageHost=127.0.0.1", f"StoragePort={DB_PORT}",
            "StorageUser=slurm", "StoragePass=stexci", "StorageLoc=slurm_acct_db"]) + "\n")
        conf.chmod(0o600)  # slurmdbd refuses a config others can read
        self._spawn("slurmdbd", ["slurmdbd", "-D"])
        _wait("slurmdbd", lambda: _ok("sacctmgr", "-n", "list", "cluster"), log=self.state / "slurmdbd.log")

    def start(self, accounting: bool, min_job_age_s: int = 300) -> "Cluster":
        """Start the daemons (munged if this machine's does not answer; with ``accounting``,
        MariaDB and slurmdbd too, and the account ``stexci`` for root). Returns self; a start
        that fails stops what it started."""
        try:
            return self._start(accounting, min_job_age_s)
        except BaseException:
            self.stop()
            raise

    def _start(self, accounting: bool, min_job_age_s: int) -> "Cluster":
        self.state.mkdir(parents=True, exist_ok=True)
        ETC.mkdir(parents=True, exist_ok=True)
        self.accounting = accounting
        self._munge()
        # before slurmdbd: sacctmgr finds it through slurm.conf
        (ETC / "slurm.conf").write_text(self.slurm_conf(accounting, min_job_age_s))
        if accounting:
            self._database()
        self._spawn("slurmctld", ["slurmctld", "-D"])
        _wait("slurmctld", lambda: _ok("scontrol", "ping"), log=self.state / "slurmctld.log")
        self._spawn("slurmd", ["slurmd", "-D"])
        _wait("the node", lambda: "idle" in subprocess.run(
            ["sinfo", "-h", "-o", "%T"], capture_output=True, text=True).stdout, log=self.state / "slurmd.log")
        if accounting:
            _wait("the cluster's registration", lambda: "stexci" in subprocess.run(
                ["sacctmgr", "-n", "list", "cluster", "format=cluster"], capture_output=True, text=True).stdout)
            subprocess.run(["sacctmgr", "-i", "add", "account", ACCOUNT], check=True, capture_output=True)
            subprocess.run(["sacctmgr", "-i", "add", "user", "root", f"account={ACCOUNT}"], check=True, capture_output=True)
        return self

    def reconfigure(self, min_job_age_s: int) -> None:
        """Change MinJobAge of the running controller (scontrol reconfigure)."""
        (ETC / "slurm.conf").write_text(self.slurm_conf(self.accounting, min_job_age_s))
        subprocess.run(["scontrol", "reconfigure"], check=True, capture_output=True)
        _wait("MinJobAge", lambda: f"= {min_job_age_s} sec" in subprocess.run(
            ["scontrol", "show", "config"], capture_output=True, text=True).stdout)

    def stop(self) -> None:
        """End the daemons this object started (last started first) and remove its configuration."""
        for name, proc in reversed(list(self.procs.items())):
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.procs.clear()
        for name in ("slurm.conf", "slurmdbd.conf"):
            path = ETC / name
            if path.exists() and path.read_text().startswith(MARK):
                path.unlink()

    def jobs(self) -> list[dict]:
        """The cluster's jobs as its status commands see them: sacct's with accounting, else
        squeue's (``--states=all``: ended jobs for MinJobAge). Each {id, name, comment, state}."""
        if self.accounting:
            out = subprocess.run(["sacct", "-X", "--parsable2", "--noheader", "--starttime", "now-1days",
                                  "--format=JobIdRaw,JobName%60,Comment%200,State"],
                                 capture_output=True, text=True, check=True).stdout
        else:
            out = subprocess.run(["squeue", "--states=all", "--noheader", "--format=%i|%j|%k|%T"],
                                 capture_output=True, text=True, check=True).stdout
        rows = [line.split("|") for line in out.splitlines() if line.strip()]
        return [dict(zip(("id", "name", "comment", "state"), row)) for row in rows]
