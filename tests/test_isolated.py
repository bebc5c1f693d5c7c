"""stex.isolated: functions run in a child process that leaves without destructors."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stex.isolated import call_in_child


def test_the_result_comes_back_from_another_process():
    assert call_in_child(os.getpid) != os.getpid()
    a, b = np.arange(12.0).reshape(3, 4), np.full((3, 4), 0.5)
    out = call_in_child(np.add, a, b)
    assert out.dtype == np.float64 and np.array_equal(out, a + b)
    assert call_in_child(divmod, 17, 5) == (3, 2)
    assert call_in_child(sorted, [3, 1, 2], reverse=True) == [3, 2, 1]


def test_the_childs_exception_is_raised_with_its_traceback():
    with pytest.raises(ValueError, match="invalid literal for int") as info:
        call_in_child(int, "seventeen")
    notes = "\n".join(getattr(info.value, "__notes__", []))
    assert "child process running builtins.int" in notes and "Traceback" in notes


def test_a_child_killed_by_a_signal_is_named():
    with pytest.raises(RuntimeError, match=r"posix\.abort ran in a child process, which was killed by SIGABRT"):
        call_in_child(os.abort)


def test_the_child_runs_no_exit_handlers(tmp_path):
    """The point of the module: the child leaves through os._exit, so nothing that runs at
    interpreter exit (atexit handlers, destructors such as xatlas' Atlas) runs in it."""
    marker = tmp_path / "ran_at_exit"
    # control: the same registration in an ordinary interpreter does run at exit
    subprocess.run([sys.executable, "-c", f"import atexit, pathlib; atexit.register(pathlib.Path({str(marker)!r}).touch)"],
                   check=True)
    assert marker.exists()
    marker.unlink()
    call_in_child(__import__("atexit").register, Path(marker).touch)
    assert not marker.exists()


def test_what_the_child_prints_goes_to_stderr_not_into_the_result(capfd):
    assert call_in_child(print, "noise from the child") is None
    out, err = capfd.readouterr()
    assert "noise from the child" in err and "noise from the child" not in out


def test_a_child_exiting_early_is_named():
    with pytest.raises(RuntimeError, match=r"exited with status 3 without a result"):
        call_in_child(os._exit, 3)
    with pytest.raises(RuntimeError, match=r"killed by SIGTERM"):
        call_in_child(signal.raise_signal, signal.SIGTERM)


def test_a_result_that_cannot_travel_back_is_named():
    with pytest.raises(TypeError, match=r"importlib\.import_module returned a module, which cannot be sent back"):
        call_in_child(__import__("importlib").import_module, "json")


def test_the_child_imports_the_callers_stex(tmp_path):
    """The child runs the stex the caller runs, even one the caller put on sys.path itself (pytest's
    rootdir, a clone beside an installed copy) and whatever the current directory."""
    import shutil

    import stex

    copy = tmp_path / "elsewhere"
    shutil.copytree(Path(stex.__file__).parent, copy / "stex", ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import sys, importlib.util; sys.path.insert(0, sys.argv[1]); import stex.isolated as m; "
            "print(m.__file__); print(m.call_in_child(importlib.util.find_spec, 'stex.isolated').origin)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([sys.executable, "-c", code, str(copy)], cwd=tmp_path, env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out == [str(copy / "stex" / "isolated.py")] * 2
