import os

import numpy as np
import pytest

from conftest import REPO
from stex.io import ARTIFACTS, FrameSequence, StoreError, artifacts_markdown, create_store, open_store


def _frames(path, ids, H=4, W=5):
    with create_store(path, "frames", attrs={"frame_ids": ids}, params={"x": 1}) as s:
        c = s.create("color", (len(ids), H, W, 3))
        for k, fid in enumerate(ids):
            c[k] = fid
        s.write("depth", np.full((len(ids), 2, 3), 1000, np.uint16))
        s.write("timestamps", np.asarray(ids, float))


def test_round_trip_attrs_and_chunks(tmp_path):
    p = tmp_path / "f.zarr"
    _frames(p, [3, 4])
    g = open_store(p, "frames")
    assert g.attrs["complete"] and g.attrs["frame_ids"] == [3, 4]
    assert g.attrs["units"]["depth"] == "mm" and g.attrs["params"] == {"x": 1}
    assert "OpenCV" in g.attrs["conventions"]
    assert g["color"].chunks == (1, 4, 5, 3)
    assert g["color"].dtype == np.uint8 and g["color"][1, 0, 0, 0] == 4


def test_failed_writer_leaves_nothing(tmp_path):
    p = tmp_path / "f.zarr"
    with pytest.raises(RuntimeError):
        with create_store(p, "frames") as s:
            s.create("color", (1, 2, 2, 3))
            raise RuntimeError("boom")
    assert not p.exists() and not list(tmp_path.glob("f.zarr.partial*"))


def test_missing_required_array_is_refused(tmp_path):
    p = tmp_path / "f.zarr"
    with pytest.raises(StoreError, match="required array 'depth'"):
        with create_store(p, "frames") as s:
            s.create("color", (1, 2, 2, 3))
            s.write("timestamps", np.zeros(1))
    assert not p.exists()


def test_inconsistent_shapes_and_undeclared_arrays(tmp_path):
    with pytest.raises(StoreError, match="T=2"):
        with create_store(tmp_path / "a.zarr", "frames") as s:
            s.create("color", (1, 2, 2, 3))
            s.create("depth", (2, 2, 2))
            s.write("timestamps", np.zeros(1))
    with pytest.raises(StoreError, match="declares no array"):
        with create_store(tmp_path / "b.zarr", "frames") as s:
            s.create("data2", (1,))
    with pytest.raises(StoreError, match="non-finite"):
        with create_store(tmp_path / "c.zarr", "scene") as s:
            s.write("template/vertices", np.array([[0, np.nan, 0]]))


def test_open_refuses_wrong_kind_incomplete_and_missing(tmp_path):
    p = tmp_path / "f.zarr"
    _frames(p, [0])
    with pytest.raises(StoreError, match="expected 'masks'"):
        open_store(p, "masks")
    with pytest.raises(StoreError, match="no such store"):
        open_store(tmp_path / "nope.zarr", "frames")
    import zarr
    g = zarr.open_group(str(p), mode="r+")
    g.attrs["complete"] = False
    with pytest.raises(StoreError, match="incomplete"):
        open_store(p, "frames")


def test_frame_sequence_across_blocks(tmp_path):
    _frames(tmp_path / "b0.zarr", [0, 1, 2])
    _frames(tmp_path / "b1.zarr", [3, 4])
    seq = FrameSequence([tmp_path / "b0.zarr", tmp_path / "b1.zarr"], "frames")
    assert len(seq) == 5 and seq.frame_ids == [0, 1, 2, 3, 4]
    assert seq.read("color", 4)[0, 0, 0] == 4
    with pytest.raises(KeyError):
        seq.read("color", 9)
    _frames(tmp_path / "dup.zarr", [2])
    with pytest.raises(StoreError, match="frame 2"):
        FrameSequence([tmp_path / "b0.zarr", tmp_path / "dup.zarr"], "frames")


def test_a_damaged_copy_is_refused_not_read_as_zeros(tmp_path):
    import shutil

    _frames(tmp_path / "b.zarr", [0, 1, 2, 3])       # frame 0 is all zeros: zarr writes no chunk
    g = open_store(tmp_path / "b.zarr", "frames")
    assert g.attrs["chunk_files"]["color"] == 3
    chunks = sorted((tmp_path / "b.zarr" / "color" / "c").rglob("*"))
    chunk = [c for c in chunks if c.is_file()][1]
    # a partial copy: one chunk file missing would read as zeros without a word
    lost = shutil.copytree(tmp_path / "b.zarr", tmp_path / "lost.zarr")
    (lost / chunk.relative_to(tmp_path / "b.zarr")).unlink()
    with pytest.raises(StoreError, match=r"lost\.zarr: array 'color' has 2 of the 3 chunk files"):
        open_store(lost, "frames")
    # a chunk cut short: named with its frame when read
    cut = shutil.copytree(tmp_path / "b.zarr", tmp_path / "cut.zarr")
    target = cut / chunk.relative_to(tmp_path / "b.zarr")
    target.write_bytes(target.read_bytes()[:5])
    seq = FrameSequence([cut], "frames")
    fid = int(chunk.relative_to(tmp_path / "b.zarr" / "color" / "c").parts[0])
    with pytest.raises(StoreError, match=rf"cut\.zarr: array 'color' of frame {fid} cannot be read"):
        seq.read("color", fid)
    # a required array gone
    gone = shutil.copytree(tmp_path / "b.zarr", tmp_path / "gone.zarr")
    shutil.rmtree(gone / "depth")
    with pytest.raises(StoreError, match=r"required array 'depth' was not written .*damaged"):
        open_store(gone, "frames")


def test_two_writers_of_one_store_keep_to_their_own_folders(tmp_path):
    """A job orphaned by a killed Snakemake and its re-run may write one store at once: each
    builds in a folder of its own, and this host's dead writers' left-overs are removed."""
    import socket
    import subprocess
    import sys

    host = socket.gethostname().replace("-", "_")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    p = tmp_path / "f.zarr"
    stale = [tmp_path / "f.zarr.partial", tmp_path / f"f.zarr.partial-{host}-{dead}"]
    elsewhere = tmp_path / "f.zarr.partial-othernode-1"          # another host's writer: not ours to judge
    for d in stale + [elsewhere]:
        d.mkdir()
    with create_store(p, "frames", attrs={"frame_ids": [0]}) as outer:
        assert not any(d.exists() for d in stale) and elsewhere.exists()
        mine = sorted(x.name for x in tmp_path.glob("f.zarr.partial*"))
        assert mine == [elsewhere.name, f"f.zarr.partial-{host}-{os.getpid()}"]
        outer.write("color", np.ones((1, 2, 2, 3), np.uint8))
        outer.write("depth", np.ones((1, 2, 2), np.uint16))
        outer.write("timestamps", np.zeros(1))
    assert open_store(p, "frames").attrs["complete"]
    assert sorted(x.name for x in tmp_path.glob("f.zarr.partial*")) == [elsewhere.name]

    # JSON files and a dead writer's old store renamed aside are cleared the same way
    from stex.io import write_json
    (tmp_path / f"r.json.partial-{host}-{dead}").write_text("{half")
    (tmp_path / f"f.zarr.partial-{host}-{dead}.old").mkdir()
    write_json(tmp_path / "r.json", {"a": 1})
    assert sorted(x.name for x in tmp_path.glob("r.json*")) == ["r.json"]
    with create_store(p, "frames", attrs={"frame_ids": [0]}) as w:
        w.write("color", np.ones((1, 2, 2, 3), np.uint8))
        w.write("depth", np.ones((1, 2, 2), np.uint16))
        w.write("timestamps", np.zeros(1))
    assert sorted(x.name for x in tmp_path.glob("f.zarr.partial*")) == [elsewhere.name]


def test_a_replaced_store_stays_whole_until_the_new_one_is_in_place(tmp_path, monkeypatch):
    """The old store is renamed aside, not deleted, before the new one moves in: if that move
    fails the old one is still there, and one complete store is at the path at every moment."""
    import stex.io as io

    p = tmp_path / "f.zarr"

    def write(value):
        with create_store(p, "frames", attrs={"frame_ids": [0]}) as w:
            w.write("color", np.full((1, 2, 2, 3), value, np.uint8))
            w.write("depth", np.ones((1, 2, 2), np.uint16))
            w.write("timestamps", np.zeros(1))

    write(1)
    real = os.replace
    seen = []

    def replace(src, dst):
        if str(dst) == str(p):      # the new store moving in: the old one is aside, intact
            aside = [x for x in tmp_path.iterdir() if x.name.endswith(".old")]
            seen.append(aside and open_store(aside[0], "frames")["color"][0, 0, 0, 0])
        return real(src, dst)

    monkeypatch.setattr(io.os, "replace", replace)
    write(2)
    assert seen == [1] and open_store(p, "frames")["color"][0, 0, 0, 0] == 2
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f.zarr"]


def test_docs_page_is_generated_from_the_registry():
    doc = (REPO / "docs" / "artifacts.md").read_text()
    assert doc == artifacts_markdown(), "regenerate: python -m stex.io > docs/artifacts.md"
    for name, spec in ARTIFACTS.items():
        assert f"`{name}`" in doc
        for aname in spec.arrays:
            assert f"`{aname}`" in doc
