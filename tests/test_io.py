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
    import platform

    import scipy
    assert g.attrs["libraries"]["numpy"] == np.__version__ and g.attrs["libraries"]["scipy"] == scipy.__version__
    assert g.attrs["libraries"]["python"] == platform.python_version()
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


def damage(chunk, how):
    """Cut a chunk file to half its length, or overwrite 16 bytes in its middle (size kept)."""
    data = bytearray(chunk.read_bytes())
    if how == "cut":
        data = data[: len(data) // 2]
    else:
        i = len(data) // 2
        data[i:i + 16] = b"\x55" * 16
    chunk.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["cut", "overwritten"])
def test_a_damaged_chunk_is_named_in_every_read(tmp_path, how):
    """A chunk cut short or damaged in place (the checksum) is a StoreError naming the store, the
    array and the chunk file, whatever reads it; the other chunks and bad selections are as before."""
    import json

    rng = np.random.default_rng(1)
    color = rng.integers(0, 256, (3, 20, 30, 3), dtype=np.uint8)
    vertices = rng.normal(size=(50, 3)).astype(np.float32)
    with create_store(tmp_path / "f.zarr", "frames", attrs={"frame_ids": [5, 6, 7]}) as s:
        s.write("color", color)
        s.write("depth", np.full((3, 2, 3), 1000, np.uint16))
        s.write("timestamps", np.arange(3.0))
    with create_store(tmp_path / "s.zarr", "scene") as s:
        s.write("template/vertices", vertices)
    meta = json.loads((tmp_path / "f.zarr" / "color" / "zarr.json").read_text())
    assert meta["codecs"][-1] == {"name": "zstd", "configuration": {"level": 0, "checksum": True}}

    damage(tmp_path / "f.zarr" / "color" / "c" / "1" / "0" / "0" / "0", how)
    damage(tmp_path / "s.zarr" / "template" / "vertices" / "c" / "0" / "0", how)
    g = open_store(tmp_path / "f.zarr", "frames")       # the chunk files are all there
    named = r"f\.zarr: array 'color' cannot be read \(chunk file color/c/1/0/0/0: .*the store is damaged"
    for read in (lambda a: a[...], lambda a: a[1], lambda a: a[-2, 3:5], lambda a: a[[0, 1]],
                 lambda a: a[:, 0, 0], np.asarray):
        with pytest.raises(StoreError, match=named):
            read(g["color"])
    np.testing.assert_array_equal(g["color"][0], color[0])
    np.testing.assert_array_equal(g["color"][[0, 2]], color[[0, 2]])
    assert g["color"].shape == (3, 20, 30, 3) and g["color"].dtype == np.uint8 and g.attrs["frame_ids"] == [5, 6, 7]
    with pytest.raises(IndexError):                     # not the store's fault: not a StoreError
        g["color"][3]
    with pytest.raises(StoreError, match=r"f\.zarr: array 'color' of frame 6 cannot be read \(chunk file color/c/1/0/0/0"):
        FrameSequence([tmp_path / "f.zarr"], "frames").read("color", 6)
    assert FrameSequence([tmp_path / "f.zarr"], "frames").read("color", 7).shape == (20, 30, 3)
    scene = open_store(tmp_path / "s.zarr", "scene")
    with pytest.raises(StoreError, match=r"s\.zarr: array 'template/vertices' cannot be read "
                                         r"\(chunk file template/vertices/c/0/0: "):
        scene["template/vertices"][...]
    with pytest.raises(StoreError, match=r"array 'template/vertices' cannot be read"):
        scene["template"]["vertices"][:3]


def test_a_failed_read_lets_zarrs_other_reads_finish():
    """zarr reads a selection's chunks concurrently on its own event loop; when one does not
    decode the others are left running, and the CLI, exiting right after its one-line error,
    printed "Task was destroyed but it is pending!" for each (4 of 8 runs of `stex export` on the
    reviewer's run with a cut texture chunk). The error path waits for them."""
    import asyncio

    from zarr.core.sync import _get_loop

    from stex.io import _settle_zarr_reads

    left = asyncio.run_coroutine_threadsafe(asyncio.sleep(0.5), _get_loop())
    _settle_zarr_reads()
    assert left.done()


def test_stores_written_without_chunk_checksums_still_read(tmp_path, monkeypatch):
    """Stores written before the checksum (zarr's default zstd codec) open and read as before."""
    import json

    import zarr

    import stex.io as io

    monkeypatch.setattr(io, "CHUNK_CODEC", zarr.codecs.ZstdCodec(level=0, checksum=False))
    _frames(tmp_path / "old.zarr", [0, 1, 2])
    monkeypatch.undo()
    meta = json.loads((tmp_path / "old.zarr" / "color" / "zarr.json").read_text())
    assert meta["codecs"][-1]["configuration"]["checksum"] is False
    g = open_store(tmp_path / "old.zarr", "frames")
    assert g["color"][2, 0, 0, 0] == 2 and g["depth"][...].sum() == 3 * 6 * 1000
    assert FrameSequence([tmp_path / "old.zarr"], "frames").read("color", 1)[0, 0, 0] == 1
    # a chunk of it cut short is still named (zstd cannot decode it)
    damage(tmp_path / "old.zarr" / "color" / "c" / "1" / "0" / "0" / "0", "cut")
    with pytest.raises(StoreError, match=r"old\.zarr: array 'color' cannot be read \(chunk file color/c/1/0/0/0"):
        open_store(tmp_path / "old.zarr", "frames")["color"][...]


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
