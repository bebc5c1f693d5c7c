"""Artifact stores: every array stex writes, its shape, dtype, units and chunking, in one place.

Each pipeline job writes one zarr v3 store (a directory ``*.zarr``). ``ARTIFACTS`` below is the
single definition of what each store holds (:mod:`stex.artifacts`); ``docs/artifacts.md`` is
generated from it (``python -m stex.artifacts > docs/artifacts.md``; a test checks the two agree).

Writing is atomic: :func:`create_store` builds the store in ``<path>.partial-<host>-<pid>``
(one folder per writer) and moves it to
``<path>`` only after every required array is present with the declared dtype and consistent
shapes, and marks it ``complete``. A crash leaves no store that looks complete, and
:func:`open_store` refuses incomplete stores and stores of another artifact kind.

Every store carries attrs: ``stex_artifact`` (its kind), ``stex_version``, ``libraries`` (the
versions of Python and of the libraries whose arithmetic enters the results, :func:`library_versions`:
a fresh install can take newer ones, which move the figures a little), ``complete``,
``frame_ids`` (global frame indices, where the store is per-frame), ``params`` (the settings that
produced it), ``units`` (per array), ``conventions`` and ``chunk_files`` (per array, the chunk
files written: zarr reads a missing chunk as zeros, so :func:`open_store` refuses a store that
lacks some, e.g. a partial copy; it also re-checks the arrays against ``ARTIFACTS``).

Chunks carry a checksum (:data:`CHUNK_CODEC`), and the arrays :func:`open_store` hands out
(:class:`StoreArray`) turn a chunk that does not decode (cut short, or damaged in place) into a
:class:`StoreError` naming the store, the array and the chunk file, in every read.

Per-frame arrays are chunked one frame per chunk along axis 0, so frame-block jobs and readers
touch only the frames they need. Frame-block artifacts (one store per block of frames) are read
as one sequence through :class:`FrameSequence`.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import os
import platform
import shutil
import warnings
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Iterator

import numpy as np
import zarr

from stex import __version__
from stex.artifacts import ARTIFACTS, CONVENTIONS, ArraySpec
# re-exported: stages write their JSON files and folders through stex.io
from stex.files import move_into_place, partial_path

# Snakemake drops a .snakemake_timestamp file into directory outputs; zarr warns about it.
warnings.filterwarnings("ignore", message=r".*\.snakemake_timestamp.*")


class StoreError(ValueError):
    """A store is missing, incomplete, of the wrong kind or malformed."""


#: Every array's chunks: zstd at its default level (zarr's own default codec, ``level=0``) with
#: the frame's content checksum (XXH64 of the decoded bytes, 4 bytes a chunk), so a chunk damaged
#: in place, which zstd would otherwise decode to wrong values without a word, fails to decode.
#: Stores written before (``checksum: false`` in each array's zarr.json) still read; there a
#: damaged chunk is caught only when it no longer decodes at all.
CHUNK_CODEC = zarr.codecs.ZstdCodec(level=0, checksum=True)

# what zstd / blosc / the bytes codec raise on a chunk that does not decode (a selection the
# array cannot take raises IndexError, which passes through)
_DECODE_ERRORS = (RuntimeError, ValueError)


class StoreArray:
    """An array of a store opened by :func:`open_store`: a read (``arr[...]``, ``arr[i]``,
    ``np.asarray(arr)``) that meets a chunk it cannot decode raises :class:`StoreError` naming
    the store, the array and the chunk file. Everything else (``shape``, ``dtype``, ``chunks``,
    ``attrs``, ...) is the zarr array's own."""

    __slots__ = ("_array", "_store", "_name")

    def __init__(self, array: zarr.Array, store: Path, name: str):
        self._array, self._store, self._name = array, store, name

    def __getitem__(self, selection):
        return self.read(selection)

    def read(self, selection, what: str = ""):
        """``self[selection]``; ``what`` (e.g. ``"of frame 12"``) goes into the error message."""
        try:
            return self._array[selection]
        except _DECODE_ERRORS as exc:
            _settle_zarr_reads()
            error = self._damaged(selection, exc, f" {what}" if what else "")
            if error is exc:
                raise
            raise error from exc

    def __array__(self, dtype=None, copy=None):
        data = self[...]
        return data if dtype is None else data.astype(dtype, copy=False)

    def __getattr__(self, attr):
        if attr in self.__slots__:  # not set yet (copy, pickle): no recursion
            raise AttributeError(attr)
        return getattr(self._array, attr)

    def __repr__(self) -> str:
        return f"<StoreArray {self._store}/{self._name} {self._array.shape} {self._array.dtype}>"

    def _damaged(self, selection, exc: Exception, what: str) -> Exception:
        """The StoreError for a failed read, naming the first chunk of ``selection`` that does
        not decode (each chunk read again on its own: the error path only). If every chunk reads,
        ``exc`` was not a damaged chunk and is returned as it is."""
        chunk = ""
        try:
            coords = _chunks_of(selection, self._array.shape, self._array.chunks)
            bad = None if coords is None else next((c for c in coords if not self._decodes(c)), "none")
        except Exception:  # naming the chunk is a courtesy: never mask the read's own error
            bad = None
        if bad == "none":
            return exc
        if bad is not None:
            try:
                key = self._array.metadata.encode_chunk_key(bad)
            except Exception:  # another metadata layout: the chunk's grid index
                key = str(bad)
            chunk = f"chunk file {self._name}/{key}: "
        reason = " ".join(str(exc).split()) or type(exc).__name__  # one line, for the CLI
        return StoreError(f"{self._store}: array {self._name!r}{what} cannot be read ({chunk}{reason}); "
                          f"the store is damaged: re-run the stage that writes it")

    def _decodes(self, coords: tuple) -> bool:
        try:
            self._array.get_block_selection(coords)
        except _DECODE_ERRORS:
            return False
        return True


def _settle_zarr_reads(timeout: float = 5.0) -> None:
    """Wait (at most ``timeout`` s) for the reads still running on zarr's event loop. zarr reads
    an array's chunks concurrently; when one does not decode, the read fails at once and leaves
    the others running, and a process that exits right away (the CLI after its one-line error)
    prints "Task was destroyed but it is pending!" for each on stderr."""
    async def settle():
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if others:
            await asyncio.wait(others, timeout=timeout)

    try:
        from zarr.core.sync import sync  # zarr 3's own loop runner

        sync(settle())
    except Exception:  # another zarr layout: the messages are cosmetic, the error stands
        pass


def _chunks_of(selection, shape: tuple, chunks: tuple, limit: int = 100_000):
    """Chunk coordinates (tuples, in order) that an integer / slice / integer-list selection of
    an array of ``shape`` and ``chunks`` touches; None for another kind of selection or more
    than ``limit`` chunks."""
    sel = selection if isinstance(selection, tuple) else (selection,)
    if any(s is Ellipsis for s in sel):
        k = next(i for i, s in enumerate(sel) if s is Ellipsis)
        sel = sel[:k] + (slice(None),) * (len(shape) - len(sel) + 1) + sel[k + 1:]
    if len(sel) > len(shape):
        return None
    sel = sel + (slice(None),) * (len(shape) - len(sel))
    axes = []
    for s, n, c in zip(sel, shape, chunks):
        if isinstance(s, slice):
            idx = np.arange(*s.indices(n))
        elif isinstance(s, (int, np.integer)):
            idx = np.array([s + n if s < 0 else s])
        else:
            idx = np.asarray(s)
            if idx.dtype == bool:
                idx = np.flatnonzero(idx)
            elif idx.dtype.kind not in "iu" or idx.ndim != 1:
                return None
            idx = np.where(idx < 0, idx + n, idx)
        axes.append(np.unique(idx // c).tolist())
    if int(np.prod([len(a) for a in axes])) > limit:
        return None
    return list(itertools.product(*axes))


class StoreGroup:
    """A store (or a group inside one) opened by :func:`open_store`: ``group[name]`` gives a
    :class:`StoreArray` (or a StoreGroup), and so does ``members()``; ``attrs``, ``in`` and
    everything else are the zarr group's own."""

    __slots__ = ("_group", "_store", "_prefix")

    def __init__(self, group: zarr.Group, store: Path, prefix: str = ""):
        self._group, self._store, self._prefix = group, store, prefix

    def _wrap(self, name: str, member):
        if isinstance(member, zarr.Group):
            return StoreGroup(member, self._store, f"{self._prefix}{name}/")
        return StoreArray(member, self._store, f"{self._prefix}{name}")

    def __getitem__(self, name: str):
        return self._wrap(name, self._group[name])

    def members(self, max_depth: int | None = 0) -> tuple:
        """((name, member), ...) as zarr's ``Group.members``, each member wrapped as ``group[name]``
        wraps it, so a read through it names a damaged chunk too."""
        return tuple((name, self._wrap(name, member)) for name, member in self._group.members(max_depth=max_depth))

    def __contains__(self, name: str) -> bool:
        return name in self._group

    def __getattr__(self, attr):
        if attr in self.__slots__:  # not set yet (copy, pickle): no recursion
            raise AttributeError(attr)
        return getattr(self._group, attr)

    def __repr__(self) -> str:
        return f"<StoreGroup {self._store}{'/' + self._prefix.rstrip('/') if self._prefix else ''}>"


def _resolve_chunks(spec: ArraySpec, shape: tuple[int, ...]) -> tuple[int, ...]:
    if spec.chunks is None:
        return tuple(max(1, s) for s in shape)
    return tuple(max(1, min(c, s) if isinstance(c, int) else s) for c, s in zip(spec.chunks, shape))


class StoreWriter:
    """A store under construction; use through :func:`create_store`."""

    def __init__(self, group: zarr.Group, artifact: str):
        self.group = group
        self.artifact = artifact
        self.spec = ARTIFACTS[artifact]

    def _spec(self, name: str) -> ArraySpec:
        if name not in self.spec.arrays:
            raise StoreError(f"artifact {self.artifact!r} declares no array {name!r} (see stex.artifacts.ARTIFACTS)")
        return self.spec.arrays[name]

    def create(self, name: str, shape: tuple[int, ...]) -> zarr.Array:
        """An empty array with the declared dtype and chunking, to be filled frame by frame."""
        spec = self._spec(name)
        if len(shape) != len(spec.shape):
            raise StoreError(f"{self.artifact}/{name}: expected {len(spec.shape)} dims {spec.shape}, got shape {shape}")
        return self.group.create_array(name, shape=tuple(shape), dtype=spec.dtype,
                                       chunks=_resolve_chunks(spec, tuple(shape)),
                                       compressors=CHUNK_CODEC, fill_value=0, overwrite=True)

    def write(self, name: str, data: np.ndarray) -> zarr.Array:
        """Write a whole array at once (converted to the declared dtype, checked for NaN)."""
        spec = self._spec(name)
        data = np.asarray(data)
        if data.dtype.kind == "f" and not np.isfinite(data).all():
            raise StoreError(f"{self.artifact}/{name}: non-finite values")
        arr = self.create(name, data.shape)
        arr[...] = data.astype(spec.dtype, copy=False)
        return arr

    @property
    def attrs(self):
        return self.group.attrs


def _check_complete(group: zarr.Group, artifact: str, where: str) -> None:
    spec = ARTIFACTS[artifact]
    sizes: dict[str, int] = {}
    for name, a in spec.arrays.items():
        if name not in group:
            if a.required:
                raise StoreError(f"{where}: required array {name!r} was not written")
            continue
        arr = group[name]
        if np.dtype(arr.dtype) != np.dtype(a.dtype):
            raise StoreError(f"{where}: array {name!r} has dtype {arr.dtype}, expected {a.dtype}")
        for sym, n in zip(a.shape, arr.shape):
            if isinstance(sym, int):
                if n != sym:
                    raise StoreError(f"{where}: array {name!r} has shape {arr.shape}, expected {a.shape}")
            elif sizes.setdefault(sym, n) != n:
                raise StoreError(f"{where}: array {name!r} has {sym}={n}, other arrays have {sym}={sizes[sym]}")


# distributions whose arithmetic enters stex's results (a newer numba, scipy or pyamg can move a
# figure in its last digits: docs/metrics.md, "Reproducing the figures")
LIBRARIES = ("numpy", "scipy", "numba", "llvmlite", "opencv-python-headless", "opencv-python",
             "scikit-image", "pyamg", "trimesh", "xatlas", "pymeshlab", "zarr", "av", "pillow")


@functools.lru_cache(maxsize=1)
def library_versions() -> dict:
    """``{"python": "3.11.2", "numpy": "2.4.6", ...}``: Python's version and that of every
    installed distribution of :data:`LIBRARIES` (those not installed are left out)."""
    out = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            pass
    return out


@contextlib.contextmanager
def create_store(path: str | os.PathLike, artifact: str, attrs: dict | None = None,
                 params: dict | None = None) -> Iterator[StoreWriter]:
    """Create the store of ``artifact`` at ``path`` atomically.

    Yields a :class:`StoreWriter`. On normal exit the arrays are checked against ``ARTIFACTS``,
    the attrs ``stex_artifact``, ``stex_version``, ``params``, ``units``, ``conventions`` and
    ``complete=True`` are written and the store is moved into place (replacing an old one). On an
    exception the partial store is deleted.
    """
    if artifact not in ARTIFACTS:
        raise StoreError(f"unknown artifact {artifact!r}; known: {sorted(ARTIFACTS)}")
    path = Path(path)
    tmp = partial_path(path)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    group = zarr.open_group(str(tmp), mode="w", zarr_format=3)
    writer = StoreWriter(group, artifact)
    try:
        group.attrs.update({"stex_artifact": artifact, "stex_version": __version__,
                            "libraries": library_versions(), "complete": False})
        if attrs:
            group.attrs.update(_jsonable(attrs))
        yield writer
        _check_complete(group, artifact, str(path))
        spec = ARTIFACTS[artifact]
        group.attrs.update({
            "params": _jsonable(params or {}),
            "units": {k: v.units for k, v in spec.arrays.items() if k in group},
            "conventions": CONVENTIONS,
            # counted so that a reader can tell a partial copy: zarr reads a missing chunk as zeros
            "chunk_files": {k: _chunk_files(tmp, k) for k in spec.arrays if k in group},
            "complete": True,
        })
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    move_into_place(tmp, path)


def open_store(path: str | os.PathLike, artifact: str) -> StoreGroup:
    """Open a complete store of kind ``artifact`` read-only, or raise :class:`StoreError`.

    Its arrays (:class:`StoreArray`) raise :class:`StoreError` naming the store, the array and
    the chunk file when a read meets a chunk that does not decode (cut short, or damaged in
    place: :data:`CHUNK_CODEC`'s checksum)."""
    path = Path(path)
    if not path.exists():
        raise StoreError(f"{path}: no such store (has the {artifact!r} stage run?)")
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for a broken store
        raise StoreError(f"{path}: not a readable zarr store ({exc})") from exc
    kind = group.attrs.get("stex_artifact")
    if kind != artifact:
        raise StoreError(f"{path}: holds artifact {kind!r}, expected {artifact!r}")
    if not group.attrs.get("complete", False):
        raise StoreError(f"{path}: store is incomplete (its writer did not finish)")
    try:
        _check_complete(group, artifact, str(path))
    except StoreError as exc:
        raise StoreError(f"{exc} (the store is damaged: re-run the stage that writes it)") from None
    except Exception as exc:  # unreadable array metadata
        raise StoreError(f"{path}: damaged store ({exc}): re-run the stage that writes it") from exc
    for name, n in (group.attrs.get("chunk_files") or {}).items():
        have = _chunk_files(path, name)
        if have != n:
            raise StoreError(f"{path}: array {name!r} has {have} of the {n} chunk files it was written with "
                             f"(a partial copy?); the store is damaged: re-run the stage that writes it")
    return StoreGroup(group, path)


def _chunk_files(root: Path, name: str) -> int:
    """Chunk files of array ``name`` in the store at ``root`` (zarr v3: ``<name>/c/...``)."""
    return sum(len(files) for _, _, files in os.walk(Path(root) / name / "c"))


def _jsonable(obj):
    """Convert numpy scalars/arrays and paths inside attrs to JSON types."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def position_range(positions, n_frames: int, what: str) -> tuple[int, int]:
    """``[start, stop)`` sequence positions of a block job, checked against ``n_frames``."""
    start, stop = int(positions[0]), int(positions[1])
    if not 0 <= start < stop <= n_frames:
        raise ValueError(f"{what} range [{start}, {stop}) outside the {n_frames} frames")
    return start, stop


def id_ranges(ids) -> list[list[int]]:
    """Increasing frame ids as runs of consecutive ones, ``[[first, last + 1], ...]``:
    ``[0, 1, 2, 5, 6]`` -> ``[[0, 3], [5, 7]]`` (a job parameter that stays short)."""
    out: list[list[int]] = []
    for i in (int(x) for x in ids):
        if out and i == out[-1][1]:
            out[-1][1] = i + 1
        else:
            out.append([i, i + 1])
    return out


def short_ids(ids) -> str:
    """A frame-id list for an error message: whole up to 4, else its count and range."""
    ids = list(ids)
    return f"{len(ids)} frames [{ids[0]}..{ids[-1]}]" if len(ids) > 4 else str(ids)


def run_block_paths(results_dir, kind: str, scene=None) -> list[Path]:
    """The ``kind`` frame-block stores of a workflow run, ``results/<scene>/<kind>/block_*.zarr``,
    one per block of the run's ``scene.zarr`` (its ``frame_blocks``, not a glob: stale blocks of
    an earlier run with other blocks are not read). ``scene``: the opened scene store, if at hand."""
    results_dir = Path(results_dir)
    scene = scene if scene is not None else open_store(results_dir / "scene.zarr", "scene")
    return [results_dir / kind / f"block_{b:04d}.zarr" for b in range(len(scene.attrs["frame_blocks"]))]


class FrameSequence:
    """Frame-block stores of one artifact read as one sequence of frames.

    >>> seq = FrameSequence(["frames/block_0000.zarr", "frames/block_0001.zarr"], "frames")
    >>> seq.read("color", 12)        # (Hc, Wc, 3) uint8 of global frame 12

    Blocks must hold disjoint, increasing ``frame_ids``.
    """

    def __init__(self, paths, artifact: str):
        self.artifact = artifact
        self.paths = [Path(p) for p in paths]
        self.groups = [open_store(p, artifact) for p in paths]
        self.frame_ids: list[int] = []
        self._where: dict[int, tuple[int, int]] = {}
        for b, g in enumerate(self.groups):
            for i, fid in enumerate(g.attrs["frame_ids"]):
                if fid in self._where:
                    raise StoreError(f"{paths[b]}: frame {fid} also appears in another block")
                self._where[fid] = (b, i)
                self.frame_ids.append(fid)
        if self.frame_ids != sorted(self.frame_ids):
            raise StoreError(f"frame blocks of {artifact!r} are not in frame order")

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def attrs(self):
        return self.groups[0].attrs

    def read(self, name: str, frame_id: int) -> np.ndarray:
        if frame_id not in self._where:
            raise KeyError(f"frame {frame_id} is not in the {self.artifact!r} blocks")
        b, i = self._where[frame_id]
        try:
            return self.groups[b][name].read(i, f"of frame {frame_id}")
        except StoreError:  # a damaged chunk, named by StoreArray
            raise
        except Exception as exc:  # e.g. the array's metadata unreadable
            raise StoreError(f"{self.paths[b]}: array {name!r} of frame {frame_id} cannot be read ({exc}); "
                             f"the store is damaged: re-run the stage that writes it") from exc

    def frame_attr(self, name: str, frame_id: int, default=None):
        """Entry ``frame_id`` of a per-frame list attr of its block (e.g. masks' support_planes),
        or ``default`` if the block has no such attr."""
        b, i = self._where[frame_id]
        values = self.groups[b].attrs.get(name)
        return default if values is None else values[i]

    def __contains__(self, name: str) -> bool:
        return name in self.groups[0]

