"""How stex's cost grows with the sequence: the paper scene family at several lengths.

For each T the scene is ``config/scenes/paper.yaml``'s procedural body (one turn every 8.83 s at
30 fps, so a longer sequence is more turns of the same motion), at the image, mesh and atlas
size of ``--preset``; the whole default workflow runs into ``ROOT/scale_<T>`` (``--run``), and
the jobs' Snakemake benchmark files give, per stage, the wall time and the CPU time (the sum over
the stage's jobs, divided by T: seconds per frame) and the peak RSS of its largest job. The
machine may be shared: CPU time per frame is the figure to compare, wall time says how long one
waited. Prints a Markdown table, writes it beside a plot (``--out``, a PNG) and checks the
issue's acceptance: cost per frame at the longest T within 1.3x of that at T = 265, every job's
peak RSS <= 4 GB.

    python benchmarks/bench_scaling.py --frames 120,265,530,1060 --root /tmp/stex_scaling --run
        [--preset small|tiny|half|paper] [--tracking track|given] [--cores 2] [--out docs/img/scaling.png]

Without ``--run`` it only reads the runs already in ROOT (those that finished are reported).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]

#: sizes of the scene family: the paper's (2048 x 1536 colour, 20k faces, 4096² atlas) and
#: smaller ones for long sequences on a 2-core machine
PRESETS = {
    "paper": {"color": {"width": 2048, "height": 1536, "fx": 1500.0},
              "depth": {"width": 640, "height": 576, "fx": 504.0},
              "procedural": {"n_around": 144, "n_rings": 70}, "texture_size": 2048, "atlas": 4096},
    "half": {"color": {"width": 1024, "height": 768, "fx": 750.0},
             "depth": {"width": 640, "height": 576, "fx": 504.0},
             "procedural": {"n_around": 144, "n_rings": 70}, "texture_size": 1024, "atlas": 2048},
    "small": {"color": {"width": 512, "height": 384, "fx": 375.0},
              "depth": {"width": 320, "height": 288, "fx": 252.0},
              "procedural": {"n_around": 72, "n_rings": 35}, "texture_size": 512, "atlas": 1024},
    "tiny": {"color": {"width": 320, "height": 240, "fx": 234.0},
             "depth": {"width": 160, "height": 144, "fx": 126.0},
             "procedural": {"n_around": 48, "n_rings": 24}, "texture_size": 256, "atlas": 512},
}


def scene_config(T: int, preset: str, root: Path, block: int, tracking: str = "track") -> dict:
    p = PRESETS[preset]
    cfg = {"scene": f"scale_{T}", "results": str(root), "frame_block": block,
           "source": {"kind": "synthetic", "synthetic": {
               "object": "procedural", "n_frames": T, "fps": 30.0, "yaw_period_s": 8.83,
               "texture_size": p["texture_size"], "procedural": p["procedural"],
               "color": p["color"], "depth": p["depth"],
               "degradations": {"motion_blur": {"enabled": False},
                                "sensor_noise": {"enabled": True, "sigma": 2.0}}}},
           "template": {"atlas_size": p["atlas"]}, "tracking": {"mode": tracking}}
    return cfg


def run(T: int, args) -> float:
    cfg = scene_config(T, args.preset, args.root, args.block, args.tracking)
    path = args.root / f"scale_{T}.yaml"
    args.root.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    t0 = time.perf_counter()
    with open(args.root / f"scale_{T}.log", "w") as log:
        subprocess.run(["snakemake", "--cores", str(args.cores), "--configfile", str(path)],
                       cwd=REPO, stdout=log, stderr=subprocess.STDOUT, check=True)
    return time.perf_counter() - t0


def stage_table(bench_dir: Path) -> dict:
    """{stage: {"wall": s, "cpu": s, "rss": peak MB, "jobs": n}} over the stage's jobs."""
    sys.path.insert(0, str(REPO))
    from stex.reporting import benchmark_rows
    out: dict = {}
    for stage, path, row in benchmark_rows(bench_dir):
        s = out.setdefault(stage, {"wall": 0.0, "cpu": 0.0, "rss": 0.0, "jobs": 0})
        s["wall"] += float(row["s"])
        cpu = row.get("cpu_time", "")
        s["cpu"] += float(cpu) if cpu not in ("", "NA", None) else 0.0
        rss = row.get("max_rss", "")
        s["rss"] = max(s["rss"], float(rss) if rss not in ("", "NA", None) else 0.0)
        s["jobs"] += 1
    return out


def report(frames: list[int], root: Path, out_png: Path | None) -> str:
    tables = {T: stage_table(root / f"scale_{T}" / "benchmarks") for T in frames}
    done = [T for T in frames if (root / f"scale_{T}" / "evaluation" / "evaluation.json").exists()]
    stages = sorted({s for T in frames for s in tables[T]},
                    key=lambda s: -max(tables[T].get(s, {}).get("cpu", 0) / T for T in frames))
    lines = [f"runs finished: {done or 'none'} (of {frames}); CPU / wall in s per frame, "
             "peak RSS of the stage's largest job in GB", ""]
    head = "| stage | " + " | ".join(f"T={T} CPU | wall | RSS" for T in frames) + " |"
    lines += [head, "|---|" + "---|---|---|" * len(frames)]
    for s in stages:
        cells = []
        for T in frames:
            x = tables[T].get(s)
            cells += ["", "", ""] if x is None else [f"{x['cpu'] / T:.3f}", f"{x['wall'] / T:.3f}",
                                                       f"{x['rss'] / 1024:.2f}"]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    totals = {T: (sum(x["cpu"] for x in tables[T].values()) / T,
                  sum(x["wall"] for x in tables[T].values()) / T,
                  max((x["rss"] for x in tables[T].values()), default=0) / 1024) for T in frames}
    lines.append("| **all jobs** | " + " | ".join(f"**{c:.3f}** | **{w:.3f}** | **{r:.2f}**"
                                             for c, w, r in totals.values()) + " |")
    lines.append("")
    if 265 in done and len(done) > 1:
        longest = max(done)
        ratio = totals[longest][0] / totals[265][0]
        lines.append(f"CPU per frame at T = {longest} / at T = 265: {ratio:.2f} (asked: <= 1.3); "
                     f"wall: {totals[longest][1] / totals[265][1]:.2f}")
    worst = max((totals[T][2] for T in done), default=0.0)
    lines.append(f"largest peak RSS of any job: {worst:.2f} GB (asked: <= 4)")
    if out_png is not None and done:
        plot(tables, done, stages, out_png)
        lines.append(f"plot: {out_png}")
    return "\n".join(lines)


def plot(tables, frames, stages, out_png: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    bottom = [0.0] * len(frames)
    for s in stages:
        v = [tables[T].get(s, {}).get("cpu", 0.0) / T for T in frames]
        a.bar([str(T) for T in frames], v, bottom=bottom, label=s)
        bottom = [x + y for x, y in zip(bottom, v)]
    a.set_xlabel("frames T")
    a.set_ylabel("CPU seconds per frame (all jobs)")
    a.legend(fontsize=6, ncol=2)
    for s in stages:
        b.plot(frames, [tables[T].get(s, {}).get("rss", 0.0) / 1024 for T in frames], marker="o", label=s)
    b.axhline(4.0, color="k", ls="--", lw=0.8)
    b.set_xlabel("frames T")
    b.set_ylabel("peak RSS of the stage's largest job (GB)")
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="120,265,530,1060")
    ap.add_argument("--root", type=Path, default=Path("/tmp/stex_scaling"))
    ap.add_argument("--preset", choices=sorted(PRESETS), default="small")
    ap.add_argument("--block", type=int, default=32, help="frame_block of every run (one for all T)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--tracking", choices=["track", "given"], default="track",
                    help="given: the synthetic source's true meshes instead of the tracker")
    ap.add_argument("--run", action="store_true", help="run the workflow for each T (else only report)")
    ap.add_argument("--out", type=Path, help="PNG plot (and a .md table beside it)")
    args = ap.parse_args(argv)
    args.root = args.root.resolve()
    frames = [int(x) for x in args.frames.split(",")]
    if args.run:
        for T in frames:
            print(f"T = {T}: {run(T, args):.0f} s wall", flush=True)
    text = report(frames, args.root, args.out)
    print(text)
    if args.out is not None:
        args.out.with_suffix(".md").write_text(text + "\n")


if __name__ == "__main__":
    main()
