"""Atomic placement of files and folders: a writer builds its output under a name of its own
(:func:`partial_path`) and moves it into place when complete (:func:`move_into_place`), so an
output under its final name is always whole, even with two writers of it or a killed one."""

from __future__ import annotations

import json
import os
import shutil
import socket
from pathlib import Path

__all__ = ["partial_path", "move_into_place", "write_json"]


def write_json(path: str | os.PathLike, doc) -> None:
    """Write ``doc`` as JSON to ``path`` atomically: built in this writer's
    :func:`partial_path` and moved into place, so a file at ``path`` is complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = partial_path(path)
    try:
        tmp.write_text(json.dumps(doc, indent=1))
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def move_into_place(tmp: Path, path: Path) -> None:
    """Replace ``path`` (a file or folder, or nothing) by ``tmp``, built by :func:`partial_path`.

    An old folder at ``path`` is first renamed aside (to ``<tmp>.old``) and removed only once
    ``tmp`` is in place: removing it first left nothing at ``path`` for as long as the removal of
    a large store took, and nothing at all if the writer was killed in between. A left-over
    ``.old`` of a dead writer is removed by the next :func:`partial_path` of ``path``.
    """
    tmp, path = Path(tmp), Path(path)
    aside = tmp.with_name(tmp.name + ".old")
    if path.is_dir() and not path.is_symlink():
        os.replace(path, aside)
    os.replace(tmp, path)
    if aside.exists():
        shutil.rmtree(aside, ignore_errors=True)


def partial_path(path: str | os.PathLike) -> Path:
    """The temporary name of one writer of ``path`` (a store, folder or file):
    ``<path>.partial-<host>-<pid>``, to be moved into place when complete
    (:func:`move_into_place`). Two writers of one output (a job orphaned by a killed Snakemake and
    its re-run, on a cluster) must not build in, delete or move each other's. Left-overs of this
    host's dead writers (and the old shared ``<path>.partial``) are removed; other hosts' are left
    to their writers."""
    path = Path(path)
    host = socket.gethostname().replace("-", "_")
    for old in path.parent.glob(path.name + ".partial*") if path.parent.is_dir() else ():
        rest = old.name[len(path.name) + len(".partial"):].removesuffix(".old")
        h, _, pid = rest[1:].rpartition("-")
        if rest == "" or (h == host and pid.isdigit() and not pid_alive(int(pid))):
            _remove(old)
    tmp = path.with_name(f"{path.name}.partial-{host}-{os.getpid()}")
    if tmp.exists() or tmp.is_symlink():  # this process's own earlier attempt
        _remove(tmp)
    return tmp


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this host (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True
