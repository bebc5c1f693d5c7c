import dataclasses
import logging

import numpy as np
import pytest

from stex import poses
from stex.config import load_config
from stex.io import StoreError, create_store, open_store
from stex.stages.poses import read_vertices, write_pose_table
from stex.synth.procedural import ProceduralBody
from stex.synth.scene import SyntheticScene


def _random_rotation(rng, angle_deg=None):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(angle_deg if angle_deg is not None else rng.uniform(5, 170))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _body(n_around=48, n_rings=24):
    b = ProceduralBody(dataclasses.replace(ProceduralBody().p, n_around=n_around, n_rings=n_rings))
    return b.vertices(0.3) + np.array([0.0, 0.0, 1.0]), b.faces


def _scene(variant="full", **synthetic):
    cfg = load_config(overrides={"source": {"synthetic": {
        "n_frames": 12, "procedural": {"n_around": 48, "n_rings": 24}, **synthetic}}})["source"]["synthetic"]
    s = SyntheticScene(cfg)
    if variant == "core":  # only the local belly bulge deforms: a genuinely rigid core
        s.body = ProceduralBody(dataclasses.replace(s.body.p, bend=0.0, twist=0.0, squash=0.0, bulge=0.35))
    X = np.stack([s.true_vertices(t) for t in range(s.n_frames)])
    M = np.stack([s.object_to_depth(s.time_of(t)) for t in range(s.n_frames)])
    K_true = M[None, :] @ poses.invert_rigid(M)[:, None]  # [t, t'] = obj2depth(t') inv(obj2depth(t))
    return s, X, K_true


def _pair_errors(P, K_true, X):
    """Rotation error (°) and translation error (m) of every pair t != t', the translation
    measured where it matters, at the object (frame t's vertex centroid): the transforms' own
    translations are at the camera centre ~1 m away and carry ~17 mm per degree."""
    i, j = np.nonzero(~np.eye(P.shape[0], dtype=bool))
    return poses.pose_error(P[i, j], K_true[i, j], center=X.mean(1)[i])


def test_kabsch_exact_batched():
    rng = np.random.default_rng(0)
    R = np.stack([_random_rotation(rng) for _ in range(6)]).reshape(2, 3, 3, 3)
    t = rng.normal(size=(2, 3, 3))
    P = rng.normal(size=(2, 3, 25, 3))
    Q = np.einsum("abij,abnj->abni", R, P) + t[:, :, None]
    Re, te = poses.kabsch(P, Q)
    assert Re.shape == (2, 3, 3, 3) and te.shape == (2, 3, 3)
    np.testing.assert_allclose(Re, R, atol=1e-10)
    np.testing.assert_allclose(te, t, atol=1e-10)
    # weights: corrupt some points, give them weight 0
    Qc = Q.copy()
    Qc[..., :5, :] += 1.0
    w = np.ones(P.shape[:-1])
    w[..., :5] = 0.0
    Rw, tw = poses.kabsch(P, Qc, w)
    np.testing.assert_allclose(Rw, R, atol=1e-10)
    np.testing.assert_allclose(tw, t, atol=1e-10)
    # mirrored data: still a proper rotation
    Rm, _ = poses.kabsch(P[0, 0], P[0, 0] * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(Rm) == pytest.approx(1.0)


def test_ransac_recovers_rigid_motion_with_40_percent_outliers():
    rng = np.random.default_rng(1)
    P, _ = _body()
    R = _random_rotation(rng, 35.0)
    t = np.array([0.08, -0.05, 0.12])
    Q = P @ R.T + t
    out = rng.random(P.shape[0]) < 0.4
    # non-rigid displacement of the outliers: smooth-ish random field, 2-20 cm
    d = rng.normal(size=(out.sum(), 3))
    d *= (rng.uniform(0.02, 0.2, out.sum()) / np.linalg.norm(d, axis=1))[:, None]
    Q[out] += d
    T, mask = poses.ransac_rigid(P, Q, n_iter=500, inlier_thresh_m=0.01, rng=np.random.default_rng(3))
    rot, trans = poses.pose_error(T, poses.to_matrix(R, t))
    assert rot < 0.1 and trans < 1e-3
    assert np.array_equal(mask, ~out)
    # the batched version over several pairs agrees
    X = np.stack([P, Q, P @ R.T])
    Tb, ratio = poses.pairwise_ransac(X, pairs=[(0, 1), (0, 2)], seed=5)
    rot, trans = poses.pose_error(Tb, poses.to_matrix(np.stack([R, R]), np.stack([t, np.zeros(3)])))
    assert (rot < 0.1).all() and (trans < 1e-3).all()
    assert ratio[0] == pytest.approx(1 - out.mean(), abs=1e-6) and ratio[1] == 1.0


def test_icp_refines_perturbed_start():
    rng = np.random.default_rng(2)
    P, F = _body()
    from stex.render import vertex_normals

    R = _random_rotation(rng, 20.0)
    t = np.array([0.02, 0.01, -0.03])
    Q = P @ R.T + t
    Q[:50] += 0.3  # a few far outliers, gated out
    N = vertex_normals(Q, F)
    T_true = poses.to_matrix(R, t)
    T0 = poses.to_matrix(_random_rotation(rng, 1.5), np.array([0.004, -0.003, 0.002])) @ T_true
    rot0, trans0 = poses.pose_error(T0, T_true)
    T, ratio = poses.icp_point_to_plane(np.stack([P, P]), np.stack([Q, Q]), np.stack([N, N]),
                                        np.stack([T0, T_true]), n_iter=10, inlier_thresh_m=0.05)
    rot, trans = poses.pose_error(T, T_true)
    assert rot0 > 1.0 and (rot < 1e-3).all() and (trans < 1e-5).all()
    np.testing.assert_allclose(ratio, 1 - 50 / P.shape[0], atol=1e-6)
    # pure point-to-plane also converges here (the body is not rotationally symmetric)
    T1, _ = poses.icp_point_to_plane(P, Q, N, T0, n_iter=10, inlier_thresh_m=0.05, point_weight=0.0)
    rot1, trans1 = poses.pose_error(T1, T_true)
    assert rot1 < 1e-2 and trans1 < 1e-4


def test_icp_point_to_plane_residuals_get_a_huber_weight_of_a_quarter_of_the_threshold():
    """Points on a cube's six faces (3 x 3 each, normals along the axes), matched to themselves
    except the centre of the +z face, displaced by d = 8 mm along z (within θ = 10 mm, so the
    inlier gate keeps it; at the face centre it exerts no torque). Point-to-plane only, the
    fixed point of the Huber IRLS balances the 17 other z-facing points at weight 1 against the
    outlier's bounded pull: 17·t_z = δ = θ/4, t_z = 0.147 mm. Least squares (or δ ≥ d) would
    give t_z = d/18 = 0.444 mm. x, y and the rotation stay 0 by symmetry."""
    g = np.array([-0.05, 0.0, 0.05])
    P, N = [], []
    for axis in range(3):
        for side in (-1.0, 1.0):
            for a in g:
                for b in g:
                    p = np.zeros(3)
                    p[axis] = 0.1 * side
                    p[[k for k in range(3) if k != axis]] = a, b
                    n = np.zeros(3)
                    n[axis] = side
                    P.append(p)
                    N.append(n)
    P, N = np.array(P), np.array(N)
    Q = P.copy()
    centre = np.flatnonzero((P == [0.0, 0.0, 0.1]).all(axis=1))
    assert centre.size == 1
    Q[centre, 2] += 0.008
    theta = 0.01
    T, ratio = poses.icp_point_to_plane(P, Q, N, n_iter=50, inlier_thresh_m=theta, point_weight=0.0)
    assert ratio == 1.0
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, theta / 4 / 17], atol=1e-6)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-9)


def test_pose_table_consistency_and_determinism():
    rng = np.random.default_rng(4)
    P, F = _body(32, 16)
    X = np.stack([P @ _random_rotation(rng).T + rng.normal(0, 0.1, 3)
                  + rng.normal(0, 0.001, P.shape) for _ in range(5)])
    A, ra = poses.pose_table(X, F, {"ransac_iterations": 200}, seed=7, threads=1)
    B, rb = poses.pose_table(X, F, {"ransac_iterations": 200}, seed=7, threads=2)
    assert A.shape == (5, 5, 4, 4) and A.dtype == np.float64 and ra.shape == (5, 5) and ra.dtype == np.float32
    assert A.tobytes() == B.tobytes() and ra.tobytes() == rb.tobytes()
    np.testing.assert_array_equal(A[np.arange(5), np.arange(5)], np.broadcast_to(np.eye(4), (5, 4, 4)))
    np.testing.assert_allclose(A @ np.swapaxes(A, 0, 1), np.broadcast_to(np.eye(4), (5, 5, 4, 4)), atol=1e-12)
    np.testing.assert_array_equal(ra, ra.T)
    assert (ra > 0.9).all()
    # poses[t, t'] maps frame t onto frame t'
    moved = np.einsum("ij,vj->vi", A[1, 3, :3, :3], X[1]) + A[1, 3, :3, 3]
    assert np.sqrt(((moved - X[3]) ** 2).sum(1).mean()) < 0.003


def test_synthetic_scene_rigid_motion():
    """The brief's scene (12 frames at the default 30 fps): every pair within 1° / 5 mm."""
    s, X, K_true = _scene()
    P, ratio = poses.pose_table(X, s.faces, load_config()["poses"])
    rot, trans = _pair_errors(P, K_true, X)
    assert rot.max() <= 1.0, (np.median(rot), rot.max())
    assert trans.max() <= 0.005, (np.median(trans), trans.max())


def test_synthetic_rigid_core_over_the_whole_motion():
    """A body whose only deformation is the local belly bulge (a genuinely rigid core), sampled
    over 8 s of its motion (12 frames at 1.5 fps): every pair within 1° / 5 mm."""
    s, X, K_true = _scene("core", fps=1.5)
    P, ratio = poses.pose_table(X, s.faces, load_config()["poses"])
    rot, trans = _pair_errors(P, K_true, X)
    assert rot.max() <= 1.0 and trans.max() <= 0.005, (rot.max(), trans.max())


def _true_inlier_ratio(X, K_true, thresh):
    i, j = np.triu_indices(X.shape[0], 1)
    K = K_true[i, j]
    moved = np.einsum("pab,pvb->pva", K[:, :3, :3], X[i]) + K[:, None, :3, 3]
    return (np.linalg.norm(moved - X[j], axis=-1) < thresh).mean(1)


def test_full_deformation_ransac_finds_the_largest_rigid_part():
    """With bend, twist and squash over the whole motion, RANSAC's consensus set is at least as
    large as the true object motion's."""
    s, X, K_true = _scene(fps=1.5)
    T, ratio = poses.pairwise_ransac(X, seed=0)
    true = _true_inlier_ratio(X, K_true, 0.01)
    assert np.median(ratio - true) >= 0.0 and (ratio >= true - 0.02).mean() >= 0.9


def test_full_deformation_matches_object_frame_over_the_whole_motion():
    """The procedural body deforms above its waist only; its rigid lower half is what RANSAC
    finds, so K matches the object-frame motion over 8 s of bending, twisting and squashing."""
    s, X, K_true = _scene(fps=1.5)
    P, _ = poses.pose_table(X, s.faces, load_config()["poses"])
    rot, trans = _pair_errors(P, K_true, X)
    assert rot.max() <= 1.0 and trans.max() <= 0.005


def test_write_pose_table_store(tmp_path, caplog):
    s, X, K_true = _scene(n_frames=4)
    scene = tmp_path / "scene.zarr"
    with create_store(scene, "scene", attrs={"frame_ids": [10, 11, 12, 13]}) as w:
        w.write("template/faces", s.faces)
        w.write("truth/vertices", X)
    out = tmp_path / "poses.zarr"
    with caplog.at_level(logging.INFO, logger="stex.poses"):
        write_pose_table(scene, out, load_config()["poses"], array="truth/vertices")
    assert any("6 / 6 pairs" in r.getMessage() for r in caplog.records)
    g = open_store(out, "poses")
    # the sparse layout: every pair of 4 frames is kept (nearest_frames >= T - 1)
    assert g["pairs"][...].tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    assert g["poses"].shape == (6, 4, 4) and g["neighbours"][...].tolist() == [[0, 1, 2, 3]] * 4
    assert g["inlier_ratio"].dtype == np.float32 and g["descriptors"].shape[0] == 4
    assert g.attrs["frame_ids"] == [10, 11, 12, 13] and g.attrs["vertices_array"] == "truth/vertices"
    assert g.attrs["params"]["inlier_threshold_m"] == 0.005
    P, r = poses.pose_table(X.astype(np.float32), s.faces, load_config()["poses"])  # stored as float32
    i, j = np.triu_indices(4, 1)
    np.testing.assert_array_equal(g["poses"][...], P[i, j])
    np.testing.assert_array_equal(g["inlier_ratio"][...], r[i, j])
    # vertices from another store, faces from the scene store (as for the tracking artifact)
    other = tmp_path / "other.zarr"
    with create_store(other, "scene", attrs={"frame_ids": [10, 11, 12, 13]}) as w:
        w.write("given/vertices", X)
    write_pose_table(other, tmp_path / "p2.zarr", load_config()["poses"], array="given/vertices", faces=scene)
    g2 = open_store(tmp_path / "p2.zarr", "poses")
    np.testing.assert_array_equal(g2["poses"][...], P[i, j])
    assert g2.attrs["vertices_array"] == "given/vertices"
    with pytest.raises(ValueError, match="no array 'nope'"):
        write_pose_table(scene, tmp_path / "x.zarr", array="nope")
    assert not (tmp_path / "x.zarr").exists()
    # a chunk cut short is named (zarr's own error named neither the store nor the array)
    chunk = sorted((scene / "truth" / "vertices" / "c").rglob("*"))[-1]
    chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])
    with pytest.raises(StoreError, match=r"scene\.zarr: array 'truth/vertices' cannot be read \(chunk file"):
        write_pose_table(scene, tmp_path / "x.zarr", load_config()["poses"], array="truth/vertices")
    assert not (tmp_path / "x.zarr").exists()


def test_read_vertices_never_falls_back_to_the_truth(tmp_path):
    """A store holding only the true vertices gives no poses unless the truth is asked for by name:
    a library user who names no array is not handed the ground truth in place of the tracking."""
    s, X, _ = _scene(n_frames=3)
    scene = tmp_path / "scene.zarr"
    with create_store(scene, "scene", attrs={"frame_ids": [0, 1, 2]}) as w:
        w.write("template/faces", s.faces)
        w.write("truth/vertices", X)
    with pytest.raises(ValueError, match="no array 'vertices'"):
        read_vertices(scene)
    with pytest.raises(ValueError, match="no array 'vertices'"):
        write_pose_table(scene, tmp_path / "p.zarr", load_config()["poses"])
    assert not (tmp_path / "p.zarr").exists()
    got, faces, ids, name = read_vertices(scene, "truth/vertices")
    assert name == "truth/vertices" and ids == [0, 1, 2] and faces.shape == s.faces.shape
    np.testing.assert_array_equal(got, X.astype(np.float32))


def test_pose_table_refuses_inputs_it_cannot_pose():
    faces = np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"vertices: no frames"):       # was numpy's "need at least one array"
        poses.pose_table(np.zeros((0, 3, 3)), faces)
    with pytest.raises(ValueError, match=r"at least 3 vertices"):
        poses.pose_table(np.zeros((2, 2, 3)), faces)
    bad = np.random.default_rng(0).normal(size=(2, 3, 3))
    bad[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"frame 1 has non-finite"):
        poses.pose_table(bad, faces)


def _noisy_rigid_pair(seed, sigma, n=300, n_out=0):
    """Frame 0: n points in a 20 cm cube 1 m from the camera; frame 1: moved rigidly, with
    Gaussian noise sigma and the first n_out points displaced by ~10 cm (outliers)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    P = rng.uniform(-0.1, 0.1, (n, 3)) + [0.0, 0.0, 1.0]
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    Q = P @ R.T + [0.05, -0.02, 0.1] + rng.normal(0, sigma, P.shape)
    out = np.arange(n) < n_out
    Q[out] += rng.normal(0, 0.06, (n_out, 3)) + 0.05
    return P, Q, out


def _least_squares_fit(P, Q):
    """Independent reference: scipy's optimal rotation between the centred sets (Kabsch)."""
    from scipy.spatial.transform import Rotation

    pc, qc = P.mean(0), Q.mean(0)
    R = Rotation.align_vectors(Q - qc, P - pc)[0].as_matrix()
    return poses.to_matrix(R, qc - R @ pc)


def test_ransac_refits_its_inliers_among_all_vertices():
    """The best 3-point hypothesis is refitted (least squares) on its inliers among all
    vertices: with 1 mm noise the result is the least-squares fit of the inliers, to rounding,
    not the noisy 3-point hypothesis (which is off by ~0.1°)."""
    P, Q, out = _noisy_rigid_pair(5, 0.001, n_out=90)
    T, mask = poses.ransac_rigid(P, Q, n_iter=200, inlier_thresh_m=0.01)
    assert np.array_equal(mask, ~out)
    np.testing.assert_allclose(T, _least_squares_fit(P[~out], Q[~out]), atol=1e-9)
    Tb, ratio = poses.pairwise_ransac(np.stack([P, Q]), n_iter=200, inlier_thresh_m=0.01)
    np.testing.assert_allclose(Tb[0], _least_squares_fit(P[~out], Q[~out]), atol=1e-9)
    assert ratio[0] == pytest.approx(0.7, abs=1e-6)


def test_inlier_ratio_is_counted_after_icp():
    """inlier_ratio[t, t'] is the fraction of vertices within θ of their partner under the
    returned pose, i.e. after the ICP refinement, not at the RANSAC pose it started from. With
    noise of the order of θ many vertices sit near the threshold, so the two counts differ."""
    P, F = _body(32, 16)
    rng = np.random.default_rng(6)
    X = np.stack([P, P @ _random_rotation(rng, 10.0).T + [0.02, 0.0, 0.01]
                  + rng.normal(0, 0.003, P.shape)])
    A, ratio = poses.pose_table(X, F, {"inlier_threshold_m": 0.005, "icp_threshold_m": 0.005,
                                       "icp_iterations": 5})
    for t, u in ((0, 1), (1, 0)):
        moved = X[t] @ A[t, u, :3, :3].T + A[t, u, :3, 3]
        brute = (np.linalg.norm(moved - X[u], axis=1) < 0.005).mean()
        assert ratio[t, u] == pytest.approx(brute, abs=0.5 / P.shape[0])


def test_no_rigid_hypothesis_falls_back_to_the_centroid_shift():
    """When no 3-vertex sample keeps its distances (frame 1 is frame 0 scaled by 2: nothing
    moves rigidly), the pose is the translation by the centroid difference, R = I, and no
    vertex is an inlier (each lands 10 cm from its partner: p + c − 2p = c − p on a 10 cm
    sphere about c)."""
    rng = np.random.default_rng(7)
    d = rng.normal(size=(200, 3))
    c = np.array([0.1, -0.05, 1.0])
    P = c + 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)
    T, mask = poses.ransac_rigid(P, 2 * P, n_iter=100, inlier_thresh_m=0.01)
    np.testing.assert_allclose(T, poses.to_matrix(np.eye(3), P.mean(0)), atol=1e-12)
    assert not mask.any()
    Tb, ratio = poses.pairwise_ransac(np.stack([P, 2 * P]), n_iter=100, inlier_thresh_m=0.01)
    np.testing.assert_allclose(Tb[0], T, atol=1e-12)
    assert ratio[0] == 0.0


def test_pose_error_by_hand():
    """pose_error: the angle of R_estᵀ R_true, and the distance between where the two transforms
    put the point c (default the origin, i.e. ‖t_est − t_true‖), every axis counted."""
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T_est = poses.to_matrix(Rz90, [0.0, 0.0, 0.5])
    T_true = np.eye(4)
    rot, trans = poses.pose_error(T_est, T_true)
    assert rot == pytest.approx(90.0) and trans == pytest.approx(0.5)
    # c = (1, 0, 0): K_est c = (0, 1, 0.5), K_true c = (1, 0, 0)
    rot, trans = poses.pose_error(T_est, T_true, center=[1.0, 0.0, 0.0])
    assert trans == pytest.approx(np.sqrt(2.25))
    rot, trans = poses.pose_error(np.stack([T_true, T_est]), np.stack([T_true, T_true]))
    np.testing.assert_allclose(rot, [0.0, 90.0], atol=1e-6)
    np.testing.assert_allclose(trans, [0.0, 0.5])


def test_ransac_refit_is_a_rotation_even_when_a_reflection_fits_better():
    """The inlier refit (Kabsch on the sums) must return a proper rotation. An octahedron with
    half-axes 3, 2, 1 m and its mirror image in z: every vertex is an inlier (θ = 100 m), and
    H = Σ p qᵀ = diag(18, 8, −2). The unconstrained fit is the mirror diag(1, 1, −1), which
    matches exactly; the best rotation, V diag(1, 1, det) Uᵀ, is the identity (the z vertices
    then miss by 2 m each; any other rotation misses more)."""
    P = np.array([[3.0, 0, 0], [-3, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 1], [0, 0, -1]])
    Q = P * [1.0, 1.0, -1.0]
    T, inliers = poses.ransac_rigid(P, Q, n_iter=50, inlier_thresh_m=100.0)
    assert inliers.all()
    np.testing.assert_allclose(T, np.eye(4), atol=1e-12)
