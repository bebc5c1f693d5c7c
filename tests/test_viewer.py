"""stex view: the viewer's buffers, the folder it writes from the tiny scene's run, and the page in
a real browser (Debian's headless chromium driven by Playwright, served by a local http.server):
frames advance when playing, and the input camera's view at frame k is `stex preview`'s render
of frame k."""

from __future__ import annotations

import base64
import functools
import io
import json
import shutil
import threading
import time
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import results_folder
from stex.camera import transform_points
from stex.metrics import render_texture
from stex.export import opencv_to_viewer, preview_frame
from stex.stages.export import RunResults
from stex.viewer import write_view
from stex.viewer.pack import corner_buffers, quantize_positions, viewer_positions
from stex.sampling import label_colors

CHROMIUM = Path("/usr/bin/chromium")
# what works headless on a machine without a GPU: WebGL through SwiftShader
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
PREVIEW_SIZE = 360  # stex preview's default panel height
BACKGROUND = 48     # stex preview's grey behind the mesh


# --------------------------------------------------------------------------------------------
# buffers (pure)
# --------------------------------------------------------------------------------------------

def test_positions_decode_within_half_a_step():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(4, 50, 3)) * [0.2, 0.3, 0.1] + [0, 0, -1.2]
    p[:, :, 0] = 0.25  # an axis without extent decodes exactly
    code, offset, step = quantize_positions(p)
    assert code.dtype == np.uint16 and code.shape == p.shape
    decoded = offset + code * step
    assert (np.abs(decoded - p) <= step / 2 + 1e-12).all()
    assert code[..., 1:].min() == 0 and code[..., 1:].max() == 65535  # the box's whole range is used
    np.testing.assert_array_equal(decoded[..., 0], 0.25)
    for bad in (np.zeros((3, 3)), np.zeros((0, 4, 3)), np.full((1, 2, 3), np.nan)):
        with pytest.raises(ValueError, match="positions must"):
            quantize_positions(bad)


def test_gpu_vertices_carry_each_corners_position_and_texcoord():
    from test_export import cube

    V, F, tc, tf = cube()
    vertex_index, uv, index = corner_buffers(F, tc, tf)
    assert len(vertex_index) == 24  # a chart per side: every corner of the cube is on 3 seams
    tri = index.reshape(-1, 3)
    np.testing.assert_array_equal(vertex_index[tri], F)
    np.testing.assert_array_equal(uv[tri], tc[tf])
    assert index.dtype == vertex_index.dtype == np.uint32 and uv.dtype == np.float32
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.05]
    np.testing.assert_allclose(viewer_positions(V, T), opencv_to_viewer(V + T[:3, 3]))


# --------------------------------------------------------------------------------------------
# the folder
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_results(tiny_pipeline, tmp_path_factory):
    return results_folder(tiny_pipeline, tmp_path_factory.mktemp("view") / "results" / "tiny")


@pytest.fixture(scope="module")
def tiny_view(tiny_results):
    out = tiny_results.parent.parent / "view"
    index = write_view(tiny_results, out)
    assert index == out / "index.html"
    return out


def test_the_folder_holds_the_page_three_js_and_every_frame(tiny_view, tiny_results):
    res = RunResults(tiny_results)
    view = json.loads((tiny_view / "view.json").read_text())
    assert [f["id"] for f in view["frames"]] == res.frame_ids == list(range(6))
    for name in ("index.html", "viewer.js", "viewer.css", "three/three.module.min.js",
                 "three/three.core.min.js", "three/OrbitControls.js", "three/LICENSE"):
        assert (tiny_view / name).is_file(), name
    assert "MIT License" in (tiny_view / "three" / "LICENSE").read_text()
    # nothing the page loads comes from elsewhere
    for name in ("index.html", "viewer.js", "three/OrbitControls.js"):
        assert "http://" not in (tiny_view / name).read_text() and "https://" not in (tiny_view / name).read_text()
    code = np.fromfile(tiny_view / "data" / "positions.bin", np.uint16).reshape(view["positions"]["shape"])
    step = np.array(view["positions"]["step"])
    cal = res.calibration
    for k, fid in enumerate(res.frame_ids):
        want = viewer_positions(res.vertices(fid), cal.depth_to_color)
        got = np.array(view["positions"]["offset"]) + code[k] * step
        assert (np.abs(got - want) <= step / 2 + 1e-9).all()
        entry = view["frames"][k]
        tex = np.asarray(Image.open(tiny_view / entry["texture"]).convert("RGB"), float)
        assert np.abs(tex - res.texture(fid)).mean() < 3  # JPEG at quality 90
        np.testing.assert_array_equal(np.asarray(Image.open(tiny_view / entry["labels"]).convert("RGB")),
                                      label_colors(res.label_map(fid)))
        assert Image.open(tiny_view / entry["color"]).size == (cal.color.width, cal.color.height)
    mesh = (tiny_view / "data" / "mesh.bin").read_bytes()
    vi = np.frombuffer(mesh, np.uint32, view["mesh"]["vertex_index"]["count"], view["mesh"]["vertex_index"]["offset"])
    tri = np.frombuffer(mesh, np.uint32, view["mesh"]["index"]["count"], view["mesh"]["index"]["offset"])
    np.testing.assert_array_equal(vi[tri.reshape(-1, 3)], res.faces)


def test_a_frame_step_and_the_global_texture(tiny_results, tmp_path):
    write_view(tiny_results, tmp_path / "v", frames="1:", every=2, source="global", image_format="png")
    view = json.loads((tmp_path / "v" / "view.json").read_text())
    assert [f["id"] for f in view["frames"]] == [1, 3, 5]
    assert view["fps"] == pytest.approx(15.0) and not view["labels"]  # 30 fps capture, every 2nd
    assert not (tmp_path / "v" / "data" / "labels").exists()
    global_texture = RunResults(tiny_results, "global").texture(1)
    for f in view["frames"]:
        np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "v" / f["texture"])), global_texture)
    # an earlier view is replaced as a whole; a folder of other files is refused
    write_view(tiny_results, tmp_path / "v", frames="4")
    assert sorted(p.name for p in (tmp_path / "v" / "data" / "texture").iterdir()) == ["00004.jpg"]
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="holds other files"):
        write_view(tiny_results, tmp_path / "mine")
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]
    with pytest.raises(ValueError, match="image format must be one of"):
        write_view(tiny_results, tmp_path / "w", image_format="webp")
    assert not list(tmp_path.glob("v.partial*")) and not (tmp_path / "w").exists()


# --------------------------------------------------------------------------------------------
# the page in a real browser
# --------------------------------------------------------------------------------------------

class _Quiet(SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def page(tiny_view, tmp_path_factory):
    """A headless chromium page, and the base URL of the tiny view served from 127.0.0.1."""
    if not CHROMIUM.exists():
        pytest.skip(f"no {CHROMIUM}: the viewer's browser test needs Debian's chromium package "
                    f"(apt-get install chromium; .ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="the viewer's browser test needs "
                                   "playwright (pip install playwright; in the 'test' extra)")
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=str(tiny_view)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    errors = []
    try:
        with sync_api.sync_playwright() as pw:
            context = pw.chromium.launch_persistent_context(
                str(tmp_path_factory.mktemp("chromium-profile")), executable_path=str(CHROMIUM),
                headless=True, args=CHROMIUM_FLAGS, viewport={"width": 1280, "height": 800},
                device_scale_factor=1)
            p = context.new_page()
            p.on("pageerror", lambda e: errors.append(str(e)))
            yield p, f"http://127.0.0.1:{server.server_address[1]}/index.html", errors
            context.close()
    finally:
        server.shutdown()
        server.server_close()


def _open(p, url, errors):
    p.goto(url)
    p.wait_for_function("window.stexViewer && (window.stexViewer.ready || window.stexViewer.error)",
                        timeout=30_000)
    assert p.evaluate("window.stexViewer.error") is None and not errors, (p.evaluate("window.stexViewer.error"), errors)


_CANVAS = "document.getElementById('view').toDataURL('image/png')"


def _pixels(data_url: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data_url.split(",", 1)[1]))).convert("RGB"))


def _canvas(p) -> np.ndarray:
    """The canvas's pixels as drawn, (H, W, 3) uint8 (one canvas pixel per image pixel)."""
    return _pixels(p.evaluate(_CANVAS))


def test_frames_advance_when_playing_and_stop_when_paused(page):
    p, url, errors = page
    _open(p, f"{url}?play=1", errors)
    seen, images, start = set(), {}, time.monotonic()
    while time.monotonic() - start < 10.0 and len(seen) < 6:
        # read in one go: the page shows the next frame between two evaluations
        k, slider, pixels = p.evaluate(f"[window.stexViewer.frame, document.getElementById('slider').value, {_CANVAS}]")
        assert slider == str(k)  # the slider follows the shown frame
        seen.add(k)
        images.setdefault(k, _pixels(pixels))
        time.sleep(0.05)
    assert len(seen) >= 4, seen  # six frames at 30 frames/s: all of them come by in far less than 10 s
    a, b = sorted(images)[:2]
    assert (np.abs(images[a].astype(int) - images[b]) > 8).any()  # the mesh moves and its texture changes
    src, fid = p.evaluate("[document.getElementById('input').src, window.stexViewer.frameId]")
    assert src.endswith("data/color/%05d.jpg" % fid)  # the input frame beside it is the same frame's
    p.click("#play")  # pause
    time.sleep(0.2)  # a frame already being shown when the button was clicked is drawn
    shown = p.evaluate("window.stexViewer.shown")
    time.sleep(0.5)
    assert p.evaluate("window.stexViewer.shown") == shown and not p.evaluate("window.stexViewer.playing")
    before = _canvas(p)
    p.click("#labels")  # the label map overlay changes the object, not the background
    after = _canvas(p)
    changed = np.any(before != after, axis=2)
    background = np.all(before == BACKGROUND, axis=2)
    assert changed.sum() > 0.5 * (~background).sum() and not (changed & background).any()
    assert not errors, errors


def test_the_input_camera_view_is_the_previews_render(page, tiny_results):
    """``camera=input&frame=k&size=360`` draws the middle panel of ``stex preview`` (the textured
    mesh from the input colour camera, its intrinsics scaled to the panel height): PSNR over the
    object (where stex's renderer covers the pixel centre, below the panel's label) >= 25 dB."""
    p, url, errors = page
    res = RunResults(tiny_results)
    cal = res.calibration
    for k in (0, 3, 5):
        _open(p, f"{url}?camera=input&frame={k}&size={PREVIEW_SIZE}", errors)
        fid = p.evaluate("window.stexViewer.frameId")
        assert fid == res.frame_ids[k]
        shot = _canvas(p)
        args = (res.vertices(fid), res.faces, res.texcoords, res.texcoord_faces, res.texture(fid))
        preview = preview_frame(res.color(fid), *args, cal, size=PREVIEW_SIZE)
        h, w = shot.shape[:2]
        assert h == PREVIEW_SIZE and preview.shape == (h, 3 * w, 3)
        panel = preview[:, w:2 * w]
        small = cal.color.scaled(h / cal.color.height)
        vc = transform_points(cal.depth_to_color, np.asarray(args[0], np.float64))
        _, mask = render_texture(vc, *args[1:], small.K, w, h)
        mask[:max(12, h // 18) + 7] = False  # preview_frame's label bar
        err = (shot.astype(float) - panel)[mask]
        psnr = 10 * np.log10(255.0 ** 2 / np.mean(err ** 2))
        drawn = np.any(shot != BACKGROUND, axis=2)
        outline = (drawn ^ mask)[max(12, h // 18) + 7:].sum()
        print(f"frame {fid}: PSNR {psnr:.2f} dB over {mask.sum()} px, silhouettes differ at {outline} px")
        assert psnr >= 25.0, (fid, psnr)
        assert outline <= 0.01 * mask.sum(), (fid, outline)
