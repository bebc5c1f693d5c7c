"""The skeleton (stex.skeleton), its place in the template store, and the articulated solve
(stex.articulated)."""
import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from stex.articulated import ArticulatedParams, ArticulatedTracker
from stex.skeleton import (
    Pose, apply_step, compose_root, identity_pose, pose_jacobian, skeleton_from_skin, skin)
from stex.tracking import TrackParams, depth_target


def _random_skeleton(rng, V=40):
    parents = [-1, 0, 1, 1, 3]
    frames = np.tile(np.eye(4), (5, 1, 1))
    frames[:, :3, 3] = rng.normal(size=(5, 3))
    return skeleton_from_skin(parents, frames, rng.integers(0, 5, (V, 4)), rng.random((V, 4))), rng.normal(size=(V, 3))


def test_pose_jacobian_matches_finite_differences_and_the_root_composes_rigidly():
    rng = np.random.default_rng(0)
    sk, rest = _random_skeleton(rng)
    assert np.allclose(skin(sk, rest, identity_pose(5)), rest)
    pose = Pose(Rotation.from_rotvec(rng.normal(size=(5, 3)) * 0.5).as_matrix(), rng.normal(size=3))
    X, D = pose_jacobian(sk, rest, pose)
    assert np.allclose(X, skin(sk, rest, pose))
    eps = 1e-6
    for k in range(D.shape[2]):
        step = np.zeros(D.shape[2])
        step[k] = eps
        plus = skin(sk, rest, apply_step(sk, pose, step))
        step[k] = -eps
        minus = skin(sk, rest, apply_step(sk, pose, step))
        assert np.abs((plus - minus) / (2 * eps) - D[:, :, k]).max() < 1e-6
    R, t = Rotation.from_rotvec([0.3, 0.1, -0.2]).as_matrix(), np.array([0.1, -0.2, 0.3])
    assert np.allclose(skin(sk, rest, compose_root(sk, pose, R, t)), X @ R.T + t)


def test_joints_are_put_parents_first_and_bad_weights_are_named():
    frames = np.tile(np.eye(4), (3, 1, 1))
    sk = skeleton_from_skin([2, -1, 1], frames, np.array([[0, 2]]), np.array([[1.0, 3.0]]), ["c", "a", "b"])
    assert sk.names == ["a", "b", "c"] and list(sk.parents) == [-1, 0, 1]
    assert list(sk.joints[0]) == [2, 1] and np.allclose(sk.weights, [[0.25, 0.75]])
    with pytest.raises(ValueError, match="cycle"):
        skeleton_from_skin([1, 0], frames[:2], np.zeros((1, 1), int), np.ones((1, 1)))
    with pytest.raises(ValueError, match="no skin weight"):
        skeleton_from_skin([-1], frames[:1], np.zeros((1, 1), int), np.zeros((1, 1)))


def _arm():
    """An L of two capsules 0.8 m in front of the camera: an upper arm along x (0.2 m) skinned to
    the root joint at its far end, a forearm along y (0.15 m) skinned to the elbow between them."""
    up = trimesh.creation.capsule(height=0.16, radius=0.03, count=[24, 24])
    fore = trimesh.creation.capsule(height=0.12, radius=0.025, count=[24, 24])
    Vu = np.asarray(up.vertices) @ Rotation.from_rotvec([0, np.pi / 2, 0]).as_matrix().T + [-0.1, 0.0, 0.8]
    Vf = np.asarray(fore.vertices) @ Rotation.from_rotvec([np.pi / 2, 0, 0]).as_matrix().T + [0.0, 0.085, 0.8]
    V = np.concatenate([Vu, Vf])
    F = np.concatenate([np.asarray(up.faces), np.asarray(fore.faces) + len(Vu)]).astype(np.int64)
    frames = np.tile(np.eye(4), (2, 1, 1))
    frames[:, :3, 3] = [[-0.2, 0, 0.8], [0.0, 0, 0.8]]
    joint = np.r_[np.zeros(len(Vu), int), np.ones(len(Vf), int)]
    return skeleton_from_skin([-1, 0], frames, joint[:, None], np.ones((len(V), 1))), V, F


def _depth(V, F, K, W=320, H=240):
    from stex.render import rasterize
    d = rasterize(V, F, K, W, H).depth.astype(np.float64)
    return depth_target(np.where(d > 0, d, 0.0), K, d > 0)


def test_the_articulated_solve_recovers_a_known_elbow_turn():
    sk, V, F = _arm()
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    turn = Rotation.from_rotvec(np.deg2rad(25) * np.array([0.6, 0.0, 0.8])).as_matrix()
    true = identity_pose(2)
    true.rotations[1] = turn
    Vt = skin(sk, V, true)
    tracker = ArticulatedTracker(sk, V, F, TrackParams(), ArticulatedParams(search_deg=()))
    got = tracker.solve(np.eye(3), np.zeros(3), _depth(Vt, F, K))
    # the forearm's direction (a capsule's turn about its own axis is not in the depth)
    fore = tracker.pose.rotations[0] @ tracker.pose.rotations[1] @ [0.0, 1.0, 0.0]
    assert np.rad2deg(np.arccos(min(1.0, fore @ turn[:, 1]))) < 2.0
    assert np.linalg.norm(got - Vt, axis=1).mean() < 0.005
    assert np.linalg.norm(V - Vt, axis=1)[sk.joints[:, 0] == 1].mean() > 0.02   # the forearm did turn


def _rig_for(vertices, path):
    """A two-joint rig (JSON) for ``vertices``: the upper part (y below the middle: the camera's y
    points down) skinned to the second joint."""
    mid = float(np.median(vertices[:, 1]))
    upper = vertices[:, 1] < mid
    doc = {"joints": [{"name": "base", "parent": -1, "position": vertices.mean(0).tolist()},
                      {"name": "top", "parent": 0, "position": [*vertices.mean(0)[:1], mid, *vertices.mean(0)[2:]]}],
           "vertex_joints": [[1] if u else [0] for u in upper],
           "vertex_weights": [[1.0] for _ in upper]}
    path.write_text(json.dumps(doc))
    return upper


def test_a_rig_survives_the_template_stage(tmp_path):
    from stex.config import load_config
    from stex.io import open_store
    from stex.mesh import transfer_vertices
    from stex.skeleton import skeleton_from_arrays
    from stex.stages.ingest import write_scene
    from stex.stages.template import write_template
    cfg = load_config(overrides={"source": {"kind": "synthetic", "synthetic": {
        "n_frames": 2, "procedural": {"n_around": 32, "n_rings": 16}}}})
    write_scene(cfg["source"], 4, tmp_path / "scene.zarr")
    scene = open_store(tmp_path / "scene.zarr", "scene")
    V0, F0 = scene["template/vertices"][...].astype(np.float64), scene["template/faces"][...]
    upper = _rig_for(V0, tmp_path / "rig.json")
    params = dict(cfg["template"], atlas_size=256, target_faces=500, min_faces=0, rig=str(tmp_path / "rig.json"))
    write_template(tmp_path / "scene.zarr", params, tmp_path / "template.zarr")
    g = open_store(tmp_path / "template.zarr", "template")
    sk = skeleton_from_arrays(g, g.attrs["skeleton_joint_names"])
    V = g["vertices"][...].astype(np.float64)
    assert g.attrs["skeleton_joint_names"] == ["base", "top"] and len(sk.joints) == len(V) < len(V0)
    assert np.allclose(g["skeleton/inverse_bind"][...] @ g["skeleton/bind"][...], np.eye(4))
    assert np.allclose(sk.weights.sum(1), 1, atol=1e-6)
    # posed, the template follows the posed source mesh where a vertex's face is skinned to one joint
    pose = identity_pose(2)
    pose.rotations[1] = Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix()
    source = skeleton_from_skin([-1, 0], np.asarray(g["skeleton/bind"][...]), upper[:, None].astype(int),
                                np.ones((len(V0), 1)))
    carried = transfer_vertices(skin(source, V0, pose), F0, g["embedding/face"][...], g["embedding/bary"][...])
    pure = upper[F0[g["embedding/face"][...]]].all(1) | ~upper[F0[g["embedding/face"][...]]].any(1)
    assert pure.sum() > len(V) / 2 and (~pure).any()
    assert np.abs(skin(sk, V, pose)[pure] - carried[pure]).max() < 1e-5
    moved = np.linalg.norm(skin(sk, V, pose) - V, axis=1)
    assert moved[pure].max() > 0.02          # the pose moved the upper part


def test_the_tracking_stage_without_the_skeleton_is_the_graph_alone(tmp_path):
    from conftest import tiny_scene_config
    from stex.io import open_store
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.stages.masks import write_masks_block
    from stex.stages.template import write_template
    from stex.stages.tracking import write_tracking
    cfg = tiny_scene_config()
    cfg["source"]["synthetic"]["n_frames"] = 2
    write_scene(cfg["source"], 4, tmp_path / "scene.zarr")
    write_frames_block(cfg["source"], 0, 2, tmp_path / "frames.zarr", tmp_path / "truth.zarr")
    write_masks_block(tmp_path / "scene.zarr", tmp_path / "frames.zarr", cfg["masks"], tmp_path / "masks.zarr")
    scene = open_store(tmp_path / "scene.zarr", "scene")
    _rig_for(scene["template/vertices"][...].astype(np.float64), tmp_path / "rig.json")
    out = {}
    for name, rig, use in (("plain", None, True), ("off", str(tmp_path / "rig.json"), False),
                           ("on", str(tmp_path / "rig.json"), True)):
        write_template(tmp_path / "scene.zarr", dict(cfg["template"], rig=rig), tmp_path / f"template_{name}.zarr")
        write_tracking(tmp_path / "scene.zarr", tmp_path / f"template_{name}.zarr", [tmp_path / "frames.zarr"],
                       [tmp_path / "masks.zarr"], dict(cfg["tracking"], mode="track", skeleton=use),
                       tmp_path / f"tracking_{name}.zarr")
        out[name] = open_store(tmp_path / f"tracking_{name}.zarr", "tracking")["vertices"][...]
    assert np.array_equal(out["plain"], out["off"])
    assert not np.array_equal(out["plain"], out["on"])     # the skeleton path is another path


def _arm_half_out_of_view():
    """The arm of :func:`_arm` with a camera whose image ends below the upper arm: the forearm
    (y > 0.04 m) is out of view, the upper arm in it."""
    sk, V, F = _arm()
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 225.0], [0, 0, 1]])
    upper = sk.joints[:, 0] == 0
    return sk, V, F, K, _depth(V, F[np.all(upper[F], axis=1)], K)


def test_a_joint_the_depth_camera_cannot_see_is_named_unseen():
    sk, V, F, K, target = _arm_half_out_of_view()
    tracker = ArticulatedTracker(sk, V, F, TrackParams(), ArticulatedParams(search_deg=(), min_seen=100.0))
    assert tracker.joints_seen(V, target).tolist() == [True, False]
    # a camera that sees the whole arm sees both joints
    K_all = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    assert tracker.joints_seen(V, _depth(V, F, K_all)).tolist() == [True, True]


def test_an_unseen_joint_stops_turning_and_turns_back_towards_the_template():
    """The forearm turned 20 degrees in the last frame and then left the view: without data it
    must not go on at its last speed (40 degrees), and it gives back ``unseen_return`` of its turn."""
    sk, V, F, K, target = _arm_half_out_of_view()
    turn = np.deg2rad(20.0) * np.array([0.0, 0.0, 1.0])
    for back, expected in ((0.0, 20.0), (0.3, 14.0)):
        tracker = ArticulatedTracker(sk, V, F, TrackParams(), ArticulatedParams(
            search_deg=(), min_seen=100.0, unseen_return=back))
        tracker.last = identity_pose(2)
        tracker.pose = identity_pose(2)
        tracker.pose.rotations[1] = Rotation.from_rotvec(turn).as_matrix()
        stats = {}
        tracker.solve(np.eye(3), np.zeros(3), target, stats=stats)
        got = np.rad2deg(np.linalg.norm(Rotation.from_matrix(tracker.pose.rotations[1]).as_rotvec()))
        assert abs(got - expected) < 1e-6, (back, got)
        assert stats["skeleton_unseen_joints"] == 1
