"""How much blur the texture's two resamplings add, by kernel and texel density (issue 56).

A photo read into a texel grid of ``s`` texels per image pixel (a smooth sub-pixel phase, as a
chart's placement gives) with the volume's kernel, then read back at the pixels bilinearly, as
the evaluation renders a slice (another smooth phase). Scored with the evaluation's blur
(``stex.metrics.blur``) in the photo's mask and in it eroded by ``evaluation.blur_interior_px``,
on every ``--stride``-th photo of a finished run. The texel density a run actually has on the
faces facing the camera is printed first (frame 0, tracked mesh, ``template.atlas_size``).

    python benchmarks/bench_blur_resample.py results/dev_body [--stride 4] [--density 1 1.5 2 3]
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
from stex.camera import Calibration, transform_points
from stex.evaluation import Atlas, evaluation_params
from stex.io import FrameSequence, open_store

KERNELS = ("bilinear", "bicubic", "lanczos4")


def texture_roundtrip(photo, density: float, kernel: str, seed: int = 0) -> np.ndarray:
    """``photo`` (H, W, 3) read into a texel grid of ``density`` texels a pixel with ``kernel``
    (one of KERNELS, OpenCV's), rounded to uint8 as a slice is, then read back at the pixels
    bilinearly; both reads at smooth sub-pixel phases within ±0.5 px (texel, resp. pixel)."""
    import cv2

    flags = {"bilinear": cv2.INTER_LINEAR, "bicubic": cv2.INTER_CUBIC, "lanczos4": cv2.INTER_LANCZOS4}
    if kernel not in flags:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if density <= 0:
        raise ValueError(f"density must be > 0 texels a pixel, got {density}")
    img = np.asarray(photo, np.float32)
    H, W = img.shape[:2]
    v, u = np.mgrid[0:int(round(H * density)), 0:int(round(W * density))].astype(np.float32)
    px = u / density + 0.5 * np.sin(u / 53 + seed) * np.cos(v / 31)
    py = v / density + 0.5 * np.cos(u / 41) * np.sin(v / 47 + seed)
    tex = np.clip(cv2.remap(img, px, py, flags[kernel], borderMode=cv2.BORDER_REPLICATE), 0, 255).round()
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    tx = xx * density + 0.5 * np.sin(xx / 37) * np.cos(yy / 23 + seed)
    ty = yy * density + 0.5 * np.cos(xx / 29 + seed) * np.sin(yy / 41)
    return cv2.remap(tex, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def texel_density(R: Path, min_cos: float = 0.5) -> float:
    """Texels per image pixel (linear: the square root of the area ratio) over the faces of the
    tracked mesh at frame 0 that face the colour camera by more than ``min_cos``."""
    scene = open_store(R / "scene.zarr", "scene")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    tpl = open_store(R / "template.zarr", "template")
    a = Atlas.from_store(tpl)
    W = int(tpl.attrs["atlas_size"])
    Vc = transform_points(cal.depth_to_color, np.asarray(open_store(R / "tracking.zarr", "tracking")["vertices"][0],
                                                          np.float64))
    p = Vc @ cal.color.K.T
    P = (p[:, :2] / p[:, 2:3])[a.faces]
    T = a.texcoords[a.texcoord_faces] * W

    def area(X):
        return 0.5 * np.abs((X[:, 1, 0] - X[:, 0, 0]) * (X[:, 2, 1] - X[:, 0, 1])
                            - (X[:, 2, 0] - X[:, 0, 0]) * (X[:, 1, 1] - X[:, 0, 1]))

    n = np.cross(Vc[a.faces[:, 1]] - Vc[a.faces[:, 0]], Vc[a.faces[:, 2]] - Vc[a.faces[:, 0]])
    c = Vc[a.faces].mean(1)
    cos = -(n * c).sum(1) / np.maximum(np.linalg.norm(n, axis=1) * np.linalg.norm(c, axis=1), 1e-12)
    sel = cos > min_cos
    return float(np.sqrt(area(T[sel]).sum() / area(P[sel]).sum()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, help="results folder of a finished run (results/dev_body)")
    ap.add_argument("--stride", type=int, default=4, help="score every n-th photo")
    ap.add_argument("--density", type=float, nargs="+", default=[1.0, 1.5, 2.0, 3.0], help="texels a pixel")
    a = ap.parse_args()
    R = a.results
    p = evaluation_params({})
    h, e = p["h_size"], p["blur_interior_px"]
    print(f"{R}: texels a pixel on faces facing the camera (cos > 0.5), frame 0: {texel_density(R):.2f}")
    photos = FrameSequence(sorted((R / "frames").glob("block_*.zarr")), "frames")
    masks = FrameSequence(sorted((R / "masks").glob("block_*.zarr")), "masks")
    ids = [int(i) for i in open_store(R / "scene.zarr", "scene").attrs["frame_ids"]]
    rows: dict = {}
    for t in range(0, len(ids), a.stride):
        photo = photos.read("color", ids[t]).astype(np.float32)
        m = np.asarray(masks.read("mask", ids[t]), bool)
        rows.setdefault(("photo", "-"), []).append((ev.blur(photo, m, h_size=h)["blur"],
                                                    ev.blur(photo, m, h_size=h, erode_px=e)["blur"]))
        for s in a.density:
            for k in KERNELS:
                r = texture_roundtrip(photo, s, k, seed=t)
                rows.setdefault((k, s), []).append((ev.blur(r, m, h_size=h)["blur"],
                                                    ev.blur(r, m, h_size=h, erode_px=e)["blur"]))
    print(f"kernel     texels/px  blur   blur, interior ({e} px)   mean of {len(rows[('photo', '-')])} photos")
    for (k, s), v in rows.items():
        b = np.mean(v, axis=0)
        print(f"{k:9s}  {s!s:>9}  {b[0]:.4f}  {b[1]:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
