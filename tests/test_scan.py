"""template.from_scan and template.align: a tiny synthetic turntable fused into a closed mesh near
the true surface, a template in another frame aligned to frame 0, and clear errors on bad scans."""
import numpy as np
import pytest

from stex.camera import mask_in_depth
from stex.config import section_params
from stex.io import open_store
from stex.masks import compute_mask
from stex.mesh import is_closed
from stex.scan import align_to_view, frame_points, fuse_scan, rotation_angle_deg, surface_distance
from stex.stages.scan import scan_capture, write_scan
from stex.synth.scene import SyntheticScene, rotation
from stex.synth.turntable import TurntableScene

# a small colour camera and the synthetic default depth camera (320x288: at 160x120 the depth
# pixels are 8 mm apart on the object and the frame-to-model ICP slides round the body's axis)
SMALL = {"color": {"width": 200, "height": 150, "fx": 175.0}, "texture_size": 128}
SOURCE = {"kind": "synthetic", "synthetic": SMALL}
SCAN = {"kind": "synthetic", "n_frames": 36, "voxel_m": 0.004}


def _template(**scan):
    return {"from_scan": True, "scan": dict(SCAN, **scan)}


def _turntable(n_frames: int) -> TurntableScene:
    synth = dict(section_params("source", SOURCE)["synthetic"], n_frames=n_frames)
    return TurntableScene(synth, section_params("template", {})["scan"]["elevation_deg"])


@pytest.fixture(scope="module")
def tiny_scan_path(tmp_path_factory):
    out = tmp_path_factory.mktemp("scan") / "scan.zarr"
    write_scan(_template(), SOURCE, {}, out)
    return out


@pytest.fixture(scope="module")
def tiny_scan(tiny_scan_path):
    return open_store(tiny_scan_path, "scan")


def test_a_turntable_scan_fuses_into_a_closed_mesh_near_the_true_surface(tiny_scan):
    V, F = tiny_scan["vertices"][...], tiny_scan["faces"][...]
    assert is_closed(V, F)
    scene = _turntable(SCAN["n_frames"])
    d = surface_distance(V, F, scene.true_vertices(0), scene.faces)
    assert d["mean"] < 0.003, d  # 36 frames 10 degrees apart, depth pixels 4 mm apart on the object
    assert tiny_scan["fused"][...].all()
    assert 330 < tiny_scan.attrs["turned_deg"] < 390
    # the poses found are the turntable's: frame k seen from frame 0
    T0 = scene.object_to_depth(0.0)
    errors = []
    for k, pose in enumerate(tiny_scan["poses"][...]):
        true = T0 @ np.linalg.inv(scene.object_to_depth(scene.time_of(k)))
        errors.append(rotation_angle_deg(true[:3, :3].T @ pose[:3, :3]))
    assert np.median(errors) < 3.0, errors


def test_a_template_in_another_frame_is_aligned_to_the_first_frame():
    synth = dict(section_params("source", SOURCE)["synthetic"], n_frames=1)
    scene = SyntheticScene(synth)
    r = scene.render_frame(0)
    mask, _ = compute_mask(r.color, r.depth_mm, scene.calibration, section_params("masks", {}))
    points = frame_points(r.depth_mm, mask_in_depth(mask, r.depth_mm, scene.calibration), r.color,
                          scene.calibration, 0.3, 1.6)[0]
    V = scene.true_vertices(0)
    G = np.eye(4)  # turned 90 degrees, moved 1 m
    G[:3, :3] = rotation("y", np.pi / 2)
    G[:3, 3] = [1.0, 0.0, 0.0]
    a = align_to_view(V @ G[:3, :3].T + G[:3, 3], scene.faces, points)
    E = a.transform @ G  # identity when the alignment undoes G
    assert rotation_angle_deg(E[:3, :3]) < 2.0
    moved = V @ E[:3, :3].T + E[:3, 3]
    assert np.linalg.norm(moved - V, axis=1).max() < 0.005
    assert a.fitness > 0.9


def test_a_scan_without_object_in_its_masks_is_refused(tmp_path):
    # the object's depth range excludes both the object (1 m) and the wall (2.2 m): every mask is empty
    with pytest.raises(ValueError, match=r"the scan has 0 frames with the object in their mask \(12 of its 12"):
        write_scan(_template(n_frames=12), SOURCE, {"depth_near_m": 1.5, "depth_far_m": 2.0}, tmp_path / "s.zarr")
    assert not (tmp_path / "s.zarr").exists()


def test_a_scan_with_too_few_frames_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"the scan has 3 frames with the object in their mask \(0 of its 3 frames have none\), fewer "
                                         r"than template.scan.min_frames = 10"):
        write_scan(_template(n_frames=3), SOURCE, {}, tmp_path / "s.zarr")


def test_a_scan_that_does_not_turn_is_refused():
    scene = _turntable(12)
    r = scene.render_frame(0)
    masks = section_params("masks", {})
    md = mask_in_depth(compute_mask(r.color, r.depth_mm, scene.calibration, masks)[0], r.depth_mm, scene.calibration)
    still = ((k, r.color, r.depth_mm, md) for k in range(12))  # the same view twelve times
    scan = section_params("template", {"scan": SCAN})["scan"]
    with pytest.raises(ValueError, match=r"turn the object by 0 degrees in total, less than template.scan.min_turn_deg"):
        fuse_scan(still, scene.calibration, scan, 0.3, 1.6)


def test_a_synthetic_scan_can_use_its_own_depth_mode():
    scan = section_params("template", {"scan": dict(SCAN, depth={"width": 64, "height": 48, "fx": 50.0})})["scan"]
    cal, n, frames, _ = scan_capture(scan, SOURCE)
    assert (cal.depth.width, cal.depth.height, cal.depth.fx) == (64, 48, 50.0)
    assert n == SCAN["n_frames"]
    _, color, depth, _ = next(frames(0, 1))
    assert depth.shape == (48, 64) and color.shape[:2] == (150, 200)  # the colour camera stays the source's
    default = section_params("template", {"scan": SCAN})["scan"]
    assert scan_capture(default, SOURCE)[0].depth.width == section_params("source", SOURCE)["synthetic"]["depth"]["width"]


def test_a_folder_or_mkv_scan_needs_a_path(tmp_path):
    with pytest.raises(ValueError, match=r"template.scan.path must name the scan's .mkv file"):
        write_scan({"from_scan": True, "scan": {"kind": "mkv"}}, SOURCE, {}, tmp_path / "s.zarr")


def test_the_template_stage_takes_the_scan_aligned_to_the_first_frame(tmp_path, tiny_scan_path):
    from stex.config import load_config
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.stages.masks import write_masks_block
    from stex.stages.template import write_template

    cfg = load_config(overrides={"scene": "scan", "frame_block": 2,  # a small atlas and mesh: fast
                                 "template": dict(_template(), atlas_size=256, target_faces=4000),
                                 "source": {"kind": "synthetic", "synthetic": dict(SMALL, n_frames=2)}})
    scene, frames, truth, masks = (tmp_path / f"{n}.zarr" for n in ("scene", "frames", "truth", "masks"))
    write_scene(cfg["source"], cfg["frame_block"], scene)
    write_frames_block(cfg["source"], 0, 2, frames, truth)
    write_masks_block(scene, frames, cfg["masks"], masks)
    out = tmp_path / "template.zarr"
    write_template(scene, cfg["template"], out, frames, masks, tiny_scan_path, masks_params=cfg["masks"])
    t = open_store(out, "template")
    assert t.attrs["origin"] == "scan"
    assert t.attrs["alignment"]["fitness"] > 0.6
    # the scan is the rest shape, frame 0 is slightly deformed (twist, squash, bulge): close, not equal
    truth0 = open_store(scene, "scene")["truth/vertices"][0]
    d = surface_distance(t["vertices"][...], t["faces"][...], truth0, SyntheticScene(
        dict(section_params("source", SOURCE)["synthetic"], n_frames=1)).faces)
    assert d["mean"] < 0.012, d


FOX = "/work/shared/data_samples/gltf_fox/glTF-Binary/Fox.glb"


@pytest.mark.parametrize("obj", ["procedural", "gltf"])
def test_the_turntable_turns_the_rest_pose_once_with_kinect_like_depth(obj):
    import os

    if obj == "gltf" and not os.path.exists(FOX):
        pytest.skip("the glTF Fox sample is not on this machine")
    synth = dict(section_params("source", {"kind": "synthetic", "synthetic": dict(
        SMALL, object=obj, gltf={"path": FOX if obj == "gltf" else None})})["synthetic"], n_frames=8)
    scene = TurntableScene(synth, 25.0)
    rest = scene.body.vertices(None)
    for k in (0, 2, 4, 6):
        T = scene.object_to_depth(scene.time_of(k))
        np.testing.assert_allclose(scene.true_vertices(k), rest @ T[:3, :3].T + T[:3, 3])  # rest pose, no sway
        np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, synth["distance_m"]])  # it turns in place: no sway
        r = scene.render_frame(k)
        assert r.true_mask.any()
        seen = r.depth_mm > 0
        assert 0 < (~seen).sum() < 0.2 * seen.size  # holes and drop-outs
        on = seen & (r.true_depth < 1.6)  # the object, not the wall behind it
        noise = r.depth_mm[on] / 1000.0 - r.true_depth[on]
        assert 0.0005 < np.std(noise[np.abs(noise) < 0.05]) < 0.004  # depth noise of a Kinect at ~1 m
    # a quarter turn apart: the object's front has turned 90 degrees about its vertical axis
    R = scene.object_to_depth(scene.time_of(2))[:3, :3].T @ scene.object_to_depth(0.0)[:3, :3]
    assert abs(rotation_angle_deg(R) - 90.0) < 30.0
    np.testing.assert_array_equal(scene.appearance(0), scene.appearance(5))
