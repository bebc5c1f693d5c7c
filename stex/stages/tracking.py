"""Tracking stage, artifact side: observations read from the ``frames`` and ``masks`` stores, the
tracker (:func:`stex.tracking.track_sequence`) or the source's given meshes, the ``tracking``
store with each frame's fit (silhouette IoU, depth difference), and the plot of that fit."""


from __future__ import annotations

import logging

import numpy as np

from stex.articulated import ArticulatedParams, ArticulatedTracker
from stex.camera import Calibration, mask_in_depth
from stex.io import FrameSequence, create_store, open_store
from stex.mesh import is_closed, transfer_vertices
from stex.preview import pyplot
from stex.frame_fit import depth_residual, depth_scale_ratio, silhouette_iou, template_fit_problem
from stex.skeleton import skeleton_from_arrays
from stex.tracking import FRAME_GUARD_CLIP_M, DepthTarget, Observation, TrackParams, depth_target, track_sequence
from stex.tracking_quality import frame_quality

log = logging.getLogger("stex.tracking")


# -- the stage ------------------------------------------------------------------------------------

def observations_from_stores(frames, masks, calibration, use_flow: bool = True):
    """Yield :class:`Observation` of every frame of ``frames``/``masks`` (:class:`FrameSequence`)."""
    K = calibration.depth.K
    for fid in frames.frame_ids:
        depth_mm = frames.read("depth", fid)
        mask = masks.read("mask", fid)
        fg = mask_in_depth(mask, depth_mm, calibration)
        target = depth_target(depth_mm.astype(np.float64) / 1000.0, K, fg)
        yield Observation(target, frames.read("color", fid) if use_flow else None, calibration, mask)


def write_tracking(scene_path, template_path, frames_paths, masks_paths, params: dict, out) -> None:
    """Tracking stage: per-frame vertices of the template, written as the ``tracking`` store.

    ``params`` is the ``tracking`` config section. Mode ``track`` runs :func:`track_sequence` on
    the depth stream; mode ``given`` carries the source's per-frame meshes (``given/vertices`` of
    the scene, on the original template's topology) over to the template's topology. In both
    modes each frame's mesh is also scored against the frame itself (:func:`silhouette_iou`,
    :func:`depth_residual`), and frames below ``min_silhouette_iou`` are named in a warning and
    in the store's ``poorly_fitted_frames``; given meshes below it at every frame raise
    ``ValueError`` (they and the calibration disagree) and no store is written. Each frame is
    also judged lost or ok, per frame and per vertex (:func:`stex.tracking_quality.frame_quality`;
    tracked frames against the tracker's appearance model, given meshes on depth and mask only):
    ``lost``, ``vertex_lost``, ``lost_share``, ``no_data`` and the ``lost_frames`` named in a warning.
    """
    scene = open_store(scene_path, "scene")
    template = open_store(template_path, "template")
    cal = Calibration.from_dict(scene.attrs["calibration"])
    frames = FrameSequence(frames_paths, "frames")
    V0 = np.asarray(template["vertices"][...], np.float64)
    F = np.asarray(template["faces"][...], np.int64)
    T = len(frames)
    mode = params["mode"]
    masks = FrameSequence(masks_paths, "masks")
    last = []   # the observation of the frame being tracked (track_sequence consumes them)

    def observed():
        for k, ob in enumerate(observations_from_stores(frames, masks, cal,
                                                        use_flow=mode == "track" and params["w_flow"] > 0)):
            if k == 0 and mode == "track":   # before the tracker has moved the template
                _check_template_fit(V0, F, ob.target, frames.frame_ids[0], template_path, params)
            last[:] = [ob]
            yield ob

    with create_store(out, "tracking", attrs={"frame_ids": frames.frame_ids, "mode": mode}, params=params) as store:
        verts = store.create("vertices", (T, len(V0), 3))
        residual = np.full(T, np.nan)
        n_corr = np.zeros(T, np.int64)
        seconds = np.zeros(T)
        iou = np.zeros(T)
        fit = np.zeros(T)
        judged = _Judgement(store, frames.frame_ids, len(V0))
        if mode == "given":
            if "given/vertices" not in scene:
                raise ValueError(f"{scene_path}: tracking.mode is 'given' but the source supplied no per-frame meshes")
            if template.attrs.get("origin", "source") != "source":
                raise ValueError(f"{template_path}: tracking.mode given: the template was built from the "
                                 f"{template.attrs['origin']} (template.from_depth), and the source's per-frame "
                                 f"meshes refer to the source's template; use tracking.mode track")
            given = scene["given/vertices"]
            orig_faces = np.asarray(scene["template/faces"][...])
            ef, eb = template["embedding/face"][...], template["embedding/bary"][...]
            solved = ((k, transfer_vertices(given[k], orig_faces, ef, eb), None) for k, _ in enumerate(observed()))
        elif mode == "track":
            tp = TrackParams.from_dict(params)
            skeleton = skeleton_from_arrays(template, template.attrs.get("skeleton_joint_names"))
            articulated = None
            if skeleton is not None and params.get("skeleton", True):
                log.info("tracking: the template's skeleton (%d joints) is solved first", len(skeleton.parents))
                articulated = ArticulatedTracker(skeleton, V0, F, tp, ArticulatedParams.from_dict(params))
            solved = track_sequence(V0, F, observed(), tp, texcoords=template["texcoords"][...],
                                    texcoord_faces=template["texcoord_faces"][...], articulated=articulated)
        else:
            raise ValueError(f"unknown tracking.mode {mode!r} (track | given)")
        no_depth = []  # frames without foreground depth: the mesh there is carried by colour and prior only
        for k, V, st in solved:
            if k == 0:
                _check_depth_scale(V, F, last[0].target, frames.frame_ids[0],
                                   template_path if mode == "track" else scene_path)
            if not last[0].target.valid.any() or (st is not None and st["n_corr"] == 0):
                no_depth.append(int(frames.frame_ids[k]))
            # the tracker judges each frame against its appearance model; given meshes have none
            judged.record(k, st["quality"] if st is not None else frame_quality(V, F, last[0].target, last[0].mask, cal),
                          st is not None and st["n_corr"] == 0)
            verts[k] = V
            # how well the mesh explains the frame, measured alike in both modes (no truth needed;
            # the tracker's frame guard has already measured the depth fit of the mesh it keeps)
            iou[k] = silhouette_iou(V, F, last[0].mask, cal)
            fit[k] = depth_residual(V, F, last[0].target, FRAME_GUARD_CLIP_M) if st is None else st["depth_residual_m"]
            if st is not None:
                residual[k] = st["data_rms_m"]
                n_corr[k] = st["n_corr"]
                seconds[k] = st["seconds"]
        threshold = float(params["min_silhouette_iou"])
        poor = [int(f) for f, v in zip(frames.frame_ids, iou) if v < threshold]
        if mode == "given" and len(poor) == T:
            # a tracker can lose the object; given meshes that miss it at every frame disagree with the camera
            raise ValueError(
                f"{scene_path}: tracking.mode given: the source's per-frame meshes cover the frames' masks poorly at "
                f"every frame (silhouette IoU {iou.min():.2f}-{iou.max():.2f}, below tracking.min_silhouette_iou "
                f"{threshold:g}): the meshes and the camera disagree. Check that the meshes are in depth-camera "
                f"coordinates in metres, the depth intrinsics and the depth-to-colour extrinsics, or the masks "
                f"(previews/masks.png; if they are known to be loose, lower tracking.min_silhouette_iou)")
        if poor:
            worst = int(np.argmin(iou))
            if poor[0] == frames.frame_ids[0]:
                # at the first frame nothing has been lost yet: the mesh itself misses part of the object
                why = (f"already at the first frame (IoU {iou[0]:.2f}), so the mesh does not cover the whole object "
                       f"(a partial template, e.g. built from one depth image) or the masks are loose "
                       f"(previews/masks.png); later frames can be no better")
            else:
                why = "the mesh has likely lost part of the object there"
            log.warning("tracking: the mesh covers the object's mask poorly (silhouette IoU below %.2f) at %d of %d "
                        "frames, first at frame %d, worst %.2f at frame %d: %s, and texture taken from those frames "
                        "will be misplaced (frames: %s)%s",
                        threshold, len(poor), T, poor[0], iou[worst], frames.frame_ids[worst], why, _runs(poor),
                        _lost_mesh_hint(poor[0] == frames.frame_ids[0], params, V0, F))
        if no_depth:
            log.warning("tracking: no depth of the object to fit at %d of %d frames (%s): no valid depth inside "
                        "the mask, or none near the mesh; the mesh there is carried by the colour terms and the "
                        "prior only (check those frames' depth images)", len(no_depth), T, _runs(no_depth))
        judged.write()
        store.attrs["poorly_fitted_frames"] = poor
        store.write("silhouette_iou", iou)
        store.write("depth_fit_m", fit)
        store.write("residual_m", np.nan_to_num(residual, nan=-1.0))
        store.write("n_correspondences", n_corr)
        store.write("seconds", seconds)


class _Judgement:
    """The tracking-quality judgement of each frame (:func:`stex.tracking_quality.frame_quality`)
    as the ``tracking`` store keeps it: ``vertex_lost`` written frame by frame, ``lost``,
    ``lost_share``, ``no_data`` and the attr ``lost_frames`` at the end, with one warning naming
    the lost frames."""

    def __init__(self, store, frame_ids, n_vertices: int):
        self.store, self.ids = store, list(frame_ids)
        T = len(self.ids)
        self.vertex_lost = store.create("vertex_lost", (T, n_vertices))
        self.lost, self.no_data, self.share = np.zeros(T, bool), np.zeros(T, bool), np.zeros(T)
        self.why = {}    # frame id -> what judged it lost

    def record(self, k: int, quality: dict, no_correspondences: bool) -> None:
        self.vertex_lost[k] = quality["vertex_lost"]
        self.lost[k], self.share[k] = quality["lost"], quality["share"]
        self.no_data[k] = quality["no_data"] or no_correspondences
        if quality["lost"]:
            self.why[int(self.ids[k])] = quality["why"]

    def write(self) -> None:
        ids = sorted(self.why)
        if ids:
            log.warning("tracking: lost %d of %d frames (%s): the mesh does not explain the frame there (first, "
                        "frame %d: %s); tracking.zarr marks them (lost, vertex_lost) and the labeling takes no "
                        "texture from them", len(ids), len(self.ids), _runs(ids), ids[0], self.why[ids[0]])
        else:
            log.info("tracking: no frame of %d judged lost (stex.tracking_quality)", len(self.ids))
        self.store.attrs["lost_frames"] = ids
        self.store.write("lost", self.lost)
        self.store.write("lost_share", self.share)
        self.store.write("no_data", self.no_data)


def _check_depth_scale(vertices, faces, target: DepthTarget, frame_id: int, where) -> None:
    """Refuse a mesh whose depth at the first frame is off by more than 1.5x from the observed
    depth (:func:`depth_scale_ratio`): a template or given meshes in millimetres or centimetres, or
    not in the depth camera's coordinates, would otherwise be tracked without one correspondence."""
    ratio = depth_scale_ratio(vertices, faces, target)
    if ratio is not None and not 1 / 1.5 < ratio < 1.5:
        raise ValueError(
            f"{where}: at frame {frame_id} the mesh lies {ratio:.{0 if ratio >= 10 else 2}f} times as far from "
            f"the depth camera as the depth image reads where they overlap: the mesh must be in metres "
            f"(millimetres give 1000, centimetres 100) and in the depth camera's coordinates. The depth is "
            f"read where the frame's mask puts the object, so a mask that marks the background instead (an "
            f"inverted mask) gives such a ratio too: look at the masks (previews/masks.png)")


def _check_template_fit(vertices, faces, target: DepthTarget, frame_id: int, template_path, params: dict) -> None:
    """Refuse a template that does not fit the object at the first frame (:func:`template_fit_problem`:
    too few faces, wrong units, no overlap with the object's depth, or out of the tracker's reach),
    naming the template store, what is wrong and what to try."""
    problem = template_fit_problem(vertices, faces, target,
                                   float(params.get("rigid_coarse_distance_m", TrackParams.rigid_coarse_distance_m)))
    if problem is not None:
        raise ValueError(
            f"{template_path}: at frame {frame_id} the template does not fit the object: {problem}. The tracker "
            f"starts from the template as it lies, so it must cover the object in the first frame. Check the source's template mesh (its units and pose), and the "
            f"masks (previews/masks.png: the object's depth is read inside them), or build the template from the "
            f"first frame's depth instead (template.from_depth: true)")


def _lost_mesh_hint(from_first_frame: bool, params: dict, vertices, faces) -> str:
    """What to try, appended to the tracking stage's warning about poorly fitted frames: for a
    tracked mesh that loses the object (not one that misses it from the first frame, ``from_first_frame``,
    nor given meshes), the settings that can help; ``params`` the ``tracking`` config section,
    ``vertices`` (V, 3) and ``faces`` (F, 3) the template (only a closed one gets links through
    the solid). "" where none applies."""
    if (from_first_frame or params["mode"] != "track" or params["volume_links"] == 0
            or not is_closed(vertices, faces)):
        return ""
    # links through the solid hold back parts that turn against each other (docs/tracking.md,
    # docs/decisions/tracking.md)
    return (f". If the object is made of parts that turn against each other (an animal, a person's head and "
            f"arms), try tracking.volume_links: 0 (now {params['volume_links']}; docs/tracking.md); fast, thin "
            f"limbs need per-frame meshes from elsewhere (tracking.mode: given)")


def _runs(ids) -> str:
    """'3, 6-39' for [3, 6, 7, ..., 39]: consecutive integers as ranges."""
    out, start = [], None
    for i, v in enumerate(ids):
        if start is None:
            start = v
        if i + 1 == len(ids) or ids[i + 1] != v + 1:
            out.append(str(start) if start == v else f"{start}-{v}")
            start = None
    return ", ".join(out)


def plot_tracking_fit(tracking_path, out) -> None:
    """Write a PNG of how well the tracked (or given) mesh explains each frame: the silhouette
    IoU against the mask, with ``min_silhouette_iou`` and the poorly fitted frames marked, and
    the clipped depth difference (``silhouette_iou`` and ``depth_fit_m`` of the store), and the
    frames the quality signal judged lost (``lost_frames``) shaded."""
    plt = pyplot()
    store = open_store(tracking_path, "tracking")
    ids = np.asarray(store.attrs["frame_ids"])
    iou = np.asarray(store["silhouette_iou"][...], np.float64)
    fit_mm = 1000 * np.asarray(store["depth_fit_m"][...], np.float64)
    params = store.attrs.get("params", {})
    threshold = params.get("min_silhouette_iou")
    poor = np.isin(ids, store.attrs["poorly_fitted_frames"])
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 4.6), dpi=120, sharex=True)
    a1.plot(ids, iou, marker=".", label="silhouette IoU (mesh vs mask)")
    if threshold is not None:
        a1.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"min_silhouette_iou {threshold:g}")
    if poor.any():
        a1.plot(ids[poor], iou[poor], "x", color="tab:red", label=f"poorly fitted ({int(poor.sum())} frames)")
    lost = np.isin(ids, store.attrs.get("lost_frames", []))
    for ax in (a1, a2):
        for f in ids[lost]:   # what the quality signal judged lost: no texture is taken from there
            ax.axvspan(f - 0.5, f + 0.5, color="tab:orange", alpha=0.25, lw=0)
    if lost.any():
        a1.plot([], [], "s", color="tab:orange", alpha=0.4, label=f"judged lost ({int(lost.sum())} frames)")
    a1.set_ylabel("IoU")
    a1.set_title(f"tracking ({store.attrs['mode']}): how well the mesh explains each frame", fontsize=9)
    a2.plot(ids, fit_mm, marker=".", color="tab:green", label="mean |rendered - observed| depth, clipped at 5 cm")
    a2.set_ylabel("mm")
    a2.set_xlabel("frame")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
