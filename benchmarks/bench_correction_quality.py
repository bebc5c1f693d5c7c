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
from stex.io import FrameSequence, open_store


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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", type=Path, help="a finished run, e.g. results/demo")
    ap.add_argument("--wide", type=int, default=6, help="texels either side of a boundary (6: the Fox's texels per image pixel)")
    args = ap.parse_args(argv)
    R, wide = args.results, args.wide
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
