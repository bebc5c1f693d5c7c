"""Labeling against the synthetic ground truth, solver checks and ablations (issue 5).

On a finished synthetic run (``snakemake --cores 2`` → results/demo) this measures:

1. **Ground truth** — for every (frame t, face f) with a label, the error between the true
   appearance of f at the chosen source frame l and at t (mean |ΔRGB| over the face's corners,
   grey levels; the true appearance is sampled from the truth atlas through the template's
   embedding), against a label chosen by E_qual alone (among the frames that see f, the lowest
   E_qual, ties to the nearest in time). Split into faces seen at t and not seen at t.
2. **α-expansion vs ICM** on every frame's initial spatial MRF (same unary and pairwise).
3. **Ablations** — the labeling re-run with temporal off / constant / selective and spatial
   selective weighting on/off (into a scratch folder): ground-truth error, label switches over
   time, energy.
4. **Pruning** (``--prune-check``) — tables re-run with every visible frame as a candidate (no
   pruning) and the labeling compared with the pruned one: label agreement and energies.

    python benchmarks/bench_labeling.py results/demo [--ablations] [--prune-check]
        [--scratch /tmp/stex_bench_labeling]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

try:
    import stex  # noqa: F401
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stex.io import FrameSequence, open_store
from stex.labeling import EdgeFeatures, frame_problem
from stex.stages.labeling import labeling_inputs, write_labels
from stex.render import sample_bilinear


def true_face_colours(results: Path) -> np.ndarray:
    """(T, F, 3) float32 true appearance of every template face at every frame (mean over its
    three corners, each mapped to the truth atlas through the template's embedding)."""
    scene = open_store(results / "scene.zarr", "scene")
    template = open_store(results / "template.zarr", "template")
    tc = np.asarray(scene["template/texcoords"][...], np.float64)
    tcf = np.asarray(scene["template/texcoord_faces"][...], np.int64)
    g = np.asarray(template["embedding/face"][...], np.int64)
    b = np.asarray(template["embedding/bary"][...], np.float64)
    uv = np.einsum("vk,vkd->vd", b, tc[tcf[g]])                    # (V, 2) in [0, 1]
    faces = np.asarray(template["faces"][...], np.int64)
    truth = FrameSequence(sorted((results / "truth").glob("block_*.zarr")), "truth")
    out = []
    for fid in truth.frame_ids:
        app = truth.read("appearance", fid)
        W = app.shape[0]
        col = sample_bilinear(app, uv * W - 0.5)                    # (V, 3)
        out.append(col[faces].mean(axis=1))
    return np.asarray(out, np.float32)


def qual_only_labels(face_visible, e_qual) -> np.ndarray:
    """(T, F) the E_qual-only label: lowest E_qual among the frames that see the face, ties to
    the nearest frame in time; -1 for never-seen faces."""
    T, F = face_visible.shape
    t = np.arange(T)
    score = np.where(face_visible, e_qual * T * 4.0, np.inf)        # E_qual dominates the tie-break
    out = np.full((T, F), -1, np.int32)
    for k in range(T):
        s = score + np.abs(t - k)[:, None]
        best = np.argmin(s, axis=0)
        out[k] = np.where(np.isfinite(s[best, np.arange(F)]), best, -1)
    return out


def gt_error(labels, colours, face_visible) -> dict:
    L = np.asarray(labels)
    T, F = L.shape
    ok = L >= 0
    t_idx = np.broadcast_to(np.arange(T)[:, None], (T, F))
    f_idx = np.broadcast_to(np.arange(F)[None, :], (T, F))
    err = np.abs(colours[np.where(ok, L, 0), f_idx] - colours[t_idx, f_idx]).mean(-1)
    seen = face_visible & ok
    unseen = ~face_visible & ok
    return {"all": float(err[ok].mean()), "seen_at_t": float(err[seen].mean()),
            "unseen_at_t": float(err[unseen].mean()), "n": int(ok.sum()),
            "label_switches_per_face": float(((L[1:] != L[:-1]) & ok[1:]).sum() / max(ok[0].sum(), 1))}


def alpha_vs_icm(results: Path) -> dict:
    obs = results / "observations.zarr"
    tables = sorted(str(p) for p in (results / "data_term").glob("block_*.zarr"))
    params = dict(open_store(results / "labels.zarr", "labels").attrs["params"])
    a = labeling_inputs(obs, tables, results / "template.zarr", params)
    feats = EdgeFeatures(a["edge_samples"])
    worse, gaps, times = 0, [], []
    for t in range(a["cand"].shape[0]):
        pr = frame_problem(a["cand"][t], a["unary"][t], a["pairs"], a["pair_weight"], feats)
        t0 = time.perf_counter()
        lab, _ = pr.solve()
        times.append(time.perf_counter() - t0)
        e_a, e_i = pr.energy(lab), pr.energy(pr.icm())
        worse += e_a > e_i + 1e-9
        gaps.append((e_i - e_a) / max(abs(e_i), 1e-12))
    return {"frames": len(gaps), "frames_where_alpha_worse": int(worse),
            "icm_minus_alpha_relative_median": float(np.median(gaps)),
            "icm_minus_alpha_relative_min": float(np.min(gaps)),
            "alpha_seconds_per_frame_median": float(np.median(times))}


def relabel(results: Path, scratch: Path, params: dict, tables=None) -> Path:
    tables = tables or sorted(str(p) for p in (results / "data_term").glob("block_*.zarr"))
    name = "labels_" + "_".join(f"{k}-{v}" for k, v in sorted(params.items())) + ".zarr"
    out = scratch / name
    shutil.rmtree(out, ignore_errors=True)
    base = dict(open_store(results / "labels.zarr", "labels").attrs["params"])
    proj = results / "projection.zarr"    # the run's own labeling reads it (glimpsed faces)
    write_labels(results / "observations.zarr", tables, results / "template.zarr",
                 dict(base, **params), out, projection_path=proj if proj.exists() else None)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path)
    ap.add_argument("--ablations", action="store_true")
    ap.add_argument("--prune-check", action="store_true")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/stex_bench_labeling"))
    args = ap.parse_args(argv)
    R = args.results
    args.scratch.mkdir(parents=True, exist_ok=True)
    obs = open_store(R / "observations.zarr", "observations")
    vis = np.asarray(obs["face_visible"][...], bool)
    e_qual = np.asarray(obs["blur_cost"][...], np.float32) + np.asarray(obs["slanted"][...], np.float32)
    colours = true_face_colours(R)
    labels = open_store(R / "labels.zarr", "labels")
    L = labels["labels"][...]
    never = labels["never_seen"][...]
    res = {"faces": int(L.shape[1]), "never_seen": int(never.sum()),
           "coverage_of_seen_faces": float((L[:, ~never] >= 0).mean()),
           "energy_per_round": [round(float(e), 3) for e in labels["energy"][...]],
           "energy_non_increasing": bool(np.all(np.diff(labels["energy"][...]) <= 1e-9)),
           "gt_ours": gt_error(L, colours, vis),
           "gt_qual_only": gt_error(qual_only_labels(vis, e_qual), colours, vis)}
    print(json.dumps(res, indent=1), flush=True)
    res["alpha_vs_icm"] = alpha_vs_icm(R)
    print(json.dumps({"alpha_vs_icm": res["alpha_vs_icm"]}, indent=1), flush=True)
    if args.ablations:
        res["ablations"] = {}
        for name, p in [("temporal off", {"temporal": "off"}),
                        ("temporal constant", {"temporal": "constant"}),
                        ("temporal selective", {"temporal": "selective"}),
                        ("selective, no spatial selective", {"spatial_selective": False}),
                        ("no selective weighting at all", {"temporal": "constant", "spatial_selective": False})]:
            g = open_store(relabel(R, args.scratch, p), "labels")
            res["ablations"][name] = dict(gt_error(g["labels"][...], colours, vis),
                                          energy=float(g["energy"][-1]))
            print(name, json.dumps(res["ablations"][name]), flush=True)
    if args.prune_check:
        from stex.stages.data_term import write_data_term
        blocks = open_store(R / "scene.zarr", "scene").attrs["frame_blocks"]
        T = vis.shape[0]
        tp = dict(open_store(sorted((R / "data_term").glob("block_*.zarr"))[0], "data_term").attrs["params"])
        full = []
        t0 = time.perf_counter()
        for b, (s, e) in enumerate(blocks):
            p = args.scratch / f"tables_full_{b}.zarr"
            shutil.rmtree(p, ignore_errors=True)
            write_data_term(R / "scene.zarr", R / "template.zarr", R / "tracking.zarr", R / "poses.zarr",
                         R / "observations.zarr", [s, e], dict(tp, candidates=T, prefilter=T), p)
            full.append(str(p))
        g = open_store(relabel(R, args.scratch, {"seed": 0}, tables=full), "labels")
        Lf = g["labels"][...]
        ok = L >= 0
        res["prune_check"] = {"candidates_pruned": tp["candidates"], "candidates_full": T,
                              "label_agreement": float((Lf[ok] == L[ok]).mean()),
                              "energy_pruned": float(labels["energy"][-1]),
                              "energy_full": float(g["energy"][-1]),
                              "gt_full": gt_error(Lf, colours, vis),
                              "seconds_full": round(time.perf_counter() - t0, 1)}
        print(json.dumps({"prune_check": res["prune_check"]}, indent=1), flush=True)
    (args.scratch / "bench_labeling.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
