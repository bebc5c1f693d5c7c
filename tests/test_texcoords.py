"""Texture-coordinate optimisation: interpolation, energy, accuracy against the truth, the store."""
import copy

import numpy as np
import pytest

from conftest import TINY_SYNTHETIC, run_stages
from stex.camera import Calibration, transform_points
from stex.config import load_config
from stex.io import open_store
from stex.synth.scene import SyntheticScene
from stex.template import transfer_vertices
from stex.texcoords import (build_stack, interpolate_displacements, keyframe_positions,
                            optimize_texcoords, photometric_energy, texcoords_params, write_texcoords)

#: few iterations: the test budget (the defaults are the authors' 300 per level)
FAST = {"levels": 3, "iterations": 25, "refine_iterations": 25, "keyframe_step": 2,
        "gauge": "mean", "edge_mode": "vector", "edge_weight": 3.0}


def _project(cal, X):
    K = cal.color.K
    Xc = transform_points(cal.depth_to_color, X)
    return np.stack([K[0, 0] * Xc[..., 0] / Xc[..., 2] + K[0, 2], K[1, 1] * Xc[..., 1] / Xc[..., 2] + K[1, 2]], -1)


@pytest.fixture(scope="module")
def drifted(tmp_path_factory):
    """The tiny scene in 'given' mode with tracking drift, through the projection stage.

    8 frames at 4 fps (2 s, so the drift, which changes slowly in time, differs between frames;
    at 30 fps the 6 tiny frames would see the same drift, which photometric consistency cannot
    detect), drift amplitude 3 cm (≈ 5 px at fx 175)."""
    syn = copy.deepcopy(TINY_SYNTHETIC)
    syn.update(n_frames=8, fps=4.0, degradations={"tracking_drift": {"enabled": True, "amplitude_m": 0.03}})
    cfg = load_config(overrides={"scene": "tiny", "frame_block": 4, "source": {"kind": "synthetic", "synthetic": syn}})
    d = tmp_path_factory.mktemp("texcoords")
    paths = run_stages(cfg, d)
    frames, masks = paths["frames"], paths["masks"]
    scene = open_store(paths["scene"], "scene")
    write_texcoords(d / "scene.zarr", d / "template.zarr", d / "projection.zarr", frames, masks,
                    FAST, d / "texcoords.zarr")
    # the truth carried to the template topology, and the consensus bound (truth slid by the
    # per-vertex time-mean of the drift, in the object frame)
    tm = open_store(d / "template.zarr", "template")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    emb = (tm["embedding/face"][...], tm["embedding/bary"][...])
    F0 = scene["template/faces"][...]
    Vt = transfer_vertices(scene["truth/vertices"][...], F0, *emb)
    Vg = transfer_vertices(scene["given/vertices"][...], F0, *emb)
    sim = SyntheticScene(cfg["source"]["synthetic"])
    ids = list(scene.attrs["frame_ids"])
    R = np.array([sim.object_to_depth(sim.time_of(f))[:3, :3] for f in ids])
    drift_obj = np.einsum("tvi,tij->tvj", Vg - Vt, R)
    proj = open_store(d / "projection.zarr", "projection")
    valid = proj["vertex_visible"][...]
    w = valid[..., None].astype(float)
    mean_drift = (drift_obj * w).sum(0) / np.maximum(w.sum(0), 1)
    consensus = _project(cal, Vt + np.einsum("vj,tij->tvi", mean_drift, R))
    return {"dir": d, "frames": frames, "masks": masks, "cfg": cfg,
            "true": _project(cal, Vt), "consensus": consensus, "valid": valid,
            "phi": proj["phi"][...], "store": open_store(d / "texcoords.zarr", "texcoords")}


def test_keyframes_and_interpolation():
    assert keyframe_positions(10, 4).tolist() == [0, 4, 8]
    assert keyframe_positions(3, 1).tolist() == [0, 1, 2]
    T, V = 10, 3
    valid = np.ones((T, V), bool)
    valid[5, 1] = False            # vertex 1: runs [0, 5) and [6, 10)
    valid[:, 2] = False
    valid[1:4, 2] = True           # vertex 2: run [1, 4) without a key frame
    keys = keyframe_positions(T, 4)
    dk = np.zeros((3, V, 2))
    dk[:, 0, 0] = [0.0, 4.0, 8.0]
    dk[:, 1, 1] = [1.0, 3.0, -2.0]
    dk[:, 2] = 7.0
    out = interpolate_displacements(dk, keys, valid)
    assert out.shape == (T, V, 2) and out.dtype == np.float64
    np.testing.assert_allclose(out[:9, 0, 0], np.arange(9.0))         # linear between keys
    assert out[9, 0, 0] == 8.0                                        # held after the last
    np.testing.assert_allclose(out[:5, 1, 1], [1.0, 1.5, 2.0, 2.5, 3.0])
    assert out[5, 1, 1] == 0.0                                        # not visible
    np.testing.assert_allclose(out[6:, 1, 1], [-2.0] * 4)  # run [6, 10): only key 8, held on both sides
    assert not out[:, 2].any()                                        # a run without a key frame


def test_params():
    # defaults come from the schema, as the workflow fills them
    assert texcoords_params(None) == load_config()["texcoords"]
    assert texcoords_params(None)["samples_per_face"] == 15
    with pytest.raises(ValueError, match="nope"):
        texcoords_params({"nope": 1})
    with pytest.raises(ValueError):
        texcoords_params({"samples_per_face": 16})


def _toy(shift):
    """A textured square of 2 triangles seen in 2 frames; frame 1's image is shifted by
    ``shift`` px but its Φ is not: the optimum moves ξ_1 by ``shift``."""
    rng = np.random.default_rng(0)
    import cv2
    base = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)).astype(np.float32), (0, 0), 2.0)
    base = (base - base.min()) / (base.max() - base.min()) * 255
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    imgs = [base, cv2.warpAffine(base, M, (160, 120), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)]
    imgs = [np.clip(np.rint(i), 0, 255).astype(np.uint8) for i in imgs]
    ys, xs = np.mgrid[30:91:10, 40:121:10]
    V = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    nx = xs.shape[1]
    F = []
    for r in range(xs.shape[0] - 1):
        for c in range(nx - 1):
            i = r * nx + c
            F += [(i, i + 1, i + nx + 1), (i, i + nx + 1, i + nx)]
    F = np.array(F)
    phi = np.stack([V, V])
    valid = np.ones((2, len(V)), bool)
    fvis = np.ones((2, len(F)), bool)
    fcos = np.ones((2, len(F)))
    mask = np.ones((120, 160), bool)
    return (lambda t: (imgs[t], mask)), phi, valid, fvis, fcos, F


def test_recovers_a_known_shift_and_energy_is_monotone():
    load, phi, valid, fvis, fcos, F = _toy((2.5, -1.5))
    r = optimize_texcoords(load, phi, valid, fvis, fcos, F, (160, 120),
                           dict(FAST, keyframe_step=1, iterations=60, refine_iterations=10), progress=False)
    # only the relative shift is observable: frame 1 relative to frame 0
    rel = (r["xi"][1] - r["xi"][0]).mean(0)
    np.testing.assert_allclose(rel, [2.5, -1.5], atol=0.15)
    for row in r["energy"]:
        e = row[~np.isnan(row)]
        assert len(e) >= 1 and np.all(np.diff(e) <= 0)
    assert r["energy"][0, 0] > 20 * np.nanmin(r["energy"][0])


def test_gauge_holds_the_mean_displacement():
    """gauge 'mean': the shift is shared by the frames (the mean of ξ − Φ over a vertex's frames
    stays 0), with the displacement-smoothness edge term (edge_mode 'vector')."""
    load, phi, valid, fvis, fcos, F = _toy((2.5, -1.5))
    r = optimize_texcoords(load, phi, valid, fvis, fcos, F, (160, 120),
                           dict(FAST, keyframe_step=1, iterations=60, refine_iterations=10,
                                gauge="mean", edge_mode="vector", edge_weight=3.0), progress=False)
    d = r["xi"].astype(np.float64) - phi
    np.testing.assert_allclose(d.mean(0), 0.0, atol=1e-3)
    np.testing.assert_allclose(d[1].mean(0), [1.25, -0.75], atol=0.1)
    for row in r["energy"]:
        e = row[~np.isnan(row)]
        assert np.all(np.diff(e) <= 0)
    assert r["energy"][0, 0] > 20 * np.nanmin(r["energy"][0])
    with pytest.raises(ValueError, match="gauge"):
        texcoords_params({"gauge": "median"})


def test_photometric_energy_zero_when_aligned():
    load, phi, valid, fvis, fcos, F = _toy((0.0, 0.0))
    st = build_stack(load, [0, 1], phi, valid, 8, 160, 120)
    st.set_blur(1)
    E, P = photometric_energy(st, phi, F, fvis, fcos)
    assert E < 1e-9 and P.shape == (len(F), 15)


def test_store(drifted):
    s = drifted["store"]
    T, V = drifted["phi"].shape[:2]
    assert s["xi"].shape == (T, V, 2) and s["xi"].dtype == np.float32
    np.testing.assert_array_equal(s["valid"][...], drifted["valid"])
    assert s["energy"].shape == (FAST["levels"] + 1, 26)
    assert s.attrs["keyframes"] == s.attrs["frame_ids"][::2]
    assert s.attrs["energy_rows"] == ["level 0", "level 1", "level 2", "refine"]
    xi = s["xi"][...]
    np.testing.assert_array_equal(xi[~drifted["valid"]], drifted["phi"][~drifted["valid"]])


def test_energy_monotone_per_level(drifted):
    E = drifted["store"]["energy"][...]
    for row in E:
        e = row[~np.isnan(row)]
        assert len(e) >= 2 and np.all(np.diff(e) <= 0)
        assert e[-1] < e[0]


def test_closer_to_the_truth(drifted):
    """ξ moves towards the true projection. Photometric consistency cannot see the part of the
    drift common to all frames (the 'consensus' bound); on the tiny scene (8 frames, 200x150)
    ξ removes most of the rest. Measured (FAST): |Φ−truth| 1.689 px → |ξ−truth| 0.732 px,
    |Φ−consensus| 1.597 px → |ξ−consensus| 0.340 px."""
    val = drifted["valid"]
    xi = drifted["store"]["xi"][...]

    def med(a, b):
        return float(np.median(np.linalg.norm(a - b, axis=-1)[val]))

    e_phi, e_xi = med(drifted["phi"], drifted["true"]), med(xi, drifted["true"])
    c_phi, c_xi = med(drifted["phi"], drifted["consensus"]), med(xi, drifted["consensus"])
    print(f"tiny: |Φ−truth| {e_phi:.3f} px |ξ−truth| {e_xi:.3f} px; |Φ−consensus| {c_phi:.3f} |ξ−consensus| {c_xi:.3f}")
    assert e_xi < 0.6 * e_phi      # the gauge keeps the unobservable part where Φ has it
    assert c_xi < 0.6 * c_phi


def test_deterministic(drifted, tmp_path):
    d = drifted["dir"]
    write_texcoords(d / "scene.zarr", d / "template.zarr", d / "projection.zarr", drifted["frames"],
                    drifted["masks"], FAST, tmp_path / "again.zarr")
    again = open_store(tmp_path / "again.zarr", "texcoords")
    np.testing.assert_array_equal(again["xi"][...], drifted["store"]["xi"][...])
    np.testing.assert_array_equal(again["energy"][...], drifted["store"]["energy"][...])


def test_displacement_picture():
    from stex.texcoords import displacement_picture
    color = np.full((120, 160, 3), 200, np.uint8)
    phi = np.array([[40.0, 60.0], [120.0, 60.0], [80.0, 100.0]])
    xi = phi + np.array([[2.0, 0.0], [0.0, -1.0], [0.0, 0.0]])
    valid = np.array([True, True, False])
    img = displacement_picture(color, phi, xi, valid, scale=10.0, spacing_px=0)
    assert img.shape == color.shape and img.dtype == np.uint8
    changed = np.any(img != img[60, 10], axis=-1)
    changed[:23] = False                                   # the caption bar
    # vertex 0: an arrow 20 px long to the right; vertex 1: 10 px up; vertex 2 not drawn
    assert changed[60, 45:58].all() and not changed[60, 64:75].any()
    assert changed[52:58, 120].all() and not changed[62:70, 120].any()
    assert not changed[90:110, 70:90].any()
    with pytest.raises(ValueError, match="color"):
        displacement_picture(color[..., 0], phi, xi, valid)
    with pytest.raises(ValueError, match="xi"):
        displacement_picture(color, phi, xi[:2], valid)
