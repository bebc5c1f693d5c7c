"""Ingest of recordings into the scene/frames stores (the synthetic and folder sources have their
own test files)."""
import numpy as np
import pytest

from conftest import data_samples
from stex.config import load_config
from stex.ingest import count_frames, frame_blocks
from stex.stages.ingest import write_frames_block, write_scene
from stex.io import open_store
from test_kinect_mkv import synthetic_mkv  # noqa: F401  (fixture)

REAL_MKV = data_samples() / "azure_kinect_pyk4a" / "recording.mkv"


def test_frame_blocks():
    assert frame_blocks(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert frame_blocks(9, 4) == [(0, 4), (4, 8), (8, 9)]  # a last block of one frame
    assert frame_blocks(3, 5) == [(0, 3)]
    with pytest.raises(ValueError):
        frame_blocks(0, 4)


def _mkv_source(path, **kw):
    return load_config(overrides={"source": {"kind": "mkv", "mkv": {"path": str(path), **kw}}})["source"]


def test_mkv_ingest_of_a_written_recording(synthetic_mkv, tmp_path):  # noqa: F811
    synthetic_mkv = synthetic_mkv[0]
    from stex.readers.kinect_mkv import open_kinect_mkv
    src = _mkv_source(synthetic_mkv, undistort=False, start=2, stop=7)
    assert count_frames(src) == 5
    # a stop past the end of the 10 captures reads to the end: captures 7, 8, 9
    assert count_frames(_mkv_source(synthetic_mkv, undistort=False, start=7, stop=50)) == 3
    write_scene(src, 3, tmp_path / "scene.zarr")
    scene = open_store(tmp_path / "scene.zarr", "scene")
    assert scene.attrs["frame_ids"] == [2, 3, 4, 5, 6] and scene.attrs["has_template"] is False
    write_frames_block(src, 3, 5, tmp_path / "b1.zarr")
    frames = open_store(tmp_path / "b1.zarr", "frames")
    assert frames.attrs["frame_ids"] == [5, 6]
    with open_kinect_mkv(synthetic_mkv) as rec:
        _, ts, color, depth = next(iter(rec.frames(5, 6)))
    assert np.array_equal(frames["depth"][0], depth)
    assert np.array_equal(frames["color"][0], color)
    assert frames["timestamps"][0] == pytest.approx(ts * 1e-6)
    # what the workflow makes the ingest rules' inputs: the recording (and a template, if named)
    from stex.ingest import open_source
    assert open_source(src).files() == open_source(src).files(3, 5) == [synthetic_mkv]
    src_t = _mkv_source(synthetic_mkv, undistort=False, template=str(tmp_path / "t.obj"))
    assert open_source(src_t).files() == [synthetic_mkv, tmp_path / "t.obj"]
    assert open_source(src_t).files(0, 2) == [synthetic_mkv]


def test_a_truncated_recording_is_read_with_source_mkv_allow_truncated(synthetic_mkv, tmp_path):  # noqa: F811
    path, _ = synthetic_mkv
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    with pytest.raises(ValueError, match=r"truncated Matroska file.*set source\.mkv\.allow_truncated: true"):
        count_frames(_mkv_source(cut, undistort=False))
    with pytest.warns(UserWarning, match="truncated"):
        n = count_frames(_mkv_source(cut, undistort=False, allow_truncated=True, stop=3))
    assert n == 3
    with pytest.warns(UserWarning, match="truncated"):
        write_frames_block(_mkv_source(cut, undistort=False, allow_truncated=True, stop=3), 0, 3, tmp_path / "f.zarr")
    assert open_store(tmp_path / "f.zarr", "frames").attrs["frame_ids"] == [0, 1, 2]


def test_captures_with_a_cut_short_colour_jpeg_are_refused_or_left_out(tmp_path):
    """A recording whose colour images 2 and 4 are cut short: the scene is refused before any
    frame is read, naming both captures; a range around them is read; with
    source.mkv.skip_damaged_color the other captures are read, and only they."""
    from test_kinect_mkv import COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION, write_test_mkv
    p = tmp_path / "damaged.mkv"
    written = write_test_mkv(p, 6, COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION, truncated_color_frame=(2, 4))
    with pytest.raises(ValueError, match=r"2 captures are cut short .*captures \[2, 4\].*skip_damaged_color: true"):
        write_scene(_mkv_source(p, undistort=False), 3, tmp_path / "scene.zarr")
    assert not (tmp_path / "scene.zarr").exists()
    assert count_frames(_mkv_source(p, undistort=False, stop=2)) == 2  # the captures before them
    src = _mkv_source(p, undistort=False, skip_damaged_color=True)
    with pytest.warns(UserWarning, match=r"2 colour images are cut short .*left out.*0\.067 s, 0\.133 s"):
        write_scene(src, 3, tmp_path / "scene.zarr")
    scene = open_store(tmp_path / "scene.zarr", "scene")
    assert scene.attrs["frame_ids"] == [0, 1, 2, 3] and scene.attrs["source"]["damaged_color_skipped"] == 2
    with pytest.warns(UserWarning, match="cut short"):
        write_frames_block(src, 0, 4, tmp_path / "f.zarr")
    frames = open_store(tmp_path / "f.zarr", "frames")
    kept = [0, 1, 3, 5]  # the written frames whose colour is whole
    np.testing.assert_array_equal(frames["depth"][...], np.stack([written[i][1] for i in kept]))
    for k, i in enumerate(kept):  # JPEG: near the written colour, far from its neighbours'
        err = np.abs(frames["color"][k].astype(int) - written[i][0]).mean()
        assert err < 3 and all(np.abs(frames["color"][k].astype(int) - written[j][0]).mean() > err for j in kept if j != i)
    steps = np.diff(frames["timestamps"][...])
    np.testing.assert_allclose(steps, [1 / 30, 2 / 30, 2 / 30], atol=2e-3)  # the gaps stay in the timestamps


@pytest.mark.skipif(not REAL_MKV.is_file(), reason="shared data samples absent")
def test_mkv_ingest_of_the_real_recording(tmp_path):
    src = _mkv_source(REAL_MKV)
    write_scene(src, 8, tmp_path / "scene.zarr")
    write_frames_block(src, 0, 1, tmp_path / "b0.zarr")
    scene = open_store(tmp_path / "scene.zarr", "scene")
    cal = scene.attrs["calibration"]
    assert (cal["color"]["width"], cal["color"]["height"]) == (1280, 720)
    assert (cal["depth"]["width"], cal["depth"]["height"]) == (640, 576)
    assert cal["color"]["distortion"] == [0.0] * 8  # undistorted at ingest
    f = open_store(tmp_path / "b0.zarr", "frames")
    depth = f["depth"][0]
    valid = depth[depth > 0]
    assert depth.dtype == np.uint16 and depth.shape == (576, 640)
    assert np.mean((valid >= 150) & (valid <= 5500)) > 0.99 and np.median(valid) > 500
    assert f["color"].shape == (1, 720, 1280, 3)


def test_a_source_that_delivers_too_few_frames_is_refused(synthetic_mkv, tmp_path, monkeypatch):  # noqa: F811
    """A reader that ends early (here the recording's reader made to stop one capture short) is
    refused, naming the count, rather than leaving the block's last frame all zeros."""
    from stex.ingest import MkvSource

    frames = MkvSource.frames
    monkeypatch.setattr(MkvSource, "frames", lambda self, start, stop: frames(self, start, stop - 1))
    with pytest.raises(ValueError, match=r"source delivered 2 of the 3 frames of block \[0, 3\)"):
        write_frames_block(_mkv_source(synthetic_mkv[0], undistort=False), 0, 3, tmp_path / "f.zarr")
    assert not (tmp_path / "f.zarr").exists()
