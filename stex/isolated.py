"""Run a function in a fresh Python process that exits without running any destructor.

Why: xatlas' ``Atlas`` destructor (``xatlas::Destroy``) joins its task scheduler's worker
threads, and xatlas wakes those threads by notifying a condition variable without holding its
mutex, a pattern that can lose the wake-up. One test run hung there for good (py-spy:
``std::thread::join <- xatlas::internal::TaskScheduler::~TaskScheduler <- xatlas::Destroy``),
with the GIL held, so nothing in the process could even report it. :func:`call_in_child` runs the
xatlas work in a child process that ends with ``os._exit`` once its result is written: the atlas
is never destroyed, the kernel ends its threads, and the calling process never loads xatlas.

A crash in the child (a signal, a C++ abort) becomes a RuntimeError naming the function instead of
taking the caller's process down.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import traceback
from pathlib import Path

# the child imports stex from the same place as the caller, whatever the current directory
_STEX_PARENT = str(Path(__file__).resolve().parent.parent)


def call_in_child(func, *args, **kwargs):
    """``func(*args, **kwargs)`` run in a new Python process; its return value.

    Args:
        func: a module-level function (pickled by reference, so the child imports its module).
        args, kwargs: picklable arguments (numpy arrays are).

    Returns:
        what ``func`` returned (pickled back).

    Raises:
        the exception ``func`` raised, re-raised here with the child's traceback as a note;
        RuntimeError when the child died without a result (killed by a signal, out of memory).
    """
    payload = pickle.dumps((func, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
    # stdout carries the result; the child's stderr (warnings, C-level prints) is the caller's
    code = "import sys; sys.path.insert(0, sys.argv[1]); from stex.isolated import _child_main; _child_main()"
    proc = subprocess.run([sys.executable, "-c", code, _STEX_PARENT], input=payload, stdout=subprocess.PIPE,
                          check=False)
    name = f"{func.__module__}.{func.__qualname__}"
    if proc.returncode != 0 or not proc.stdout:
        rc = proc.returncode
        how = (f"was killed by {signal.Signals(-rc).name}" if rc < 0 and -rc in signal.valid_signals()
               else f"exited with status {rc}")
        raise RuntimeError(f"{name} ran in a child process, which {how} without a result")
    status, value, child_traceback = pickle.loads(proc.stdout)
    if status == "ok":
        return value
    value.add_note(f"(raised in the child process running {name}:)\n{child_traceback}")
    raise value


def _child_main() -> None:
    """The child's side: read (func, args, kwargs) from stdin, write (status, value, traceback)
    to the original stdout, leave through ``os._exit`` (no destructors, no atexit)."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything else printed to stdout (by Python or C) goes to stderr
    try:
        func, args, kwargs = pickle.loads(sys.stdin.buffer.read())
        value = func(*args, **kwargs)
        try:
            data = pickle.dumps(("ok", value, ""), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # noqa: BLE001 - named below, as the caller's error
            raise TypeError(f"{func.__module__}.{func.__qualname__} returned a {type(value).__name__}, "
                            f"which cannot be sent back: {exc}") from None
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the caller
        text = traceback.format_exc()
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # noqa: BLE001 - an exception that cannot travel becomes one that can
            exc = RuntimeError(f"{type(exc).__name__}: {exc}")
        data = pickle.dumps(("error", exc, text), protocol=pickle.HIGHEST_PROTOCOL)
    out.write(data)
    out.flush()
    sys.stderr.flush()
    os._exit(0)
