"""Observations stage: grey samples per face and edge, and the E_qual flags."""
import numpy as np
import pytest

from stex.image import grey_float32 as grey
from stex.observations import (blur_cost, blurred_faces, edge_samples, face_centroids, face_motion,
                               face_samples, slanted_faces, theta_b_for_width)
from stex.texcoords import SAMPLE_BARY


def _ramp(h=40, w=60):
    """Grey image whose value is the column index (a linear ramp, exact under bilinear lookup)."""
    return np.tile(np.arange(w, dtype=np.float32), (h, 1))


def test_face_samples_follow_the_coordinates():
    img = _ramp()
    coords = np.array([[10.0, 5.0], [30.0, 8.0], [20.0, 30.0], [50.0, 20.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    out = face_samples(img, coords, faces, np.array([True, False]))
    want = SAMPLE_BARY @ coords[faces[0], 0]
    assert out.dtype == np.uint8 and out.shape == (2, 15)
    assert np.abs(out[0].astype(float) - want).max() <= 0.5
    assert not out[1].any()                       # invisible face: zeros


def test_edge_samples_run_from_first_to_second_vertex():
    img = _ramp()
    coords = np.array([[8.0, 5.0], [40.0, 9.0], [0.0, 0.0]])
    out = edge_samples(img, coords, np.array([[0, 1], [1, 2]]), np.array([True, True, False]))
    assert np.allclose(out[0], np.linspace(8, 40, 9), atol=0.5)
    assert not out[1].any()                       # vertex 2 invalid


def test_grey_is_luma():
    img = np.zeros((2, 2, 3), np.uint8)
    img[0, 0] = (255, 0, 0)
    img[1, 1] = (255, 255, 255)
    g = grey(img)
    assert g[0, 0] == pytest.approx(0.299 * 255, abs=1e-3) and g[1, 1] == pytest.approx(255, abs=1e-3)


def test_blur_step_and_missing_neighbours():
    T, F = 5, 2
    c = np.zeros((T, F, 2))
    c[:, 0, 0] = [0, 5, 10, 40, 70]               # face 0: slow, then fast (30 px/frame)
    vis = np.ones((T, F), bool)
    vis[3, 1] = False                             # face 1 unseen at frame 3
    b = blurred_faces(c, vis, theta_b_px=20)
    assert b[0].all() and b[-1][vis[-1]].all()    # sequence ends count as blurred
    assert not b[1, 0] and b[3, 0]                # mean move 5 px vs 30 px
    assert b[2, 1] and b[4, 1] and not b[1, 1]    # neighbours of the unseen frame
    assert not b[3, 1]                            # not visible: not a candidate, not flagged


def test_graded_blur_cost_ranks_frames_the_step_cannot():
    T, F = 5, 1
    c = np.zeros((T, F, 2))
    c[:, 0, 0] = [0, 4, 12, 20, 40]               # moves 4, 8, 8, 20 px between frames
    vis = np.ones((T, F), bool)
    m = face_motion(c, vis)
    assert np.isnan(m[0, 0]) and np.isnan(m[-1, 0])
    assert m[1:4, 0].tolist() == pytest.approx([6.0, 8.0, 14.0])
    step = blur_cost(m, vis, 5.0, "step")
    assert step[:, 0].tolist() == [1, 1, 1, 1, 1]  # all above θ_b or unknown: the step cannot choose
    graded = blur_cost(m, vis, 5.0, "graded", cap=2.0)
    assert graded[:, 0].tolist() == pytest.approx([2.0, 1.2, 1.6, 2.0, 2.0])  # 14/5 capped; unknown = cap
    vis[2, 0] = False
    m = face_motion(c, vis)
    assert np.isnan(m[1:4, 0]).all()              # the unseen frame and both its neighbours
    assert blur_cost(m, vis, 5.0, "graded")[:, 0].tolist() == [2, 2, 0, 2, 2]
    assert blur_cost(m, vis, 5.0, "step")[2, 0] == 0
    assert (blurred_faces(c, vis, 5.0) == (blur_cost(m, vis, 5.0, "step") > 0)).all()
    with pytest.raises(ValueError, match="blur_rule"):
        blur_cost(m, vis, 5.0, "smooth")


def test_measured_motion_ignores_the_neighbours_visibility():
    c = np.zeros((5, 1, 2))
    c[:, 0, 1] = [0, 2, 4, 10, 16]                # moves 2, 2, 6, 6 px between frames
    vis = np.ones((5, 1), bool)
    vis[3, 0] = False
    authors = face_motion(c, vis, "unknown")
    ours = face_motion(c, vis, "measured")
    assert np.isnan(authors[[0, 2, 4], 0]).all() and authors[1, 0] == pytest.approx(2.0)
    assert ours[:, 0][[0, 1, 2, 4]].tolist() == pytest.approx([2.0, 2.0, 4.0, 6.0])  # ends: one side
    assert np.isnan(ours[3, 0])                   # not visible: never a candidate
    step = blur_cost(ours, vis, 3.0, "step")[:, 0].tolist()
    assert step == [0, 0, 1, 0, 1]                # frame 2 (4 px) blurred by its motion, not its neighbour
    assert blur_cost(authors, vis, 3.0, "step")[:, 0].tolist() == [1, 0, 1, 0, 1]
    with pytest.raises(ValueError, match="unseen_neighbours"):
        face_motion(c, vis, "guess")


def test_theta_b_scales_the_papers_threshold_to_the_colour_width():
    assert theta_b_for_width(None, 4096) == pytest.approx(20.0)     # the paper's images
    assert theta_b_for_width(None, 640) == pytest.approx(3.125)
    assert theta_b_for_width(7.5, 640) == 7.5                      # an explicit value wins
    c = np.zeros((3, 1, 2))
    c[:, 0, 0] = [0, 4, 8]                                          # 4 px per frame
    vis = np.ones((3, 1), bool)
    assert blurred_faces(c, vis, theta_b_for_width(None, 640))[1, 0]
    assert not blurred_faces(c, vis, theta_b_for_width(None, 2048))[1, 0]


def test_angle_rules():
    cos = np.array([[0.2, 0.5, 0.8]])
    assert slanted_faces(cos, 0.3, "paper").tolist() == [[True, True, False]]
    assert slanted_faces(cos, 0.3, "authors").tolist() == [[True, False, False]]
    with pytest.raises(ValueError, match="angle_rule"):
        slanted_faces(cos, 0.3, "other")


def test_bad_inputs():
    with pytest.raises(ValueError, match="face_visible"):
        face_samples(_ramp(), np.zeros((3, 2)), np.array([[0, 1, 2]]), np.ones(2, bool))
    with pytest.raises(ValueError, match="coords"):
        face_samples(_ramp(), np.zeros((2, 2)), np.array([[0, 1, 2]]), np.ones(1, bool))
    with pytest.raises(ValueError, match="centroids"):
        blurred_faces(np.zeros((3, 2, 2)), np.ones((3, 3), bool), 20)
    assert face_centroids(np.array([[0, 0], [3, 0], [0, 3.0]]), np.array([[0, 1, 2]])).tolist() == [[1, 1]]


def test_samples_follow_both_coordinates():
    """The lookups use the row coordinate v as well as the column u. The ramp of the tests above
    varies along u only, so a v taken from the wrong corner went unnoticed; on the plane
    g = u + 2 v (exact under bilinear interpolation inside the image) every sample must equal
    the plane at its interpolated position."""
    h, w = 40, 60
    img = (np.arange(w, dtype=np.float32)[None, :] + 2 * np.arange(h, dtype=np.float32)[:, None])
    coords = np.array([[10.0, 5.0], [30.0, 8.0], [20.0, 30.0], [50.0, 20.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    out = face_samples(img, coords, faces, np.ones(2, bool))
    plane = coords[:, 0] + 2 * coords[:, 1]
    want = SAMPLE_BARY @ plane[faces].T                      # (15, F)
    assert np.abs(out.astype(float) - want.T).max() <= 0.5
    e = edge_samples(img, coords, np.array([[0, 2], [3, 1]]), np.ones(4, bool))
    s = np.linspace(0, 1, 9)
    want_e = np.stack([(1 - s) * plane[0] + s * plane[2], (1 - s) * plane[3] + s * plane[1]])
    assert np.abs(e.astype(float) - want_e).max() <= 0.5


def test_grey_weights_each_channel():
    """grey is 0.299 R + 0.587 G + 0.114 B (BT.601); red and white alone do not tell G from B."""
    img = np.zeros((1, 3, 3), np.uint8)
    img[0, 0, 0] = img[0, 1, 1] = img[0, 2, 2] = 200
    np.testing.assert_allclose(grey(img)[0], [59.8, 117.4, 22.8], atol=1e-3)


def test_thresholds_are_inclusive_or_strict_as_documented():
    """E_qual's steps at their thresholds: a face is blurred when its motion *exceeds* θ_b (a
    motion of exactly θ_b is sharp), and slanted when cos ≤ 1 − θ_n (paper) or cos ≤ θ_n
    (authors), equality included. θ_n = 0.25 keeps 0.25 and 0.75 exact in float32."""
    c = np.zeros((3, 1, 2))
    c[:, 0, 0] = [0, 5, 10]                       # 5 px per frame at frame 1
    vis = np.ones((3, 1), bool)
    m = face_motion(c, vis)
    assert m[1, 0] == 5.0
    assert blur_cost(m, vis, 5.0, "step")[1, 0] == 0 and not blurred_faces(c, vis, 5.0)[1, 0]
    assert blur_cost(m, vis, 4.999, "step")[1, 0] == 1
    cos = np.array([[0.25, 0.75, 0.7501]])
    assert slanted_faces(cos, 0.25, "paper").tolist() == [[True, True, False]]
    assert slanted_faces(cos, 0.25, "authors").tolist() == [[True, False, False]]
