import os
import re

import numpy as np
import pytest

from conftest import REPO
from stex.artifacts import ARTIFACTS, artifacts_markdown
from stex.io import FrameSequence, StoreError, create_store, id_ranges, open_store, position_range, run_block_paths


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


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])  # Ctrl-C is no Exception
def test_failed_writer_leaves_nothing(tmp_path, error):
    p = tmp_path / "f.zarr"
    with pytest.raises(error):
        with create_store(p, "frames") as s:
            s.create("color", (1, 2, 2, 3))
            raise error("boom")
    assert not p.exists() and not list(tmp_path.glob("f.zarr.partial*"))


def test_missing_required_array_is_refused(tmp_path):
    p = tmp_path / "f.zarr"
    with pytest.raises(StoreError, match=re.escape(f"{p}: required array 'depth'")):
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
    with pytest.raises(StoreError, match=re.escape(f"{tmp_path / 'nope.zarr'}: no such store")):
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
    with pytest.raises(StoreError, match="not in frame order"):
        FrameSequence([tmp_path / "b1.zarr", tmp_path / "b0.zarr"], "frames")
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
    # members() hands out the store's arrays too, not zarr's own (which raise zarr's error)
    with pytest.raises(StoreError, match=r"array 'template/vertices' cannot be read"):
        dict(scene.members())["template"]["vertices"][...]
    with pytest.raises(StoreError, match=r"array 'template/vertices' cannot be read"):
        dict(scene.members(max_depth=None))["template/vertices"][...]
    with pytest.raises(StoreError, match=named):
        dict(g.members())["color"][1]
    np.testing.assert_array_equal(dict(g.members())["color"][0], color[0])


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
    from stex.files import write_json
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


def test_a_store_counts_as_complete_only_once_its_writer_finished(tmp_path):
    """While the writer runs, its partial folder says complete=False, so a copy of it (or what a
    crash leaves) is refused as incomplete; a store whose complete attr is lost is refused too,
    not taken for complete."""
    import zarr

    p = tmp_path / "f.zarr"
    with create_store(p, "frames", attrs={"frame_ids": [0]}) as s:
        s.write("color", np.ones((1, 2, 2, 3), np.uint8))
        s.write("depth", np.ones((1, 2, 2), np.uint16))
        s.write("timestamps", np.zeros(1))
        (partial,) = tmp_path.glob("f.zarr.partial*")
        assert zarr.open_group(str(partial), mode="r").attrs["complete"] is False
        with pytest.raises(StoreError, match="incomplete"):
            open_store(partial, "frames")
    g = zarr.open_group(str(p), mode="r+")
    del g.attrs["complete"]
    with pytest.raises(StoreError, match="incomplete"):
        open_store(p, "frames")


def test_per_frame_arrays_hold_one_frame_per_chunk_and_every_chunk_is_counted(tmp_path):
    """Three non-zero frames (so zarr writes every chunk): colour, depth and the optional mask are
    chunked one frame per chunk (3 chunk files each, the chunk the frame's shape), timestamps are
    one chunk; chunk_files records these counts and units the declared units (docs/artifacts.md:
    sRGB, mm, 1, s), the optional mask included, and a copy that lost a chunk of the mask is refused
    like one of a required array."""
    p = tmp_path / "f.zarr"
    with create_store(p, "frames", attrs={"frame_ids": [0, 1, 2]}) as s:
        s.write("color", np.ones((3, 4, 5, 3), np.uint8))
        s.write("depth", np.full((3, 2, 3), 1000, np.uint16))
        s.write("mask", np.ones((3, 4, 5), bool))
        s.write("timestamps", np.arange(1.0, 4.0))
    g = open_store(p, "frames")
    assert g.attrs["chunk_files"] == {"color": 3, "depth": 3, "mask": 3, "timestamps": 1}
    assert g.attrs["units"] == {"color": "sRGB", "depth": "mm", "mask": "1", "timestamps": "s"}
    assert [g[k].chunks for k in ("color", "depth", "mask", "timestamps")] == [(1, 4, 5, 3), (1, 2, 3), (1, 4, 5), (3,)]
    (p / "mask" / "c" / "1" / "0" / "0").unlink()
    with pytest.raises(StoreError, match=r"f\.zarr: array 'mask' has 2 of the 3 chunk files"):
        open_store(p, "frames")


def test_every_array_is_written_with_the_chunk_checksum(tmp_path):
    """Each array's own zarr.json (read as JSON) ends in zstd with checksum: the 1-D timestamps
    as well as the per-frame images."""
    import json

    _frames(tmp_path / "f.zarr", [0, 1])
    metas = sorted((tmp_path / "f.zarr").glob("*/zarr.json"))
    assert [m.parent.name for m in metas] == ["color", "depth", "timestamps"]
    for m in metas:
        assert json.loads(m.read_text())["codecs"][-1] == {"name": "zstd", "configuration": {"level": 0, "checksum": True}}


def test_arrays_of_another_dtype_or_axis_length_are_refused(tmp_path):
    """open_store re-checks the arrays: depth rewritten in place as uint8 (same kind as the
    declared uint16, but no room for millimetres above 255) is refused; create_store refuses
    template vertices with 4 coordinates (the declared axis length is 3)."""
    import zarr

    p = tmp_path / "f.zarr"
    _frames(p, [0, 1])
    g = zarr.open_group(str(p), mode="r+")
    g.create_array("depth", shape=(2, 2, 3), dtype="uint8", overwrite=True)[...] = 7  # 2 chunk files, as before
    with pytest.raises(StoreError, match=r"f\.zarr: array 'depth' has dtype uint8, expected uint16"):
        open_store(p, "frames")
    with pytest.raises(StoreError, match=r"s\.zarr: array 'template/vertices' has shape \(5, 4\), expected \('V', 3\)"):
        with create_store(tmp_path / "s.zarr", "scene") as s:
            s.write("template/vertices", np.zeros((5, 4)))


def test_a_live_writer_on_this_host_keeps_its_folder(tmp_path):
    """Only dead writers' left-overs are removed: the partial folder named with this host and a
    live process id (this test's parent process) is left to its writer."""
    import socket

    live = tmp_path / f"f.zarr.partial-{socket.gethostname().replace('-', '_')}-{os.getppid()}"
    live.mkdir()
    _frames(tmp_path / "f.zarr", [0])
    assert live.is_dir() and open_store(tmp_path / "f.zarr", "frames").attrs["frame_ids"] == [0]


def test_the_versions_recorded_are_the_installed_ones(tmp_path):
    """stex_version is pyproject.toml's version; libraries holds the version each library
    reports itself (numba, llvmlite, zarr, scikit-image, pyamg, trimesh, pillow, av), and only
    installed libraries: every value is a version string."""
    import tomllib

    import av
    import llvmlite
    import numba
    import PIL
    import pyamg
    import skimage
    import trimesh
    import zarr

    _frames(tmp_path / "f.zarr", [0])
    attrs = open_store(tmp_path / "f.zarr", "frames").attrs
    assert attrs["stex_version"] == tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    libs = attrs["libraries"]
    assert {k: libs.get(k) for k in ("numba", "llvmlite", "zarr", "scikit-image", "pyamg", "trimesh", "pillow", "av")} == {
        "numba": numba.__version__, "llvmlite": llvmlite.__version__, "zarr": zarr.__version__,
        "scikit-image": skimage.__version__, "pyamg": pyamg.__version__, "trimesh": trimesh.__version__,
        "pillow": PIL.__version__, "av": av.__version__}
    assert all(isinstance(v, str) and v for v in libs.values())


def test_id_ranges_and_position_range_by_hand():
    """id_ranges: runs of consecutive ids as [first, last + 1] ([0, 1, 2, 5, 6] -> [[0, 3], [5, 7]],
    its docstring's example; [4, 6, 7] -> [[4, 5], [6, 8]]). position_range: [start, stop) within
    the frames, the last block [7, 10) of 10 frames included; [0, 11), [-1, 2), [3, 3) refused."""
    assert id_ranges([0, 1, 2, 5, 6]) == [[0, 3], [5, 7]]
    assert id_ranges([4, 6, 7]) == [[4, 5], [6, 8]]
    assert position_range([7, 10], 10, "slice") == (7, 10)
    for bad in ([0, 11], [-1, 2], [3, 3]):
        with pytest.raises(ValueError, match=r"slice range .* outside the 10 frames"):
            position_range(bad, 10, "slice")


def test_run_block_paths_lists_every_block_of_the_scene_and_no_stale_one(tmp_path):
    """A scene of 10 frames in blocks [0, 4), [4, 8), [8, 10): block_0000..block_0002 of the
    kind, in order; a block_0003 left by an earlier run with other blocks is not listed."""
    with create_store(tmp_path / "scene.zarr", "scene", attrs={"frame_blocks": [[0, 4], [4, 8], [8, 10]]}):
        pass
    (tmp_path / "volume" / "block_0003.zarr").mkdir(parents=True)
    assert run_block_paths(tmp_path, "volume") == [tmp_path / "volume" / f"block_{b:04d}.zarr" for b in range(3)]


def test_frame_attr_is_the_entry_of_the_frame_in_its_own_block(tmp_path):
    """Per-frame list attrs (e.g. masks' support_planes) of blocks [0, 1, 2] and [3, 4]: frame f
    gets entry f - (its block's first frame) of its own block's list; the default without it."""
    import zarr

    for name, ids in (("b0.zarr", [0, 1, 2]), ("b1.zarr", [3, 4])):
        _frames(tmp_path / name, ids)
        zarr.open_group(str(tmp_path / name), mode="r+").attrs["planes"] = [f"plane of {i}" for i in ids]
    seq = FrameSequence([tmp_path / "b0.zarr", tmp_path / "b1.zarr"], "frames")
    assert [seq.frame_attr("planes", f) for f in range(5)] == [f"plane of {f}" for f in range(5)]
    assert seq.frame_attr("other", 4, default="none") == "none"


def test_docs_page_is_generated_from_the_registry():
    doc = (REPO / "docs" / "artifacts.md").read_text()
    assert doc == artifacts_markdown(), "regenerate: python -m stex.artifacts > docs/artifacts.md"
    for name, spec in ARTIFACTS.items():
        assert f"`{name}`" in doc
        for aname in spec.arrays:
            assert f"`{aname}`" in doc
