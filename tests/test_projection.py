"""Projection stage: Φ against OpenCV, visibility on the tiny synthetic scene, the store."""
import cv2
import numpy as np
import pytest
from scipy import ndimage

from conftest import run_stages, tiny_scene_config
from stex.camera import Calibration, transform_points
from stex.io import FrameSequence, open_store
from stex.projection import project_frame
from stex.stages.projection import projection_overlay, write_projection
from stex.render import face_normals, rasterize


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Scene, frames, truth, masks (GrabCut), template and 'given' tracking of the tiny scene."""
    cfg = tiny_scene_config()
    d = tmp_path_factory.mktemp("proj")
    paths = run_stages(cfg, d)
    frames, truth, masks = paths["frames"], paths["truth"], paths["masks"]
    scene = open_store(paths["scene"], "scene")
    tracking = open_store(d / "tracking.zarr", "tracking")
    return {
        "dir": d, "cfg": cfg, "params": cfg["projection"], "masks_paths": masks,
        "cal": Calibration.from_dict(scene.attrs["calibration"]),
        "faces": np.asarray(open_store(d / "template.zarr", "template")["faces"][...], np.int64),
        "vertices": np.asarray(tracking["vertices"][...], np.float64),
        "frame_ids": list(tracking.attrs["frame_ids"]),
        "frames": FrameSequence(frames, "frames"),
        "truth": FrameSequence(truth, "truth"),
        "masks": FrameSequence(masks, "masks"),
    }


def _frame(tiny, k, **over):
    p = dict(tiny["params"], **over)
    fid = tiny["frame_ids"][k]
    mask = tiny["masks"].read("mask", fid) if p["use_mask"] else None
    return project_frame(tiny["vertices"][k], tiny["faces"], tiny["cal"], p, mask)


def _face_areas(V, F):
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def test_phi_matches_opencv_projectpoints(tiny):
    cal = tiny["cal"]
    T = cal.depth_to_color
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    for k in range(len(tiny["frame_ids"])):
        r = _frame(tiny, k)
        ref, _ = cv2.projectPoints(tiny["vertices"][k], rvec, T[:3, 3], cal.color.K, np.zeros(5))
        assert r["phi"].dtype == np.float32 and r["phi"].shape == (len(tiny["vertices"][k]), 2)
        assert np.abs(r["phi"] - ref[:, 0]).max() < 1e-4


def test_visibility_against_the_truth(tiny):
    F = tiny["faces"]
    for k, fid in enumerate(tiny["frame_ids"]):
        r = _frame(tiny, k)
        V = tiny["vertices"][k]
        # visible vertices land on the object (true mask, 1 px of slack for the rounding)
        true_mask = ndimage.binary_dilation(tiny["truth"].read("mask", fid), iterations=1)
        uv = np.floor(r["phi"][r["vertex_visible"]] + 0.5).astype(int)
        assert true_mask[uv[:, 1], uv[:, 0]].all()
        # about a third of the surface is seen (the scene's design)
        area = _face_areas(V, F)
        frac = area[r["face_visible"]].sum() / area.sum()
        assert 0.2 <= frac <= 0.45, (fid, frac)
        # faces turned away from the colour camera are never visible
        Xc = transform_points(tiny["cal"].depth_to_color, V)
        n = face_normals(Xc, F)
        cen = Xc[F].mean(axis=1)
        away = (n * cen).sum(1) / np.linalg.norm(cen, axis=1) > 0.02
        assert away.sum() > 0.3 * len(F)
        assert not (r["face_visible"] & away).any()
        # a face is visible only with its three vertices
        assert r["vertex_visible"][F[r["face_visible"]]].all()
        for key in ("vertex_cos", "face_cos"):
            assert r[key].dtype == np.float32 and r[key].min() >= 0 and r[key].max() <= 1
        assert (r["face_cos"][r["face_visible"]] > 0).all()
        assert (r["vertex_cos"][r["vertex_visible"]] > 0).all()


def test_glimpsed_faces_are_on_the_object(tiny):
    """face_glimpsed adds faces the image shows although a corner fails the vertex rule."""
    F, cal = tiny["faces"], tiny["cal"]
    extra = 0
    for k, fid in enumerate(tiny["frame_ids"]):
        r = _frame(tiny, k)
        g, vis = r["face_glimpsed"], r["face_visible"]
        assert g.dtype == bool and not (vis & ~g).any()
        only = g & ~vis
        extra += only.sum()
        assert not r["vertex_visible"][F[only]].all(axis=1).any()   # else they would be visible
        assert (r["face_cos"][only] > 0).all()
        # their centroid is on the object (true silhouette, 1 px of slack) and the mesh's own
        # render shows most of them
        cen = np.floor(r["phi"][F[only]].mean(axis=1) + 0.5).astype(int)
        true_mask = ndimage.binary_dilation(tiny["truth"].read("mask", fid), iterations=1)
        assert true_mask[cen[:, 1], cen[:, 0]].all()
        Xc = transform_points(cal.depth_to_color, tiny["vertices"][k])
        shown = np.unique(rasterize(Xc, F, cal.color.K, cal.color.width, cal.color.height).face_id)
        # (measured 71-75 %; the rest are sliver faces on the silhouette, thinner than a pixel,
        # which own no pixel of the face-id buffer; front-facing faces not glimpsed: 49-60 %)
        assert np.isin(np.flatnonzero(only), shown).mean() >= 0.65
        # nothing is glimpsed where the mask holds no object
        empty = project_frame(tiny["vertices"][k], F, cal, tiny["params"],
                              np.zeros_like(tiny["masks"].read("mask", fid)))
        assert not empty["face_glimpsed"].any()
    assert extra > 0


def test_far_side_is_occluded_not_only_back_facing(tiny):
    # the depth test matters: some front-facing faces are hidden behind the body's bend
    r = _frame(tiny, 0, use_mask=False, margin_px=0)
    nodepth = _frame(tiny, 0, use_mask=False, margin_px=0, depth_tol_m=10.0)
    assert not (r["face_visible"] & ~nodepth["face_visible"]).any()
    assert nodepth["face_visible"].sum() > r["face_visible"].sum()


def test_mask_changes_only_the_silhouette(tiny):
    erode = tiny["params"]["mask_erode_px"]
    for k, fid in enumerate(tiny["frame_ids"]):
        with_mask = _frame(tiny, k)
        without = _frame(tiny, k, use_mask=False)
        assert not (with_mask["vertex_visible"] & ~without["vertex_visible"]).any()
        assert not (with_mask["face_visible"] & ~without["face_visible"]).any()
        dropped = without["vertex_visible"] & ~with_mask["vertex_visible"]
        # distance of each pixel to the mask's outside: dropped vertices sit near the silhouette
        inside_dist = ndimage.distance_transform_edt(tiny["masks"].read("mask", fid))
        uv = np.floor(without["phi"][dropped] + 0.5).astype(int)
        assert (inside_dist[uv[:, 1], uv[:, 0]] <= erode + 4).all()
        # (on this 200x150 image the object is ~45 px wide, so the eroded band holds a third of
        # the visible vertices; at 2048x1536 it is a few per cent)
        assert 0 < dropped.sum() < 0.5 * without["vertex_visible"].sum()
        # the rest is untouched
        assert np.array_equal(with_mask["phi"], without["phi"])
        assert np.array_equal(with_mask["face_cos"], without["face_cos"])


def test_margin(tiny):
    cal = tiny["cal"]
    r = _frame(tiny, 2, use_mask=False, margin_px=70)
    u, v = r["phi"][r["vertex_visible"]].T
    assert (u >= 70).all() and (u <= cal.color.width - 71).all()
    assert (v >= 70).all() and (v <= cal.color.height - 71).all()
    assert r["vertex_visible"].sum() < _frame(tiny, 2, use_mask=False, margin_px=0)["vertex_visible"].sum()


def test_cos_modes(tiny):
    F = tiny["faces"]
    cal = tiny["cal"]
    k = 3
    view = _frame(tiny, k)
    axis = _frame(tiny, k, cos_mode="optical_axis")
    Xc = transform_points(cal.depth_to_color, tiny["vertices"][k])
    n = face_normals(Xc, F)
    front = view["face_cos"] > 0
    # optical_axis: cos = -n_z (camera looks along +z), only where the face faces its ray
    assert np.allclose(axis["face_cos"][front], np.clip(-n[front, 2], 0, 1), atol=1e-6)
    assert (axis["face_cos"][~front] == 0).all()
    # |n.d - n.e| <= |d - e| for the unit ray d and the axis e: small near the image centre
    cen = Xc[F].mean(axis=1)
    d = cen / np.linalg.norm(cen, axis=1, keepdims=True)
    bound = np.linalg.norm(d - [0, 0, 1], axis=1)
    diff = np.abs(view["face_cos"] - axis["face_cos"])[front]
    assert (diff <= bound[front] + 1e-5).all()
    assert diff.max() > 0.02
    # visibility: same depth test, so with min_cos = 0 the sets agree
    assert np.array_equal(view["face_visible"], axis["face_visible"])
    # a threshold selects different faces in the two modes
    v3 = _frame(tiny, k, min_cos=0.3)
    a3 = _frame(tiny, k, cos_mode="optical_axis", min_cos=0.3)
    assert (v3["face_visible"] != a3["face_visible"]).any()
    assert (v3["face_cos"][v3["face_visible"]] > 0.3).all()
    assert (a3["face_cos"][a3["face_visible"]] > 0.3).all()


def test_store_round_trip(tiny):
    proj = open_store(tiny["dir"] / "projection.zarr", "projection")
    T, V, nF = len(tiny["frame_ids"]), tiny["vertices"].shape[1], len(tiny["faces"])
    assert proj.attrs["frame_ids"] == tiny["frame_ids"]
    assert proj.attrs["params"]["margin_px"] == tiny["params"]["margin_px"]
    assert proj["phi"].shape == (T, V, 2) and proj["phi"].chunks == (1, V, 2)
    assert proj["face_visible"].shape == (T, nF) and proj["face_visible"].dtype == bool
    assert len(proj.attrs["visible_area_fraction"]) == T
    for k in (0, T - 1):
        r = _frame(tiny, k)
        for name, arr in r.items():
            assert np.array_equal(proj[name][k], arr), name
    # a subset of frames, without masks
    out = tiny["dir"] / "projection_sub.zarr"
    write_projection(tiny["dir"] / "tracking.zarr", tiny["dir"] / "template.zarr",
                     tiny["dir"] / "scene.zarr", [], dict(tiny["params"], use_mask=False), out,
                     frames=[1, 4])
    sub = open_store(out, "projection")
    assert sub.attrs["frame_ids"] == [1, 4]
    assert np.array_equal(sub["face_visible"][1], _frame(tiny, 4, use_mask=False)["face_visible"])


def test_errors(tiny):
    d = tiny["dir"]
    with pytest.raises(ValueError, match="no masks"):
        write_projection(d / "tracking.zarr", d / "template.zarr", d / "scene.zarr", [],
                         tiny["params"], d / "bad.zarr")
    with pytest.raises(ValueError, match="not tracked"):
        write_projection(d / "tracking.zarr", d / "template.zarr", d / "scene.zarr",
                         tiny["masks_paths"], tiny["params"], d / "bad.zarr", frames=[99])
    assert not (d / "bad.zarr").exists()
    # a tracking store of another run (here: its frames but the first) is named as such
    from stex.io import create_store

    with create_store(d / "other_tracking.zarr", "tracking", attrs={"frame_ids": tiny["frame_ids"][1:]}) as s:
        s.write("vertices", tiny["vertices"][1:].astype(np.float32))
        for name in ("residual_m", "depth_fit_m", "silhouette_iou", "seconds"):
            s.write(name, np.zeros(len(tiny["frame_ids"]) - 1))
        s.write("n_correspondences", np.zeros(len(tiny["frame_ids"]) - 1, np.int32))
    with pytest.raises(ValueError, match=r"other_tracking\.zarr: tracks frames .* but .*scene\.zarr has frames .*another run"):
        write_projection(d / "other_tracking.zarr", d / "template.zarr", d / "scene.zarr",
                         tiny["masks_paths"], tiny["params"], d / "bad.zarr")
    V = tiny["vertices"][0].copy()
    V[7] = [0.0, 0.0, -1.0]
    with pytest.raises(ValueError, match="vertex 7"):
        project_frame(V, tiny["faces"], tiny["cal"], dict(tiny["params"], use_mask=False))
    with pytest.raises(ValueError, match="cos_mode"):
        project_frame(tiny["vertices"][0], tiny["faces"], tiny["cal"], {"cos_mode": "x", "use_mask": False})


def test_preview(tiny, tmp_path):
    from stex.stages.projection import preview_projection
    out = tmp_path / "projection.png"
    preview_projection(sorted(tiny["dir"].glob("frames_*.zarr")), tiny["dir"] / "projection.zarr",
                       out, n_show=3)
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] == 960
    r = _frame(tiny, 0)
    pic = projection_overlay(tiny["frames"].read("color", 0), r["phi"], r["vertex_visible"],
                             r["vertex_cos"], size=200, title="t")
    assert pic.shape == (200, 200, 3) and pic.dtype == np.uint8


def _facing_grid(us, vs):
    """A flat grid 1 m in front of a 100 x 100 colour camera (f = 100 px, centre 49.5; depth and
    colour cameras coincide) whose vertex (i, j) projects exactly onto pixel (us[j], vs[i]);
    faces wound to face the camera. Returns vertices, faces, calibration."""
    K = np.array([[100.0, 0.0, 49.5], [0.0, 100.0, 49.5], [0.0, 0.0, 1.0]])
    from stex.camera import Intrinsics

    cam = Intrinsics(K, 100, 100)
    U, Vv = np.meshgrid(np.asarray(us, float), np.asarray(vs, float))
    V = np.stack([(U.ravel() - 49.5) / 100, (Vv.ravel() - 49.5) / 100, np.ones(U.size)], 1)
    n, F = len(us), []
    for i in range(len(vs) - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a + n + 1, a + 1, a], [a + n, a + n + 1, a]]
    return V, np.array(F), Calibration(cam, cam, np.eye(4))


def test_margin_bounds_are_inclusive_on_both_sides():
    """The projection must lie in u ∈ [m, Wc-1-m], v ∈ [m, Hc-1-m] (module docstring): with
    m = 10 on a 100 px image, vertices at 10 and 89 are inside, at 9.5 and 89.5 outside. Faces
    with a corner outside the margin are not glimpsed either (the face's own test passes)."""
    p = {"use_mask": False, "margin_px": 10}
    V, F, cal = _facing_grid([0, 10, 49.5, 89, 99], [0, 10, 49.5, 89, 99])
    r = project_frame(V, F, cal, p)
    inner = np.zeros((5, 5), bool)
    inner[1:4, 1:4] = True
    np.testing.assert_array_equal(r["vertex_visible"].reshape(5, 5), inner)
    corners_in = inner.ravel()[F].all(axis=1)
    assert corners_in.sum() == 8
    np.testing.assert_array_equal(r["face_visible"], corners_in)
    np.testing.assert_array_equal(r["face_glimpsed"], corners_in)
    assert (r["face_cos"] > 0.8).all()                 # every face faces the camera
    V, F, cal = _facing_grid([0, 9.5, 49.5, 89.5, 99], [0, 9.5, 49.5, 89.5, 99])
    r = project_frame(V, F, cal, p)
    only_centre = np.zeros((5, 5), bool)
    only_centre[2, 2] = True
    np.testing.assert_array_equal(r["vertex_visible"].reshape(5, 5), only_centre)
    assert not r["face_glimpsed"].any()


def test_mask_is_read_at_the_nearest_pixel():
    """The mask is looked up at the nearest pixel of the projection (integer = pixel centre): a
    vertex at u = 30.6 reads column 31, one at u = 70.4 column 70."""
    V, F, cal = _facing_grid([0, 10, 30.6, 49.5, 70.4, 89, 99], [0, 10, 49.5, 89, 99])
    mask = np.ones((100, 100), bool)
    mask[:, [30, 70]] = False
    r = project_frame(V, F, cal, {"use_mask": True, "mask_erode_px": 0, "margin_px": 10}, mask)
    vis = r["vertex_visible"].reshape(5, 7)
    assert vis[1:4, 2].all()                            # column 31: in the mask
    assert not vis[:, 4].any()                          # column 70: outside
    assert vis[1:4, [1, 3, 5]].all()


def test_min_cos_applies_to_vertices():
    """A vertex is visible only with cos > min_cos. On a flat grid facing the camera 1 m away the
    view-ray cosine of the point (x, y, 1) is 1 / sqrt(1 + x² + y²)."""
    us = [0, 10, 30, 49.5, 70, 89, 99]
    V, F, cal = _facing_grid(us, us)
    r = project_frame(V, F, cal, {"use_mask": False, "margin_px": 10, "min_cos": 0.9})
    cos = 1 / np.sqrt(1 + V[:, 0] ** 2 + V[:, 1] ** 2)
    np.testing.assert_allclose(r["vertex_cos"], cos, atol=1e-5)
    inside = np.isin(np.round(r["phi"]), [10, 30, 50, 70, 89]).all(axis=1)
    want = inside & (cos > 0.9)
    assert want.sum() == 21           # 5 x 5 inside the margin less the 4 corners (x² + y² = 0.31)
    np.testing.assert_array_equal(r["vertex_visible"], want)


def test_min_cos_applies_to_faces_by_their_own_cosine():
    """A face's own test needs its cosine (view ray from its centroid) > min_cos too. Inside the
    margin, at min_cos 0.91, two faces fail it and no other test: in the two corner cells the
    diagonal does not cut, the face holding the grid's corner (centroid x² + y² = 0.218, cos
    0.906); the other corner faces are seen at 0.922 or more. They are not glimpsed (flat grid, no
    mask). The visible set alone would not show it: their corner vertex fails min_cos as well."""
    us = [0, 10, 30, 49.5, 70, 89, 99]
    V, F, cal = _facing_grid(us, us)
    r = project_frame(V, F, cal, {"use_mask": False, "margin_px": 10, "min_cos": 0.91})
    centroid = V[F].mean(axis=1)
    cos = 1 / np.linalg.norm(centroid, axis=1)          # the grid's normal is the camera's axis
    np.testing.assert_allclose(r["face_cos"], cos, atol=1e-5)
    inside = np.isin(np.round(r["phi"]), [10, 30, 50, 70, 89]).all(axis=1)[F].all(axis=1)
    want = inside & (cos > 0.91)
    assert inside.sum() == 32 and want.sum() == 30
    np.testing.assert_array_equal(r["face_glimpsed"], want)
