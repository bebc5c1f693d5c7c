"""Tests for stex.export on a tiny textured cube: PNG, MP4, OBJ, glTF, previews, store reading."""

from __future__ import annotations

import json
import struct
from fractions import Fraction

import av
import numpy as np
import pytest
import trimesh
import zarr
from PIL import Image

from stex.camera import Calibration, Intrinsics
from stex.export import (
    opencv_to_viewer,
    parse_frame_range,
    preview_frame,
    select_frames,
    split_seams,
    write_gltf_frame,
    write_obj_frame,
    write_obj_sequence,
    write_png_slices,
    write_texture_video,
)
from stex.io import StoreError, create_store
from stex.stages.export import export_results

W = 64  # texture side
FRAME_IDS = [10, 11, 12, 13, 14]
BLOCKS = [[10, 11, 12], [13, 14]]
CENTER = np.array([0.0, 0.0, 0.6])
HALF = 0.1

# Cube sides as (outward normal, u axis, v axis) with u x v = normal, so the corners
# c - u - v, c + u - v, c + u + v, c - u + v are counter-clockwise seen from outside.
SIDES = [((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
         ((0, 1, 0), (0, 0, 1), (1, 0, 0)), ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
         ((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (0, 1, 0), (1, 0, 0))]
SIDE_FRONT, SIDE_BACK = 5, 4  # -z faces the camera, +z faces away


def cube():
    """A cube in front of the camera: 8 vertices, 12 faces, one UV chart per side (24 texcoords,
    seams everywhere) in a 3 x 2 grid of cells of the atlas."""
    corners, faces, tcs, tfaces = [], [], [], []
    quad = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)], float)
    for s, (n, u, v) in enumerate(SIDES):
        n, u, v = (np.array(a, float) for a in (n, u, v))
        idx = []
        for a, b in quad:
            p = CENTER + HALF * (n + a * u + b * v)
            key = tuple(np.round(p, 6))
            if key not in corners:
                corners.append(key)
            idx.append(corners.index(key))
        cell = np.array([s % 3 / 3, s // 3 / 2])
        t0 = len(tcs)
        tcs += [cell + np.array([(a + 1) / 2 * 0.8 + 0.1, (b + 1) / 2 * 0.8 + 0.1]) * [1 / 3, 1 / 2]
                for a, b in quad]
        faces += [[idx[0], idx[1], idx[2]], [idx[0], idx[2], idx[3]]]
        tfaces += [[t0, t0 + 1, t0 + 2], [t0, t0 + 2, t0 + 3]]
    return (np.array(corners, np.float32), np.array(faces, np.int32),
            np.array(tcs, np.float32), np.array(tfaces, np.int32))


def gradient_texture(t=0, w=W):
    """(w, w, 3) uint8, a different smooth colour per texel: R down the rows, G along columns."""
    r, c = np.mgrid[0:w, 0:w]
    return np.stack([4 * r, 4 * c, (255 - 2 * (r + c) + 7 * t) % 256], -1).astype(np.uint8)


def rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def frame_vertices(V, t):
    return ((V - CENTER) @ rot_y(5.0 * t).T + CENTER).astype(np.float32)


def calibration():
    color = Intrinsics.from_focal(80.0, 80.0, 39.5, 29.5, 80, 60)
    return Calibration(color, color, np.eye(4))


def sample(image, uv_pixels):
    """Bilinear lookup of an (H, W, C) image at (N, 2) pixel coordinates (u column, v row)."""
    img = np.asarray(image, np.float64)
    u = np.clip(uv_pixels[:, 0], 0, img.shape[1] - 1)
    v = np.clip(uv_pixels[:, 1], 0, img.shape[0] - 1)
    c0, r0 = np.floor(u).astype(int), np.floor(v).astype(int)
    c1, r1 = np.minimum(c0 + 1, img.shape[1] - 1), np.minimum(r0 + 1, img.shape[0] - 1)
    a, b = (u - c0)[:, None], (v - r0)[:, None]
    return ((1 - a) * (1 - b) * img[r0, c0] + a * (1 - b) * img[r0, c1]
            + (1 - a) * b * img[r1, c0] + a * b * img[r1, c1])


def expected_centroid_colors(tc, tf, tex):
    """Colour of the stex texture at each face's UV centroid (v down from the top row)."""
    cen = tc[tf].astype(np.float64).mean(axis=1)
    return sample(tex, np.column_stack([cen[:, 0] * tex.shape[1] - 0.5, cen[:, 1] * tex.shape[0] - 0.5]))


def loaded_centroid_colors(mesh):
    """Colour at each face's UV centroid of a mesh loaded by trimesh (its uv has v up, OBJ style)."""
    mat = mesh.visual.material  # OBJ: SimpleMaterial (.image), glTF: PBRMaterial (.baseColorTexture)
    img = np.asarray(getattr(mat, "baseColorTexture", None) or mat.image)
    cen = np.asarray(mesh.visual.uv)[mesh.faces].mean(axis=1)
    return sample(img, np.column_stack([cen[:, 0] * img.shape[1] - 0.5, (1 - cen[:, 1]) * img.shape[0] - 0.5])), img


def make_results(root, volume=True, corrected=True):
    """Stores of a 5-frame scene (frame ids 10..14, two blocks) as the workflow lays them out."""
    V, F, tc, tf = cube()
    cal = calibration()
    with create_store(root / "scene.zarr", "scene",
                      attrs={"calibration": cal.to_dict(), "frame_ids": FRAME_IDS,
                             "frame_blocks": [[0, 3], [3, 5]], "has_template": False}):
        pass
    with create_store(root / "template.zarr", "template", attrs={"atlas_size": W}) as s:
        s.write("vertices", V)
        s.write("faces", F)
        s.write("texcoords", tc)
        s.write("texcoord_faces", tf)
        s.write("face_chart", np.arange(len(F)) // 2)
        s.write("adjacency/pairs", np.zeros((0, 2), np.int32))
        s.write("adjacency/edges", np.zeros((0, 2), np.int32))
        s.write("texel/face_id", -np.ones((W, W), np.int32))
        s.write("texel/bary", np.zeros((W, W, 3), np.float32))
        s.write("embedding/face", np.zeros(len(V), np.int32))
        s.write("embedding/bary", np.zeros((len(V), 3), np.float32))
    with create_store(root / "tracking.zarr", "tracking", attrs={"frame_ids": FRAME_IDS, "mode": "given"}) as s:
        s.write("vertices", np.stack([frame_vertices(V, t) for t in range(len(FRAME_IDS))]))
        s.write("residual_m", np.zeros(len(FRAME_IDS)))
        s.write("n_correspondences", np.zeros(len(FRAME_IDS), np.int32))
        s.write("seconds", np.zeros(len(FRAME_IDS)))
        s.write("silhouette_iou", np.ones(len(FRAME_IDS)))
        s.write("depth_fit_m", np.zeros(len(FRAME_IDS)))
        s.attrs["poorly_fitted_frames"] = []
    rng = np.random.default_rng(0)
    for b, ids in enumerate(BLOCKS):
        ts = [FRAME_IDS.index(i) for i in ids]
        with create_store(root / "frames" / f"block_{b:04d}.zarr", "frames", attrs={"frame_ids": ids}) as s:
            s.write("color", rng.integers(0, 256, (len(ids), 60, 80, 3), dtype=np.uint8))
            s.write("depth", np.zeros((len(ids), 60, 80), np.uint16))
            s.write("timestamps", np.array(ts, float) / 15.0)
        for kind, offset in (("volume", 0), ("corrected", 100)):
            if not (volume if kind == "volume" else corrected):
                continue
            with create_store(root / kind / f"block_{b:04d}.zarr", kind,
                              attrs={"frame_ids": ids, "gutter_px": 2}) as s:
                s.write("texture", np.stack([gradient_texture(t + offset) for t in ts]))
                if kind == "volume":
                    s.write("label_map", np.zeros((len(ids), W, W), np.int16))
    return root


# --------------------------------------------------------------------------------------------


def test_png_slices_round_trip_exactly(tmp_path):
    texs = [gradient_texture(t) for t in range(3)]
    paths = write_png_slices(iter(texs), [7, 8, 9], tmp_path / "png")
    assert [p.name for p in paths] == ["texture_00007.png", "texture_00008.png", "texture_00009.png"]
    for p, t in zip(paths, texs):
        np.testing.assert_array_equal(np.asarray(Image.open(p)), t)
    with pytest.raises(ValueError, match="frame_ids"):
        write_png_slices(iter(texs), [1, 2], tmp_path / "bad")
    with pytest.raises(ValueError, match="uint8"):
        write_png_slices([texs[0].astype(np.float32)], [1], tmp_path / "bad")


def _read_video(path):
    with av.open(str(path)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        rate = c.streams.video[0].average_rate
    return frames, rate


@pytest.mark.parametrize("w", [64, 63])
def test_texture_video_reads_back(tmp_path, w):
    texs = [gradient_texture(t, w) for t in range(4)]
    seen = []
    n, ew, eh = write_texture_video(iter(texs), tmp_path / "t.mp4", fps=15, crf=12, total=4,
                                    progress=lambda d, t: seen.append((d, t)))
    assert (n, ew, eh) == (4, 64, 64)  # odd sizes padded to even
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]
    frames, rate = _read_video(tmp_path / "t.mp4")
    assert len(frames) == 4 and frames[0].shape == (64, 64, 3) and rate == 15
    # chroma subsampling and x264 loss on a smooth gradient: small mean error, content in place
    for f, t in zip(frames, texs):
        assert np.abs(f[:w, :w].astype(int) - t).mean() < 3.0
    assert not list(tmp_path.glob(".*partial*"))
    write_texture_video(iter(texs), tmp_path / "again.mp4", fps=15, crf=12)
    assert (tmp_path / "again.mp4").read_bytes() == (tmp_path / "t.mp4").read_bytes()  # deterministic


def test_yuv444_keeps_odd_size_and_colour_detail(tmp_path):
    # a colour checkerboard of single texels: yuv420p averages its chroma away, yuv444p keeps it
    r, c = np.mgrid[0:63, 0:63]
    tex = np.where(((r + c) % 2 == 0)[..., None], [200, 40, 40], [40, 40, 200]).astype(np.uint8)
    err = {}
    for fmt in ("yuv420p", "yuv444p"):
        n, w, h = write_texture_video([tex] * 2, tmp_path / f"{fmt}.mp4", crf=0, pix_fmt=fmt)
        frames, _ = _read_video(tmp_path / f"{fmt}.mp4")
        assert (n, len(frames)) == (2, 2) and frames[0].shape == ((64, 64, 3) if fmt == "yuv420p" else (63, 63, 3))
        err[fmt] = np.abs(frames[0][:63, :63].astype(int) - tex).mean()
    assert err["yuv444p"] < 3 < 30 < err["yuv420p"], err
    with pytest.raises(ValueError, match="pix_fmt"):
        write_texture_video([tex], tmp_path / "x.mp4", pix_fmt="rgb24")


def test_video_rejects_mixed_sizes_and_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="video frame 1 has size 32x32"):
        write_texture_video([gradient_texture(0), gradient_texture(0, 32)], tmp_path / "x.mp4")
    assert list(tmp_path.iterdir()) == []


def test_split_seams_one_vertex_per_corner_pair():
    _, F, _, tf = cube()
    vi, ti, nf = split_seams(F, tf)
    assert len(vi) == len({(a, b) for a, b in zip(F.ravel(), tf.ravel())}) == 24
    np.testing.assert_array_equal(vi[nf], F)
    np.testing.assert_array_equal(ti[nf], tf)


def _faces_positions(mesh):
    return np.asarray(mesh.vertices)[np.asarray(mesh.faces)]


def test_obj_frame_geometry_and_texture_mapping(tmp_path):
    V, F, tc, tf = cube()
    tex = gradient_texture(3)
    Image.fromarray(tex).save(tmp_path / "tex.png")
    obj, mtl = write_obj_frame(tmp_path / "m.obj", V, F, tc, tf, "tex.png")
    assert "map_Kd tex.png" in mtl.read_text()
    vt = np.array([[float(x) for x in line.split()[1:]] for line in obj.read_text().splitlines()
                   if line.startswith("vt ")])
    np.testing.assert_allclose(vt, np.column_stack([tc[:, 0], 1 - tc[:, 1]]), atol=1e-7)  # OBJ v up
    m = trimesh.load(obj, process=False)
    assert len(m.faces) == len(F)
    np.testing.assert_allclose(_faces_positions(m), opencv_to_viewer(V)[F], atol=1e-6)
    got, img = loaded_centroid_colors(m)
    assert img.shape == (W, W, 3)
    np.testing.assert_allclose(got, expected_centroid_colors(tc, tf, tex), atol=1.0)
    # the viewer-axes mesh keeps outward normals (proper rotation): volume positive
    assert m.volume > 0 and abs(m.volume - (2 * HALF) ** 3) < 1e-6


def test_obj_sequence_writes_obj_mtl_png_per_frame(tmp_path):
    V, F, tc, tf = cube()
    texs = [gradient_texture(t) for t in range(2)]
    paths = write_obj_sequence([frame_vertices(V, t) for t in range(2)], F, tc, tf, texs, [4, 5], tmp_path)
    assert [p.name for p in paths] == ["frame_00004.obj", "frame_00005.obj"]
    for t, p in enumerate(paths):
        np.testing.assert_array_equal(np.asarray(Image.open(p.with_suffix(".png"))), texs[t])
        m = trimesh.load(p, process=False)
        np.testing.assert_allclose(_faces_positions(m), opencv_to_viewer(frame_vertices(V, t))[F], atol=1e-6)


def _glb_texcoords(path):
    """TEXCOORD_0 of the first primitive, parsed from the .glb bytes (no trimesh)."""
    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    gl = json.loads(data[20:20 + jlen])
    binary = data[20 + jlen + 8:]
    acc = gl["accessors"][gl["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    view = gl["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    assert acc["componentType"] == 5126 and "byteStride" not in view
    return np.frombuffer(binary, np.float32, acc["count"] * 2, start).reshape(-1, 2), gl


def test_gltf_frame_loads_with_texture(tmp_path):
    V, F, tc, tf = cube()
    tex = gradient_texture(5)
    path = tmp_path / "f.glb"
    write_gltf_frame(path, V, F, tc, tf, tex)
    m = trimesh.load(path, force="mesh")
    assert len(m.vertices) == 24 and len(m.faces) == len(F)
    np.testing.assert_allclose(_faces_positions(m), opencv_to_viewer(V)[F], atol=1e-6)
    got, img = loaded_centroid_colors(m)
    assert img.shape == (W, W, 3)
    np.testing.assert_array_equal(img, tex)  # PNG embedded losslessly
    np.testing.assert_allclose(got, expected_centroid_colors(tc, tf, tex), atol=1.0)
    # glTF's own texcoords are v down from the top row: the stex values, unflipped
    raw, gl = _glb_texcoords(path)
    _, ti, _ = split_seams(F, tf)
    np.testing.assert_allclose(raw, tc[ti], atol=1e-6)
    assert gl["images"][0]["mimeType"] == "image/png"
    # smooth normals, computed before the seam split, point out of the cube
    assert "NORMAL" in gl["meshes"][0]["primitives"][0]["attributes"]
    outward = np.asarray(m.vertices) - opencv_to_viewer(CENTER)
    assert (np.sum(np.asarray(m.vertex_normals) * outward, axis=1) > 0.5 * np.linalg.norm(outward, axis=1)).all()


def _glb_attribute(path, name, width):
    """A float32 vertex attribute of the first primitive, parsed from the .glb bytes (no trimesh)."""
    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    gl = json.loads(data[20:20 + jlen])
    acc = gl["accessors"][gl["meshes"][0]["primitives"][0]["attributes"][name]]
    view = gl["bufferViews"][acc["bufferView"]]
    assert acc["componentType"] == 5126 and "byteStride" not in view
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(data[20 + jlen + 8:], np.float32, acc["count"] * width, start).reshape(-1, width), gl


def test_gltf_normals_smooth_across_seams_and_material_double_sided(tmp_path):
    """Every side of the cube is its own chart, so each corner is three .glb vertices: they carry
    one normal, the area-weighted normal of the unsplit mesh (sum of the incident faces'
    (v1 - v0) x (v2 - v0), here in viewer axes), not their side's face normal (shading would show
    the seams). The material is double-sided (open templates show their inside), metallic 0,
    roughness 1."""
    V, F, tc, tf = cube()
    path = tmp_path / "f.glb"
    write_gltf_frame(path, V, F, tc, tf, gradient_texture(0))
    pos, gl = _glb_attribute(path, "POSITION", 3)
    nrm, _ = _glb_attribute(path, "NORMAL", 3)
    assert len(pos) == 24
    v = opencv_to_viewer(V)
    cross = np.cross(v[F[:, 1]] - v[F[:, 0]], v[F[:, 2]] - v[F[:, 0]])
    want = np.zeros_like(v)
    for k in range(3):
        np.add.at(want, F[:, k], cross)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    corner = np.argmin(np.linalg.norm(pos[:, None] - v[None], axis=2), axis=1)
    assert np.abs(pos - v[corner]).max() < 1e-6 and np.bincount(corner).tolist() == [3] * 8
    np.testing.assert_allclose(nrm, want[corner], atol=1e-6)
    mat = gl["materials"][0]
    assert mat["doubleSided"] is True
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0
    assert mat["pbrMetallicRoughness"]["roughnessFactor"] == 1


def test_video_keeps_a_fractional_frame_rate(tmp_path):
    """29.97 fps is written as 2997/100 (not rounded to 30: a 10-minute video would drift by 0.6 s);
    NTSC's 30000/1001 as a float keeps its exact rate."""
    tex = gradient_texture(0, 16)
    for fps, want in ((29.97, Fraction(2997, 100)), (30000 / 1001, Fraction(30000, 1001))):
        write_texture_video([tex] * 3, tmp_path / "v.mp4", fps=fps)
        with av.open(str(tmp_path / "v.mp4")) as c:
            assert c.streams.video[0].average_rate == want
            times = [float(f.time) for f in c.decode(video=0)]
        np.testing.assert_allclose(times, np.arange(3) / float(want), atol=1e-9)


def test_frame_range_parsing_and_selection():
    assert parse_frame_range("10:20") == (10, 20)
    assert parse_frame_range("12") == (12, 13)
    assert parse_frame_range(":3") == (None, 3) and parse_frame_range(None) == (None, None)
    with pytest.raises(ValueError, match="START:STOP"):
        parse_frame_range("a:b")
    assert select_frames(FRAME_IDS, 11, 13) == [11, 12]
    assert select_frames(FRAME_IDS, None, None) == FRAME_IDS
    with pytest.raises(ValueError, match=r"outside the sequence \(frames 10..14\)"):
        select_frames(FRAME_IDS, 0, 3)
    with pytest.raises(ValueError, match="outside"):
        select_frames(FRAME_IDS, 12, 12)


def test_preview_frame_shows_front_and_back(tmp_path):
    V, F, tc, tf = cube()
    tex = gradient_texture(0)
    color = np.random.default_rng(1).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    img = preview_frame(color, V, F, tc, tf, tex, calibration(), size=60, frame_id=3)
    assert img.shape == (60, 240, 3)
    inp, front, back = img[:, :80], img[:, 80:160], img[:, 160:]
    np.testing.assert_array_equal(inp[30:], color[30:])  # same size: the input unchanged below the label
    assert (inp[:6] == 255).any()  # a label was drawn
    cells = np.array([[s % 3 / 3 + 1 / 6, s // 3 / 2 + 1 / 4] for s in range(6)])
    chart_colors = sample(tex, cells * W - 0.5)
    for panel, side in ((front, SIDE_FRONT), (back, SIDE_BACK)):
        centre = panel[29:31, 39:41].reshape(-1, 3).astype(float).mean(0)
        dist = np.abs(chart_colors - centre).max(axis=1)
        assert dist.argmin() == side and dist[side] < 10, (side, dist)
    with pytest.raises(ValueError, match="calibrated colour camera is 80x60"):
        preview_frame(color[:50], V, F, tc, tf, tex, calibration())


def test_export_results_reads_stores(tmp_path):
    res = make_results(tmp_path / "res")
    paths = export_results(res, "png", tmp_path / "png", frames="11:13", source="volume")
    assert [p.name for p in paths] == ["texture_00011.png", "texture_00012.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(paths[1])), gradient_texture(2))
    paths = export_results(res, "gltf", tmp_path / "glb", frames="14")
    m = trimesh.load(paths[0], force="mesh")
    np.testing.assert_allclose(_faces_positions(m), opencv_to_viewer(frame_vertices(cube()[0], 4))[cube()[1]], atol=1e-6)
    got, img = loaded_centroid_colors(m)
    np.testing.assert_array_equal(img, gradient_texture(104))  # corrected is the default source
    paths = export_results(res, "mp4", tmp_path / "mp4")
    frames, rate = _read_video(paths[0])
    assert len(frames) == 5 and rate == 15  # fps from the frames' timestamps
    zarr.open_group(str(res / "volume" / "block_0001.zarr"), mode="r+").attrs["complete"] = False
    with pytest.raises(StoreError, match="block_0001.zarr: store is incomplete"):
        export_results(res, "png", tmp_path / "x", source="volume")


def test_non_finite_tracked_vertices_name_their_store_and_frame(tmp_path):
    """A store written before chunk checksums and damaged in place can decode to garbage: the
    export names the store and frame, not only the writer's "vertices must be finite"."""
    res = make_results(tmp_path / "res")
    zarr.open_group(str(res / "tracking.zarr"), mode="r+")["vertices"][2, 3] = np.nan
    with pytest.raises(StoreError, match=r"tracking\.zarr: the vertices of frame 12 are not finite; "
                                         r"the store is damaged"):
        export_results(res, "obj", tmp_path / "obj", frames="11:14")
    assert len(export_results(res, "gltf", tmp_path / "glb", frames="13:")) == 2


def test_sequence_writers_refuse_names_that_collide(tmp_path):
    """Repeated frame ids (or a pattern without {frame}) wrote one file and returned two paths."""
    import numpy as np

    from stex import export

    tex = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="share the file names"):
        export.write_png_slices([tex, tex], [5, 5], tmp_path / "a")
    with pytest.raises(ValueError, match="share the file names"):
        export.write_png_slices([tex, tex], [5, 6], tmp_path / "b", pattern="slice.png")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(ValueError, match="positive finite number"):
        export.write_video([tex], tmp_path / "v.mp4", fps="30")


def test_a_folder_of_another_export_is_not_mixed_into(tmp_path):
    """An export of frames 2-3 into a folder holding an earlier export of 0-3 would leave a set
    of four that reads as one: refused before anything is written; the same frames again, or a
    folder with unrelated files, are fine."""
    texs = [gradient_texture(t) for t in range(4)]
    write_png_slices(iter(texs), [0, 1, 2, 3], tmp_path / "png")
    (tmp_path / "png" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"already holds 2 file\(s\) of other frames \(texture_00000.png, "
                                         r"texture_00001.png\)"):
        write_png_slices(iter(texs[2:]), [2, 3], tmp_path / "png")
    assert np.array_equal(np.asarray(Image.open(tmp_path / "png" / "texture_00002.png")), texs[2])
    again = write_png_slices(iter(texs[::-1]), [0, 1, 2, 3], tmp_path / "png")   # re-export: replaced
    np.testing.assert_array_equal(np.asarray(Image.open(again[0])), texs[3])
    V, F, tc, tf = cube()
    write_obj_sequence([V, V], F, tc, tf, texs[:2], [4, 5], tmp_path / "obj")
    with pytest.raises(ValueError, match=r"3 file\(s\) of other frames \(frame_00005.mtl, frame_00005.obj, "):
        write_obj_sequence([V], F, tc, tf, texs[:1], [4], tmp_path / "obj")


def add_global_texture(root, atlas_digest=None):
    """A global_texture store beside make_results' stores: one texture for the whole sequence."""
    attrs = {"source_frames": FRAME_IDS[::2], "sequence_frame_ids": FRAME_IDS, "seconds": 0.1}
    if atlas_digest:
        attrs["atlas_digest"] = atlas_digest
    with create_store(root / "global_texture.zarr", "global_texture", attrs=attrs) as s:
        s.write("texture", gradient_texture(50))
        s.write("weight_sum", np.ones((W, W), np.float32))
        s.write("face_textured", np.ones(len(cube()[1]), bool))
    return root


def test_every_nth_frame_is_exported_and_the_video_keeps_its_pace(tmp_path):
    res = make_results(tmp_path / "res")
    paths = export_results(res, "png", tmp_path / "png", source="volume", every=2)
    assert [p.name for p in paths] == ["texture_00010.png", "texture_00012.png", "texture_00014.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(paths[2])), gradient_texture(4))
    paths = export_results(res, "obj", tmp_path / "obj", frames="11:", every=3)
    assert [p.name for p in paths] == ["frame_00011.obj", "frame_00014.obj"]
    m = trimesh.load(paths[1], force="mesh")
    np.testing.assert_allclose(_faces_positions(m), opencv_to_viewer(frame_vertices(cube()[0], 4))[cube()[1]], atol=1e-6)
    frames, rate = _read_video(export_results(res, "mp4", tmp_path / "mp4", every=2)[0])
    assert len(frames) == 3 and rate == Fraction(15, 2)  # frames 15 fps apart, every 2nd: 7.5 fps
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="frame step must be an integer of 1 or more"):
            export_results(res, "png", tmp_path / "bad", every=bad)
    assert select_frames(FRAME_IDS, 11, None, every=2) == [11, 13]


def test_the_global_texture_exports_as_one_image_and_on_the_meshes(tmp_path):
    res = add_global_texture(make_results(tmp_path / "res"))
    (png,) = export_results(res, "png", tmp_path / "png", source="global")
    assert png.name == "global_texture.png"
    np.testing.assert_array_equal(np.asarray(Image.open(png)), gradient_texture(50))
    objs = export_results(res, "obj", tmp_path / "obj", source="global", every=2)
    assert [p.name for p in objs] == ["frame_00010.obj", "frame_00012.obj", "frame_00014.obj"]
    # one PNG for all frames, named by every MTL
    assert sorted(p.name for p in (tmp_path / "obj").glob("*.png")) == ["global_texture.png"]
    for p in objs:
        m = trimesh.load(p, force="mesh")
        got, img = loaded_centroid_colors(m)
        np.testing.assert_array_equal(img, gradient_texture(50))
    (glb,) = export_results(res, "gltf", tmp_path / "glb", source="global", frames="13")
    got, img = loaded_centroid_colors(trimesh.load(glb, force="mesh"))
    np.testing.assert_array_equal(img, gradient_texture(50))
    with pytest.raises(ValueError, match="not a video"):
        export_results(res, "mp4", tmp_path / "mp4", source="global")
    with pytest.raises(ValueError, match="--frames and --every do not apply"):
        export_results(res, "png", tmp_path / "png2", source="global", every=2)
    add_global_texture(make_results(tmp_path / "other"), atlas_digest="another-atlas")
    with pytest.raises(ValueError, match="global_texture.zarr holds textures of another UV atlas"):
        export_results(tmp_path / "other", "png", tmp_path / "png3", source="global")
    with pytest.raises(StoreError, match="global_texture.zarr: no such store"):
        export_results(make_results(tmp_path / "none"), "png", tmp_path / "png4", source="global")
