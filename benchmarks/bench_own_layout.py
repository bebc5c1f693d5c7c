"""A synthetic asset reconstructed in its own UV layout, scored texel by texel against its truth.

With ``template.uv: mesh`` the slices live in the source mesh's own layout, which is also the
layout of a synthetic scene's true appearance (``truth/block_*.zarr``), so the reconstruction can
be compared with the truth in texture space over the whole surface, seen or not, without any
render. On a finished run (e.g. the Fox: ``snakemake --cores 2 --configfile
config/scenes/fox.yaml X.yaml`` with X.yaml ``{scene: fox_own_uv, template: {uv: mesh}}``) this
prints, per method, the PSNR over the texels the layout covers (each slice area-averaged to the
truth's size; texels whose footprint is only partly covered are left out), averaged over the
frames, and writes a picture of one frame: truth | ours | ours uncorrected | global texture.

    python benchmarks/bench_own_layout.py results/fox_own_uv [--frame 20] [--out fox_own_uv.jpg]
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

from stex.io import FrameSequence, open_store


def _area(img: np.ndarray, size: int) -> np.ndarray:
    import cv2

    return cv2.resize(img.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)


def _psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    mse = float(((a[where] - b[where]) ** 2).mean())
    return 10 * np.log10(255.0 ** 2 / mse)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results folder of a finished synthetic run with template.uv: mesh")
    ap.add_argument("--frame", type=int, default=20, help="frame shown in the picture")
    ap.add_argument("--out", type=Path, default=None, help="picture (.jpg/.png) of that frame")
    a = ap.parse_args()
    R = a.results
    template = open_store(R / "template.zarr", "template")
    if template.attrs.get("uv") != "mesh":
        raise SystemExit(f"{R}: the template keeps no source layout (template.uv is {template.attrs.get('uv')!r}); "
                         f"run with template: {{uv: mesh}}")
    blocks = lambda name: sorted((R / name).glob("block_*.zarr"))  # noqa: E731
    if not blocks("truth"):
        raise SystemExit(f"{R}: no truth/ stores (a synthetic source is needed)")
    truth = FrameSequence(blocks("truth"), "truth")
    ours = FrameSequence(blocks("corrected"), "corrected")
    raw = FrameSequence(blocks("volume"), "volume")
    glob = np.asarray(open_store(R / "global_texture.zarr", "global_texture")["texture"][...])
    size = truth.read("appearance", truth.frame_ids[0]).shape[0]
    W = template.attrs["atlas_size"]
    if W % size:
        raise SystemExit(f"atlas {W} is not a multiple of the truth's texture size {size}")
    # texels of the truth's size whose whole footprint in the atlas is covered
    covered = _area((np.asarray(template["texel/face_id"][...]) >= 0).astype(np.float32), size) == 1.0
    frames = [f for f in ours.frame_ids if f in truth.frame_ids]
    scores = {"ours": [], "ours, uncorrected": [], "global texture": []}
    g_small = _area(glob, size)
    for f in frames:
        t = truth.read("appearance", f).astype(np.float32)
        scores["ours"].append(_psnr(_area(ours.read("texture", f), size), t, covered))
        scores["ours, uncorrected"].append(_psnr(_area(raw.read("texture", f), size), t, covered))
        scores["global texture"].append(_psnr(g_small, t, covered))
    print(f"{R}: {len(frames)} frames, {int(covered.sum())} texels of {size}^2 ({100 * covered.mean():.1f} %)")
    for name, s in scores.items():
        s = np.asarray(s)
        print(f"  {name:18s} PSNR against the true appearance {s.mean():.2f} dB (frames: min {s.min():.2f}, "
              f"max {s.max():.2f})")
    if a.out is not None:
        import cv2

        f = a.frame if a.frame in frames else frames[len(frames) // 2]
        panels = [truth.read("appearance", f), _area(ours.read("texture", f), size), _area(raw.read("texture", f), size),
                  g_small]
        # texels outside the layout (the asset's own texture has its paint there) shown black in all
        inside = _area((np.asarray(template["texel/face_id"][...]) >= 0).astype(np.float32), size) > 0
        row = np.concatenate([np.where(inside[..., None], np.clip(p, 0, 255), 0).astype(np.uint8) for p in panels], 1)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(a.out), cv2.cvtColor(row, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
        print(f"  frame {f}: truth | ours | ours uncorrected | global texture -> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
