"""Folder datasets (stex.readers.folder) in the authors' layout and in stex's layout, and their ingest.

Small datasets are written to disk from the synthetic scene generator (realistic colour, depth,
masks and deforming meshes with a texture atlas), read back, ingested, and compared with what
was written. Bad inputs must fail with a message naming the file or frame.
"""

import json
import re
import shutil
import warnings
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import trimesh

from conftest import data_samples
from stex.config import load_config
from stex.ingest import FolderSource
from stex.stages.ingest import write_frames_block, write_scene
from stex.io import open_store
from stex.readers.folder import FolderDataset
from stex.readers.meshes import load_mesh
from stex.synth.scene import SyntheticScene

SYN = {
    "n_frames": 4,
    "color": {"width": 160, "height": 120, "fx": 140.0},
    "depth": {"width": 80, "height": 72, "fx": 63.0},
    "procedural": {"n_around": 24, "n_rings": 12},
    "texture_size": 64,
}
N = SYN["n_frames"]
FIRST = 7  # absolute index of the first frame on disk (datasets rarely start at 0)
IDS = list(range(FIRST, FIRST + N))


# -- the synthetic content ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def synth():
    cfg = load_config(overrides={"source": {"synthetic": SYN}})["source"]["synthetic"]
    scene = SyntheticScene(cfg)
    renders = [scene.render_frame(i) for i in range(N)]
    return SimpleNamespace(
        cal=scene.calibration,
        faces=scene.faces, texcoords=scene.texcoords, texcoord_faces=scene.texcoord_faces,
        color=[r.color for r in renders], depth=[r.depth_mm for r in renders],
        mask=[r.true_mask for r in renders], verts=[scene.given_vertices(i) for i in range(N)],
    )


def _write_obj(path: Path, V, F, tc=None, tf=None) -> None:
    """A plain OBJ written here (not with stex's writer): full precision, OBJ's v pointing up."""
    lines = ["# test mesh"] + [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(V).tolist()]
    if tc is not None:
        lines += [f"vt {u!r} {1.0 - v!r}" for u, v in np.asarray(tc).tolist()]
        lines += ["f " + " ".join(f"{a + 1}/{b + 1}" for a, b in zip(f, t))
                  for f, t in zip(np.asarray(F).tolist(), np.asarray(tf).tolist())]
    else:
        lines += ["f " + " ".join(str(a + 1) for a in f) for f in np.asarray(F).tolist()]
    path.write_text("\n".join(lines) + "\n")


def _write_off(path: Path, V, F) -> None:
    trimesh.Trimesh(np.asarray(V), np.asarray(F), process=False).export(path)


def _intr(cam) -> dict:
    return {k: v for k, v in cam.to_dict().items() if k != "distortion"}


def _conf(s, tex_mesh_path="tex_mesh.obj", **mapper) -> dict:
    m = {
        "layer_number": 4,
        "color_intrinsic": _intr(s.cal.color),
        "depth_intrinsic": _intr(s.cal.depth),
        # 3x4 row-major, rounded to 8 digits as in the authors' files
        "d_c_extrinsic": [round(x, 8) for x in s.cal.depth_to_color[:3].ravel().tolist()],
    }
    m.update(mapper)
    main = {"start_idx": FIRST, "end_idx": FIRST + N - 1, "data_root_path": "./", "is_viewer": False}
    if tex_mesh_path:
        main["tex_mesh_path"] = tex_mesh_path
    # a first case without cameras: the reader takes the case that has a mapper4D section
    return {"case_other": {"main": {"start_idx": 0}}, "case_test": {"main": main, "mapper4D": m}}


def make_authors(root: Path, s, masks=True, meshes=True, template=True) -> Path:
    (root / "stream" / "color").mkdir(parents=True)
    (root / "stream" / "depth").mkdir()
    (root / "conf.json").write_text(json.dumps(_conf(s, "tex_mesh.obj" if template else None), indent=1))
    if masks:
        (root / "stream" / "mask").mkdir()
    if meshes:
        (root / "mesh").mkdir()
    for k, fid in enumerate(IDS):
        bgr = s.color[k][..., ::-1]
        if k == 1:  # BGRA on disk is fine too
            bgr = np.dstack([bgr, np.full(bgr.shape[:2], 255, np.uint8)])
        assert cv2.imwrite(str(root / "stream" / "color" / f"Frame_{fid:06d}.png"), bgr)
        assert cv2.imwrite(str(root / "stream" / "depth" / f"Frame_{fid:06d}.png"), s.depth[k])
        if masks:  # foreground >= 1: frame 2 uses 1, the others 255
            m = s.mask[k].astype(np.uint8) * (1 if k == 2 else 255)
            assert cv2.imwrite(str(root / "stream" / "mask" / f"Frame_{fid:06d}.png"), m)
        if meshes:  # RELATIVE 3-digit index
            _write_off(root / "mesh" / f"Frame_{k:03d}.off", s.verts[k], s.faces)
    if template:
        _write_obj(root / "tex_mesh.obj", s.verts[0], s.faces, s.texcoords, s.texcoord_faces)
    return root


def make_stex(root: Path, s, masks=True, meshes=True, template=True) -> Path:
    for d in ("color", "depth") + (("mask",) if masks else ()) + (("meshes",) if meshes else ()):
        (root / d).mkdir(parents=True)
    (root / "calibration.json").write_text(json.dumps(s.cal.to_dict(), indent=1))
    for k, fid in enumerate(IDS):
        assert cv2.imwrite(str(root / "color" / f"{fid:06d}.png"), s.color[k][..., ::-1])  # RGB image file
        assert cv2.imwrite(str(root / "depth" / f"{fid:06d}.png"), s.depth[k])
        if masks:
            assert cv2.imwrite(str(root / "mask" / f"{fid:06d}.png"), s.mask[k].astype(np.uint8) * 255)
        if meshes:  # absolute 6-digit index
            _write_obj(root / "meshes" / f"{fid:06d}.obj", s.verts[k], s.faces)
    if template:
        _write_obj(root / "template.obj", s.verts[0], s.faces, s.texcoords, s.texcoord_faces)
    return root


@pytest.fixture(scope="module")
def datasets(tmp_path_factory, synth):
    base = tmp_path_factory.mktemp("datasets")
    return {"authors": make_authors(base / "authors", synth), "stex": make_stex(base / "stex", synth)}


@pytest.fixture
def authors(tmp_path, datasets) -> Path:
    """A private copy of the authors'-layout dataset, free to damage."""
    return Path(shutil.copytree(datasets["authors"], tmp_path / "ds"))


@pytest.fixture
def stex_ds(tmp_path, datasets) -> Path:
    return Path(shutil.copytree(datasets["stex"], tmp_path / "ds"))


def folder_cfg(root, layout="authors", **kw) -> dict:
    return load_config(overrides={"source": {"kind": "folder",
                                             "folder": {"path": str(root), "layout": layout, **kw}}})["source"]


def _check_calibration(cal, s, atol):
    for name in ("color", "depth"):
        a, b = getattr(cal, name), getattr(s.cal, name)
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.K, b.K, atol=atol)
        assert not a.distortion.any()
    np.testing.assert_allclose(cal.depth_to_color, s.cal.depth_to_color, atol=atol)
    R = cal.depth_to_color[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


# -- reading ------------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_reader_returns_what_was_written(datasets, synth, layout):
    s = synth
    ds = FolderDataset(datasets[layout], layout)
    assert ds.frame_ids == IDS and len(ds) == N and ds.has_masks
    _check_calibration(ds.calibration, s, 1e-6 if layout == "authors" else 0)
    for k, fid in enumerate(IDS):
        c = ds.color(fid)
        assert c.dtype == np.uint8 and c.shape == (120, 160, 3)
        np.testing.assert_array_equal(c, s.color[k])  # RGB order, not the BGR on disk
        assert (s.color[k][..., 0] != s.color[k][..., 2]).any()
        d = ds.depth(fid)
        assert d.dtype == np.uint16
        np.testing.assert_array_equal(d, s.depth[k])
        m = ds.mask(fid)
        assert m.dtype == bool
        np.testing.assert_array_equal(m, s.mask[k])
        mesh = ds.load_given_mesh(fid)
        assert mesh is not None
        np.testing.assert_allclose(mesh.vertices, s.verts[k], atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, s.faces)
    expected = f"Frame_{N - 1:03d}.off" if layout == "authors" else f"{IDS[-1]:06d}.obj"
    assert ds.mesh_path(IDS[-1]).name == expected


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_template_obj_texcoords_are_flipped_at_import(datasets, synth, layout):
    s = synth
    src = FolderSource(folder_cfg(datasets[layout], layout)["folder"])
    path = src.ds.template_path()
    assert path.name == ("tex_mesh.obj" if layout == "authors" else "template.obj")
    t = src.template()
    np.testing.assert_allclose(t.vertices, s.verts[0], atol=1e-6)
    np.testing.assert_array_equal(t.faces, s.faces)
    np.testing.assert_array_equal(t.texcoord_faces, s.texcoord_faces)
    np.testing.assert_allclose(t.texcoords, s.texcoords, atol=1e-12)  # stex: v down
    raw_vt = np.array([[float(x) for x in ln.split()[1:3]] for ln in path.read_text().splitlines()
                       if ln.startswith("vt ")])
    np.testing.assert_allclose(t.texcoords[:, 1], 1.0 - raw_vt[:, 1], atol=1e-12)  # OBJ: v up
    assert np.abs(raw_vt[:, 1] - t.texcoords[:, 1]).max() > 0.1


def test_authors_default_template_is_first_mesh_off(tmp_path, synth):
    s = synth
    root = make_authors(tmp_path / "ds", s, template=False)
    src = FolderSource(folder_cfg(root)["folder"])
    assert src.ds.template_path() == root / "mesh" / "Frame_000.off"
    t = src.template()
    np.testing.assert_allclose(t.vertices, s.verts[0], atol=1e-6)
    np.testing.assert_array_equal(t.faces, s.faces)
    assert t.texcoords is None and t.texcoord_faces is None
    # an explicit template (relative to the root) wins
    _write_obj(root / "other.obj", s.verts[1], s.faces, s.texcoords, s.texcoord_faces)
    src = FolderSource(folder_cfg(root, template="other.obj")["folder"])
    np.testing.assert_allclose(src.template().vertices, s.verts[1], atol=1e-6)
    with pytest.raises(FileNotFoundError, match="template mesh not found: .*nope.obj"):
        FolderSource(folder_cfg(root, template="nope.obj")["folder"]).template()


def test_start_stop_select_frames_and_authors_mesh_index_stays_relative_to_start_idx(datasets, synth):
    s = synth
    ds = FolderDataset(datasets["authors"], "authors", start=FIRST + 2)
    assert ds.frame_ids == IDS[2:]
    # Frame_000 belongs to conf.json's start_idx, not to the first frame read
    assert ds.mesh_path(FIRST + 2).name == "Frame_002.off"
    np.testing.assert_allclose(ds.load_given_mesh(FIRST + 2).vertices, s.verts[2], atol=1e-6)
    src = FolderSource(folder_cfg(datasets["authors"], start=FIRST + 1, stop=FIRST + 3)["folder"])
    assert src.frame_ids == IDS[1:3]
    np.testing.assert_allclose(src.given_vertices(0), s.verts[1], atol=1e-6)
    np.testing.assert_array_equal(next(iter(src.frames(1, 2)))[1], s.color[2])
    ds = FolderDataset(datasets["stex"], "stex", start=FIRST + 1, stop=FIRST + 2)
    assert ds.frame_ids == [FIRST + 1]
    with pytest.raises(ValueError, match=r"no colour frames in \[100, None\)"):
        FolderDataset(datasets["stex"], "stex", start=100)


def test_without_masks_meshes_or_template(tmp_path, synth):
    root = make_stex(tmp_path / "ds", synth, masks=False, meshes=False, template=False)
    src = FolderSource(folder_cfg(root, "stex")["folder"])
    assert not src.ds.has_masks
    assert src.template() is None and src.given_vertices(0) is None
    pos, c, d, m, ts, extra = next(iter(src.frames(0, 1)))
    assert pos == 0 and m is None
    np.testing.assert_array_equal(c, synth.color[0])
    cfg = folder_cfg(root, "stex")
    write_scene(cfg, 2, tmp_path / "scene.zarr")
    g = open_store(tmp_path / "scene.zarr", "scene")
    assert g.attrs["has_template"] is False and "template/vertices" not in g and "given/vertices" not in g
    write_frames_block(cfg, 0, 2, tmp_path / "f.zarr")
    f = open_store(tmp_path / "f.zarr", "frames")
    assert "mask" not in f
    np.testing.assert_array_equal(f["depth"][:], np.stack(synth.depth[:2]))


def test_stex_layout_default_template_is_first_given_mesh(tmp_path, synth):
    s = synth
    root = make_stex(tmp_path / "ds", s, template=False)
    src = FolderSource(folder_cfg(root, "stex", start=FIRST + 1)["folder"])
    assert src.ds.template_path() == root / "meshes" / f"{FIRST + 1:06d}.obj"
    np.testing.assert_allclose(src.template().vertices, s.verts[1], atol=1e-9)
    assert src.template().texcoords is None
    # the scene job's inputs: the calibration and the given meshes, the first (the template) once
    assert src.files() == [root / "calibration.json"] + [root / "meshes" / f"{i:06d}.obj" for i in IDS[1:]]
    bad = root / "meshes" / f"{FIRST + 3:06d}.obj"
    _write_obj(bad, s.verts[3], s.faces[:, [0, 2, 1]])  # the same triangles turned round (other winding)
    with pytest.raises(ValueError, match=re.escape(bad.name) + r": mesh topology differs from the template \(.*\): "
                       r"its face 0 \[\d+, \d+, \d+\] is among the template's triangles with the other winding"):
        write_scene(folder_cfg(root, "stex"), 2, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()


def test_given_mesh_with_an_extra_vertex_is_refused(tmp_path, stex_ds, synth):
    bad = stex_ds / "meshes" / f"{FIRST + 3:06d}.obj"
    _write_obj(bad, np.vstack([synth.verts[3], [[0.0, 0.0, 1.0]]]), synth.faces)  # one unused extra vertex
    with pytest.raises(ValueError, match=re.escape(bad.name)):
        write_scene(folder_cfg(stex_ds, "stex"), 2, tmp_path / "scene.zarr")


# -- ingest -------------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_ingest_stores_equal_the_files(tmp_path, datasets, synth, layout):
    s = synth
    cfg = folder_cfg(datasets[layout], layout)
    write_scene(cfg, 3, tmp_path / "scene.zarr")
    g = open_store(tmp_path / "scene.zarr", "scene")
    assert g.attrs["frame_ids"] == IDS
    assert g.attrs["frame_blocks"] == [[0, 3], [3, 4]]
    assert g.attrs["source"]["kind"] == "folder" and g.attrs["source"]["layout"] == layout
    assert g.attrs["has_template"] is True
    cal = g.attrs["calibration"]
    np.testing.assert_allclose(cal["depth_to_color"], s.cal.depth_to_color, atol=1e-6)
    assert cal["color"]["fx"] == pytest.approx(s.cal.color.fx) and cal["depth"]["width"] == 80
    np.testing.assert_allclose(g["template/vertices"][:], s.verts[0], atol=1e-6)
    np.testing.assert_array_equal(g["template/faces"][:], s.faces)
    np.testing.assert_allclose(g["template/texcoords"][:], s.texcoords, atol=1e-6)
    np.testing.assert_array_equal(g["template/texcoord_faces"][:], s.texcoord_faces)
    np.testing.assert_allclose(g["given/vertices"][:], np.stack(s.verts), atol=1e-6)
    assert "truth/vertices" not in g

    for b, (start, stop) in enumerate(g.attrs["frame_blocks"]):
        out = tmp_path / "frames" / f"block_{b:04d}.zarr"
        write_frames_block(cfg, start, stop, out)
        f = open_store(out, "frames")
        assert f.attrs["frame_ids"] == IDS[start:stop]
        np.testing.assert_array_equal(f["color"][:], np.stack(s.color[start:stop]))
        np.testing.assert_array_equal(f["depth"][:], np.stack(s.depth[start:stop]))
        np.testing.assert_array_equal(f["mask"][:], np.stack(s.mask[start:stop]))
        # no capture times in a folder dataset: sequence position / source.folder.fps (30 by default)
        np.testing.assert_array_equal(f["timestamps"][:], np.arange(start, stop) / 30.0)
        assert f.attrs["calibration"] == g.attrs["calibration"]


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_source_files_are_what_ingest_reads(datasets, layout):
    root = datasets[layout]
    src = FolderSource(folder_cfg(root, layout)["folder"])
    cal = root / ("conf.json" if layout == "authors" else "calibration.json")
    scene = src.files()
    assert scene[0] == cal and len(scene) == len(set(scene))
    # the template, then every given mesh (the stex layout's template is its own file here)
    assert len(scene) == 2 + N and all(p.is_file() for p in scene)
    block = src.files(1, 3)
    assert block[0] == cal and len(block) == 1 + 2 * 3  # colour, depth, mask of 2 frames
    assert {p.name for p in block[1:]} == ({f"Frame_{i:06d}.png" for i in IDS[1:3]} if layout == "authors"
                                           else {f"{i:06d}.png" for i in IDS[1:3]})


def test_a_dataset_file_changed_after_a_run_reruns_the_ingest_jobs_that_read_it(tmp_path, authors):
    """The dataset's files are the ingest rules' inputs: a frame replaced after a run re-runs its
    block's ingest, a fixed calibration every ingest job, and nothing else is touched. Settings of
    the other source kinds are not the ingest's parameters: changing them re-runs nothing (a new
    ``source.mkv`` key once re-ran every synthetic and folder scene from its ingest on)."""
    import subprocess
    import sys
    import time

    import yaml

    from conftest import REPO

    res = tmp_path / "results" / "ds"
    (tmp_path / "ds.yaml").write_text(yaml.safe_dump({
        "scene": "ds", "results": str(tmp_path / "results"), "frame_block": 2,
        "source": {"kind": "folder", "folder": {"path": str(authors), "layout": "authors"}}}))
    targets = [str(res / "scene.zarr"), str(res / "frames" / "block_0000.zarr"), str(res / "frames" / "block_0001.zarr")]

    def snakemake(*args, configs=()):
        cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path),
               "--configfile", str(tmp_path / "ds.yaml"), *configs, "--cores", "1", *args, *targets]
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
        return run.stdout + run.stderr

    def planned(configs=()):
        out = snakemake("-n", configs=configs)
        return sorted((rule, m.group(1) if (m := re.search(r"block=(\d{4})", body)) else None)
                      for rule, body in re.findall(r"^(?:local)?rule (\w+):\n(.*?)(?=\n\n|\n\[|\Z)", out, re.M | re.S))

    snakemake()
    assert planned() == []
    (tmp_path / "other_kinds.yaml").write_text(yaml.safe_dump({"source": {
        "mkv": {"undistort": False}, "synthetic": {"n_frames": 7}}}))
    assert planned(configs=[str(tmp_path / "other_kinds.yaml")]) == []

    time.sleep(1.1)  # past the outputs' mtimes; Snakemake also compares the contents (a touch alone is no change)
    depth = authors / "stream" / "depth" / f"Frame_{IDS[3]:06d}.png"  # a frame of block 1
    assert cv2.imwrite(str(depth), cv2.imread(str(depth), cv2.IMREAD_UNCHANGED) + np.uint16(1))
    assert planned() == [("ingest_block", "0001")]
    conf = authors / "conf.json"
    conf.write_text(json.dumps(json.loads(conf.read_text()), indent=2))
    assert planned() == [("ingest_block", "0000"), ("ingest_block", "0001"), ("ingest_scene", None)]


def test_folder_source_needs_a_path():
    cfg = load_config(overrides={"source": {"kind": "folder"}})["source"]
    with pytest.raises(ValueError, match="source.folder.path"):
        FolderSource(cfg["folder"])


# -- bad input ----------------------------------------------------------------------------------

def _set_mapper(root: Path, **changes):
    conf = json.loads((root / "conf.json").read_text())
    conf["case_test"]["mapper4D"].update(changes)
    (root / "conf.json").write_text(json.dumps(conf))


def test_missing_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"dataset folder not found: .*nope"):
        FolderDataset(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="dataset folder not found"):
        write_scene(folder_cfg(tmp_path / "nope"), 2, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()


def test_missing_conf_json(authors):
    (authors / "conf.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"conf\.json: missing"):
        FolderDataset(authors)


def test_conf_json_without_mapper4d(authors):
    conf = json.loads((authors / "conf.json").read_text())
    del conf["case_test"]["mapper4D"]
    (authors / "conf.json").write_text(json.dumps(conf))
    with pytest.raises(ValueError, match=r"conf\.json: no case with a 'mapper4D' section"):
        FolderDataset(authors)


def test_conf_json_not_json(authors):
    (authors / "conf.json").write_text("{ not json")
    with pytest.raises(ValueError, match=r"conf\.json: invalid camera settings"):
        FolderDataset(authors)


def test_conf_json_missing_intrinsic_key(authors, synth):
    bad = _intr(synth.cal.color)
    del bad["fy"]
    _set_mapper(authors, color_intrinsic=bad)
    with pytest.raises(ValueError, match=r"conf\.json: invalid camera settings \(color_intrinsic: missing key 'fy'"):
        FolderDataset(authors)


def test_intrinsics_of_another_resolution_and_an_extrinsic_in_millimetres(authors, synth):
    """A principal point outside its image (intrinsics for another resolution) and a depth-to-colour
    translation in millimetres are refused when the calibration is read, naming the camera, not
    later as an empty mask."""
    _set_mapper(authors, depth_intrinsic=dict(_intr(synth.cal.depth), cx=synth.cal.depth.width * 2.0))
    with pytest.raises(ValueError, match=r"conf\.json: .*depth_intrinsic: principal point .* outside the 80x72 image"):
        FolderDataset(authors)
    T = synth.cal.depth_to_color[:3].copy()
    T[:, 3] = [-32.0, -2.0, 4.0]  # mm
    _set_mapper(authors, depth_intrinsic=_intr(synth.cal.depth), d_c_extrinsic=T.ravel().tolist())
    with pytest.raises(ValueError, match=r"conf\.json: .*translation is 32.3 m.*millimetres"):
        FolderDataset(authors)


def test_extrinsic_with_11_numbers(authors, synth):
    _set_mapper(authors, d_c_extrinsic=synth.cal.depth_to_color[:3].ravel().tolist()[:11])
    with pytest.raises(ValueError, match=r"conf\.json: .*d_c_extrinsic needs 12 numbers.*got 11"):
        FolderDataset(authors)


def test_authors_extrinsic_that_is_no_rotation(authors, synth):
    T = synth.cal.depth_to_color[:3].copy()
    T[:3, :3] *= 2.0  # would silently become a rotation if only re-orthonormalised
    _set_mapper(authors, d_c_extrinsic=T.ravel().tolist())
    with pytest.raises(ValueError, match=r"conf\.json: .*not a rotation"):
        FolderDataset(authors)
    T[:3, :3] = -synth.cal.depth_to_color[:3, :3]  # reflection
    _set_mapper(authors, d_c_extrinsic=T.ravel().tolist())
    with pytest.raises(ValueError, match=r"conf\.json: .*not a rotation"):
        FolderDataset(authors)


def test_missing_depth_frame(authors):
    (authors / "stream" / "depth" / f"Frame_{FIRST + 2:06d}.png").unlink()
    with pytest.raises(ValueError, match=rf"depth: depth missing for frame\(s\) \[{FIRST + 2}\]"):
        FolderDataset(authors)


def test_missing_colour_folder(authors):
    shutil.rmtree(authors / "stream" / "color")
    with pytest.raises(FileNotFoundError, match="color: colour folder missing"):
        FolderDataset(authors)


def test_non_consecutive_frames(authors):
    for d in ("color", "depth", "mask"):
        (authors / "stream" / d / f"Frame_{FIRST + 2:06d}.png").unlink()
    with pytest.raises(ValueError, match=rf"not consecutive: frame\(s\) \[{FIRST + 2}\] missing"):
        FolderDataset(authors)


def test_masks_missing_for_some_frames(authors):
    (authors / "stream" / "mask" / f"Frame_{FIRST + 1:06d}.png").unlink()
    with pytest.raises(ValueError, match=rf"mask: masks missing for frame\(s\) \[{FIRST + 1}\]"):
        FolderDataset(authors)


def _truncate(path: Path, keep: float = 0.6) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def test_corrupt_png_fails_ingest_and_leaves_no_store(tmp_path, authors):
    bad = authors / "stream" / "color" / f"Frame_{FIRST + 1:06d}.png"
    _truncate(bad)
    ds = FolderDataset(authors)  # listing works; decoding names the file
    with pytest.raises(ValueError, match=re.escape(str(bad)) + ": cannot decode image"):
        ds.color(FIRST + 1)
    out = tmp_path / "frames" / "block_0000.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": cannot decode"):
        write_frames_block(folder_cfg(authors), 0, N, out)
    assert not out.exists() and not list(out.parent.glob(out.name + ".partial*"))
    write_frames_block(folder_cfg(authors), 0, 1, out)  # the frames before it are fine
    assert open_store(out, "frames").attrs["frame_ids"] == [FIRST]


def test_corrupt_depth_png(authors):
    bad = authors / "stream" / "depth" / f"Frame_{FIRST:06d}.png"
    _truncate(bad)
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": cannot decode"):
        FolderDataset(authors).depth(FIRST)


def test_colour_of_the_wrong_size(tmp_path, authors, synth):
    bad = authors / "stream" / "color" / f"Frame_{FIRST + 3:06d}.png"
    cv2.imwrite(str(bad), cv2.resize(synth.color[3], (80, 60)))
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": colour is 80x60, calibration says 160x120"):
        FolderDataset(authors).color(FIRST + 3)
    out = tmp_path / "f.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name)):
        write_frames_block(folder_cfg(authors), 2, 4, out)
    assert not out.exists() and not list(tmp_path.glob("f.zarr.partial*"))


def test_8bit_depth(authors, synth):
    bad = authors / "stream" / "depth" / f"Frame_{FIRST + 1:06d}.png"
    cv2.imwrite(str(bad), (synth.depth[1] // 16).astype(np.uint8))
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": depth must be single-channel 16-bit.*uint8"):
        FolderDataset(authors).depth(FIRST + 1)


def test_authors_meshes_without_start_idx_count_from_the_first_colour_frame_on_disk(authors, synth):
    """Without conf.json's main.start_idx, mesh/Frame_000 is the first colour frame on disk (7),
    whatever source.folder.start selects: with start 9, frame 9's mesh is Frame_002 (9 - 7)."""
    conf = json.loads((authors / "conf.json").read_text())
    del conf["case_test"]["main"]["start_idx"]
    (authors / "conf.json").write_text(json.dumps(conf))
    ds = _silent(authors, "authors", FIRST + 2)
    assert ds.frame_ids == IDS[2:] and ds.mesh_base == FIRST
    assert ds.mesh_path(FIRST + 2).name == "Frame_002.off"
    np.testing.assert_allclose(ds.load_given_mesh(FIRST + 2).vertices, synth.verts[2], atol=1e-6)


def test_start_idx_that_is_no_whole_non_negative_number_is_refused(authors):
    """A start_idx of 7.5 would be cut to 7, one of -1 would put Frame_000 before frame 0."""
    for bad in (7.5, -1):
        conf = json.loads((authors / "conf.json").read_text())
        conf["case_test"]["main"]["start_idx"] = bad
        (authors / "conf.json").write_text(json.dumps(conf))
        with pytest.raises(ValueError, match=r"main\.start_idx must be a non-negative integer, got " + re.escape(str(bad))):
            FolderDataset(authors)


def test_16bit_depth_with_three_channels_is_refused(authors, synth):
    """Depth is one channel of millimetres: a 16-bit image with three channels is not depth."""
    bad = authors / "stream" / "depth" / f"Frame_{FIRST + 1:06d}.png"
    assert cv2.imwrite(str(bad), np.dstack([synth.depth[1]] * 3))
    with pytest.raises(ValueError, match=re.escape(bad.name) + r": depth must be single-channel 16-bit millimetres, "
                                                               r"got uint16 \(72, 80, 3\)"):
        FolderDataset(authors).depth(FIRST + 1)


def test_colour_mask_labels_in_any_channel_are_foreground(authors, synth):
    """A colour mask's label in the red channel (BGR (0, 0, 1) on disk) or the green one
    ((0, 255, 0)) marks foreground as one in the blue channel does."""
    folder = authors / "stream" / "mask"
    for k, bgr in ((0, (0, 0, 1)), (1, (0, 255, 0))):
        m = np.zeros(synth.mask[k].shape + (3,), np.uint8)
        m[synth.mask[k]] = bgr
        assert cv2.imwrite(str(folder / f"Frame_{IDS[k]:06d}.png"), m)
    ds = FolderDataset(authors)
    for k in (0, 1):
        np.testing.assert_array_equal(ds.mask(IDS[k]), synth.mask[k])


def test_files_with_a_further_suffix_are_named_not_read(authors, synth):
    """An editor's or a copy tool's 'Frame_000007.png.bak' is not frame 7 (the name must end in the
    image extension): it is named in a warning, and frame 7 is read from its own file."""
    folder = authors / "stream" / "color"
    shutil.copy(folder / f"Frame_{FIRST:06d}.png", folder / f"Frame_{FIRST:06d}.png.bak")
    with pytest.warns(UserWarning, match=r"color: 1 file\(s\) not read.*\['Frame_000007\.png\.bak'\]"):
        ds = FolderDataset(authors)
    assert ds.frame_ids == IDS
    np.testing.assert_array_equal(ds.color(FIRST), synth.color[0])


def test_16bit_colour_is_refused_not_rescaled(authors, synth):
    bad = authors / "stream" / "color" / f"Frame_{FIRST:06d}.png"
    cv2.imwrite(str(bad), synth.color[0][..., ::-1].astype(np.uint16) * 257)
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": colour must be 8-bit, got uint16"):
        FolderDataset(authors).color(FIRST)


def test_grey_colour_and_16bit_or_colour_masks(authors, synth):
    """Grey colour images become RGB; a mask pixel is foreground if any channel is >= 1, whatever
    the bit depth (a 16-bit mask of 0/1 must not be rescaled to 0)."""
    grey = cv2.cvtColor(synth.color[0], cv2.COLOR_RGB2GRAY)
    cv2.imwrite(str(authors / "stream" / "color" / f"Frame_{FIRST:06d}.png"), grey)
    m16 = synth.mask[1].astype(np.uint16)
    cv2.imwrite(str(authors / "stream" / "mask" / f"Frame_{FIRST + 1:06d}.png"), m16)
    mc = np.zeros(synth.mask[3].shape + (3,), np.uint8)
    mc[synth.mask[3]] = (1, 0, 0)  # dark blue label (BGR), grey value 0
    cv2.imwrite(str(authors / "stream" / "mask" / f"Frame_{FIRST + 3:06d}.png"), mc)
    ds = FolderDataset(authors)
    np.testing.assert_array_equal(ds.color(FIRST), np.dstack([grey] * 3))
    np.testing.assert_array_equal(ds.mask(FIRST + 1), synth.mask[1])
    np.testing.assert_array_equal(ds.mask(FIRST + 3), synth.mask[3])


def test_depth_of_the_wrong_size(authors, synth):
    bad = authors / "stream" / "depth" / f"Frame_{FIRST:06d}.png"
    cv2.imwrite(str(bad), synth.depth[0][:, :40].copy())
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": depth is 40x72, calibration says 80x72"):
        FolderDataset(authors).depth(FIRST)


def test_mask_of_the_wrong_size(tmp_path, authors, synth):
    bad = authors / "stream" / "mask" / f"Frame_{FIRST + 2:06d}.png"
    cv2.imwrite(str(bad), synth.mask[2][:60, :80].astype(np.uint8) * 255)
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": mask is 80x60, must match the colour size 160x120"):
        FolderDataset(authors).mask(FIRST + 2)
    out = tmp_path / "f.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name)):
        write_frames_block(folder_cfg(authors), 0, N, out)
    assert not out.exists() and not list(tmp_path.glob("f.zarr.partial*"))


def test_empty_mask_at_ingest(tmp_path, authors):
    bad = authors / "stream" / "mask" / f"Frame_{FIRST + 1:06d}.png"
    cv2.imwrite(str(bad), np.zeros((120, 160), np.uint8))
    out = tmp_path / "frames" / "block_0000.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name) + r": the mask is empty"):
        write_frames_block(folder_cfg(authors), 0, N, out)
    assert not out.exists() and not list(out.parent.glob(out.name + ".partial*"))
    assert not any((tmp_path / "frames").iterdir())


def test_masks_all_foreground_or_inverted_are_refused(tmp_path, authors, synth, monkeypatch):
    """A mask of every pixel, or an inverted one (object 0, background 255, 88 % of the image), was
    stored; tracking then blamed the mesh's units. Refused at reading, naming the file, and at
    ingest for any source, naming the frame."""
    bad = authors / "stream" / "mask" / f"Frame_{FIRST + 1:06d}.png"
    cv2.imwrite(str(bad), np.full((120, 160), 255, np.uint8))
    with pytest.raises(ValueError, match=re.escape(str(bad)) + r": the mask is all foreground \(every pixel >= 1\)"):
        FolderDataset(authors).mask(FIRST + 1)
    cv2.imwrite(str(bad), (~synth.mask[1]).astype(np.uint8) * 255)
    out = tmp_path / "f.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name) + r": the mask's foreground covers 100 % of the image "
                       r"border \(more than 50 %\) and 8\d % of the image: .* Is the mask inverted"):
        write_frames_block(folder_cfg(authors), 0, N, out)
    assert not out.exists()
    # a source whose reader checks nothing: ingest refuses it too
    monkeypatch.setattr(FolderDataset, "mask", lambda self, fid: ~synth.mask[IDS.index(fid)])
    with pytest.raises(ValueError, match=rf"frame {FIRST} \(the source's mask\): the mask's foreground covers 100 % "
                       r"of the image border"):
        write_frames_block(folder_cfg(authors), 0, N, out)
    # an object that reaches into the image from one side is fine: the bottom edge and a quarter of each side
    m = np.zeros((120, 160), bool)
    m[90:, 20:140] = True
    m[95:, :] = True
    monkeypatch.setattr(FolderDataset, "mask", lambda self, fid: m)
    write_frames_block(folder_cfg(authors), 0, 1, out)
    np.testing.assert_array_equal(open_store(out, "frames")["mask"][0], m)


@pytest.mark.skipif(not (data_samples() / "killingfusion_snoopy").is_dir(), reason="shared data samples absent")
def test_real_masks_leave_the_image_border_to_the_background():
    """The shared samples' real masks (KillingFusion Snoopy, frames 0, 1, 50, 51) have no
    foreground on the image border, far below the 50 % an inverted mask is refused at."""
    from stex.readers.images import MAX_MASK_BORDER_FOREGROUND, border_foreground, check_mask

    paths = sorted((data_samples() / "killingfusion_snoopy").glob("*/*omask_*.png"))
    assert len(paths) == 4
    for p in paths:
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED) >= 1
        assert border_foreground(m) == 0.0 and border_foreground(~m) == 1.0
        check_mask(m, str(p))
        with pytest.raises(ValueError, match="Is the mask inverted"):
            check_mask(~m, str(p))
    assert MAX_MASK_BORDER_FOREGROUND == 0.5


def test_rgba_masks_cut_out_in_the_alpha_or_ambiguous(authors, synth):
    """An RGBA cut-out (the same colour everywhere, the object in the alpha, as image editors export
    a selection) was read as all foreground (the alpha was ignored). Its alpha is the mask now; a
    mask in the colour with a constant alpha is read from the colour; colour and alpha that both
    vary and disagree are refused."""
    folder = authors / "stream" / "mask"
    obj = synth.mask[0].astype(np.uint8) * 255
    white = np.full_like(obj, 255)
    cv2.imwrite(str(folder / f"Frame_{FIRST:06d}.png"), np.dstack([white] * 3 + [obj]))
    in_colour = synth.mask[1].astype(np.uint8) * 255
    cv2.imwrite(str(folder / f"Frame_{FIRST + 1:06d}.png"), np.dstack([in_colour] * 3 + [white]))
    grey_alpha = np.dstack([synth.mask[2].astype(np.uint8) * 255] * 3 + [synth.mask[2].astype(np.uint8) * 255])
    cv2.imwrite(str(folder / f"Frame_{FIRST + 2:06d}.png"), grey_alpha)  # both vary, and agree
    ds = FolderDataset(authors)
    np.testing.assert_array_equal(ds.mask(FIRST), synth.mask[0])
    np.testing.assert_array_equal(ds.mask(FIRST + 1), synth.mask[1])
    np.testing.assert_array_equal(ds.mask(FIRST + 2), synth.mask[2])
    photo = np.dstack([synth.color[3][..., ::-1], synth.mask[3].astype(np.uint8) * 255])  # a cut-out photo
    bad = folder / f"Frame_{FIRST + 3:06d}.png"
    cv2.imwrite(str(bad), photo)
    with pytest.raises(ValueError, match=re.escape(str(bad)) + r": ambiguous mask: its colour channels and its alpha "
                       r"channel both vary and mark different pixels \(\d+ % and 1\d % of the image"):
        ds.mask(FIRST + 3)


def test_masks_that_match_no_frame_are_named(tmp_path, authors):
    """Masks numbered from 0 (as the authors' meshes) while the colour frames are 7..10 were dropped
    without a word, and masks.use_given said 'the source supplied no masks'. A mask file with no
    colour frame beside masks that match is named too."""
    from stex.stages.masks import write_masks_block

    folder = authors / "stream" / "mask"
    extra = folder / f"Frame_{FIRST + 50:06d}.png"
    shutil.copy(folder / f"Frame_{FIRST:06d}.png", extra)
    with pytest.warns(UserWarning, match=re.escape(str(folder)) + r": 1 mask file\(s\) match no colour frame on disk "
                      r"and are not read: \['Frame_000057\.png'\]; .* colour frames on disk are "
                      rf"{FIRST}\.\.{FIRST + N - 1}"):
        assert FolderDataset(authors).has_masks
    extra.unlink()
    for k, fid in enumerate(IDS):
        (folder / f"Frame_{fid:06d}.png").rename(folder / f"Frame_{k:06d}.png")
    expected = (re.escape(str(folder)) + r": 4 mask file\(s\) exist but match no selected frame "
                rf"\({FIRST}\.\.{FIRST + N - 1}\): \['Frame_000000\.png', .*\]; masks are named Frame_<frame index>\.png "
                rf"with the colour frame's absolute index \(e\.g\. Frame_{FIRST:06d}\.png; .*these look numbered from 0"
                rf".*add {FIRST} to their numbers")
    with pytest.warns(UserWarning, match=expected):
        assert not FolderDataset(authors).has_masks
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_scene(folder_cfg(authors), N, tmp_path / "scene.zarr")
        write_frames_block(folder_cfg(authors), 0, N, tmp_path / "frames.zarr")
    with pytest.raises(ValueError, match=r"frames\.zarr: masks\.use_given is set but the source supplied no masks: "
                       + expected):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "frames.zarr",
                          dict(load_config()["masks"], use_given=True), tmp_path / "masks.zarr")


def test_a_dropped_depth_frame_is_named_and_float_depth_refused(tmp_path, authors, monkeypatch, caplog):
    """A depth frame with no valid pixel (a dropped frame) is ingested with a warning naming it;
    depth that is not uint16 millimetres (a reader returning float metres or NaN) is refused
    instead of being cast to 0 or 1 mm."""
    cv2.imwrite(str(authors / "stream" / "depth" / f"Frame_{FIRST + 2:06d}.png"), np.zeros((72, 80), np.uint16))
    with caplog.at_level("WARNING", logger="stex.ingest"):
        write_frames_block(folder_cfg(authors), 0, N, tmp_path / "f.zarr")
    assert f"frame(s) [{FIRST + 2}] have no valid depth pixel" in caplog.text
    metres = FolderDataset.depth
    monkeypatch.setattr(FolderDataset, "depth", lambda self, fid: metres(self, fid) / np.float32(1000.0))
    with pytest.raises(ValueError, match=rf"frame {FIRST}: depth must be uint16 millimetres, got float32"):
        write_frames_block(folder_cfg(authors), 0, N, tmp_path / "g.zarr")
    assert not (tmp_path / "g.zarr").exists()


def test_given_mesh_with_other_topology(tmp_path, authors, synth):
    """A per-frame mesh supplies vertex positions only: the same triangles in another order, or
    with their corners rotated, are its template's topology. Another triangle is refused, naming
    the first face the template lacks; so are other counts."""
    bad = authors / "mesh" / "Frame_002.off"
    order = np.random.default_rng(0).permutation(len(synth.faces))
    _write_off(bad, synth.verts[2], np.roll(synth.faces[order], 1, axis=1))  # reordered, corners rotated
    out = tmp_path / "scene.zarr"
    write_scene(folder_cfg(authors), 2, out)
    np.testing.assert_allclose(open_store(out, "scene")["given/vertices"][2], synth.verts[2], atol=1e-6)
    shutil.rmtree(out)
    F = synth.faces.copy()
    F[5, 2] = next(v for v in range(len(synth.verts[2])) if v not in F[5])  # one corner moved to another vertex
    _write_off(bad, synth.verts[2], F)
    with pytest.raises(ValueError, match=re.escape(str(bad)) + rf": mesh topology differs from the template \(.*\): "
                       rf"its face 5 {re.escape(str(F[5].tolist()))} is not among the template's triangles; the "
                       rf"template's face 5 is {re.escape(str(synth.faces[5].tolist()))}"):
        write_scene(folder_cfg(authors), 2, out)
    assert not out.exists() and not list(tmp_path.glob("scene.zarr.partial*"))
    keep = (synth.faces < len(synth.verts[2]) - 5).all(1)
    _write_off(bad, synth.verts[2][:-5], synth.faces[keep])  # fewer vertices and faces
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": mesh topology differs"):
        write_scene(folder_cfg(authors), 2, out)


def test_a_quad_mesh_as_obj_template_and_off_or_ply_frames(tmp_path, authors):
    """The same quads split by two readers: OBJ fans each quad in place ([0,1,5], [0,5,4]),
    trimesh (OFF, PLY) lists every quad's first triangle before the second ones. It was refused as
    'topology differs (18 faces / 16 vertices vs 18 faces / 16 vertices)'."""
    n = 4
    g = np.linspace(-0.1, 0.1, n)
    V = np.array([[x, y, 0.5] for y in g for x in g])
    Q = [[r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)]
    (authors / "tex_mesh.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in V)
                                          + "".join("f " + " ".join(str(i + 1) for i in q) + "\n" for q in Q))
    off = "OFF\n%d %d 0\n" % (len(V), len(Q)) + "".join(f"{x} {y} {z}\n" for x, y, z in V) \
        + "".join("4 " + " ".join(map(str, q)) + "\n" for q in Q)
    ply = ("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
           "element face %d\nproperty list uchar int vertex_indices\nend_header\n" % (len(V), len(Q))
           + "".join(f"{x} {y} {z}\n" for x, y, z in V) + "".join("4 " + " ".join(map(str, q)) + "\n" for q in Q))
    for p in (authors / "mesh").iterdir():
        p.unlink()
    for k in range(N):
        (authors / "mesh" / f"Frame_{k:03d}.{'off' if k % 2 else 'ply'}").write_text(off if k % 2 else ply)
    template, frame = load_mesh(authors / "tex_mesh.obj"), load_mesh(authors / "mesh" / "Frame_001.off")
    assert not np.array_equal(template.faces, frame.faces)  # the two orders differ
    write_scene(folder_cfg(authors), 2, tmp_path / "scene.zarr")
    given = open_store(tmp_path / "scene.zarr", "scene")["given/vertices"][:]
    np.testing.assert_allclose(given, np.broadcast_to(V, given.shape), atol=1e-6)


def test_given_mesh_with_nan_vertices(tmp_path, authors, synth):
    bad = authors / "mesh" / "Frame_001.off"
    V = synth.verts[1].copy()
    V[5, 1] = np.nan
    _write_off(bad, V, synth.faces)
    out = tmp_path / "scene.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": vertex 5 is not finite"):
        write_scene(folder_cfg(authors), 2, out)
    assert not out.exists() and not list(tmp_path.glob("scene.zarr.partial*"))


def test_given_mesh_missing_for_a_later_frame(tmp_path, authors):
    (authors / "mesh" / "Frame_003.off").unlink()
    with pytest.raises(ValueError, match=rf"given mesh missing for frame {FIRST + 3}"):
        write_scene(folder_cfg(authors), 2, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()


def test_obj_face_index_out_of_range(tmp_path, stex_ds, synth):
    bad = stex_ds / "meshes" / f"{FIRST + 1:06d}.obj"
    F = synth.faces.copy()
    F[3, 1] = len(synth.verts[1])  # one past the last vertex
    _write_obj(bad, synth.verts[1], F)
    with pytest.raises(ValueError, match=re.escape(bad.name) + r": face refers to a vertex outside 1\.\."):
        load_mesh(bad)
    out = tmp_path / "scene.zarr"
    with pytest.raises(ValueError, match=re.escape(bad.name) + ": face refers to a vertex outside"):
        write_scene(folder_cfg(stex_ds, "stex"), 2, out)
    assert not out.exists() and not list(tmp_path.glob("scene.zarr.partial*"))


def test_obj_texcoord_index_out_of_range_and_bad_lines(tmp_path, synth):
    p = tmp_path / "t.obj"
    tf = synth.texcoord_faces.copy()
    tf[0, 0] = len(synth.texcoords) + 3
    _write_obj(p, synth.verts[0], synth.faces, synth.texcoords, tf)
    with pytest.raises(ValueError, match=r"t\.obj: face refers to a texcoord outside"):
        load_mesh(p)
    p.write_text("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"t\.obj:2: cannot parse OBJ line 'v 1 0'"):
        load_mesh(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n")
    with pytest.raises(ValueError, match=r"t\.obj:4: cannot parse"):
        load_mesh(p)
    p.write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match=r"t\.obj: OBJ has no vertices or no faces"):
        load_mesh(p)
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(tmp_path / "absent.off")


def test_stex_calibration_is_validated(stex_ds, synth):
    path = stex_ds / "calibration.json"
    good = synth.cal.to_dict()

    bad = json.loads(json.dumps(good))
    bad["color"]["fx"] = -140.0
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration.*focal"):
        FolderDataset(stex_ds, "stex")

    bad = json.loads(json.dumps(good))
    bad["depth_to_color"][0][0] = 1.5  # scaled axis: not a rotation
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration.*not a proper rotation"):
        FolderDataset(stex_ds, "stex")

    bad = json.loads(json.dumps(good))
    bad["depth_to_color"] = (np.diag([1.0, 1.0, -1.0, 1.0])).tolist()  # reflection
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration.*not a proper rotation"):
        FolderDataset(stex_ds, "stex")

    bad = json.loads(json.dumps(good))
    del bad["depth"]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration.*depth"):
        FolderDataset(stex_ds, "stex")

    bad = json.loads(json.dumps(good))
    bad["color"]["distortion"] = [0.1, -0.05, 0, 0, 0, 0, 0, 0]
    path.write_text(json.dumps(bad))
    with pytest.warns(UserWarning, match=r"calibration\.json: non-zero distortion"):
        ds = FolderDataset(stex_ds, "stex")
    assert ds.calibration.color.distortion[0] == 0.1  # reported, kept, not applied

    # "distortion": null is no distortion, as a missing key (it was refused as "got [nan]")
    bad = json.loads(json.dumps(good))
    bad["color"]["distortion"] = None
    path.write_text(json.dumps(bad))
    assert not _silent(stex_ds, "stex").calibration.color.distortion.any()
    bad["color"]["distortion"] = [0.1, None]
    path.write_text(json.dumps(bad))
    with pytest.raises(ValueError, match=r"color camera: distortion coefficients must be finite, got \[0\.1, nan\]"):
        FolderDataset(stex_ds, "stex")

    path.unlink()
    with pytest.raises(FileNotFoundError, match=r"calibration\.json: missing"):
        FolderDataset(stex_ds, "stex")


def test_unknown_layout(stex_ds):
    with pytest.raises(ValueError, match="unknown folder layout 'kim'"):
        FolderDataset(stex_ds, "kim")


# -- damaged or ambiguous files (each found by an adversarial review) ---------------------------

def _as_jpeg(root: Path, fid: int, exif_orientation=None) -> Path:
    """Replace colour frame ``fid`` of a stex-layout dataset by a JPEG (optionally with EXIF)."""
    from PIL import Image

    png = root / "color" / f"{fid:06d}.png"
    jpg = png.with_suffix(".jpg")
    im = Image.fromarray(cv2.imread(str(png if png.exists() else jpg))[..., ::-1].copy())
    png.unlink(missing_ok=True)
    if exif_orientation is None:
        im.save(jpg, quality=95)
    else:
        exif = im.getexif()
        exif[0x0112] = exif_orientation
        im.save(jpg, quality=95, exif=exif.tobytes())
    return jpg


def test_a_truncated_colour_jpeg_is_refused(stex_ds):
    jpg = _as_jpeg(stex_ds, IDS[1])
    ds = FolderDataset(stex_ds, "stex")
    whole = ds.color(IDS[1])
    jpg.write_bytes(jpg.read_bytes()[: int(jpg.stat().st_size * 0.66)])
    # libjpeg would decode it to a full-size image with its lower rows invented
    with pytest.raises(ValueError, match=rf"{IDS[1]:06d}\.jpg: the JPEG ends without its end-of-image marker"):
        ds.color(IDS[1])
    assert whole.shape == (SYN["color"]["height"], SYN["color"]["width"], 3)


def test_a_colour_jpeg_damaged_inside_is_refused(tmp_path, stex_ds, synth):
    """600 bytes zeroed in the middle, the end marker intact: libjpeg decodes a full-size image,
    wrong in 88 of its 120 rows, and says so only on stderr (which OpenCV does not pass on).
    Ingest stored it; now the file is named with libjpeg's words."""
    jpg = _as_jpeg(stex_ds, IDS[1])
    ds = FolderDataset(stex_ds, "stex")
    whole = ds.color(IDS[1])  # the undamaged JPEG reads as OpenCV decodes it
    np.testing.assert_array_equal(whole, cv2.imread(str(jpg))[..., ::-1])
    b = bytearray(jpg.read_bytes())
    b[len(b) // 3: len(b) // 3 + 600] = bytes(600)
    jpg.write_bytes(bytes(b))
    with pytest.raises(ValueError, match=re.escape(str(jpg)) + r": the JPEG's data is damaged \(libjpeg: 'Corrupt JPEG "
                       r"data: [^']+'\)"):
        ds.color(IDS[1])
    out = tmp_path / "f.zarr"
    with pytest.raises(ValueError, match=re.escape(jpg.name) + ": the JPEG's data is damaged"):
        write_frames_block(folder_cfg(stex_ds, "stex"), 0, N, out)
    assert not out.exists()


def test_exif_orientation_of_a_colour_jpeg_is_not_applied(stex_ds):
    from PIL import Image

    jpg = _as_jpeg(stex_ds, IDS[2], exif_orientation=3)   # "rotate 180" in the EXIF only
    stored = np.asarray(Image.open(jpg).convert("RGB"))    # the pixels as stored, unrotated
    got = FolderDataset(stex_ds, "stex").color(IDS[2])
    # aligned with the depth: not turned round (turned, it is off by tens of grey levels)
    assert np.abs(got.astype(int) - stored).mean() < 1.0
    assert np.abs(got.astype(int) - stored[::-1, ::-1]).mean() > 5.0


def test_two_files_for_one_frame_are_refused(stex_ds):
    src = stex_ds / "color" / f"{IDS[1]:06d}.png"
    shutil.copy(src, stex_ds / "color" / f"{IDS[1]}.png")
    with pytest.raises(ValueError, match=rf"two files for frame {IDS[1]}: {IDS[1]:06d}\.png and {IDS[1]}\.png"):
        FolderDataset(stex_ds, "stex")


def test_a_stray_frame_with_a_far_index_is_counted_not_listed(authors):
    for d in ("color", "depth"):
        shutil.copy(authors / "stream" / d / f"Frame_{IDS[0]:06d}.png",
                    authors / "stream" / d / "Frame_1000000000.png")
    # the gap is 10^9 frames long: named by its first frames and counted, at once
    with pytest.raises(ValueError, match=rf"frame\(s\) \[{IDS[-1] + 1}, .*\] missing \(and {10**9 - IDS[-1] - 11} more\)"):
        FolderDataset(authors)


@pytest.mark.parametrize("layout", ["authors", "stex"])
@pytest.mark.parametrize("ext", [".jpg", ".JPEG"])
def test_jpeg_masks_are_refused_in_both_layouts(tmp_path, datasets, synth, layout, ext):
    """The authors' layout listed only ``.png`` masks: JPEG masks were skipped without a word and
    the run went on without masks, while the stex layout refused them."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    m = _files(root, layout, "mask")[0]
    m.unlink()
    assert cv2.imwrite(str(m.with_suffix(".jpg")), synth.mask[0].astype(np.uint8) * 255)
    m.with_suffix(".jpg").rename(m.with_suffix(ext))
    with pytest.raises(ValueError, match=r"mask: masks must be PNG: JPEG's lossy compression smears the mask's "
                                         rf"edges.*{re.escape(m.stem + ext)}.*Save the masks as PNG"):
        FolderDataset(root, layout)


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_meshes_missing_for_the_first_frame_only_are_refused(tmp_path, datasets, layout):
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    first = (root / "mesh" / "Frame_000.off") if layout == "authors" else (root / "meshes" / f"{IDS[0]:06d}.obj")
    first.unlink()
    with pytest.raises(ValueError, match=rf"given meshes exist for {N - 1} of the {N} frames, from frame "
                                         rf"{IDS[1]}, but not for the first frame {IDS[0]}"):
        write_scene(folder_cfg(root, layout), 2, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()


@pytest.mark.parametrize("conf, match", [
    ([1, 2], "the file must hold an object of cases, got list"),
    ({"case": {"mapper4D": None}}, "mapper4D must be an object"),
    ({"case": {"mapper4D": "x"}}, "mapper4D must be an object"),
])
def test_conf_json_of_the_wrong_shape(authors, conf, match):
    (authors / "conf.json").write_text(json.dumps(conf))
    with pytest.raises(ValueError, match=rf"conf\.json: invalid camera settings \({match}"):
        FolderDataset(authors)


def test_conf_json_main_of_the_wrong_type(authors):
    conf = json.loads((authors / "conf.json").read_text())
    case = conf["case_test"]
    case["main"] = None          # allowed: no main section
    (authors / "conf.json").write_text(json.dumps(conf))
    FolderDataset(authors)
    case["main"] = {"tex_mesh_path": 5}
    (authors / "conf.json").write_text(json.dumps(conf))
    with pytest.raises(ValueError, match=r"main\.tex_mesh_path must be a path"):
        FolderDataset(authors)


def test_stex_calibration_that_is_not_an_object(stex_ds):
    (stex_ds / "calibration.json").write_text("[]")
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration \(the file must hold an object"):
        FolderDataset(stex_ds, "stex")


def test_obj_negative_indices_count_back_from_the_vertices_read_so_far(tmp_path):
    p = tmp_path / "rel.obj"
    p.write_text("o A\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf -3/-3 -2/-2 -1/-1\n"
                 "o B\nv 5 5 5\nv 6 5 5\nv 5 6 5\nvt .5 .5\nvt 1 .5\nvt .5 1\nf -3/-3 -2/-2 -1/-1\n")
    m = load_mesh(p)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(m.texcoord_faces, [[0, 1, 2], [3, 4, 5]])


def test_obj_with_texture_coordinates_on_some_faces_only_warns(tmp_path):
    p = tmp_path / "part.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 2 4 3\n")
    with pytest.warns(UserWarning, match=r"1 of 2 faces have no texture coordinates"):
        m = load_mesh(p)
    assert m.texcoords is None and len(m.faces) == 2


@pytest.mark.parametrize("bad", [9, -1])
def test_ply_face_index_out_of_range(tmp_path, bad):
    p = tmp_path / "bad.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
                 f"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 {bad}\n")
    with pytest.raises(ValueError, match=rf"bad\.ply: face 1 refers to vertex \[0, 1, {bad}\], outside 0\.\.2"):
        load_mesh(p)


def test_obj_polygons_are_fanned_with_their_texture_corners(tmp_path):
    """A pentagon with corners a..e (vertices 1..5, texture coordinates 5..1) is fanned from its
    first corner into (a, b, c), (a, c, d), (a, d, e), by hand: faces [[0, 1, 2], [0, 2, 3],
    [0, 3, 4]] and, corner for corner, texcoord faces [[4, 3, 2], [4, 2, 1], [4, 1, 0]]."""
    p = tmp_path / "pentagon.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1.5 1 0\nv 0.5 1.6 0\nv -0.5 1 0\n"
                 "vt 0 0\nvt 0.25 0\nvt 0.5 0\nvt 0.75 0\nvt 1 0\nf 1/5 2/4 3/3 4/2 5/1\n")
    m = load_mesh(p)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    np.testing.assert_array_equal(m.texcoord_faces, [[4, 3, 2], [4, 2, 1], [4, 1, 0]])


def test_obj_texture_coordinate_without_v_and_faces_with_normals_only(tmp_path):
    """OBJ's 'vt u [v [w]]': a missing v is 0, i.e. 1 in stex's downward v. Faces 'f v//vn' (normals,
    no texture coordinates) are read as 'f v'."""
    p = tmp_path / "u_only.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.25\nvt 1 0.5\nvt 0 0.75 0\nf 1/1 2/2 3/3\n")
    np.testing.assert_allclose(load_mesh(p).texcoords, [[0.25, 1.0], [1.0, 0.5], [0.0, 0.25]])
    p = tmp_path / "normals.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nf 2//1 4//1 3//1\n")
    m = load_mesh(p)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [1, 3, 2]])
    assert m.texcoords is None and m.texcoord_faces is None


def test_write_obj_without_texture_coordinates_is_read_back_by_trimesh(tmp_path):
    """stex's OBJ writer, untextured branch, read by trimesh's own OBJ loader: OBJ's 1-based faces
    come back as the 0-based faces written."""
    from stex.readers.meshes import Mesh, write_obj

    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.5]])
    F = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    write_obj(tmp_path / "m.obj", Mesh(V, F))
    tm = trimesh.load(tmp_path / "m.obj", process=False, maintain_order=True, force="mesh")
    np.testing.assert_allclose(tm.vertices, V)
    np.testing.assert_array_equal(tm.faces, F)


def test_intrinsics_refuse_non_finite_distortion_and_fractional_sizes():
    from stex.camera import Intrinsics

    Intrinsics.from_focal(100.0, 100.0, 79.5, 59.5, 160, 120, [0.1, 0.0])
    with pytest.raises(ValueError, match=r"distortion coefficients must be finite"):
        Intrinsics.from_focal(100.0, 100.0, 79.5, 59.5, 160, 120, [0.1, float("nan")])
    with pytest.raises(ValueError, match=r"image width must be a whole number of pixels, got 160\.9"):
        Intrinsics.from_focal(100.0, 100.0, 79.5, 59.5, 160.9, 120)
    assert Intrinsics.from_focal(100.0, 100.0, 79.5, 59.5, 160.0, 120).width == 160


def test_intrinsics_refuse_skew_and_another_last_row_and_look_at_degenerate_views():
    """Projection and back-projection use fx, fy, cx, cy only: a K with skew or a last row other
    than (0, 0, 1) was accepted and half ignored. look_at along its up vector gave NaN rows."""
    import numpy as np

    from stex.camera import Intrinsics, look_at

    for K in ([[500, 1, 320], [0, 500, 240], [0, 0, 1]], [[500, 0, 320], [0, 500, 240], [0, 0, 2]]):
        with pytest.raises(ValueError, match="no skew"):
            Intrinsics(np.array(K, float), 640, 480)
    with pytest.raises(ValueError, match="parallel to up"):
        look_at((0, 1, 0), (0, 0, 0))
    with pytest.raises(ValueError, match="apart from the eye"):
        look_at((0, 0, 0), (0, 0, 0))
    assert np.isfinite(look_at((0, 0, -1), (0, 0, 0))).all()


def test_project_points_matches_opencv_with_unequal_focal_lengths_and_is_nan_behind_the_camera():
    """project_points against OpenCV's projectPoints (no rotation, translation or distortion) with
    fx != fy and cx != cy, so that a swapped focal length or principal point shows; a point behind
    the camera (z < 0) or on its plane (z = 0) gets NaN pixel coordinates and its own z."""
    from stex.camera import project_points

    K = np.array([[520.0, 0.0, 310.25], [0.0, 480.0, 245.75], [0.0, 0.0, 1.0]])
    P = np.random.default_rng(3).uniform([-0.3, -0.2, 0.5], [0.3, 0.2, 2.0], (20, 3))
    expected = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, None)[0].reshape(-1, 2)
    uv, z = project_points(P, K)
    np.testing.assert_allclose(uv, expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(z, P[:, 2])
    uv, z = project_points([[0.1, 0.2, -1.0], [0.1, 0.2, 0.0]], K)
    assert np.isnan(uv).all() and z.tolist() == [-1.0, 0.0]


def _pinhole_pair(t):
    """Colour and depth cameras alike (4x2 pixels, f = 10, principal point (1.5, 0.5)) with the
    depth camera translated by ``t`` (metres) into the colour camera's frame."""
    from stex.camera import Calibration, Intrinsics

    cam = Intrinsics.from_focal(10.0, 10.0, 1.5, 0.5, 4, 2)
    T = np.eye(4)
    T[:3, 3] = t
    return Calibration(cam, cam, T)


def test_depth_pixels_in_color_by_hand():
    """Worked by hand. Depth 1 m everywhere: depth pixel (row r, column c) is the point
    ((c - 1.5) / 10, (r - 0.5) / 10, 1).
    - Shifted 7 cm along x it lands at colour (u, v) = (c + 0.7, r): the nearest pixel is column
      c + 1 (not the c of rounding down), and column 3 lands on column 4, outside the 4-pixel-wide
      image, so it is left out. Pixel (1, 1) has depth 0 (invalid) and is left out.
    - Shifted 1 cm forward (z 1.01), pixel (r, c) lands at ((c - 1.5) / 1.01 + 1.5, ...), nearest
      pixel (c, r). A depth-0 pixel backprojects to the depth camera's centre, which lies 1 cm
      before the colour camera at its principal point (1.5, 0.5) (on the image): it must stay out
      because its depth is invalid, not because it projects outside.
    - The same depth in uint16 millimetres is refused, not read as kilometres."""
    from stex.camera import depth_pixels_in_color

    depth = np.ones((2, 4))
    depth[1, 1] = 0.0
    idx, px, z = depth_pixels_in_color(depth, _pinhole_pair([0.07, 0.0, 0.0]))
    assert idx.tolist() == [0, 1, 2, 4, 6]
    assert px.tolist() == [[1, 0], [2, 0], [3, 0], [1, 1], [3, 1]]
    np.testing.assert_allclose(z, 1.0)
    idx, px, z = depth_pixels_in_color(depth, _pinhole_pair([0.0, 0.0, 0.01]))
    assert idx.tolist() == [0, 1, 2, 3, 4, 6, 7]
    assert px.tolist() == [[0, 0], [1, 0], [2, 0], [3, 0], [0, 1], [2, 1], [3, 1]]
    np.testing.assert_allclose(z, 1.01)
    with pytest.raises(ValueError, match=r"depth_m must be float metres, got uint16"):
        depth_pixels_in_color((depth * 1000).astype(np.uint16), _pinhole_pair([0.0, 0.0, 0.0]))


def test_scaled_intrinsics_keep_pixel_centres():
    """Halving a 640x480 camera (fx 500, fy 400, cx 300, cy 200): the focal lengths halve, and pixel
    i of the small image covers pixels 2i and 2i + 1 of the large one, so its centre is the large
    image's 2i + 0.5: cx' = (300 - 0.5) / 2 = 149.75, cy' = (200 - 0.5) / 2 = 99.75. Checked with a
    point too: its large-image u equals 2 u' + 0.5 of the small one (OpenCV's projectPoints)."""
    from stex.camera import Intrinsics

    big = Intrinsics.from_focal(500.0, 400.0, 300.0, 200.0, 640, 480)
    small = big.scaled(0.5)
    assert (small.fx, small.fy, small.cx, small.cy) == (250.0, 200.0, 149.75, 99.75)
    assert (small.width, small.height) == (320, 240)
    P = np.array([[0.12, -0.07, 1.3]])
    uv_big = cv2.projectPoints(P, np.zeros(3), np.zeros(3), big.K, None)[0].reshape(2)
    uv_small = cv2.projectPoints(P, np.zeros(3), np.zeros(3), small.K, None)[0].reshape(2)
    np.testing.assert_allclose(uv_big, 2 * uv_small + 0.5, atol=1e-9)


def test_principal_point_may_lie_anywhere_on_the_image_pixels():
    """Pixel centres are integers, so a W x H image spans [-0.5, W - 0.5] x [-0.5, H - 0.5]: a
    principal point on that edge is accepted (if odd), one a hundredth of a pixel beyond refused."""
    from stex.camera import Intrinsics

    for cx, cy in ((-0.5, 59.5), (159.5, 59.5), (79.5, -0.5), (79.5, 119.5)):
        Intrinsics.from_focal(100.0, 100.0, cx, cy, 160, 120)
    for cx, cy in ((-0.51, 59.5), (159.51, 59.5), (79.5, -0.51), (79.5, 119.51)):
        with pytest.raises(ValueError, match=r"lies outside the 160x120 image"):
            Intrinsics.from_focal(100.0, 100.0, cx, cy, 160, 120)


def test_look_at_puts_the_target_ahead_and_up_upwards():
    """By hand, with the default up (0, -1, 0) (world -y appears up in the image, OpenCV's -y):
    - from (0, 0, -1) at the origin the camera axes are the world's: R = I, t = (0, 0, 1);
    - from (3, 0, 0) at the origin z = (-1, 0, 0), x = (-up) x z = (0, 0, 1), y = z x x = (0, 1, 0),
      t = -R eye = (0, 0, 3): the target is 3 m straight ahead, the world point (0, -1, 0) is
      above it in the image (camera y < 0), and (0, 0, 1) right of it (camera x > 0).
    A right-handed rotation (det +1) either way."""
    from stex.camera import look_at, transform_points

    np.testing.assert_allclose(look_at((0, 0, -1), (0, 0, 0)), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]],
                               atol=1e-12)
    T = look_at((3, 0, 0), (0, 0, 0))
    np.testing.assert_allclose(T, [[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 3], [0, 0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(transform_points(T, [[0, 0, 0], [0, -1, 0], [0, 0, 1]]),
                               [[0, 0, 3], [0, -1, 3], [1, 0, 3]], atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


# -- file names: the same rules in both layouts; files not read are named -----------------------

def _dir(root: Path, layout: str, kind: str) -> Path:
    """The folder of ``kind`` (color, depth, mask or mesh) in ``layout``."""
    if kind == "mesh":
        return root / ("mesh" if layout == "authors" else "meshes")
    return root / "stream" / kind if layout == "authors" else root / kind


def _files(root: Path, layout: str, kind: str) -> list[Path]:
    return sorted(_dir(root, layout, kind).iterdir())


def _silent(*args) -> FolderDataset:
    """FolderDataset(*args), failing on any warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return FolderDataset(*args)


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_mesh_names_with_any_number_of_digits_and_any_extension_case(tmp_path, datasets, synth, layout):
    """Only ``%06d``/``%03d`` names with lower-case extensions were looked up: ``meshes/7.obj``,
    ``meshes/000008.OBJ``, ``mesh/Frame_000001.off`` were dropped without a word and the run had
    no given meshes. Colour names took any number of digits; meshes now do too."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    prefix = "Frame_" if layout == "authors" else ""
    for k, p in enumerate(_files(root, layout, "mesh")):
        number = int(re.search(r"\d+", p.name).group())
        ext = p.suffix.upper() if k % 2 else p.suffix
        p.rename(p.with_name(f"{prefix}{number:{['', '06', '03', '02'][k]}d}{ext}"))
    ds = _silent(root, layout)
    for k, fid in enumerate(IDS):
        np.testing.assert_allclose(ds.load_given_mesh(fid).vertices, synth.verts[k], atol=1e-6)
    assert ds.mesh_path(IDS[1]).name == (f"Frame_000001.OFF" if layout == "authors" else f"{IDS[1]:06d}.OBJ")
    write_scene(folder_cfg(root, layout), 2, tmp_path / "scene.zarr")
    g = open_store(tmp_path / "scene.zarr", "scene")
    np.testing.assert_allclose(g["given/vertices"][:], np.stack(synth.verts), atol=1e-6)
    if layout == "authors":  # without conf.json's template, the default is mesh/Frame_000 in any spelling
        (root / "tex_mesh.obj").unlink()
        assert FolderDataset(root).template_path() == root / "mesh" / "Frame_0.off"


def test_authors_meshes_numbered_by_absolute_index_are_named(authors):
    """mesh/Frame_%03d counts from conf.json's start_idx (documented, kept). Meshes numbered by the
    absolute frame index (Frame_007 for frame 7) matched no frame and were dropped without a word."""
    for p in sorted(_files(authors, "authors", "mesh"), reverse=True):
        p.rename(p.with_name(f"Frame_{int(p.stem[6:]) + FIRST:03d}.off"))
    with pytest.warns(UserWarning, match=rf"mesh: 4 mesh file\(s\) give no frame its mesh and are not read: "
                                         rf"\['Frame_007\.off', .*numbers them from frame {FIRST} \(conf\.json's "
                                         rf"main\.start_idx\): Frame_000 is frame {FIRST}.*look like absolute frame "
                                         r"indices: rename .*\(e\.g\. Frame_007 to Frame_000\)"):
        ds = FolderDataset(authors)
    assert all(ds.mesh_path(fid) is None for fid in IDS)


def test_mesh_files_that_match_no_frame_are_named(stex_ds):
    """A mesh file that is no frame's mesh is named; the meshes that match are still read. An
    OBJ's .mtl is not a mesh."""
    meshes = stex_ds / "meshes"
    for name in (f"{IDS[-1] + 90:06d}.obj", "mesh_8.obj", "000007.glb"):
        shutil.copy(meshes / f"{IDS[0]:06d}.obj", meshes / name)
    (meshes / "000007.mtl").write_text("newmtl skin\n")
    with pytest.warns(UserWarning) as rec:
        ds = FolderDataset(stex_ds, "stex")
    msg = "\n".join(str(w.message) for w in rec)
    assert re.search(r"meshes: 3 mesh file\(s\) give no frame its mesh and are not read: \['000100\.obj', "
                     r"'000007\.glb', 'mesh_8\.obj'\]; name them <frame index>\.obj .*on disk are 7\.\.10", msg)
    assert ".mtl" not in msg
    assert all(ds.mesh_path(fid).name == f"{fid:06d}.obj" for fid in IDS)


def test_authors_template_in_the_mesh_folder_is_not_named(authors):
    conf = json.loads((authors / "conf.json").read_text())
    conf["case_test"]["main"]["tex_mesh_path"] = "mesh/template.obj"
    (authors / "conf.json").write_text(json.dumps(conf))
    (authors / "tex_mesh.obj").rename(authors / "mesh" / "template.obj")
    assert _silent(authors).template_path() == authors / "mesh" / "template.obj"


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_two_mesh_files_for_one_frame_are_refused(tmp_path, datasets, layout):
    """Two spellings of one frame's mesh are refused, as for images (the lookup took the first of
    .off, .obj, .ply)."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    first = _files(root, layout, "mesh")[0]
    other = "Frame_0.obj" if layout == "authors" else f"{IDS[0]}.ply"
    shutil.copy(first, first.with_name(other))
    with pytest.raises(ValueError, match=rf"{_dir(root, layout, 'mesh').name}: two files for frame {IDS[0]}: ") as exc:
        FolderDataset(root, layout)
    assert {first.name, other} == set(re.search(r": (\S+) and (\S+); keep one$", str(exc.value)).groups())


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_upper_case_image_extensions_are_read(tmp_path, datasets, synth, layout):
    """``000007.PNG`` masks were ignored in both layouts (the run went on without masks)."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    for kind in ("color", "depth", "mask"):
        for p in _files(root, layout, kind):
            p.rename(p.with_suffix(".PNG"))
    ds = _silent(root, layout)
    assert ds.frame_ids == IDS and ds.has_masks
    for k, fid in enumerate(IDS):
        np.testing.assert_array_equal(ds.mask(fid), synth.mask[k])
        np.testing.assert_array_equal(ds.color(fid), synth.color[k])
        np.testing.assert_array_equal(ds.depth(fid), synth.depth[k])


def test_authors_colour_jpegs_are_read_and_other_formats_named(authors, synth):
    """Colour saved as .jpg failed with "no colour frames in [0, None)", not saying what was
    found. JPEG colour is read as in the stex layout; files of another format are named."""
    for p in _files(authors, "authors", "color"):
        assert cv2.imwrite(str(p.with_suffix(".jpg")), cv2.imread(str(p)), [cv2.IMWRITE_JPEG_QUALITY, 95])
        p.unlink()
    ds = _silent(authors)
    assert ds.frame_ids == IDS
    assert np.abs(ds.color(IDS[0]).astype(int) - synth.color[0]).mean() < 3  # RGB, JPEG's error only
    for p in _files(authors, "authors", "color"):
        p.rename(p.with_suffix(".bmp"))
    with pytest.raises(ValueError, match=r"color: no colour frames in \[0, None\); 4 file\(s\) not read, as they "
                                         r"are not named Frame_<frame index>\.png or \.jpg: \['Frame_000007\.bmp'"):
        FolderDataset(authors)


@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_image_files_that_are_not_read_are_named(tmp_path, datasets, layout):
    """Masks in another format were skipped without a word: the run went on without them."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    for p in _files(root, layout, "mask"):
        p.rename(p.with_suffix(".bmp"))
    (_dir(root, layout, "color") / "notes.txt").write_text("shot on Tuesday")
    (_dir(root, layout, "color") / ".DS_Store").write_bytes(b"\0")  # hidden: an OS's, not the user's
    with pytest.warns(UserWarning) as rec:
        ds = FolderDataset(root, layout)
    assert not ds.has_masks
    msg = "\n".join(str(w.message) for w in rec)
    prefix = "Frame_" if layout == "authors" else ""
    assert re.search(rf"mask: 4 file\(s\) not read, as they are not named {prefix}<frame index>\.png: "
                     rf"\['{prefix}0*7\.bmp', ", msg)
    assert "rename them (or move them out of the folder)" in msg
    assert re.search(r"color: 1 file\(s\) not read.*\['notes\.txt'\]", msg) and "DS_Store" not in msg
    for p in _files(root, layout, "depth"):
        p.rename(p.with_suffix(".tif"))
    with pytest.raises(ValueError, match=rf"depth: depth missing for frame\(s\) \[7, 8, 9, 10\]; 4 file\(s\) not "
                                         rf"read, as they are not named {prefix}<frame index>\.png: .*7\.tif"):
        FolderDataset(root, layout)


# -- calibrations that are valid but wrong ------------------------------------------------------

@pytest.mark.parametrize("layout", ["authors", "stex"])
def test_colour_intrinsics_of_a_lower_resolution_warn(tmp_path, datasets, synth, layout):
    """A 160x120 colour camera given the intrinsics of 80x60 (fx 70, cx 39.5, cy 29.5) passed, as
    its principal point is inside the image, and the run's texture came out 25.7 dB, not 37.3."""
    root = Path(shutil.copytree(datasets[layout], tmp_path / "ds"))
    _silent(root, layout)  # the synthetic cameras are centred
    small = dict(_intr(synth.cal.color), fx=70.0, fy=70.0, cx=39.5, cy=29.5)
    if layout == "authors":
        _set_mapper(root, color_intrinsic=small)
    else:
        cal = synth.cal.to_dict()
        cal["color"].update(small)
        (root / "calibration.json").write_text(json.dumps(cal))
    name = "conf.json" if layout == "authors" else "calibration.json"
    with pytest.warns(UserWarning, match=rf"{re.escape(name)}: color camera: principal point \(39\.5, 29\.5\) is "
                                         r"25 % of the width and 25 % of the height from the centre of the 160x120 "
                                         r"image .*another resolution, 80x60 \(2\*cx\+1 by 2\*cy\+1\); give the "
                                         r"intrinsics of the 160x120 images"):
        FolderDataset(root, layout)


def test_principal_point_threshold():
    """Suspect beyond 15 % of the width or height from the centre: half-resolution intrinsics are
    25 % off, 720p intrinsics given for 1080p 16.7 %; the Azure Kinect's NFOV depth is 10.6 %."""
    from stex.camera import MAX_PRINCIPAL_OFFSET, Intrinsics

    assert MAX_PRINCIPAL_OFFSET == 0.15
    assert Intrinsics.from_focal(500, 500, 319.5, 287.5 + 0.149 * 576, 640, 576).resolution_mismatch() is None
    assert "another resolution" in Intrinsics.from_focal(500, 500, 319.5, 287.5 + 0.151 * 576, 640, 576).resolution_mismatch()
    assert "another resolution" in Intrinsics.from_focal(500, 500, 319.5 - 0.151 * 640, 287.5, 640, 576).resolution_mismatch()
    assert "1280x720" in Intrinsics.from_focal(900, 900, 639.5, 359.5, 1920, 1080).resolution_mismatch()


@pytest.mark.skipif(not data_samples().is_dir(), reason="shared data samples absent")
def test_real_cameras_are_not_suspected_of_another_resolution():
    """The shared samples' calibrations: Kinect v1 (Snoopy), Structure sensor (DeepDeform) and the
    Azure Kinect in every colour resolution and depth mode."""
    from stex.camera import Intrinsics
    from stex.readers.kinect_calibration import COLOR_RESOLUTIONS, DEPTH_MODES, calibration_from_k4a_json

    root = data_samples()
    K = np.loadtxt(root / "killingfusion_snoopy" / "frames_000000_000001" / "intrinsics_kinect1.txt")
    cams = [Intrinsics(K, 640, 480)]
    K = np.loadtxt(root / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017" / "intrinsics.txt")[:3, :3]
    assert cv2.imread(str(root / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017" / "color"
                          / "000300.jpg")).shape[:2] == (480, 640)
    cams.append(Intrinsics(K, 640, 480))
    k4a = json.loads((root / "azure_kinect_pyk4a" / "calibration.json").read_text())
    for res in COLOR_RESOLUTIONS:
        for mode in DEPTH_MODES:
            cal = calibration_from_k4a_json(k4a, res, mode)
            cams += [cal.color, cal.depth]
    assert len(cams) == 2 + 2 * len(COLOR_RESOLUTIONS) * len(DEPTH_MODES)
    assert [c.resolution_mismatch() for c in cams] == [None] * len(cams)


@pytest.mark.parametrize("row", [[0, 0, 0, 0], [0.1, 0, 0, 2]])
def test_depth_to_color_with_another_last_row_is_refused(stex_ds, synth, row):
    """It was accepted and stored (transform_points uses the top 3x4 only, so never applied)."""
    cal = synth.cal.to_dict()
    cal["depth_to_color"][3] = row
    (stex_ds / "calibration.json").write_text(json.dumps(cal))
    with pytest.raises(ValueError, match=r"calibration\.json: invalid calibration \(depth_to_color's last row must "
                                         r"be \(0, 0, 0, 1\) \(a rigid transform\), got "
                                         + re.escape(str([float(x) for x in row])) + r": give \[\[R, t\], \[0, 0, 0, 1\]\]"):
        FolderDataset(stex_ds, "stex")


def test_depth_to_color_last_row_rounding_is_stored_exact_and_rotation_checked(synth):
    from stex.camera import Calibration

    T = synth.cal.depth_to_color.copy()
    T[3] = [1e-12, 0.0, 0.0, 1.0 - 1e-12]  # computed, not typed
    given = T.copy()
    cal = Calibration(synth.cal.color, synth.cal.depth, T)
    assert cal.depth_to_color[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_array_equal(T, given)  # the caller's matrix is not changed
    with pytest.raises(ValueError, match=r"not a proper rotation matrix \(R Rt differs from the identity by 0, det -1;"):
        Calibration(synth.cal.color, synth.cal.depth, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"not a proper rotation matrix \(R Rt differs from the identity by 0\.21, det 1\.1"):
        Calibration(synth.cal.color, synth.cal.depth, np.diag([1.1, 1.0, 1.0, 1.0]))


def test_frames_added_to_a_dataset_after_a_run_rewrite_the_scene_store(tmp_path, authors):
    """A folder dataset's frame list is found on disk: frames copied in after a run re-run the
    scene's ingest (and the new block's), so scene.zarr lists them. Before, only the new block
    was ingested, scene.zarr kept the old list and the projection failed blaming the tracking."""
    import subprocess
    import sys

    import yaml

    from conftest import REPO

    res = tmp_path / "results" / "ds"
    (tmp_path / "ds.yaml").write_text(yaml.safe_dump({
        "scene": "ds", "results": str(tmp_path / "results"), "frame_block": 2,
        "source": {"kind": "folder", "folder": {"path": str(authors), "layout": "authors"}}}))
    shutil.rmtree(authors / "mesh")  # per-frame meshes are inputs of the scene's ingest: the frames alone
    last = IDS[-1]
    aside = tmp_path / "aside"
    aside.mkdir()
    held = [authors / "stream" / d / f"Frame_{last:06d}.png" for d in ("color", "depth", "mask")]
    for k, f in enumerate(held):
        f.rename(aside / f"{k}.png")

    def snakemake(*args):
        blocks = [str(res / "frames" / f"block_{b:04d}.zarr") for b in range(2)]  # 3 or 4 frames, 2 a block
        run = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"),
                              "--directory", str(tmp_path), "--configfile", str(tmp_path / "ds.yaml"),
                              "--cores", "1", *args, str(res / "scene.zarr"), *blocks],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, (run.stdout + run.stderr)[-3000:]
        return run.stdout + run.stderr

    snakemake()
    assert open_store(res / "scene.zarr", "scene").attrs["frame_ids"] == IDS[:-1]
    assert "Nothing to be done" in snakemake("-n")
    for k, f in enumerate(held):
        (aside / f"{k}.png").rename(f)
    plan = snakemake("-n")
    assert "rule ingest_scene:" in plan, plan[-2000:]
    snakemake()
    assert open_store(res / "scene.zarr", "scene").attrs["frame_ids"] == IDS


def test_degenerate_triangles_count_as_the_same_with_their_corners_rotated():
    """A per-frame mesh's triangle counts as the template's with its corners rotated; that held
    for degenerate triangles (a vertex twice) only when the repeated vertex was not the smallest:
    [1, 3, 1] was refused against the template's [1, 1, 3] as 'not among the template's triangles'.
    The rotations of [1, 1, 3] are [1, 3, 1] and [3, 1, 1] (by hand); [1, 3, 3] is another triangle."""
    from stex.readers.meshes import Mesh, check_same_topology

    V, ref = np.zeros((4, 3)), np.array([[0, 1, 2], [1, 1, 3]])
    for F in ([[1, 3, 1], [0, 1, 2]], [[0, 1, 2], [1, 3, 1]], [[3, 1, 1], [2, 0, 1]]):
        check_same_topology(ref, 4, Mesh(V, np.array(F)), "f.off")
    with pytest.raises(ValueError, match=r"f\.off: .*its face 1 \[1, 3, 3\] is not among the template's triangles"):
        check_same_topology(ref, 4, Mesh(V, np.array([[0, 1, 2], [1, 3, 3]])), "f.off")
