"""The whole workflow on a real capture: KillingFusion's Snoopy (Kinect v1, two frames), read as a
folder dataset in stex's layout, with GrabCut masks that leave out the table (the support plane)
and the template built from the first frame's depth (template.from_depth). Skipped without the
shared data samples."""
import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from conftest import REPO, data_samples
from stex.io import FrameSequence, open_store

SNOOPY = data_samples() / "killingfusion_snoopy" / "frames_000000_000001"
pytestmark = pytest.mark.skipif(not SNOOPY.is_dir(), reason="shared data samples absent")


def snoopy_dataset(root):
    """Write the two Snoopy frames in stex's folder layout under ``root``: colour and depth
    (registered to colour, so one camera and an identity extrinsic); no masks, no template."""
    for sub in ("color", "depth"):
        (root / sub).mkdir(parents=True)
    for i in (0, 1):
        (root / "color" / f"{i:06d}.png").write_bytes((SNOOPY / f"color_{i:06d}.png").read_bytes())
        (root / "depth" / f"{i:06d}.png").write_bytes((SNOOPY / f"depth_{i:06d}.png").read_bytes())
    cam = {"fx": 517.0, "fy": 517.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}
    (root / "calibration.json").write_text(json.dumps({"color": cam, "depth": cam,
                                                       "depth_to_color": np.eye(4).tolist()}))


@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("real")
    snoopy_dataset(work / "snoopy")
    cfg = {"scene": "snoopy", "results": str(work / "results"), "frame_block": 2,
           "source": {"kind": "folder", "folder": {"path": str(work / "snoopy"), "layout": "stex"}},
           "masks": {"support_plane_tolerance_m": 0.01},
           "template": {"atlas_size": 512, "from_depth": True},
           "texcoords": {"levels": 2, "iterations": 10, "refine_iterations": 10}}
    (work / "snoopy.yaml").write_text(yaml.safe_dump(cfg))
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(work),
           "--configfile", str(work / "snoopy.yaml"), "--cores", "2"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    return work / "results" / "snoopy"


def test_real_capture_runs_through_and_every_store_is_complete(real_run):
    for name in ("scene", "template", "tracking", "poses", "projection", "texcoords", "observations",
                 "labels", "global_texture"):
        assert open_store(real_run / f"{name}.zarr", name).attrs["complete"]
    masks = FrameSequence(sorted((real_run / "masks").glob("block_*.zarr")), "masks")
    corrected = FrameSequence(sorted((real_run / "corrected").glob("block_*.zarr")), "corrected")
    assert masks.frame_ids == corrected.frame_ids == [0, 1]
    # the masks leave out the table: the toy is about 15-22k of the 307k pixels
    for t in (0, 1):
        assert 10_000 < masks.read("mask", t).sum() < 30_000
    # the support plane removed at each frame is the table: normal upwards (y is down)
    planes = open_store(real_run / "masks" / "block_0000.zarr", "masks").attrs["support_planes"]
    assert len(planes) == 2 and all(p is not None and p[1] < -0.9 and p[4] > 0.5 for p in planes)
    assert (real_run / "previews" / "masks.png").stat().st_size > 10_000
    texture = corrected.read("texture", 1)
    assert texture.shape == (512, 512, 3) and texture.std() > 10
    template = open_store(real_run / "template.zarr", "template")
    assert template.attrs["origin"] == "depth of frame 0" and template.attrs["gutter_conflicts"] == 0
    # the template from frame 0's depth covers that frame's mask
    assert open_store(real_run / "tracking.zarr", "tracking")["silhouette_iou"][0] > 0.85


def test_real_capture_scores(real_run):
    """Against the input photos, our texture beats the per-frame projection at both frames and
    covers the whole surface."""
    ev = json.loads((real_run / "evaluation" / "evaluation.json").read_text())
    assert ev["scored_frames"] == [0, 1] and not ev["has_truth"]
    for rec in ev["frames"]:
        ours, projection = rec["methods"]["ours"], rec["methods"]["projection"]
        assert ours["coverage_faces"] == 1.0 and projection["coverage_faces"] < 1.0
        assert ours["psnr"] > projection["psnr"] + 3
