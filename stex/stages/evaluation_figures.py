"""The evaluation folder's CSV tables, plots and pictures (:func:`stex.stages.evaluation.write_evaluation`)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from PIL import Image

from stex.evaluation import dynamism_regions, frame_views, method_views
from stex.preview import pyplot
from stex.reporting import METHOD_NAMES, METHODS, method_name, sampling_rows, timing_rows
from stex.sampling import label_colors

__all__ = ["write_csvs", "plot_psnr", "plot_blur_motion", "plot_dynamism", "picture_side_by_side",
           "picture_label_map"]


def _crop_box(masks, pad=4):
    m = np.zeros_like(masks[0])
    for x in masks:
        m |= x
    if not m.any():
        return 0, m.shape[0], 0, m.shape[1]
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return (max(0, rows[0] - pad), min(m.shape[0], rows[-1] + 1 + pad),
            max(0, cols[0] - pad), min(m.shape[1], cols[-1] + 1 + pad))


def write_csvs(out_dir: Path, records, tabs, timing, sampling=None):
    keys = list(dict.fromkeys(k for r in records for s in r["methods"].values() for k in s))
    with open(out_dir / "per_frame.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "position", "held_out", "motion_mm", "method"] + keys)
        for r in records:
            for m, s in r["methods"].items():
                w.writerow([r["frame"], r["position"], int(r["held_out"]), _csv(r["motion_mm"]), m]
                           + [_csv(s.get(k, math.nan)) for k in keys])
    all_tabs = dict(tabs)
    if timing:
        all_tabs["timing"] = timing_rows(timing)
    if sampling:
        all_tabs["sampling"] = sampling_rows(sampling)
    for name, rows in all_tabs.items():
        with open(out_dir / f"table_{name}.csv", "w", newline="") as f:
            csv.writer(f).writerows(rows)


def _csv(x):
    return "" if isinstance(x, float) and not math.isfinite(x) else x


def _finish(plt, fig, ax, path, xlabel, ylabel):
    """Label, legend and grid a one-axis figure, write it to ``path`` and close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_psnr(path, records):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    x = [r["frame"] for r in records]
    for m in (records[0]["methods"] if records else METHODS):
        ax.plot(x, [r["methods"][m]["psnr"] for r in records], marker=".", label=method_name(m))
    held = [r["frame"] for r in records if r["held_out"]]
    for i, h in enumerate(held):
        ax.axvline(h, color="0.85", lw=3, zorder=0, label="held-out frame" if i == 0 else None)
    _finish(plt, fig, ax, path, "frame", "patch-shift PSNR (dB)")


def plot_blur_motion(path, records, ids, motion):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    x = [r["frame"] for r in records]
    ax.plot(x, [r["methods"]["ours"]["blur_input"] for r in records], "k.-", label="input")
    if all("blur_truth" in r["methods"]["ours"] for r in records):
        ax.plot(x, [r["methods"]["ours"]["blur_truth"] for r in records], "k:", label="true appearance")
    others = [m for m in (records[0]["methods"] if records else ()) if m not in METHODS]
    for m in ["ours", "global"] + others:
        ax.plot(x, [r["methods"][m]["blur"] for r in records], ".-", label=method_name(m))
    ax.set_xlabel("frame")
    ax.set_ylabel("blur (Crete), smaller is sharper")
    ax2 = ax.twinx()
    ax2.bar(ids, np.nan_to_num(motion), color="0.6", alpha=0.35, width=0.8, label="vertex motion")
    ax2.set_ylabel("mean vertex motion (mm/frame)")
    ax.set_zorder(ax2.get_zorder() + 1)
    ax.patch.set_visible(False)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_dynamism(path, S, face_chart, face_area, ids, n_regions):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=120)
    for c, s in dynamism_regions(S, face_chart, face_area, n_regions):
        ax.plot(ids, s, ".-", label=f"chart {c}")
    ax.axhline(0.95, color="k", ls="--", lw=0.8, label="θ_Ω = 0.95")
    _finish(plt, fig, ax, path, "frame", "SSIM dynamism S (area-weighted mean)")


def picture_side_by_side(path, t, ids, photos, masks, textures, V, atlas, cal, tv, face_visible):
    plt = pyplot()
    texs = textures(t)
    image = photos.read("color", ids[t])
    shown = ["ours", "global", "projection"]
    geom = frame_views(V, atlas, cal, None if tv is None else tv["novel_transform"], face_visible)
    views = {m: method_views(texs[m], V, atlas, cal, geometry=geom) for m in shown}
    top = [("input", image.astype(np.float32))] + [(m, views[m]["input"][0]) for m in shown]
    box = _crop_box([masks.read("mask", ids[t])] + [views[m]["input"][1] for m in shown])
    rows = [[(METHOD_NAMES[n] if n != "input" else "input photo", im, box) for n, im in top]]
    if tv is not None:
        nbox = _crop_box([tv["novel"][1]] + [views[m]["novel"][1] for m in shown])
        rows.append([("truth, novel view", tv["novel"][0], nbox)]
                    + [(METHOD_NAMES[m] + ", novel view", views[m]["novel"][0], nbox) for m in shown])
    fig, axes = plt.subplots(len(rows), 4, figsize=(10, 2.8 * len(rows)), dpi=120, squeeze=False)
    for r, row in enumerate(rows):
        for c, (title, im, (r0, r1, c0, c1)) in enumerate(row):
            axes[r, c].imshow(np.clip(im[r0:r1, c0:c1], 0, 255).astype(np.uint8))
            axes[r, c].set_title(title, fontsize=8)
            axes[r, c].axis("off")
    fig.suptitle(f"frame {ids[t]}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def picture_label_map(path, label_map, frame_id):
    Image.fromarray(label_colors(np.asarray(label_map))).save(path)
