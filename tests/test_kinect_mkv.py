"""Tests for stex.readers.kinect_mkv (Azure Kinect .mkv reader, PyAV backend).

Synthetic recordings are written here with PyAV (``write_test_mkv``); the real recording comes
from the shared data samples (``STEX_DATA_SAMPLES`` or ``<repo>/../shared/data_samples``) and its
tests skip when the folder is absent.
"""

from __future__ import annotations

import copy
import json
import os
import re
import warnings
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest

av = pytest.importorskip("av")

from stex.camera import Calibration, transform_points  # noqa: E402
from stex.readers.kinect_mkv import FrameIndexError, KinectRecording, open_kinect_mkv  # noqa: E402
from stex.readers.kinect_calibration import Undistorter, calibration_from_k4a_json, undistort_frame  # noqa: E402

# Camera entries of a real device's calibration.json (pyk4a's MIT-licensed test asset
# tests/assets/calibration.json, the same device as the shared sample recording).
K4A_CALIBRATION = {
    "CalibrationInformation": {
        "Cameras": [
            {
                "Intrinsics": {
                    "ModelParameterCount": 14,
                    "ModelParameters": [
                        0.51296979188919067, 0.51692354679107666, 0.4927808940410614, 0.49290284514427185,
                        0.54793977737426758, -0.020971370860934258, -0.0026522316038608551,
                        0.88967907428741455, 0.086130209267139435, -0.013910384848713875, 0, 0,
                        -7.2104157879948616e-5, 2.0557534298859537e-5,
                    ],
                    "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
                },
                "Location": "CALIBRATION_CameraLocationD0",
                "Purpose": "CALIBRATION_CameraPurposeDepth",
                "MetricRadius": 1.7399997711181641,
                "Rt": {"Rotation": [1, 0, 0, 0, 1, 0, 0, 0, 1], "Translation": [0, 0, 0]},
                "SensorHeight": 1024,
                "SensorWidth": 1024,
            },
            {
                "Intrinsics": {
                    "ModelParameterCount": 14,
                    "ModelParameters": [
                        0.49984714388847351, 0.50661760568618774, 0.47796511650085449, 0.63742393255233765,
                        0.33012130856513977, -2.4893965721130371, 1.453670859336853, 0.20891207456588745,
                        -2.302915096282959, 1.3751275539398193, 0, 0,
                        -0.00012944525224156678, -0.00016178244550246745,
                    ],
                    "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
                },
                "Location": "CALIBRATION_CameraLocationPV0",
                "Purpose": "CALIBRATION_CameraPurposePhotoVideo",
                "MetricRadius": 0,
                "Rt": {
                    "Rotation": [
                        0.99999922513961792, 0.0011817576596513391, -0.00044814043212682009,
                        -0.0011387512786313891, 0.99628061056137085, 0.0861603245139122,
                        0.0005482942215166986, -0.086159750819206238, 0.9962812066078186,
                    ],
                    "Translation": [-0.032083429396152496, -0.0022053730208426714, 0.0038836926687508821],
                },
                "SensorHeight": 3072,
                "SensorWidth": 4096,
            },
        ],
        "Metadata": {"SerialId": "001514394512"},
    }
}

_COLOR_MODE_NAMES = {(1280, 720): "720P", (1920, 1080): "1080P", (2048, 1536): "1536P"}
_DEPTH_MODE_NAMES = {(640, 576): "NFOV_UNBINNED", (320, 288): "NFOV_2X2BINNED", (512, 512): "WFOV_2X2BINNED"}

# Known depth values written at known pixels (row, col) of every synthetic frame.
SPECIAL_DEPTH = {(0, 0): 1, (1, 2): 256, (10, 20): 1000, (-1, -1): 65535, (5, -3): 0}
START_OFFSET_US = 1_000_000  # written as K4A_START_OFFSET_NS


def synthetic_depth(i: int, size: tuple[int, int]) -> np.ndarray:
    """(H, W) uint16 depth of synthetic frame i: a ramp plus SPECIAL_DEPTH values."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    d = (500 + 3 * xx + 2 * yy + 10 * i).astype(np.uint16)
    for (r, c), val in SPECIAL_DEPTH.items():
        d[r, c] = val
    return d


def synthetic_color(i: int, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) uint8 RGB of synthetic frame i: smooth ramps (JPEG-friendly), blue encodes i."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.empty((h, w, 3), np.uint8)
    rgb[..., 0] = (xx * 255 // max(w - 1, 1)).astype(np.uint8)
    rgb[..., 1] = (yy * 255 // max(h - 1, 1)).astype(np.uint8)
    rgb[..., 2] = (40 + 20 * i) % 256
    return rgb


def _patch_bitmap_header(path: Path, width: int, height: int, fourcc: bytes, bits: int, image_size: int) -> None:
    """Make a raw track's VFW BITMAPINFOHEADER look like k4arecorder's.

    PyAV does not carry ``codec_tag`` into the header, so the bytes are patched in place: the
    Matroska CodecPrivate element (ID 0x63A2, size 40) holding biSize=40, biWidth=width.
    biHeight is made positive (k4arecorder writes top-down images with a positive height);
    biCompression gets the FourCC ('b16g' = 0x67363162 for depth, 'BGRA').
    The file is written without CRC-32 elements, so patching keeps it valid.
    """
    data = bytearray(path.read_bytes())
    marker = b"\x63\xa2\xa8" + (40).to_bytes(4, "little") + width.to_bytes(4, "little")
    hits = []
    pos = data.find(marker)
    while pos >= 0:
        hits.append(pos)
        pos = data.find(marker, pos + 1)
    assert len(hits) == 1, f"expected one {width}-wide BITMAPINFOHEADER, found {len(hits)}"
    h0 = hits[0] + 3  # start of the 40-byte header
    data[h0 + 8: h0 + 12] = height.to_bytes(4, "little", signed=True)
    data[h0 + 14: h0 + 16] = bits.to_bytes(2, "little")  # biBitCount
    data[h0 + 16: h0 + 20] = fourcc  # biCompression
    data[h0 + 20: h0 + 24] = image_size.to_bytes(4, "little")  # biSizeImage
    path.write_bytes(bytes(data))


def _rgb_to_nv12(rgb: np.ndarray) -> bytes:
    h, w = rgb.shape[:2]
    i420 = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420).ravel()
    y, u, v = i420[: w * h], i420[w * h: w * h * 5 // 4], i420[w * h * 5 // 4:]
    uv = np.empty(w * h // 2, np.uint8)
    uv[0::2], uv[1::2] = u, v
    return y.tobytes() + uv.tobytes()


def write_test_mkv(path, n_frames, color_size, depth_size, calibration_json, *, tags=True,
                   depth_title="DEPTH", bad_depth_frame=None, drop_depth_frames=(), fps=30,
                   color_format="MJPG", truncated_color_frame=None):
    """Write a k4arecorder-like .mkv with PyAV.

    Tracks: COLOR (MJPEG, colour from ``synthetic_color``), DEPTH (raw 'b16g' big-endian uint16,
    values from ``synthetic_depth``), attachment ``calibration.json`` (skipped when
    ``calibration_json`` is None), container tag K4A_START_OFFSET_NS. Frame i has timestamp
    round(i * 1000 / fps) ms (the Matroska muxer stores milliseconds).

    Options: ``tags=False`` omits the K4A_*_MODE track tags; ``depth_title`` renames the depth
    track; ``bad_depth_frame=k`` writes a short depth packet for frame k;
    ``drop_depth_frames`` writes no depth for those frames (colour only);
    ``truncated_color_frame=k`` (or a tuple of frames) writes the first 60 % of frame k's JPEG
    (as a camera that lost USB packets);
    ``color_format='BGRA'`` or ``'NV12'`` writes raw colour like k4arecorder's raw modes.
    Returns the list of (color, depth) arrays written.
    """
    path = Path(path)
    (cw, ch), (dw, dh) = color_size, depth_size
    oc = av.open(str(path), "w", format="matroska", options={"allow_raw_vfw": "1", "write_crc32": "0"})
    oc.metadata["title"] = "Azure Kinect"
    oc.metadata["K4A_START_OFFSET_NS"] = str(START_OFFSET_US * 1000)
    if color_format == "MJPG":
        cs = oc.add_stream("mjpeg", rate=fps)
        cs.width, cs.height, cs.pix_fmt = cw, ch, "yuvj420p"
    else:
        cs = oc.add_stream("rawvideo", rate=fps)
        cs.width, cs.height, cs.pix_fmt = cw, ch, {"BGRA": "bgra", "NV12": "nv12"}[color_format]
    cs.metadata["title"] = "COLOR"
    ds = oc.add_stream("rawvideo", rate=fps)
    ds.width, ds.height, ds.pix_fmt = dw, dh, "gray16be"
    ds.metadata["title"] = depth_title
    if tags:
        cs.metadata["K4A_COLOR_MODE"] = f"{color_format}_{_COLOR_MODE_NAMES[(cw, ch)]}"
        ds.metadata["K4A_DEPTH_MODE"] = _DEPTH_MODE_NAMES[(dw, dh)]
    if calibration_json is not None:
        oc.add_attachment("calibration.json", "application/octet-stream",
                          json.dumps(calibration_json).encode())
    tb = Fraction(1, 1000)
    written = []
    for i in range(n_frames):
        t = round(i * 1000 / fps)
        rgb = synthetic_color(i, color_size)
        if color_format == "MJPG":
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            payload = jpg.tobytes()
            if i in np.atleast_1d(truncated_color_frame if truncated_color_frame is not None else []):
                payload = payload[: len(payload) * 6 // 10]
        elif color_format == "BGRA":
            payload = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGRA).tobytes()
        else:
            payload = _rgb_to_nv12(rgb)
        pkt = av.Packet(payload)
        pkt.stream, pkt.pts, pkt.dts, pkt.time_base, pkt.duration = cs, t, t, tb, round(1000 / fps)
        oc.mux(pkt)
        depth = synthetic_depth(i, depth_size)
        if i not in drop_depth_frames:
            raw = depth.astype(">u2").tobytes()
            if i == bad_depth_frame:
                raw = raw[: len(raw) // 2]
            pkt = av.Packet(raw)
            pkt.stream, pkt.pts, pkt.dts, pkt.time_base, pkt.duration = ds, t, t, tb, round(1000 / fps)
            oc.mux(pkt)
        written.append((rgb, depth))
    oc.close()
    _patch_bitmap_header(path, dw, dh, b"b16g", 16, dw * dh * 2)
    if color_format == "BGRA":
        _patch_bitmap_header(path, cw, ch, b"BGRA", 32, cw * ch * 4)
    # (NV12: FFmpeg writes V_UNCOMPRESSED with ColourSpace 'NV12' instead of a VFW header;
    # the reader sees the same FourCC, so it is left as is.)
    return written


COLOR_SIZE = (1280, 720)
DEPTH_SIZE = (320, 288)


@pytest.fixture(scope="module")
def synthetic_mkv(tmp_path_factory):
    path = tmp_path_factory.mktemp("kinect") / "synthetic.mkv"
    written = write_test_mkv(path, 10, COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION)
    return path, written


# ------------------------------------------------------------------ synthetic round trip


def test_synthetic_round_trip(synthetic_mkv):
    path, written = synthetic_mkv
    with open_kinect_mkv(path, backend="pyav") as rec:
        assert isinstance(rec, KinectRecording)
        assert rec.backend == "pyav"
        assert rec.n_frames == len(rec) == 10
        assert rec.color_size == COLOR_SIZE and rec.depth_size == DEPTH_SIZE
        assert rec.color_mode == "720P" and rec.depth_mode == "NFOV_2X2BINNED"
        assert rec.color_format == "MJPG"
        # Matroska stores ms here; timestamps are device µs = pts + K4A_START_OFFSET_NS.
        expected_ts = np.array([round(i * 1000 / 30) * 1000 for i in range(10)]) + START_OFFSET_US
        np.testing.assert_array_equal(rec.timestamps_us, expected_ts)
        assert np.all(np.diff(rec.timestamps_us) > 0)
        seen = []
        for index, ts, color, depth in rec.frames():
            seen.append(index)
            rgb, dep = written[index]
            assert ts == expected_ts[index]
            assert depth.dtype == np.uint16 and depth.shape == (DEPTH_SIZE[1], DEPTH_SIZE[0])
            np.testing.assert_array_equal(depth, dep)  # exact, incl. 1, 256, 1000, 65535, 0
            for (r, c), val in SPECIAL_DEPTH.items():
                assert depth[r, c] == val
            assert color.dtype == np.uint8 and color.shape == (COLOR_SIZE[1], COLOR_SIZE[0], 3)
            diff = np.abs(color.astype(int) - rgb.astype(int))
            assert diff.mean() < 2.0 and np.percentile(diff, 99.9) <= 12, (diff.mean(), diff.max())
        assert seen == list(range(10))
        assert np.allclose(rec.calibration.depth_to_color,
                           calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_2X2BINNED").depth_to_color)


def test_synthetic_random_access(synthetic_mkv):
    path, written = synthetic_mkv
    with open_kinect_mkv(path, backend="pyav") as rec:
        got = list(rec.frames(6, 9))
        assert [g[0] for g in got] == [6, 7, 8]
        for index, ts, color, depth in got:
            np.testing.assert_array_equal(depth, written[index][1])
            assert abs(int(color[..., 2].mean()) - int(written[index][0][0, 0, 2])) <= 2
        ts, color, depth = rec.read_frame(9)
        np.testing.assert_array_equal(depth, written[9][1])
        assert ts == rec.timestamps_us[9]
        assert list(rec.frames(4, 4)) == []
        with pytest.raises(FrameIndexError, match="out of range") as e:
            rec.read_frame(10)
        assert str(path) in str(e.value)
        with pytest.raises(ValueError, match="out of range"):
            list(rec.frames(3, 11))
        with pytest.raises(IndexError):
            rec.read_frame(-1)


def test_modes_inferred_from_track_sizes_and_unpaired_frames(tmp_path):
    path = tmp_path / "notags.mkv"
    written = write_test_mkv(path, 5, (1280, 720), (640, 576), K4A_CALIBRATION, tags=False,
                             drop_depth_frames=(2,))
    with pytest.warns(UserWarning, match="not evenly spaced"), open_kinect_mkv(path, backend="pyav") as rec:
        assert rec.color_mode == "720P" and rec.depth_mode == "NFOV_UNBINNED"
        assert rec.n_frames == 4 and rec.n_unpaired_color == 1 and rec.n_unpaired_depth == 0
        frames = list(rec.frames())
        # capture 2 (colour only) is skipped; the remaining captures keep their own data
        for (index, ts, color, depth), src in zip(frames, [0, 1, 3, 4]):
            np.testing.assert_array_equal(depth, written[src][1])
            assert ts == round(src * 1000 / 30) * 1000 + START_OFFSET_US


@pytest.mark.parametrize("fmt", ["BGRA", "NV12"])
def test_raw_color_formats(tmp_path, fmt):
    path = tmp_path / f"{fmt}.mkv"
    written = write_test_mkv(path, 3, COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION, color_format=fmt)
    with open_kinect_mkv(path, backend="pyav") as rec:
        assert rec.color_format == fmt and rec.n_frames == 3
        for index, ts, color, depth in rec.frames():
            assert color.shape == (COLOR_SIZE[1], COLOR_SIZE[0], 3) and color.dtype == np.uint8
            diff = np.abs(color.astype(int) - written[index][0].astype(int))
            if fmt == "BGRA":
                assert diff.max() == 0
            else:  # 4:2:0 chroma + YUV rounding
                assert diff.mean() < 2.0 and diff.max() <= 8, (diff.mean(), diff.max())
            np.testing.assert_array_equal(depth, written[index][1])


# ------------------------------------------------------------------ calibration


def test_calibration_mode_specific_by_hand():
    p_d = K4A_CALIBRATION["CalibrationInformation"]["Cameras"][0]["Intrinsics"]["ModelParameters"]
    p_c = K4A_CALIBRATION["CalibrationInformation"]["Cameras"][1]["Intrinsics"]["ModelParameters"]
    cal = calibration_from_k4a_json(K4A_CALIBRATION, (1280, 720), "NFOV_UNBINNED")
    # depth NFOV unbinned: 1024x1024 sensor, crop (192, 180) -> 640x576; -0.5 = corner -> centre
    assert cal.depth.size == (640, 576)
    np.testing.assert_allclose(
        [cal.depth.fx, cal.depth.fy, cal.depth.cx, cal.depth.cy],
        [p_d[2] * 1024, p_d[3] * 1024, p_d[0] * 1024 - 192 - 0.5, p_d[1] * 1024 - 180 - 0.5], rtol=0, atol=1e-9)
    # colour 720P: 4:3 calibration binned to 1280x960, crop (0, 120) -> 1280x720
    assert cal.color.size == (1280, 720)
    np.testing.assert_allclose(
        [cal.color.fx, cal.color.fy, cal.color.cx, cal.color.cy],
        [p_c[2] * 1280, p_c[3] * 960, p_c[0] * 1280 - 0.5, p_c[1] * 960 - 120 - 0.5], rtol=0, atol=1e-9)
    # OpenCV order (k1, k2, p1, p2, k3, k4, k5, k6); the JSON stores ... codx, cody, p2, p1
    np.testing.assert_allclose(cal.color.distortion, [p_c[4], p_c[5], p_c[13], p_c[12], *p_c[6:10]])
    np.testing.assert_allclose(cal.depth.distortion, [p_d[4], p_d[5], p_d[13], p_d[12], *p_d[6:10]])
    # the other modes
    c1536 = calibration_from_k4a_json(K4A_CALIBRATION, "K4A_COLOR_RESOLUTION_1536P", "WFOV_2X2BINNED")
    assert c1536.color.size == (2048, 1536) and c1536.depth.size == (512, 512)
    assert c1536.color.cy == pytest.approx(p_c[1] * 1536 - 0.5)
    assert c1536.depth.cx == pytest.approx(p_d[0] * 512 - 0.5)
    assert c1536.depth.fx == pytest.approx(cal.depth.fx / 2)
    c1080 = calibration_from_k4a_json(K4A_CALIBRATION, "1920x1080", "K4A_DEPTH_MODE_NFOV_2X2BINNED")
    assert c1080.color.cy == pytest.approx(p_c[1] * 1440 - 180 - 0.5)
    assert c1080.depth.size == (320, 288) and c1080.depth.cx == pytest.approx(p_d[0] * 512 - 96 - 0.5)
    # text input works too; bad modes are refused
    assert np.allclose(calibration_from_k4a_json(json.dumps(K4A_CALIBRATION), "720P", "NFOV_UNBINNED").color.K,
                       cal.color.K)
    with pytest.raises(ValueError, match="colour resolution"):
        calibration_from_k4a_json(K4A_CALIBRATION, (1000, 700), "NFOV_UNBINNED")
    with pytest.raises(ValueError, match="depth mode"):
        calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_4X4")


def test_calibration_extrinsic_metres_and_chain():
    cal = calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_UNBINNED")
    T = cal.depth_to_color
    R, t = T[:3, :3], T[:3, 3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(t, [-0.032083429396152496, -0.0022053730208426714, 0.0038836926687508821], atol=1e-12)
    assert 0.025 < np.linalg.norm(t) < 0.040  # ~32 mm baseline, in metres
    # depth tilted ~6 deg about x relative to colour
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) == pytest.approx(4.94, abs=0.1)
    # a non-identity depth Rt is composed as Rt_color @ inv(Rt_depth)
    calib2 = copy.deepcopy(K4A_CALIBRATION)
    cam_d = calib2["CalibrationInformation"]["Cameras"][0]
    a = np.radians(10)
    Rd = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    cam_d["Rt"] = {"Rotation": Rd.ravel().tolist(), "Translation": [0.1, 0.0, 0.0]}
    T2 = calibration_from_k4a_json(calib2, "720P", "NFOV_UNBINNED").depth_to_color
    W2D = np.eye(4)
    W2D[:3, :3], W2D[:3, 3] = Rd, [0.1, 0, 0]
    np.testing.assert_allclose(T2, T @ np.linalg.inv(W2D), atol=1e-9)


# ------------------------------------------------------------------ errors


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.mkv"):
        open_kinect_mkv(tmp_path / "nothere.mkv")


def test_not_a_matroska_file(tmp_path):
    p = tmp_path / "image.mkv"
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((8, 8, 3), np.uint8))
    p.write_bytes((tmp_path / "x.png").read_bytes())
    with pytest.raises(ValueError, match="not a Matroska") as e:
        open_kinect_mkv(p, backend="pyav")
    assert str(p) in str(e.value)
    empty = tmp_path / "empty.mkv"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="not a Matroska"):
        open_kinect_mkv(empty, backend="pyav")


def test_truncated_file(synthetic_mkv, tmp_path):
    path, _ = synthetic_mkv
    data = path.read_bytes()
    for frac in (0.6, 0.02):
        p = tmp_path / f"truncated_{frac}.mkv"
        p.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(ValueError, match="truncated|corrupt") as e:
            open_kinect_mkv(p, backend="pyav")
        assert str(p) in str(e.value)
    # allow_truncated reads what is complete, and a cut packet is reported with its frame
    p = tmp_path / "truncated_0.6.mkv"
    with pytest.warns(UserWarning, match="truncated"):
        rec = open_kinect_mkv(p, backend="pyav", allow_truncated=True)
    with rec:
        assert 0 < rec.n_frames < 10
        try:
            n = sum(1 for _ in rec.frames())
        except ValueError as err:  # the last, cut packet
            assert str(p) in str(err) and "frame" in str(err)
        else:
            assert n == rec.n_frames


def test_missing_calibration_attachment(tmp_path):
    p = tmp_path / "nocalib.mkv"
    write_test_mkv(p, 2, COLOR_SIZE, DEPTH_SIZE, None)
    with pytest.raises(ValueError, match="calibration.json") as e:
        open_kinect_mkv(p, backend="pyav")
    assert str(p) in str(e.value)


def test_missing_depth_track(tmp_path):
    p = tmp_path / "nodepth.mkv"
    write_test_mkv(p, 2, COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION, depth_title="IR")
    with pytest.raises(ValueError, match="no DEPTH track") as e:
        open_kinect_mkv(p, backend="pyav")
    assert str(p) in str(e.value)


@pytest.mark.parametrize("damage, match", [
    ({"bad_depth_frame": 2}, r"frame 2 .*depth packet has 92160 bytes, expected 184320"),
    # a JPEG cut short: OpenCV refuses it, the FFmpeg fallback invents its lower rows, and only
    # stderr says so
    ({"truncated_color_frame": 2}, r"frame 2.*ends without the JPEG end marker.*source\.mkv\.start / stop"),
])
def test_a_damaged_packet_names_its_frame(tmp_path, damage, match):
    p = tmp_path / "damaged.mkv"
    write_test_mkv(p, 4, COLOR_SIZE, DEPTH_SIZE, K4A_CALIBRATION, **damage)
    with open_kinect_mkv(p, backend="pyav") as rec:
        it = rec.frames()
        assert next(it)[0] == 0 and next(it)[0] == 1
        with pytest.raises(ValueError, match=match) as e:
            next(it)
        assert str(p) in str(e.value)


def test_a_truncated_jpeg_would_decode_with_invented_rows():
    """What the end-marker check prevents: the decoder fallback turns a JPEG cut to 60 % into a
    full-size image whose lower rows are not the picture."""
    # what the check prevents: the decoder fallback turns the same bytes into a full-size image
    # whose lower rows are not the picture
    from stex.readers.kinect_mkv import _decode_mjpeg_ffmpeg
    rgb = synthetic_color(2, COLOR_SIZE)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    img = _decode_mjpeg_ffmpeg(jpg.tobytes()[: jpg.size * 6 // 10])
    assert img is not None and img.shape[:2] == (COLOR_SIZE[1], COLOR_SIZE[0])
    bottom = np.abs(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)[-50:].astype(int) - rgb[-50:]).mean()
    top = np.abs(cv2.cvtColor(img, cv2.COLOR_BGR2RGB)[:50].astype(int) - rgb[:50]).mean()
    assert top < 3 and bottom > 20, (top, bottom)


def test_damaged_depth_data_is_named(recwarn):
    """Random bytes in a depth packet decode to a full-size image, but much of it reads farther
    than any Azure Kinect depth mode measures: a warning names the frame."""
    import warnings

    from stex.readers.kinect_mkv import _decode_depth

    w, h = DEPTH_SIZE
    good = np.full((h, w), 1500, ">u2")
    good[:5] = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _decode_depth(good.tobytes(), DEPTH_SIZE, ">u2", "f.mkv: frame 3").max() == 1500
    noise = np.random.default_rng(0).integers(0, 256, w * h * 2, dtype=np.uint8).tobytes()
    with pytest.warns(UserWarning, match=r"f\.mkv: frame 3: 8\d % of the depth pixels read beyond 8 m"):
        _decode_depth(noise, DEPTH_SIZE, ">u2", "f.mkv: frame 3")


def test_bad_backend_name(synthetic_mkv):
    with pytest.raises(ValueError, match="backend"):
        open_kinect_mkv(synthetic_mkv[0], backend="ffmpeg")


# ------------------------------------------------------------------ undistortion


def _blob_image(points_uv, size, sigma=1.5):
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w), np.float64)
    for u, v in points_uv:
        r = int(4 * sigma) + 2
        u0, v0 = int(round(u)), int(round(v))
        sl = (slice(max(v0 - r, 0), v0 + r + 1), slice(max(u0 - r, 0), u0 + r + 1))
        img[sl] += np.exp(-((xx[sl] - u) ** 2 + (yy[sl] - v) ** 2) / (2 * sigma**2))
    return img


def test_undistorter_moves_points_to_pinhole_projection():
    cal = calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_UNBINNED")
    und = Undistorter(cal)
    assert np.all(und.calibration.color.distortion == 0) and np.all(und.calibration.depth.distortion == 0)
    np.testing.assert_array_equal(und.calibration.color.K, cal.color.K)

    # colour: Gaussian blobs drawn where the distorted camera sees 3D points
    cam = cal.color
    rng = np.random.default_rng(0)
    n = 60
    pin = np.column_stack([rng.uniform(40, cam.width - 40, n), rng.uniform(40, cam.height - 40, n)])
    z = rng.uniform(0.5, 3.0, n)
    X = np.column_stack([(pin[:, 0] - cam.cx) / cam.fx * z, (pin[:, 1] - cam.cy) / cam.fy * z, z])
    dist_uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.distortion)
    dist_uv = dist_uv.reshape(-1, 2)
    assert np.abs(dist_uv - pin).max() > 3.0  # the lens really distorts here
    img = _blob_image(dist_uv, cam.size)
    color = np.repeat((np.clip(img, 0, 1) * 250).astype(np.uint8)[..., None], 3, axis=2)
    depth = np.zeros((cal.depth.height, cal.depth.width), np.uint16)
    out_color, _ = und(color, depth)
    g = out_color[..., 0].astype(np.float64)
    errs = []
    for u, v in pin:
        u0, v0 = int(round(u)), int(round(v))
        win = g[v0 - 5: v0 + 6, u0 - 5: u0 + 6]
        yy, xx = np.mgrid[v0 - 5: v0 + 6, u0 - 5: u0 + 6]
        errs.append(np.hypot((win * xx).sum() / win.sum() - u, (win * yy).sum() / win.sum() - v))
    assert max(errs) < 0.5, max(errs)

    # depth: nearest neighbour -- no new values, and marker blocks land at the pinhole position
    dcam = cal.depth
    centres = np.array([[100, 100], [540, 90], [320, 288], [90, 480], [560, 500]], dtype=np.float64)
    depth = np.full((dcam.height, dcam.width), 2000, np.uint16)
    depth[:, :40] = 0
    for k, (u, v) in enumerate(centres):
        depth[int(v) - 2: int(v) + 3, int(u) - 2: int(u) + 3] = 1000 + k
    c2, d2, cal2 = undistort_frame(None, depth, cal)
    assert c2 is None and isinstance(cal2, Calibration)
    assert set(np.unique(d2).tolist()) <= set(np.unique(depth).tolist())
    target = cv2.undistortPoints(centres.reshape(-1, 1, 2), dcam.K, dcam.distortion, P=dcam.K).reshape(-1, 2)
    for k, (u, v) in enumerate(target):
        vv, uu = np.nonzero(d2 == 1000 + k)
        assert len(uu) >= 15
        assert np.hypot(uu.mean() - u, vv.mean() - v) < 0.5


def test_undistorter_rejects_wrong_size():
    cal = calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_UNBINNED")
    with pytest.raises(ValueError, match="calibration is for 640x576"):
        Undistorter(cal)(None, np.zeros((288, 320), np.uint16))


# ------------------------------------------------------------------ real recording


def _samples_dir() -> Path:
    env = os.environ.get("STEX_DATA_SAMPLES")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data_samples"


REAL = _samples_dir() / "azure_kinect_pyk4a"
needs_real = pytest.mark.skipif(not (REAL / "recording.mkv").is_file(),
                                reason=f"sample recording not found at {REAL}")


@pytest.fixture(scope="module")
def real_frame():
    with open_kinect_mkv(REAL / "recording.mkv", backend="pyav") as rec:
        frames = list(rec.frames())
        return rec, frames


@needs_real
def test_real_recording_frames(real_frame):
    rec, frames = real_frame
    assert rec.n_frames == 1 and len(frames) == 1
    assert rec.color_mode == "720P" and rec.depth_mode == "NFOV_UNBINNED" and rec.color_format == "MJPG"
    index, ts, color, depth = frames[0]
    # The SDK reports device timestamp 800222 us for this capture (pyk4a's own tests):
    # Matroska time 463945 us + K4A_START_OFFSET_NS 336277000 ns.
    assert ts == 800222 and rec.start_offset_us == 336277
    assert color.shape == (720, 1280, 3) and color.dtype == np.uint8
    assert depth.shape == (576, 640) and depth.dtype == np.uint16
    valid = depth[depth > 0]
    frac_valid = valid.size / depth.size
    frac_in_range = np.mean((valid >= 250) & (valid <= 5500))
    # measured: 76.5 % of pixels have depth; 93.9 % of those lie in 250-5500 mm, the rest are
    # 165-250 mm (the mug and table edge right in front of the camera); max 3690 mm.
    assert 0.70 < frac_valid < 0.82, frac_valid
    assert frac_in_range > 0.9, frac_in_range
    assert valid.max() <= 5500 and valid.min() >= 100
    assert 1000 < np.median(valid) < 2500


@needs_real
def test_real_calibration_matches_hand_computation(real_frame):
    rec, _ = real_frame
    cal = rec.calibration
    raw = json.loads((REAL / "calibration.json").read_text())
    assert rec.calibration_json == raw
    # by hand from calibration.json, NFOV_UNBINNED depth and 720P colour (see the docstring)
    np.testing.assert_allclose([cal.depth.fx, cal.depth.fy, cal.depth.cx, cal.depth.cy],
                               [504.607635, 504.732513, 332.781067, 348.829712], atol=1e-5)
    np.testing.assert_allclose([cal.color.fx, cal.color.fy, cal.color.cx, cal.color.cy],
                               [611.795349, 611.926975, 639.304344, 365.852901], atol=1e-5)
    assert cal.depth.size == (640, 576) and cal.color.size == (1280, 720)
    np.testing.assert_allclose(cal.color.distortion[:2], [0.330121, -2.489397], atol=1e-6)
    np.testing.assert_allclose(cal.color.distortion[2:4], [-0.000162, -0.000129], atol=1e-6)  # p1, p2
    np.testing.assert_allclose(cal.depth.distortion[[0, 1, 4, 5]], [0.547940, -0.020971, -0.002652, 0.889679],
                               atol=1e-6)
    T = cal.depth_to_color
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [-0.0320834, -0.0022054, 0.0038837], atol=1e-6)
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(0.0324, abs=0.001)  # ~32 mm baseline, metres


@needs_real
def test_real_depth_not_flipped_and_registered(real_frame):
    """Depth rows are top-down and the calibration registers depth onto colour.

    The scene is a mug close to the camera (lower left of the colour image) in front of a wall
    ~2 m away. Every valid depth pixel is back-projected (exact undistortion of its ray),
    moved to the colour camera and projected with the colour distortion. Depth points landing
    on the mug body in the colour image (box x 300-480, y 420-600) must be near (< 0.5 m) and
    points landing on the wall right of it (x 700-1100, y 100-350) far (> 1.5 m). A vertically
    flipped or mirrored depth image fails this (the mug box then sees ~1.0 / ~1.5 m).
    """
    rec, frames = real_frame
    cal = rec.calibration
    _, _, color, depth = frames[0]

    def medians(d):
        vv, uu = np.nonzero(d > 0)
        rays = cv2.undistortPoints(np.column_stack([uu, vv]).astype(np.float64).reshape(-1, 1, 2),
                                   cal.depth.K, cal.depth.distortion).reshape(-1, 2)
        z = d[vv, uu] / 1000.0
        Xc = transform_points(cal.depth_to_color, np.column_stack([rays * z[:, None], z]))
        uv, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), cal.color.K, cal.color.distortion)
        uv = uv.reshape(-1, 2)
        mug = (uv[:, 0] > 300) & (uv[:, 0] < 480) & (uv[:, 1] > 420) & (uv[:, 1] < 600)
        wall = (uv[:, 0] > 700) & (uv[:, 0] < 1100) & (uv[:, 1] > 100) & (uv[:, 1] < 350)
        return float(np.median(z[mug])), float(np.median(z[wall]))

    mug, wall = medians(depth)
    assert mug < 0.5 and wall > 1.5, (mug, wall)  # measured 0.266 m and 1.973 m
    flipped_mug, _ = medians(np.ascontiguousarray(depth[::-1]))
    mirrored_mug, _ = medians(np.ascontiguousarray(depth[:, ::-1]))
    assert flipped_mug > 0.8 and mirrored_mug > 0.8, (flipped_mug, mirrored_mug)
    # the colour image is upright too: the bright window is in the upper right, above the
    # darker wall/table (measured means 197 vs 88)
    assert color[50:350, 750:980].mean() > color[420:700, 750:980].mean() + 60


# ------------------------------------------------------------------ pyk4a backend plumbing
# pyk4a cannot be installed here (it needs the Azure Kinect SDK). This fake module mimics the
# parts of pyk4a's documented playback API that the reader uses (PyK4APlayback.open/close,
# configuration, calibration_raw, get_next_capture raising EOFError, seek with SeekOrigin,
# captures with color/depth arrays and *_timestamp_usec), serving the synthetic file's frames.
# It checks the backend's plumbing, not pyk4a itself.


def _fake_pyk4a(source: Path):
    import enum
    import types

    mod = types.ModuleType("pyk4a")

    class ImageFormat(enum.IntEnum):
        COLOR_MJPG = 0
        COLOR_NV12 = 1
        COLOR_YUY2 = 2
        COLOR_BGRA32 = 3

    class ColorResolution(enum.IntEnum):
        OFF = 0
        RES_720P = 1

    class DepthMode(enum.IntEnum):
        OFF = 0
        NFOV_2X2BINNED = 1
        NFOV_UNBINNED = 2

    class FPS(enum.IntEnum):
        FPS_5 = 0
        FPS_15 = 1
        FPS_30 = 2

    class SeekOrigin(enum.IntEnum):
        BEGIN = 0
        END = 1
        DEVICE_TIME = 2

    with open_kinect_mkv(source, backend="pyav") as rec:
        caps = [(ts, cv2.cvtColor(c, cv2.COLOR_RGB2BGRA), d) for _, ts, c, d in rec.frames()]
        raw = json.dumps(rec.calibration_json)
        offset = rec.start_offset_us

    class Capture:
        def __init__(self, ts, bgra, depth):
            self.color, self.depth = bgra, depth
            self.color_timestamp_usec = self.depth_timestamp_usec = ts

    class PyK4APlayback:
        def __init__(self, path, thread_safe=True):
            self.path, self.pos, self.seeks = Path(path), 0, []

        def open(self):
            pass

        def close(self):
            pass

        @property
        def configuration(self):
            return {"color_format": ImageFormat.COLOR_BGRA32, "color_resolution": ColorResolution.RES_720P,
                    "depth_mode": DepthMode.NFOV_2X2BINNED, "camera_fps": FPS.FPS_30,
                    "color_track_enabled": True, "depth_track_enabled": True,
                    "start_timestamp_offset_usec": offset}

        @property
        def calibration_raw(self):
            return raw

        def seek(self, offset_us, origin=SeekOrigin.BEGIN):
            self.seeks.append((int(offset_us), SeekOrigin(origin)))
            t = offset_us if origin == SeekOrigin.DEVICE_TIME else offset_us + offset
            self.pos = next((i for i, c in enumerate(caps) if c[0] >= t), len(caps))

        def get_next_capture(self):
            if self.pos >= len(caps):
                raise EOFError()
            self.pos += 1
            return Capture(*caps[self.pos - 1])

    for name, obj in dict(ImageFormat=ImageFormat, ColorResolution=ColorResolution, DepthMode=DepthMode,
                          FPS=FPS, SeekOrigin=SeekOrigin, PyK4APlayback=PyK4APlayback).items():
        setattr(mod, name, obj)
    return mod


def test_pyk4a_backend_with_fake_module(synthetic_mkv, monkeypatch):
    import sys

    path, written = synthetic_mkv
    monkeypatch.setitem(sys.modules, "pyk4a", _fake_pyk4a(path))
    with open_kinect_mkv(path) as rec:  # 'auto' picks pyk4a when importable
        assert rec.backend == "pyk4a"
        assert rec.n_frames == 10 and rec.color_format == "BGRA"
        assert rec.color_size == COLOR_SIZE and rec.depth_size == DEPTH_SIZE
        ref = calibration_from_k4a_json(K4A_CALIBRATION, "720P", "NFOV_2X2BINNED")
        np.testing.assert_allclose(rec.calibration.color.K, ref.color.K)
        got = list(rec.frames(3, 6))
        assert [g[0] for g in got] == [3, 4, 5]
        for index, ts, color, depth in got:
            assert ts == rec.timestamps_us[index]
            np.testing.assert_array_equal(depth, written[index][1])
            assert color.shape == (COLOR_SIZE[1], COLOR_SIZE[0], 3)
            assert np.abs(color.astype(int) - written[index][0].astype(int)).mean() < 2.0
    with pytest.raises(ValueError, match="out of range"):
        with open_kinect_mkv(path, backend="pyk4a") as rec:
            rec.read_frame(10)


def test_a_calibration_rotation_that_is_no_rotation_is_refused():
    calib = copy.deepcopy(K4A_CALIBRATION)
    calib["CalibrationInformation"]["Cameras"][1]["Rt"]["Rotation"] = [0.0] * 9
    with pytest.raises(ValueError, match=r"colour camera: Rt\.Rotation is not a rotation matrix"):
        calibration_from_k4a_json(calib, "720P", "NFOV_UNBINNED")
    calib["CalibrationInformation"]["Cameras"][1]["Rt"]["Rotation"] = [1.0] * 8
    with pytest.raises(ValueError, match=r"colour camera: Rt needs 9 rotation and 3 translation numbers, got 8"):
        calibration_from_k4a_json(calib, "720P", "NFOV_UNBINNED")
    calib["CalibrationInformation"]["Cameras"] = ["a", "b"]
    with pytest.raises(ValueError, match=r"must be a list of camera objects"):
        calibration_from_k4a_json(calib, "720P", "NFOV_UNBINNED")


def test_non_finite_distortion_is_refused_naming_the_camera():
    calib = copy.deepcopy(K4A_CALIBRATION)
    cams = calib["CalibrationInformation"]["Cameras"]
    colour = next(c for c in cams if c["Location"] == "CALIBRATION_CameraLocationPV0")
    colour["Intrinsics"]["ModelParameters"][4] = float("nan")
    # undistorted with NaN, every colour image would come out black
    with pytest.raises(ValueError, match=r"colour camera: distortion coefficients must be finite"):
        calibration_from_k4a_json(calib, "720P", "NFOV_UNBINNED")


def test_a_capture_lost_inside_the_recording_warns(tmp_path):
    path = tmp_path / "gap.mkv"
    write_test_mkv(path, 6, (1280, 720), (640, 576), K4A_CALIBRATION, drop_depth_frames=(3,))
    with pytest.warns(UserWarning, match=r"not evenly spaced: 1 gap\(s\) .* after capture\(s\) \[2\]"):
        rec = open_kinect_mkv(path, backend="pyav")
    with rec:
        assert rec.n_frames == 5
    # unpaired images at the ends only: no such warning
    path2 = tmp_path / "ends.mkv"
    write_test_mkv(path2, 6, (1280, 720), (640, 576), K4A_CALIBRATION, drop_depth_frames=(0, 5))
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*not evenly spaced.*")
        with open_kinect_mkv(path2, backend="pyav") as rec:
            assert rec.n_frames == 4


# ------------------------------------------------------------------ principal point check


def _with_colour_cx(calibration: dict, cx_normalised: float) -> dict:
    """``calibration`` with the colour camera's principal point x moved (fraction of the sensor width)."""
    out = copy.deepcopy(calibration)
    colour = next(c for c in out["CalibrationInformation"]["Cameras"] if c["Location"] == "CALIBRATION_CameraLocationPV0")
    colour["Intrinsics"]["ModelParameters"][0] = cx_normalised
    return out


def _principal_point_warnings(path) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with open_kinect_mkv(path, backend="pyav"):
            pass
    return [str(w.message) for w in caught if "principal point" in str(w.message)]


def test_a_principal_point_far_from_the_image_centre_warns_naming_the_recording(synthetic_mkv, tmp_path):
    """Colour cx at 0.70 of the sensor width is 0.70 * 1280 - 0.5 = 895.5 px in the 720P image,
    20 % of its width right of the centre (639.5): beyond stex.camera's 15 %, the warning the
    folder reader gives too. The device's own calibration (0.4998) does not warn."""
    assert _principal_point_warnings(synthetic_mkv[0]) == []
    path = tmp_path / "shifted.mkv"
    write_test_mkv(path, 2, COLOR_SIZE, DEPTH_SIZE, _with_colour_cx(K4A_CALIBRATION, 0.70))
    with pytest.warns(UserWarning, match=re.escape(f"{path}: color camera: principal point (895.5, ") + r"[\d.]+\) is "
                                         r"20 % of the width and 1 % of the height from the centre of the 1280x720 "
                                         r"image .* another resolution"):
        with open_kinect_mkv(path, backend="pyav") as rec:
            assert rec.calibration.color.cx == pytest.approx(895.5)


@needs_real
def test_the_real_recording_does_not_warn_about_its_principal_point():
    assert _principal_point_warnings(REAL / "recording.mkv") == []


@needs_real
def test_a_colour_jpeg_damaged_inside_is_refused_naming_its_frame(tmp_path):
    """16 bytes zeroed inside the real recording's MJPEG packet (its end marker intact): libjpeg
    decodes it to a full-size image, wrong from the damage on, and only says so on stderr."""
    data = bytearray((REAL / "recording.mkv").read_bytes())
    data[28084:28100] = bytes(16)  # inside the colour packet (found by zeroing 16 bytes at offsets)
    p = tmp_path / "damaged.mkv"
    p.write_bytes(bytes(data))
    with open_kinect_mkv(p, backend="pyav") as rec:
        with pytest.raises(ValueError, match=r"damaged\.mkv: frame 0 .*source\.mkv\.start / stop.*"
                                             r"the JPEG's data is damaged \(libjpeg: 'Corrupt JPEG data"):
            list(rec.frames())
