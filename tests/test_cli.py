import shutil

import numpy as np
import pytest

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
    # the versions the store was written with, for figures compared across installs
    assert "written with python " in out and f"numpy {np.__version__}" in out
    assert main(["inspect", str(tmp_path / "missing.zarr")]) == 1
    assert "missing.zarr" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# stex export / stex preview, end to end on the tiny cube scene of test_export
# --------------------------------------------------------------------------------------------

import av  # noqa: E402
import trimesh  # noqa: E402
from PIL import Image  # noqa: E402
from test_export import FRAME_IDS, gradient_texture, make_results  # noqa: E402


def test_version_prints_the_package_version(capsys):
    from stex import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"stex {__version__}"


def test_inspect_a_run_folder_summarises_every_store(tmp_path, capsys):
    """`stex inspect results/<scene>`: one entry per store of the run (its own stores and the
    frame-block ones), with kind, complete or partial, size on disk, frames and main arrays; a
    store a killed writer left behind shows as partial, and a single store still reads alone."""
    import zarr

    res = make_results(tmp_path / "results" / "cube")
    assert main(["inspect", str(res)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith(f"{res}: run of 5 frames in 2 block(s)")
    stores = sorted(p.relative_to(res).as_posix() for p in res.rglob("*.zarr"))
    assert len(stores) >= 6 and f"{len(stores)} stores" in lines[0]
    for name in stores:
        row = next(line for line in lines if line.split() and line.split()[0] == name)
        kind = zarr.open_group(str(res / name), mode="r").attrs["stex_artifact"]
        assert row.split()[1] == kind and row.split()[2] == "complete", row
        assert any(u in row for u in (" B ", " KB ", " MB ")), row
    block = next(line for line in lines if line.split() and line.split()[0] == "corrected/block_0001.zarr")
    assert "frames 13..14 (2)" in block
    tracking = lines[lines.index(next(line for line in lines if line.split()[:1] == ["tracking.zarr"])) + 1]
    assert "vertices (5, " in tracking and "float32" in tracking
    # a writer's unfinished store, and a store marked incomplete, are partial
    shutil.copytree(res / "corrected" / "block_0001.zarr", res / "corrected" / "block_0002.zarr.partial-h-1")
    zarr.open_group(str(res / "volume" / "block_0000.zarr"), mode="r+").attrs["complete"] = False
    assert main(["inspect", str(res)]) == 0
    lines = capsys.readouterr().out.splitlines()
    states = {line.split()[0]: line.split()[2] for line in lines[1:] if ".zarr" in line.split()[0]}
    assert states["corrected/block_0002.zarr.partial-h-1"] == "partial"
    assert states["volume/block_0000.zarr"] == "partial"
    assert states["corrected/block_0001.zarr"] == "complete"
    assert main(["inspect", str(res / "tracking.zarr")]) == 0
    assert "artifact 'tracking'" in capsys.readouterr().out


def _video_frames(path):
    with av.open(str(path)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


def test_export_every_kind_end_to_end(tmp_path, capsys):
    res = make_results(tmp_path / "results" / "cube")
    out = tmp_path / "out"
    assert main(["export", str(res), "--what", "png", "--frames", "12:14", "--source", "volume",
                 "--out", str(out / "png")]) == 0
    assert sorted(p.name for p in (out / "png").iterdir()) == ["texture_00012.png", "texture_00013.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(out / "png" / "texture_00013.png")), gradient_texture(3))
    captured = capsys.readouterr()
    assert "frame 2/2" in captured.err and "wrote 2 png" in captured.out

    assert main(["export", str(res), "--what", "obj", "--frames", "10", "--out", str(out / "obj")]) == 0
    assert sorted(p.name for p in (out / "obj").iterdir()) == ["frame_00010.mtl", "frame_00010.obj", "frame_00010.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(out / "obj" / "frame_00010.png")), gradient_texture(100))
    assert len(trimesh.load(out / "obj" / "frame_00010.obj", process=False).faces) == 12

    assert main(["export", str(res), "--what", "gltf", "--frames", "13:", "--out", str(out / "glb")]) == 0
    assert sorted(p.name for p in (out / "glb").iterdir()) == ["frame_00013.glb", "frame_00014.glb"]

    assert main(["export", str(res), "--what", "mp4", "--fps", "10", "--out", str(out / "mp4")]) == 0
    frames = _video_frames(out / "mp4" / "texture.mp4")
    assert len(frames) == len(FRAME_IDS) and frames[0].shape == (64, 64, 3)


def test_export_every_nth_frame_and_the_global_texture(tmp_path, capsys):
    from test_export import add_global_texture

    res = add_global_texture(make_results(tmp_path / "results" / "cube"))
    out = tmp_path / "out"
    assert main(["export", str(res), "--what", "gltf", "--every", "2", "--out", str(out / "glb")]) == 0
    assert sorted(p.name for p in (out / "glb").iterdir()) == [
        "frame_00010.glb", "frame_00012.glb", "frame_00014.glb"]
    assert "wrote 3 gltf" in capsys.readouterr().out
    assert main(["export", str(res), "--what", "png", "--source", "global", "--out", str(out / "g")]) == 0
    np.testing.assert_array_equal(np.asarray(Image.open(out / "g" / "global_texture.png")), gradient_texture(50))
    with pytest.raises(SystemExit):
        main(["export", str(res), "--what", "png", "--every", "0", "--out", str(out / "x")])
    assert "--every: must be 1 or more, got 0" in capsys.readouterr().err
    assert main(["export", str(res), "--what", "mp4", "--source", "global", "--out", str(out / "v")]) == 1
    assert "error: the global texture is one image for the whole sequence, not a video" in capsys.readouterr().err


def test_view_end_to_end(tmp_path, capsys):
    import json

    res = make_results(tmp_path / "results" / "cube")
    out = tmp_path / "view"
    assert main(["view", str(res), "--every", "2", "--source", "volume", "--out", str(out)]) == 0
    assert "python -m http.server" in capsys.readouterr().out
    view = json.loads((out / "view.json").read_text())
    assert [f["id"] for f in view["frames"]] == [10, 12, 14] and view["labels"]
    assert (out / "index.html").is_file() and (out / "three" / "LICENSE").is_file()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["view", str(res), "--out", str(tmp_path / "other")]) == 1
    assert "holds other files" in capsys.readouterr().err


def test_preview_end_to_end(tmp_path, capsys):
    res = make_results(tmp_path / "cube")
    out = tmp_path / "preview.mp4"
    assert main(["preview", str(res), "--frames", "11:14", "--size", "48", "--out", str(out)]) == 0
    frames = _video_frames(out)
    assert len(frames) == 3 and frames[0].shape == (48, 3 * 64, 3)  # 80x60 colour scaled to 64x48
    assert "3 frames" in capsys.readouterr().out


def test_export_errors_are_one_line_and_status_1(tmp_path, capsys):
    res = make_results(tmp_path / "cube", corrected=False)
    out = str(tmp_path / "out")
    assert main(["export", str(res), "--what", "png", "--frames", "12:99", "--source", "volume", "--out", out]) == 1
    err = capsys.readouterr().err
    assert "error: frame range 12:99 is outside the sequence (frames 10..14)" in err
    assert main(["export", str(res), "--what", "png", "--frames", "x", "--source", "volume", "--out", out]) == 1
    assert "START:STOP" in capsys.readouterr().err
    # corrected (the default source) was not written
    assert main(["export", str(res), "--what", "png", "--out", out]) == 1
    err = capsys.readouterr().err
    assert "corrected/block_0000.zarr: no such store (has the 'corrected' stage run?)" in err
    shutil.rmtree(res / "volume" / "block_0001.zarr")
    assert main(["export", str(res), "--what", "png", "--source", "volume", "--out", out]) == 1
    assert "volume/block_0001.zarr: no such store" in capsys.readouterr().err
    make_results(res, corrected=False)
    shutil.rmtree(res / "tracking.zarr")
    assert main(["export", str(res), "--what", "gltf", "--source", "volume", "--out", out]) == 1
    assert "tracking.zarr: no such store" in capsys.readouterr().err
    assert main(["preview", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p.mp4")]) == 1
    assert "nowhere: no such results folder" in capsys.readouterr().err
    assert not (tmp_path / "p.mp4").exists()
    # output paths are checked before any work: a folder where a file goes, and the reverse
    afile = tmp_path / "afile"
    afile.write_text("x")
    stores = tmp_path / "stores"
    shutil.copytree(res / "template.zarr", stores / "template.zarr")
    for argv, message in [(["preview", str(res), "--out", str(tmp_path / "pdir") + "/"], "is a folder; give a .mp4 file"),
                          (["preview", str(res), "--out", str(tmp_path / "p.avi")], "give a .mp4 file name"),
                          (["export", str(res), "--what", "png", "--source", "volume", "--out", str(afile)],
                           "is a file; give a folder"),
                          (["evaluate", str(res), "--out", str(afile)], "is a file; give a folder"),
                          (["inspect", str(afile)], "afile: not a stex store (give a store a run writes"),
                          # a folder of stores that is no run's (a run's folder is summarised: see
                          # test_inspect_a_run_folder_summarises_every_store)
                          (["inspect", str(stores)], "not a stex store (a folder of stores: template.zarr")]:
        assert main(argv) == 1, argv
        assert message in capsys.readouterr().err, argv
    assert afile.read_text() == "x" and not (tmp_path / "pdir").exists()
    assert list(tmp_path.glob(".*partial*")) == []


@pytest.mark.parametrize("chunk,array,how", [
    ("tracking.zarr/vertices/c/2/0/0", "vertices", "overwritten"),
    ("template.zarr/faces/c/0/0", "faces", "cut"),
    ("corrected/block_0000.zarr/texture/c/1/0/0/0", "texture", "overwritten"),
    ("corrected/block_0000.zarr/texture/c/1/0/0/0", "texture", "cut"),
])
def test_export_of_a_run_with_a_damaged_chunk_is_one_line_and_status_1(tmp_path, capsys, chunk, array, how):
    """A chunk cut short or damaged in place (same size) in a finished run: `stex export` says so
    in one line naming the store, the array and the chunk file, and writes nothing."""
    from test_io import damage

    res = make_results(tmp_path / "cube")
    damage(res / chunk, how)
    store, _, key = chunk.partition(f"/{array}/")
    out = tmp_path / "out"
    assert main(["export", str(res), "--what", "obj", "--out", str(out)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {res / store}: array '{array}'"), err
    assert f"cannot be read (chunk file {array}/{key}: " in err[0] and "re-run the stage" in err[0], err
    assert not out.exists() or list(out.iterdir()) == []


def test_an_interrupted_export_leaves_no_file_under_its_final_name(tmp_path, monkeypatch):
    """A sequence of PNG, OBJ/MTL or glTF files is written in a hidden folder and moved into
    place when all are complete: an export stopped inside a write (here a KeyboardInterrupt after
    one whole slice and half of the next) leaves neither the whole slice, which would look like a
    complete export of fewer frames, nor a truncated one, nor the temporary folder."""
    import cv2

    from stex import export

    real = cv2.imwrite
    calls = []

    def half_then_stop(path, img):
        real(path, img)
        calls.append(path)
        if len(calls) == 2:
            with open(path, "r+b") as fh:
                fh.truncate(100)
            raise KeyboardInterrupt
        return True

    monkeypatch.setattr(export.cv2, "imwrite", half_then_stop)
    tex = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(KeyboardInterrupt):
        export.write_png_slices([tex, tex], [3, 4], tmp_path)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# stex tables: the paper-style tables over runs
# --------------------------------------------------------------------------------------------

def _fake_run(d, scene, psnr, held_out=(), sampling=None):
    """A results/<scene> folder with an evaluation.json of 4 frames (ours at ``psnr`` dB, the
    global texture 2 dB below; no flicker, stored as null; ``sampling``: its sampling-table
    rows) and one job's benchmark file."""
    import json
    import math

    from stex.evaluation import summarise_frames
    from stex.reporting import finite_or_none

    records = [{"frame": t, "position": t, "held_out": t in held_out, "motion_mm": 1.0,
                "methods": {"ours": {"psnr": psnr + 0.1 * t, "flicker": math.nan},
                            "global": {"psnr": psnr - 2}}} for t in range(4)]
    summary = summarise_frames(records, methods=("ours", "global"))
    summary.update(n_held_out=len(held_out), held_out_label="(1/2)" if held_out else "")
    (d / "evaluation").mkdir(parents=True)
    (d / "evaluation" / "evaluation.json").write_text(
        json.dumps(finite_or_none({"scene": scene, "summary": summary, "sampling": sampling})))
    (d / "benchmarks").mkdir()
    (d / "benchmarks" / "labeling.tsv").write_text("s\th:m:s\n120.0\t0:02:00\n")
    return d


def _sampling(ratios):
    return [{"step": n, "keyframes": 12 // n, "energy": r, "seconds": 60.0 / n, "error_ratio": r,
             "speedup": float(n)} for n, r in zip((1, 2, 4), ratios)]


def test_tables_over_runs(tmp_path, capsys):
    a = _fake_run(tmp_path / "demo", "demo", 30.0, sampling=_sampling((1.0, 1.02, 1.04)))
    other = _fake_run(tmp_path / "paper", "paper", 20.0, sampling=_sampling((1.0, 1.0, 1.08)))
    assert main(["tables", str(a), str(other)]) == 0
    rst = capsys.readouterr().out
    # the sampling table: a row per run and measure, and the mean over the runs as the paper's
    assert "| demo: error ratio " in rst and "| paper: speed-up " in rst
    mean = next(line for line in rst.splitlines() if "mean error ratio over the runs" in line)
    assert mean.split("|")[2:5] == [" 1.0000 ", " 1.0100 ", " 1.0600 "]
    shutil.rmtree(other)
    b = _fake_run(tmp_path / "demo_heldout", "demo_heldout", 25.0, held_out=(1, 3))
    assert main(["tables", str(a), str(b)]) == 0
    rst = capsys.readouterr().out
    header = next(line for line in rst.splitlines() if "demo_heldout" in line)
    assert header.index("demo ") < header.index("demo_heldout")          # a column per run
    ours = next(line for line in rst.splitlines() if "| Ours " in line)
    assert "30.15" in ours and "25.15" in ours                            # mean over the 4 frames
    held = next(line for line in rst.splitlines() if "Ours (1/2)" in line)
    assert "25.20" in held and "–" in held                                # frames 1, 3; demo has none
    assert "Computation time" in rst and "2.00" in rst                    # labeling 120 s
    out = tmp_path / "tables.html"
    assert main(["tables", str(a), str(b), "--out", str(out)]) == 0
    assert b"<table" in out.read_bytes() and "wrote" in capsys.readouterr().out
    # errors: one line, status 1, naming the folder
    assert main(["tables", str(a), str(tmp_path / "nothing")]) == 1
    assert "nothing/evaluation/evaluation.json: no evaluation" in capsys.readouterr().err
    assert main(["tables", str(a), str(a)]) == 1
    assert "second run of scene 'demo'" in capsys.readouterr().err
    assert main(["tables", str(a), "--out", str(tmp_path / "t.txt")]) == 1
    assert ".rst or .html" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# guards an adversarial review of the CLI asked for
# --------------------------------------------------------------------------------------------

def test_evaluate_never_replaces_a_folder_that_is_not_an_evaluation(tmp_path, capsys):
    res = make_results(tmp_path / "cube")
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "thesis.tex").write_text("x")
    for out in (precious, res, res / "corrected"):
        assert main(["evaluate", str(res), "--out", str(out)]) == 1
        assert "is not an evaluation folder" in capsys.readouterr().err
    assert (precious / "thesis.tex").read_text() == "x"
    assert (res / "scene.zarr").is_dir() and (res / "corrected" / "block_0000.zarr").is_dir()
    # an earlier evaluation's folder may be replaced
    from stex.stages.evaluation import check_replaceable

    earlier = tmp_path / "earlier"
    earlier.mkdir()
    for name in ("evaluation.json", "per_frame.csv", "table_coverage.csv", "tables.rst", "side_by_side.png"):
        (earlier / name).write_text("{}")
    check_replaceable(earlier)
    (earlier / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"holds \['notes.txt'\]"):
        check_replaceable(earlier)


def test_interrupt_and_errors_after_a_progress_line(tmp_path, capsys, monkeypatch):
    from stex import cli

    def stop(args):
        cli._Counter("export png")(1, 3)
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_run_export", stop)
    res = make_results(tmp_path / "cube")
    assert main(["export", str(res), "--what", "png", "--out", str(tmp_path / "o")]) == 130
    assert capsys.readouterr().err.splitlines()[-1] == "interrupted"
    # an output under a file, and a frame rate no encoder takes: refused before any work
    afile = tmp_path / "afile"
    afile.write_text("x")
    monkeypatch.undo()
    assert main(["export", str(res), "--what", "mp4", "--out", str(afile / "x")]) == 1
    assert f"{afile} is a file, not a folder" in capsys.readouterr().err
    assert main(["export", str(res), "--what", "mp4", "--fps", "1e12", "--out", str(tmp_path / "v")]) == 1
    assert "fps must be 0.01 .. 1000" in capsys.readouterr().err
    with pytest.raises(SystemExit):                 # argparse: usage and status 2
        main(["preview", str(res), "--size", "100000", "--out", str(tmp_path / "p.mp4")])
    assert "must be 16..4096" in capsys.readouterr().err
    assert main(["export", str(res / "scene.zarr"), "--what", "png", "--out", str(tmp_path / "o")]) == 1
    assert "a store, not a results folder" in capsys.readouterr().err
    assert main(["inspect", str(res / "template.zarr" / "faces")]) == 1
    assert "an array inside a store, not a store" in capsys.readouterr().err


def test_obj_export_writes_the_obj_last(tmp_path, monkeypatch):
    """The .obj names the .mtl: if the .mtl cannot be written there is no .obj; and an export that
    fails at its second frame leaves none of the first frame's files."""
    from stex import export
    from stex.stages.export import export_results

    one = tmp_path / "one"
    one.mkdir()
    (one / ".f.partial.mtl").mkdir()                # the .mtl cannot be written
    tri = np.array([[0, 1, 2]])
    with pytest.raises(OSError):
        export.write_obj_frame(one / "f.obj", np.eye(3), tri, np.eye(3)[:, :2], tri, "f.png")
    assert not (one / "f.obj").exists()

    res = make_results(tmp_path / "cube")
    out = tmp_path / "objx"
    real, calls = export.write_obj_frame, []

    def second_fails(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(f"cannot write {path}")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(export, "write_obj_frame", second_fails)
    with pytest.raises(OSError):
        export_results(res, "obj", out)
    assert len(calls) == 2 and list(out.iterdir()) == []
    monkeypatch.setattr(export, "write_obj_frame", real)
    written = export_results(res, "obj", out)
    assert [p.parent for p in written] == [out] * len(written) and all(p.exists() for p in written)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_tables_read_an_evaluation_folder_and_refuse_malformed_ones(tmp_path, capsys):
    import json

    run = _fake_run(tmp_path / "demo", "demo", 30.0)
    own = tmp_path / "eval_mine"
    shutil.copytree(run / "evaluation", own)        # as `stex evaluate --out eval_mine` writes
    assert main(["tables", str(run), str(own)]) == 0
    header = next(line for line in capsys.readouterr().out.splitlines() if "eval_mine" in line)
    assert "demo" in header
    for doc in ([], {"summary": 3}, {"summary": {}}):
        (own / "evaluation.json").write_text(json.dumps(doc))
        assert main(["tables", str(own)]) == 1
        assert "not an evaluation.json" in capsys.readouterr().err
    (run / "benchmarks" / "labeling.tsv").write_text("x\n1\n")
    assert main(["tables", str(run)]) == 1
    assert "labeling.tsv: not a Snakemake benchmark file" in capsys.readouterr().err
