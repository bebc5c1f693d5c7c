"""Embedded-deformation tracking with the L0 regulariser."""
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import data_samples, real_pair_fits
from stex.render import face_normals, rasterize, vertex_visibility
from stex.synth.shapes import bumpy_sphere
from stex.template import template_from_depth
from stex.frame_fit import depth_residual
from stex.tracking import (Observation, TrackParams, _solve_frame, depth_target, fit_rest_warp, lm_step,
    track_sequence)
from stex.deformation import block_jacobi, build_graph, compose_rigid, deform, identity_params, rigid_fit

K = np.array([[200.0, 0, 119.5], [0, 200.0, 89.5], [0, 0, 1]])


def _scene_observations(s, n_frames=None):
    """Observations of a synthetic scene's first frames (all by default): depth inside the true
    mask, colour image, calibration and true mask, as the tracking stage builds them."""
    from stex.camera import mask_in_depth
    cal = s.calibration
    for t in range(s.n_frames if n_frames is None else n_frames):
        r = s.render_frame(t)
        fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
        yield Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg), r.color, cal, r.true_mask)


def _sphere():
    V, F = bumpy_sphere(subdivisions=3, radius=0.3, distance=1.2)
    return V, F


def test_graph_covers_and_binds():
    V, F = _sphere()
    g = build_graph(V, F, 0.08)
    assert 10 < len(g.nodes) < len(V)
    assert np.allclose(g.vertex_weights.sum(1), 1)
    # every vertex is within the spacing of some node (Euclidean is a lower bound of geodesic)
    d = np.linalg.norm(V[:, None] - V[g.nodes][None], axis=2).min(1)
    assert d.max() <= 0.08 + 1e-9
    assert (g.edges[:, 0] < g.edges[:, 1]).all() and len(np.unique(g.edges, axis=0)) == len(g.edges)


def test_deform_identity_and_rigid():
    V, F = _sphere()
    g = build_graph(V, F, 0.08)
    nodes = V[g.nodes]
    assert np.allclose(deform(V, nodes, g, identity_params(len(nodes))), V)
    R = Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix()
    t = np.array([0.01, -0.02, 0.03])
    # x' = A (v - g) + g + t_j with A = R, t_j = R g + t - g gives R v + t for every node
    x = np.zeros((len(nodes), 12))
    x[:, :9] = R.ravel()
    x[:, 9:] = nodes @ R.T + t - nodes
    assert np.allclose(deform(V, nodes, g, x), V @ R.T + t)


def _target(V, F):
    d = rasterize(V, F, K, 240, 180).depth.astype(np.float64)
    return depth_target(d, K)


def test_one_frame_recovers_a_small_rigid_motion():
    V, F = _sphere()
    R = Rotation.from_euler("xyz", [2, -3, 1], degrees=True).as_matrix()
    c = V.mean(0)
    V1 = (V - c) @ R.T + c + np.array([0.01, 0.005, -0.01])
    g = build_graph(V, F, 0.08)
    x, stats = _solve_frame(V, F.astype(np.int64), V[g.nodes], g, _target(V1, F), TrackParams(gn_iterations=8),
                            identity_params(len(g.nodes)))
    err = np.linalg.norm(deform(V, V[g.nodes], g, x) - V1, axis=1)
    vis = face_normals(V1, F)  # noqa: F841  (the visible half is what the data constrains)
    assert stats["n_corr"] > 100
    assert np.median(err) < 0.002 and err.mean() < 0.004


def test_depth_target_rejects_nan():
    d = np.ones((10, 10))
    d[3, 4] = np.nan
    with pytest.raises(ValueError, match="row 3, column 4"):
        depth_target(d, K)


def test_template_from_depth_faces_the_camera():
    V, F = _sphere()
    d = rasterize(V, F, K, 240, 180).depth.astype(np.float64)
    TV, TF = template_from_depth(d, K, stride=2)
    n = face_normals(TV, TF)
    assert ((n * TV[TF].mean(1)).sum(1) < 0).all()  # normals point back towards the camera
    with pytest.raises(ValueError, match="no valid depth"):
        template_from_depth(np.zeros((20, 20)), K)


def test_tracking_follows_a_deforming_synthetic_scene(tiny_config):
    """A short run on a tiny synthetic scene (low resolution): the tracked mesh stays on the
    truth; the full-resolution figures are in benchmarks/bench_tracking.py."""

    from stex.synth.scene import SyntheticScene
    cfg = tiny_config["source"]["synthetic"]
    s = SyntheticScene(cfg)
    cal = s.calibration

    def obs():
        return _scene_observations(s)

    errors = []
    for pos, V, st in track_sequence(s.true_vertices(0), s.faces, obs(), TrackParams(), progress=False,
                                     texcoords=s.texcoords, texcoord_faces=s.texcoord_faces):
        Vt = s.true_vertices(pos)
        d = rasterize(Vt, s.faces, cal.depth.K, *cal.depth.size).depth
        vis, _ = vertex_visibility(Vt, s.faces, cal.depth.K, d)
        e = np.linalg.norm(V - Vt, axis=1)
        errors.append((e[vis].mean(), e.mean()))
    errors = np.array(errors)
    moved = np.linalg.norm(s.true_vertices(s.n_frames - 1) - s.true_vertices(0), axis=1).mean()
    assert moved > 0.02  # the object really moves
    assert errors[:, 0].max() < 0.006 and errors[:, 1].max() < 0.012, errors


REAL = data_samples()


@pytest.mark.skipif(not (REAL / "killingfusion_snoopy").is_dir(), reason="shared data samples absent")
def test_real_pairs_fit_better_than_rigid():
    """A template from the first frame's depth tracks to the second with a lower depth residual
    than the rigid-only fit, and the rigid fit no higher than the template left where it was
    (benchmarks/bench_tracking_real.py prints the figures)."""
    for name, before, rigid, tracked in real_pair_fits(REAL):
        assert tracked < rigid <= before + 1e-4, (name, before, rigid, tracked)


def test_volume_links_run_through_the_solid_only():
    """Two closed balls side by side: links cross each ball's inside but never the air between
    the balls; an open mesh (a hemisphere) gets none."""
    import trimesh

    from stex.deformation import build_graph
    a = trimesh.creation.icosphere(3, radius=0.1)
    b = a.copy()
    b.apply_translation([0.23, 0, 0])
    both = trimesh.util.concatenate([a, b])
    V, F = np.asarray(both.vertices), np.asarray(both.faces)
    plain = build_graph(V, F, 0.03)
    g = build_graph(V, F, 0.03, volume_links=16, volume_range=8.0)
    P = V[g.nodes]
    side = P[:, 0] > 0.115
    extra = {tuple(e) for e in g.edges.tolist()} - {tuple(e) for e in plain.edges.tolist()}
    assert len(extra) > 20
    extra = np.array(sorted(extra))
    assert not np.any(side[extra[:, 0]] != side[extra[:, 1]])          # none across the gap
    mid = 0.5 * (P[extra[:, 0]] + P[extra[:, 1]])
    centre = np.where(side[extra[:, 0]], 0.23, 0.0)[:, None] * np.array([[1.0, 0, 0]])
    assert np.all(np.linalg.norm(mid - centre, axis=1) < 0.1)           # midpoints inside a ball
    # the Euclidean neighbours across the gap exist: they were refused, not out of range
    from scipy.spatial import cKDTree
    d, idx = cKDTree(P).query(P, k=17)
    assert np.any((side[idx[:, 1:]] != side[:, None]) & (d[:, 1:] <= 8 * 0.03))
    keep = a.vertices[:, 2] > 0.0
    hemi = a.submesh([np.flatnonzero(keep[a.faces].all(1))], append=True)
    open_plain = build_graph(np.asarray(hemi.vertices), np.asarray(hemi.faces), 0.03)
    open_vol = build_graph(np.asarray(hemi.vertices), np.asarray(hemi.faces), 0.03, volume_links=16)
    np.testing.assert_array_equal(open_plain.edges, open_vol.edges)


def test_track_params_defaults_match_the_schema():
    from dataclasses import asdict

    from stex.config import section_params
    from stex.articulated import ArticulatedParams
    schema = section_params("tracking")
    fields = asdict(TrackParams())
    # mode, min_silhouette_iou and skeleton (on/off) are the stage's; skeleton_* the skeleton solver's
    stage = ("mode", "min_silhouette_iou", "skeleton")
    assert {k: v for k, v in schema.items() if k not in stage and not k.startswith("skeleton_")} == fields
    skeleton = {k.removeprefix("skeleton_"): tuple(v) if isinstance(v, list) else v
                for k, v in schema.items() if k.startswith("skeleton_")}
    assert skeleton == asdict(ArticulatedParams())


def test_flow_on_the_object_box_matches_the_whole_image(tiny_config):
    """Cropping the flow to the object's box changes the targets by a fraction of a pixel."""
    import cv2

    from stex.synth.scene import SyntheticScene
    from stex.flow import AppearanceModel, flow_constraints
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    r0, r1 = s.render_frame(0), s.render_frame(1)
    g0, g1 = (cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY) for r in (r0, r1))
    V0 = s.true_vertices(0)
    model = AppearanceModel(s.texcoords, s.texcoord_faces, s.faces, 256)
    assert model.capture(V0, g0, cal, 0.3)[0] > 0
    ids_a, ua = flow_constraints(V0, s.faces, model, g1, r1.true_mask, cal, prev_image=g0, crop_margin_px=16)
    ids_b, ub = flow_constraints(V0, s.faces, model, g1, r1.true_mask, cal, prev_image=g0, crop_margin_px=10**6)
    common, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
    assert len(common) > 0.8 * max(len(ids_a), len(ids_b)) > 20
    assert np.abs(ua[ia] - ub[ib]).mean() < 0.15


def test_chroma_flow_follows_the_surface_under_shading_stripes(tiny_config):
    """Stripes of shading (the frame darkened by up to 60 % in rows, as the demo's wrinkles do)
    move the grey channel by tens of grey levels and its flow targets off the surface; the two
    chromaticity channels of :func:`flow_image` barely change, and their targets stay put."""
    from stex.camera import project_points, transform_points
    from stex.synth.scene import SyntheticScene
    from stex.flow import AppearanceModel, flow_constraints, flow_image
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    r0 = s.render_frame(0)
    V0 = s.true_vertices(0)
    rows = np.arange(r0.color.shape[0])[:, None, None]
    striped = (r0.color * (1 - 0.6 * (0.5 + 0.5 * np.cos(2 * np.pi * rows / 9.0)))).round().astype(np.uint8)
    assert flow_image(r0.color).shape == (*r0.color.shape[:2], 3) and flow_image(r0.color).dtype == np.uint8
    before, after = flow_image(r0.color).astype(float), flow_image(striped).astype(float)
    change = np.abs(after - before)[r0.true_mask].mean(0)     # grey levels, per channel
    assert change[0] > 20 and (change[1:] < 0.1 * change[0]).all(), change
    uv = project_points(transform_points(cal.depth_to_color, V0), cal.color.K)[0]
    median_px, kept = [], []
    for ch in range(3):
        model = AppearanceModel(s.texcoords, s.texcoord_faces, s.faces, 256)
        model.capture(V0, flow_image(r0.color)[..., ch], cal, 0.3)
        same = flow_constraints(V0, s.faces, model, flow_image(r0.color)[..., ch], r0.true_mask, cal)[0]
        ids, u1 = flow_constraints(V0, s.faces, model, flow_image(striped)[..., ch], r0.true_mask, cal)
        median_px.append(np.median(np.linalg.norm(u1 - uv[ids], axis=1)))
        kept.append(len(ids) / len(same))
    assert median_px[0] > 0.2 and kept[0] < 0.9, (median_px, kept)      # grey: off, and fewer pass
    assert max(median_px[1:]) < 0.1 and min(kept[1:]) > 0.95, (median_px, kept)


def test_flow_image_channels_and_bad_input():
    from stex.flow import flow_image
    rgb = np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    assert flow_image(rgb, "grey").shape == (6, 8, 1)
    assert flow_image(rgb, "chroma").shape == (6, 8, 2)
    np.testing.assert_array_equal(flow_image(rgb)[..., 1:], flow_image(rgb, "chroma"))
    assert flow_image(rgb[..., 0]).shape == (6, 8, 1)              # a grey frame: its one channel
    grey = np.full((6, 8, 3), 90, np.uint8)                         # no colour: chroma at its zero
    assert (flow_image(grey, "chroma") == 128).all()
    with pytest.raises(ValueError, match="flow channels"):
        flow_image(rgb, "hue")
    with pytest.raises(ValueError, match=r"\(6, 8, 4\)"):
        flow_image(np.zeros((6, 8, 4), np.uint8))


def test_appearance_model_recaptures_texels_seen_more_squarely(tiny_config):
    """A texel first seen at a slant is captured again once seen much more squarely (and only
    then); the others keep their first capture."""
    import cv2

    from stex.synth.scene import SyntheticScene
    from stex.flow import AppearanceModel
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    gray = cv2.cvtColor(s.render_frame(0).color, cv2.COLOR_RGB2GRAY)
    V0 = s.true_vertices(0)
    c = V0.mean(axis=0)
    a = np.deg2rad(50.0)                                         # turned about the vertical axis
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    turned = (V0 - c) @ R.T + c
    models = {m: AppearanceModel(s.texcoords, s.texcoord_faces, s.faces, 256) for m in (None, 0.3)}
    for margin, model in models.items():
        added, refreshed = model.capture(turned, gray, cal, 0.3, frame=0, refresh_margin=margin)
        assert added > 0 and refreshed == 0
    first = {m: (model.texture.copy(), model.captured_cos.copy()) for m, model in models.items()}
    never = models[None].capture(V0, gray, cal, 0.3, frame=1, refresh_margin=None)
    added, refreshed = models[0.3].capture(V0, gray, cal, 0.3, frame=1, refresh_margin=0.3)
    assert never[1] == 0 and added == never[0] and refreshed > 50
    old_tex = first[None][0]
    filled_before = old_tex[..., 1].ravel() > 0
    # without a margin, every texel filled at frame 0 keeps its value, cosine and frame
    assert np.array_equal(models[None].texture.reshape(-1, 2)[filled_before], old_tex.reshape(-1, 2)[filled_before])
    assert (models[None].captured_at[filled_before] == 0).all()
    # with one, exactly the texels seen 0.3 more squarely moved to frame 1, with their new cosine
    m = models[0.3]
    again = filled_before & (m.captured_at == 1)
    assert again.sum() == refreshed
    assert (m.captured_cos[again] > first[0.3][1][again] + 0.3).all()
    kept = filled_before & ~again
    assert np.array_equal(m.texture.reshape(-1, 2)[kept], first[0.3][0].reshape(-1, 2)[kept])


def test_silhouette_field_signs_and_gradient():
    from stex.tracking import silhouette_field
    m = np.zeros((40, 60), bool)
    m[10:30, 20:45] = True
    sdf, grad = silhouette_field(m)
    assert (sdf[m] < 0).all() and (sdf[~m] > 0).all()
    assert sdf[20, 5] == pytest.approx(14.5) and sdf[20, 30] == pytest.approx(-9.5)
    assert grad[20, 5, 0] == pytest.approx(-1.0) and grad[20, 50, 0] == pytest.approx(1.0)  # points outwards
    with pytest.raises(ValueError, match="empty"):
        silhouette_field(np.zeros((5, 5), bool))


def test_silhouette_term_pulls_a_shifted_mesh_onto_the_mask():
    """Without depth data, the silhouette term alone moves a mesh shifted sideways back onto
    the mask it is given; with w_silhouette 0 nothing moves."""
    from stex.tracking import silhouette_field
    V, F = _sphere()
    F = F.astype(np.int64)
    mask = rasterize(V, F, K, 240, 180).depth > 0
    field = silhouette_field(mask)
    shifted = V + np.array([0.012, -0.006, 0.0])
    empty = depth_target(np.zeros((180, 240)), K)
    g = build_graph(shifted, F, 0.08)
    out = {}
    for w in (0.0, 1.0):
        x, st = _solve_frame(shifted, F, shifted[g.nodes], g, empty,
                             TrackParams(w_silhouette=w, l0_rounds=2, gn_iterations=8), identity_params(len(g.nodes)),
                             silhouette=(*field, K, np.eye(4)))
        out[w] = deform(shifted, shifted[g.nodes], g, x)
    assert np.allclose(out[0.0], shifted)
    before = np.abs((shifted - V).mean(0)[:2])
    after = np.abs((out[1.0] - V).mean(0)[:2])
    assert (after < 0.3 * before).all(), (before, after)


def test_normal_equations_match_the_jacobian_by_finite_differences():
    """The 12x12 node-pair blocks assembled per vertex equal J^T J and J^T r of the stacked
    residuals (data rows D . x'_i, rotation A^T A - I, graph smoothness), J by central differences."""
    from stex.deformation import NormalPattern, normal_equations, rotation_terms
    V, F = _sphere()
    g = build_graph(V, F, 0.12)
    nodes = V[g.nodes]
    N = len(nodes)
    rng = np.random.default_rng(3)
    x0 = identity_params(N) + rng.normal(0, 0.05, (N, 12))
    vid = rng.integers(0, len(V), 400)
    Dw = rng.normal(0, 1, (400, 3))
    c = rng.normal(0, 0.01, 400)
    s = rng.normal(0, 0.01, (len(g.edges), 3))
    w_rot, w_smooth = 2.0, 3.0
    j_, k_ = g.edges[:, 0], g.edges[:, 1]
    d_jk = nodes[k_] - nodes[j_]

    def residuals(xf):
        x = xf.reshape(N, 12)
        data = (Dw * deform(V, nodes, g, x)[vid]).sum(1) - c
        rot, _ = rotation_terms(x)
        A, t = x[:, :9].reshape(N, 3, 3), x[:, 9:]
        r_jk = np.einsum("eab,eb->ea", A[j_], d_jk) + nodes[j_] + t[j_] - nodes[k_] - t[k_]
        return np.concatenate([data, np.sqrt(w_rot) * rot.ravel(), np.sqrt(w_smooth) * (r_jk - s).ravel()])

    r0 = residuals(x0.ravel())
    eps = 1e-6
    J = np.stack([(residuals(x0.ravel() + eps * e) - residuals(x0.ravel() - eps * e)) / (2 * eps)
                  for e in np.eye(12 * N)], axis=1)
    rot, Jr = rotation_terms(x0)
    A, t = x0[:, :9].reshape(N, 3, 3), x0[:, 9:]
    r_jk = np.einsum("eab,eb->ea", A[j_], d_jk) + nodes[j_] + t[j_] - nodes[k_] - t[k_]
    local = V[:, None, :] - nodes[g.vertex_nodes]
    JtJ, grad, diag = normal_equations(NormalPattern(g, N), g, local, vid.astype(np.int64), Dw, r0[:400],
                                        rot * np.sqrt(w_rot), Jr * np.sqrt(w_rot), r_jk - s, w_smooth, d_jk,
                                        damping=0.5)
    ref = J.T @ J + 0.5 * np.eye(12 * N)
    assert np.abs(JtJ.toarray() - ref).max() < 1e-6 * np.abs(ref).max()
    assert np.allclose(grad, J.T @ r0, rtol=1e-6, atol=1e-9 * np.abs(J.T @ r0).max())
    assert np.allclose(diag, np.stack([ref[12 * n:12 * n + 12, 12 * n:12 * n + 12] for n in range(N)]))


def test_step_guard_keeps_a_thin_limb_on_its_depth():
    """A leg-like cylinder (2 cm radius) moved sideways by half its radius: nodes strung along
    its axis are free to turn about it to first order (the rotation term is flat there), and the
    undamped Gauss-Newton steps twist them (measured without the guard: 6.8 mm mean, 9.3 mm max
    error); with steps accepted only when they lower the energy the solve lands on the truth."""
    import trimesh

    m = trimesh.creation.cylinder(radius=0.02, height=0.4, sections=16).subdivide().subdivide()
    V = m.vertices @ Rotation.from_euler("y", 90, degrees=True).as_matrix().T + [0.0, 0.0, 0.8]
    F = np.asarray(m.faces, np.int64)
    V1 = V + [0.0, 0.01, 0.0]
    g = build_graph(V, F, 0.05, volume_links=20)
    x, stats = _solve_frame(V, F, V[g.nodes], g, _target(V1, F), TrackParams(), identity_params(len(g.nodes)))
    err = np.linalg.norm(deform(V, V[g.nodes], g, x) - V1, axis=1)
    assert stats["lm_rejected"] >= 1 and stats["lm_failed"] == 0   # the guard did trigger
    assert err.max() < 0.002, (err.mean(), err.max())


def test_frame_guard_drops_a_solve_that_fits_the_depth_worse(tiny_config, monkeypatch):
    """A non-rigid solve that flings the mesh 0.3 m (stand-in for one that walked off with its
    own correspondences) explains the depth frame worse than the rigid fit: the frame keeps the
    rigid fit, says so in its stats, and stays on the truth."""

    import stex.tracking as tracking
    from stex.synth.scene import SyntheticScene
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    solve = tracking._solve_frame

    def flinging_solve(V0, faces, node_pos, graph, *args, **kwargs):
        x, stats = solve(V0, faces, node_pos, graph, *args, **kwargs)
        if len(node_pos) > 1:   # the non-rigid stage only
            x = x.copy()
            x[:, 9:] += [0.3, 0.0, 0.0]
        return x, stats

    monkeypatch.setattr(tracking, "_solve_frame", flinging_solve)

    def obs():
        return _scene_observations(s, 3)

    for pos, V, st in track_sequence(s.true_vertices(0), s.faces, obs(), TrackParams(), progress=False,
                                     texcoords=s.texcoords, texcoord_faces=s.texcoord_faces):
        assert st["frame_fallback"] == 1
        assert np.linalg.norm(V - s.true_vertices(pos), axis=1).mean() < 0.02


def test_silhouette_crop_matches_the_whole_image_field():
    """The field over the mask's box (with K's principal point moved) samples like the field over
    the whole image wherever a vertex can count (|distance| below SILHOUETTE_MAX_PX)."""
    from stex.camera import project_points
    from stex.render import sample_bilinear
    from stex.tracking import SILHOUETTE_MAX_PX, silhouette_crop, silhouette_field
    V, F = _sphere()
    mask = rasterize(V, F, K, 240, 180).depth > 0
    full, _ = silhouette_field(mask)
    crop, _, Kc = silhouette_crop(mask, K, margin_px=24)
    assert crop.shape[0] < mask.shape[0] and crop.shape[1] < mask.shape[1]
    pts = V + np.random.default_rng(1).normal(0, 0.02, V.shape)
    a = sample_bilinear(full, project_points(pts, K)[0])
    b = sample_bilinear(crop, project_points(pts, Kc)[0])
    near = np.abs(a) < SILHOUETTE_MAX_PX
    assert near.sum() > 100 and np.allclose(a[near], b[near], atol=1e-4)


def test_link_weights_enter_the_normal_equations_per_link():
    """A per-link smoothness weight (TrackParams.link_length_power) scales exactly that link's
    part of J^T J and J^T r: weight 0 on some links equals a graph without them."""
    from stex.deformation import DeformationGraph, NormalPattern, normal_equations

    V, F = _sphere()
    g = build_graph(V, F, 0.08)
    rng = np.random.default_rng(0)
    N, E = len(g.nodes), len(g.edges)
    nodes = V[g.nodes]
    d_jk = nodes[g.edges[:, 1]] - nodes[g.edges[:, 0]]
    local = V[:, None, :] - nodes[g.vertex_nodes]
    res = rng.normal(size=(E, 3))
    rot_res, rot_jac = np.zeros((N, 6)), np.zeros((N, 6, 9))
    none = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))

    def normal(graph, r, w, d):
        JtJ, grad, _ = normal_equations(NormalPattern(graph, N), graph, local, *none, rot_res, rot_jac, r, w, d)
        return JtJ.toarray(), grad

    keep = rng.random(E) < 0.5
    sub = DeformationGraph(g.nodes, g.vertex_nodes, g.vertex_weights, g.edges[keep])
    A, a = normal(g, res, np.where(keep, 2.5, 0.0), d_jk)
    B, b = normal(sub, res[keep], 2.5, d_jk[keep])
    assert np.allclose(A, B) and np.allclose(a, b)
    C, c = normal(g, res, np.full(E, 2.5), d_jk)   # a uniform vector weight is the scalar one
    D, dd = normal(g, res, 2.5, d_jk)
    assert np.allclose(C, D) and np.allclose(c, dd) and not np.allclose(A, C)


def test_silhouette_iou_of_a_mesh_and_its_own_mask(tiny_config):
    from stex.camera import transform_points
    from stex.synth.scene import SyntheticScene
    from stex.frame_fit import silhouette_iou

    scene = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = scene.calibration
    V = scene.true_vertices(0)
    c = cal.color
    own = rasterize(transform_points(cal.depth_to_color, V), scene.faces, c.K, c.width, c.height).depth > 0
    assert silhouette_iou(V, scene.faces, own, cal) == pytest.approx(1.0)
    shifted = silhouette_iou(V + [0.02, 0.0, 0.0], scene.faces, own, cal)
    assert 0.3 < shifted < 0.95
    assert shifted < silhouette_iou(V + [0.005, 0.0, 0.0], scene.faces, own, cal)
    with pytest.raises(ValueError, match="colour camera"):
        silhouette_iou(V, scene.faces, own[:-1], cal)


def test_tracking_stage_names_frames_the_mesh_does_not_cover(tmp_path, caplog):
    """Given meshes that fit (the tiny scene's truth) pass; the same meshes moved 5 cm aside at
    two frames are named in a warning and in poorly_fitted_frames, and judged lost (lost_frames),
    without any ground truth; at
    every frame, or with the colour camera's focal length off by 15 %, the stage refuses them."""
    import shutil

    import zarr

    from conftest import run_stages, tiny_scene_config
    from stex.io import open_store
    from stex.stages.tracking import write_tracking

    cfg = tiny_scene_config(template={"atlas_size": 128})
    P = run_stages(cfg, tmp_path)
    good = open_store(P["tracking"], "tracking")
    assert good.attrs["poorly_fitted_frames"] == []
    assert (good["silhouette_iou"][...] > 0.9).all()
    assert good.attrs["lost_frames"] == [] and not good["lost"][...].any()   # the quality signal agrees
    ids = open_store(P["scene"], "scene").attrs["frame_ids"]
    params = dict(cfg["tracking"], mode="given")

    def with_scene(name, edit):
        path = tmp_path / f"{name}_scene.zarr"
        shutil.copytree(P["scene"], path)
        edit(zarr.open_group(str(path), mode="r+"))
        return path

    def move(frames):
        def edit(z):
            v = z["given/vertices"][...]
            v[frames] += np.array([0.05, 0.0, 0.0], np.float32)
            z["given/vertices"][...] = v
        return edit

    with caplog.at_level("WARNING", logger="stex.tracking"):
        write_tracking(with_scene("two", move([2, 3])), P["template"], P["frames"], P["masks"], params,
                       tmp_path / "two_tracking.zarr")
    bad = open_store(tmp_path / "two_tracking.zarr", "tracking")
    assert bad.attrs["poorly_fitted_frames"] == [ids[2], ids[3]]
    iou, fit = bad["silhouette_iou"][...], bad["depth_fit_m"][...]
    assert (iou[[2, 3]] < 0.85).all() and (iou[[0, 1, 4, 5]] == good["silhouette_iou"][...][[0, 1, 4, 5]]).all()
    assert (fit[[2, 3]] > good["depth_fit_m"][...][[2, 3]]).all()
    assert f"frames: {ids[2]}-{ids[3]}" in caplog.text and "lost part of the object" in caplog.text
    assert bad.attrs["lost_frames"] == [ids[2], ids[3]] and bad["vertex_lost"][2].any()
    assert not bad["vertex_lost"][0].any() and f"lost 2 of {len(ids)} frames" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="stex.tracking"):  # poor from the first frame: not a loss
        write_tracking(with_scene("first", move([0, 1])), P["template"], P["frames"], P["masks"], params,
                       tmp_path / "first_tracking.zarr")
    assert "already at the first frame" in caplog.text and "lost part" not in caplog.text
    with pytest.raises(ValueError, match="every frame.*depth-camera coordinates"):
        write_tracking(with_scene("all", move(slice(None))), P["template"], P["frames"], P["masks"], params,
                       tmp_path / "all_tracking.zarr")
    assert not (tmp_path / "all_tracking.zarr").exists()

    def wrong_focal(z):
        cal = dict(z.attrs["calibration"])
        cal["color"] = dict(cal["color"], fx=cal["color"]["fx"] * 1.15, fy=cal["color"]["fy"] * 1.15)
        z.attrs["calibration"] = cal
    with pytest.raises(ValueError, match="every frame"):
        write_tracking(with_scene("focal", wrong_focal), P["template"], P["frames"], P["masks"], params,
                       tmp_path / "focal_tracking.zarr")


def test_a_lost_tracked_mesh_is_told_what_to_try():
    """The warning for a mesh that loses the object points a tracked run at the settings that can
    help (links through the solid hold back parts that turn against each other: docs/tracking.md),
    only where they apply: not to given meshes, not when the links are already off or the template
    is open (it gets none), and not when the mesh misses the object from the first frame (nothing
    was lost)."""
    import trimesh

    from stex.stages.tracking import _lost_mesh_hint

    closed = trimesh.creation.icosphere(2, radius=0.2)
    V, F = closed.vertices, closed.faces
    track = {"mode": "track", "volume_links": 20}
    hint = _lost_mesh_hint(False, track, V, F)
    assert "try tracking.volume_links: 0 (now 20" in hint and "tracking.mode: given" in hint
    assert _lost_mesh_hint(True, track, V, F) == ""
    assert _lost_mesh_hint(False, track, V, F[1:]) == ""   # an open template has no such links
    assert _lost_mesh_hint(False, {"mode": "track", "volume_links": 0}, V, F) == ""
    assert _lost_mesh_hint(False, {"mode": "given", "volume_links": 20}, V, F) == ""


def test_tracking_stage_refuses_a_mesh_in_millimetres_and_names_frames_without_depth(tmp_path, caplog):
    """A template (track) or given meshes (given) in millimetres project like metres, so the
    silhouette cannot tell; the depth can, and the stage refuses them at the first frame. A frame
    whose depth is all invalid is named in a warning: there the mesh has nothing to fit."""
    import shutil

    import zarr

    from conftest import run_stages, tiny_scene_config
    from stex.io import FrameSequence, open_store
    from stex.stages.tracking import write_tracking

    cfg = tiny_scene_config(template={"atlas_size": 128})
    P = run_stages(cfg, tmp_path)
    ids = open_store(P["scene"], "scene").attrs["frame_ids"]

    def copy_edit(path, name, key, edit):
        out = tmp_path / name
        shutil.copytree(path, out)
        z = zarr.open_group(str(out), mode="r+")
        z[key][...] = edit(z[key][...])
        # zarr drops a chunk rewritten as zeros: the edited copy no longer has the chunk files it
        # was written with, which a reader would take for a partial copy
        z.attrs["chunk_files"] = {}
        return out

    in_mm = copy_edit(P["template"], "mm_template.zarr", "vertices", lambda v: v * 1000)
    with pytest.raises(ValueError, match=r"mm_template\.zarr: at frame .* (9\d\d|1\d\d\d) times as far .* metres"):
        write_tracking(P["scene"], in_mm, P["frames"], P["masks"], dict(cfg["tracking"], mode="track"),
                       tmp_path / "mm_tracking.zarr")
    assert not (tmp_path / "mm_tracking.zarr").exists()
    given_mm = copy_edit(P["scene"], "mm_scene.zarr", "given/vertices", lambda v: v * 1000)
    with pytest.raises(ValueError, match=r"mm_scene\.zarr: at frame .* (9\d\d|1\d\d\d) times as far"):
        write_tracking(given_mm, P["template"], P["frames"], P["masks"], dict(cfg["tracking"], mode="given"),
                       tmp_path / "mm_given.zarr")

    blocks = [Path(p) for p in P["frames"]]
    dropped = [copy_edit(b, f"f{i}.zarr", "depth", (lambda d: np.concatenate([d[:1], 0 * d[1:2], d[2:]]))
                         if i == 0 else (lambda d: d)) for i, b in enumerate(blocks)]
    assert FrameSequence(dropped, "frames").read("depth", 1).max() == 0
    with caplog.at_level("WARNING", logger="stex.tracking"):
        write_tracking(P["scene"], P["template"], dropped, P["masks"], dict(cfg["tracking"], mode="given"),
                       tmp_path / "dropped.zarr")
    assert f"no depth of the object to fit at 1 of {len(ids)} frames ({ids[1]})" in caplog.text


def _path_mesh(n, h=0.01, offset=0.0):
    """n collinear vertices h apart along x (at z = 1), joined by degenerate triangles (i, i+1, i+2):
    the edges are h and 2h long, so the geodesic distance between vertices i and j is |i - j| h."""
    V = np.zeros((n, 3))
    V[:, 0] = offset + h * np.arange(n)
    V[:, 2] = 1.0
    return V, np.array([[i, i + 1, i + 2] for i in range(n - 2)])


def test_graph_sampling_binding_and_links_worked_by_hand():
    """On a path (geodesic distance |i - j| h, h = 1 cm) the greedy covering, the binding weights
    (1 - d/d_max)^2 with d_max the (k+1)-th nearest node's distance, normalised, and the links
    (nearest nodes within 2.5 spacings, never across to another piece) all follow by hand."""
    V, F = _path_mesh(10)
    g = build_graph(V, F, 0.025, k=2)
    # a vertex within 2.5 cm of a node is covered: nodes at 0, 3, 6, 9 (3 cm apart, not 2)
    np.testing.assert_array_equal(g.nodes, [0, 3, 6, 9])
    # vertex 1: nodes 0, 3, 6 at 1, 2, 5 cm -> (1 - 1/5)^2 = 0.64, (1 - 2/5)^2 = 0.36 (sum 1)
    np.testing.assert_array_equal(g.vertex_nodes[1], [0, 1])
    np.testing.assert_allclose(g.vertex_weights[1], [0.64, 0.36])
    # vertex 4: nodes 3, 6, 0 at 1, 2, 4 cm -> 9/16 and 1/4, normalised
    np.testing.assert_array_equal(g.vertex_nodes[4], [1, 2])
    np.testing.assert_allclose(g.vertex_weights[4], np.array([9 / 16, 1 / 4]) / (9 / 16 + 1 / 4))
    # the same path twice, 1 m apart: links within 6.25 cm (3 and 6 cm), none between the pieces
    V2, F2 = _path_mesh(10, offset=1.0)
    two = build_graph(np.concatenate([V, V2]), np.concatenate([F, F2 + 10]), 0.025, k=2)
    np.testing.assert_array_equal(two.nodes, [0, 3, 6, 9, 10, 13, 16, 19])
    one = [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    assert two.edges.tolist() == one + [[a + 4, b + 4] for a, b in one]
    # k = 1, nodes 2 cm apart: vertex 1 lies midway, (1 - d/d_max)^2 = 0 for both: it is bound
    # wholly to a nearest node instead of to nothing (0/0)
    g1 = build_graph(V, F, 0.015, k=1)
    np.testing.assert_array_equal(g1.nodes, [0, 2, 4, 6, 8])
    assert g1.vertex_weights[1, 0] == 1.0
    assert np.linalg.norm(V[g1.nodes[g1.vertex_nodes[1, 0]]] - V[1]) == pytest.approx(0.01)


def test_depth_target_drops_depth_edges_and_background():
    """Pixels whose neighbours jump by more than max_jump_m (3 cm) and pixels outside the
    foreground get no point; a 1 cm step keeps them. A flat depth's normal faces the camera."""
    Ks = np.array([[200.0, 0, 14.5], [0, 200.0, 9.5], [0, 0, 1]])
    d = np.ones((20, 30))
    d[:, 15:] = 1.05
    t = depth_target(d, Ks)
    inner = np.zeros((20, 30), bool)
    inner[1:-1, 1:-1] = True          # central differences need both neighbours
    edge = inner.copy()
    edge[:, 14:16] = False            # the columns whose left/right neighbours straddle the 5 cm step
    np.testing.assert_array_equal(t.valid, edge)
    np.testing.assert_allclose(t.normals[5, 5], [0, 0, -1])
    d[:, 15:] = 1.01
    np.testing.assert_array_equal(depth_target(d, Ks).valid, inner)
    fg = np.zeros((20, 30), bool)
    fg[:, :10] = True
    t = depth_target(d, Ks, fg)
    np.testing.assert_array_equal(t.valid, inner & fg)
    assert (t.points[~fg] == 0).all()


def _grid_mesh(n=11, size=0.2, z=1.0):
    """A square grid of n x n vertices at depth z, facing the camera (normals (0, 0, -1))."""
    u = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(u, u)
    V = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None]).ravel()
    F = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return V, F


def test_correspondences_need_a_near_point_and_an_agreeing_normal():
    """Projective association of a plane facing the camera with a parallel depth plane: every
    vertex pairs 2 cm away, none 10 cm away (max_distance 5 cm), and none where the depth
    normals are flipped or tilted 70 degrees (cos 0.34 below min_normal_dot 0.5)."""
    from stex.tracking import DepthTarget, _correspondences
    V, F = _grid_mesh()
    p = TrackParams()
    near = depth_target(np.full((180, 240), 1.02), K)
    ids, q, nq, vis, _ = _correspondences(V, F, near, p, 0.05)
    assert vis.all() and len(ids) == len(V)
    np.testing.assert_allclose(q[:, 2], 1.02)
    assert len(_correspondences(V, F, depth_target(np.full((180, 240), 1.1), K), p, 0.05)[0]) == 0
    a = np.deg2rad(70)
    for n in ([0.0, 0.0, 1.0], [np.sin(a), 0.0, -np.cos(a)]):
        bad = DepthTarget(near.points, np.where(near.valid[..., None], np.array(n), 0.0), near.valid, K)
        assert len(_correspondences(V, F, bad, p, 0.05)[0]) == 0


def test_data_rows_huber_and_the_fixed_pixel_scale_by_hand():
    """Point-to-plane residuals 2 cm and -3 mm with the Huber threshold 5 mm: the outlier costs
    2 delta |r| - delta^2 and its row is scaled by sqrt(delta / |r|) = 0.5, the inlier costs r^2.
    The silhouette residual is the signed distance in pixels times the metres per pixel given
    for the solve (px_scale), not the vertex's current z / fx."""
    from stex.tracking import data_rows
    Vd = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [0.05, 0.0, 1.5]])
    n = np.array([[0.0, 0.0, -1.0]] * 2)
    q = np.array([[0.0, 0.0, 1.02], [0.01, 0.0, 0.997]])
    cost, vids, Dws, rws = data_rows(Vd, TrackParams(), depth=(np.array([0, 1]), q, n))
    assert cost == pytest.approx((2 * 0.005 * 0.02 - 0.005**2) + 0.003**2, rel=1e-12)
    np.testing.assert_allclose(rws[0], [0.02 * 0.5, -0.003], rtol=1e-12)
    np.testing.assert_allclose(Dws[0], [[0, 0, -0.5], [0, 0, -1.0]], rtol=1e-12)
    # signed distance u - 120 px; vertex 2 projects to u = 200 * 0.05 / 1.5 + 119.5
    sdf = np.arange(240, dtype=np.float32)[None].repeat(180, 0) - 120
    grad = np.stack([np.ones_like(sdf), np.zeros_like(sdf)], -1)
    r = (200 * 0.05 / 1.5 + 119.5 - 120) * 0.005       # px_scale 5 mm/px (z = 1), not 7.5 (z = 1.5)
    cost, *_ = data_rows(Vd, TrackParams(w_silhouette=2.0), silhouette=(np.array([2]), sdf, grad, K, np.eye(4)),
                          px_scale=np.full(3, 0.005))
    assert cost == pytest.approx(2.0 * (2 * 0.005 * r - 0.005**2), rel=1e-6)


def test_data_rows_gradient_matches_finite_differences():
    """For every data-like term (point-to-plane, point-to-point, flow, silhouette) the rows and
    weighted residuals give the cost's gradient: 2 sum rw Dw = d cost / d x', by central
    differences (a linear signed-distance field, so that its sampled gradient is exact)."""
    from stex.tracking import data_rows
    rng = np.random.default_rng(0)
    V = np.array([0, 0, 1.0]) + rng.normal(0, 0.05, (6, 3))
    ids = np.arange(6)
    nq = rng.normal(size=(6, 3))
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    Tdc = np.eye(4)
    Tdc[:3, :3] = Rotation.from_euler("xyz", [3, -5, 2], degrees=True).as_matrix()
    Tdc[:3, 3] = [-0.05, 0.01, 0.02]
    yy, xx = np.mgrid[0:180, 0:240].astype(np.float32)
    sdf = 0.6 * (xx - 120) + 0.8 * (yy - 90)
    grad = np.stack([np.full_like(sdf, 0.6), np.full_like(sdf, 0.8)], -1)
    p = TrackParams(w_point=0.3, w_flow=0.7, w_silhouette=2.0)
    args = dict(depth=(ids, V + rng.normal(0, 0.01, (6, 3)), nq),
                flow=(ids, rng.normal([120, 90], 8, (6, 2)), K, Tdc, np.linspace(0.5, 1.5, 6)),
                silhouette=(ids, sdf, grad, K, Tdc), px_scale=np.full(6, 0.004))
    _, vids, Dws, rws = data_rows(V, p, **args)
    G = np.zeros((6, 3))
    for i, D, r in zip(vids, Dws, rws):
        np.add.at(G, i, 2 * r[:, None] * D)
    eps = 1e-4
    FD = np.zeros((6, 3))
    for v in range(6):
        for a in range(3):
            Vp, Vm = V.copy(), V.copy()
            Vp[v, a] += eps
            Vm[v, a] -= eps
            FD[v, a] = (data_rows(Vp, p, rows=False, **args)[0] - data_rows(Vm, p, rows=False, **args)[0]) / (2 * eps)
    assert np.abs(G - FD).max() < 1e-4 * np.abs(FD).max()


def test_silhouette_rim_takes_rim_vertices_and_visible_ones_outside_the_mask():
    """Vertices on pixel row 89.5 of a rectangular mask (boundary at u = 179.5): 5.5 px outside
    (facing the camera): taken; 9.5 px inside: only if on the rim (cos below silhouette_rim_cos);
    30.5 px outside (beyond SILHOUETTE_MAX_PX), unseen, or behind the camera: not taken."""
    from stex.tracking import _silhouette_rim, silhouette_field
    mask = np.zeros((180, 240), bool)
    mask[30:150, 60:180] = True
    sdf, grad = silhouette_field(mask)
    u = np.array([185.0, 170.0, 170.0, 210.0, 170.0, 170.0])
    V = np.stack([(u - 119.5) / 200, np.zeros(6), np.ones(6)], 1)
    V[5] *= -1                                          # behind the camera
    vis = np.array([True, True, True, True, False, True])
    cos = np.array([1.0, 1.0, 0.01, 1.0, 0.01, 0.01])
    ids = _silhouette_rim(V, vis, cos, (sdf, grad, K, np.eye(4)), TrackParams())
    np.testing.assert_array_equal(ids, [0, 2])


def test_l0_step_keeps_exactly_the_links_whose_weighted_difference_pays():
    """The s-step alone (no Gauss-Newton steps): s_jk = r_jk where w_jk |r_jk|^2 > lambda / beta,
    with w_jk = w_reg max(1, length / spacing)^link_length_power and beta growing per round.
    Links 10 cm (w = 2^1.5) and 2.5 cm (w = 1) long, both |r| = 1 cm; lambda 4e-4, beta 2 then 8:
    round 1 keeps the long link only (2.83e-4 > 2e-4 > 1e-4), round 2 both (> 5e-5)."""
    from stex.deformation import DeformationGraph
    V = np.array([[0.0, 0, 1], [0.1, 0, 1], [0.025, 0, 1]])
    g = DeformationGraph(np.arange(3, dtype=np.int32), np.arange(3, dtype=np.int32)[:, None], np.ones((3, 1)),
                         np.array([[0, 1], [0, 2]], np.int32))
    x = identity_params(3)
    x[1, 9:] = [0.01, 0, 0]
    x[2, 9:] = [0, 0.01, 0]
    empty = depth_target(np.zeros((180, 240)), K)
    active = []
    for rounds in (1, 2):
        p = TrackParams(gn_iterations=0, l0_rounds=rounds, l0_lambda=4e-4, l0_beta0=2.0, l0_beta_growth=4.0)
        out, st = _solve_frame(V, np.array([[0, 1, 2]]), V, g, empty, p, x)
        np.testing.assert_array_equal(out, x)
        active.append(st["l0_active"])
    assert active == [1, 2]


def test_solve_reaches_the_least_squares_minimum_of_its_energy():
    """A dome (5 mm high) pressed onto a flat depth plane, every residual within the Huber
    threshold: the Gauss-Newton solve ends at the minimum of sum (n . (x'_i - q_i))^2 + w_rot
    ||A^T A - I||^2 + beta w_jk ||r_jk||^2 (w_jk = w_reg max(1, |g_k - g_j| / spacing)^1.5,
    beta = l0_beta0 in the first round, s = 0), found independently with scipy's least_squares.
    (On a flat target the residual is 1 - z'_i whichever pixel a vertex pairs with.)"""
    from scipy.optimize import least_squares

    from stex.deformation import rotation_terms
    n = 9
    u = np.linspace(-0.12, 0.12, n)
    X, Y = np.meshgrid(u, u)
    V = np.stack([X.ravel(), Y.ravel(), (1.0 - 0.005 * (1 - (X**2 + Y**2) / 0.12**2 / 2)).ravel()], 1)
    _, F = _grid_mesh(n)
    g = build_graph(V, F, 0.08)
    N, nodes = len(g.nodes), V[g.nodes]
    p = TrackParams(l0_rounds=1, gn_iterations=10, l0_beta0=5.0, w_rot=0.01)
    x, st = _solve_frame(V, F, nodes, g, depth_target(np.full((180, 240), 1.0), K), p, identity_params(N))
    assert st["n_corr"] == len(V)
    j_, k_ = g.edges.T
    d_jk = nodes[k_] - nodes[j_]
    w = p.w_reg * np.maximum(1.0, np.linalg.norm(d_jk, axis=1) / p.node_spacing_m) ** 1.5

    def residuals(xf):
        x = xf.reshape(N, 12)
        A, t = x[:, :9].reshape(N, 3, 3), x[:, 9:]
        r_jk = np.einsum("eab,eb->ea", A[j_], d_jk) + nodes[j_] + t[j_] - nodes[k_] - t[k_]
        return np.concatenate([1.0 - deform(V, nodes, g, x)[:, 2], np.sqrt(p.w_rot) * rotation_terms(x)[0].ravel(),
                               (np.sqrt(p.l0_beta0 * w)[:, None] * r_jk).ravel()])

    def energy(x):
        return float((residuals(np.ravel(x)) ** 2).sum())

    ref = least_squares(residuals, identity_params(N).ravel(), method="lm")
    assert energy(identity_params(N)) > 3 * energy(ref.x)             # the solve has work to do
    assert energy(x) <= energy(ref.x) * (1 + 1e-4), (energy(x), energy(ref.x))


def test_depth_residual_clips_and_counts_the_union_by_hand():
    """A mesh 2 cm in front of the observed depth on the pixels both cover: mean 2 cm; 20 cm in
    front: clipped at 5 cm; as many observed pixels again that the mesh misses count 5 cm each
    with union (so (2 + 5) / 2 cm), and not without."""
    from stex.tracking import DepthTarget
    V, F = _grid_mesh(size=0.3)
    d = rasterize(V, F, K, 240, 180).depth.astype(np.float64)
    cover = d > 0
    assert cover.sum() > 1000 and not cover[:, :60].any()

    def target(offset, extra=False):
        valid = cover.copy()
        if extra:  # as many pixels again, in columns the mesh does not reach
            rows, cols = np.nonzero(cover)
            valid[rows, cols - cols.min()] = True
        pts = np.zeros((180, 240, 3))
        pts[..., 2] = np.where(valid, 1.0 + offset, 0.0)
        return DepthTarget(pts, np.zeros_like(pts), valid, K)

    assert depth_residual(V, F, target(0.02)) == pytest.approx(0.02, abs=1e-6)
    assert depth_residual(V, F, target(0.2)) == pytest.approx(0.05)
    assert depth_residual(V, F, target(0.02, extra=True)) == pytest.approx(0.035, abs=1e-6)
    assert depth_residual(V, F, target(0.02, extra=True), union=False) == pytest.approx(0.02, abs=1e-6)


def test_depth_scale_check_refuses_a_mesh_twice_as_far():
    """Scaling a mesh about the camera centre keeps its silhouette and scales its depth: the
    ratio is the scale, and the check refuses 2 (outside 1/1.5 .. 1.5) but passes 1.3 and 1/1.3."""
    from stex.stages.tracking import _check_depth_scale
    from stex.frame_fit import depth_scale_ratio
    V, F = _sphere()
    t = _target(V, F)
    assert depth_scale_ratio(2.0 * V, F, t) == pytest.approx(2.0, rel=1e-3)
    for s in (1.3, 1 / 1.3):
        _check_depth_scale(s * V, F, t, 0, "t.zarr")
    with pytest.raises(ValueError, match="2.00 times as far"):
        _check_depth_scale(2.0 * V, F, t, 0, "t.zarr")


def test_rigid_stage_catches_a_motion_beyond_the_non_rigid_radius():
    """The rigid stage associates within twice max_distance_m (5 cm): a sphere 7 cm farther
    than the template is caught (each vertex's depth pixel is about 7 cm away along its ray)."""
    V, F = _sphere()
    V1 = V + [0.0, 0.0, 0.07]
    (_, out, st), = track_sequence(V, F, [Observation(_target(V1, F))], TrackParams(rigid_only=True, w_flow=0.0),
                                   progress=False)
    assert st["n_corr"] > 50 and st["frame_fallback"] == 0
    assert np.linalg.norm(out - V1, axis=1).max() < 0.002
    # the non-rigid solve alone pairs within max_distance_m only: nothing to pull on, nothing moves
    g = build_graph(V, F, 0.08)
    x, st = _solve_frame(V, F, V[g.nodes], g, _target(V1, F), TrackParams(), identity_params(len(g.nodes)))
    assert st["n_corr"] == 0 and np.allclose(x, identity_params(len(g.nodes)), rtol=0, atol=1e-12)


@pytest.mark.parametrize("degrees", [10.0, 30.0])
def test_rigid_stage_takes_a_turn_whole(degrees):
    """The rigid stage solves for a rotation (6 unknowns), not for one affine graph node held
    rigid by a large rotation weight: the sphere turned 10 or 30 degrees about its vertical axis
    is recovered to a fraction of a millimetre in one frame (the held node left 10 degrees
    14 mm off after its 12 steps)."""
    V, F = _sphere()
    c = V.mean(0)
    V1 = (V - c) @ Rotation.from_euler("y", degrees, degrees=True).as_matrix().T + c
    (_, out, st), = track_sequence(V, F, [Observation(_target(V1, F))], TrackParams(rigid_only=True, w_flow=0.0),
                                   progress=False)
    assert st["frame_fallback"] == 0 and st["lm_failed"] == 0
    assert np.linalg.norm(out - V1, axis=1).mean() < 0.0005


def test_rigid_solve_returns_a_rotation_and_its_translation():
    """_solve_rigid's (R, t): R orthonormal with det +1 and the moved mesh V0 @ R.T + t, here the
    sphere turned 5 degrees about a tilted axis and moved 1 cm (recovered within 1e-3 rad / 1 mm)."""
    from stex.tracking import _solve_rigid
    V, F = _sphere()
    rotvec = np.deg2rad(5.0) * np.array([0.6, 0.8, 0.0])
    R_true = Rotation.from_rotvec(rotvec).as_matrix()
    t_true = np.array([0.01, 0.0, 0.005])
    V1 = V @ R_true.T + t_true
    R, t, st = _solve_rigid(V, F, _target(V1, F), TrackParams(gn_iterations=12))
    assert np.allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert Rotation.from_matrix(R @ R_true.T).magnitude() < 1e-3
    assert np.abs(V @ R.T + t - V1).max() < 0.001
    assert st["n_corr"] > 50


def test_constant_velocity_predicts_the_last_motion_once_more(monkeypatch):
    """With constant_velocity, frame 2 starts from frame 1's mesh moved again by the motion from
    frame 0 to 1 (here 2 cm along x); without it, from frame 1's mesh."""
    import stex.tracking as tracking
    V, F = _sphere()
    step = np.array([0.02, 0.0, 0.0])
    solve = tracking._solve_rigid
    for cv in (False, True):
        starts = []

        def spy(V0, *args, **kwargs):   # the rigid stage: it starts from the prediction
            starts.append(V0.copy())
            return solve(V0, *args, **kwargs)

        monkeypatch.setattr(tracking, "_solve_rigid", spy)
        out = [Vb for _, Vb, _ in track_sequence(V, F, [Observation(_target(V + i * step, F)) for i in range(3)],
                                                 TrackParams(rigid_only=True, w_flow=0.0, constant_velocity=cv),
                                                 progress=False)]
        assert np.abs(out[1] - out[0] - step).max() < 1e-3      # the tracker did follow the motion
        assert np.abs(starts[2] - (out[1] + step if cv else out[1])).max() < 2e-3


def test_flow_constraints_keep_only_forward_backward_consistent_flow(tiny_config, monkeypatch):
    """With DIS replaced by known fields (forward +3 px in u everywhere; backward -3 px, or -1 px
    from column 100 on), a vertex's target is its pixel + (3, 0), and it is kept only where the
    backward flow at the target returns within consistency_px (1 px): u < 99.5 (bilinear between
    columns 99 and 100, the round-trip error grows from 0 to 2 px)."""
    import cv2

    from stex.camera import project_points, transform_points
    from stex.synth.scene import SyntheticScene
    from stex.flow import AppearanceModel, flow_constraints
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    r0 = s.render_frame(0)
    g0 = cv2.cvtColor(r0.color, cv2.COLOR_RGB2GRAY)
    V0 = s.true_vertices(0)
    model = AppearanceModel(s.texcoords, s.texcoord_faces, s.faces, 256)
    model.capture(V0, g0, cal, 0.3)
    H, W = g0.shape

    class KnownFlow:
        def __init__(self, backward):
            self.backward, self.calls = backward, 0

        def calc(self, a, b, _):   # forward (model -> image) first, then backward
            self.calls += 1
            f = np.zeros((H, W, 2), np.float32)
            f[..., 0] = 3.0 if self.calls == 1 else self.backward
            return f

    out = {}
    for name in ("consistent", "split"):
        bw = np.full((H, W), -3.0, np.float32)
        if name == "split":
            bw[:, 100:] = -1.0
        monkeypatch.setattr(cv2, "DISOpticalFlow_create", lambda preset, bw=bw: KnownFlow(bw))
        out[name] = flow_constraints(V0, s.faces, model, g0, r0.true_mask, cal, crop_margin_px=10**6)
    ids, u1 = out["consistent"]
    uv = project_points(transform_points(cal.depth_to_color, V0), cal.color.K)[0]
    np.testing.assert_allclose(u1, uv[ids] + [3.0, 0.0], atol=1e-9)
    keep = u1[:, 0] < 99.5
    assert 10 < keep.sum() < len(ids) - 10       # the split runs through the object
    np.testing.assert_array_equal(out["split"][0], ids[keep])
    np.testing.assert_allclose(out["split"][1], u1[keep])


def test_frame_guard_keeps_the_best_fit_beyond_a_5_percent_margin(monkeypatch):
    """The frame keeps the solve unless it explains the depth more than FRAME_GUARD_MARGIN (5 %)
    worse than the rigid fit or the prediction; then the best of those two, with its fit in the
    stats. The fits (solve, rigid, prediction; in the order the guard measures them) are given."""
    import stex.tracking as tracking
    V, F = _sphere()
    target = _target(V + [0.0, 0.0, 0.01], F)
    for fits, keep in [((1.04, 1.0, 2.0), "solve"), ((1.06, 1.0, 2.0), "rigid"), ((1.2, 1.0, 2.0), "rigid"),
                       ((1.2, 2.0, 1.0), "prediction"), ((0.5, 1.0, 2.0), "solve")]:
        meshes = []

        def given_fit(Vm, *args, **kwargs):
            meshes.append(Vm)
            return fits[len(meshes) - 1]

        monkeypatch.setattr(tracking, "depth_residual", given_fit)
        # unseen_from_rest off: it re-poses the unseen vertices of whichever mesh the guard keeps
        (_, out, st), = track_sequence(V, F, [Observation(target)], TrackParams(w_flow=0.0, unseen_from_rest=False),
                                       progress=False)
        assert len(meshes) == 3 and np.array_equal(meshes[2], V)       # the prediction of frame 0: the template
        k = ["solve", "rigid", "prediction"].index(keep)
        assert out is meshes[k] and st["frame_fallback"] == int(keep != "solve")
        assert st["depth_residual_m"] == fits[k]


def test_volume_links_stay_within_their_range():
    """On a closed rod 40 cm long (radius 2 cm), every link through the solid joins nodes at most
    volume_range spacings (here 4 x 3 cm) apart (Euclidean), however many links a node may have."""
    import trimesh
    m = trimesh.creation.cylinder(radius=0.02, height=0.4, sections=16).subdivide().subdivide()
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    plain = build_graph(V, F, 0.03)
    g = build_graph(V, F, 0.03, volume_links=20, volume_range=4.0)
    extra = np.array(sorted({tuple(e) for e in g.edges.tolist()} - {tuple(e) for e in plain.edges.tolist()}))
    assert len(extra) > 20
    P = V[g.nodes]
    assert np.linalg.norm(P[extra[:, 0]] - P[extra[:, 1]], axis=1).max() <= 4.0 * 0.03


def test_flow_weights_fall_with_the_age_of_the_model_texels(tiny_config, monkeypatch):
    """flow_age_frames k: a flow constraint on a texel captured at frame a weighs 1 / (1 + a / k).
    With k = 2 over three frames the model holds texels of frames 0 and 1: weights 1 and 2/3
    (1/2 for a texel not captured yet, taken as captured now, at frame 2)."""

    import stex.tracking as tracking
    from stex.synth.scene import SyntheticScene
    # turning ~40 degrees a frame, frame 1 captures texels that frame 2's flow uses (measured:
    # 15 of 29 constraints; at the tiny scene's own slow turn, none, so nothing would be tested)
    s = SyntheticScene({**tiny_config["source"]["synthetic"], "yaw_period_s": 0.5})
    weights = []
    solve = tracking._solve_frame

    def spy(V0, faces, node_pos, graph, target, p, x_init, flow=None, silhouette=None):
        if flow is not None:
            weights.append(flow[4])
        return solve(V0, faces, node_pos, graph, target, p, x_init, flow, silhouette)

    monkeypatch.setattr(tracking, "_solve_frame", spy)

    def obs():
        return _scene_observations(s, 3)

    seen = []
    for pos, _, _ in track_sequence(s.true_vertices(0), s.faces, obs(), TrackParams(flow_age_frames=2.0, flow_passes=1),
                                    progress=False, texcoords=s.texcoords, texcoord_faces=s.texcoord_faces):
        seen.append(np.concatenate(weights) if weights else np.zeros(0))
        weights.clear()

    def near(w, values):   # (n, len(values)) bool: which of the values each weight is
        return np.isclose(w[:, None], np.asarray(values)[None], rtol=1e-12, atol=0)

    assert len(seen[0]) == 0                                            # no model yet at frame 0
    assert near(seen[1], [1.0, 2 / 3]).any(1).all() and near(seen[1], [1.0]).any()  # frame-0 texels, new at 1
    assert near(seen[2], [1.0, 2 / 3, 0.5]).any(1).all() and near(seen[2], [2 / 3]).any()


def _rod_bent_at_the_waist():
    """A closed rod 40 cm long (radius 5 cm) 1 m in front of the camera, and its pose after the
    lower half turned 10 degrees about the rod's axis and moved by (1, -2, 0.5) cm while the
    upper half bent 25 degrees at the waist on top of it."""
    import trimesh
    m = trimesh.creation.cylinder(radius=0.05, height=0.4, sections=24).subdivide().subdivide()
    V, F = np.asarray(m.vertices) + [0.0, 0.0, 1.0], np.asarray(m.faces)
    waist = np.array([0.0, 0.0, 1.0])
    turn = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    bend = Rotation.from_euler("x", 25, degrees=True).as_matrix()
    local = V - waist
    upper = local[:, 2] > 0
    local[upper] = local[upper] @ bend.T
    return V, F, local @ turn.T + waist + [0.01, -0.02, 0.005], upper


def test_compose_rigid_is_the_warp_then_the_motion():
    V, F = _sphere()
    g = build_graph(V, F, 0.08)
    x = identity_params(len(g.nodes)) + np.random.default_rng(0).normal(size=(len(g.nodes), 12)) * 0.1
    R, t = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([0.1, 0.2, -0.3])
    nodes = V[g.nodes]
    assert np.allclose(deform(V, nodes, g, compose_rigid(x, nodes, R, t)), deform(V, nodes, g, x) @ R.T + t,
                       atol=1e-12)


def test_rest_warp_puts_the_hidden_side_where_its_part_went():
    """fit_rest_warp holds the seen front half of a rod at its pose and poses the hidden back
    from the rest shape: exactly for a rigid motion; after a 25-degree bend at the waist, the
    back (at least 2 cm behind the axis) lands within 7 mm of the truth on average (measured
    5.7 mm: 4.8 below the waist, 6.9 above), against 15.2 mm (17.6 / 12.0) where the seen half's
    rigid fit puts it."""
    V, F, bent, upper = _rod_bent_at_the_waist()
    p = TrackParams()
    g = build_graph(V, F, p.node_spacing_m, p.k_nodes, volume_links=p.volume_links, volume_range=p.volume_link_range)
    seen, hidden = np.flatnonzero(V[:, 1] < 0), V[:, 1] >= 0.02
    R, t = Rotation.from_euler("z", 10, degrees=True).as_matrix(), np.array([0.01, -0.02, 0.005])
    moved = V @ R.T + t
    x = fit_rest_warp(V, g, identity_params(len(g.nodes)), seen, moved[seen], p)
    assert np.abs(deform(V, V[g.nodes], g, x) - moved).max() < 1e-6
    x = fit_rest_warp(V, g, identity_params(len(g.nodes)), seen, bent[seen], p)
    err = np.linalg.norm(deform(V, V[g.nodes], g, x) - bent, axis=1)
    R, t = rigid_fit(V[seen], bent[seen])
    rigid_err = np.linalg.norm(V @ R.T + t - bent, axis=1)
    assert err[seen].mean() < 0.5e-3
    assert err[hidden].mean() < 7e-3 and err[hidden].mean() < 0.5 * rigid_err[hidden].mean()
    assert err[hidden & upper].mean() < rigid_err[hidden & upper].mean()


def test_unseen_from_rest_moves_only_what_the_depth_camera_does_not_see():
    """One frame of a squashed sphere tracked with and without unseen_from_rest: the meshes agree
    bit for bit on the vertices the depth camera sees at the result, and differ on the others."""
    V, F = _sphere()
    c = V.mean(0)
    target = _target((V - c) * [1.0, 1.1, 0.9] + c + [0.01, 0.0, 0.01], F)   # squashed: not a rigid motion
    out = {}
    for on in (False, True):
        (_, out[on], _), = track_sequence(V, F, [Observation(target)], TrackParams(w_flow=0.0, unseen_from_rest=on),
                                          progress=False)
    H, W = target.valid.shape
    seen = vertex_visibility(out[True], F, target.K, rasterize(out[True], F, target.K, W, H).depth)[0]
    assert 0.2 < seen.mean() < 0.8
    assert np.array_equal(out[True][seen], out[False][seen])
    assert np.linalg.norm(out[True][~seen] - out[False][~seen], axis=1).max() > 1e-5


def test_block_jacobi_takes_a_node_with_degenerate_data():
    """A node whose data span one direction only has a rank-deficient 12x12 block; with large
    entries np.linalg.inv calls it singular (the crash a walking limb caused): the preconditioner
    still applies, as the exact inverse on the regular blocks and finite on the degenerate one."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(12, 1)) * 1e4
    m = rng.normal(size=(12, 12))
    regular = m @ m.T + np.eye(12)
    blocks = np.stack([regular, a @ a.T])
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.inv(blocks + np.eye(12) * 1e-12)
    M = block_jacobi(blocks)
    v = rng.normal(size=24)
    out = M.matvec(v)
    assert np.isfinite(out).all()
    assert np.allclose(out[:12], np.linalg.solve(regular, v[:12]), rtol=1e-6)
    assert np.allclose(block_jacobi(blocks[:1]).matvec(v[:12]), np.linalg.solve(regular, v[:12]))


def test_a_step_singular_in_floating_point_is_damped_not_a_crash():
    """Gauss-Newton normal equations of data on a line (here: two unknowns seen only through
    their sum) are singular without damping, and np.linalg.solve raises (the rigid stage crashed so
    on a scan whose correspondences collapsed): the step is damped instead and still descends; a
    system no damping makes solvable ends the round (None) without raising."""
    JtJ, g = np.array([[1.0, 1.0], [1.0, 1.0]]), np.array([-1.0, -1.0])
    diag = np.diag(JtJ).copy()

    def energy(d):                                 # 0.5 |J d - r|^2 with J = [1 1], r = 1
        return float((d.sum() - 1.0) ** 2)

    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(JtJ, -g)
    stats = {"lm_rejected": 0, "lm_failed": 0}
    step, mu, _ = lm_step(energy(np.zeros(2)), g, JtJ, lambda mu: np.linalg.solve(JtJ + np.diag(mu * diag), -g),
                          energy, 0.0, 2.0, stats)
    assert step is not None and np.isfinite(step).all() and energy(step) < 1e-3
    assert stats["lm_rejected"] == 1 and mu > 0

    def never(mu):
        raise np.linalg.LinAlgError("Singular matrix")

    stats = {"lm_rejected": 0, "lm_failed": 0}
    assert lm_step(1.0, g, JtJ, never, energy, 0.0, 2.0, stats)[0] is None
    assert stats["lm_failed"] == 1


@pytest.mark.parametrize("axis, shift", [("x", [0.0, 0.15, 0.2]), ("y", [-0.15, 0.0, 0.2])])
def test_rigid_stage_recovers_a_jump_of_25_cm_and_30_degrees(axis, shift):
    """A 0.25 m jump with a 30 degree turn of the bumpy sphere, beyond the fine level's reach
    (its rigid_iterations projective steps): the rigid stage goes coarse to fine and lands on
    the moved sphere to within a millimetre, where the fine steps alone stop 5 cm or more off."""
    V, F = _sphere()
    c = V.mean(0)
    assert np.linalg.norm(shift) == pytest.approx(0.25)
    V1 = (V - c) @ Rotation.from_euler(axis, 30, degrees=True).as_matrix().T + c + shift
    target = _target(V1, F)
    p = TrackParams(rigid_only=True, w_flow=0.0)
    (_, out, st), = track_sequence(V, F, [Observation(target)], p, progress=False)
    assert st["rigid_coarse_to_fine"] == 1
    assert np.linalg.norm(out - V1, axis=1).mean() < 0.001
    # the fine level alone, as the stage ran before: a fixed count of projective steps
    from stex.tracking import _rigid_steps
    fine = TrackParams(**{**p.__dict__, "max_distance_m": 2 * p.max_distance_m})
    R, t, steps, _, _ = _rigid_steps(V - c, c, np.eye(3), np.zeros(3), F.astype(np.int64), target, fine, None, None,
                                     None, p.rigid_iterations, 0.0, {"n_corr": 0, "data_rms_m": 0.0,
                                                                     "lm_rejected": 0, "lm_failed": 0})
    assert steps == p.rigid_iterations
    assert np.linalg.norm((V - c) @ R.T + c + t - V1, axis=1).mean() > 0.05


def test_rigid_stage_keeps_its_fine_steps_where_they_converge():
    """A small motion (1 cm, 3 degrees) converges within the fine level's rigid_iterations steps:
    no coarse-to-fine search, the result that of the fine steps (as before the search existed)."""
    V, F = _sphere()
    c = V.mean(0)
    V1 = (V - c) @ Rotation.from_euler("y", 3, degrees=True).as_matrix().T + c + [0.01, 0.0, 0.0]
    (_, out, st), = track_sequence(V, F, [Observation(_target(V1, F))], TrackParams(rigid_only=True, w_flow=0.0),
                                   progress=False)
    assert st["rigid_coarse_to_fine"] == 0 and st["rigid_steps"] <= TrackParams.rigid_iterations
    assert np.linalg.norm(out - V1, axis=1).mean() < 0.0005


def test_rigid_stage_without_depth_stops_within_its_bound():
    """No foreground depth at all: the rigid stage cannot converge on anything, searches, and
    stops within its bound (rigid_max_iterations after the start poses' coarse level) with the
    mesh where it was."""
    from stex.tracking import RIGID_LEVEL_STEPS
    V, F = _sphere()
    empty = depth_target(np.zeros((180, 240)), K)
    p = TrackParams(rigid_only=True, w_flow=0.0, rigid_max_iterations=7)
    (_, out, st), = track_sequence(V, F, [Observation(empty)], p, progress=False)
    assert st["rigid_steps"] <= p.rigid_iterations + RIGID_LEVEL_STEPS + p.rigid_max_iterations
    assert np.abs(out - V).max() < 1e-9


def test_template_fit_problem_names_what_is_wrong():
    """The sphere in place fits; moved 0.8 m aside it shares no depth pixel with the object and
    the offset is named (measured from the part of its camera-facing side in view); 0.6 m farther along the view it overlaps in the image but lies beyond
    the rigid stage's reach; in millimetres its depth is 1000-odd times the object's; one face
    is too few."""
    from stex.frame_fit import template_fit_problem
    V, F = _sphere()
    t = _target(V, F)
    assert template_fit_problem(V, F, t, 0.4) is None
    aside = template_fit_problem(V + [0.8, 0.0, 0.0], F, t, 0.4)
    assert aside.startswith("it shares 0 depth pixels")
    assert float(re.search(r"depth lies ([\d.]+) m from", aside).group(1)) > 0.5 and "x -0.5" in aside
    farther = template_fit_problem(V + [0.0, 0.0, 0.6], F, t, 0.4)
    assert "lies 0.6" in farther and "m behind the object's depth" in farther and "farther than the tracker" in farther
    mm = template_fit_problem(1000 * V, F, t, 0.4)
    assert re.search(r"1\d\d\d times as far .* metres", mm)
    one = template_fit_problem(V, F[:1], t, 0.4)
    assert one.startswith("it has 1 face of non-zero area")


def test_tracking_stage_refuses_a_template_that_does_not_fit_the_object(tmp_path):
    """Shifted 0.6 m, in millimetres, or one face: the tracking stage raises before tracking,
    naming the template store, what is wrong and what to try, and writes no store; the tiny
    scene's own template passes the same check."""
    import shutil

    import zarr

    from conftest import run_stages, tiny_scene_config
    from stex.camera import Calibration
    from stex.io import FrameSequence, open_store
    from stex.stages.tracking import _check_template_fit, observations_from_stores, write_tracking

    cfg = tiny_scene_config(template={"atlas_size": 128})
    P = run_stages(cfg, tmp_path)

    def copy_edit(name, key, edit):
        out = tmp_path / name
        shutil.copytree(P["template"], out)
        z = zarr.open_group(str(out), mode="r+")
        z[key][...] = edit(z[key][...])
        z.attrs["chunk_files"] = {}   # see the millimetre test above
        return out

    cases = {"shifted": (copy_edit("shifted.zarr", "vertices", lambda v: v + [0.6, 0.0, 0.0]), r"it shares \d+ depth pixels"),
             "mm": (copy_edit("mm.zarr", "vertices", lambda v: 1000 * v), r"its vertices lie \d+ times as far .* metres"),
             "one face": (copy_edit("one.zarr", "faces", lambda f: np.concatenate([f[:1], 0 * f[1:]])),
                          "it has 1 face of non-zero area")}
    for name, (store, what) in cases.items():
        with pytest.raises(ValueError, match=rf"{store.name}: at frame \d+ the template does not fit the object: "
                                             rf"{what}.*template\.from_depth: true"):
            write_tracking(P["scene"], store, P["frames"], P["masks"], dict(cfg["tracking"], mode="track"),
                           tmp_path / f"{name}_tracking.zarr")
        assert not (tmp_path / f"{name}_tracking.zarr").exists()
    cal = Calibration.from_dict(open_store(P["scene"], "scene").attrs["calibration"])
    template = open_store(P["template"], "template")
    first = next(observations_from_stores(FrameSequence(P["frames"], "frames"), FrameSequence(P["masks"], "masks"),
                                          cal, use_flow=False))
    _check_template_fit(template["vertices"][...], template["faces"][...], first.target, 0, P["template"],
                        cfg["tracking"])
