"""The tracking-quality signal (stex.tracking_quality), its use by the data term, and frames
without data (issue 55)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import TINY_SYNTHETIC
from stex.camera import mask_in_depth
from stex.config import load_config
from stex.data_term import lost_sources
from stex.flow import AppearanceModel, flow_image
from stex.render import rasterize
from stex.synth.scene import SyntheticScene
from stex.synth.shapes import bumpy_sphere
from stex.tracking import Observation, TrackParams, depth_target, track_sequence
from stex.tracking_quality import THRESHOLDS, QualityMonitor, frame_quality, judge, template_area_ratio

K = np.array([[200.0, 0, 119.5], [0, 200.0, 89.5], [0, 0, 1]])


@pytest.fixture(scope="module")
def tiny():
    """The tiny synthetic scene's frames 0 and 3 (true meshes, observations) and an appearance
    model captured at the true mesh of frame 0."""
    syn = {**TINY_SYNTHETIC, "procedural": {"n_around": 48, "n_rings": 24}, "texture_size": 256,
           "color": {"width": 320, "height": 240, "fx": 280.0}, "depth": {"width": 160, "height": 144, "fx": 126.0}}
    s = SyntheticScene(load_config(overrides={"source": {"synthetic": syn}})["source"]["synthetic"])
    cal = s.calibration
    out = {"faces": s.faces.astype(np.int64), "cal": cal, "scene": s}
    for t in (0, 3):
        r = s.render_frame(t)
        fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
        out[t] = (s.true_vertices(t), depth_target(r.depth_mm / 1000.0, cal.depth.K, fg),
                  flow_image(r.color), r.true_mask)
    model = AppearanceModel(s.body.texcoords, s.body.texcoord_faces, s.faces, 512, 3)
    model.capture(out[0][0], out[0][2], cal, 0.3, 0)
    out["model"] = model
    return out


def _quality(tiny, V, t=3):
    _, target, image, mask = tiny[t]
    return frame_quality(V, tiny["faces"], target, mask, tiny["cal"], tiny["model"], image, tiny[0][2])


def test_the_signal_passes_a_true_track_and_flags_a_wrong_one(tiny):
    """At frame 3, the true mesh is ok (hardly a vertex marked); the same mesh turned 15 degrees
    about the body's own axis, so that it slides along its surface and still fits the depth, is
    lost, and so is the true mesh moved 4 cm sideways (off the depth and the mask)."""
    V = tiny[3][0]
    good = _quality(tiny, V)
    assert not good["lost"] and good["share"] < 0.1 and not good["no_data"]
    assert good["depth_m"].shape == (len(V),) and np.isfinite(good["depth_mean_m"])   # per vertex, and the mean
    assert np.nanmedian(good["flow_px"]) < 1.0
    axis = tiny["scene"].object_to_depth(tiny["scene"].time_of(3))[:3, 1]
    c = V.mean(0)
    slid = (V - c) @ Rotation.from_rotvec(np.deg2rad(15) * axis).as_matrix().T + c
    bad = _quality(tiny, slid)
    assert bad["lost"] and "appearance" in bad["why"]
    assert bad["vertex_lost"][bad["seen"]].mean() > 3 * good["vertex_lost"][good["seen"]].mean()
    moved = _quality(tiny, V + [0.04, 0.0, 0.0])
    assert moved["lost"] and moved["share"] > 0.25


def test_outside_the_mask_is_one_sided(tiny):
    """A mask that holds more than the object (the frame's mask grown by 15 px, as one that also
    holds an arm) leaves the true mesh ok: the silhouette counts mesh outside the mask only."""
    import cv2
    V, target, image, mask = tiny[3]
    loose = cv2.dilate(mask.astype(np.uint8), np.ones((31, 31), np.uint8)) > 0
    q = frame_quality(V, tiny["faces"], target, loose, tiny["cal"])
    assert not q["lost"] and np.nanmax(q["outside_px"]) == 0.0


def test_lost_frames_and_faces_are_no_source():
    """lost_sources: a lost frame excludes every face, a lost vertex the faces around it at that
    frame only."""
    F = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 2]])
    frame_lost = np.array([False, True, False])
    vertex_lost = np.zeros((3, 5), bool)
    vertex_lost[2, 4] = True
    out = lost_sources(frame_lost, vertex_lost, F)
    assert out.tolist() == [[False] * 3, [True] * 3, [False, False, True]]


def test_write_data_term_takes_no_source_from_lost_frames(tmp_path):
    """The data-term stage: with frame 11 judged lost and vertex 0 lost at frame 12, frame 11 is
    nobody's candidate, face 0 (which holds vertex 0) has no candidate from 12, face 1 keeps it;
    with data_term.exclude_lost false they are candidates again. `stex inspect` counts the lost frame."""
    from test_data_term import _stores
    from stex.io import create_store, open_store
    from stex.stages.data_term import write_data_term
    T = 4
    paths = _stores(tmp_path, np.zeros((T, 2)), np.zeros((T, 2), bool), np.ones((T, 2), bool))
    V = np.asarray(open_store(paths[2], "tracking")["vertices"][...])   # the given meshes, with a judgement
    vertex_lost = np.zeros((T, 4), bool)
    vertex_lost[2, 1] = True          # vertex 1 is in face 0 only
    paths[2] = tmp_path / "tracking_judged.zarr"
    with create_store(paths[2], "tracking", attrs={"frame_ids": list(range(10, 10 + T)), "mode": "given",
                                                   "lost_frames": [11]}) as s:
        s.write("vertices", V)
        for name in ("residual_m", "n_correspondences", "seconds", "silhouette_iou", "depth_fit_m", "lost_share"):
            s.write(name, np.zeros(T))
        s.write("lost", np.array([False, True, False, False]))
        s.write("no_data", np.zeros(T, bool))
        s.write("vertex_lost", vertex_lost)
    from stex.cli import inspect_store
    assert "lost frames (tracking quality; no texture taken from them): 1 of 4: frames 11 (1)" in inspect_store(
        str(paths[2]))
    cands = {}
    for exclude in (True, False):
        out = tmp_path / f"dt_{exclude}.zarr"
        write_data_term(*paths, [0, T], {"similarity": "global", "candidates": 4, "prefilter": 4,
                                         "omega_str": 0.0, "exclude_lost": exclude}, out)
        store = open_store(out, "data_term")
        cands[exclude] = store["candidates"][0]
        assert (11 in store.attrs["source_frames"]) is not exclude
    assert sorted(cands[True][0][cands[True][0] >= 0].tolist()) == [0, 3]
    assert sorted(cands[True][1][cands[True][1] >= 0].tolist()) == [0, 2, 3]
    assert sorted(cands[False][0].tolist()) == [0, 1, 2, 3]


def _sphere_frames():
    V, F = bumpy_sphere(subdivisions=3, radius=0.3, distance=1.2)
    c = V.mean(0)
    step = Rotation.from_euler("y", 2, degrees=True).as_matrix()
    frames = [(V - c) @ np.linalg.matrix_power(step, k).T + c + [0.004 * k, 0, 0] for k in range(3)]
    targets = [depth_target(rasterize(X, F, K, 240, 180).depth.astype(np.float64), K) for X in frames]
    return V, F.astype(np.int64), frames, targets


@pytest.mark.parametrize("settings", [{}, {"volume_links": 0}, {"rigid_only": True}, {"association": "closest"},
                                      {"unseen_from_rest": False, "constant_velocity": True}])
def test_a_frame_without_data_keeps_the_rigid_solution_and_is_flagged(settings):
    """Frame 1 has no depth at all (between two good ones): the tracker does not crash, keeps
    frame 1 at its rigid solution (here: where frame 0 left it, nothing moves it; to 10 µm), flags it
    (no correspondences, judged lost for no data) and tracks frame 2 again, for every setting."""
    V, F, frames, targets = _sphere_frames()
    empty = depth_target(np.zeros((180, 240)), K)
    obs = [Observation(targets[0]), Observation(empty), Observation(targets[2])]
    out = list(track_sequence(V, F, obs, TrackParams(w_flow=0.0, **settings), progress=False))
    (_, V0, s0), (_, V1, s1), (_, V2, s2) = out
    assert s1["n_corr"] == 0 and s1["quality"]["no_data"] and s1["quality"]["lost"]
    assert np.isfinite(V1).all() and np.abs(V1 - V0).max() < 1e-5   # the rest fit re-poses the hidden side by round-off
    assert not s0["quality"]["lost"] and not s2["quality"]["lost"]
    assert np.linalg.norm(V2 - frames[2], axis=1).mean() < 0.003


def test_the_first_frames_reference_sees_a_slide_the_drifting_model_follows(tiny):
    """A mesh slid 8 degrees about the body's axis at frame 3, judged against a tracker model that
    was captured at that slid mesh (a model that drifted with it): the tracker's own flow sees about
    nothing, the reference captured by the monitor at the true frame 0 sees the slide and the frame
    is lost for it; the true mesh at frame 3 (its model captured there) stays ok."""
    s, F, cal = tiny["scene"], tiny["faces"], tiny["cal"]
    V0, target0, image0, mask0 = tiny[0]
    V3, target3, image3, mask3 = tiny[3]
    axis = s.object_to_depth(s.time_of(3))[:3, 1]
    c = V3.mean(0)
    slid = (V3 - c) @ Rotation.from_rotvec(np.deg2rad(8) * axis).as_matrix().T + c
    results = {}
    for name, V in (("true", V3), ("slid", slid)):
        drifted = AppearanceModel(s.body.texcoords, s.body.texcoord_faces, F, 512, 3)  # it follows the mesh
        drifted.capture(V, image3, cal, 0.3, 0)
        mon = QualityMonitor(F, s.body.texcoords, s.body.texcoord_faces, TrackParams(model_size=512))
        first = mon.frame(0, V0, Observation(target0, None, cal, mask0), image=image0)
        assert not first["lost"] and mon.reference is not None
        results[name] = mon.frame(1, V, Observation(target3, None, cal, mask3), drifted, image3)
    slid_q, true_q = results["slid"], results["true"]
    assert np.nanmedian(slid_q["flow_px"]) < 0.5                 # the drifted model sits on the image
    assert slid_q["lost"] and "first frames" in slid_q["why"]
    assert slid_q["ref_flow_m"] > 3 * true_q["ref_flow_m"]
    assert not true_q["lost"]


def _signals(n=100, depth=0.002, ref_px=0.0):
    """Signals of a frame whose n vertices are all seen, at ``depth`` (m) off, 1 mm a pixel."""
    return {"seen": np.ones(n, bool), "depth_m": np.full(n, depth, np.float32), "outside_px": np.zeros(n, np.float32),
            "flow_px": np.full(n, np.nan, np.float32), "flow_fail": np.zeros(n, bool),
            "m_per_px": np.full(n, 0.001, np.float32), "ref_flow_px": np.full(n, ref_px, np.float32),
            "ref_fail": np.zeros(n, bool)}


def test_a_lost_track_stays_lost_until_reacquired():
    """judge's memory: a frame just under the reference-flow bound is ok after an ok frame and
    lost after a lost one; a clean frame after a lost one is ok again (re-acquired)."""
    px = 1000 * (THRESHOLDS.reacquire_flow_m + THRESHOLDS.frame_ref_flow_m) / 2   # between the two bounds
    marginal = _signals(ref_px=px)
    assert not judge(marginal, THRESHOLDS, was_lost=False)[1]
    lost, why = judge(marginal, THRESHOLDS, was_lost=True)[1:]
    assert lost and "re-acquired" in why["why"]
    assert not judge(_signals(), THRESHOLDS, was_lost=True)[1]
    assert judge(_signals(ref_px=2000 * THRESHOLDS.frame_ref_flow_m), THRESHOLDS)[1]


def test_a_template_too_large_for_the_object_is_lost_from_the_first_frame(tiny):
    """The scale cue: the true mesh of frame 0 covers about its foreground depth (a little more:
    the grazing pixels have no depth), the same mesh grown 20 % about its centre covers clearly
    more, over the threshold, and the monitor then judges every frame lost, naming the template."""
    V, target, _, _ = tiny[0]
    F = tiny["faces"]
    right = template_area_ratio(V, F, target)
    c = V.mean(0)
    grown = (V - c) * 1.2 + c
    big = template_area_ratio(grown, F, target)
    assert 0.9 < right < THRESHOLDS.template_area_ratio < big
    assert big > 1.3 * right
    monitor = QualityMonitor(F, rest=grown)
    for pos, t in enumerate((0, 3)):
        Vt, target_t, _, mask = tiny[t]
        q = monitor.frame(pos, Vt, Observation(target_t, None, tiny["cal"], mask))
        assert q["lost"] and "too large" in q["why"]
    assert np.isnan(template_area_ratio(np.full_like(V, np.nan), F, target))


def test_the_scale_cue_holds_at_a_small_depth_image_and_over_depth_holes(tiny):
    """A right template stays under the scale cue's bound where the depth image is small (its
    edge band, without normals, is a large share of the object) and where the depth has holes
    inside the object that the template covers (a template from depth fills them): the cue counts
    the pixels with depth only, edges included."""
    small = SyntheticScene(load_config(overrides={"source": {"synthetic": TINY_SYNTHETIC}})["source"]["synthetic"])
    r = small.render_frame(0)
    target = depth_target(r.depth_mm / 1000.0, small.calibration.depth.K,
                          mask_in_depth(r.true_mask, r.depth_mm, small.calibration))
    assert target.valid.sum() < 0.8 * target.foreground.sum()      # the edge band matters here
    assert template_area_ratio(small.true_vertices(0), small.faces, target) < THRESHOLDS.template_area_ratio
    V, target, _, _ = tiny[0]
    F = tiny["faces"]
    rows = np.nonzero(target.foreground)[0]
    hole = np.zeros_like(target.valid)
    hole[rows.min():(rows.min() + rows.max()) // 2] = True          # the object's upper half: no depth
    holed = replace(target, valid=target.valid & ~hole, measured=target.measured & ~hole,
                    foreground=target.foreground & ~hole)
    assert holed.foreground.sum() < 0.7 * target.foreground.sum()
    right = template_area_ratio(V, F, holed)
    assert abs(right - template_area_ratio(V, F, target)) < 0.05
    assert right < THRESHOLDS.template_area_ratio
