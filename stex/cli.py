"""The ``stex`` command line: tasks a user runs outside Snakemake.

    stex --version                            # the installed stex's version
    stex inspect results/demo                 # every store of a run: kind, arrays, state, size, frames
    stex inspect results/demo/scene.zarr      # what a store holds: kind, frames, arrays, params
    stex export results/demo --what mp4 --out out/   # texture volume as PNG/MP4/OBJ/glTF
    stex preview results/demo --frames 0:50 --out preview.mp4   # input | textured mesh, 2 views
    stex view results/demo --out view/       # web page playing the textured mesh (static folder)
    stex tables results/demo results/fox --out tables.html   # the paper's tables, a column per run
    stex evaluate results/demo --texture mine=my_slices/ --out eval_mine/   # another method beside ours
    stex evaluate results/demo --texture kim=their_out/ --uv-mesh kim=their_mesh.obj --out eval_kim/

Errors (missing, incomplete or damaged stores, a frame range outside the sequence) print one
line on stderr and exit with status 1; progress of long work goes to stderr as a frame counter.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

import zarr

from stex import __version__
from stex.artifacts import ARTIFACTS
from stex.export import EXPORT_KINDS, PIX_FMTS, SOURCES, output_folder, parse_frame_range, select_frames
from stex.io import StoreArray, StoreError, StoreGroup, id_ranges, open_store
from stex.reporting import runs_tables, tables_html
from stex.stages.evaluation import evaluate_results
from stex.stages.export import export_results, preview_results
from stex.viewer import IMAGE_FORMATS, write_view


def _arrays(group: StoreGroup):
    """(path, array) of every array in the store, in path order."""
    for name, member in sorted(group.members(max_depth=None), key=lambda m: m[0]):
        if isinstance(member, StoreArray):
            yield name, member


def inspect_store(path: str) -> str:
    """A human-readable summary of one artifact store."""
    try:
        raw = zarr.open_group(path, mode="r")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError, zarr.errors.NodeNotFoundError) as exc:
        stores = sorted(p.name for p in Path(path).glob("*.zarr")) if Path(path).is_dir() else []
        listed = ", ".join(stores[:6]) + (f" and {len(stores) - 6} more" if len(stores) > 6 else "")
        hint = (f"a folder of stores: {listed}" if stores
                else "give a store a run writes, e.g. results/demo/labels.zarr")
        raise StoreError(f"{path}: not a stex store ({hint})") from exc
    except zarr.errors.ContainsArrayError:
        raise StoreError(f"{path}: an array inside a store, not a store; give the store's folder "
                         f"({Path(path).parent})") from None
    except Exception as exc:  # e.g. a damaged zarr.json
        raise StoreError(f"{path}: not a readable zarr store ({type(exc).__name__}: {exc})") from exc
    kind = raw.attrs.get("stex_artifact")
    if kind not in ARTIFACTS:
        raise StoreError(f"{path}: not a stex artifact store (stex_artifact={kind!r})")
    group = open_store(path, kind)
    lines = [f"{path}: artifact '{kind}' (stex {group.attrs.get('stex_version')})",
             f"  {ARTIFACTS[kind].description}"]
    libs = group.attrs.get("libraries")
    if libs:
        lines.append("  written with " + ", ".join(f"{k} {v}" for k, v in libs.items()))
    ids = group.attrs.get("frame_ids")
    if ids:
        lines.append(f"  frames: {len(ids)} ({ids[0]}..{ids[-1]})")
    lines += _lost_note(group.attrs)
    units = group.attrs.get("units", {})
    for name, arr in _arrays(group):
        lines.append(f"  {name:28s} {str(arr.shape):24s} {str(arr.dtype):8s} {units.get(name, '')}")
    params = group.attrs.get("params")
    if params:
        lines.append("  params: " + json.dumps(params, sort_keys=True)[:400])
    return "\n".join(lines)


def is_run_folder(path) -> bool:
    """``path`` is a run's folder (``results/<scene>``: a ``scene.zarr`` inside), not a store."""
    path = Path(path)
    return path.is_dir() and not (path / "zarr.json").exists() and (path / "scene.zarr").is_dir()


def run_stores(results_dir) -> list[Path]:
    """Every store of a run folder, and every writer's unfinished one (``*.partial-*``): its
    own ``*.zarr`` first, then the frame-block stores ``<kind>/block_*.zarr``, in name order."""
    root = Path(results_dir)
    own = sorted(p for p in root.iterdir() if p.is_dir() and (p.suffix == ".zarr" or ".zarr.partial" in p.name))
    blocks = sorted(p for d in root.iterdir() if d.is_dir() and d.suffix != ".zarr"
                    for p in d.glob("block_*.zarr*") if p.is_dir())
    return own + blocks


def _disk_size(path: Path) -> str:
    """The bytes under ``path`` (every file, recursively), as B / KB / MB / GB."""
    n = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(path) for f in files)
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def _frames_covered(ids) -> str:
    """``frames 0..59, 70..79 (70)``: the runs of consecutive frame ids and their count."""
    if not ids:
        return "no per-frame arrays"
    runs = ", ".join(f"{a}..{b - 1}" if b - a > 1 else str(a) for a, b in id_ranges(ids))
    return f"frames {runs} ({len(ids)})"


def _store_line(path: Path, root: Path) -> list[str]:
    """Two lines on one store of a run: name, kind, complete or partial, size, frames; its arrays."""
    name = str(path.relative_to(root))
    try:
        raw = zarr.open_group(str(path), mode="r")
        kind = raw.attrs.get("stex_artifact")
    except Exception as exc:  # zarr raises several types for what is not a store
        return [f"  {name:34s} not a readable store ({type(exc).__name__})"]
    if kind not in ARTIFACTS:
        return [f"  {name:34s} not a stex store (stex_artifact={kind!r})"]
    group = None
    if ".zarr.partial" in path.name:  # a writer's temporary name: not in place, whatever it holds
        state = "partial"
    else:
        try:
            group, state = open_store(path, kind), "complete"
        except StoreError as exc:
            state = ("partial" if not raw.attrs.get("complete", False)
                     else f"damaged ({str(exc).removeprefix(f'{path}: ')})")
    declared = ARTIFACTS[kind].arrays
    # the required arrays are the store's main ones; a store with none (scene) shows what it has
    main = [a for a, spec in declared.items() if spec.required and a in raw] or [a for a in declared if a in raw]
    arrays = [f"{a} {tuple(raw[a].shape)} {raw[a].dtype}" for a in main]
    shown = arrays[:4] + ([f"and {len(arrays) - 4} more"] if len(arrays) > 4 else [])
    ids = (group or raw).attrs.get("frame_ids")
    return [f"  {name:34s} {kind:15s} {state:9s} {_disk_size(path):>9s}  {_frames_covered(ids)}",
            f"  {'':34s} {', '.join(shown) or 'no arrays'}"] + [f"  {'':32s}{note}" for note in _lost_note((group or raw).attrs)]


def _lost_note(attrs) -> list[str]:
    """``lost frames: 3 of 120 (40..42)`` for a tracking store that judged frames (attr
    ``lost_frames``), else nothing."""
    lost, ids = attrs.get("lost_frames"), attrs.get("frame_ids") or []
    if lost is None:
        return []
    where = f": {_frames_covered(lost)}" if lost else ""
    return [f"  lost frames (tracking quality; no texture taken from them): {len(lost)} of {len(ids)}{where}"]


def inspect_run(results_dir) -> str:
    """A human-readable summary of every store of a run folder (``results/<scene>``): each
    store's name, artifact kind, complete or partial (or damaged), size on disk, the frames it
    covers and the shapes and dtypes of its main (required) arrays."""
    root = Path(results_dir)
    stores = run_stores(root)
    scene = open_store(root / "scene.zarr", "scene")
    ids = scene.attrs.get("frame_ids") or []
    lines = [f"{root}: run of {len(ids)} frames in {len(scene.attrs.get('frame_blocks') or [])} "
             f"block(s), {len(stores)} stores ({_disk_size(root)} in the folder)"]
    for path in stores:
        lines += _store_line(path, root)
    return "\n".join(lines)


class _Counter:
    """Frame counter on stderr: rewrites one line while running, ends it when done."""

    def __init__(self, what: str):
        self.what = what
        self.live = sys.stderr.isatty()

    #: a counter line is being rewritten (not ended): an error message starts a new line
    open_line = False

    def __call__(self, done: int, total: int | None) -> None:
        text = f"{self.what}: frame {done}/{total if total is not None else '?'}"
        if self.live:
            print("\r" + text, end="\n" if done == total else "", file=sys.stderr, flush=True)
            _Counter.open_line = done != total
        elif done == total or done % 10 == 0:
            print(text, file=sys.stderr, flush=True)


def _run_export(args) -> int:
    paths = export_results(args.results, args.what, args.out, frames=args.frames,
                           source=args.source, fps=args.fps, crf=args.crf, pix_fmt=args.pix_fmt,
                           every=args.every, progress=_Counter(f"export {args.what}"))
    print(f"wrote {len(paths)} {args.what} file(s) to {args.out}")
    return 0


def _run_preview(args) -> int:
    n, w, h = preview_results(args.results, args.out, frames=args.frames, source=args.source,
                              fps=args.fps, size=args.size, progress=_Counter("preview"))
    print(f"wrote {args.out}: {n} frames, {w}x{h}")
    return 0


def _run_view(args) -> int:
    index = write_view(args.results, args.out, frames=args.frames, every=args.every,
                       source=args.source, image_format=args.format, quality=args.quality,
                       texture_size=args.texture_size, color_height=args.color_height,
                       labels=not args.no_labels, progress=_Counter("view"))
    print(f"wrote {index.parent}: open it through a static file server, e.g. "
          f"python -m http.server -d {index.parent} 8000, then http://127.0.0.1:8000/")
    return 0


def _run_tables(args) -> int:
    rst = runs_tables(args.results)
    if args.out is None:
        print(rst)
        return 0
    out = Path(args.out)
    if out.suffix not in (".rst", ".html"):
        raise ValueError(f"--out {out}: give a .rst or .html file")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(tables_html(rst) if out.suffix == ".html" else rst.encode())
    print(f"wrote {out}: {len(args.results)} run(s)")
    return 0


def _run_inspect(args) -> int:
    status = 0
    for store in args.stores:
        try:
            print(inspect_run(store) if is_run_folder(store) else inspect_store(store))
        except (StoreError, FileNotFoundError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 1
    return status


def _run_evaluate(args) -> int:
    others = {}
    for item in args.texture:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--texture {item!r}: expected NAME=PATH")
        if name in others:
            raise ValueError(f"--texture: method name {name!r} given twice")
        others[name] = path
    for item in args.uv_mesh:
        name, sep, mesh = item.partition("=")
        if not sep or not name or not mesh:
            raise ValueError(f"--uv-mesh {item!r}: expected NAME=MESH")
        if name not in others:
            raise ValueError(f"--uv-mesh {item!r}: no --texture {name}=PATH")
        if isinstance(others[name], dict):
            raise ValueError(f"--uv-mesh: method name {name!r} given twice")
        others[name] = {"slices": others[name], "uv_mesh": mesh}
    output_folder(args.out)  # the evaluation checks that it may replace it, before scoring
    frames = None
    if args.frames is not None:
        ids = open_store(f"{args.results}/scene.zarr", "scene").attrs["frame_ids"]
        frames = select_frames(ids, *parse_frame_range(args.frames))
    # the evaluation logs one line per scored frame: that is the progress
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    log = logging.getLogger("stex.evaluation")
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        res = evaluate_results(args.results, args.out, others, frames=frames, stride=args.stride,
                               threads=args.threads)
    finally:
        log.removeHandler(handler)
    print(f"wrote {args.out}: {len(res['frames'])} frames, methods {', '.join(res['methods'])}")
    print((Path(args.out) / "tables.rst").read_text())
    return 0


def _panel_size(text: str) -> int:
    value = int(text)
    if not 16 <= value <= 4096:
        raise argparse.ArgumentTypeError(f"must be 16..4096 pixels, got {value}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {value}")
    return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="stex", description=__doc__.splitlines()[0].replace("``", ""))
    parser.add_argument("--version", action="version", version=f"stex {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("inspect", help="summarise artifact stores, or every store of a run folder")
    p.add_argument("stores", nargs="+", help="stores (*.zarr) or results/<scene> folders")
    p.set_defaults(run=_run_inspect)

    frames_help = "frame ids START:STOP (STOP excluded), START:, :STOP or one id; default all"
    p = sub.add_parser("export", help="export the texture volume (PNG slices, MP4, OBJ or glTF per frame)")
    p.add_argument("results", help="results/<scene> folder holding the stores")
    p.add_argument("--what", choices=EXPORT_KINDS, required=True)
    p.add_argument("--out", required=True, help="output folder (mp4: the video is <out>/texture.mp4)")
    p.add_argument("--frames", default=None, help=frames_help)
    p.add_argument("--every", type=_positive_int, default=1, metavar="N",
                   help="every N-th frame of the range, from its first (default 1: all)")
    p.add_argument("--source", choices=SOURCES, default="corrected",
                   help="texture to export: corrected (default), volume (before colour correction) "
                        "or global (Kim et al. 2019: one texture for the sequence; png writes "
                        "<out>/global_texture.png)")
    p.add_argument("--fps", type=float, default=None,
                   help="mp4 frame rate (default: from the frames' timestamps, divided by --every)")
    p.add_argument("--crf", type=int, default=18, help="mp4 x264 quality, 0..51, lower is better (default 18)")
    p.add_argument("--pix-fmt", choices=PIX_FMTS, default="yuv420p",
                   help="mp4 chroma layout: yuv420p plays everywhere, yuv444p keeps full colour detail")
    p.set_defaults(run=_run_export)

    p = sub.add_parser("preview", help="video: input image | textured mesh from the input camera | from behind")
    p.add_argument("results", help="results/<scene> folder holding the stores")
    p.add_argument("--out", required=True, help="output .mp4")
    p.add_argument("--frames", default=None, help=frames_help)
    p.add_argument("--source", choices=SOURCES, default="corrected",
                   help="texture to show: corrected (default), volume or global")
    p.add_argument("--fps", type=float, default=None, help="frame rate (default: from the frames' timestamps)")
    p.add_argument("--size", type=_panel_size, default=360, help="panel height in pixels, 16..4096 (default 360)")
    p.set_defaults(run=_run_preview)

    p = sub.add_parser("view", help="a web page that plays the textured mesh: a static folder "
                                    "(index.html, three.js, the frames' data)")
    p.add_argument("results", help="results/<scene> folder of a finished run")
    p.add_argument("--out", required=True, help="output folder: new, empty or an earlier view (replaced)")
    p.add_argument("--frames", default=None, help=frames_help)
    p.add_argument("--every", type=_positive_int, default=1, metavar="N",
                   help="every N-th frame of the range (default 1: all); playback keeps the capture's pace")
    p.add_argument("--source", choices=SOURCES, default="corrected",
                   help="texture to show: corrected (default), volume or global")
    p.add_argument("--format", choices=IMAGE_FORMATS, default="jpg",
                   help="texture and colour images (default jpg)")
    p.add_argument("--quality", type=int, default=90, help="JPEG quality, 1..100 (default 90)")
    p.add_argument("--texture-size", type=_panel_size, default=1024,
                   help="largest texture side written; larger atlases are downscaled (default 1024)")
    p.add_argument("--color-height", type=_panel_size, default=480,
                   help="height of the colour images written (default 480)")
    p.add_argument("--no-labels", action="store_true", help="leave out the label-map overlay")
    p.set_defaults(run=_run_view)

    p = sub.add_parser("tables", help="the paper-style tables over runs, one column per run "
                                      "(from each run's evaluation and job times)")
    p.add_argument("results", nargs="+", help="results/<scene> folders, each with an evaluation")
    p.add_argument("--out", default=None, help="output .rst or .html (default: print the tables)")
    p.set_defaults(run=_run_tables)

    p = sub.add_parser("evaluate", help="score a finished run's methods, and other methods' texture "
                                        "slices beside them, into a new evaluation folder")
    p.add_argument("results", help="results/<scene> folder of a finished run")
    p.add_argument("--texture", action="append", default=[], metavar="NAME=PATH",
                   help="another method's slices in the run's atlas: a folder of texture_<frame>.png "
                        "(as 'stex export --what png' writes; or the authors' Smooth_/Frame_%%06d.png) "
                        "or a corrected/volume store or folder of block stores; repeatable")
    p.add_argument("--uv-mesh", action="append", default=[], metavar="NAME=MESH",
                   help="the slices of --texture NAME are in this mesh's UV layout (OBJ with vt, or "
                        "glTF; in the run's template coordinates), not the run's atlas: each slice is "
                        "carried into the run's atlas; repeatable")
    p.add_argument("--out", required=True, help="output folder, new or an earlier evaluation's (replaced); "
                                                "not the run's own evaluation/")
    p.add_argument("--frames", default=None, help=frames_help)
    p.add_argument("--stride", type=_positive_int, default=None,
                   help="score every k-th frame (default: the run's evaluation.stride)")
    p.add_argument("--threads", type=_positive_int, default=1, help="frames scored at once (default 1)")
    p.set_defaults(run=_run_evaluate)

    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (StoreError, ValueError, OSError) as exc:
        if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in str(exc):
            exc = f"{exc.strerror or exc}: {exc.filename}"
        _end_counter_line()
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outputs are written under temporary names, removed on the way out
        _end_counter_line()
        print("interrupted", file=sys.stderr)
        return 130


def _end_counter_line() -> None:
    if _Counter.open_line:
        print(file=sys.stderr)
        _Counter.open_line = False


if __name__ == "__main__":
    sys.exit(main())
