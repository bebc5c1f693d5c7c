"""How far the texture is registered from the truth on a finished synthetic run, and what that
costs in PSNR: the part of the ground-truth scores no texture method can win back.

    python benchmarks/bench_registration.py results/paper [--every 5] [--frames 26,130,208]

Reads (never writes) the run's scene (truth), template, tracking, projection, texcoords (when the
run optimised ξ), frames and truth stores.

1. Every ``--every``-th frame, over the vertices the projection stage marks visible: the distance
   in colour pixels of Φ (the tracked vertices projected) and of ξ (the optimised texture
   coordinates) to the true projection of the same surface point (the true vertices carried to
   the template's topology by its embedding, as the evaluation does), |ξ − Φ|, and the tracked
   vertices' distance to the true ones (mm). Medians and 90th percentiles over all (frame,
   vertex) pairs, and the range of the per-frame medians. And the tracker's error split as
   ``bench_texcoords.py`` splits its synthetic drift: Eq. 1 cannot see a sliding of the texture
   that is the same in every frame, so the per-vertex mean of (tracked − true) over the frames
   that see the vertex (in the object's frame, where a sliding lives; the scene's rigid motion
   rebuilt from its stored settings) is out of reach of any photometric correction under the
   plain-mean gauge: "|consensus − truth|" is that part, "|Φ − consensus|" the rest.
2. On each of ``--frames`` (frame ids): frame t's photo copied into the atlas at Φ and at ξ
   (:func:`stex.global_texture.projection_texture`, the per-frame projection baseline) and rendered on
   the tracked mesh in the input view, scored on the pixels of faces seen at t (inside the true
   silhouette) against the photo and against the true appearance rendered on the true mesh
   (:func:`stex.evaluation.truth_views`); the photo itself against that truth; and the photo
   against itself moved by 0.25-2 px (bicubic, inside its mask eroded by 4 px): how much detail
   the scene has at the pixel scale.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # source checkout without install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SHIFTS_PX = (0.25, 0.5, 1.0, 2.0)


def _psnr(a, b, m) -> float:
    d = np.asarray(a, np.float64)[m] - np.asarray(b, np.float64)[m]
    return float(10 * np.log10(255.0 ** 2 / np.mean(d * d)))


def _project(cal, X):
    """(N, 3) depth-camera points -> (N, 2) colour pixels (no distortion: synthetic scenes)."""
    from stex.camera import project_points, transform_points

    return project_points(transform_points(cal.depth_to_color, np.asarray(X, np.float64)), cal.color.K)[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--every", type=int, default=5, help="part 1: every k-th frame")
    ap.add_argument("--frames", default=None,
                    help="part 2: comma-separated frame ids (default: three spread over the run)")
    a = ap.parse_args(argv)

    from stex.global_texture import projection_texture
    from stex.camera import Calibration
    from stex.evaluation import Atlas, frame_views, method_views, truth_views
    from stex.io import FrameSequence, open_store
    from stex.mesh import transfer_vertices
    from stex.sampling import TexelSampler

    R = a.results
    scene = open_store(R / "scene.zarr", "scene")
    if "truth" not in scene:
        sys.exit(f"{R}: the scene has no truth (a synthetic scene is needed)")
    ids = [int(i) for i in scene.attrs["frame_ids"]]
    cal = Calibration.from_dict(scene.attrs["calibration"])
    template = open_store(R / "template.zarr", "template")
    if "embedding" not in template:
        sys.exit(f"{R}/template.zarr has no embedding in the scene's mesh: the truth cannot be "
                 f"carried to the template")
    emb = (np.asarray(template["embedding/face"][...], np.int64),
           np.asarray(template["embedding/bary"][...], np.float64))
    true_faces = scene["template/faces"][...]
    tracked = open_store(R / "tracking.zarr", "tracking")["vertices"]
    proj = open_store(R / "projection.zarr", "projection")
    has_xi = (R / "texcoords.zarr").exists()
    xi_store = open_store(R / "texcoords.zarr", "texcoords") if has_xi else None

    def true_surface(t):
        return transfer_vertices(np.asarray(scene["truth/vertices"][t], np.float64), true_faces, *emb)

    # the tracker's error in the object's frame, averaged per vertex over the frames that see it
    from stex.synth.scene import SyntheticScene

    synth = SyntheticScene(scene.attrs["params"]["source"]["synthetic"])
    rotations = [synth.object_to_depth(synth.time_of(t))[:3, :3] for t in range(len(ids))]
    error_sum = np.zeros((tracked.shape[1], 3))
    seen_count = np.zeros(tracked.shape[1])
    sampled = range(0, len(ids), a.every)
    surfaces = {}                                   # the true surfaces of part 1's frames
    for t in range(len(ids)):
        vis = np.asarray(proj["vertex_visible"][t], bool)
        X = true_surface(t)
        if t in sampled:
            surfaces[t] = X
        err = (np.asarray(tracked[t], np.float64) - X) @ rotations[t]
        error_sum[vis] += err[vis]
        seen_count[vis] += 1
    mean_error = error_sum / np.maximum(seen_count, 1)[:, None]

    # 1. registration of every k-th frame
    pools = {"|Φ − truth| (px)": [], "|ξ − truth| (px)": [], "|ξ − Φ| (px)": [],
             "|consensus − truth| (px)": [], "|Φ − consensus| (px)": [], "|ξ − consensus| (px)": [],
             "|tracked − truth| (mm)": []}
    for t in sampled:
        X = surfaces[t]
        vis = np.asarray(proj["vertex_visible"][t], bool)
        if has_xi:
            vis &= np.asarray(xi_store["valid"][t], bool)
        truth_px = _project(cal, X[vis])
        consensus_px = _project(cal, X[vis] + mean_error[vis] @ rotations[t].T)
        phi = np.asarray(proj["phi"][t], np.float64)[vis]
        pools["|Φ − truth| (px)"].append(np.linalg.norm(phi - truth_px, axis=1))
        pools["|consensus − truth| (px)"].append(np.linalg.norm(consensus_px - truth_px, axis=1))
        pools["|Φ − consensus| (px)"].append(np.linalg.norm(phi - consensus_px, axis=1))
        if has_xi:
            xi = np.asarray(xi_store["xi"][t], np.float64)[vis]
            pools["|ξ − truth| (px)"].append(np.linalg.norm(xi - truth_px, axis=1))
            pools["|ξ − Φ| (px)"].append(np.linalg.norm(xi - phi, axis=1))
            pools["|ξ − consensus| (px)"].append(np.linalg.norm(xi - consensus_px, axis=1))
        pools["|tracked − truth| (mm)"].append(
            1000 * np.linalg.norm(np.asarray(tracked[t], np.float64)[vis] - X[vis], axis=1))
    n = len(sampled)
    print(f"{R}: {len(ids)} frames, colour {cal.color.width}x{cal.color.height} fx {cal.color.K[0, 0]:g}; "
          f"registration over every {a.every}th frame ({n} frames, visible vertices)")
    for name, pool in pools.items():
        if not pool:
            continue
        allv = np.concatenate(pool)
        per = [float(np.median(p)) for p in pool]
        print(f"  {name}: median {np.median(allv):.2f}, p90 {np.percentile(allv, 90):.2f}; "
              f"per-frame medians {min(per):.2f}-{max(per):.2f}")

    # 2. what that costs on frames of their own
    frames = ([int(f) for f in a.frames.split(",")] if a.frames
              else [ids[len(ids) // 10], ids[len(ids) // 2], ids[(4 * len(ids)) // 5]])
    photos = FrameSequence(sorted((R / "frames").glob("block_*.zarr")), "frames")
    truth = FrameSequence(sorted((R / "truth").glob("block_*.zarr")), "truth")
    atlas, true_atlas = Atlas.from_store(template), Atlas.from_store(scene, "template/")
    sampler = TexelSampler(template["texel/face_id"][...], template["texel/bary"][...], atlas.faces)
    coords = {"Φ": proj["phi"]}
    if has_xi:
        coords["ξ"] = xi_store["xi"]
    print("PSNR (dB) on the pixels of faces seen at the frame: the photo projected into the atlas "
          "and rendered on the tracked mesh, against the photo / against the truth")
    for fid in frames:
        t = ids.index(fid)
        photo = photos.read("color", fid)
        visible = np.asarray(proj["face_visible"][t], bool)
        tv = truth_views(scene["truth/vertices"][t], true_atlas, truth.read("appearance", fid), cal)
        t_img, t_mask = tv["input"]
        geom = frame_views(tracked[t], atlas, cal, None, visible)
        m = geom["input"].mask & geom["input_seen"] & t_mask
        parts = []
        for name, c in coords.items():
            tex, _ = projection_texture(sampler, np.asarray(c[t], np.float64), visible, photo)
            rec = method_views(tex, tracked[t], atlas, cal, geometry=geom)["input"][0]
            parts.append(f"at {name} {_psnr(photo, rec, m):.2f} / {_psnr(t_img, rec, m):.2f}")
        parts.append(f"the photo against the truth {_psnr(t_img, photo, m):.2f}")
        inner = cv2.erode(truth.read("mask", fid).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        p32 = photo.astype(np.float32)
        moved = []
        for s in SHIFTS_PX:
            q = cv2.warpAffine(p32, np.float32([[1, 0, s], [0, 1, 0]]), (p32.shape[1], p32.shape[0]),
                               flags=cv2.INTER_CUBIC)
            moved.append(f"{s:g} px {_psnr(p32, q, inner):.2f}")
        print(f"  frame {fid} ({int(m.sum())} px): " + "; ".join(parts)
              + "; the photo moved by " + ", ".join(moved))


if __name__ == "__main__":
    main()
