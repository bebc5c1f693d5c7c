"""Evaluation stage, the artifact layer: open a run's stores, score every method on the chosen
frames (:mod:`stex.evaluation`), and write ``evaluation.json``, the CSV tables, ``tables.rst`` /
``tables.html`` and the figures.

What it does
------------
- :func:`write_evaluation` — the stage: reads the Kim 2019 global texture over the source
  frames (the ``global_texture`` store, :func:`stex.stages.global_texture.write_global_texture`), builds the
  naive per-frame projection baseline, scores ``ours`` (corrected volume),
  ``ours_uncorrected`` (volume), ``global`` and ``projection`` on the chosen frames, temporal
  flicker in borrowed regions, and writes ``evaluation.json``, one CSV per table, ``tables.rst``
  and PNG figures into a folder. Its stores are named by one :class:`EvaluationInputs`.
- :func:`score_frames` — the scoring of :func:`write_evaluation` for one frame block, into a
  JSON file of per-frame records, so that the workflow scores blocks in separate jobs (as soon
  as each block's slices exist) and :func:`write_evaluation` (``inputs.records``) merges them.
- :func:`evaluate_results` — :func:`write_evaluation` of a finished run's folder with other
  methods' texture slices (:class:`TextureSlices`: PNG files or a texture store in the run's
  atlas, or in another UV layout carried into it by :mod:`stex.resample`) scored beside ours by
  the same code (``stex evaluate``).

Held-out protocol
-----------------
With ``data_term.source_stride`` = k only every k-th frame may texture anything (attr
``source_frames`` of the data_term stores); every frame is still a target. Frames that are not
sources are scored as ``held_out``: their own photo was not used by ``ours`` nor by ``global``
(built from the source frames only by the ``global_texture`` stage, which takes the same
``data_term.source_stride``; its attr ``source_frames`` is checked against the data term's). The
naive ``projection`` baseline of a held-out frame is its own photo, so it is left out of the
held-out summaries.
"""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr
from PIL import Image

from stex import metrics as ev
from stex.camera import Calibration
from stex.config import RESERVED_METHOD_NAMES, other_method_paths, scoring_settings
from stex.evaluation import (Atlas, evaluation_params, frame_views, score_methods, summarise_frames,
                             truth_views, vertex_motion)
from stex.export import PNG_SLICE_NAME
from stex.global_texture import projection_texture
from stex.files import move_into_place, partial_path, write_json
from stex.io import FrameSequence, StoreError, library_versions, open_store, run_block_paths, short_ids
from stex.mesh import transfer_vertices
from stex.readers.meshes import load_mesh
from stex.reporting import METHODS, finite_or_none, nan_for_none, rst_tables, table_rows, tables_html
from stex.resample import atlas_transfer
from stex.sampling import TexelSampler
from stex.stages.evaluation_figures import (picture_label_map, picture_side_by_side, plot_blur_motion,
                                            plot_dynamism, plot_psnr, write_csvs)
from stex.stages.observations import open_coordinates
from stex.stages.template import check_atlas

log = logging.getLogger("stex.evaluation")

__all__ = ["EvaluationInputs", "TextureSlices", "check_replaceable", "score_frames",
           "write_evaluation", "evaluate_results"]


@dataclass
class EvaluationInputs:
    """The stores an evaluation reads, named as the workflow's ``evaluate`` rule names its inputs.

    scene: ``scene`` store (calibration, frame ids; truth/vertices and the scene template's
    atlas on synthetic scenes). frames, masks: ``frames`` / ``masks`` block stores (photos,
    GrabCut masks). template: ``template`` store (faces, atlas, texel map, face charts).
    tracking: ``tracking`` store (vertices [T, V, 3]). projection: ``projection`` store
    (face_visible [T, F]). labels: ``labels`` store (labels [T, F], never_seen). volume,
    corrected: ``volume`` / ``corrected`` block stores (``ours_uncorrected`` / ``ours``).
    global_texture: ``global_texture`` store, the ``global`` method
    (:func:`stex.stages.global_texture.write_global_texture`: texture (W, W, 3) uint8, face_textured
    (F,) bool, attrs source_frames and seconds); its source frames must be the data term's.
    truth: ``truth`` block stores (synthetic scenes) -> ground-truth scores and flicker, or None.
    coords: ``texcoords`` store (ξ) or None for the projection store (Φ): the texture
    coordinates of the baselines, as used by the volume. observations: ``observations`` store
    -> the SSIM-dynamism figure, or None. data_term: ``data_term`` block stores: attr
    ``source_frames`` marks the frames that may texture (held-out protocol); without, the global
    texture's ``source_frames``. records: :func:`score_frames` files whose records together
    cover the frames to score (checked: same settings, frames and sources), merged by
    :func:`write_evaluation` instead of scoring there; None scores. sampling:
    :func:`stex.stages.texcoords.write_sampling_table`'s JSON -> the paper's sampling table
    (``sampling`` in ``evaluation.json``, ``table_sampling.csv``), or None.
    """

    scene: str | Path
    frames: list
    masks: list
    template: str | Path
    tracking: str | Path
    projection: str | Path
    labels: str | Path
    volume: list
    corrected: list
    global_texture: str | Path
    truth: list | None = None
    coords: str | Path | None = None
    observations: str | Path | None = None
    data_term: list | None = None
    records: list | None = None
    sampling: str | Path | None = None


# the authors' texture volume files (TextureMappingNonRigid, ColorCorrection), in preference order
AUTHORS_SLICE_NAMES = ("Smooth_{frame:06d}.png", "Frame_{frame:06d}.png")


class TextureSlices:
    """Another method's texture slices, to score beside ours in the run's atlas.

    ``path`` is either a folder of PNG files ``texture_{frame:05d}.png``
    (:data:`stex.export.PNG_SLICE_NAME`, what ``stex export --what png`` writes; 8-bit RGB, one
    per frame id; the authors' ``Smooth_{frame:06d}.png``, else ``Frame_{frame:06d}.png``, as
    their code writes into ``atlas/<atlas_path>/video/``) or a stex texture store: a ``corrected``
    or ``volume`` zarr store, or a folder of such block stores (e.g. another run's
    ``corrected/``). Black texels (0, 0, 0) count as "no texture" for the coverage scores.

    Slices in the run's atlas are read as they are. Slices in another UV layout need
    ``uv_mesh``: that layout's mesh (OBJ with ``vt``, or glTF), in the run's template
    coordinates; :meth:`into_atlas` then carries every slice into the run's atlas
    (:mod:`stex.resample`).
    """

    def __init__(self, path, uv_mesh=None):
        self.path = Path(path)
        if not self.path.exists():
            raise StoreError(f"{self.path}: no such texture folder or store")
        self.uv_mesh = None if uv_mesh is None else Path(uv_mesh)
        if self.uv_mesh is not None and not self.uv_mesh.is_file():
            raise StoreError(f"{self.uv_mesh}: no such mesh file (the UV layout of {self.path})")
        self.transfer = None
        is_store = any((self.path / f).exists() for f in (".zgroup", ".zattrs", "zarr.json"))
        stores = [self.path] if is_store else sorted(self.path.glob("block_*.zarr"))
        self._seq = None
        if stores:
            kind = zarr.open_group(str(stores[0]), mode="r").attrs.get("stex_artifact")
            if kind not in ("corrected", "volume"):
                raise StoreError(f"{stores[0]}: expected a 'corrected' or 'volume' store, found {kind!r}")
            self._seq = FrameSequence([str(x) for x in stores], kind)
            self.frame_ids = [int(i) for i in self._seq.frame_ids]
        else:
            # stex's names, else the authors' texture volume (atlas/<atlas_path>/video/):
            # Smooth_%06d.png (colour-corrected, what their viewer shows), else Frame_%06d.png
            for name in (PNG_SLICE_NAME, *AUTHORS_SLICE_NAMES):
                head, tail = name.split("{frame:")[0], ".png"
                found = {int(f.name[len(head):-len(tail)]): f for f in self.path.glob(f"{head}*{tail}")
                         if f.name[len(head):-len(tail)].isdigit()}
                if found:
                    break
            self._name = name
            if not found:
                raise StoreError(f"{self.path}: no texture_<frame>.png files (nor the authors' Smooth_<frame>.png "
                                 f"or Frame_<frame>.png) and no block_*.zarr stores")
            self._files = found
            self.frame_ids = sorted(found)

    def into_atlas(self, template, template_path="the run's template") -> None:
        """Carry the slices from ``uv_mesh``'s layout into the atlas of ``template`` (an open
        ``template`` store, at ``template_path``) on every :meth:`read`. Without ``uv_mesh`` the
        slices must be in that atlas: stex stores that record another one raise ValueError."""
        if self.uv_mesh is None:
            if self._seq is not None:
                try:
                    check_atlas(zip(self._seq.paths, self._seq.groups), template, template_path)
                except ValueError as exc:
                    raise ValueError(f"{exc}; slices in another UV layout need that layout's mesh "
                                     f"(--uv-mesh NAME=MESH, or other_methods' uv_mesh)") from None
            return
        mesh = load_mesh(self.uv_mesh)
        self.transfer = atlas_transfer(
            template["texel/face_id"][...], template["texel/bary"][...], template["vertices"][...],
            template["faces"][...], mesh.vertices, mesh.faces, mesh.texcoords, mesh.texcoord_faces,
            gutter_px=int(template.attrs.get("gutter_px", 0)), where=str(self.uv_mesh))

    def read(self, frame_id: int) -> np.ndarray:
        """(W, W, 3) uint8 slice of ``frame_id`` (in the run's atlas once :meth:`into_atlas` ran)."""
        if self.uv_mesh is not None and self.transfer is None:
            raise RuntimeError(f"{self.path}: slices in the layout of {self.uv_mesh}: call into_atlas first")
        if self._seq is not None:
            tex = np.asarray(self._seq.read("texture", frame_id), np.uint8)
        else:
            f = self._files.get(int(frame_id))
            if f is None:
                raise StoreError(f"{self.path}: no {self._name.format(frame=int(frame_id))}")
            try:
                with Image.open(f) as im:
                    if im.mode != "RGB":
                        raise StoreError(f"{f}: an 8-bit RGB PNG is needed, found mode {im.mode}")
                    tex = np.asarray(im)
            except OSError as exc:  # truncated or not an image: PIL's message does not name the file
                raise StoreError(f"{f}: cannot read the image ({exc})") from None
        if self.transfer is not None:
            try:
                tex = self.transfer.apply(tex)
            except ValueError as exc:
                raise ValueError(f"{self.path}, frame {frame_id}: {exc}") from exc
        return tex


def _other_methods(others) -> dict:
    """``{name: TextureSlices}`` of the setting ``other_methods``, names checked."""
    out = {}
    for name, (path, uv_mesh) in other_method_paths(others).items():
        if not re.fullmatch(r"[a-z][a-z0-9_]*", str(name)) or name in RESERVED_METHOD_NAMES:
            raise ValueError(f"method name {name!r}: use lower-case letters, digits and '_', "
                             f"not one of {', '.join(RESERVED_METHOD_NAMES)}")
        out[name] = TextureSlices(path, uv_mesh)
    return out


def _check_frames(name, path, ids, expected, needed=None):
    """A store's frames: exactly the scene's, or (``needed`` given) at least those."""
    if needed is None:
        if list(ids) != list(expected):
            raise ValueError(f"{name} store {path} holds frames {short_ids(ids)}, the scene has "
                             f"{short_ids(expected)}")
        return
    missing = sorted(set(needed) - set(ids))
    if missing or not set(ids) <= set(expected):
        raise ValueError(f"{name} store {path} holds frames {short_ids(ids)}; frames "
                         f"{short_ids(missing or sorted(set(ids) - set(expected)))} "
                         f"{'are needed' if missing else 'are not frames of the scene'}")


class _Inputs:
    """The stores of an evaluation, opened and checked, and what scoring one frame reads.

    ``block`` ([start, stop) sequence positions) keeps the frames to score inside a frame
    block; the frame-block stores then need to hold only those frames (and, with truth, each
    one's predecessor, for the flicker). Without it they must hold every frame of the scene.
    """

    def __init__(self, inputs: EvaluationInputs, params, *, frames, block):
        self.p = evaluation_params(params)
        self.scene_path, self.template_path = inputs.scene, inputs.template
        scene, projection, labels_store = self._open_stores(inputs)
        self._open_global(inputs.global_texture)
        self._held_out(inputs.data_term)
        self._frames_to_score(frames, block)
        self._open_blocks(inputs, scene, block)
        self._read_per_frame(projection, labels_store, inputs.coords, inputs.projection)
        self._open_others(inputs.truth)

    def _open_stores(self, inputs: EvaluationInputs):
        """The scene, template, tracking, projection and labels stores, checked against each other."""
        scene_path, template_path, tracking_path = inputs.scene, inputs.template, inputs.tracking
        projection_path, labels_path = inputs.projection, inputs.labels
        scene = open_store(scene_path, "scene")
        self.ids = ids = [int(i) for i in scene.attrs["frame_ids"]]
        self.pos_of = {fid: k for k, fid in enumerate(ids)}
        self.cal = Calibration.from_dict(scene.attrs["calibration"])
        self.template = template = open_store(template_path, "template")
        self.tracking = tracking = open_store(tracking_path, "tracking")
        projection = open_store(projection_path, "projection")
        labels_store = open_store(labels_path, "labels")
        for name, path, g in (("tracking", tracking_path, tracking), ("projection", projection_path, projection),
                              ("labels", labels_path, labels_store)):
            _check_frames(name, path, g.attrs["frame_ids"], ids)
        self.atlas = atlas = Atlas.from_store(template)
        F = len(atlas.faces)
        if tracking["vertices"].shape[1] != template["vertices"].shape[0]:
            raise ValueError(f"tracking store {tracking_path} has {tracking['vertices'].shape[1]} "
                             f"vertices, template {template_path} has {len(template['vertices'])}")
        for name, path, arr in (("projection", projection_path, projection["face_visible"]),
                                ("labels", labels_path, labels_store["labels"])):
            if arr.shape[1] != F:
                raise ValueError(f"{name} store {path} has {arr.shape[1]} faces, template has {F}")
        self.atlas_size = int(template.attrs["atlas_size"])
        return scene, projection, labels_store

    def _open_global(self, global_texture_path):
        """The global baseline (Kim 2019), built from the source frames by the global_texture stage."""
        template, template_path, scene_path = self.template, self.template_path, self.scene_path
        ids, F, W = self.ids, len(self.atlas.faces), self.atlas_size
        global_store = open_store(global_texture_path, "global_texture")
        check_atlas([(global_texture_path, global_store)], template, template_path)
        self.global_tex = np.asarray(global_store["texture"][...], np.uint8)
        self.global_faces = np.asarray(global_store["face_textured"][...], bool)
        if self.global_tex.shape[0] != W:
            raise ValueError(f"global_texture store {global_texture_path} is "
                             f"{self.global_tex.shape[0]} texels wide, template {template_path} "
                             f"atlas_size is {W}")
        if self.global_faces.shape != (F,):
            raise ValueError(f"global_texture store {global_texture_path} has "
                             f"{len(self.global_faces)} faces, template {template_path} has {F}")
        self.global_path = global_texture_path
        self.global_sources = global_sources = [int(i) for i in global_store.attrs["source_frames"]]
        if not set(global_sources) <= set(ids):
            raise ValueError(f"global_texture store {global_texture_path} was built from frames "
                             f"{short_ids(global_sources)} that are not all frames of the scene "
                             f"{scene_path} ({short_ids(ids)})")
        self.seconds_global = float(global_store.attrs["seconds"])
        self._global_stride = global_store.attrs.get("params", {}).get("source_stride")

    def _held_out(self, data_term_paths):
        """The held-out protocol: the frames allowed to texture."""
        global_texture_path, global_sources = self.global_path, self.global_sources
        ids, T = self.ids, len(self.ids)
        sources = set(global_sources)
        k = self._global_stride
        if data_term_paths:
            data_term_attrs = open_store(list(data_term_paths)[0], "data_term").attrs
            src = data_term_attrs.get("source_frames")
            if src is not None:  # frames lost by the tracking texture nothing but are not held out
                sources = {int(i) for i in src} | {int(i) for i in data_term_attrs.get("lost_source_frames", [])}
                k = data_term_attrs.get("params", {}).get("source_stride")
            if sorted(sources) != sorted(global_sources):
                raise ValueError(f"global_texture store {global_texture_path} was built from source "
                                 f"frames {short_ids(sorted(global_sources))}, the tables "
                                 f"{list(data_term_paths)[0]} allow {short_ids(sorted(sources))} "
                                 f"(global_texture and tables must use the same source_stride)")
        self.sources = sorted(sources)
        self.stride_label = "" if len(sources) == T else (f"(1/{k})" if k else f"({len(sources)}/{T} frames)")
        self.is_source = np.array([i in sources for i in ids])

    def _frames_to_score(self, frames, block):
        """The frames to score (every ``stride``-th, or ``frames``; inside ``block``) and the figures' frame."""
        p, ids, T, scene_path = self.p, self.ids, len(self.ids), self.scene_path
        score_ids = list(ids[::int(p["stride"])]) if frames is None else [int(f) for f in frames]
        bad = [f for f in score_ids if f not in self.pos_of]
        if bad or not score_ids:
            raise ValueError(f"frames to score {bad or score_ids} are not frames of the scene "
                             f"{scene_path} ({short_ids(ids)})")
        if block is not None:
            start, stop = (int(x) for x in block)
            if not 0 <= start < stop <= T:
                raise ValueError(f"frame block [{start}, {stop}) is outside the scene's {T} frames")
            score_ids = [f for f in score_ids if start <= self.pos_of[f] < stop]
        self.score_ids = score_ids
        fig_t = score_ids[len(score_ids) // 2] if score_ids else ids[0]
        fig_t = fig_t if p["figure_frame"] is None else int(p["figure_frame"])
        if fig_t not in self.pos_of:
            raise ValueError(f"figure_frame {fig_t} is not a frame of the scene ({short_ids(ids)})")
        self.fig_pos = self.pos_of[fig_t]

    def _open_blocks(self, inputs: EvaluationInputs, scene, block):
        """The frame-block stores (photos, masks, volume, corrected) and the ground truth."""
        scene_path, template, template_path = self.scene_path, self.template, self.template_path
        frames_paths, masks_paths, truth_paths = inputs.frames, inputs.masks, inputs.truth
        volume_paths, corrected_paths = inputs.volume, inputs.corrected
        ids, T, W, score_ids = self.ids, len(self.ids), self.atlas_size, self.score_ids
        # ground truth
        self.truth = None
        self.true_embedding = None
        if truth_paths and "truth" not in scene:
            raise StoreError(f"{scene_path}: truth stores given but the scene has no truth/vertices")
        # what the frame-block stores must hold: with a block, its frames to score and (flicker)
        # their predecessors; else every frame of the scene
        needed = None
        if block is not None:
            needed = set(score_ids)
            if truth_paths:
                needed |= {ids[self.pos_of[f] - 1] for f in score_ids if self.pos_of[f] > 0}
        self.photos = FrameSequence(list(frames_paths), "frames")
        self.masks = FrameSequence(list(masks_paths), "masks")
        self.volume = FrameSequence(list(volume_paths), "volume")
        self.corrected = FrameSequence(list(corrected_paths), "corrected")
        check_atlas([(p, g) for seq in (self.volume, self.corrected) for p, g in zip(seq.paths, seq.groups)],
                    template, template_path)
        for name, paths, seq in (("frames", frames_paths, self.photos), ("masks", masks_paths, self.masks),
                                 ("volume", volume_paths, self.volume),
                                 ("corrected", corrected_paths, self.corrected)):
            _check_frames(name, ", ".join(str(x) for x in paths), seq.frame_ids, ids,
                          None if needed is None else (set(score_ids) if name == "masks" else needed))
        if self.volume.groups[0]["texture"].shape[1] != W:
            raise ValueError(f"volume stores are {self.volume.groups[0]['texture'].shape[1]} texels "
                             f"wide, template atlas_size is {W}")
        if truth_paths:
            self.truth = FrameSequence(list(truth_paths), "truth")
            _check_frames("truth", ", ".join(str(x) for x in truth_paths), self.truth.frame_ids, ids,
                          needed)
            self.true_atlas = Atlas.from_store(scene, "template/")
            self.true_vertices = scene["truth/vertices"]
            # the template's embedding in the scene's mesh carries the truth onto the template
            if "embedding" in template:
                emb_face = np.asarray(template["embedding/face"][...], np.int64)
                if (len(emb_face) == template["vertices"].shape[0]
                        and emb_face.max(initial=-1) < len(self.true_atlas.faces)):
                    self.true_embedding = (emb_face, np.asarray(template["embedding/bary"][...], np.float64))
            if self.true_vertices.shape[0] != T:
                raise ValueError(f"{scene_path}: truth/vertices has {self.true_vertices.shape[0]} "
                                 f"frames, the scene has {T}")

    def _read_per_frame(self, projection, labels_store, coords_path, projection_path):
        """Visibility, labels, texture coordinates and the texel sampler of the baselines."""
        template, atlas, T, F = self.template, self.atlas, len(self.ids), len(self.atlas.faces)
        self.face_visible = np.asarray(projection["face_visible"][...], bool)
        self.labels = labels_store["labels"]
        self.seen_faces = (self.face_visible & self.is_source[:, None]).any(axis=0)
        self.coords, _, _ = open_coordinates(coords_path or projection_path)
        if self.coords.shape[0] != T:
            raise ValueError(f"texture coordinates {coords_path or projection_path} hold "
                             f"{self.coords.shape[0]} frames, the scene has {T}")
        self.sampler = TexelSampler(template["texel/face_id"][...], template["texel/bary"][...], atlas.faces)
        # the volume fills never-seen faces from the nearest seen surface: they carry texture too
        self.filled = (np.asarray(labels_store["never_seen"][...], bool)
                       if int(self.volume.attrs.get("never_seen_texels", 0)) > 0
                       else np.zeros(F, bool))

    def _open_others(self, truth_paths):
        """Other methods' slices, scored beside ours."""
        p, ids, score_ids = self.p, self.ids, self.score_ids
        template, template_path = self.template, self.template_path
        self.others = _other_methods(p["other_methods"])
        self.methods = METHODS + tuple(self.others)
        want = set(score_ids)
        if truth_paths:  # the flicker of a frame compares it with its predecessor
            want |= {ids[self.pos_of[f] - 1] for f in score_ids if self.pos_of[f] > 0}
        for name, src in self.others.items():
            src.into_atlas(template, template_path)
            missing = sorted(want - set(src.frame_ids))
            if missing:
                why = ("; the frame before each scored frame is read too, for the flicker: give the slices "
                       "from one frame earlier" if set(missing) - set(score_ids) else "")
                raise ValueError(f"method {name!r}: {src.path} has no slices for frames {short_ids(missing)}{why}")
            self._other_slice(name, score_ids[0] if score_ids else src.frame_ids[0])  # fail early
        self.texel_face = np.asarray(template["texel/face_id"][...]) if self.others else None

    def textures(self, t):
        """Every method's texture slice (W, W, 3) at sequence position t."""
        fid = self.ids[t]
        proj_tex, _ = projection_texture(self.sampler, np.asarray(self.coords[t], np.float64),
                                         self.face_visible[t], self.photos.read("color", fid))
        out = {"ours": self.corrected.read("texture", fid),
               "ours_uncorrected": self.volume.read("texture", fid),
               "global": self.global_tex, "projection": proj_tex}
        for name in self.others:
            out[name] = self._other_slice(name, fid)
        return out

    def _other_slice(self, name, fid):
        """Other method ``name``'s slice of frame ``fid``, checked against the atlas."""
        src = self.others[name]
        tex = src.read(fid)
        if tex.shape != self.global_tex.shape:
            raise ValueError(f"method {name!r}: {src.path} slices are {tex.shape} (frame {fid}), "
                             f"the atlas ({self.template_path}) is {self.global_tex.shape}")
        return tex

    def has_texture(self, t, textures):
        """Every method's faces with texture (F,) bool at position t (``textures``: what
        :meth:`textures` gave; an other method textures the faces with a texel not black)."""
        lab = (np.asarray(self.labels[t]) >= 0) | self.filled
        out = {"ours": lab, "ours_uncorrected": lab, "global": self.global_faces,
               "projection": self.face_visible[t]}
        for name in self.others:
            has = np.zeros(len(self.atlas.faces), bool)
            f = self.texel_face[textures[name].any(axis=2)]
            has[f[f >= 0]] = True
            out[name] = has
        return out

    def truth_at(self, t):
        """:func:`truth_views` at position t."""
        surface = None
        if self.true_embedding is not None:
            surface = transfer_vertices(np.asarray(self.true_vertices[t], np.float64),
                                        self.true_atlas.faces, *self.true_embedding)
        return truth_views(self.true_vertices[t], self.true_atlas,
                           self.truth.read("appearance", self.ids[t]), self.cal,
                           self.p["novel_angle_deg"], template_vertices=surface)

    def novel_renders(self, t, tv, texs):
        """Novel-view renders of every method (and the truth) at t, for the flicker."""
        g = frame_views(self.tracking["vertices"][t], self.atlas, self.cal, tv["novel_transform"],
                        self.face_visible[t], input_view=False)
        out = {m: (ev.view_texture(g["novel"], tex), g["novel"].mask, g["novel_seen"])
               for m, tex in texs.items()}
        out["truth"] = tv["novel"]
        return out


def _score_run(inp: _Inputs, frame_ids, progress) -> list[dict]:
    """Score consecutive frames; the first one's predecessor is rendered afresh for the
    flicker, later ones reuse the renders of the frame before."""
    p, out, prev_novel = inp.p, [], {}
    for fid in frame_ids:
        t = inp.pos_of[fid]
        V = inp.tracking["vertices"][t]
        motion = vertex_motion(inp.tracking["vertices"][t - 1], V) if t > 0 else math.nan
        image, mask = inp.photos.read("color", fid), inp.masks.read("mask", fid)
        texs = inp.textures(t)
        has = inp.has_texture(t, texs)
        tv = inp.truth_at(t) if inp.truth is not None else None
        rec = {"frame": fid, "position": t, "held_out": bool(not inp.is_source[t]),
               "motion_mm": motion, "methods": {}}
        novel_now = {}
        # a property of the photo, not of a method: once per frame, stored with every method
        noise = ev.noise_sigma(image, mask)["sigma"]
        scores = score_methods({m: texs[m] for m in inp.methods}, V, inp.atlas, image, mask, inp.cal,
                               face_has_texture=has, seen_faces=inp.seen_faces,
                               face_visible=inp.face_visible[t], truth=tv, patch=p["patch"],
                               radius=p["radius"], h_size=p["h_size"],
                               blur_interior_px=p["blur_interior_px"], return_views=tv is not None)
        for m, s in scores.items():
            if tv is not None:
                v = s.pop("views")
                novel_now[m] = (v["novel"][0], v["novel"][1], v["novel_seen"])
            s["noise_input"] = noise
            rec["methods"][m] = s
        if tv is not None:
            novel_now["truth"] = tv["novel"]
        if tv is not None and t > 0:
            prev = prev_novel.get(t - 1) or inp.novel_renders(t - 1, inp.truth_at(t - 1), inp.textures(t - 1))
            tp_img, tp_mask = prev["truth"]
            for m in inp.methods:
                r_img, r_mask, seen = novel_now[m]
                p_img, p_mask, p_seen = prev[m]
                # borrowed in both frames: object in all four renders, unseen at t-1 and at t
                sel = tv["novel"][1] & tp_mask & r_mask & p_mask & ~seen & ~p_seen
                fl = ev.temporal_flicker(p_img, r_img, tp_img, tv["novel"][0], sel)
                rec["methods"][m].update(flicker=fl["flicker"], flicker_excess=fl["excess"],
                                         flicker_change=fl["recon_change"],
                                         flicker_true_change=fl["true_change"],
                                         flicker_pixels=fl["n_pixels"])
        prev_novel = {t: novel_now} if tv is not None else {}
        out.append(rec)
        progress(rec)
    return out


def _score(inp: _Inputs, score_ids, threads: int) -> list[dict]:
    """Per-frame records of ``score_ids``, in order; runs of consecutive frames in threads."""
    lock, done, t0 = threading.Lock(), [0], time.perf_counter()

    def progress(rec):
        with lock:
            done[0] += 1
            log.info("evaluation: frame %d (%d/%d%s) ours PSNR %.2f dB, global %.2f dB; "
                     "%.2f s per frame", rec["frame"], done[0], len(score_ids),
                     ", held out" if rec["held_out"] else "", rec["methods"]["ours"]["psnr"],
                     rec["methods"]["global"]["psnr"], (time.perf_counter() - t0) / done[0])

    # frames are scored independently (the flicker re-renders a run's first predecessor), so
    # runs of consecutive frames go to threads: the renders and most metrics release the GIL
    n = len(score_ids)
    n_threads = max(1, min(int(threads), n))
    runs = [score_ids[k * n // n_threads:(k + 1) * n // n_threads] for k in range(n_threads)]
    with ThreadPoolExecutor(n_threads) as pool:
        return [rec for run in pool.map(lambda r: _score_run(inp, r, progress), runs) for rec in run]


def _json_params(p: dict) -> dict:
    """The settings as they read back from JSON (tuples as lists), for comparisons."""
    return json.loads(json.dumps(finite_or_none(p)))


def score_frames(inputs: EvaluationInputs, out_path, params: dict | None = None, *, frames=None,
                 block=None, threads: int = 1) -> dict:
    """Evaluation, one frame block: score every method on the block's frames to score.

    The part of :func:`write_evaluation` that takes the time, split by frame block so that
    blocks are scored in separate processes (jobs) as soon as their slices exist; the records
    are merged by :func:`write_evaluation` (``inputs.records``).

    Args:
        inputs, params, frames: the stores, settings and frames to score, as for
            :func:`write_evaluation` (``observations``, ``records`` and ``sampling`` unused).
        out_path: JSON file to write (:func:`stex.files.write_json`: built aside, moved into place).
        block: [start, stop) sequence positions: score only the frames to score in it. The
            frame-block stores may then be just the ones holding those frames (and, with
            truth, each one's predecessor, for the flicker).
        threads: frames scored at once (runs of consecutive frames, one per thread); the
            result does not depend on it.

    Writes ``out_path``: ``{"stex_artifact": "evaluation_frames", "params"`` (the scoring
    settings, :func:`stex.config.scoring_settings`), ``"frame_ids",
    "source_frames", "scored_frames", "frames": [record, ...], "seconds"}`` with the records of
    ``evaluation.json`` (NaN as null). A block with no frame to score writes an empty list.

    Returns:
        the file's content.
    """
    t_start = time.perf_counter()
    inp = _Inputs(inputs, params, frames=frames, block=block)
    records = _score(inp, inp.score_ids, threads) if inp.score_ids else []
    doc = finite_or_none({"stex_artifact": "evaluation_frames", "params": scoring_settings(inp.p),
                           "frame_ids": inp.ids, "source_frames": inp.sources,
                           "scored_frames": inp.score_ids, "frames": records,
                           "seconds": time.perf_counter() - t_start})
    write_json(out_path, doc)
    log.info("evaluation: %d frames of block %s scored in %.1f s; written to %s", len(records),
             block, doc["seconds"], out_path)
    return doc


def _load_records(records_paths, inp: _Inputs) -> tuple[list[dict], float]:
    """Records of :func:`score_frames` files, checked against the evaluation's inputs, in
    scene order, and the seconds they took."""
    records, seconds, want = [], 0.0, _json_params(scoring_settings(inp.p))
    for path in records_paths:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise StoreError(f"{path}: not a readable evaluation_frames file ({e})") from e
        if not isinstance(doc, dict) or doc.get("stex_artifact") != "evaluation_frames":
            raise StoreError(f"{path}: not an evaluation_frames file")
        got = scoring_settings(doc["params"])  # records of older versions held the figures' too
        if got != want:
            diff = sorted(k for k in set(want) | set(got) if got.get(k) != want.get(k))
            raise ValueError(f"{path} was scored with other evaluation settings ({', '.join(diff)})")
        if doc["frame_ids"] != inp.ids or doc["source_frames"] != inp.sources:
            raise ValueError(f"{path} was scored on frames {short_ids(doc['frame_ids'])} with "
                             f"source frames {short_ids(doc['source_frames'])}; the scene has "
                             f"{short_ids(inp.ids)}, sources {short_ids(inp.sources)}")
        records += nan_for_none(doc["frames"])
        seconds += float(doc["seconds"])
    records.sort(key=lambda r: r["position"])
    got = [r["frame"] for r in records]
    if got != inp.score_ids:
        missing = sorted(set(inp.score_ids) - set(got))
        extra = sorted(f for f in set(got) if got.count(f) > 1 or f not in inp.score_ids)
        raise ValueError(f"records {', '.join(str(p) for p in records_paths)}: frames to score "
                         f"{short_ids(missing)} missing, {short_ids(extra)} twice or not to score")
    return records, seconds


def write_evaluation(inputs: EvaluationInputs, out_dir, params: dict | None = None, *, frames=None,
                     timing: dict | None = None, threads: int = 1, others: dict | None = None) -> dict:
    """Evaluation stage: score every method on the chosen frames and write the report content.

    Args:
        inputs: the stores (:class:`EvaluationInputs`); with ``inputs.records`` the blocks'
            records are merged instead of scoring here.
        out_dir: folder to write (built in ``<out_dir>.partial-<host>-<pid>`` and moved into
            place when complete, replacing an older evaluation's).
        params: the evaluation settings (:func:`stex.evaluation.evaluation_params`).
        frames: global frame ids to score; None -> every ``stride``-th frame of the scene.
        timing: ``{stage: seconds}`` for the timing table, or None.
        threads: frames scored at once (runs of consecutive frames, one per thread); the
            result does not depend on it.
        others: ``{name: path}`` other methods' texture slices in the template's atlas
            (:class:`TextureSlices`: a folder of ``texture_<frame>.png`` or a texture store), or
            ``{name: {"slices": path, "uv_mesh": mesh}}`` for slices in that mesh's UV layout,
            scored by the same code beside ours and shown in every table under ``name``: added
            to the settings' ``other_methods``.

    Writes into ``out_dir``: ``evaluation.json`` (params, per-frame records
    ``frames[i] = {frame, position, held_out, motion_mm, methods: {method: {metric: value}}}``,
    ``summary`` (:func:`stex.evaluation.summarise_frames`), ``tables``
    (:func:`stex.reporting.table_rows`)); ``per_frame.csv`` (one row per frame x method);
    ``table_<name>.csv`` per table; ``tables.rst`` (:func:`stex.reporting.rst_tables`) and
    ``tables.html``; figures ``psnr_per_frame.png``, ``blur_vs_motion.png``,
    ``side_by_side.png``, ``label_map.png`` and, with observations, ``dynamism.png``.

    Returns:
        the ``evaluation.json`` content (NaN as None).
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    check_replaceable(out_dir)       # before the scoring, which takes minutes
    sampling = _read_sampling(inputs.sampling)
    if others:
        params = _with_others(params, others)
    inp = _Inputs(inputs, params, frames=frames, block=None)
    log.info("evaluation: global texture %s from %d source frames (built in %.1f s)",
             inputs.global_texture, len(inp.global_sources), inp.seconds_global)
    if inputs.records is None:
        records = _score(inp, inp.score_ids, threads)
        seconds_scoring = time.perf_counter() - t_start
    else:
        records, seconds_scoring = _load_records(list(inputs.records), inp)
        log.info("evaluation: %d frames' records read from %d files (scored in %.1f s)",
                 len(records), len(inputs.records), seconds_scoring)
    result = _result(inp, records, sampling, seconds_scoring, inputs.scene)

    # built in this writer's <out_dir>.partial-<host>-<pid> and moved into place: a folder at
    # out_dir is complete
    final_dir, out_dir = out_dir, partial_path(out_dir)
    out_dir.mkdir(parents=True)
    try:
        _write_folder(out_dir, inp, result, timing, inputs.observations, t_start)
    except BaseException:
        shutil.rmtree(out_dir, ignore_errors=True)
        raise
    if final_dir.exists():
        try:
            check_replaceable(final_dir)
        except BaseException:
            shutil.rmtree(out_dir, ignore_errors=True)
            raise
    move_into_place(out_dir, final_dir)
    log.info("evaluation: %d frames in %.1f s; written to %s", len(records),
             time.perf_counter() - t_start, final_dir)
    return finite_or_none(result)


def _read_sampling(sampling_path):
    """The rows of :func:`stex.stages.texcoords.write_sampling_table`'s JSON, or None without one."""
    sampling = None
    if sampling_path is not None:
        try:
            sampling = json.loads(Path(sampling_path).read_text())["steps"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{sampling_path}: not a sampling table ({exc})") from exc
    return sampling


def _with_others(params, others) -> dict:
    """``params`` with ``others`` added to its ``other_methods``."""
    params = dict(params or {})
    params["other_methods"] = {**params.get("other_methods", {}), **{
        k: ({"slices": p, "uv_mesh": m} if m else p) for k, (p, m) in other_method_paths(others).items()}}
    return params


def _result(inp: _Inputs, records, sampling, seconds_scoring, scene_path) -> dict:
    """The content of ``evaluation.json`` (NaN still NaN, the total time still to add)."""
    p, ids = inp.p, inp.ids
    summary = summarise_frames(records, inp.methods)
    summary["n_frames"] = len(records)
    summary["n_held_out"] = int(sum(r["held_out"] for r in records))
    summary["held_out_label"] = inp.stride_label
    summary["blur_interior_px"] = int(p["blur_interior_px"])
    scene_name = str(Path(scene_path).parent.name or "scene")
    tabs = table_rows({scene_name: summary})
    return {
        "params": p,
        "scene": scene_name,
        "frame_ids": ids,
        "source_frames": inp.sources,
        "scored_frames": inp.score_ids,
        "methods": list(inp.methods),
        "has_truth": inp.truth is not None,
        "frames": records,
        "summary": summary,
        "tables": tabs,
        "sampling": sampling,
        "seconds": {"global_texture": inp.seconds_global, "scoring": seconds_scoring},
        "libraries": library_versions(),
    }


def _write_folder(out_dir: Path, inp: _Inputs, result: dict, timing, observations_path, t_start) -> None:
    """Every file of the evaluation folder, into ``out_dir``; ``evaluation.json`` last."""
    p, ids, T = inp.p, inp.ids, len(inp.ids)
    records, tabs, sampling = result["frames"], result["tables"], result["sampling"]
    scene_name, summary = result["scene"], result["summary"]
    # vertex motion of every frame (the blur figure's x axis)
    tracked = np.asarray(inp.tracking["vertices"][...])
    motion = np.full(T, math.nan)
    for t in range(1, T):
        motion[t] = vertex_motion(tracked[t - 1], tracked[t])
    fig_pos = inp.fig_pos
    write_csvs(out_dir, records, tabs, timing, sampling)
    rst = rst_tables({scene_name: summary}, timing, sampling)
    (out_dir / "tables.rst").write_text(rst)
    (out_dir / "tables.html").write_bytes(tables_html(rst))
    plot_psnr(out_dir / "psnr_per_frame.png", records)
    plot_blur_motion(out_dir / "blur_vs_motion.png", records, ids, motion)
    picture_side_by_side(out_dir / "side_by_side.png", fig_pos, ids, inp.photos, inp.masks,
                         inp.textures, tracked[fig_pos], inp.atlas, inp.cal,
                         inp.truth_at(fig_pos) if inp.truth is not None else None,
                         inp.face_visible[fig_pos])
    picture_label_map(out_dir / "label_map.png", inp.volume.read("label_map", ids[fig_pos]),
                      ids[fig_pos])
    if observations_path is not None:
        obs = open_store(observations_path, "observations")
        _check_frames("observations", observations_path, obs.attrs["frame_ids"], ids)
        if "dynamism" in obs:
            plot_dynamism(out_dir / "dynamism.png", np.asarray(obs["dynamism"][...], np.float32),
                          np.asarray(inp.template["face_chart"][...]),
                          ev.face_areas(inp.template["vertices"][...], inp.atlas.faces), ids,
                          int(p["dynamism_regions"]))
    result["seconds"]["total"] = time.perf_counter() - t_start
    (out_dir / "evaluation.json").write_text(json.dumps(finite_or_none(result), indent=1))


#: what an evaluation folder holds (write_evaluation): only such a folder is replaced
_EVALUATION_FILES = re.compile(r"^(evaluation\.json|per_frame\.csv|table_\w+\.csv|tables\.(rst|html)|\w+\.png)$")


def check_replaceable(out_dir) -> None:
    """Refuse to replace ``out_dir`` unless it is missing, empty or an earlier evaluation's folder (an
    ``evaluation.json`` and only the files an evaluation writes): a mistyped ``--out`` must not
    delete a run, its textures or anything else."""
    out_dir = Path(out_dir)
    if not out_dir.exists():
        if not out_dir.name or out_dir.name in (".", ".."):
            raise ValueError(f"{out_dir}: give the evaluation a folder of its own (a new name)")
        return
    if not out_dir.is_dir():
        raise ValueError(f"{out_dir} exists and is not a folder: give the evaluation a new folder")
    names = sorted(p.name for p in out_dir.iterdir())
    if not names:  # an empty folder: nothing to lose
        return
    others = [n for n in names if not (_EVALUATION_FILES.match(n) and (out_dir / n).is_file())]
    if "evaluation.json" not in names or others:
        what = f"it holds {others[:3]}" if others else "it has no evaluation.json"
        raise ValueError(f"{out_dir} exists and is not an evaluation folder ({what}); it would be "
                         f"replaced: give a new folder, or an earlier evaluation's")


def evaluate_results(results_dir, out_dir, others: dict | None = None, frames=None,
                     stride: int | None = None, threads: int = 1) -> dict:
    """:func:`write_evaluation` of a finished run's folder, with other methods beside ours.

    Finds the stores of ``results/<scene>`` as the workflow lays them out (the scene's own
    block list, not a glob; ξ or Φ as its observations used; truth on synthetic scenes) and
    scores them with the run's evaluation settings (its ``evaluation/evaluation.json``, else the
    defaults).

    Args:
        results_dir: the run's folder (``results/<scene>``).
        out_dir: folder to write (as :func:`write_evaluation`; not the run's own
            ``evaluation``, which the workflow owns).
        others: ``{name: path or {"slices": path, "uv_mesh": mesh}}`` other methods' slices
            (:class:`TextureSlices`; :func:`write_evaluation`).
        frames: frame ids to consider, or None (all); every ``stride``-th of them is scored.
        stride: score every k-th frame; None -> the run's setting.
        threads: frames scored at once.

    Returns:
        the ``evaluation.json`` content. ``out_dir`` holds what the workflow's evaluation folder
        holds (with the run's sampling table, ``tables.html``) but the timing table: the stage
        times are the run's (``stex tables results/<scene>``).
    """
    R = Path(results_dir)
    if not (R / "scene.zarr").exists():
        raise StoreError(f"{R}: not a results folder (no scene.zarr)")
    if Path(out_dir).resolve() == (R / "evaluation").resolve():
        raise ValueError(f"{out_dir} is the run's own evaluation folder: write elsewhere")
    scene = open_store(R / "scene.zarr", "scene")

    def blocks(kind):
        return run_block_paths(R, kind, scene)

    params = {}
    previous = R / "evaluation" / "evaluation.json"
    if previous.exists():
        params = dict(json.loads(previous.read_text()).get("params", {}))
    if stride is not None:
        params["stride"] = int(stride)
    params = evaluation_params(params)
    coords = R / "projection.zarr"
    observations = R / "observations.zarr"
    if observations.exists():
        if open_store(observations, "observations").attrs.get("coordinates") == "texcoords":
            coords = R / "texcoords.zarr"
    elif (R / "texcoords.zarr").exists():
        coords = R / "texcoords.zarr"
    chosen = None if frames is None else [int(f) for f in frames][::int(params["stride"])]
    sampling = R / "texcoords_sampling.json"
    inputs = EvaluationInputs(
        scene=R / "scene.zarr", frames=blocks("frames"), masks=blocks("masks"), template=R / "template.zarr",
        tracking=R / "tracking.zarr", projection=R / "projection.zarr", labels=R / "labels.zarr",
        volume=blocks("volume"), corrected=blocks("corrected"), global_texture=R / "global_texture.zarr",
        truth=blocks("truth") if "truth" in scene else None, coords=coords,
        observations=observations if observations.exists() else None, data_term=blocks("data_term"),
        sampling=sampling if sampling.is_file() else None)
    return write_evaluation(inputs, out_dir, params, frames=chosen, threads=threads, others=others)
