"""GrabCut masks seeded from depth."""
import numpy as np
import pytest

from conftest import data_samples
from stex.masks import (compute_mask, depth_region_in_color, grabcut_seeds, mask_iou, object_depth_pixels,
                        support_plane)
from stex.synth.scene import SyntheticScene


def test_default_scene_masks_reach_iou_095(demo_config):
    scene = SyntheticScene(demo_config["source"]["synthetic"])
    ious = []
    for t in range(0, scene.n_frames, 10):
        r = scene.render_frame(t)
        mask, seeds = compute_mask(r.color, r.depth_mm, scene.calibration, demo_config["masks"], seed=t)
        ious.append(mask_iou(mask, r.true_mask))
        # Seeds are consistent with the truth: sure foreground inside, sure background outside.
        assert r.true_mask[seeds == 1].mean() > 0.99
        assert (~r.true_mask[seeds == 0]).mean() > 0.99
    assert min(ious) >= 0.95, ious


def test_depth_region_lands_on_the_object(tiny_config):
    scene = SyntheticScene(tiny_config["source"]["synthetic"])
    r = scene.render_frame(0)
    region = depth_region_in_color(r.depth_mm, scene.calibration, 0.3, 1.6)
    assert mask_iou(region, r.true_mask) > 0.8
    empty = depth_region_in_color(np.zeros_like(r.depth_mm), scene.calibration, 0.3, 1.6)
    assert not empty.any()


def test_seeds_layers():
    region = np.zeros((60, 60), bool)
    region[20:40, 20:40] = True
    s = grabcut_seeds(region, sure_erode_px=3, bg_margin_px=5)
    assert s[30, 30] == 1 and s[21, 30] == 3 and s[17, 30] == 2 and s[5, 5] == 0



def test_seed_bands_have_the_widths_asked_for_and_holes_are_filled():
    """Down the middle column of a 20 x 20 px region (rows 20-39): sure background, 5 px of
    probable background (the bg_margin_px band), 3 px of probable foreground (what the 3 px
    erosion takes), sure foreground, and the same mirrored. A hole in the region is filled
    first: a ring gives the same seeds as the full square."""
    region = np.zeros((60, 60), bool)
    region[20:40, 20:40] = True
    s = grabcut_seeds(region, sure_erode_px=3, bg_margin_px=5)
    want = np.repeat([0, 2, 3, 1, 3, 2, 0], [15, 5, 3, 14, 3, 5, 15])
    np.testing.assert_array_equal(s[:, 30], want)
    np.testing.assert_array_equal(s[30, :], want)
    ring = region.copy()
    ring[27:33, 27:33] = False
    np.testing.assert_array_equal(grabcut_seeds(ring, sure_erode_px=3, bg_margin_px=5), s)


def _two_squares(size, a, b):
    """(size, size, 3) uint8 black image with white squares at slices ``a`` and ``b``."""
    img = np.zeros((size, size, 3), np.uint8)
    img[a] = img[b] = 255
    return img


def test_grabcut_keeps_the_parts_with_sure_foreground_and_fills_their_holes():
    """Two white squares on black, both probable foreground, only the first with sure foreground
    inside: the mask is the first square alone, with the sure-background hole in its middle
    filled (the object's own holes are the object's)."""
    from stex.masks import GC_BGD, GC_FGD, GC_PR_FGD, grabcut_mask
    a, b = np.s_[10:30, 10:30], np.s_[40:55, 40:55]
    seeds = np.full((60, 60), GC_BGD, np.uint8)
    seeds[a] = seeds[b] = GC_PR_FGD
    seeds[14:26, 14:26] = GC_FGD
    seeds[18:22, 18:22] = GC_BGD
    img = _two_squares(60, a, b)
    img[18:22, 18:22] = 0
    want = np.zeros((60, 60), bool)
    want[a] = True
    np.testing.assert_array_equal(grabcut_mask(img, seeds), want)


def test_grabcut_keeps_a_region_without_sure_foreground():
    """A region too small to survive the sure-foreground erosion (10 px across, sure_erode_px 5)
    is still segmented from its probable labels: the white square is the mask."""
    from stex.masks import GC_FGD, grabcut_mask
    sq = np.s_[15:25, 15:25]
    region = np.zeros((40, 40), bool)
    region[sq] = True
    seeds = grabcut_seeds(region, sure_erode_px=5, bg_margin_px=3)
    assert not (seeds == GC_FGD).any()
    np.testing.assert_array_equal(grabcut_mask(_two_squares(40, sq, sq), seeds), region)


def test_sure_labels_hold_when_grabcut_runs_at_a_reduced_size():
    """Above max_pixels GrabCut runs on a half-size image (nearest-neighbour labels keep even rows
    and columns): sure labels on odd ones, a lone sure-foreground pixel and a 1 px sure-background
    cut into the object, are lost there, and must hold again in the full-size mask."""
    from stex.masks import GC_BGD, GC_FGD, GC_PR_FGD, grabcut_mask
    sq = np.s_[50:150, 50:150]
    seeds = np.full((200, 200), GC_BGD, np.uint8)
    seeds[sq] = GC_PR_FGD
    seeds[70:130, 70:130] = GC_FGD
    seeds[11, 11] = GC_FGD
    seeds[40:100, 101] = GC_BGD
    mask = grabcut_mask(_two_squares(200, sq, sq), seeds, max_pixels=10_000)
    assert mask[seeds == GC_FGD].all() and not mask[seeds == GC_BGD].any()
    assert mask[sq].mean() > 0.99  # the square itself


def test_masks_block_rejects_empty_depth_range(tmp_path, tiny_config):
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.stages.masks import write_masks_block
    src = tiny_config["source"]
    write_scene(src, 4, tmp_path / "scene.zarr")
    write_frames_block(src, 0, 2, tmp_path / "f.zarr", tmp_path / "t.zarr")
    params = dict(tiny_config["masks"], depth_near_m=5.0, depth_far_m=6.0)
    with pytest.raises(ValueError, match="frame 0: empty mask"):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr", params, tmp_path / "m.zarr")
    assert not (tmp_path / "m.zarr").exists()
    # three in-range points on a line: no plane to remove, and the error names the frame
    line = np.zeros((90, 100), np.uint16)
    line[40, 10:13] = 1000
    import zarr
    z = zarr.open_group(str(tmp_path / "f.zarr"), mode="r+")
    d = z["depth"][...]
    d[1] = line
    z["depth"][...] = d
    with pytest.raises(ValueError, match=r"f\.zarr: frame 1: support_plane: no plane found"):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr",
                          dict(tiny_config["masks"], support_plane_tolerance_m=0.01), tmp_path / "m.zarr")
    assert not (tmp_path / "m.zarr").exists()
    with pytest.raises(ValueError, match="supplied no masks"):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr", dict(tiny_config["masks"], use_given=True), tmp_path / "m.zarr")


def test_an_empty_mask_says_why(tiny_config):
    """The empty-mask error names the cause: no depth, depth out of range (with the range the
    depth spans, so millimetres read as metres show), depth that lands outside the colour image
    (a calibration mistake), or everything in range on the support plane."""
    from stex.camera import Calibration
    from stex.masks import why_no_object_depth
    from stex.synth.scene import SyntheticScene
    scene = SyntheticScene(tiny_config["source"]["synthetic"])
    cal, depth = scene.calibration, scene.render_frame(0).depth_mm
    params = tiny_config["masks"]
    assert "no valid pixel" in why_no_object_depth(np.zeros_like(depth), cal, params)
    # depth in 0.1 mm units: 10x too far for the range
    too_far = why_no_object_depth(np.minimum(depth.astype(np.int64) * 10, 65535).astype(np.uint16), cal, params)
    assert "no depth inside" in too_far and "millimetres" in too_far and "median 22 m" in too_far  # the wall, 2.2 m
    # a colour principal point at the image's corner and a camera rotated away: nothing lands inside
    d = cal.to_dict()
    d["depth_to_color"] = [[1, 0, 0, 0.0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]  # 90 degrees about x
    assert "land outside the colour image" in why_no_object_depth(depth, Calibration.from_dict(d), params)
    assert "support plane" in why_no_object_depth(depth, cal, dict(params, support_plane_tolerance_m=0.01))


def test_support_plane_is_found_and_faces_the_camera():
    rng = np.random.default_rng(0)
    # a table 0.3 m below the camera (y down): y = 0.3, normal towards the camera = -y
    table = np.column_stack([rng.uniform(-0.5, 0.5, 4000), 0.3 + rng.normal(0, 0.002, 4000),
                             rng.uniform(0.6, 1.6, 4000)])
    thing = np.column_stack([rng.uniform(-0.1, 0.1, 1000), rng.uniform(0.05, 0.29, 1000),
                             rng.uniform(0.9, 1.1, 1000)])
    n, off, fraction = support_plane(np.concatenate([thing, table]), 0.01, seed=3)
    np.testing.assert_allclose(n, [0, -1, 0], atol=0.01)
    assert off == pytest.approx(0.3, abs=0.003) and fraction == pytest.approx(0.8, abs=0.02)
    assert (thing @ n + off > 0).all()  # the object on the camera's side
    with pytest.raises(ValueError, match="N >= 3"):
        support_plane(table[:2], 0.01)


def test_support_plane_is_not_a_flat_object_with_something_behind_it():
    """A panel held up in front of a body (a shirt in front of a person) holds the most points, but
    the body lies beyond it: the floor the person stands on is the support, and without a floor
    there is none."""
    rng = np.random.default_rng(1)
    panel = np.column_stack([rng.uniform(-0.3, 0.3, 3000), rng.uniform(-0.3, 0.3, 3000), np.full(3000, 1.0)])
    body = np.column_stack([rng.uniform(-0.2, 0.2, 1500), rng.uniform(-0.5, 0.85, 1500), rng.uniform(1.1, 1.3, 1500)])
    floor = np.column_stack([rng.uniform(-0.6, 0.6, 700), np.full(700, 0.9), rng.uniform(1.0, 1.6, 700)])
    n, off, fraction = support_plane(np.concatenate([panel, body, floor]), 0.01)
    np.testing.assert_allclose(n, [0, -1, 0], atol=0.01)
    assert off == pytest.approx(0.9, abs=0.003) and fraction == pytest.approx(700 / 5200, abs=0.01)
    assert support_plane(np.concatenate([panel, body]), 0.01) is None



def test_the_depth_range_includes_both_ends():
    """[near_m, far_m] is closed: millimetre depths land on its ends exactly (300 and 1600 mm for
    0.3-1.6 m); 0 is no depth."""
    K = np.array([[100.0, 0, 2], [0, 100.0, 0], [0, 0, 1]])
    depth = np.array([[0, 299, 300, 1600, 1601]], np.uint16)
    np.testing.assert_array_equal(object_depth_pixels(depth, K, 0.3, 1.6), [[False, False, True, True, False]])


def test_object_depth_pixels_remove_what_lies_beyond_the_support_plane():
    """A floor 0.3 m below the camera (y down) fills the lower rows of the image; two columns of
    it are seen 0.5 m farther (past the floor's edge: beyond its plane by 5-25 cm), and an upright
    patch at 1 m stands in front. Only the patch is the object: the floor and what lies beyond it
    go."""
    f, cy = 60.0, 29.5
    K = np.array([[f, 0, 39.5], [0, f, cy], [0, 0, 1]])
    z = np.zeros((60, 80))
    rows = np.arange(35, 60)
    z[35:] = (0.3 * f / (rows - cy))[:, None]  # y = z (row - cy) / f = 0.3 on the floor
    z[35:, :2] += 0.5
    obj = np.zeros((60, 80), bool)
    obj[20:35, 30:50] = True                    # y <= 0.075 m: 22+ cm above the floor
    z[obj] = 1.0
    depth_mm = np.rint(z * 1000).astype(np.uint16)
    info = {}
    kept = object_depth_pixels(depth_mm, K, 0.3, 4.0, plane_tolerance_m=0.01, info=info)
    np.testing.assert_allclose(info["support_plane"][:4], [0, -1, 0, 0.3], atol=1e-3)
    np.testing.assert_array_equal(kept, obj)


def test_object_depth_pixels_remove_the_table_the_object_stands_on():
    import trimesh

    from stex.render import rasterize
    # a 20 cm box standing on a floor 0.3 m below the camera, seen from above at an angle
    box = trimesh.creation.box([0.2, 0.2, 0.2])
    box.apply_translation([0.0, 0.2, 1.2])
    floor_v = np.array([[-1.0, 0.3, 0.4], [1.0, 0.3, 0.4], [1.0, 0.3, 2.5], [-1.0, 0.3, 2.5]])
    V = np.concatenate([box.vertices, floor_v])
    F = np.concatenate([box.faces, np.array([[0, 1, 2], [0, 2, 3]]) + len(box.vertices)])
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    r = rasterize(V, F, K, 320, 240)
    depth_mm = np.rint(r.depth * 1000).astype(np.uint16)
    on_box = (r.face_id >= 0) & (r.face_id < len(box.faces))
    in_range = object_depth_pixels(depth_mm, K, 0.3, 3.0)
    assert in_range[~on_box & (depth_mm > 0)].all()  # without the option the floor is taken too
    info = {}
    kept = object_depth_pixels(depth_mm, K, 0.3, 3.0, plane_tolerance_m=0.01, info=info)
    np.testing.assert_allclose(info["support_plane"][:4], [0, -1, 0, 0.3], atol=1e-3)
    assert not kept[~on_box].any()
    assert kept[on_box].mean() > 0.9  # all but the box's bottom centimetre
    # the preview's tint of the plane removed: the floor, not the box
    from stex.camera import Calibration, Intrinsics
    from stex.masks import plane_in_color
    cam = Intrinsics(K=K, width=320, height=240)
    floor = plane_in_color(depth_mm, Calibration(color=cam, depth=cam), info["support_plane"], 0.01)
    assert floor[~on_box & (depth_mm > 0)].mean() > 0.95 and floor[on_box].mean() < 0.1
    np.testing.assert_array_equal(kept, object_depth_pixels(depth_mm, K, 0.3, 3.0, plane_tolerance_m=0.01))


SNOOPY = data_samples() / "killingfusion_snoopy" / "frames_000000_000001"


@pytest.mark.skipif(not SNOOPY.is_dir(), reason="shared data samples absent")
@pytest.mark.parametrize("frame", [0, 1])
def test_real_capture_masks_leave_out_the_table_with_the_support_plane(frame, demo_config):
    """KillingFusion's Snoopy stands on a table that is in the depth range: without the support
    plane GrabCut takes the table; with it, the mask is the toy. Its own mask (omask) comes from
    the depth and has holes where the depth has, so it is compared by what it covers, not IoU."""
    import cv2
    from scipy import ndimage

    from stex.camera import Calibration, Intrinsics
    cam = Intrinsics(K=[[517.0, 0, 320], [0, 517.0, 240], [0, 0, 1]], width=640, height=480)
    cal = Calibration(color=cam, depth=cam, depth_to_color=np.eye(4))
    color = cv2.cvtColor(cv2.imread(str(SNOOPY / f"color_{frame:06d}.png")), cv2.COLOR_BGR2RGB)
    depth = cv2.imread(str(SNOOPY / f"depth_{frame:06d}.png"), cv2.IMREAD_UNCHANGED)
    omask = cv2.imread(str(SNOOPY / f"omask_{frame:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
    outline = ndimage.binary_fill_holes(cv2.morphologyEx(omask.astype(np.uint8), cv2.MORPH_CLOSE,
                                                         np.ones((15, 15), np.uint8)))
    outline = cv2.dilate(outline.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    params = demo_config["masks"]
    table, _ = compute_mask(color, depth, cal, params, seed=frame)
    toy, _ = compute_mask(color, depth, cal, dict(params, support_plane_tolerance_m=0.01), seed=frame)
    assert outline[table].mean() < 0.3                  # mostly table
    assert outline[toy].mean() > 0.9 and toy[omask].mean() > 0.93
