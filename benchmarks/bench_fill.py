"""The fill of never-seen faces (volume.fill), before / after, on a synthetic run.

Two measures, both per fill (``nearest``: the blend of the nearest seen surface points;
``harmonic[:<screen_length>]``: the seam-aware screened harmonic fill of stex.fill):

**Texture space** (default; needs the run's scene, truth, template and labels, or the
projection store, whose faces visible or glimpsed in no frame then stand for the never-seen
ones): every ``--stride``-th frame's true appearance is carried into the template atlas
(stex.resample), its texels of seen faces are the fill's boundary (``--boundary truth``, the fill
alone; ``volume``: the run's volume slices, what the stage really holds) and the texels of
never-seen faces are filled and compared with the truth:

- ``PSNR, dB``: over the filled texels of all scored frames (one pooled mean squared error);
- ``seam step``: mean |Δ| (grey levels) of the bilinear values on the two sides of the atlas
  seams whose both sides are filled texels (seams inside the filled region); ``truth``: the same
  on the true appearance;
- ``edge step``: mean |Δ| over 4-neighbour texel pairs in one chart, one filled and one seen
  (``truth``: the same pairs on the true appearance);
- ``flicker``: mean |Δ| of the filled texels between frame t − 1 and t (``truth``: the truth's);
- ``CPU ms``: CPU time of the fill per slice (this process; set-up once per job beside it).

With ``--correct`` the filled slices are scored after the colour correction (default settings;
the seen texels labelled with the slice's own frame, so kept): the correction itself smooths a
region without labels, and what matters is what is left after it.

**Rendered** (``--evaluate BLOCKS``, a finished run): those frame blocks' volume and correction
stages are run again with each fill into a scratch folder and the evaluation scores the slices
beside the run's own against the truth: ``gt_novel_psnr_never_seen`` (novel view, surface no
source frame saw), ``gt_truegeom_psnr_never_seen`` (texture on the true surface), corrected and
uncorrected, and the volume stage's CPU seconds per block. Every block but the first can be
scored, from its second frame on (the flicker needs each frame's predecessor).

    python benchmarks/bench_fill.py results/demo --stride 10 --fills nearest,harmonic:0.0625
    python benchmarks/bench_fill.py results/demo --evaluate 3,9
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex.config import section_params
from stex.correction import CorrectionSystem
from stex.fill import SeamFill
from stex.io import FrameSequence, open_store, run_block_paths
from stex.resample import atlas_transfer
from stex.sampling import nearest_seen_texels
from stex.stages.correction import write_corrected
from stex.stages.evaluation import evaluate_results
from stex.stages.volume import write_volume
from stex.texel_graph import texel_graph


def _fill_params(spec: str) -> dict:
    """``nearest`` or ``harmonic[:screen_length]`` -> the volume settings that select it."""
    kind, _, length = spec.partition(":")
    if kind not in ("nearest", "harmonic"):
        raise SystemExit(f"--fills: {spec!r} is not nearest or harmonic[:screen_length]")
    out = {"fill": kind}
    if kind == "harmonic" and length:
        out["fill_screen_length"] = float(length)
    return out


def _coords(R: Path) -> Path:
    obs = R / "observations.zarr"
    if obs.exists() and open_store(obs, "observations").attrs.get("coordinates") == "texcoords":
        return R / "texcoords.zarr"
    return R / "projection.zarr"


def rerun_block(R: Path, block: int, fill: dict, out: Path) -> dict:
    """The volume and correction stages of one block with ``fill``; their CPU and wall s."""
    scene = open_store(R / "scene.zarr", "scene")
    vol_run = open_store(run_block_paths(R, "volume", scene)[block], "volume")
    cor_paths = run_block_paths(R, "corrected", scene)
    vparams = {**dict(vol_run.attrs["params"]), **fill}
    first = int(vol_run.attrs["first_position"])
    stop = first + len(vol_run.attrs["frame_ids"])
    vout = out / "volume" / f"block_{block:04d}.zarr"
    cout = out / "corrected" / f"block_{block:04d}.zarr"
    c0, w0 = time.process_time(), time.perf_counter()
    write_volume(R / "template.zarr", R / "labels.zarr", _coords(R), run_block_paths(R, "frames", scene),
                 [first, stop], vparams, vout, projection_path=R / "projection.zarr")
    c1, w1 = time.process_time(), time.perf_counter()
    cparams = dict(open_store(cor_paths[block], "corrected").attrs["params"])
    # the run's own previous corrected slice: the filled texels are not coupled in time
    # (the temporal term acts on borrowed texels), so it stands in for this fill's own
    write_corrected(R / "template.zarr", vout, cparams, cout,
                    previous_path=cor_paths[block - 1] if block > 0 else None)
    return {"volume_cpu_s": c1 - c0, "volume_wall_s": w1 - w0,
            "correction_cpu_s": time.process_time() - c1}


def never_seen_faces(R: Path) -> np.ndarray:
    """(F,) bool: the labels' ``never_seen``, else the faces visible or glimpsed in no frame."""
    if (R / "labels.zarr").exists():
        return np.asarray(open_store(R / "labels.zarr", "labels")["never_seen"][...], bool)
    pr = open_store(R / "projection.zarr", "projection")
    return ~(np.asarray(pr["face_visible"][...], bool).any(0) | np.asarray(pr["face_glimpsed"][...], bool).any(0))


class _Seams:
    """Seam rows and texel pairs of the atlas, split by filled / seen texels."""

    def __init__(self, T, never):
        tf = np.asarray(T["texel/face_id"][...])
        g = texel_graph(tf, T["face_chart"][...], T["texcoords"][...], T["texcoord_faces"][...],
                        T["faces"][...], T["adjacency/pairs"][...], T["adjacency/edges"][...])
        self.g = g
        self.filled = never[np.maximum(tf.ravel()[g.index], 0)]            # per unknown
        S = g.S.tocsr()
        nnz_filled = np.add.reduceat(self.filled[S.indices].astype(np.int64), S.indptr[:-1]) \
            if S.nnz else np.zeros(0, np.int64)
        self.S = S[nnz_filled == np.diff(S.indptr)]                        # both sides filled
        self.edge = self.filled[g.p] != self.filled[g.q]

    def values(self, img):
        return np.asarray(img).reshape(-1, 3)[self.g.index].astype(np.float64)

    def seam_step(self, f):
        return float(np.abs(self.S @ f).mean()) if self.S.shape[0] else float("nan")

    def edge_step(self, f):
        return float(np.abs(f[self.g.p[self.edge]] - f[self.g.q[self.edge]]).mean())


def _corrector(T, W):
    """The correction stage's system with the default settings (stex.stages.correction)."""
    p = section_params("correction")
    return CorrectionSystem(T["texel/face_id"][...], T["texcoords"][...], T["texcoord_faces"][...], T["faces"][...],
                            T["adjacency/pairs"][...], T["adjacency/edges"][...], T["face_chart"][...],
                            factor=max(1, W // int(p["solve_size"])), screen_length=p["screen_length"],
                            seam_weight=p["seam_weight"], temporal_length=None, tol=p["tol"],
                            boundary_gradient=p["boundary_gradient"], keep_own_frame=True, gutter_px=0)


def texture_space(R: Path, fills, stride: int, boundary: str, correct: bool = False) -> list[dict]:
    """Per fill, the texture-space figures of the module docstring; with ``correct`` after the
    colour correction (the seen texels labelled with the slice's own frame: kept)."""
    scene = open_store(R / "scene.zarr", "scene")
    T = open_store(R / "template.zarr", "template")
    never = never_seen_faces(R)
    tf, tb = np.asarray(T["texel/face_id"][...]), np.asarray(T["texel/bary"][...])
    faces, verts = np.asarray(T["faces"][...]), np.asarray(T["vertices"][...])
    transfer = atlas_transfer(tf, tb, verts, faces, scene["template/vertices"][...], scene["template/faces"][...],
                              scene["template/texcoords"][...], scene["template/texcoord_faces"][...],
                              gutter_px=0)
    truth = FrameSequence(run_block_paths(R, "truth", scene), "truth")
    vol = FrameSequence(run_block_paths(R, "volume", scene), "volume") if boundary == "volume" else None
    ids = list(truth.frame_ids)
    scored = ids[1::stride]
    cov = tf >= 0
    hole = cov & never[np.maximum(tf, 0)] & transfer.reads
    seams = _Seams(T, never)
    c0 = time.process_time()
    dst, src, weight = nearest_seen_texels(tf, tb, verts, faces, never)
    setup_nearest = time.process_time() - c0
    systems = {}
    for spec in fills:
        if spec != "nearest":
            c0 = time.process_time()
            systems[spec] = SeamFill(tf, T["face_chart"][...], T["texcoords"][...], T["texcoord_faces"][...],
                                     faces, T["adjacency/pairs"][...], T["adjacency/edges"][...], never,
                                     screen_length=_fill_params(spec).get("fill_screen_length",
                                                                         section_params("volume")["fill_screen_length"]))
            systems[spec].setup_cpu_s = time.process_time() - c0
    corrector = _corrector(T, tf.shape[0]) if correct else None
    own = np.where(cov & ~never[np.maximum(tf, 0)], 0, -1).astype(np.int32)
    acc = {spec: {"se": 0.0, "n": 0, "seam": [], "edge": [], "flicker": [], "cpu": []} for spec in fills}
    acc["truth"] = {"seam": [], "edge": [], "flicker": []}
    print(f"{R}: {int(never.sum())} never-seen faces, {int(hole.sum())} texels; frames {scored}", flush=True)
    for fid in scored:
        prev_out = {}
        for k, f in enumerate((ids[ids.index(fid) - 1], fid)):
            true = transfer.apply(truth.read("appearance", f))
            base = true if vol is None else np.array(vol.read("texture", f))
            tv = seams.values(true)
            if k == 1:
                acc["truth"]["seam"].append(seams.seam_step(tv))
                acc["truth"]["edge"].append(seams.edge_step(tv))
                acc["truth"]["flicker"].append(float(np.abs(true[hole].astype(float) - prev_out["truth"][hole]).mean()))
            prev_out_f = {"truth": true}
            for spec in fills:
                tex = np.array(base, order="C", copy=True)
                c0 = time.process_time()
                flat = tex.reshape(-1, 3)
                flat[dst] = np.round(np.einsum("nk,nkc->nc", weight, flat[src].astype(np.float32)))
                if spec in systems:
                    systems[spec].fill(tex)
                cpu = time.process_time() - c0
                if corrector is not None:
                    tex = corrector.correct(tex, own, frame=0)
                prev_out_f[spec] = tex
                if k == 1:
                    a = acc[spec]
                    d = tex[hole].astype(np.float64) - true[hole]
                    a["se"] += float((d ** 2).sum())
                    a["n"] += d.size
                    fv = seams.values(tex)
                    a["seam"].append(seams.seam_step(fv))
                    a["edge"].append(seams.edge_step(fv))
                    a["flicker"].append(float(np.abs(tex[hole].astype(float) - prev_out[spec][hole]).mean()))
                    a["cpu"].append(cpu)
            prev_out = prev_out_f
        print(f"  frame {fid}: " + ", ".join(f"{spec} {10 * np.log10(255 ** 2 / (acc[spec]['se'] / acc[spec]['n'])):.2f} dB"
                                            for spec in fills), flush=True)
    rows = []
    for spec in fills:
        a = acc[spec]
        rows.append({"fill": spec, "psnr_db": float(10 * np.log10(255 ** 2 / (a["se"] / a["n"]))),
                     "seam_step": float(np.mean(a["seam"])), "edge_step": float(np.mean(a["edge"])),
                     "flicker": float(np.mean(a["flicker"])), "cpu_ms": 1e3 * float(np.mean(a["cpu"])),
                     "setup_cpu_s": setup_nearest + getattr(systems.get(spec), "setup_cpu_s", 0.0)})
    rows.append({"fill": "truth", **{k: float(np.mean(v)) for k, v in acc["truth"].items()}})
    return rows


def print_texture_table(R, rows, boundary, stride, correct):
    t = rows[-1]
    print(f"\n{R}: texture space, boundary {boundary}, every {stride}th frame"
          f"{', corrected' if correct else ''}; grey levels of 255")
    print("| fill | PSNR, dB | seam step (truth) | edge step (truth) | flicker (truth) | CPU ms per slice (set-up s) |")
    print("|---|---|---|---|---|---|")
    for r in rows[:-1]:
        print(f"| {r['fill']} | {r['psnr_db']:.2f} | {r['seam_step']:.2f} ({t['seam']:.2f}) | "
              f"{r['edge_step']:.2f} ({t['edge']:.2f}) | {r['flicker']:.2f} ({t['flicker']:.2f}) | "
              f"{r['cpu_ms']:.0f} ({r['setup_cpu_s']:.1f}) |")


def rendered(R: Path, fills, blocks, out: Path) -> list[dict]:
    """Per fill, the rendered figures of the module docstring (volume and correction redone)."""
    scene = open_store(R / "scene.zarr", "scene")
    n_blocks = len(scene.attrs["frame_blocks"])
    if not blocks or min(blocks) < 1 or max(blocks) >= n_blocks:
        raise SystemExit(f"--evaluate: blocks must be among 1..{n_blocks - 1} (block 0 has no predecessor)")
    times, others, frames = {}, {}, []
    for b in blocks:
        frames += list(open_store(run_block_paths(R, "volume", scene)[b], "volume").attrs["frame_ids"])[1:]
    for spec in fills:
        name = spec.replace(":", "_")
        times[name] = [rerun_block(R, b, _fill_params(spec), out / name) for b in blocks]
        others[f"{name}_corrected"] = str(out / name / "corrected")
        others[f"{name}_volume"] = str(out / name / "volume")
        print(f"{name}: blocks {blocks} redone, volume CPU {[round(t['volume_cpu_s'], 1) for t in times[name]]} s",
              flush=True)
    summ = evaluate_results(R, out / "evaluation", others=others, frames=frames, stride=1)["summary"]["all"]
    rows = []
    for spec in fills:
        name = spec.replace(":", "_")
        c, v = summ[f"{name}_corrected"], summ[f"{name}_volume"]
        rows.append({"fill": spec, "never_seen_db": c["gt_novel_psnr_never_seen"]["mean"],
                     "never_seen_uncorrected_db": v["gt_novel_psnr_never_seen"]["mean"],
                     "true_surface_db": c["gt_truegeom_psnr_never_seen"]["mean"],
                     "n_frames": c["gt_novel_psnr_never_seen"]["n"],
                     "volume_cpu_s": float(np.mean([t["volume_cpu_s"] for t in times[name]])),
                     "volume_wall_s": float(np.mean([t["volume_wall_s"] for t in times[name]]))})
    print(f"\n{R}: rendered, blocks {blocks}, {len(frames)} frames scored; CPU s per volume block")
    print("| fill | never seen, dB | uncorrected, dB | true surface, dB | frames | volume CPU s (wall) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['fill']} | {r['never_seen_db']:.2f} | {r['never_seen_uncorrected_db']:.2f} | "
              f"{r['true_surface_db']:.2f} | {r['n_frames']} | {r['volume_cpu_s']:.1f} ({r['volume_wall_s']:.1f}) |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="a synthetic run, results/<scene>")
    ap.add_argument("--fills", default="nearest,harmonic",
                    help="fills to compare: nearest, harmonic[:screen_length] (default nearest,harmonic)")
    ap.add_argument("--stride", type=int, default=10, help="texture space: every k-th frame (default 10)")
    ap.add_argument("--boundary", choices=("truth", "volume"), default="truth",
                    help="texture space: the seen texels, the truth's or the run's volume slices")
    ap.add_argument("--correct", action="store_true",
                    help="texture space: score the slices after the colour correction (default settings)")
    ap.add_argument("--evaluate", default=None, metavar="BLOCKS",
                    help="instead: redo these frame blocks' volume and correction and score them rendered")
    ap.add_argument("--out", type=Path, default=None, help="--evaluate's scratch folder (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None, help="also write the table's figures here")
    a = ap.parse_args(argv)
    fills = [s.strip() for s in a.fills.split(",") if s.strip()]
    for spec in fills:
        _fill_params(spec)
    if a.evaluate:
        out = a.out or Path(tempfile.mkdtemp(prefix="bench_fill_"))
        rows = rendered(a.results, fills, sorted({int(b) for b in a.evaluate.split(",")}), out)
    else:
        rows = texture_space(a.results, fills, max(1, a.stride), a.boundary, a.correct)
        print_texture_table(a.results, rows, a.boundary, a.stride, a.correct)
    if a.json:
        a.json.write_text(json.dumps({"results": str(a.results), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
