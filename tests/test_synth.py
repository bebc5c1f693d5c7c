"""Synthetic scenes: geometry, coverage, shape-tied appearance, determinism, degradations, ingest."""
import copy

import numpy as np
import pytest
import trimesh

from conftest import data_samples
from stex.config import load_config
from stex.render import face_visibility, rasterize
from stex.synth.procedural import ProceduralBody, ProceduralParams
from stex.synth.scene import SyntheticScene


def test_procedural_mesh_is_closed_and_outward():
    body = ProceduralBody(ProceduralParams(n_around=32, n_rings=16))
    for t in (None, 0.4, 1.3):
        m = trimesh.Trimesh(body.vertices(t), body.faces, process=False)
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume > 0  # outward normals
    assert body.texcoord_faces.shape == body.faces.shape
    assert body.texcoords.min() >= 0 and body.texcoords.max() <= 1


def test_appearance_follows_shape():
    body = ProceduralBody(ProceduralParams(n_around=32, n_rings=16))
    base = body.base_texture(128)
    rest = body.appearance(None, 128, base).astype(float)
    # Two times with the same deformation state have the same appearance (shape -> texture).
    p = body.p
    period = np.lcm.reduce([int(round(x * 10)) for x in (p.bend_period, p.twist_period, p.squash_period, p.bulge_period)]) / 10
    a, b = body.appearance(0.7, 128, base), body.appearance(0.7 + period, 128, base)
    assert np.array_equal(a, b)
    # Where the surface is compressed the texture darkens; where it is not, it is unchanged.
    t = p.bend_period / 4  # maximum bend
    c = (np.arange(128) + 0.5) / 128
    s, v = np.meshgrid(c, c)
    comp = body.compression(s, 1 - v, t)
    app = body.appearance(t, 128, base).astype(float)
    patch = np.exp(-(((s - 0.02 + 0.5) % 1 - 0.5) ** 2 / 0.06**2 + ((1 - v) - 0.33) ** 2 / 0.07**2)) > 0.01
    squeezed = (comp > 0.1) & ~patch
    relaxed = (comp < 1e-3) & ~patch
    assert squeezed.sum() > 100 and relaxed.sum() > 100
    assert app[squeezed].mean() < 0.85 * rest[squeezed].mean()
    assert np.abs(app[relaxed] - rest[relaxed]).max() <= 1
    # The pose patch turns red when bent one way and blue the other.
    t_neg = 3 * p.bend_period / 4
    core = np.exp(-(((s - 0.02 + 0.5) % 1 - 0.5) ** 2 / 0.06**2 + ((1 - v) - 0.33) ** 2 / 0.07**2)) > 0.6
    red = body.appearance(t, 128, base)[core].mean(0)
    blue = body.appearance(t_neg, 128, base)[core].mean(0)
    assert red[0] > red[2] + 40 and blue[2] > blue[0] + 40


def _coverage(scene):
    K = scene.calibration.depth.K
    W, H = scene.calibration.depth.size
    F = scene.faces
    ever = np.zeros(len(F), bool)
    per_frame = []
    V0 = scene.true_vertices(0)
    area = 0.5 * np.linalg.norm(np.cross(V0[F[:, 1]] - V0[F[:, 0]], V0[F[:, 2]] - V0[F[:, 0]]), axis=1)
    for t in range(scene.n_frames):
        V = scene.true_vertices(t)
        vis, _ = face_visibility(V, F, K, rasterize(V, F, K, W, H).depth, min_cos=0.3)
        per_frame.append((area * vis).sum() / area.sum())
        ever |= vis
    return np.array(per_frame), (area * ever).sum() / area.sum()


def test_demo_scene_sees_a_third_per_frame_and_most_overall(demo_config):
    cfg = copy.deepcopy(demo_config["source"]["synthetic"])
    scene = SyntheticScene(cfg)
    per_frame, ever = _coverage(scene)
    # Measured: per frame 0.26-0.33 of the area (faces at cos > 0.3), 0.79 seen at some frame.
    assert 0.25 <= per_frame.min() and per_frame.max() <= 0.42
    assert 0.75 <= ever <= 0.95  # most regions seen at some frame, a few (underside, back) never


def test_frames_are_deterministic_and_independent_of_order(tiny_config):
    cfg = tiny_config["source"]["synthetic"]
    a = SyntheticScene(cfg).render_frame(3)
    s = SyntheticScene(cfg)
    s.render_frame(5)
    b = s.render_frame(3)
    assert np.array_equal(a.color, b.color) and np.array_equal(a.depth_mm, b.depth_mm)
    assert np.array_equal(a.appearance, b.appearance)


def _with(tiny_config, **switch):
    cfg = copy.deepcopy(tiny_config["source"]["synthetic"])
    for name, value in switch.items():
        cfg["degradations"][name]["enabled"] = value
    return SyntheticScene(cfg)


@pytest.mark.parametrize("name", ["motion_blur", "sensor_noise", "exposure_drift", "depth_noise"])
def test_each_degradation_is_a_switch(tiny_config, name):
    off = {k: False for k in ("motion_blur", "sensor_noise", "exposure_drift", "depth_noise")}
    clean = _with(tiny_config, **off).render_frame(2)
    dirty = _with(tiny_config, **{**off, name: True}).render_frame(2)
    assert np.array_equal(clean.true_mask, dirty.true_mask)
    if name == "depth_noise":
        assert not np.array_equal(clean.depth_mm, dirty.depth_mm)
        assert np.array_equal(clean.color, dirty.color)
        assert (dirty.depth_mm == 0).sum() > (clean.depth_mm == 0).sum()  # holes
    else:
        assert np.array_equal(clean.depth_mm, dirty.depth_mm)
        diff = np.abs(clean.color.astype(int) - dirty.color.astype(int))[clean.true_mask]
        if name == "motion_blur":
            # blur changes colours only where the texture varies along the motion: measured
            # 31-33 % of the object's pixels over the tiny scene's frames 0-5, by 0.47-0.51 grey
            # levels on average (too close to any round threshold to test the mean); how much
            # it blurs is test_motion_blur_averages_renders_centred_on_the_frame_time's job
            assert (diff.max(-1) > 0).mean() > 0.1
        else:
            # noise and exposure change every pixel: measured 1.59-1.61 / 4.36-4.56 levels
            assert (diff.max(-1) > 0).mean() > 0.9 and diff.mean() > 0.5


def test_clean_depth_matches_truth(tiny_config):
    s = _with(tiny_config, depth_noise=False)
    r = s.render_frame(1)
    assert np.abs(r.depth_mm / 1000.0 - r.true_depth).max() <= 0.0005 + 1e-6


def test_the_rest_template_is_the_undeformed_shape_where_frame_0_holds_the_object(tiny_config):
    from stex.ingest import open_source

    src = dict(tiny_config["source"], synthetic=dict(tiny_config["source"]["synthetic"], template="rest"))
    rest = open_source(src).template()
    frame0 = open_source(tiny_config["source"]).template()
    assert np.array_equal(rest.faces, frame0.faces) and np.array_equal(rest.texcoords, frame0.texcoords)
    scene = SyntheticScene(tiny_config["source"]["synthetic"])
    R = scene.object_to_depth(0.0)
    undeformed = scene.body.vertices(None) @ R[:3, :3].T + R[:3, 3]
    np.testing.assert_allclose(rest.vertices, undeformed, atol=1e-9)
    assert np.linalg.norm(rest.vertices - frame0.vertices, axis=1).max() > 1e-3  # frame 0 is deformed


def test_tracking_drift_is_tangential_and_bounded(tiny_config):
    cfg = copy.deepcopy(tiny_config["source"]["synthetic"])
    cfg["degradations"]["tracking_drift"] = {"enabled": True, "amplitude_m": 0.01, "period_s": 1.0}
    s = SyntheticScene(cfg)
    from stex.render import vertex_normals
    for t in (0, 4):
        true, given = s.true_vertices(t), s.given_vertices(t)
        d = given - true
        norm = np.linalg.norm(d, axis=1)
        assert norm.max() == pytest.approx(0.01, rel=1e-6) and np.median(norm) > 0.002
        n = vertex_normals(true, s.faces)
        assert np.abs((d * n).sum(1)).max() < 1e-9
    cfg["degradations"]["tracking_drift"]["enabled"] = False
    s = SyntheticScene(cfg)
    assert np.array_equal(s.given_vertices(2), s.true_vertices(2))


def test_paper_scene_config_has_paper_scale():
    from conftest import REPO
    cfg = load_config(REPO / "config" / "config.yaml", REPO / "config" / "scenes" / "paper.yaml")
    syn = cfg["source"]["synthetic"]
    assert syn["n_frames"] == 265 and (syn["color"]["width"], syn["color"]["height"]) == (2048, 1536)
    assert (syn["depth"]["width"], syn["depth"]["height"]) == (640, 576)
    body = ProceduralBody(ProceduralParams(n_around=syn["procedural"]["n_around"], n_rings=syn["procedural"]["n_rings"]))
    assert 18_000 <= len(body.faces) <= 22_000


@pytest.mark.skipif(not (data_samples() / "gltf_fox").is_dir(), reason="shared data samples absent")
def test_fox_gltf_scene(tiny_config):
    cfg = copy.deepcopy(tiny_config["source"]["synthetic"])
    cfg["object"] = "gltf"
    cfg["gltf"] = {"path": str(data_samples() / "gltf_fox" / "glTF-Binary" / "Fox.glb"), "animation": "Walk", "size_m": 0.6}
    from pathlib import Path

    from stex.ingest import SyntheticSource
    src = SyntheticSource(cfg)
    s = src.scene
    # every ingest job reads the asset: it is their input (a replaced .glb re-runs them)
    assert src.files() == src.files(0, 2) == [Path(cfg["gltf"]["path"])]
    r0, r3 = s.render_frame(0), s.render_frame(3)
    assert r0.true_mask.sum() > 200
    extent = np.ptp(s.true_vertices(0), axis=0).max()
    assert 0.5 < extent < 0.7
    # Walking changes the shape, and with it the appearance.
    assert np.abs(s.true_vertices(3) - s.true_vertices(0)).max() > 0.01
    assert not np.array_equal(r0.appearance, r3.appearance)
    with pytest.raises(ValueError, match="available"):
        cfg["gltf"]["animation"] = "Dance"
        SyntheticScene(cfg)


def _scene(tiny_config, on=(), deg=None, **settings):
    """The tiny scene with only the degradations named in ``on`` enabled, ``deg`` updating
    degradation settings ({name: {key: value}}) and ``settings`` overriding source.synthetic
    keys (a dict value updates that sub-dict)."""
    cfg = copy.deepcopy(tiny_config["source"]["synthetic"])
    for name in ("motion_blur", "sensor_noise", "exposure_drift", "depth_noise", "tracking_drift"):
        cfg["degradations"][name]["enabled"] = name in on
    for name, values in (deg or {}).items():
        cfg["degradations"][name].update(values)
    for key, value in settings.items():
        if isinstance(value, dict):
            cfg[key].update(value)
        else:
            cfg[key] = value
    return SyntheticScene(cfg)


def test_calibration_follows_the_config_conventions(tiny_config):
    """Each camera's principal point is the image centre in stex's pixel convention (integer =
    pixel centre, so cx = (W - 1) / 2, cy = (H - 1) / 2) with fy = fx, and depth_to_color is
    the rotation of the x-y-z angles (x applied last: Rx @ Ry @ Rz, scipy's intrinsic 'XYZ')
    with the configured translation."""
    from scipy.spatial.transform import Rotation

    s = _scene(tiny_config, depth_to_color={"rotation_deg": [3.0, -5.0, 7.0],
                                            "translation_m": [-0.03, 0.01, 0.004]})
    cal = s.calibration
    np.testing.assert_allclose(cal.color.K, [[175.0, 0, 99.5], [0, 175.0, 74.5], [0, 0, 1]])  # 200 x 150
    np.testing.assert_allclose(cal.depth.K, [[79.0, 0, 49.5], [0, 79.0, 44.5], [0, 0, 1]])    # 100 x 90
    assert (cal.color.size, cal.depth.size) == ((200, 150), (100, 90))
    R = Rotation.from_euler("XYZ", [3.0, -5.0, 7.0], degrees=True).as_matrix()
    np.testing.assert_allclose(cal.depth_to_color[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(cal.depth_to_color[:3, 3], [-0.03, 0.01, 0.004])
    np.testing.assert_allclose(cal.depth_to_color[3], [0, 0, 0, 1])


def _object_pose(s, k, t):
    """Frame k's true vertices (camera) against the body's shape at time t (object frame), fitted
    by scipy's Rotation.align_vectors: (rotation (3, 3), the fit's rssd, camera points, object
    points)."""
    from scipy.spatial.transform import Rotation

    cam, obj = s.true_vertices(k), s.body.vertices(t)
    rot, rssd = Rotation.align_vectors(cam - cam.mean(0), obj - obj.mean(0))
    return rot.as_matrix(), rssd, cam, obj


def test_object_pose_follows_the_yaw_law_at_the_frame_times(tiny_config):
    """The true vertices of frame k are the body's shape at t = k / fps moved rigidly; the
    rigid motion (fitted with scipy's Rotation.align_vectors) turns the object about its own
    vertical axis by yaw(t) = offset + range * sin(2 pi t / period), right-handed about +y.

    By hand: at yaw 0 the object faces the camera upright (object +y -> image up = camera -y,
    object +z -> towards the camera = camera -z), so object +x = y x z maps to camera +x; the
    elevation tilt is about camera x. Turning by yaw about object +y takes object +z towards
    object +x, so the camera-x components of the object's +z and +x axes are sin(yaw) and
    cos(yaw): yaw = atan2(R[0, 2], R[0, 0]). The object's up axis has camera-y component
    -cos(elevation). The object sits distance_m in front of the camera (a sway of a few cm)."""
    s = _scene(tiny_config, fps=10.0, yaw_offset_deg=30.0, yaw_range_deg=50.0, yaw_period_s=2.0)
    assert s.render_frame(5).timestamp == pytest.approx(0.5)
    for k in range(6):
        t = k / 10.0
        R, rssd, cam, obj = _object_pose(s, k, t)
        assert rssd < 1e-6  # a rigid motion of the shape at time k / fps
        yaw = np.rad2deg(np.arctan2(R[0, 2], R[0, 0]))
        assert yaw == pytest.approx(30.0 + 50.0 * np.sin(2 * np.pi * t / 2.0), abs=1e-6)
        assert R[1, 1] == pytest.approx(-np.cos(np.deg2rad(20.0)), abs=1e-9)  # elevation 20 deg
        shift = cam.mean(0) - R @ obj.mean(0)
        assert np.abs(shift - [0, 0, 1.0]).max() < 0.035


def test_depth_noise_grows_with_z_squared_and_holes_and_edges_are_as_configured(tiny_config):
    """Kinect-like depth noise: sigma = sigma_1m * z^2, so on the wall (true depth 2.2 m) the
    error of depth_mm has std 1.5 mm * 2.2^2 = 7.26 mm (mm rounding adds 1/12 mm^2 of variance,
    negligible; ~8000 wall pixels give the std to ~1 %); the noise of two frames is drawn
    independently (correlation ~ 0 +- 0.012). Holes cover hole_fraction of the pixels; with
    edge_dropout = 1 exactly the pixels whose 3 x 3 neighbourhood of true depth spans more than
    5 cm are dropped (worked out here by brute force over the 9 shifts, borders repeated)."""
    dn = {"sigma_1m": 0.0015, "hole_fraction": 0.0, "edge_dropout": 0.0}
    s = _scene(tiny_config, ["depth_noise"], {"depth_noise": dn})
    errs, walls = [], []
    for k in (1, 2):
        r = s.render_frame(k)
        assert r.true_depth.dtype == np.float32 and (r.depth_mm > 0).all()
        walls.append(r.true_depth == np.float32(2.2))
        errs.append(r.depth_mm / 1000.0 - r.true_depth)
        assert walls[-1].sum() > 5000
        assert np.std(errs[-1][walls[-1]]) == pytest.approx(0.0015 * 2.2**2, rel=0.05)
    both = walls[0] & walls[1]
    assert abs(np.corrcoef(errs[0][both], errs[1][both])[0, 1]) < 0.06

    holes = _scene(tiny_config, ["depth_noise"], {"depth_noise": {**dn, "hole_fraction": 0.05}}).render_frame(1)
    assert (holes.depth_mm == 0).mean() == pytest.approx(0.05, abs=0.002)

    r = _scene(tiny_config, ["depth_noise"], {"depth_noise": {**dn, "edge_dropout": 1.0}}).render_frame(1)
    d = np.pad(r.true_depth.astype(np.float64), 1, mode="edge")
    H, W = r.true_depth.shape
    shifts = np.stack([d[i:i + H, j:j + W] for i in range(3) for j in range(3)])
    edge = shifts.max(0) - shifts.min(0) > 0.05
    assert edge.sum() > 100
    np.testing.assert_array_equal(r.depth_mm == 0, edge)


def test_colour_noise_has_the_configured_sigma_and_colours_are_rounded(tiny_config):
    """Sensor noise is Gaussian with std sigma grey levels: noisy - clean has std
    sqrt(sigma^2 + 2 / 12) (two independent roundings to uint8) = 2.04 for sigma = 2 and zero
    mean. Colours are rounded, not truncated: a wall of constant linear value 100.7 renders as
    101 wherever the object is not."""
    clean = _scene(tiny_config).render_frame(2)
    noisy = _scene(tiny_config, ["sensor_noise"], {"sensor_noise": {"sigma": 2.0}}).render_frame(2)
    diff = noisy.color.astype(float) - clean.color.astype(float)
    assert np.std(diff) == pytest.approx(np.sqrt(4 + 2 / 12), rel=0.03)
    assert abs(diff.mean()) < 0.05
    s = _scene(tiny_config)
    s._wall = np.full_like(s._wall, 100.7)  # the wall texture (float, 0..255) of this scene
    r = s.render_frame(2)
    assert (~r.true_mask).sum() > 10000
    assert (r.color[~r.true_mask] == 101).all()


def test_exposure_drift_is_a_per_channel_gain_within_the_amplitude(tiny_config):
    """Exposure/white-balance drift multiplies each colour channel by its own smooth gain
    1 + a * g_c(t), |g_c| <= 1: on the wall (values ~70-200, clipping negligible) the ratio of drifted
    to clean means stays within 1 +- a (+ rounding, < 0.005) and the three channels' gains
    differ (white balance), by much more than rounding at some frame."""
    a = 0.3
    clean = _scene(tiny_config, n_frames=60, fps=5.0)
    drift = _scene(tiny_config, ["exposure_drift"], {"exposure_drift": {"amplitude": a}}, n_frames=60, fps=5.0)
    spread = []
    for k in range(0, 60, 6):
        c, d = clean.render_frame(k), drift.render_frame(k)
        wall = ~c.true_mask
        gain = d.color[wall].astype(float).mean(0) / c.color[wall].astype(float).mean(0)
        assert (np.abs(gain - 1) <= a + 0.005).all(), (k, gain)
        spread.append(np.ptp(gain))
    assert max(spread) > 0.05


def test_motion_blur_averages_renders_centred_on_the_frame_time(tiny_config):
    """With 2 samples and an exposure of 2 frame intervals, the sub-frame renders fall at
    t -+ 1 / fps, i.e. exactly on frames k - 1 and k + 1: the blurred frame k is their mean
    up to the rounding of the three images to uint8 and the true texture (frame k's is used for
    both sub-frames, frames k -+ 1 have their own, a little different): mean error under 0.1
    grey level, 99.5 % of the errors at most 1.5."""
    sharp = _scene(tiny_config)
    blur = _scene(tiny_config, ["motion_blur"], {"motion_blur": {"samples": 2, "exposure": 2.0}}).render_frame(2)
    before, after = sharp.render_frame(1).color.astype(float), sharp.render_frame(3).color.astype(float)
    err = np.abs(blur.color - (before + after) / 2)
    assert err.mean() < 0.1 and np.percentile(err, 99.5) <= 1.5
    assert np.abs(before - after).mean() > 0.5  # the object moves: the check has teeth


def test_a_scenes_seed_fixes_its_texture_and_noise(tiny_config):
    """The seed is used: the same seed gives the same true appearance and the same noisy frame,
    another seed another appearance and another noise draw."""
    a, b = _scene(tiny_config, ["sensor_noise"], seed=0), _scene(tiny_config, ["sensor_noise"], seed=0)
    c = _scene(tiny_config, ["sensor_noise"], seed=1)
    np.testing.assert_array_equal(a.appearance(1), b.appearance(1))
    np.testing.assert_array_equal(a.render_frame(1).color, b.render_frame(1).color)
    assert np.abs(a.appearance(1).astype(int) - c.appearance(1)).mean() > 10
    assert not np.array_equal(a.render_frame(1).color, c.render_frame(1).color)


def test_tracking_drift_oscillates_with_its_period(tiny_config):
    """The drift field oscillates in time with period_s: half a period later it is reversed.
    Seen in the object frame (undoing the object's rigid motion, object_to_depth), the drift of
    frame 3 is about minus that of frame 0 for period_s = 6 frames (0.2 s at 30 fps): their
    correlation is near -1 (not exactly: the tangent planes of the two frames differ a little)."""
    s = _scene(tiny_config, ["tracking_drift"], {"tracking_drift": {"amplitude_m": 0.01, "period_s": 0.2}})
    d = []
    for k in (0, 3):
        R = s.object_to_depth(s.time_of(k))[:3, :3]
        d.append(((s.given_vertices(k) - s.true_vertices(k)) @ R).ravel())
    assert np.corrcoef(d[0], d[1])[0, 1] < -0.8


def test_frame_appearance_is_the_bodys_at_the_frame_time(tiny_config):
    """The true appearance of frame k is the body's at t = k / fps: at 30 fps, frame 45
    (1.5 s = a quarter of the 6 s bend period, maximum bend one way) has the red pose patch and
    frame 135 (4.5 s, the other way) the blue one (patch core at u ~ 0.02, v ~ 0.67)."""
    s = _scene(tiny_config, n_frames=136)
    c = (np.arange(128) + 0.5) / 128
    u, v = np.meshgrid(c, c)
    core = np.exp(-(((u - 0.02 + 0.5) % 1 - 0.5) ** 2 / 0.06**2 + (0.67 - v) ** 2 / 0.07**2)) > 0.6
    red, blue = s.appearance(45)[core].astype(float).mean(0), s.appearance(135)[core].astype(float).mean(0)
    assert red[0] > red[2] + 40 and blue[2] > blue[0] + 40


def _only(**motion):
    """A small procedural body with only the named deformations (amplitudes) switched on."""
    amps = {"bend": 0.0, "twist": 0.0, "squash": 0.0, "bulge": 0.0, **motion}
    return ProceduralBody(ProceduralParams(n_around=32, n_rings=16, **amps))


def test_procedural_deformations_match_their_closed_forms():
    """Each deformation alone, at its extreme (phases of ProceduralBody.state: twist peaks at
    2 pi t / 7 + 0.7 = pi / 2, squash at 2 pi t / 5 + 1.3 = pi / 2, bend at t = 6 / 4 s), against
    what it is by hand (height H = 0.5 m):

    - twist: a point at height h > 0.5 turns about the axis by twist * 2 (h - 0.5) (the top
      turns by the full twist against the rigid lower half);
    - squash: the top pole rises to H / 2 * (1 + squash), the bottom one stays at -H / 2, and
      above h = 0.65 the radius shrinks by 1 / sqrt(1 + squash) (volume preserving);
    - bend: the axis above the waist becomes an arc of radius 1 / kappa, kappa = bend / (H / 2),
      of the same length, so the top pole goes to ((1 - cos bend) / kappa, sin(bend) / kappa, 0);
      lengths along the axis shrink by 1 - kappa x (radial ones are kept), so a profile curve
      (dx, dy) on the concave side (x > 0, s = 0) is compressed by
      1 - |(dx, (1 - kappa x) dy)| / |(dx, dy)|, on the convex side not at all;
    - bulge: the belly (s = 0.75, h = 0.7) breathes outwards only, by between 0 and bulge times
      the local base radius radius * sqrt(sin(pi h)) * (1 + 0.2 sin(2 pi h + 0.5))."""
    H, R = 0.5, 0.15
    s = np.linspace(0, 1, 8, endpoint=False)
    h = np.array([0.6, 0.75, 0.9])[:, None] * np.ones_like(s)
    s = s * np.ones_like(h)

    body = _only(twist=0.35)
    t = (np.pi / 2 - 0.7) * 7 / (2 * np.pi)
    rest, moved = body.surface(s, h, None), body.surface(s, h, t)
    turn = np.arctan2(moved[..., 2], moved[..., 0]) - np.arctan2(rest[..., 2], rest[..., 0])
    np.testing.assert_allclose((turn + np.pi) % (2 * np.pi) - np.pi, 0.35 * 2 * (h - 0.5), atol=1e-9)
    np.testing.assert_allclose(moved[..., 1], rest[..., 1], atol=1e-12)

    body = _only(squash=0.06)
    t = (np.pi / 2 - 1.3) * 5 / (2 * np.pi)
    V = body.vertices(t)
    np.testing.assert_allclose(V[-1], [0, H / 2 * 1.06, 0], atol=1e-7)  # top pole (radius ~ sqrt(sin pi) ~ 1e-8)
    np.testing.assert_allclose(V[-2], [0, -H / 2, 0], atol=1e-7)         # bottom pole
    rest, moved = body.surface(s, h, None), body.surface(s, h, t)
    radius = lambda p: np.hypot(p[..., 0], p[..., 2])  # noqa: E731
    np.testing.assert_allclose(radius(moved[1:]) / radius(rest[1:]), 1 / np.sqrt(1.06), rtol=1e-9)

    bend = 0.5
    kappa = bend / (H / 2)
    body = _only(bend=bend)
    top = [(1 - np.cos(bend)) / kappa, np.sin(bend) / kappa, 0]
    np.testing.assert_allclose(body.vertices(1.5)[-1], top, atol=1e-7)
    # s = 0, h = 0.75: no lump, no nose, x = r = R * prof(h); the profile curve (dx, dy) =
    # (R prof'(h), H) dh keeps its radial part and has its axial part scaled by 1 - kappa x
    a = 0.75
    prof = np.sqrt(np.sin(np.pi * a)) * (1 + 0.2 * np.sin(2 * np.pi * a + 0.5))
    dprof = (np.pi * np.cos(np.pi * a) / (2 * np.sqrt(np.sin(np.pi * a))) * (1 + 0.2 * np.sin(2 * np.pi * a + 0.5))
             + np.sqrt(np.sin(np.pi * a)) * 0.4 * np.pi * np.cos(2 * np.pi * a + 0.5))
    x, dx = R * prof, R * dprof
    expected = 1 - np.hypot(dx, (1 - kappa * x) * H) / np.hypot(dx, H)
    comp = body.compression(np.array([0.0, 0.5]), np.array([a, a]), 1.5)
    assert comp[0] == pytest.approx(expected, rel=1e-3) and comp[0] > 0.15 and comp[1] == 0.0

    body = _only(bulge=0.15)
    base = R * np.sqrt(np.sin(0.7 * np.pi)) * (1 + 0.2 * np.sin(1.4 * np.pi + 0.5))
    r0 = radius(body.surface(0.75, 0.7, None))
    grow = np.array([radius(body.surface(0.75, 0.7, t)) - r0 for t in np.linspace(0, 4, 81)]) / base
    assert grow.min() >= -1e-12 and grow.min() < 0.01 and grow.max() == pytest.approx(0.15, rel=1e-3)


def test_procedural_texcoords_are_s_and_one_minus_h():
    """stex's UV convention (v down): every face corner's texcoord is (s, 1 - h) of its vertex,
    with s = 1 on the seam's second copy, so the top of the body is at the top of the texture."""
    body = ProceduralBody(ProceduralParams(n_around=32, n_rings=16))
    uv = body.texcoords[body.texcoord_faces]
    s, h = body.vertex_s[body.faces], body.vertex_h[body.faces]
    pole = (h == 0) | (h == 1)
    np.testing.assert_allclose(uv[..., 1], 1 - h, atol=1e-12)
    np.testing.assert_allclose(np.where(pole, 0, uv[..., 0] % 1), np.where(pole, 0, s), atol=1e-12)


FOX_GLB = data_samples() / "gltf_fox" / "glTF-Binary" / "Fox.glb"
needs_fox = pytest.mark.skipif(not FOX_GLB.is_file(), reason="shared data samples absent")


@pytest.fixture(scope="module")
def walking_fox():
    from stex.synth.skinned import SkinnedBody

    return SkinnedBody(FOX_GLB, animation="Walk", size_m=0.6, texture_size=128)


@needs_fox
def test_skinned_body_is_centred_scaled_and_loops(walking_fox):
    """The asset is centred on its bounding box and scaled so its largest extent is size_m; the
    posed body keeps that frame (its box centre moves only a few cm while walking in place);
    the animation loops: the shape and the true appearance at t + duration are those at t."""
    body = walking_fox
    lo, hi = body.rest_vertices.min(0), body.rest_vertices.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    assert np.ptp(body.rest_vertices, axis=0).max() == pytest.approx(0.6)
    d = body.duration
    for t in (0.1, 0.3):
        V = body.vertices(t)
        assert np.abs((V.min(0) + V.max(0)) / 2).max() < 0.05
        np.testing.assert_allclose(body.vertices(t + d), V, atol=1e-9)
        np.testing.assert_array_equal(body.appearance(t + d), body.appearance(t))


@needs_fox
def test_skinned_compression_is_the_mean_shortening_of_a_vertexs_edges(walking_fox, monkeypatch):
    """vertex_compression of a body squashed to half its height: each edge (u, v) of the
    triangles shortens by 1 - |(dx, dy / 2, dz)| / |(dx, dy, dz)|, and a vertex gets the mean over
    its edges (brute force over the faces' edges, each counted once)."""
    body = walking_fox
    rest = body.rest_vertices
    monkeypatch.setattr(body, "vertices", lambda t: rest * [1.0, 0.5, 1.0])
    edges = {tuple(sorted((int(f[i]), int(f[(i + 1) % 3])))) for f in body.faces for i in range(3)}
    total, count = np.zeros(len(rest)), np.zeros(len(rest))
    for a, b in edges:
        e = rest[a] - rest[b]
        shortening = 1 - np.linalg.norm(e * [1, 0.5, 1]) / np.linalg.norm(e)
        for v in (a, b):
            total[v] += shortening
            count[v] += 1
    np.testing.assert_allclose(body.vertex_compression(0.2), total / count, atol=1e-12)


@needs_fox
def test_skinned_pose_patch_sits_on_the_highest_vertex(walking_fox):
    """The pose patch is centred on the highest rest vertex and tinted red at pose +1
    (t = duration / 4: sin(2 pi t / duration) = 1) and blue at pose -1 (t = 3 duration / 4):
    the texels at the UV centroids of the faces around that vertex are red, then bluer than red
    (the Fox's own colour there is orange or white, red > blue: only the tint makes them blue)."""
    body = walking_fox
    top = np.argmax(body.rest_vertices[:, 1])
    around = np.flatnonzero((body.faces == top).any(1))
    uv = body.texcoords[body.texcoord_faces[around]].mean(1)
    px = np.clip((uv * body.size).astype(int), 0, body.size - 1)
    d = body.duration
    red = body.appearance(d / 4)[px[:, 1], px[:, 0]].astype(int)
    blue = body.appearance(3 * d / 4)[px[:, 1], px[:, 0]].astype(int)
    assert (red[:, 0] > red[:, 2] + 100).all() and (blue[:, 2] > blue[:, 0]).all()


def test_synthetic_ingest_stores_the_scene_as_rendered(tiny_config, tmp_path):
    """The tiny scene (6 frames) ingested in blocks of 4: the scene store holds the true and the
    given vertices of all 6 frames as SyntheticScene gives them (float32); the last, partial block
    [4, 6) holds frames 4 and 5 as render_frame draws them (colour, depth, timestamps) and its
    truth store their appearance, mask and true depth, value for value."""
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.io import open_store

    src = tiny_config["source"]
    write_scene(src, 4, tmp_path / "scene.zarr")
    write_frames_block(src, 4, 6, tmp_path / "f.zarr", tmp_path / "t.zarr")
    s = SyntheticScene(src["synthetic"])
    g = open_store(tmp_path / "scene.zarr", "scene")
    assert g.attrs["frame_ids"] == list(range(6)) and g.attrs["frame_blocks"] == [[0, 4], [4, 6]]
    np.testing.assert_array_equal(g["truth/vertices"][...], np.float32([s.true_vertices(t) for t in range(6)]))
    np.testing.assert_array_equal(g["given/vertices"][...], np.float32([s.given_vertices(t) for t in range(6)]))
    f, t = open_store(tmp_path / "f.zarr", "frames"), open_store(tmp_path / "t.zarr", "truth")
    assert f.attrs["frame_ids"] == t.attrs["frame_ids"] == [4, 5]
    r = [s.render_frame(i) for i in (4, 5)]
    for store, name, attr in ((f, "color", "color"), (f, "depth", "depth_mm"), (t, "appearance", "appearance"),
                              (t, "mask", "true_mask"), (t, "depth", "true_depth")):
        np.testing.assert_array_equal(store[name][...], np.stack([getattr(x, attr) for x in r]), err_msg=name)
    np.testing.assert_array_equal(f["timestamps"][...], [r[0].timestamp, r[1].timestamp])


def test_camera_looks_at_the_object_from_above(tiny_config):
    """elevation_deg tilts the view so the camera looks down at the object (schema: "Camera
    elevation above the object; the underside is never seen"). By hand, for a camera pitched
    down by e: the object's up axis (+y) is image-up (camera -y) and leans towards the
    camera (the viewing direction points down), so in camera coordinates it is
    (0, -cos e, -sin e), and the bottom cap (the faces around the bottom pole) is not visible
    in any frame."""
    s = _scene(tiny_config, elevation_deg=20.0)
    e = np.deg2rad(20.0)
    K, (W, H) = s.calibration.depth.K, s.calibration.depth.size
    bottom = np.isin(s.faces, np.flatnonzero(s.body.vertex_h == 0)).any(1)  # the fan around the bottom pole
    assert bottom.sum() == 32
    for k in range(s.n_frames):
        R, _, cam, _ = _object_pose(s, k, s.time_of(k))
        np.testing.assert_allclose(R[:, 1], [0, -np.cos(e), -np.sin(e)], atol=1e-9)
        vis, _ = face_visibility(cam, s.faces, K, rasterize(cam, s.faces, K, W, H).depth)
        assert not vis[bottom].any()
    # a negative elevation looks up from below (the schema: -20 is the view of the figures
    # measured before the fix): the up axis leans away from the camera
    below = _scene(tiny_config, elevation_deg=-20.0)
    R = _object_pose(below, 0, below.time_of(0))[0]
    np.testing.assert_allclose(R[:, 1], [0, -np.cos(e), np.sin(e)], atol=1e-9)
