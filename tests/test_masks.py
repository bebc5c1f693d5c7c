"""GrabCut masks seeded from depth."""
import numpy as np
import pytest

from stex.masks import compute_mask, depth_region_in_color, grabcut_seeds, mask_iou
from stex.synth.scene import SyntheticScene


def test_default_scene_masks_reach_iou_095(demo_config):
    scene = SyntheticScene(demo_config["source"]["synthetic"])
    ious = []
    for t in range(0, scene.n_frames, 5):
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


def test_masks_block_rejects_empty_depth_range(tmp_path, tiny_config):
    from stex.ingest import write_frames_block, write_scene
    from stex.masks import write_masks_block
    src = tiny_config["source"]
    write_scene(src, 4, tmp_path / "scene.zarr")
    write_frames_block(src, 0, 2, tmp_path / "f.zarr", tmp_path / "t.zarr")
    params = dict(tiny_config["masks"], depth_near_m=5.0, depth_far_m=6.0)
    with pytest.raises(ValueError, match="frame 0: empty mask"):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr", params, tmp_path / "m.zarr")
    assert not (tmp_path / "m.zarr").exists()
    with pytest.raises(ValueError, match="supplied no masks"):
        write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr", dict(tiny_config["masks"], use_given=True), tmp_path / "m.zarr")
