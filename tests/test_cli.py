import numpy as np

from stex.cli import main
from stex.io import create_store


def test_inspect_prints_arrays_and_fails_on_bad_store(tmp_path, capsys):
    p = tmp_path / "m.zarr"
    with create_store(p, "masks", attrs={"frame_ids": [4, 5]}, params={"iterations": 5}) as s:
        s.write("mask", np.zeros((2, 3, 4), bool))
        s.write("seed", np.zeros((2, 3, 4), np.uint8))
    assert main(["inspect", str(p)]) == 0
    out = capsys.readouterr().out
    assert "artifact 'masks'" in out and "frames: 2 (4..5)" in out and "(2, 3, 4)" in out
    assert main(["inspect", str(tmp_path / "missing.zarr")]) == 1
    assert "missing.zarr" in capsys.readouterr().err
