"""Azure Kinect recordings (``k4arecorder`` Matroska files) -> colour, depth and a ``Calibration``.

File layout (written by the Azure Kinect SDK's recorder; see Microsoft's "record file format" page):

- track ``COLOR``: MJPEG (stored as ``V_MS/VFW/FOURCC`` ``MJPG`` or ``V_MJPEG``), or raw
  ``V_MS/VFW/FOURCC`` ``BGRA`` / ``NV12`` / ``YUY2``; tag ``K4A_COLOR_MODE`` e.g. ``MJPG_720P``;
- track ``DEPTH`` (and ``IR``): raw ``V_MS/VFW/FOURCC`` ``b16g`` = 16-bit **big-endian** grey,
  millimetres, rows stored top-down (checked on a real recording: not flipped); tag
  ``K4A_DEPTH_MODE`` e.g. ``NFOV_UNBINNED``;
- attachment ``calibration.json`` (tag ``K4A_CALIBRATION_FILE``): the device's factory
  ``CalibrationInformation`` (normalised sensor-wide intrinsics, see
  :func:`stex.readers.kinect_calibration.calibration_from_k4a_json`);
- segment tags ``K4A_START_OFFSET_NS`` (device time of Matroska time 0) and
  ``K4A_DEPTH_DELAY_NS`` (colour-to-depth capture delay).

Tracks are always selected by their title, never by index (indices change with the mode).

Backends: ``pyk4a`` (the official SDK through its Python wrapper, ``pyk4a.PyK4APlayback``) is
used when it can be imported; otherwise PyAV is used as a pure demuxer (packets are decoded here:
depth/IR bytes with numpy, MJPEG with OpenCV). The pyk4a path is written against pyk4a's
documented API (``PyK4APlayback``, ``configuration``, ``calibration_raw``, ``get_next_capture``,
``seek``) but is **not exercised by the test suite** (pyk4a needs the SDK's native library, which
is not installed where the tests run); only the PyAV path is tested. Both backends derive the
calibration from the same ``calibration.json`` through
:func:`stex.readers.kinect_calibration.calibration_from_k4a_json`.

Timestamps are **device timestamps in microseconds** (what the SDK reports as
``device_timestamp_usec``): Matroska block time + ``K4A_START_OFFSET_NS``. A capture's timestamp
is the one of its depth image.
"""

from __future__ import annotations

import json
import logging
import warnings
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from stex.readers.images import decode_jpeg
from stex.readers.kinect_calibration import (
    COLOR_RESOLUTIONS, DEPTH_MODES, calibration_from_k4a_json, parse_color_resolution, parse_depth_mode)

log = logging.getLogger("stex.readers.kinect_mkv")


_COLOR_FORMATS = ("MJPG", "BGRA", "NV12", "YUY2")


class FrameIndexError(ValueError, IndexError):
    """A frame index outside ``[0, n_frames)``."""


# --------------------------------------------------------------------------------------------
# Matroska container checks
# --------------------------------------------------------------------------------------------

_EBML_MAGIC = b"\x1a\x45\xdf\xa3"
_SEGMENT_ID = b"\x18\x53\x80\x67"


def _read_vint(buf: bytes, pos: int) -> tuple[int, int, bool]:
    """EBML variable-size integer at ``pos``: (value, length in bytes, is 'unknown size')."""
    if pos >= len(buf):
        raise ValueError("header ends early")
    first = buf[pos]
    if first == 0:
        raise ValueError("invalid EBML size")
    length = 8 - first.bit_length() + 1
    if pos + length > len(buf):
        raise ValueError("header ends early")
    value = first & (0xFF >> length)
    for b in buf[pos + 1: pos + length]:
        value = (value << 8) | b
    unknown = value == (1 << (7 * length)) - 1
    return value, length, unknown


def _check_matroska(path: Path, allow_truncated: bool) -> None:
    """Cheap structural checks before handing the file to a demuxer.

    Raises ValueError when the file is not EBML/Matroska, or when the Segment's declared size
    runs past the end of the file (a truncated copy or an interrupted recording) -- unless
    ``allow_truncated``, in which case it only warns.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:4] != _EBML_MAGIC:
        raise ValueError(f"{path}: not a Matroska (.mkv) file: it does not start with the EBML magic bytes")
    try:
        hdr_size, n, _ = _read_vint(head, 4)
        pos = 4 + n + hdr_size
        if head[pos:pos + 4] != _SEGMENT_ID:
            raise ValueError("no Segment element after the EBML header")
        seg_size, n, unknown = _read_vint(head, pos + 4)
        seg_start = pos + 4 + n
    except ValueError as e:
        raise ValueError(f"{path}: corrupt Matroska header ({e}); file size {size} bytes") from None
    if not unknown and seg_start + seg_size > size:
        msg = (f"{path}: truncated Matroska file: the Segment declares {seg_start + seg_size} bytes "
               f"but the file has only {size} ({100.0 * size / (seg_start + seg_size):.1f}%)")
        if not allow_truncated:
            raise ValueError(msg + "; to read the complete captures it still holds set source.mkv.allow_truncated: "
                             "true (open_kinect_mkv(..., allow_truncated=True))")
        warnings.warn(msg, stacklevel=3)


# --------------------------------------------------------------------------------------------
# Frame decoding (shared by the PyAV backend)
# --------------------------------------------------------------------------------------------

#: The farthest an Azure Kinect depth mode measures is 5.46 m (NFOV 2x2 binned); depth read beyond
#: this over more than 1 % of a frame's pixels is damaged data, not a far wall.
DEPTH_IMPLAUSIBLE_MM = 8000


def _decode_depth(buf: bytes, size: tuple[int, int], dtype: str, what: str) -> np.ndarray:
    w, h = size
    if len(buf) != w * h * 2:
        raise ValueError(f"{what}: depth packet has {len(buf)} bytes, expected {w * h * 2} "
                         f"({w}x{h} 16-bit pixels); the file is corrupt or truncated")
    depth = np.frombuffer(buf, dtype=dtype).reshape(h, w).astype(np.uint16)
    far = float(np.mean(depth > DEPTH_IMPLAUSIBLE_MM))
    if far > 0.01:
        warnings.warn(f"{what}: {100 * far:.0f} % of the depth pixels read beyond "
                      f"{DEPTH_IMPLAUSIBLE_MM / 1000:g} m, farther than any Azure Kinect depth mode "
                      f"measures: damaged depth data?", stacklevel=2)
    return depth


def jpeg_ends(buf) -> bool:
    """Whether JPEG bytes end with the end-of-image marker FF D9 (trailing zero padding allowed);
    ``buf`` is bytes or a memoryview (only its tail is read)."""
    m = memoryview(buf).cast("B")
    n = len(m)
    while n and m[n - 1] == 0:
        n -= 1
    return n == 0 or (n >= 2 and m[n - 2] == 0xFF and m[n - 1] == 0xD9)


def _check_jpeg_ends(buf: bytes, what: str) -> None:
    """Refuse a JPEG without its end-of-image marker (FF D9; trailing zero padding allowed).

    OpenCV refuses such a JPEG, but the FFmpeg fallback decodes it to a full-size image with
    its missing rows invented and only says so on stderr, so the frame would enter the texture
    looking whole. The Azure Kinect writes such frames when USB bandwidth or storage cannot keep up
    (Azure-Kinect-Sensor-SDK issue 1354)."""
    if not jpeg_ends(buf):
        raise ValueError(f"{what}: colour MJPEG packet ({len(buf)} bytes) ends without the JPEG end marker: "
                         f"the image is truncated (a decoder would invent its lower rows); the file is corrupt. "
                         f"To leave out such captures set source.mkv.skip_damaged_color: true, or read around it with "
                         f"source.mkv.start / stop")


def _decode_color(buf: bytes, size: tuple[int, int], fmt: str, what: str) -> np.ndarray:
    """Packet bytes -> (H, W, 3) uint8 RGB."""
    w, h = size
    a = np.frombuffer(buf, dtype=np.uint8)
    if fmt == "MJPG":
        _check_jpeg_ends(buf, what)
        img = None
        if a.size:
            # damage inside the data (end marker intact) decodes to a wrong full-size image: refused
            img = decode_jpeg(a, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION,
                              f"{what} (read around it with source.mkv.start / stop)")
        if img is None:
            img = _decode_mjpeg_ffmpeg(buf)
        if img is None:
            raise ValueError(f"{what}: colour MJPEG packet ({len(buf)} bytes) cannot be decoded; "
                             "the file is corrupt or truncated")
        if img.shape[:2] != (h, w):
            raise ValueError(f"{what}: colour image is {img.shape[1]}x{img.shape[0]}, the track says {w}x{h}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    expected = {"BGRA": w * h * 4, "NV12": w * h * 3 // 2, "YUY2": w * h * 2}[fmt]
    if a.size != expected:
        raise ValueError(f"{what}: {fmt} colour packet has {a.size} bytes, expected {expected} "
                         f"for {w}x{h}; the file is corrupt or truncated")
    if fmt == "BGRA":
        return cv2.cvtColor(a.reshape(h, w, 4), cv2.COLOR_BGRA2RGB)
    if fmt == "NV12":
        return cv2.cvtColor(a.reshape(h * 3 // 2, w), cv2.COLOR_YUV2RGB_NV12)
    return cv2.cvtColor(a.reshape(h, w, 2), cv2.COLOR_YUV2RGB_YUY2)


def _decode_mjpeg_ffmpeg(buf: bytes) -> np.ndarray | None:
    """Fallback MJPEG decoder (FFmpeg through PyAV); returns BGR like cv2.imdecode, or None."""
    try:
        import av  # PyAV is slow to import; only this fallback decoder needs it

        ctx = av.CodecContext.create("mjpeg", "r")
        frames = ctx.decode(av.Packet(buf)) + ctx.decode(None)
        if not frames:
            return None
        return frames[0].to_ndarray(format="bgr24")
    except Exception:  # noqa: BLE001 -- any decoder failure means "cannot decode"
        return None


# --------------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------------

def _to_us(pts: int, time_base: Fraction) -> int:
    """Stream timestamp -> integer microseconds (exact integer arithmetic, rounded half up).

    Matroska time bases differ between writers (k4arecorder: 1/1000000 s; FFmpeg: 1/1000 s).
    """
    num, den = time_base.numerator, time_base.denominator
    return (2 * int(pts) * num * 1_000_000 + den) // (2 * den)


def _int_tag(tags: dict, key: str, path: Path) -> int:
    value = tags.get(key)
    if value in (None, ""):
        return 0
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"{path}: tag {key} is not an integer: {value!r}") from None


def _pair_captures(color_us: np.ndarray, depth_us: np.ndarray, tolerance_us: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy in-order pairing of two sorted timestamp lists within ``tolerance_us``.

    Returns index arrays (ic, id) of the paired colour and depth images.
    """
    ic, idp = [], []
    i = j = 0
    while i < len(color_us) and j < len(depth_us):
        dt = int(color_us[i]) - int(depth_us[j])
        if abs(dt) < tolerance_us:
            ic.append(i)
            idp.append(j)
            i += 1
            j += 1
        elif dt < 0:
            i += 1
        else:
            j += 1
    return np.asarray(ic, dtype=np.int64), np.asarray(idp, dtype=np.int64)


def open_kinect_mkv(path, backend: str = "auto", allow_truncated: bool = False,
                    skip_damaged_color: bool = False) -> "KinectRecording":
    """Open an Azure Kinect recording; see :class:`KinectRecording`."""
    return KinectRecording(path, backend=backend, allow_truncated=allow_truncated, skip_damaged_color=skip_damaged_color)


class KinectRecording:
    """An Azure Kinect ``.mkv`` recording opened for reading (a context manager).

    Args:
        path: the ``.mkv`` file written by ``k4arecorder`` (or the SDK's record API).
        backend: ``'pyav'`` (PyAV demuxer + numpy/OpenCV decoding; tested), ``'pyk4a'`` (the
            Azure Kinect SDK through pyk4a; untested here, needs the SDK installed) or
            ``'auto'`` (pyk4a when importable, else PyAV).
        allow_truncated: read a truncated file's complete captures instead of refusing it
            (PyAV backend; a warning is issued).
        skip_damaged_color: leave out the colour images whose MJPEG is cut short (no JPEG end
            marker; the Azure Kinect writes such frames when USB bandwidth or storage cannot keep
            up), so their depth images go unpaired and those captures are skipped (PyAV backend;
            a warning says how many and when). Without it they stay captures, listed in
            ``damaged_color_captures``, and reading one raises ValueError.

    Attributes:
        path: ``pathlib.Path`` of the file.
        backend: ``'pyav'`` or ``'pyk4a'``.
        calibration: ``stex.camera.Calibration`` for the recorded modes (see
            :func:`stex.readers.kinect_calibration.calibration_from_k4a_json`); distortion is *not* removed from the frames,
            use :class:`Undistorter` for that.
        calibration_json: the parsed ``calibration.json`` attachment (dict).
        color_mode: e.g. ``'720P'``; depth_mode: e.g. ``'NFOV_UNBINNED'``.
        color_format: ``'MJPG'``, ``'BGRA'``, ``'NV12'`` or ``'YUY2'`` (as stored).
        color_size, depth_size: ``(width, height)`` in pixels.
        n_frames: number of captures holding both a colour and a depth image (colour and depth
            images are paired like the SDK does: timestamps closer than half a frame period,
            after the ``K4A_DEPTH_DELAY_NS`` correction). ``len(recording)`` is the same.
        timestamps_us: (n_frames,) int64 device timestamps of the captures' depth images, µs.
        color_timestamps_us: (n_frames,) int64 device timestamps of the colour images, µs.
        start_offset_us: device time of the file's time 0 (``K4A_START_OFFSET_NS`` / 1000).
        frame_period_us: median spacing of the depth images (pairing tolerance is half of it).
        n_unpaired_color, n_unpaired_depth: images that found no partner (skipped).
        damaged_color_captures: capture indices whose colour MJPEG is cut short (PyAV backend;
            empty with ``skip_damaged_color``). n_damaged_color_skipped: such colour images left
            out with ``skip_damaged_color``.
        metadata: container-level tags (dict of str).
    """

    def __init__(self, path, backend: str = "auto", allow_truncated: bool = False, skip_damaged_color: bool = False):
        self.path = Path(path)
        self.skip_damaged_color = bool(skip_damaged_color)
        self.damaged_color_captures: list[int] = []
        self.n_damaged_color_skipped = 0
        if backend not in ("auto", "pyav", "pyk4a"):
            raise ValueError(f"backend must be 'auto', 'pyav' or 'pyk4a', got {backend!r}")
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such Azure Kinect recording")
        if not self.path.is_file():
            raise ValueError(f"{self.path}: is not a regular file")
        if backend == "auto":
            try:
                import pyk4a  # noqa: F401

                backend = "pyk4a"
            except Exception:  # noqa: BLE001 -- ImportError, or the native library failing to load
                backend = "pyav"
        self.backend = backend
        self._closed = False
        self._playback = None
        _check_matroska(self.path, allow_truncated)
        try:
            if backend == "pyav":
                self._open_pyav()
            else:
                self._open_pyk4a()
        except BaseException:
            self.close()
            raise

    # ---------------------------------------------------------------- common API

    def __enter__(self) -> "KinectRecording":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return (f"KinectRecording({str(self.path)!r}, backend={self.backend!r}, n_frames={self.n_frames}, "
                f"color={self.color_format} {self.color_size[0]}x{self.color_size[1]}, "
                f"depth={self.depth_mode} {self.depth_size[0]}x{self.depth_size[1]})")

    def close(self) -> None:
        """Release the file (idempotent)."""
        if self._playback is not None:
            try:
                self._playback.close()
            finally:
                self._playback = None
        self._closed = True

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """Iterate over captures ``start .. stop-1`` in order.

        Yields:
            ``(index, timestamp_us, color, depth)``: capture index (int), device timestamp of the
            depth image (int, µs), colour (Hc, Wc, 3) uint8 **RGB**, depth (Hd, Wd) uint16
            millimetres (0 = no measurement). Lens distortion is left in both images.

        Raises:
            FrameIndexError (a ValueError) when ``start``/``stop`` fall outside ``[0, n_frames]``;
            ValueError naming the file and the frame for corrupt packets.
        """
        if self._closed:
            raise ValueError(f"{self.path}: recording is closed")
        start, stop = self._check_range(start, stop)
        if start == stop:
            return iter(())
        if self.backend == "pyav":
            return self._frames_pyav(start, stop)
        return self._frames_pyk4a(start, stop)

    def read_frame(self, index: int) -> tuple[int, np.ndarray, np.ndarray]:
        """One capture: ``(timestamp_us, color (Hc,Wc,3) uint8 RGB, depth (Hd,Wd) uint16 mm)``."""
        index = int(index)
        if not 0 <= index < self.n_frames:
            raise FrameIndexError(f"{self.path}: frame index {index} out of range: the recording has "
                                  f"{self.n_frames} captures with colour and depth (0..{self.n_frames - 1})")
        for _, ts, color, depth in self.frames(index, index + 1):
            return ts, color, depth
        raise ValueError(f"{self.path}: frame {index} could not be read")  # pragma: no cover

    def _check_range(self, start, stop) -> tuple[int, int]:
        n = self.n_frames
        start = int(start)
        stop = n if stop is None else int(stop)
        if not 0 <= start <= n:
            raise FrameIndexError(f"{self.path}: start frame {start} out of range 0..{n} "
                                  f"(the recording has {n} captures with colour and depth)")
        if not start <= stop <= n:
            raise FrameIndexError(f"{self.path}: stop frame {stop} out of range {start}..{n} "
                                  f"(the recording has {n} captures with colour and depth)")
        return start, stop

    def _set_modes(self, color_tag: str | None, depth_tag: str | None) -> None:
        """Resolve colour/depth modes from the track tags, cross-checked with the track sizes."""
        self.color_mode = parse_color_resolution(color_tag if color_tag else self.color_size)
        if COLOR_RESOLUTIONS[self.color_mode].output != self.color_size:
            raise ValueError(f"{self.path}: COLOR track is {self.color_size[0]}x{self.color_size[1]} but its "
                             f"K4A_COLOR_MODE tag says {color_tag!r}")
        self.depth_mode = parse_depth_mode(depth_tag if depth_tag else self.depth_size)
        if DEPTH_MODES[self.depth_mode].output != self.depth_size:
            raise ValueError(f"{self.path}: DEPTH track is {self.depth_size[0]}x{self.depth_size[1]} but its "
                             f"K4A_DEPTH_MODE tag says {depth_tag!r}")
        try:
            self.calibration = calibration_from_k4a_json(self.calibration_json, self.color_mode, self.depth_mode)
        except ValueError as e:
            raise ValueError(f"{self.path}: bad calibration.json attachment: {e}") from e
        # as the folder reader does for its calibration file: a principal point far from the
        # centre of the recorded images (in none of the 30 modes of the shared sample's device)
        self.calibration.warn_suspicious(str(self.path))

    # ---------------------------------------------------------------- PyAV backend

    def _av_open(self):
        import av  # PyAV is slow to import; only the PyAV backend needs it

        try:
            return av.open(str(self.path), mode="r")
        except av.error.FFmpegError as e:
            raise ValueError(f"{self.path}: cannot be opened as a Matroska file: {e}") from e

    def _open_pyav(self) -> None:
        import av  # PyAV is slow to import; only the PyAV backend needs it

        container = self._av_open()
        try:
            if "matroska" not in container.format.name:
                raise ValueError(f"{self.path}: not a Matroska file (container format {container.format.name!r})")
            self.metadata = dict(container.metadata)
            by_title: dict[str, object] = {}
            for s in container.streams:
                title = s.metadata.get("title")
                if s.type == "video" and title and title not in by_title:
                    by_title[title] = s
            for need in ("COLOR", "DEPTH"):
                if need not in by_title:
                    raise ValueError(f"{self.path}: no {need} track (video tracks found: "
                                     f"{sorted(by_title) or 'none'}); a k4arecorder file with colour and depth "
                                     "is needed")
            cs, ds = by_title["COLOR"], by_title["DEPTH"]
            self.calibration_json = self._read_attachment(container)
            self.color_size = (int(cs.codec_context.width), int(cs.codec_context.height))
            self.depth_size = (int(ds.codec_context.width), int(ds.codec_context.height))
            self.color_format = self._color_format(cs)
            self._depth_dtype = self._depth_format(ds)
            self._set_modes(cs.metadata.get("K4A_COLOR_MODE"), ds.metadata.get("K4A_DEPTH_MODE"))
            self._color_index, self._depth_index = cs.index, ds.index
            self.start_offset_us = _int_tag(self.metadata, "K4A_START_OFFSET_NS", self.path) // 1000
            depth_delay_us = _int_tag(self.metadata, "K4A_DEPTH_DELAY_NS", self.path) / 1000.0

            # One pass over the packets (no decoding) to build the capture index.
            c_pts, c_dur, c_whole, d_pts, d_dur = [], [], [], [], []
            mjpeg = self.color_format == "MJPG"
            try:
                for pkt in container.demux(cs, ds):
                    if pkt.pts is None or pkt.size == 0:
                        continue
                    if pkt.stream.index == cs.index:
                        c_pts.append(pkt.pts)
                        c_dur.append(pkt.duration or 0)
                        c_whole.append(not mjpeg or jpeg_ends(memoryview(pkt)))
                    else:
                        d_pts.append(pkt.pts)
                        d_dur.append(pkt.duration or 0)
            except av.error.FFmpegError as e:
                raise ValueError(f"{self.path}: corrupt Matroska data after {len(c_pts)} colour and "
                                 f"{len(d_pts)} depth images: {e}") from e
            self._color_tb = Fraction(cs.time_base)
            self._depth_tb = Fraction(ds.time_base)
        finally:
            container.close()

        c_pts = np.asarray(c_pts, dtype=np.int64)
        d_pts = np.asarray(d_pts, dtype=np.int64)
        oc, od = np.argsort(c_pts, kind="stable"), np.argsort(d_pts, kind="stable")
        c_pts, d_pts = c_pts[oc], d_pts[od]
        c_whole = np.asarray(c_whole, bool)[oc]
        if self.skip_damaged_color and not c_whole.all():
            cut = c_pts[~c_whole]
            self.n_damaged_color_skipped = int(len(cut))
            warnings.warn(f"{self.path}: {len(cut)} colour images are cut short (no JPEG end marker) and are left "
                          f"out with their depth images (source.mkv.skip_damaged_color), at "
                          f"{', '.join(f'{float(_to_us(p, self._color_tb)) * 1e-6:.3f} s' for p in cut[:10])}{' ...' if len(cut) > 10 else ''} "
                          f"(recording time); the captures after them are numbered on", stacklevel=3)
            c_pts, c_whole = c_pts[c_whole], c_whole[c_whole]
        c_us = np.array([_to_us(p, self._color_tb) for p in c_pts], dtype=np.int64)
        d_us = np.array([_to_us(p, self._depth_tb) for p in d_pts], dtype=np.int64)
        period = self._frame_period_us(d_us, [d_dur[i] for i in od], self._depth_tb)
        ic, idp = _pair_captures(c_us + depth_delay_us, d_us, period / 2.0)
        self.frame_period_us = period
        self._cap_color_pts = c_pts[ic]
        self._cap_depth_pts = d_pts[idp]
        self.timestamps_us = d_us[idp] + self.start_offset_us
        self.color_timestamps_us = c_us[ic] + self.start_offset_us
        self.n_frames = int(len(idp))
        self.damaged_color_captures = np.flatnonzero(~c_whole[ic]).tolist()
        self.n_unpaired_color = int(len(c_us) - len(ic))
        self.n_unpaired_depth = int(len(d_us) - len(idp))
        if self.n_unpaired_color or self.n_unpaired_depth:
            log.info("%s: %d colour and %d depth images have no partner and are skipped",
                     self.path, self.n_unpaired_color, self.n_unpaired_depth)
        # unpaired images at the ends are usual; a hole inside the sequence is a lost capture
        gap = np.flatnonzero(np.diff(self.timestamps_us) > 1.5 * period)
        if len(gap):
            warnings.warn(f"{self.path}: the captures are not evenly spaced: {len(gap)} gap(s) of more than one "
                          f"frame period ({period / 1000:.1f} ms), after capture(s) {gap[:10].tolist()} (lost or "
                          f"damaged data, or an image without its partner); the frames after each gap are "
                          f"numbered on without it", stacklevel=3)

    @staticmethod
    def _frame_period_us(d_us: np.ndarray, durations: list, tb: Fraction) -> float:
        if len(d_us) >= 2:
            diffs = np.diff(d_us)
            diffs = diffs[diffs > 0]
            if diffs.size:
                return float(np.median(diffs))
        durs = [d for d in durations if d > 0]
        if durs:
            return float(_to_us(int(np.median(durs)), tb))
        return 1e6 / 30.0

    def _read_attachment(self, container) -> dict:
        for s in container.streams:
            if s.type != "attachment":
                continue
            name = getattr(s, "name", None) or s.metadata.get("filename")
            if name == "calibration.json" or "K4A_CALIBRATION_FILE" in s.metadata:
                try:
                    return json.loads(bytes(s.data).decode("utf-8"))
                except (UnicodeDecodeError, json.JSONDecodeError) as e:
                    raise ValueError(f"{self.path}: calibration.json attachment is not valid JSON: {e}") from e
        raise ValueError(f"{self.path}: no calibration.json attachment (tag K4A_CALIBRATION_FILE); "
                         "without it the camera intrinsics are unknown")

    def _color_format(self, s) -> str:
        cc = s.codec_context
        if cc.name == "mjpeg":
            return "MJPG"
        tag = (cc.codec_tag or "").strip("\x00 ")
        if tag.upper() in _COLOR_FORMATS:
            return tag.upper()
        pix = cc.format.name if cc.format is not None else ""
        by_pix = {"bgra": "BGRA", "nv12": "NV12", "yuyv422": "YUY2"}
        if pix in by_pix:
            return by_pix[pix]
        raise ValueError(f"{self.path}: unsupported COLOR track (codec {cc.name!r}, FourCC {tag!r}, pixel format "
                         f"{pix!r}); expected MJPEG, BGRA, NV12 or YUY2")

    def _depth_format(self, s) -> str:
        cc = s.codec_context
        tag = (cc.codec_tag or "").strip("\x00 ")
        pix = cc.format.name if cc.format is not None else ""
        if cc.name == "rawvideo" and (tag == "b16g" or pix == "gray16be"):
            return ">u2"
        if cc.name == "rawvideo" and pix == "gray16le":
            return "<u2"
        raise ValueError(f"{self.path}: unsupported DEPTH track (codec {cc.name!r}, FourCC {tag!r}, pixel format "
                         f"{pix!r}); expected raw 16-bit 'b16g' as written by k4arecorder")

    def _frames_pyav(self, start: int, stop: int):
        import av  # PyAV is slow to import; only the PyAV backend needs it

        want_c = {int(p): i for i, p in enumerate(self._cap_color_pts[start:stop], start)}
        want_d = {int(p): i for i, p in enumerate(self._cap_depth_pts[start:stop], start)}
        first_c, first_d = int(self._cap_color_pts[start]), int(self._cap_depth_pts[start])

        def packets(seek: bool):
            container = self._av_open()
            try:
                cs = container.streams[self._color_index]
                ds = container.streams[self._depth_index]
                if seek:
                    t_us = min(_to_us(first_c, self._color_tb), _to_us(first_d, self._depth_tb))
                    container.seek(max(t_us - 1, 0), backward=True, any_frame=False)  # offset in av.time_base = µs
                for pkt in container.demux(cs, ds):
                    if pkt.pts is None or pkt.size == 0:
                        continue
                    yield pkt
            finally:
                container.close()

        next_idx = start
        color_buf: dict[int, bytes] = {}
        depth_buf: dict[int, bytes] = {}
        gen = packets(seek=start > 0)
        source = gen
        if start > 0:
            # The seek must not land after the first wanted packet of either stream (packets of
            # one stream arrive in timestamp order); check the first packet of each stream and
            # fall back to reading from the beginning when it did.
            pre = []
            first_seen: dict[int, int] = {}
            try:
                for pkt in gen:
                    pre.append(pkt)
                    first_seen.setdefault(pkt.stream.index, int(pkt.pts))
                    if len(first_seen) == 2:
                        break
            except av.error.FFmpegError as e:
                raise ValueError(f"{self.path}: corrupt Matroska data near frame {start}: {e}") from e
            ok = (first_seen.get(self._color_index, first_c + 1) <= first_c
                  and first_seen.get(self._depth_index, first_d + 1) <= first_d)
            if not ok:
                gen.close()
                log.debug("%s: seek to frame %d imprecise; reading from the start", self.path, start)
                gen = packets(seek=False)
                pre = []
            source = _chain(pre, gen)

        try:
            for pkt in source:
                sidx = pkt.stream.index
                if sidx == self._color_index:
                    i = want_c.get(int(pkt.pts))
                    if i is not None and i >= next_idx:
                        color_buf[i] = bytes(pkt)
                elif sidx == self._depth_index:
                    i = want_d.get(int(pkt.pts))
                    if i is not None and i >= next_idx:
                        depth_buf[i] = bytes(pkt)
                while next_idx in color_buf and next_idx in depth_buf:
                    yield self._decode_capture(next_idx, color_buf.pop(next_idx), depth_buf.pop(next_idx))
                    next_idx += 1
                    if next_idx >= stop:
                        return
        except av.error.FFmpegError as e:
            raise ValueError(f"{self.path}: corrupt Matroska data while reading frame {next_idx}: {e}") from e
        finally:
            gen.close()
        if next_idx < stop:
            raise ValueError(f"{self.path}: the file ended before frame {next_idx} "
                             f"(expected {self.n_frames} captures); it was modified or is corrupt")

    def _decode_capture(self, index: int, cbuf: bytes, dbuf: bytes):
        what = f"{self.path}: frame {index} (t={int(self.timestamps_us[index])} us)"
        depth = _decode_depth(dbuf, self.depth_size, self._depth_dtype, what)
        color = _decode_color(cbuf, self.color_size, self.color_format, what)
        return index, int(self.timestamps_us[index]), color, depth

    # ---------------------------------------------------------------- pyk4a backend (untested here)

    def _open_pyk4a(self) -> None:
        import pyk4a  # optional: the Azure Kinect SDK's binding, for its own backend

        try:
            pb = pyk4a.PyK4APlayback(str(self.path))
            pb.open()
        except Exception as e:  # noqa: BLE001 -- pyk4a raises K4AException for anything
            raise ValueError(f"{self.path}: the Azure Kinect SDK cannot open this recording: {e}") from e
        self._playback = pb
        try:
            cfg = pb.configuration
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"{self.path}: the Azure Kinect SDK cannot read the recording configuration: {e}") from e
        if not cfg["color_track_enabled"] or not cfg["depth_track_enabled"]:
            raise ValueError(f"{self.path}: no {'COLOR' if not cfg['color_track_enabled'] else 'DEPTH'} track; "
                             "a recording with colour and depth is needed")
        try:
            raw = pb.calibration_raw
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"{self.path}: no readable calibration.json attachment: {e}") from e
        try:
            self.calibration_json = json.loads(raw)
        except json.JSONDecodeError as e:
            raise ValueError(f"{self.path}: calibration.json attachment is not valid JSON: {e}") from e
        fmt = pyk4a.ImageFormat(cfg["color_format"]).name  # COLOR_MJPG, COLOR_BGRA32, ...
        self.color_format = {"COLOR_MJPG": "MJPG", "COLOR_BGRA32": "BGRA", "COLOR_NV12": "NV12",
                             "COLOR_YUY2": "YUY2"}.get(fmt)
        if self.color_format is None:
            raise ValueError(f"{self.path}: unsupported colour format {fmt}")
        color_key = parse_color_resolution(pyk4a.ColorResolution(cfg["color_resolution"]).name)
        depth_key = parse_depth_mode(pyk4a.DepthMode(cfg["depth_mode"]).name)
        self.color_size = COLOR_RESOLUTIONS[color_key].output
        self.depth_size = DEPTH_MODES[depth_key].output
        self._set_modes(color_key, depth_key)
        self.metadata = {}
        self.start_offset_us = int(cfg.get("start_timestamp_offset_usec", 0))
        self.frame_period_us = {0: 200000.0, 1: 1e6 / 15, 2: 1e6 / 30}.get(int(cfg["camera_fps"]), 1e6 / 30)
        # Index pass: the SDK groups images into captures itself.
        d_ts, c_ts = [], []
        n_c_only = n_d_only = 0
        while True:
            try:
                cap = pb.get_next_capture()
            except EOFError:
                break
            has_c = cap.color is not None
            has_d = cap.depth is not None
            if has_c and has_d:
                d_ts.append(int(cap.depth_timestamp_usec))
                c_ts.append(int(cap.color_timestamp_usec))
            else:
                n_c_only += has_c and not has_d
                n_d_only += has_d and not has_c
        self.timestamps_us = np.asarray(d_ts, dtype=np.int64)
        self.color_timestamps_us = np.asarray(c_ts, dtype=np.int64)
        self.n_frames = len(d_ts)
        self.n_unpaired_color, self.n_unpaired_depth = int(n_c_only), int(n_d_only)
        self._ts_to_index = {t: i for i, t in enumerate(d_ts)}

    def _frames_pyk4a(self, start: int, stop: int):
        import pyk4a  # optional: the Azure Kinect SDK's binding, for its own backend

        pb = self._playback
        target = int(self.timestamps_us[start])

        def run(seek_origin_device: bool):
            if seek_origin_device:
                pb.seek(target, origin=pyk4a.SeekOrigin.DEVICE_TIME)
            else:
                pb.seek(0, origin=pyk4a.SeekOrigin.BEGIN)
            while True:
                try:
                    cap = pb.get_next_capture()
                except EOFError:
                    return
                if cap.color is None or cap.depth is None:
                    continue
                i = self._ts_to_index.get(int(cap.depth_timestamp_usec))
                if i is None:
                    continue
                yield i, cap

        nxt = start
        gen = run(True)
        restarted = False
        try:
            while nxt < stop:
                item = next(gen, None)
                if item is None:
                    break
                i, cap = item
                if i > nxt and not restarted:  # the seek overshot: read from the beginning
                    gen.close()
                    gen, restarted = run(False), True
                    continue
                if i < nxt:
                    continue
                if i > nxt:
                    raise ValueError(f"{self.path}: frame {nxt} was not found when reading the file again")
                yield self._decode_pyk4a(i, cap)
                nxt += 1
        finally:
            gen.close()
        if nxt < stop:
            raise ValueError(f"{self.path}: the file ended before frame {nxt}")

    def _decode_pyk4a(self, index: int, cap):
        what = f"{self.path}: frame {index} (t={int(self.timestamps_us[index])} us)"
        depth = np.asarray(cap.depth)
        w, h = self.depth_size
        if depth.shape != (h, w):
            raise ValueError(f"{what}: depth image is {depth.shape}, expected ({h}, {w})")
        raw = np.ascontiguousarray(np.asarray(cap.color, dtype=np.uint8))
        color = _decode_color(raw.tobytes(), self.color_size, self.color_format, what)
        return index, int(self.timestamps_us[index]), color, depth.astype(np.uint16, copy=False)


def _chain(first, rest):
    yield from first
    yield from rest
