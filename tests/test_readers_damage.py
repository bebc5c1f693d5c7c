"""Damaged or implausible input, found by a review of bad inputs: what the readers refuse, and
what the errors say (stex.readers.images, stex.readers.meshes, the tracking stage's scale check)."""

import os
import tempfile
import threading

import cv2
import numpy as np
import pytest

from conftest import data_samples
from stex.readers.meshes import load_mesh


def _jpeg(size=(160, 120)) -> bytes:
    """A real colour frame (DeepDeform seq017 frame 300, Structure sensor), resized and encoded;
    without the shared samples, a frame of the tiny synthetic scene."""
    path = data_samples() / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017" / "color" / "000300.jpg"
    if path.is_file():
        img = cv2.imread(str(path))
    else:
        from conftest import tiny_scene_config
        from stex.synth.scene import SyntheticScene

        img = SyntheticScene(tiny_scene_config()["source"]["synthetic"]).render_frame(0).color[..., ::-1]
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def _damaged(buf: bytes, n: int = 600) -> bytes:
    b = bytearray(buf)
    b[len(b) // 3: len(b) // 3 + n] = bytes(n)
    return bytes(b)


def test_decode_jpeg_refuses_damaged_data_and_passes_other_libjpeg_text_on(capfd):
    """cv2.imdecode decoded a JPEG zeroed inside to a full-size image; libjpeg's 'Corrupt JPEG
    data' went to stderr only. decode_jpeg raises with it; libjpeg's other warnings still reach
    stderr; an undecodable buffer gives None, as cv2.imdecode."""
    from stex.readers.images import decode_jpeg

    good = _jpeg()
    np.testing.assert_array_equal(decode_jpeg(good, cv2.IMREAD_COLOR, "good.jpg"),
                                  cv2.imdecode(np.frombuffer(good, np.uint8), cv2.IMREAD_COLOR))
    with pytest.raises(ValueError, match=r"^frame 3: the JPEG's data is damaged \(libjpeg: 'Corrupt JPEG data: "):
        decode_jpeg(_damaged(good), cv2.IMREAD_COLOR, "frame 3")
    assert "Corrupt JPEG data" not in capfd.readouterr().err  # in the error, not on stderr
    odd = bytearray(good)
    i = odd.find(b"JFIF\x00")
    odd[i + 5] = 2  # JFIF version 2.01: libjpeg warns, the pixels are fine
    np.testing.assert_array_equal(decode_jpeg(bytes(odd), cv2.IMREAD_COLOR, "odd.jpg"),
                                  decode_jpeg(good, cv2.IMREAD_COLOR, "good.jpg"))
    assert "unknown JFIF revision number 2.01" in capfd.readouterr().err
    assert decode_jpeg(b"", cv2.IMREAD_COLOR, "empty") is None
    assert decode_jpeg(b"\xff\xd8 not a jpeg \xff\xd9", cv2.IMREAD_COLOR, "junk") is None
    os.write(2, b"after\n")  # stderr is back where it was
    assert capfd.readouterr().err == "after\n"


def test_extraneous_bytes_can_be_the_only_sign_of_damage():
    """Why "N extraneous bytes before marker" stays among the warnings that refuse a JPEG,
    although some webcams' MJPEG encoders cause it on intact frames (docs/datasets.md): with
    restart markers (RST every 4 MCUs, as MJPEG cameras write them), 200 bytes zeroed in the
    middle are reported only so, and rows of the image are wrong."""
    from stex.readers.images import _stderr_into, decode_jpeg

    img = cv2.imdecode(np.frombuffer(_jpeg((320, 240)), np.uint8), cv2.IMREAD_COLOR)
    enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_RST_INTERVAL, 4])[1].ravel()
    whole = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    damaged = enc.copy()
    damaged[len(enc) // 2: len(enc) // 2 + 200] = 0
    with tempfile.TemporaryFile() as log:
        with _stderr_into(log):
            wrong = cv2.imdecode(damaged, cv2.IMREAD_COLOR)
        log.seek(0)
        said = log.read().decode().strip().splitlines()
    assert len(said) == 1 and "extraneous bytes before marker 0xd" in said[0], said
    assert wrong.shape == whole.shape and (wrong != whole).any(axis=(1, 2)).sum() >= 8
    with pytest.raises(ValueError, match=r"^frame 7: the JPEG's data is damaged \(libjpeg: 'Corrupt JPEG data: "
                                         r"\d+ extraneous bytes before marker"):
        decode_jpeg(damaged, cv2.IMREAD_COLOR, "frame 7")


def test_decode_jpeg_from_threads_blames_the_damaged_file_only():
    """stderr is the process's: decodes in threads must not take each other's libjpeg warnings."""
    from stex.readers.images import decode_jpeg

    good, bad = _jpeg((320, 240)), _damaged(_jpeg((320, 240)))
    errors = {}

    def run(name, buf):
        for _ in range(10):
            try:
                decode_jpeg(buf, cv2.IMREAD_COLOR, name)
            except ValueError as e:
                errors.setdefault(name, []).append(str(e))

    threads = [threading.Thread(target=run, args=(f"{kind}{k}", buf))
               for k in range(2) for kind, buf in (("good", good), ("bad", bad))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(errors) == ["bad0", "bad1"] and all(len(v) == 10 for v in errors.values())
    assert all(e.startswith(name + ": the JPEG's data is damaged") for name, v in errors.items() for e in v)


def _obj(path, vt_line="vt 0.5 0.5", v_line="v 0 1 0"):
    path.write_text(f"# tri\nv 0 0 0\nv 1 0 0\n{v_line}\nvt 0 0\nvt 1 0\n{vt_line}\nf 1/1 2/2 3/3\n")
    return path


def test_obj_with_non_finite_texture_coordinates_or_vertices_names_the_line(tmp_path):
    """'vt nan 0.5' in a template was accepted; the scene store then refused 'scene/template/texcoords:
    non-finite values', naming neither the file nor the line."""
    m = load_mesh(_obj(tmp_path / "ok.obj"))
    assert np.isfinite(m.texcoords).all()
    with pytest.raises(ValueError, match=r"bad\.obj:7: texture coordinate 2 is not finite: 'vt nan 0\.5'"):
        load_mesh(_obj(tmp_path / "bad.obj", vt_line="vt nan 0.5"))
    with pytest.raises(ValueError, match=r"inf\.obj:4: vertex 2 is not finite: 'v 0 inf 0'"):
        load_mesh(_obj(tmp_path / "inf.obj", v_line="v 0 inf 0"))


def test_ingest_names_the_template_with_a_non_finite_texture_coordinate(tmp_path):
    """End to end: write_scene fails naming the template file and line (before: a StoreError about
    'scene/template/texcoords')."""
    import json

    from stex.stages.ingest import write_scene
    from test_folder import IDS, folder_cfg
    cal = {"color": {"fx": 140.0, "fy": 140.0, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120},
           "depth": {"fx": 63.0, "fy": 63.0, "cx": 39.5, "cy": 35.5, "width": 80, "height": 72},
           "depth_to_color": np.eye(4).tolist()}
    root = tmp_path / "ds"
    for d in ("color", "depth"):
        (root / d).mkdir(parents=True)
    (root / "calibration.json").write_text(json.dumps(cal))
    for fid in IDS:
        cv2.imwrite(str(root / "color" / f"{fid:06d}.png"), np.zeros((120, 160, 3), np.uint8))
        cv2.imwrite(str(root / "depth" / f"{fid:06d}.png"), np.full((72, 80), 1000, np.uint16))
    _obj(root / "template.obj", vt_line="vt nan 0.5")
    with pytest.raises(ValueError, match=r"template\.obj:7: texture coordinate 2 is not finite"):
        write_scene(folder_cfg(root, "stex"), 2, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()


def test_depth_scale_error_names_the_masks_as_a_cause():
    """With an inverted mask the tracker reads the depth where the mask puts the object: the
    background, around the mesh's outline. The ratio is far off, as for a mesh in other units, and
    the error blamed the units alone."""
    from stex.render import rasterize
    from stex.synth.shapes import bumpy_sphere
    from stex.stages.tracking import _check_depth_scale
    from stex.tracking import depth_target

    K = np.array([[200.0, 0, 119.5], [0, 200.0, 89.5], [0, 0, 1]])
    V, F = bumpy_sphere(subdivisions=3, radius=0.3, distance=1.2)
    sphere = rasterize(V, F, K, 240, 180).depth.astype(np.float64)
    depth = np.where(sphere > 0, sphere, 3.0)  # the object before a wall 3 m away
    c = V.mean(0)
    mesh = (V - c) * 1.08 + c  # a mesh a little larger than the object: its outline overlaps the wall
    _check_depth_scale(mesh, F, depth_target(depth, K, sphere > 0), 0, "t.zarr")  # the right mask: fine
    with pytest.raises(ValueError, match=r"t\.zarr: at frame 0 the mesh lies 0\.\d+ times as far .* in metres .* "
                       r"a mask that marks the background instead \(an inverted mask\) gives such a ratio too"):
        _check_depth_scale(mesh, F, depth_target(depth, K, ~(sphere > 0)), 0, "t.zarr")


def test_border_foreground_counts_each_border_pixel_once():
    """A 4x5 image has 2 * 5 + 2 * (4 - 2) = 14 border pixels (corners once). Its first column (4
    pixels, 2 of them corners) as foreground is 4/14 of the border; the top row alone 5/14."""
    from stex.readers.images import border_foreground

    m = np.zeros((4, 5), bool)
    m[:, 0] = True
    assert border_foreground(m) == pytest.approx(4 / 14)
    m = np.zeros((4, 5), bool)
    m[0] = True
    assert border_foreground(m) == pytest.approx(5 / 14)


def test_check_mask_refuses_more_than_half_of_the_border_as_foreground():
    """Of the 14 border pixels of a 4x5 mask, 7 as foreground (the top row and two of the left
    column's middle pixels: exactly half) is accepted; one more (8/14, 57 %) is refused."""
    from stex.readers.images import check_mask

    m = np.zeros((4, 5), bool)
    m[0] = True
    m[1:3, 0] = True
    check_mask(m, "half.png")
    m[1, 4] = True
    with pytest.raises(ValueError, match=r"^more\.png: the mask's foreground covers 57 % of the image border"):
        check_mask(m, "more.png")
