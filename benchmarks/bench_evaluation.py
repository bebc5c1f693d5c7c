"""Benchmark the evaluation's per-frame scoring (stex.evaluation.score_frame) on a results folder.

Reads (never writes) a scene's stores up to the projection stage — scene, frames, masks,
template, tracking, projection and, on synthetic scenes, truth — and scores the two baselines
that need no labels: the Kim 2019 global texture (built from every ``--global-step``-th frame,
timed once) and the naive per-frame projection, on ``--frames`` frames spread over the
sequence. Reported: median seconds per ``score_frame`` call (input view + coverage + ground
truth from the novel and input views), the truth renders, and the scores.

    python benchmarks/bench_evaluation.py [--results results/demo] [--frames 5] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # source checkout without install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="results/demo")
    ap.add_argument("--frames", type=int, default=5, help="frames scored")
    ap.add_argument("--runs", type=int, default=3, help="repetitions of each score_frame call")
    ap.add_argument("--global-step", type=int, default=10, help="global texture from every k-th frame")
    a = ap.parse_args(argv)

    from stex.global_texture import global_texture, projection_texture
    from stex.camera import Calibration
    from stex.evaluation import Atlas, score_frame, truth_views
    from stex.io import FrameSequence, open_store
    from stex.sampling import TexelSampler

    R = Path(a.results)
    scene = open_store(R / "scene.zarr", "scene")
    ids = list(scene.attrs["frame_ids"])
    cal = Calibration.from_dict(scene.attrs["calibration"])
    blocks = sorted((R / "frames").glob("block_*.zarr"))
    photos = FrameSequence(blocks, "frames")
    masks = FrameSequence(sorted((R / "masks").glob("block_*.zarr")), "masks")
    truth_blocks = sorted((R / "truth").glob("block_*.zarr"))
    truth = FrameSequence(truth_blocks, "truth") if truth_blocks else None
    template = open_store(R / "template.zarr", "template")
    V = open_store(R / "tracking.zarr", "tracking")["vertices"]
    proj = open_store(R / "projection.zarr", "projection")
    vis, cos, phi = proj["face_visible"], proj["face_cos"], proj["phi"]
    atlas = Atlas.from_store(template)
    sampler = TexelSampler(template["texel/face_id"][...], template["texel/bary"][...], atlas.faces)
    src = list(range(0, len(ids), a.global_step))

    t0 = time.perf_counter()
    gtex, _ = global_texture(lambda k: (photos.read("color", ids[src[k]]), phi[src[k]], vis[src[k]]),
                             len(src), sampler, face_weight=lambda k: cos[src[k]])
    t_global = time.perf_counter() - t0
    print(f"{R}: {len(ids)} frames {cal.color.width}x{cal.color.height}, {len(atlas.faces)} faces, "
          f"atlas {sampler.W}; global texture from {len(src)} frames in {t_global:.2f} s "
          f"({t_global / len(src):.3f} s per frame)")
    if truth is not None:
        true_atlas = Atlas.from_store(scene, "template/")
    seen = np.asarray(vis[...])[src].any(0)
    timings = {"truth_views": [], "global": [], "projection": []}
    for t in np.linspace(0, len(ids) - 1, a.frames).round().astype(int):
        fid = ids[t]
        image, mask = photos.read("color", fid), masks.read("mask", fid)
        tv = None
        if truth is not None:
            for _ in range(a.runs):
                t0 = time.perf_counter()
                tv = truth_views(scene["truth/vertices"][t], true_atlas, truth.read("appearance", fid), cal)
                timings["truth_views"].append(time.perf_counter() - t0)
        ptex, _ = projection_texture(sampler, phi[t], vis[t], image)
        line = [f"frame {fid}:"]
        for name, tex, has in (("global", gtex, seen), ("projection", ptex, vis[t])):
            for _ in range(a.runs):
                t0 = time.perf_counter()
                s = score_frame(tex, V[t], atlas, image, mask, cal, face_has_texture=has,
                                seen_faces=seen, face_visible=vis[t], truth=tv)
                timings[name].append(time.perf_counter() - t0)
            line.append(f"{name} PSNR {s['psnr']:.2f} dB SSIM {s['ssim']:.3f} blur {s['blur']:.3f} "
                        f"(input {s['blur_input']:.3f}) cov {100 * s['coverage_faces']:.1f} %"
                        + (f" gt-unseen {s['gt_novel_psnr_unseen']:.2f} dB" if tv else ""))
        print("  ".join(line))
    for k, v in timings.items():
        if v:
            print(f"{k}: median {statistics.median(v):.3f} s over {len(v)} calls")


if __name__ == "__main__":
    main()
