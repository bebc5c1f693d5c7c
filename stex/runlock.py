"""One writer per results folder: a lock file of stex's own in ``results/<scene>``.

Snakemake locks the files a run writes only against other runs in the same working directory
(its locks live in that directory's ``.snakemake/``); two runs started from different
directories on one ``results:`` folder would both write it. :func:`acquire` creates
``<folder>/.stex-run.lock`` holding who writes the folder (host, pid, start time, working
directory, command line); a second run fails at once with a :class:`RunLocked` naming that
holder. A lock whose holder ran on this host and is gone (no process with its pid, or a newer
process that reuses the pid) is stale and is taken over; a holder on another host cannot be
checked from here, so its lock stays until that run ends or someone deletes the file.

The file appears complete or not at all (written to a private name, then hard-linked to the
lock's name, which fails if it exists), also on NFS, where ``O_EXCL`` has not always been
atomic.
"""
from __future__ import annotations

import json
import os
import socket
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from stex.files import pid_alive

LOCK_NAME = ".stex-run.lock"


@dataclass(frozen=True)
class Holder:
    """Who holds a results folder: ``host`` (``socket.gethostname()``), ``pid``, ``started``
    (local time, ISO 8601 to the second), ``process_start`` (the process's start in clock ticks
    after boot, from ``/proc/<pid>/stat``; None where there is no ``/proc``), ``cwd`` and
    ``command`` (the command line)."""

    host: str
    pid: int
    started: str
    process_start: int | None
    cwd: str
    command: str

    def describe(self) -> str:
        return (f"pid {self.pid} on host {self.host}, started {self.started} in {self.cwd} "
                f"({self.command})")


class RunLocked(RuntimeError):
    """Another live run holds a results folder: ``folder``, its ``holder`` and the lock's ``path``."""

    def __init__(self, folder: Path, holder: Holder, path: Path):
        self.folder, self.holder, self.path = folder, holder, path
        where = ("" if holder.host == socket.gethostname()
                 else f" (another host: whether it still runs cannot be checked from {socket.gethostname()})")
        super().__init__(
            f"{folder} is being written by another stex run: {holder.describe()}{where}. "
            f"One results folder takes one run at a time: wait for that run to end, or give this "
            f"one another `results:` folder or scene name. If that run is gone, delete {path}")


def lock_path(folder: str | os.PathLike) -> Path:
    return Path(folder) / LOCK_NAME


def process_start(pid: int) -> int | None:
    """Start time of process ``pid`` in clock ticks after boot (``/proc/<pid>/stat`` field 22),
    or None when there is no such process or no ``/proc``."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may itself hold spaces and ')'
    return int(stat[stat.rindex(")") + 2:].split()[19])


def this_process(command: str | None = None) -> Holder:
    """The :class:`Holder` record of the calling process (``command`` defaults to ``sys.argv``)."""
    pid = os.getpid()
    return Holder(host=socket.gethostname(), pid=pid, started=time.strftime("%Y-%m-%dT%H:%M:%S"),
                  process_start=process_start(pid), cwd=os.getcwd(),
                  command=command if command is not None else " ".join(sys.argv))


def read_holder(folder: str | os.PathLike) -> Holder | None:
    """The holder recorded in ``folder``'s lock, or None when it has none. A lock that is not
    stex's record raises ValueError naming the file."""
    path = lock_path(folder)
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    try:
        record = json.loads(text)
        return Holder(**{k: record[k] for k in Holder.__dataclass_fields__})
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path} is not a stex run lock ({e}): delete it if no run writes {folder}") from None


def is_stale(holder: Holder) -> bool:
    """True when ``holder`` ran on this host and has ended: no process has its pid, or the one
    that has it started at another time (the pid was reused)."""
    if holder.host != socket.gethostname():
        return False
    if not pid_alive(holder.pid):
        return True
    now = process_start(holder.pid)
    return holder.process_start is not None and now is not None and now != holder.process_start


def is_mine(holder: Holder | None) -> bool:
    return holder is not None and holder.host == socket.gethostname() and holder.pid == os.getpid()


def _take(folder: Path, me: Holder) -> Holder | None:
    """Create ``folder``'s lock for ``me``; returns None when taken, else the present holder."""
    folder.mkdir(parents=True, exist_ok=True)
    path = lock_path(folder)
    private = folder / f"{LOCK_NAME}.{me.host}.{me.pid}"
    private.write_text(json.dumps(asdict(me), indent=1) + "\n")
    try:
        os.link(private, path)
        return None
    except FileExistsError:
        return read_holder(folder)
    finally:
        private.unlink()


def acquire(folders, command: str | None = None) -> list[Path]:
    """Lock every folder of ``folders`` (created if missing) for the calling process, in order;
    stale locks are replaced. Raises :class:`RunLocked` for the first folder another live run
    holds, after releasing the ones this call took. Returns the lock files. A folder this process
    holds already counts as taken."""
    me = this_process(command)
    taken = []
    try:
        for folder in map(Path, folders):
            for _ in range(2):  # once more after removing a stale lock
                holder = _take(folder, me)
                if holder is None or is_mine(holder):
                    taken.append(lock_path(folder))
                    break
                if not is_stale(holder):
                    raise RunLocked(folder, holder, lock_path(folder))
                # another run may have replaced the stale lock meanwhile: remove only that record
                if read_holder(folder) == holder:
                    lock_path(folder).unlink(missing_ok=True)
            else:  # the lock came back between removal and retry: a live run took it
                raise RunLocked(folder, read_holder(folder) or holder, lock_path(folder))
    except BaseException:
        release(Path(p).parent for p in taken)
        raise
    return taken


def release(folders) -> None:
    """Remove the locks of ``folders`` that the calling process holds (others are left alone)."""
    for folder in folders:
        try:
            holder = read_holder(folder)
        except ValueError:
            continue
        if is_mine(holder):
            lock_path(folder).unlink(missing_ok=True)
