"""Benchmark the template stage on a 100k-face input (acceptance: decimation + atlas <= 30 s).

Input: the bumpy sphere of ``stex.synth.shapes`` at subdivision 7 (327,680 faces), decimated once
(untimed) to 100,000 faces. Timed, median of ``--runs`` runs each: cleaning, decimation to
``--target`` faces, the UV atlas (``--size`` texels, ``--gutter`` texels), the embedding in the
input surface, the texel map; plus one end-to-end :func:`stex.template.prepare_template`.
Reports the mirrored UV triangles xatlas produced and how many remain (must be 0), texcoords
outside [0, 1] (must be 0), and the smallest empty-texel gap between two charts and between a
chart and the atlas border (both must be at least the gutter).

With ``--own-layout`` the input first gets a UV layout of its own (xatlas, untimed), and the
template stage keeps it (``template.uv: mesh``): timed, the texture-aware decimation and
:func:`stex.atlas.keep_layout` (which checks it for overlaps); reported, how far each texel's
surface point moved (the layout must follow the surface through the decimation).

    python benchmarks/bench_template.py [--runs 3] [--target 20000] [--size 4096] [--gutter 4] [--own-layout]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

try:
    from stex import atlas as A
    from stex import mesh as M
    from stex import template as T
    from stex.readers.meshes import Mesh
    from stex.synth.shapes import bumpy_sphere
except ImportError:  # run from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stex import atlas as A
    from stex import mesh as M
    from stex import template as T
    from stex.readers.meshes import Mesh
    from stex.synth.shapes import bumpy_sphere


def _timed(fn, runs):
    times, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, times


def _line(name, times):
    t = np.asarray(times)
    print(f"{name:<34s} median {np.median(t):7.2f} s   min {t.min():7.2f} s   max {t.max():7.2f} s   (n={t.size})")
    return float(np.median(t))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--input-faces", type=int, default=100_000)
    ap.add_argument("--target", type=int, default=20_000)
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--gutter", type=int, default=4)
    ap.add_argument("--own-layout", action="store_true", help="also: keep the input's own UV layout (template.uv: mesh)")
    args = ap.parse_args(argv)

    V, F = bumpy_sphere(subdivisions=7)
    V, F = M.decimate(V, F, args.input_faces)
    print(f"input: {len(F)} faces, {len(V)} vertices; target {args.target} faces, atlas {args.size}^2, "
          f"gutter {args.gutter} px; {args.runs} runs per step")

    (Vc, Fc, _), t_clean = _timed(lambda: M.clean_mesh(V, F), args.runs)
    (Vd, Fd), t_dec = _timed(lambda: M.decimate(Vc, Fc, args.target), args.runs)
    (face, bary, closest, dist), t_emb = _timed(lambda: M.embed_vertices(Vd, V, F), args.runs)
    (tc, tf, info), t_atlas = _timed(lambda: A.build_atlas(closest, Fd, args.size, args.gutter, return_info=True), args.runs)
    (fid, _), t_tex = _timed(lambda: A.texel_map(tc, tf, args.size), args.runs)
    m_clean = _line("clean_mesh", t_clean)
    m_dec = _line(f"decimate -> {len(Fd)} faces", t_dec)
    m_emb = _line("embed_vertices", t_emb)
    m_atlas = _line("build_atlas", t_atlas)
    _line("texel_map", t_tex)
    print(f"  atlas: charting {info['time_chart_s']:.2f} s + packing {info['time_pack_s']:.2f} s (last run), "
          f"{info['charts']} charts, utilization {100 * info['utilization']:.1f} %, "
          f"{info['texels_per_unit']:.0f} texels/m")
    print(f"decimation + atlas (medians): {m_dec + m_atlas:.2f} s  "
          f"(+ clean + embedding: {m_clean + m_dec + m_emb + m_atlas:.2f} s; acceptance <= 30 s)")

    flipped = int(A.uv_flipped(tc, tf).sum())
    outside = int(((tc < 0) | (tc > 1)).any(1).sum())
    chart = A.uv_charts(tf)
    gap = 0
    while A.gutter_conflicts(fid, chart, gap + 1) == 0 and gap < 4 * args.gutter + 8:
        gap += 1
    missing = len(Fd) - len(np.unique(fid[fid >= 0]))
    to_border = A.border_gap(fid)
    print(f"mirrored UV triangles: xatlas {info['flipped_xatlas']} of {len(Fd)} "
          f"({info['flipped_charts']} charts) -> after fix {flipped}")
    print(f"texcoords outside [0,1]: {outside}; smallest gap between charts: {gap} empty texels, "
          f"to the atlas border: {to_border} (gutter {args.gutter}); faces covering no texel centre: {missing}")
    print(f"embedding: largest move onto the input surface {1e3 * dist.max():.3f} mm")

    t0 = time.perf_counter()
    out = T.prepare_template(Mesh(V, F), dict(decimate=True, target_faces=args.target,
                                              atlas_size=args.size, gutter_px=args.gutter))
    print(f"prepare_template end to end: {time.perf_counter() - t0:.2f} s  "
          f"(steps: {', '.join(f'{k} {v:.2f}' for k, v in out['attrs']['timings_s'].items())})")
    ok = flipped == 0 and outside == 0 and min(gap, to_border) >= args.gutter and m_dec + m_atlas <= 30
    print("acceptance:", "PASS" if ok else "FAIL")
    if args.own_layout:
        ok = own_layout(V, F, args) and ok
    return 0 if ok else 1


def _surface_at_texels(V, F, tc, tf, size):
    fid, bary = A.texel_map(tc, tf, size)
    hit = fid >= 0
    p = np.zeros(fid.shape + (3,))
    p[hit] = np.einsum("nk,nkd->nd", bary[hit].astype(np.float64), np.asarray(V, np.float64)[np.asarray(F)[fid[hit]]])
    return p, hit


def own_layout(V, F, args) -> bool:
    """template.uv: mesh on the same input, given a layout of its own first."""
    tc_in, tf_in = A.build_atlas(V, F, args.size, args.gutter)
    corner_uv = np.asarray(tc_in, np.float64)[tf_in]
    print(f"own layout: the input's xatlas layout ({A.uv_charts(tf_in).max() + 1} charts) kept (template.uv: mesh)")
    (Vd, Fd, cd), t_dec = _timed(lambda: M.decimate(V, F, args.target, corner_uv=corner_uv), args.runs)
    (tc, tf, info), t_keep = _timed(lambda: A.keep_layout(cd, args.size), args.runs)
    m_dec = _line(f"decimate with texture -> {len(Fd)} faces", t_dec)
    m_keep = _line("keep_layout (checks, overlaps)", t_keep)
    p_in, hit_in = _surface_at_texels(V, F, tc_in, tf_in, args.size)
    p_out, hit_out = _surface_at_texels(Vd, Fd, tc, tf, args.size)
    both = hit_in & hit_out
    d = np.linalg.norm(p_in[both] - p_out[both], axis=1)
    extent = float(np.ptp(V, axis=0).max())
    print(f"  texels still covered: {100 * both.sum() / hit_in.sum():.1f} %; surface point moved: median "
          f"{1e3 * np.median(d):.2f} mm, 99th percentile {1e3 * np.percentile(d, 99):.2f} mm (object {extent:.2f} m "
          f"across); overlap texels {info['overlap_texels']}, mirrored {info['mirrored_faces']}")
    print(f"decimation + kept layout (medians): {m_dec + m_keep:.2f} s (the atlas criterion, <= 30 s)")
    return info["overlap_texels"] == 0 and m_dec + m_keep <= 30


if __name__ == "__main__":
    sys.exit(main())
