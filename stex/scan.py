"""Scan stage: a closed template mesh from a capture of the motionless object turning in front of
the camera (``template.from_scan``), and the rigid alignment of a template to a capture's first
frame (``template.align``).

What it computes (pure functions over arrays; :mod:`stex.stages.scan` reads the capture, computes
the masks with :func:`stex.masks.compute_mask` and writes the ``scan`` store):

- :func:`frame_points` — the masked depth pixels of one frame as a coloured point cloud in its
  depth camera's coordinates.
- :class:`ScanFusion` — frame-to-model rigid alignment (Open3D's coloured ICP: point-to-plane
  plus a colour term, against the voxel-averaged points of the frames aligned so far) and TSDF
  fusion (Open3D's voxel block grid) of every frame into the coordinates of the scan's first
  depth frame;
  :meth:`ScanFusion.mesh` runs marching cubes on the volume.
- :func:`close_mesh` — cleaning and hole closing (pymeshlab): keep the largest part, drop
  non-manifold faces, close every hole, so the template stage gets a closed mesh.
- :func:`align_to_view` — global registration (FPFH features, RANSAC) and point-to-plane ICP of a
  mesh onto the points of a view; the frame-0 alignment of ``template.align``.
- :func:`surface_distance` — symmetric mean distance between two meshes (the acceptance measure).

Conventions: metres; poses are 4x4 rigid transforms; a scan frame's pose maps its depth-camera
coordinates to the scan's (those of its first depth frame); meshes are counter-clockwise seen
from outside.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stex.camera import Calibration, backproject_pixels, depth_pixels_in_color
from stex.mesh import nonmanifold_edges

log = logging.getLogger("stex.scan")


def _o3d():
    # Open3D is heavy to import (a second and more) and only the scan and alignment need it
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (degrees) of the 3x3 rotation ``R``."""
    c = (np.trace(np.asarray(R, np.float64)[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def frame_points(depth_mm: np.ndarray, mask_depth: np.ndarray, color: np.ndarray, calibration: Calibration,
                 near_m: float, far_m: float, erode_px: int = 1):
    """The masked depth pixels of one frame as points in its depth camera's coordinates.

    Args:
        depth_mm: (Hd, Wd) uint16 depth, millimetres (0 = invalid).
        mask_depth: (Hd, Wd) bool, the object's depth pixels (:func:`stex.camera.mask_in_depth`).
        color: (Hc, Wc, 3) uint8 RGB image of the same capture.
        calibration: the capture's calibration.
        near_m, far_m: the object's depth range (m); depth outside it is dropped.
        erode_px: the mask is eroded by this many depth pixels first, so silhouette pixels, which
            mix object and background, stay out of the model.

    Returns:
        (points (N, 3) float64 m, colours (N, 3) float64 in [0, 1], color_in_depth (Hd, Wd, 3)
        uint8 the colour image resampled at the depth pixels (0 where none lands), depth_m (Hd, Wd)
        float32 the kept depth in metres, 0 elsewhere).
    """
    d = depth_mm.astype(np.float64) / 1000.0
    keep = np.asarray(mask_depth, bool) & (d >= near_m) & (d <= far_m)
    if erode_px > 0:
        keep = cv2.erode(keep.astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8)) > 0
    d = np.where(keep, d, 0.0)
    idx, px, _ = depth_pixels_in_color(d, calibration)
    Hd, Wd = d.shape
    cid = np.zeros((Hd * Wd, 3), np.uint8)
    cid[idx] = color[px[:, 1], px[:, 0]]
    # depth pixels that land outside the colour image carry no colour: left out
    d_out = np.zeros(Hd * Wd, np.float32)
    d_out[idx] = d.ravel()[idx]
    P = backproject_pixels(d, calibration.depth.K, idx)
    return P, cid[idx].astype(np.float64) / 255.0, cid.reshape(Hd, Wd, 3), d_out.reshape(Hd, Wd)


#: The frame-to-model ICP's correspondence distances, in units of ``icp_distance_m``, coarse to fine:
#: the last, finer than the depth noise at the object, removes most of the pose bias (docs/scan.md).
ICP_SCALES = (2.0, 1.0, 0.5, 0.25)


@dataclass
class FusionParams:
    """Settings of :class:`ScanFusion` (the ``template.scan`` config section's fusion keys)."""

    voxel_m: float = 0.003           # TSDF voxel side (m)
    truncation_voxels: float = 4.0   # TSDF truncation distance, in voxels
    icp_distance_m: float = 0.02     # largest frame-to-model correspondence distance (m)
    icp_iterations: int = 10
    color_weight: float = 0.032      # weight of the colour term against geometry in coloured ICP
    model_every: int = 5             # the aligned frames join the model every this many frames
    min_fitness: float = 0.25        # frames whose fraction of points matched is lower are not fused
    far_m: float = 1.6               # depth beyond this is not fused (m)
    min_weight: float = 3.0          # marching cubes keeps voxels fused from at least this many frames
    block_count: int = 40000         # voxel blocks (8^3 voxels each) the hash map starts with


@dataclass
class ScanFusion:
    """Frame-to-model rigid alignment and TSDF fusion of a scan, one frame at a time.

    ``poses`` (list of 4x4 float64) maps each added frame's depth-camera coordinates to the scan's
    (the first frame's); ``fitness`` and ``rmse`` are the ICP's inlier fraction and inlier RMS
    distance (m) per frame; ``fused`` whether the frame was integrated.
    """

    calibration: Calibration
    params: FusionParams = field(default_factory=FusionParams)
    poses: list = field(default_factory=list)
    fitness: list = field(default_factory=list)
    rmse: list = field(default_factory=list)
    fused: list = field(default_factory=list)

    def __post_init__(self):
        o3d = _o3d()
        p = self.params
        self._o3d = o3d
        # the tensor (hashed voxel block) grid: sparse, so the object's bounds need not be known
        self._grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3d.core.float32,) * 3, attr_channels=(1, 1, 3),
            voxel_size=p.voxel_m, block_resolution=8, block_count=p.block_count, device=o3d.core.Device("CPU:0"))
        self._K = o3d.core.Tensor(np.asarray(self.calibration.depth.K, np.float64))
        self._model = None
        self._pending = None  # aligned frames' points not yet in the model
        self._since_model = 0

    def _cloud(self, points, colours):
        o3d = self._o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pc.colors = o3d.utility.Vector3dVector(colours)
        pc = pc.voxel_down_sample(2.0 * self.params.voxel_m)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.params.voxel_m, max_nn=30))
        pc.orient_normals_towards_camera_location(np.zeros(3))
        return pc

    def _predict(self) -> np.ndarray:
        """Constant-velocity guess of the next pose from the last two."""
        if not self.poses:
            return np.eye(4)
        if len(self.poses) == 1:
            return self.poses[-1].copy()
        step = np.linalg.inv(self.poses[-2]) @ self.poses[-1]
        return self.poses[-1] @ step

    def _register(self, source, init: np.ndarray):
        o3d = self._o3d
        p = self.params
        reg = o3d.pipelines.registration
        criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-5, relative_rmse=1e-5, max_iteration=p.icp_iterations)
        result = init, 0.0, 0.0
        # coarse to fine: a wide search first recovers a turn larger than the guess's error; every
        # step keeps the colour term, which holds the turn where the shape is near-symmetric
        if p.color_weight > 0:
            method = reg.TransformationEstimationForColoredICP(lambda_geometric=1.0 - p.color_weight)
            icp = reg.registration_colored_icp
        else:  # geometry only: Open3D's coloured ICP with no colour term fails to converge
            method, icp = reg.TransformationEstimationPointToPlane(), reg.registration_icp
        for scale in ICP_SCALES:
            try:
                r = icp(source, self._model, p.icp_distance_m * scale, result[0], method, criteria)
            except RuntimeError:  # Open3D raises when no point has a counterpart: the frame is lost
                return init, 0.0, 0.0
            result = np.asarray(r.transformation), float(r.fitness), float(r.inlier_rmse)
        return result

    def add(self, depth_m: np.ndarray, color_in_depth: np.ndarray, points: np.ndarray, colours: np.ndarray) -> bool:
        """Align one frame to the model and fuse it; returns whether it was fused.

        Args:
            depth_m: (Hd, Wd) float32 depth in metres of the object's pixels only (0 elsewhere).
            color_in_depth: (Hd, Wd, 3) uint8 colour at each depth pixel.
            points, colours: that frame's points (N, 3) m and colours (N, 3) in [0, 1]
                (:func:`frame_points`).
        """
        o3d = self._o3d
        p = self.params
        source = self._cloud(points, colours)
        if self._model is None:
            pose, fit, rmse = np.eye(4), 1.0, 0.0
        else:
            pose, fit, rmse = self._register(source, self._predict())
        self.fitness.append(fit)
        self.rmse.append(rmse)
        ok = fit >= p.min_fitness
        self.fused.append(ok)
        # an unmatched frame keeps the guess, so the next frame's prediction stays smooth
        self.poses.append(pose if ok else self._predict())
        if not ok:
            return False
        depth = o3d.t.geometry.Image(np.round(depth_m * 1000.0).astype(np.uint16))
        color = o3d.t.geometry.Image(np.ascontiguousarray(color_in_depth))
        extrinsic = o3d.core.Tensor(np.linalg.inv(pose))
        blocks = self._grid.compute_unique_block_coordinates(depth, self._K, extrinsic, 1000.0, p.far_m,
                                                             p.truncation_voxels)
        self._grid.integrate(blocks, depth, color, self._K, extrinsic, 1000.0, p.far_m, p.truncation_voxels)
        # The model frames are aligned to is the aligned frames' own points, voxel-averaged, not
        # the TSDF's surface: the TSDF extends the surface along the rays at the edge of what a
        # view saw, and those skirts pull the next frames (a drift along the turn's axis).
        seen = o3d.geometry.PointCloud(source).transform(pose)
        self._pending = seen if self._pending is None else self._pending + seen
        self._since_model += 1
        if self._model is None or self._since_model >= p.model_every:
            merged = self._pending if self._model is None else self._model + self._pending
            self._model = merged.voxel_down_sample(2.0 * p.voxel_m)
            self._pending, self._since_model = None, 0
        return True

    def turned_deg(self) -> float:
        """Total rotation (degrees) of the fused frames, summed over consecutive fused frames."""
        P = [q for q, f in zip(self.poses, self.fused) if f]
        return float(sum(rotation_angle_deg((np.linalg.inv(a) @ b)[:3, :3]) for a, b in zip(P, P[1:])))

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Marching cubes on the fused volume: (vertices (V, 3) float64 m, faces (F, 3) int32)."""
        m = self._grid.extract_triangle_mesh(weight_threshold=float(self.params.min_weight) - 0.5).to_legacy()
        return np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int32)


def close_mesh(vertices: np.ndarray, faces: np.ndarray, max_hole_edges: int = 100000):
    """Clean a marching-cubes mesh and close its holes (pymeshlab).

    Merges close vertices, keeps the largest connected part (floating fragments of noise), removes
    non-manifold faces and vertices, closes every hole with at most ``max_hole_edges`` boundary
    edges, and re-orients the faces coherently. Returns (vertices (V, 3) float64 m, faces (F, 3)
    int32); raises ValueError when the result is still not closed (naming its boundary edges).
    """
    import pymeshlab  # heavy; only the scan stage and decimation need it

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int32)
    if len(F) == 0:
        raise ValueError("the fused volume holds no surface (marching cubes gave no face)")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(V, F))
    ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(0.01))
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PercentageValue(50))
    for _ in range(3):  # repairing non-manifold parts can open a hole that the next closing fills
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
        ms.meshing_remove_unreferenced_vertices()
        ms.meshing_close_holes(maxholesize=int(max_hole_edges), newfaceselected=False, selfintersection=False)
        if _boundary_edges(ms.current_mesh().face_matrix()) == 0:
            break
    m = ms.current_mesh()
    V, F = np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int32)
    n_open = _boundary_edges(F)
    if n_open:
        raise ValueError(f"the fused mesh still has {n_open} boundary edges after hole closing: "
                         f"raise template.scan.max_hole_edges or scan the unseen side")
    if _signed_volume(V, F) < 0:  # marching cubes' winding depends on the sign convention: face out
        F = F[:, ::-1].copy()
    return V, F


def _boundary_edges(F: np.ndarray) -> int:
    """Edges not shared by exactly two faces (boundary and non-manifold)."""
    nonmanifold, boundary = nonmanifold_edges(F)
    return len(nonmanifold) + len(boundary)


def _signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed volume (m^3) enclosed by a closed mesh: positive when its faces wind outwards."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


@dataclass
class Alignment:
    """A rigid alignment: ``transform`` (4x4 float64) maps the mesh's coordinates to the view's;
    ``fitness`` is the fraction of the view's points within ``inlier_m`` of the aligned mesh,
    ``rmse`` their RMS distance (m)."""

    transform: np.ndarray
    fitness: float
    rmse: float
    inlier_m: float


def _mesh_cloud(o3d, V, F, n_points: int, seed: int):
    # copies: Open3D refuses read-only arrays (a glTF asset's buffers are)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.array(V, np.float64)),
                                     o3d.utility.Vector3iVector(np.array(F, np.int32)))
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(seed)
    return mesh.sample_points_uniformly(number_of_points=n_points, use_triangle_normal=True)


def _view_cloud(o3d, points, voxel):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pc = pc.voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return pc


def align_to_view(vertices: np.ndarray, faces: np.ndarray, view_points: np.ndarray, voxel_m: float = 0.01,
                  restarts: int = 4, seed: int = 0, inlier_m: float = 0.005) -> Alignment:
    """Rigid transform putting a mesh where a view sees it: FPFH + RANSAC, then point-to-plane ICP.

    The view (one side of the object) is registered to the whole mesh, so every view point has a
    counterpart; RANSAC runs ``restarts`` times with different seeds and the result whose ICP
    refinement matches most view points wins (a near-symmetric object can fool one run).

    Args:
        vertices: (V, 3) float mesh vertices, any rigid frame, metres.
        faces: (F, 3) int.
        view_points: (N, 3) float the object's points in the view's camera coordinates, metres.
        voxel_m: voxel side of the global registration's downsampling (m); features use 5 voxels.
        inlier_m: a view point within this distance of the aligned mesh counts as matched (m).

    Returns:
        :class:`Alignment` (mesh -> view).
    """
    o3d = _o3d()
    reg = o3d.pipelines.registration
    V = np.asarray(vertices, np.float64)
    if len(view_points) < 100:
        raise ValueError(f"the view has only {len(view_points)} object points: too few to align to")
    dense = _mesh_cloud(o3d, V, np.asarray(faces, np.int32), 100000, seed)
    coarse_t = dense.voxel_down_sample(voxel_m)
    coarse_s = _view_cloud(o3d, view_points, voxel_m)
    fine_s = _view_cloud(o3d, view_points, voxel_m / 4)
    feature = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_m, max_nn=100)
    f_s = reg.compute_fpfh_feature(coarse_s, feature)
    f_t = reg.compute_fpfh_feature(coarse_t, feature)
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel_m)]
    best = None
    for k in range(max(1, int(restarts))):
        o3d.utility.random.seed(seed + k)
        g = reg.registration_ransac_based_on_feature_matching(
            coarse_s, coarse_t, f_s, f_t, True, 1.5 * voxel_m, reg.TransformationEstimationPointToPoint(False), 3,
            checkers, reg.RANSACConvergenceCriteria(100000, 0.999))
        T = np.asarray(g.transformation)
        for dist in (2.0 * voxel_m, voxel_m, voxel_m / 3):
            r = reg.registration_icp(fine_s, dense, dist, T, reg.TransformationEstimationPointToPlane(),
                                     reg.ICPConvergenceCriteria(max_iteration=50))
            T = np.asarray(r.transformation)
        e = reg.evaluate_registration(fine_s, dense, inlier_m, T)
        cand = (float(e.fitness), -float(e.inlier_rmse), T)
        if best is None or cand[:2] > best[:2]:
            best = cand
    fit, neg_rmse, T = best
    return Alignment(np.linalg.inv(T), fit, -neg_rmse, inlier_m)


def surface_distance(vertices_a, faces_a, vertices_b, faces_b, n_points: int = 50000, seed: int = 0) -> dict:
    """Symmetric surface distance between two meshes (m): points sampled uniformly on each and
    their exact distance to the other surface. Returns {'mean': symmetric mean, 'a_to_b', 'b_to_a'
    means, 'p95': 95th percentile of both directions, 'max'}."""
    o3d = _o3d()
    out = {}
    d_all = []
    for name, (Va, Fa, Vb, Fb) in {"a_to_b": (vertices_a, faces_a, vertices_b, faces_b),
                                   "b_to_a": (vertices_b, faces_b, vertices_a, faces_a)}.items():
        pts = np.asarray(_mesh_cloud(o3d, np.asarray(Va, np.float64), np.asarray(Fa, np.int32), n_points, seed).points)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(Vb, np.float32)), o3d.core.Tensor(np.asarray(Fb, np.uint32)))
        d = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy().astype(np.float64)
        out[name] = float(d.mean())
        d_all.append(d)
    d = np.concatenate(d_all)
    out.update(mean=float(d.mean()), p95=float(np.percentile(d, 95)), max=float(d.max()))
    return out


def fusion_params(scan: dict, far_m: float) -> FusionParams:
    """:class:`FusionParams` from the validated ``template.scan`` section; ``far_m`` is the
    object's far depth limit (masks.depth_far_m)."""
    keys = ("voxel_m", "truncation_voxels", "icp_distance_m", "icp_iterations", "color_weight", "model_every",
            "min_fitness", "min_weight")
    return FusionParams(**{k: scan[k] for k in keys}, far_m=float(far_m))


def fuse_scan(frames, calibration: Calibration, scan: dict, near_m: float, far_m: float) -> dict:
    """Fuse a scan capture into a closed mesh in the coordinates of its first fused depth frame.

    Args:
        frames: iterable of (frame id, colour (Hc, Wc, 3) uint8, depth (Hd, Wd) uint16 mm,
            object mask in depth (Hd, Wd) bool, or None when the frame has no object).
        calibration: the scan's calibration.
        scan: the validated ``template.scan`` section (fusion settings, min_frames, min_turn_deg,
            max_hole_edges).
        near_m, far_m: the object's depth range (m), as the masks stage uses it.

    Returns:
        dict with vertices (V, 3) float64 m, faces (F, 3) int32 (closed, facing out), frame_ids
        (T,) int64 of the frames tried, poses (T, 4, 4) float64 (frame -> first frame; identity
        for frames without object), fitness (T,) float64, fused (T,) bool, turned_deg, n_empty.

    Raises ValueError when too few frames have the object (``min_frames``), when the fused frames
    do not turn the object (``min_turn_deg``) or the mesh cannot be closed.
    """
    fusion = ScanFusion(calibration, fusion_params(scan, far_m))
    ids, poses, fitness, fused, empty = [], [], [], [], []
    for fid, color, depth_mm, mask_depth in frames:
        ids.append(int(fid))
        P = None
        if mask_depth is not None:
            P, C, cid, dm = frame_points(depth_mm, mask_depth, color, calibration, near_m, far_m)
        if P is None or len(P) < 100:  # no object, or a sliver too small to align
            empty.append(int(fid))
            poses.append(np.eye(4))
            fitness.append(0.0)
            fused.append(False)
            continue
        ok = fusion.add(dm, cid, P, C)
        poses.append(fusion.poses[-1])
        fitness.append(fusion.fitness[-1])
        fused.append(ok)
        log.debug("scan: frame %d fitness %.2f rmse %.4f m%s", fid, fusion.fitness[-1], fusion.rmse[-1],
                  "" if ok else " (not fused)")
    n_fused, n_object, need = int(sum(fused)), len(ids) - len(empty), int(scan["min_frames"])
    if n_object < need:
        raise ValueError(f"the scan has {n_object} frames with the object in their mask ({len(empty)} of its "
                         f"{len(ids)} frames have none), fewer than template.scan.min_frames = {need}")
    if n_fused < need:
        raise ValueError(f"only {n_fused} of the scan's {n_object} frames with the object matched the model, "
                         f"fewer than template.scan.min_frames = {need}: the object moves too far between frames "
                         f"(fuse more of them: template.scan.step) or is not rigid")
    turned = fusion.turned_deg()
    if turned < float(scan["min_turn_deg"]):
        raise ValueError(f"the scan's fused frames turn the object by {turned:.0f} degrees in total, less than "
                         f"template.scan.min_turn_deg = {scan['min_turn_deg']}: the object (or the camera) must "
                         f"go once round, or the unseen side would be invented by hole filling")
    V, F = fusion.mesh()
    V, F = close_mesh(V, F, int(scan["max_hole_edges"]))
    return {"vertices": V, "faces": F, "frame_ids": np.asarray(ids, np.int64), "poses": np.asarray(poses),
            "fitness": np.asarray(fitness), "fused": np.asarray(fused, bool), "turned_deg": turned,
            "n_empty": len(empty)}
