"""Colour-correction quality on a finished run (issue 6 acceptance on the demo scene).

For every slice: the mean colour step across label boundaries (channel-mean |Δ| over 4-neighbour
texel pairs of two different labels in one chart) before (volume) and after (corrected)
correction — stored by the stage in each corrected store's attr ``label_boundary_step``; for every
10th slice the natural step between same-label neighbours (the texture's own detail, which no
correction removes) and the mean absolute change inside label regions more than 4 / 8 / 16 texels
from any boundary.

    python benchmarks/bench_correction_quality.py results/demo [--wide 6]

``--wide k`` (default 6, the Fox's texels per image pixel) adds the step between texels k before
and k after each boundary, the scale at which a render shows it.

``--input-view 26,130,208`` instead renders those frames' slices, corrected and not, on the
tracked mesh in the input camera and compares them with the photo, apart on the pixels of faces
labelled with the frame itself and of faces borrowed from another: the mean squared error, and
the part of it at low spatial frequency (the error image blurred by a Gaussian of ``--sigma`` px,
default the colour image's width / 128, within the region), the colour offsets a correction is
for. What the correction should lower, and does not where the borrowed error is mostly detail
out of place.

    python benchmarks/bench_correction_quality.py results/paper --input-view 26,130,208
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

from stex.correction import interior_change
from stex.io import FrameSequence, open_store, run_block_paths


def neighbour_steps(image, label_map, chart):
    """Mean channel |Δ| over 4-neighbour texel pairs in one chart: (across labels, same label)."""
    im = np.asarray(image, np.float64)
    across, same = [], []
    for a, b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                 ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        ok = (label_map[a] >= 0) & (label_map[b] >= 0) & (chart[a] == chart[b]) & (chart[a] >= 0)
        d = np.abs(im[a] - im[b]).mean(-1)
        across.append(d[ok & (label_map[a] != label_map[b])])
        same.append(d[ok & (label_map[a] == label_map[b])])
    return float(np.concatenate(across).mean()), float(np.concatenate(same).mean())


def _run_lengths(key):
    """Per texel, how many texels before it along axis 1 carry the same key (0 at a change)."""
    run = np.zeros(key.shape, np.int32)
    for c in range(1, key.shape[1]):
        run[:, c] = np.where(key[:, c] == key[:, c - 1], run[:, c - 1] + 1, 0)
    return run


def wide_steps(image, label_map, chart, k):
    """Mean grey |Δ| between the texels k before and k after a label boundary, where each side is
    one label for those k + 1 texels (same chart), and the same over 2k + 1 texels inside one
    label: (across, same). k about the texels per image pixel measures the step a render shows
    at the scale of a pixel, which a correction spread over fewer texels than that leaves."""
    grey = np.asarray(image, np.float64).mean(-1)
    across, same = [], []
    for g, lm, ch in ((grey, label_map, chart), (grey.T, label_map.T, chart.T)):
        key = np.where((lm >= 0) & (ch >= 0), lm.astype(np.int64) * (int(ch.max()) + 1) + ch, -1)
        run = _run_lengths(key)
        c = np.arange(k, g.shape[1] - k - 1)
        a, b = key[:, c], key[:, c + 1]
        d = np.abs(g[:, c + 1 + k] - g[:, c - k])
        sides = (a >= 0) & (b >= 0) & (run[:, c] >= k) & (run[:, c + 1 + k] >= k)
        across.append(d[sides & (lm[:, c] != lm[:, c + 1]) & (ch[:, c] == ch[:, c + 1])])
        same.append(d[(a >= 0) & (run[:, c + 1 + k] >= 2 * k + 1)])
    return float(np.concatenate(across).mean()), float(np.concatenate(same).mean())


def input_view_split(R: Path, frames, sigma=None) -> dict:
    """{(method, region): (mean squared error, its low-pass part)} over ``frames`` (grey levels²),
    method "volume" (uncorrected) or "corrected", region "own" or "borrowed" (see the module
    docstring); pixels inside the frame's mask and the tracked mesh's render."""
    import cv2

    import stex.metrics as ev
    from stex.camera import Calibration, transform_points
    from stex.evaluation import Atlas

    scene = open_store(R / "scene.zarr", "scene")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    K, W, H = cal.color.K, cal.color.width, cal.color.height
    sigma = W / 128 if sigma is None else sigma
    atlas = Atlas.from_store(open_store(R / "template.zarr", "template"))
    vertices = open_store(R / "tracking.zarr", "tracking")["vertices"]
    labels = open_store(R / "labels.zarr", "labels")["labels"]
    pos = {int(f): k for k, f in enumerate(scene.attrs["frame_ids"])}
    seq = {k: FrameSequence(run_block_paths(R, k, scene), k) for k in ("frames", "masks", "volume", "corrected")}
    sums = {}
    for fid in frames:
        Vc = transform_points(cal.depth_to_color, np.asarray(vertices[pos[fid]], np.float64))
        view = ev.mesh_view(Vc, atlas.faces, atlas.texcoords, atlas.texcoord_faces, K, W, H)
        photo = seq["frames"].read("color", fid).astype(np.float32)
        inside = seq["masks"].read("mask", fid) & view.mask
        lab = np.full(view.face_id.shape, -1, np.int64)
        lab[view.mask] = np.asarray(labels[pos[fid]])[view.face_id[view.mask]]
        regions = {"own": inside & (lab == pos[fid]), "borrowed": inside & (lab >= 0) & (lab != pos[fid])}
        for method in ("volume", "corrected"):
            image = ev.view_texture(view, seq[method].read("texture", fid).astype(np.float32))
            for region, m in regions.items():
                err = np.where(m[..., None], image - photo, 0.0).astype(np.float32)
                weight = cv2.GaussianBlur(m.astype(np.float32), (0, 0), sigma)
                low = cv2.GaussianBlur(err, (0, 0), sigma) / np.maximum(weight, 1e-6)[..., None]
                acc = sums.setdefault((method, region), [0.0, 0.0, 0])
                acc[0] += float((err[m] ** 2).sum())
                acc[1] += float((low[m] ** 2).sum())
                acc[2] += int(m.sum()) * 3
    return {k: (a / n, b / n) for k, (a, b, n) in sums.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", type=Path, help="a finished run, e.g. results/demo")
    ap.add_argument("--wide", type=int, default=6, help="texels either side of a boundary (6: the Fox's texels per image pixel)")
    ap.add_argument("--input-view", default=None, help="comma-separated frame ids: the input-view split instead")
    ap.add_argument("--sigma", type=float, default=None, help="low-pass Gaussian of --input-view (px; default width / 128)")
    args = ap.parse_args(argv)
    R, wide = args.results, args.wide
    if args.input_view:
        frames = [int(f) for f in args.input_view.split(",")]
        res = input_view_split(R, frames, args.sigma)
        print(f"input view, frames {frames}: mean squared error (its low-pass part), grey levels²")
        for region in ("own", "borrowed"):
            (v, vl), (c, cl) = res[("volume", region)], res[("corrected", region)]
            print(f"  {region:9s} uncorrected {v:8.2f} ({vl:6.2f})   corrected {c:8.2f} ({cl:6.2f})")
        return
    vol = FrameSequence(sorted((R / "volume").glob("block_*.zarr")), "volume")
    cor = FrameSequence(sorted((R / "corrected").glob("block_*.zarr")), "corrected")
    t = open_store(R / "template.zarr", "template")
    tf, fc = t["texel/face_id"][...], t["face_chart"][...]
    chart = np.where(tf >= 0, fc[np.maximum(tf, 0)], -1)
    steps = np.array([s for p in sorted((R / "corrected").glob("block_*.zarr"))
                      for s in open_store(p, "corrected").attrs["label_boundary_step"]])
    fall = 1 - steps[:, 1] / steps[:, 0]
    print(f"label-boundary step over {len(steps)} slices: {steps[:, 0].mean():.3f} -> "
          f"{steps[:, 1].mean():.3f} grey levels, fall {100 * (1 - steps[:, 1].mean() / steps[:, 0].mean()):.1f} % "
          f"(worst slice {100 * fall.min():.1f} %)")
    rows, inner, wides = [], [], []
    for fid in vol.frame_ids[::10]:
        lm = vol.read("label_map", fid).astype(np.int32)
        before, after = vol.read("texture", fid), cor.read("texture", fid)
        rows.append(neighbour_steps(before, lm, chart) + neighbour_steps(after, lm, chart))
        wides.append(wide_steps(before, lm, chart, wide) + wide_steps(after, lm, chart, wide))
        inner.append([interior_change(before, after, lm, m) for m in (4, 8, 16)])
    r, inner = np.array(rows).mean(0), np.array(inner)
    print(f"every 10th slice: across labels {r[0]:.3f} -> {r[2]:.3f}, same label {r[1]:.3f} -> {r[3]:.3f}; "
          f"excess at boundaries {r[0] - r[1]:.3f} -> {r[2] - r[3]:.3f} "
          f"(fall {100 * (1 - (r[2] - r[3]) / (r[0] - r[1])):.1f} %)")
    w = np.array(wides).mean(0)
    print(f"every 10th slice, {wide} texels either side of a boundary (--wide): across {w[0]:.3f} -> {w[2]:.3f}, "
          f"same label {w[1]:.3f} -> {w[3]:.3f}; excess {w[0] - w[1]:.3f} -> {w[2] - w[3]:.3f}")
    print("change inside label regions at > 4 / 8 / 16 texels from a boundary: mean "
          + " / ".join(f"{x:.3f}" for x in np.nanmean(inner, 0)) + ", max "
          + " / ".join(f"{x:.3f}" for x in np.nanmax(inner, 0)) + " grey levels")


if __name__ == "__main__":
    main()
