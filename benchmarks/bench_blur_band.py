"""Where the Crete blur of a photo and of a render differ: the mask eroded step by step.

On a finished run (``snakemake --cores 2`` → results/demo; the Fox: results/fox) this scores, on
every ``--stride``-th frame and with the evaluation's own blur code (``stex.metrics.blur``, same
h_size), the input photo, our corrected slice, our volume slice before the correction and the
global texture rendered on the tracked mesh in the input view, and on synthetic scenes the true appearance rendered on the true mesh, all
inside one mask: the photo's mask ∩ our render's silhouette (∩ the true silhouette), eroded by
each of ``--erode`` pixels. What changes between erosion 0 and 1-3 px is the silhouette band,
where a photo's pixels mix the object with the background (motion blur) and a render's do not
(``evaluation.blur_interior_px``, docs/metrics.md); what changes between the volume and ours is
the correction's doing.

    python benchmarks/bench_blur_band.py results/fox [--stride 2] [--erode 0 1 2 3 5]
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
from stex.evaluation import Atlas, evaluation_params, method_views, truth_views
from stex.io import FrameSequence, open_store


def blur_sweep(images: dict, mask, erodes, h_size: int) -> dict:
    """The blur (``stex.metrics.blur``) of every image in ``images`` ({name: (H, W, 3)}) inside
    ``mask`` eroded by each of ``erodes`` (px): {(erosion, name): blur}. One mask for every image,
    so the figures of one erosion differ only by the images."""
    m = np.asarray(mask, bool)
    cache: dict = {}
    return {(e, n): ev.blur(img, m, h_size=h_size, erode_px=e, cache=cache)["blur"]
            for e in erodes for n, img in images.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run (results/demo)")
    ap.add_argument("--stride", type=int, default=2, help="score every n-th frame")
    ap.add_argument("--erode", type=int, nargs="+", default=[0, 1, 2, 3, 5], help="erosions (px)")
    a = ap.parse_args()
    R = a.results
    scene = open_store(R / "scene.zarr", "scene")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    ids = [int(i) for i in scene.attrs["frame_ids"]]
    atlas = Atlas.from_store(open_store(R / "template.zarr", "template"))
    vertices = open_store(R / "tracking.zarr", "tracking")["vertices"]
    photos = FrameSequence(sorted((R / "frames").glob("block_*.zarr")), "frames")
    masks = FrameSequence(sorted((R / "masks").glob("block_*.zarr")), "masks")
    corrected = FrameSequence(sorted((R / "corrected").glob("block_*.zarr")), "corrected")
    volume = FrameSequence(sorted((R / "volume").glob("block_*.zarr")), "volume")
    global_tex = np.asarray(open_store(R / "global_texture.zarr", "global_texture")["texture"][...])
    has_truth = "truth" in scene
    if has_truth:
        true_atlas = Atlas.from_store(scene, "template/")
        truth = FrameSequence(sorted((R / "truth").glob("block_*.zarr")), "truth")
    h_size = evaluation_params({})["h_size"]
    names = ["photo", "volume", "ours", "global"] + (["truth"] if has_truth else [])
    scores = {(e, n): [] for e in a.erode for n in names}
    frames = range(0, len(ids), a.stride)
    for t in frames:
        V = np.asarray(vertices[t], np.float64)
        ours, rmask = method_views(corrected.read("texture", ids[t]), V, atlas, cal)["input"]
        images = {"photo": photos.read("color", ids[t]), "ours": ours,
                  "volume": method_views(volume.read("texture", ids[t]), V, atlas, cal)["input"][0],
                  "global": method_views(global_tex, V, atlas, cal)["input"][0]}
        m = np.asarray(masks.read("mask", ids[t]), bool) & rmask
        if has_truth:
            images["truth"], tmask = truth_views(scene["truth/vertices"][t], true_atlas,
                                                 truth.read("appearance", ids[t]), cal)["input"]
            m &= tmask
        for k, v in blur_sweep({n: images[n] for n in names}, m, a.erode, h_size).items():
            scores[k].append(v)
    print(f"{R}: {len(frames)} frames (every {a.stride}), blur h_size {h_size}, mean over frames")
    print("erode px  " + "  ".join(f"{n:>7}" for n in names))
    for e in a.erode:
        print(f"{e:8d}  " + "  ".join(f"{np.nanmean(scores[(e, n)]):7.4f}" for n in names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
