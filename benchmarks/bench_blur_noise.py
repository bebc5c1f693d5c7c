"""How much of the inputs' Crete sharpness is sensor noise (issue 7's blur criterion).

On a finished synthetic run (``snakemake --cores 2`` → results/demo) this measures, on every
``--stride``-th frame and with the evaluation's own blur code (``stex.metrics.blur``, same
h_size, inside the photo's mask and the true silhouette): the input photo, the true appearance
rendered on the true mesh in the input view (no noise: what a perfect reconstruction renders to),
and that same render with the scene's sensor noise added (Gaussian, the scene's σ, seeded). If
the last equals the photo, the photo is "sharper" than the truth only by its noise, which the
Crete metric (a ratio of neighbour differences before / after re-blurring) reads as detail.

It also resamples the photo at a smooth field of sub-pixel offsets (±0.5 px), as a texture does
that is sampled from the photo and rendered again, with bilinear and with bicubic interpolation
(the volume's ``interpolation``): how much softer a texture gets from its lookups alone.

    python benchmarks/bench_blur_noise.py results/demo [--stride 12] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex import metrics as ev
from stex.camera import Calibration
from stex.evaluation import Atlas, evaluation_params, truth_views
from stex.io import FrameSequence, open_store


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results folder of a synthetic run (results/demo)")
    ap.add_argument("--stride", type=int, default=12, help="score every n-th frame")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    R = a.results
    scene = open_store(R / "scene.zarr", "scene")
    if "truth" not in scene:
        raise SystemExit(f"{R}: not a synthetic scene (no truth/vertices)")
    syn = scene.attrs["params"]["source"]["synthetic"]
    noise = syn.get("degradations", {}).get("sensor_noise", {})
    sigma = float(noise.get("sigma", 0.0)) if noise.get("enabled", False) else 0.0
    cal = Calibration.from_dict(scene.attrs["calibration"])
    atlas = Atlas.from_store(scene, "template/")
    truth = FrameSequence(sorted((R / "truth").glob("block_*.zarr")), "truth")
    photos = FrameSequence(sorted((R / "frames").glob("block_*.zarr")), "frames")
    masks = FrameSequence(sorted((R / "masks").glob("block_*.zarr")), "masks")
    h_size = evaluation_params({})["h_size"]
    ids = list(scene.attrs["frame_ids"])
    rng = np.random.default_rng(a.seed)
    rows = []
    print(f"{R}: sensor noise σ {sigma} grey levels, blur h_size {h_size}")
    print("frame  photo   truth   truth+noise  photo resampled: bilinear  bicubic")
    for t in range(0, len(ids), a.stride):
        img, tmask = truth_views(scene["truth/vertices"][t], atlas, truth.read("appearance", ids[t]), cal)["input"]
        m = np.asarray(masks.read("mask", ids[t]), bool) & tmask
        noisy = np.clip(img + rng.normal(0.0, sigma, img.shape), 0, 255) if sigma > 0 else img
        photo = photos.read("color", ids[t]).astype(np.float32)
        row = [ev.blur(photo, m, h_size=h_size)["blur"], ev.blur(img, m, h_size=h_size)["blur"],
               ev.blur(noisy, m, h_size=h_size)["blur"]]
        row += [ev.blur(r, m, h_size=h_size)["blur"] for r in resampled(photo, t)]
        rows.append(row)
        print(f"{ids[t]:5d}  " + "  ".join(f"{x:.4f}" for x in row))
    mean = np.mean(rows, axis=0)
    print("mean   " + "  ".join(f"{x:.4f}" for x in mean) + f"   ({len(rows)} frames)")
    return 0


def resampled(photo, seed):
    """``photo`` read at a smooth field of offsets within ±0.5 px, bilinearly and bicubically."""
    import cv2

    H, W = photo.shape[:2]
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    dx = 0.5 * np.sin(xx / 37 + seed) * np.cos(yy / 23)
    dy = 0.5 * np.cos(xx / 29) * np.sin(yy / 41 + seed)
    return [np.clip(cv2.remap(photo, xx + dx, yy + dy, f, borderMode=cv2.BORDER_REPLICATE), 0, 255)
            for f in (cv2.INTER_LINEAR, cv2.INTER_CUBIC)]


if __name__ == "__main__":
    raise SystemExit(main())
