"""GrabCut masks on a real capture, with and without the support plane (``masks.support_plane_tolerance_m``).

KillingFusion's Snoopy (the shared samples, two Kinect v1 frames, depth registered to colour)
stands on a table inside the depth range. For each frame and tolerance (0 = off) this prints,
against the dataset's own mask (``omask``, cut from the depth, with holes where the depth has):
the fraction of omask pixels inside ours, the fraction of ours inside the omask's outline (closed
by 15 px, holes filled, dilated by 3 px), the IoU with the omask closed by 9 px and filled, the
support plane found (normal, inlier fraction of the in-range points) and the time of
``stex.masks.compute_mask``.

    python benchmarks/bench_masks_real.py [--samples ../shared/data_samples]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex.camera import Calibration, Intrinsics, backproject_depth
from stex.config import load_config
from stex.masks import compute_mask, mask_iou, support_plane


def closed_filled(mask, close_px, dilate_px=0):
    import cv2
    from scipy import ndimage

    out = ndimage.binary_fill_holes(cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE,
                                                     np.ones((close_px, close_px), np.uint8)))
    if dilate_px:
        out = cv2.dilate(out.astype(np.uint8), np.ones((2 * dilate_px + 1,) * 2, np.uint8)) > 0
    return out


def main() -> int:
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data_samples")
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.005, 0.01, 0.02, 0.03])
    a = ap.parse_args()
    folder = a.samples / "killingfusion_snoopy" / "frames_000000_000001"
    if not folder.is_dir():
        raise SystemExit(f"{folder}: not found (the shared data samples)")
    cam = Intrinsics(K=[[517.0, 0, 320], [0, 517.0, 240], [0, 0, 1]], width=640, height=480)
    cal = Calibration(color=cam, depth=cam, depth_to_color=np.eye(4))
    params = load_config(overrides={})["masks"]
    print(f"masks (schema defaults): {params}")
    print("frame  tolerance  omask in ours  ours in outline  IoU(closed omask)  seconds")
    for t in (0, 1):
        color = cv2.cvtColor(cv2.imread(str(folder / f"color_{t:06d}.png")), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(folder / f"depth_{t:06d}.png"), cv2.IMREAD_UNCHANGED)
        omask = cv2.imread(str(folder / f"omask_{t:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
        outline, filled = closed_filled(omask, 15, 3), closed_filled(omask, 9)
        d = depth / 1000.0
        inside = (d >= params["depth_near_m"]) & (d <= params["depth_far_m"])
        for seed in (0, 1, 2):
            n, off, frac = support_plane(backproject_depth(d, cal.depth.K)[inside], 0.01, seed=seed)
            print(f"  frame {t}: plane (seed {seed}) normal {np.round(n, 3)}, offset {off:.3f} m, "
                  f"{frac:.3f} of the in-range points")
        for tol in a.tolerances:
            t0 = time.perf_counter()
            m, _ = compute_mask(color, depth, cal, dict(params, support_plane_tolerance_m=tol), seed=t)
            dt = time.perf_counter() - t0
            print(f"{t:5d}  {tol:9.3f}  {m[omask].mean():13.3f}  {outline[m].mean():15.3f}  "
                  f"{mask_iou(m, filled):17.3f}  {dt:7.2f}")
    deepdeform(a.samples)
    return 0


def deepdeform(samples: Path) -> None:
    """A capture with no support in range: DeepDeform's person holding up a shirt (depth range
    up to 2.05 m, the wall beyond). The dominant plane of the in-range points is the shirt; the
    support test (the object on the plane's camera side) must not take it."""
    import cv2

    from stex.masks import dominant_plane

    folder = samples / "deepdeform_neuraltracking" / "example_data" / "test" / "seq017"
    if not folder.is_dir():
        return
    K = np.loadtxt(folder / "intrinsics.txt")[:3, :3]
    cam = Intrinsics(K=K, width=640, height=480)
    cal = Calibration(color=cam, depth=cam, depth_to_color=np.eye(4))
    params = dict(load_config(overrides={})["masks"], depth_far_m=2.05)
    print("\nDeepDeform seq017 (no support in range), depth_far_m 2.05:")
    for f in ("000300", "000600"):
        color = cv2.cvtColor(cv2.imread(str(folder / "color" / f"{f}.jpg")), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(folder / "depth" / f"{f}.png"), cv2.IMREAD_UNCHANGED)
        d = depth / 1000.0
        inside = (d >= params["depth_near_m"]) & (d <= params["depth_far_m"])
        P = backproject_depth(d, K)[inside]
        n, off = dominant_plane(P, 0.01)
        dist = P @ n + off
        on = np.abs(dist) <= 0.01
        plain, _ = compute_mask(color, depth, cal, params, seed=0)
        info = {}
        m, _ = compute_mask(color, depth, cal, dict(params, support_plane_tolerance_m=0.01), seed=0, info=info)
        print(f"  frame {f}: dominant plane normal {np.round(n, 3)}, {on.mean():.3f} of the points on it, "
              f"{(dist[~on] < 0).mean():.3f} of the others beyond it; support taken: "
              f"{'none' if info['support_plane'] is None else np.round(info['support_plane'], 3).tolist()}; "
              f"mask {m.sum()} px, {plain[m].mean():.3f} of it and {m[plain].mean():.3f} of the mask "
              f"without the option in common")


if __name__ == "__main__":
    raise SystemExit(main())
