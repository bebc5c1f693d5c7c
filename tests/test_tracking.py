"""Embedded-deformation tracking with the L0 regulariser."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import data_samples
from stex.render import face_normals, rasterize
from stex.synth.shapes import bumpy_sphere
from stex.template import template_from_depth
from stex.tracking import (Observation, TrackParams, _solve_frame, build_graph, deform, depth_residual,
                           depth_target, identity_params, track_sequence)

K = np.array([[200.0, 0, 119.5], [0, 200.0, 89.5], [0, 0, 1]])


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
    import cv2

    from stex.synth.scene import SyntheticScene
    from stex.tracking import mask_in_depth
    from stex.render import vertex_visibility
    cfg = tiny_config["source"]["synthetic"]
    s = SyntheticScene(cfg)
    cal = s.calibration

    def obs():
        for t in range(s.n_frames):
            r = s.render_frame(t)
            fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
            yield Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg),
                              cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY), cal, r.true_mask)

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
    import cv2
    from scipy import ndimage

    sd = REAL / "killingfusion_snoopy" / "frames_000050_000051"
    Ks = np.array([[517.0, 0, 320], [0, 517.0, 240], [0, 0, 1]])
    pairs = [(Ks, [cv2.imread(str(sd / f"snoopy_depth_0000{i}.png"), -1) / 1000.0 for i in (50, 51)],
              [cv2.imread(str(sd / f"snoopy_omask_0000{i}.png"), 0) > 0 for i in (50, 51)])]
    dd = REAL / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017"
    Kd = np.loadtxt(dd / "intrinsics.txt")[:3, :3]
    ds = [cv2.imread(str(dd / "depth" / f"000{i}.png"), -1) / 1000.0 for i in (300, 600)]

    def largest(m):
        lab, n = ndimage.label(m)
        return lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    pairs.append((Kd, ds, [largest((d > 0) & (d < 2.05)) for d in ds]))
    for Kp, depths, masks in pairs:
        V, F = template_from_depth(depths[0], Kp, masks[0], stride=2)
        targets = [depth_target(d, Kp, m) for d, m in zip(depths, masks)]
        res = {}
        for mode in ("rigid", "ed"):
            p = TrackParams(rigid_only=mode == "rigid", w_flow=0.0, gn_iterations=8)
            *_, (_, Vb, _) = track_sequence(V, F, [Observation(t) for t in targets], p, progress=False)
            res[mode] = depth_residual(Vb, F, targets[1], union=False)
        before = depth_residual(V, F, targets[1], union=False)
        assert res["ed"] < res["rigid"] <= before + 1e-4, (before, res)


def test_volume_links_run_through_the_solid_only():
    """Two closed balls side by side: links cross each ball's inside but never the air between
    the balls; an open mesh (a hemisphere) gets none."""
    import trimesh

    from stex.tracking import build_graph
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
    schema = section_params("tracking")
    fields = asdict(TrackParams())
    # mode and min_silhouette_iou are the stage's, not the solver's
    assert {k: v for k, v in schema.items() if k not in ("mode", "min_silhouette_iou")} == fields


def test_flow_on_the_object_box_matches_the_whole_image(tiny_config):
    """Cropping the flow to the object's box changes the targets by a fraction of a pixel."""
    import cv2

    from stex.synth.scene import SyntheticScene
    from stex.tracking import AppearanceModel, flow_constraints
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    r0, r1 = s.render_frame(0), s.render_frame(1)
    g0, g1 = (cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY) for r in (r0, r1))
    V0 = s.true_vertices(0)
    model = AppearanceModel(s.texcoords, s.texcoord_faces, s.faces, 256)
    assert model.capture(V0, g0, cal, 0.3)[0] > 0
    ids_a, ua = flow_constraints(V0, s.faces, model, g1, r1.true_mask, cal, prev_gray=g0, crop_margin_px=16)
    ids_b, ub = flow_constraints(V0, s.faces, model, g1, r1.true_mask, cal, prev_gray=g0, crop_margin_px=10**6)
    common, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
    assert len(common) > 0.8 * max(len(ids_a), len(ids_b)) > 20
    assert np.abs(ua[ia] - ub[ib]).mean() < 0.15


def test_appearance_model_recaptures_texels_seen_more_squarely(tiny_config):
    """A texel first seen at a slant is captured again once seen much more squarely (and only
    then); the others keep their first capture."""
    import cv2

    from stex.synth.scene import SyntheticScene
    from stex.tracking import AppearanceModel
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
    from stex.tracking import _NormalPattern, _normal_equations, _rot_terms
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
        rot, _ = _rot_terms(x)
        A, t = x[:, :9].reshape(N, 3, 3), x[:, 9:]
        r_jk = np.einsum("eab,eb->ea", A[j_], d_jk) + nodes[j_] + t[j_] - nodes[k_] - t[k_]
        return np.concatenate([data, np.sqrt(w_rot) * rot.ravel(), np.sqrt(w_smooth) * (r_jk - s).ravel()])

    r0 = residuals(x0.ravel())
    eps = 1e-6
    J = np.stack([(residuals(x0.ravel() + eps * e) - residuals(x0.ravel() - eps * e)) / (2 * eps)
                  for e in np.eye(12 * N)], axis=1)
    rot, Jr = _rot_terms(x0)
    A, t = x0[:, :9].reshape(N, 3, 3), x0[:, 9:]
    r_jk = np.einsum("eab,eb->ea", A[j_], d_jk) + nodes[j_] + t[j_] - nodes[k_] - t[k_]
    local = V[:, None, :] - nodes[g.vertex_nodes]
    JtJ, grad, diag = _normal_equations(_NormalPattern(g, N), g, local, vid.astype(np.int64), Dw, r0[:400],
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
    import cv2

    import stex.tracking as tracking
    from stex.synth.scene import SyntheticScene
    from stex.tracking import mask_in_depth
    s = SyntheticScene(tiny_config["source"]["synthetic"])
    cal = s.calibration
    solve = tracking._solve_frame

    def flinging_solve(V0, faces, node_pos, graph, *args, **kwargs):
        x, stats = solve(V0, faces, node_pos, graph, *args, **kwargs)
        if len(node_pos) > 1:   # the non-rigid stage only
            x = x.copy()
            x[:, 9:] += [0.3, 0.0, 0.0]
        return x, stats

    monkeypatch.setattr(tracking, "_solve_frame", flinging_solve)

    def obs():
        for t in range(3):
            r = s.render_frame(t)
            fg = mask_in_depth(r.true_mask, r.depth_mm, cal)
            yield Observation(depth_target(r.depth_mm / 1000.0, cal.depth.K, fg),
                              cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY), cal, r.true_mask)

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
    from stex.tracking import DeformationGraph, _normal_equations, _NormalPattern

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
        JtJ, grad, _ = _normal_equations(_NormalPattern(graph, N), graph, local, *none, rot_res, rot_jac, r, w, d)
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
    from stex.tracking import silhouette_iou

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
    two frames are named in a warning and in poorly_fitted_frames, without any ground truth; at
    every frame, or with the colour camera's focal length off by 15 %, the stage refuses them."""
    import shutil

    import zarr

    from conftest import run_stages, tiny_scene_config
    from stex.io import open_store
    from stex.tracking import write_tracking

    cfg = tiny_scene_config(template={"atlas_size": 128})
    P = run_stages(cfg, tmp_path)
    good = open_store(P["tracking"], "tracking")
    assert good.attrs["poorly_fitted_frames"] == []
    assert (good["silhouette_iou"][...] > 0.9).all()
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


def test_tracking_stage_refuses_a_mesh_in_millimetres_and_names_frames_without_depth(tmp_path, caplog):
    """A template (track) or given meshes (given) in millimetres project like metres, so the
    silhouette cannot tell; the depth can, and the stage refuses them at the first frame. A frame
    whose depth is all invalid is named in a warning: there the mesh has nothing to fit."""
    import shutil

    import zarr

    from conftest import run_stages, tiny_scene_config
    from stex.io import FrameSequence, open_store
    from stex.tracking import write_tracking

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
