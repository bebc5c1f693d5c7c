"""Stage scripts' logging: a failure lands in the job's log file, where Snakemake points."""
import subprocess
import sys


def test_an_exception_that_ends_a_stage_is_in_its_log_file(tmp_path):
    log = tmp_path / "stage.log"
    code = ("from stex.logs import setup_logging\n"
            f"setup_logging({str(log)!r})\n"
            "import logging; logging.getLogger('stex.x').info('working on frame 3')\n"
            "raise ValueError('frames/block_0000.zarr: frame 3: empty mask')\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 1
    text = log.read_text()
    assert "working on frame 3" in text and "Traceback" in text
    assert "ValueError: frames/block_0000.zarr: frame 3: empty mask" in text
    assert "ValueError: frames/block_0000.zarr: frame 3: empty mask" in run.stderr  # once on stderr too
    assert run.stderr.count("Traceback") == 1
