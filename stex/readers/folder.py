"""Folder datasets: the authors' layout (Kim et al.'s code) and stex's own layout.

Authors' layout (``layout: authors``), as their ``TextureMappingNonRigid`` reads it::

    <root>/conf.json                      {"<case>": {"main": {start_idx, end_idx, tex_mesh_path},
                                             "mapper4D": {color_intrinsic, depth_intrinsic,
                                                          d_c_extrinsic (3x4 row-major, m)}}}
    <root>/stream/color/Frame_%06d.png    8-bit colour (BGR/BGRA on disk; or .jpg, .jpeg)
    <root>/stream/depth/Frame_%06d.png    16-bit depth, millimetres
    <root>/stream/mask/Frame_%06d.png     optional, colour resolution, foreground >= 1
    <root>/mesh/Frame_%03d.{off,obj,ply}  optional per-frame meshes, RELATIVE index: Frame_000 is
                                          frame start_idx (else the first colour frame on disk)

stex layout (``layout: stex``), see docs/datasets.md::

    <root>/calibration.json               stex.camera.Calibration.to_dict()
    <root>/color/%06d.{png,jpg}           colour, RGB on disk as usual image files
    <root>/depth/%06d.png                 uint16 millimetres
    <root>/mask/%06d.png                  optional
    <root>/meshes/%06d.{obj,ply,off}      optional per-frame meshes (absolute frame index)
    <root>/template.{obj,ply,off,glb}     optional template (default: the first frame's given mesh)

Frame indices in file names are absolute (but the authors' mesh numbers); the reader exposes them as
``frame_ids``. Both layouts: any number of digits (%06d is the convention), extensions in any case;
files in these folders that are not read are named in a warning (or in the error they cause).
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import cv2
import numpy as np

from stex.camera import Calibration, Intrinsics
from stex.readers.images import check_mask, decode_jpeg
from stex.readers.kinect_mkv import jpeg_ends
from stex.readers.meshes import Mesh, load_mesh

_MESH_EXT = (".off", ".obj", ".ply")
_IMAGE_EXT = (".png", ".jpg", ".jpeg")  # listed in every image folder; masks and depth refuse JPEG later
_OTHER_MESH_EXT = (".glb", ".gltf", ".stl")  # never a frame's mesh: named if left in the mesh folder
_NAMED = 5  # file names quoted in a warning


def _numbered(prefix: str, exts: tuple[str, ...]) -> re.Pattern:
    """``<prefix><digits><ext>``: any number of digits, the extension in any case (group 1: the index)."""
    return re.compile(rf"^{re.escape(prefix)}(\d+)(?i:{'|'.join(re.escape(e) for e in exts)})$")


def _numbered_files(folder: Path, pattern: re.Pattern, shift: int = 0) -> tuple[dict[int, Path], list[str]]:
    """The files of ``folder`` that ``pattern`` names, by index + ``shift``, and the names of the
    other files (hidden ones, such as .DS_Store, left out). Two files for one index are refused."""
    out, other = {}, []
    if not folder.is_dir():
        return out, other
    for p in sorted(folder.iterdir()):
        m = pattern.match(p.name)
        if m:
            i = int(m.group(1)) + shift
            if i in out:  # e.g. 8.png and 000008.png, or 000008.png and 000008.jpg
                raise ValueError(f"{folder}: two files for frame {i}: {out[i].name} and {p.name}; keep one")
            out[i] = p
        elif p.is_file() and not p.name.startswith("."):
            other.append(p.name)
    return out, other


def _mask_values(img: np.ndarray, path: Path) -> np.ndarray:
    """(H, W) values of a mask image as read (any bit depth), foreground where >= 1: grey as it
    is, colour as the largest colour channel; with alpha (BGRA, or grey + alpha), the alpha
    channel when the colour is the same everywhere (a cut-out, as image editors export a
    selection: the object in the alpha), else the colour. Refused when colour and alpha both vary
    and mark different pixels (which of the two is the mask cannot be told)."""
    if img.ndim == 2:
        return img
    colour = img[..., :3].max(axis=2)
    if img.shape[2] != 4:
        return colour
    alpha = img[..., 3]
    colour_varies = bool((img[..., :3] != img[0, 0, :3]).any())
    alpha_varies = bool((alpha != alpha[0, 0]).any())
    if alpha_varies and not colour_varies:
        return alpha
    if alpha_varies and not np.array_equal(colour >= 1, alpha >= 1):
        raise ValueError(f"{path}: ambiguous mask: its colour channels and its alpha channel both vary and mark "
                         f"different pixels ({100 * float((colour >= 1).mean()):.0f} % and "
                         f"{100 * float((alpha >= 1).mean()):.0f} % of the image as foreground); give the mask in the "
                         "colour (or grey) channels with a constant alpha, or in the alpha with a constant colour")
    return colour


def _some(names: list[str]) -> str:
    """The first few of ``names``, and how many more."""
    more = len(names) - _NAMED
    return f"{names[:_NAMED]}{f' (and {more} more)' if more > 0 else ''}"


class FolderDataset:
    """Random access to the frames of a folder dataset.

    Attributes:
        root: dataset folder. layout: 'authors' or 'stex'.
        calibration: :class:`~stex.camera.Calibration`.
        frame_ids: list of absolute frame indices (sorted).
        has_masks: whether every selected frame has a mask file.
        mask_note: the warning naming the mask files when there are some but none for a selected
            frame (masks.use_given repeats it in its error), else None.
        mesh_base: authors' layout: the frame of ``mesh/Frame_000`` (conf.json's ``main.start_idx``,
            else the first colour frame on disk); None in stex's layout.

    The same rules in both layouts: colour JPEGs are read as stored (their EXIF orientation is
    ignored, as the depth and the calibration know nothing of it) and refused when cut short or
    damaged inside (libjpeg's corrupt-data warnings); masks must be PNG and neither empty, all
    foreground nor inverted (:func:`stex.readers.images.check_mask`); two files for one frame
    (``8.png`` and ``000008.png``, or ``.png`` and ``.jpg``; ``7.obj`` and ``000007.ply``) are
    refused; files of the image and mesh folders that are not read are named in a warning.
    """

    def __init__(self, root: str | Path, layout: str = "authors", start: int = 0, stop: int | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"dataset folder not found: {self.root}")
        if layout not in ("authors", "stex"):
            raise ValueError(f"unknown folder layout {layout!r} (authors | stex)")
        self.layout = layout
        self.template_hint: str | None = None
        self.mesh_base: int | None = None  # authors: frame id of mesh/Frame_000 (conf.json start_idx)
        self._start_idx = False  # authors: mesh_base comes from conf.json (else the first frame on disk)
        if layout == "authors":
            self.calibration_path = self.root / "conf.json"
            self.calibration = self._authors_calibration()
            self._color_dir, self._depth_dir, self._mask_dir = (self.root / "stream" / d for d in ("color", "depth", "mask"))
            self._mesh_dir, self._prefix = self.root / "mesh", "Frame_"
        else:
            path = self.calibration_path = self.root / "calibration.json"
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing (stex layout needs calibration.json)")
            try:
                cal = json.loads(path.read_text())
                if not isinstance(cal, dict):
                    raise ValueError(f"the file must hold an object, got {type(cal).__name__}")
                self.calibration = Calibration.from_dict(cal)
            except (KeyError, ValueError, TypeError, AttributeError) as exc:
                raise ValueError(f"{path}: invalid calibration ({exc})") from exc
            if self.calibration.color.distortion.any() or self.calibration.depth.distortion.any():
                warnings.warn(f"{path}: non-zero distortion coefficients; the folder reader does not undistort "
                              "and stex projects with the pinhole model, so the images should be undistorted "
                              "and the coefficients zero", stacklevel=2)
            self._color_dir, self._depth_dir, self._mask_dir = (self.root / d for d in ("color", "depth", "mask"))
            self._mesh_dir, self._prefix = self.root / "meshes", ""
        self.calibration.warn_suspicious(str(self.calibration_path))
        self._pattern = _numbered(self._prefix, _IMAGE_EXT)
        if not self._color_dir.is_dir():
            raise FileNotFoundError(f"{self._color_dir}: colour folder missing")
        color_ids, color_other = _numbered_files(self._color_dir, self._pattern)
        depth_ids, depth_other = _numbered_files(self._depth_dir, self._pattern)
        ids = sorted(i for i in color_ids if start <= i and (stop is None or i < stop))
        if not ids:
            raise ValueError(f"{self._color_dir}: no colour frames in [{start}, {stop})"
                             + (f"; {self._not_read(color_other, 'png or .jpg')}" if color_other else ""))
        missing = [i for i in ids if i not in depth_ids]
        if missing:
            raise ValueError(f"{self._depth_dir}: depth missing for frame(s) {missing[:10]}"
                             + (f"; {self._not_read(depth_other, 'png')}" if depth_other else ""))
        gaps = np.diff(np.asarray(ids, np.int64)) - 1
        if gaps.any():
            # counted, not listed: one stray file with a far index would make the list huge
            n_missing = int(gaps.sum())
            first = [i for a, b in zip(ids, ids[1:]) if b > a + 1 for i in range(a + 1, min(b, a + 11))][:10]
            raise ValueError(f"{self._color_dir}: frames are not consecutive: frame(s) {first} missing"
                             f"{f' (and {n_missing - 10} more)' if n_missing > 10 else ''} between "
                             f"{ids[0]} and {ids[-1]} (source.folder.start/stop select a consecutive part)")
        self.frame_ids = ids
        self._color_files = color_ids
        self._depth_files = depth_ids
        self._mask_files, mask_other = _numbered_files(self._mask_dir, self._pattern)
        lossy = [p.name for p in self._mask_files.values() if p.suffix.lower() != ".png"]
        if lossy:
            raise ValueError(f"{self._mask_dir}: masks must be PNG: JPEG's lossy compression smears the mask's "
                             f"edges, turning background pixels next to them into foreground; got {_some(lossy)}. "
                             "Save the masks as PNG from their source (a JPEG converted to PNG keeps its noise)")
        for folder, other, exts in ((self._color_dir, color_other, "png or .jpg"), (self._depth_dir, depth_other, "png"),
                                    (self._mask_dir, mask_other, "png")):
            if other:
                warnings.warn(f"{folder}: {self._not_read(other, exts)}; rename them (or move them out of the folder)",
                              stacklevel=2)
        with_mask = [i for i in ids if i in self._mask_files]
        if with_mask and len(with_mask) != len(ids):
            raise ValueError(f"{self._mask_dir}: masks missing for frame(s) {[i for i in ids if i not in self._mask_files][:10]} "
                             "(give a mask for every frame or none)")
        self.has_masks = bool(with_mask)
        self.mask_note = self._unread_masks(ids, color_ids, with_mask)
        if layout == "authors" and self.mesh_base is None:
            self.mesh_base = min(color_ids)
        self._mesh_files = self._meshes(color_ids)

    def _not_read(self, names: list[str], exts: str) -> str:
        return (f"{len(names)} file(s) not read, as they are not named {self._prefix}<frame index>.{exts}: "
                f"{_some(names)}")

    def _unread_masks(self, ids: list[int], on_disk: dict[int, Path], with_mask: list[int]) -> str | None:
        """Warn about mask files that are not read: when none is for a selected frame (``ids``),
        all of them, and return that text (``mask_note``, for the error of masks.use_given);
        else those whose index is no colour frame on disk (``on_disk``). None when all are read."""
        stray = sorted(p.name for i, p in self._mask_files.items() if i not in on_disk)
        if with_mask or not self._mask_files:
            if stray:
                warnings.warn(f"{self._mask_dir}: {len(stray)} mask file(s) match no colour frame on disk and are not "
                              f"read: {_some(stray)}; {self._mask_naming(on_disk)}", stacklevel=3)
            return None
        names = sorted(p.name for p in self._mask_files.values())
        note = (f"{self._mask_dir}: {len(names)} mask file(s) exist but match no selected frame "
                f"({ids[0]}..{ids[-1]}): {_some(names)}; {self._mask_naming(on_disk)}")
        warnings.warn(f"{note}. The masks are not read", stacklevel=3)
        return note

    def _mask_naming(self, on_disk: dict[int, Path]) -> str:
        """How masks are named, for the texts about those that are not read."""
        first = min(on_disk)
        out = (f"masks are named {self._prefix}<frame index>.png with the colour frame's absolute index "
               f"(e.g. {self._prefix}{first:06d}.png; the colour frames on disk are {first}..{max(on_disk)})")
        numbers = sorted(self._mask_files)
        if first and numbers[0] == 0 and all(k + first in on_disk for k in numbers):
            out += f"; these look numbered from 0, as the authors' meshes: add {first} to their numbers"
        return out

    def _meshes(self, on_disk: dict[int, Path]) -> dict[int, Path]:
        """The per-frame mesh files by absolute frame id (frames not on disk included: the authors'
        default template is mesh/Frame_000 whatever frames exist). Warns about mesh files that
        give no mesh to any colour frame on disk (``on_disk``), naming a few."""
        shift = self.mesh_base if self.layout == "authors" else 0
        meshes, other = _numbered_files(self._mesh_dir, _numbered(self._prefix, _MESH_EXT), shift)
        hint = (self.root / self.template_hint).resolve() if self.template_hint else None
        stray = sorted(p.name for f, p in meshes.items() if f not in on_disk)
        stray += [n for n in other if Path(n).suffix.lower() in _MESH_EXT + _OTHER_MESH_EXT
                  and (self._mesh_dir / n).resolve() != hint]  # conf.json's template may live in mesh/
        if stray:
            warnings.warn(f"{self._mesh_dir}: {len(stray)} mesh file(s) give no frame its mesh and are not read: "
                          f"{_some(stray)}; {self._mesh_naming(meshes, on_disk)}", stacklevel=3)
        return meshes

    def _mesh_naming(self, meshes: dict[int, Path], on_disk: dict[int, Path]) -> str:
        """How per-frame meshes are named, for the warning about those that are not read."""
        frames = f"the colour frames on disk are {min(on_disk)}..{max(on_disk)}"
        if self.layout == "stex":
            return f"name them <frame index>.obj (.ply, .off), the absolute frame index ({frames})"
        source = "conf.json's main.start_idx" if self._start_idx else "the first colour frame on disk"
        out = (f"the authors' layout numbers them from frame {self.mesh_base} ({source}): Frame_000 is frame "
               f"{self.mesh_base}, Frame_<k> frame {self.mesh_base} + k ({frames})")
        numbers = [f - self.mesh_base for f in meshes]
        if self.mesh_base and numbers and all(k in on_disk for k in numbers):
            # documented meaning kept; only pointed out when every number reads as an absolute index
            out += (f"; these numbers look like absolute frame indices: rename Frame_<k> to Frame_<k - "
                    f"{self.mesh_base}> (e.g. Frame_{numbers[0]:03d} to Frame_{numbers[0] - self.mesh_base:03d})")
        return out

    def _authors_calibration(self) -> Calibration:
        path = self.root / "conf.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (the authors' layout keeps the cameras in conf.json)")
        try:
            conf = json.loads(path.read_text())
            if not isinstance(conf, dict):
                raise ValueError(f"the file must hold an object of cases, got {type(conf).__name__}")
            case = next(v for v in conf.values() if isinstance(v, dict) and "mapper4D" in v)
            m = case["mapper4D"]
            if not isinstance(m, dict):
                raise ValueError(f"mapper4D must be an object, got {type(m).__name__}")
            color, depth = (Intrinsics.from_dict(m.get(key), key) for key in ("color_intrinsic", "depth_intrinsic"))
            ext = np.asarray(m["d_c_extrinsic"], np.float64)
            if ext.size != 12:
                raise ValueError(f"d_c_extrinsic needs 12 numbers (3x4 row-major), got {ext.size}")
            T = np.vstack([ext.reshape(3, 4), [0, 0, 0, 1]])
            R = T[:3, :3]
            if not (np.isfinite(T).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
                raise ValueError("d_c_extrinsic's left 3x3 block is not a rotation matrix")
            # The authors' extrinsic is rounded to 8 digits; re-orthonormalise the rotation.
            u, _, vt = np.linalg.svd(R)
            T[:3, :3] = u @ vt
            main = case.get("main") or {}
            if not isinstance(main, dict):
                raise ValueError(f"main must be an object, got {type(main).__name__}")
            self.template_hint = main.get("tex_mesh_path")
            if self.template_hint is not None and not isinstance(self.template_hint, str):
                raise ValueError(f"main.tex_mesh_path must be a path (text), got {self.template_hint!r}")
            if main.get("start_idx") is not None:
                if int(main["start_idx"]) != main["start_idx"] or main["start_idx"] < 0:
                    raise ValueError(f"main.start_idx must be a non-negative integer, got {main['start_idx']!r}")
                self.mesh_base = int(main["start_idx"])
                self._start_idx = True
            return Calibration(color, depth, T)
        except StopIteration:
            raise ValueError(f"{path}: no case with a 'mapper4D' section") from None
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{path}: invalid camera settings ({exc})") from exc

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _read(self, path: Path, flags: int) -> np.ndarray:
        # pixels as stored: an EXIF orientation would turn the image against its depth and calibration
        if path.suffix.lower() in (".jpg", ".jpeg"):
            buf = path.read_bytes()
            if not jpeg_ends(buf):
                # libjpeg decodes a JPEG cut short to a full-size image with invented rows
                raise ValueError(f"{path}: the JPEG ends without its end-of-image marker (the file is cut short)")
            # libjpeg's "Corrupt JPEG data" warnings (damage inside, end marker intact) raise
            img = decode_jpeg(buf, flags | cv2.IMREAD_IGNORE_ORIENTATION, str(path))
        else:
            img = cv2.imread(str(path), flags)
        if img is None:
            raise ValueError(f"{path}: cannot decode image (missing or corrupt)")
        return img

    def color(self, frame_id: int) -> np.ndarray:
        """(Hc, Wc, 3) uint8 RGB of ``frame_id``."""
        path = self._color_files[frame_id]
        img = self._read(path, cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)  # ANYDEPTH: refuse 16-bit, don't rescale
        if img.dtype != np.uint8:
            raise ValueError(f"{path}: colour must be 8-bit, got {img.dtype}")
        c = self.calibration.color
        if img.shape[:2] != (c.height, c.width):
            raise ValueError(f"{path}: colour is {img.shape[1]}x{img.shape[0]}, calibration says {c.width}x{c.height}")
        return img[..., ::-1].copy()

    def depth(self, frame_id: int) -> np.ndarray:
        """(Hd, Wd) uint16 depth in millimetres of ``frame_id`` (0 = invalid)."""
        path = self._depth_files[frame_id]
        img = self._read(path, cv2.IMREAD_UNCHANGED)
        if img.dtype != np.uint16 or img.ndim != 2:
            raise ValueError(f"{path}: depth must be single-channel 16-bit millimetres, got {img.dtype} {img.shape}")
        d = self.calibration.depth
        if img.shape != (d.height, d.width):
            raise ValueError(f"{path}: depth is {img.shape[1]}x{img.shape[0]}, calibration says {d.width}x{d.height}")
        return img

    def mask(self, frame_id: int) -> np.ndarray:
        """(Hc, Wc) bool foreground mask of ``frame_id`` (source-supplied)."""
        path = self._mask_files.get(frame_id)
        if path is None:
            raise FileNotFoundError(f"{self._mask_dir}: no mask for frame {frame_id}")
        # not IMREAD_GRAYSCALE: it rescales 16-bit and weights colours
        img = _mask_values(self._read(path, cv2.IMREAD_UNCHANGED), path)
        c = self.calibration.color
        if img.shape != (c.height, c.width):
            raise ValueError(f"{path}: mask is {img.shape[1]}x{img.shape[0]}, must match the colour size {c.width}x{c.height}")
        mask = img >= 1
        check_mask(mask, str(path))  # empty, all foreground, or inverted
        return mask

    def mesh_path(self, frame_id: int) -> Path | None:
        """The given mesh file of ``frame_id``, or None.

        Authors' layout: relative index, mesh/Frame_000 belongs to conf.json's start_idx (else the
        first colour frame on disk), whatever source.folder.start selects."""
        return self._mesh_files.get(frame_id)

    def template_path(self, override: str | None = None) -> Path | None:
        """The template mesh: ``override`` (relative to the root), else the layout's default."""
        if override:
            p = self.root / override
            if not p.is_file():
                raise FileNotFoundError(f"template mesh not found: {p}")
            return p
        candidates = []
        if self.layout == "authors":
            if self.template_hint:
                candidates.append(self.root / self.template_hint)
            if self.mesh_base in self._mesh_files:  # mesh/Frame_000 (any digits, any case)
                candidates.append(self._mesh_files[self.mesh_base])
        else:
            candidates += [self.root / f"template{e}" for e in (".obj", ".ply", ".off", ".glb", ".gltf")]
            first = self.mesh_path(self.frame_ids[0])  # as in the authors' layout: the first given mesh
            if first is not None:
                candidates.append(first)
        return next((p for p in candidates if p.is_file()), None)

    def frame_files(self, frame_id: int) -> list[Path]:
        """The image files of ``frame_id``: colour, depth and, when the dataset has them, mask."""
        files = [self._color_files[frame_id], self._depth_files[frame_id]]
        return files + ([self._mask_files[frame_id]] if self.has_masks else [])

    def load_given_mesh(self, frame_id: int) -> Mesh | None:
        p = self.mesh_path(frame_id)
        return None if p is None else load_mesh(p)
