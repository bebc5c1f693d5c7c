"""The artifact catalogue: every store stex writes, its arrays' shapes, dtypes, units and
chunking, and its attrs, in one place (:data:`ARTIFACTS`). :mod:`stex.io` writes and checks
stores against it; ``docs/artifacts.md`` is generated from it
(``python -m stex.artifacts > docs/artifacts.md``; a test checks the two agree)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["CONVENTIONS", "ArraySpec", "ArtifactSpec", "ARTIFACTS", "artifacts_markdown"]


CONVENTIONS = (
    "OpenCV pinhole cameras (x right, y down, z forward), metres; integer pixel coordinates are "
    "pixel centres; meshes in depth-camera coordinates; depth stored as uint16 millimetres "
    "(0 = invalid); texcoords in [0,1]^2 with u right, v down, origin at the texture's top-left "
    "corner; faces counter-clockwise seen from outside."
)


@dataclass(frozen=True)
class ArraySpec:
    """One array of an artifact.

    ``shape`` uses symbols (T frames in the store, V vertices, F faces, Vt texcoords, J joints,
    Hc/Wc colour image, Hd/Wd depth image, W texture side); ``chunks`` likewise, where a
    number is a literal chunk length and a symbol means the whole axis.
    """

    shape: tuple
    dtype: str
    units: str
    description: str
    chunks: tuple | None = None  # None: one chunk
    required: bool = True


@dataclass(frozen=True)
class ArtifactSpec:
    description: str
    path: str  # where the workflow writes it, relative to results/<scene>/
    arrays: dict[str, ArraySpec]
    attrs: dict[str, str] = field(default_factory=dict)


ARTIFACTS: dict[str, ArtifactSpec] = {
    "scene": ArtifactSpec(
        description="Scene-wide inputs gathered once at ingest: calibration, frame list, template "
        "mesh and, when the source provides them, per-frame meshes of fixed topology ('given' "
        "tracking mode). Synthetic scenes add their true per-frame geometry.",
        path="scene.zarr",
        arrays={
            "template/vertices": ArraySpec(("V", 3), "float32", "m", "template mesh vertices, depth-camera coordinates (absent when the source has no template: attr has_template)", required=False),
            "template/faces": ArraySpec(("F", 3), "int32", "index", "template triangles into template/vertices", required=False),
            "template/texcoords": ArraySpec(("Vt", 2), "float32", "1", "template texture coordinates, if the template file has them", required=False),
            "template/texcoord_faces": ArraySpec(("F", 3), "int32", "index", "per-corner index into template/texcoords", required=False),
            "template/skeleton/parents": ArraySpec(("J",), "int32", "index", "skinned sources (synthetic glTF asset, biped): each joint's parent, -1 for the root; parents before children (stex.skeleton)", required=False),
            "template/skeleton/bind": ArraySpec(("J", 4, 4), "float64", "m", "each joint's frame at the template's pose, depth-camera coordinates (its translation is the joint's pivot)", required=False),
            "template/skeleton/inverse_bind": ArraySpec(("J", 4, 4), "float64", "m", "inverse of template/skeleton/bind", required=False),
            "template/skeleton/vertex_joints": ArraySpec(("V", 4), "int32", "index", "up to 4 joints skinning each template vertex", required=False),
            "template/skeleton/vertex_weights": ArraySpec(("V", 4), "float32", "1", "their linear-blend-skinning weights (rows sum to 1)", required=False),
            "given/vertices": ArraySpec(("T", "V", 3), "float32", "m", "per-frame meshes supplied by the source (same faces as the template)", (1, "V", 3), required=False),
            "truth/vertices": ArraySpec(("T", "V", 3), "float32", "m", "synthetic scenes: true per-frame vertices (same faces as the template)", (1, "V", 3), required=False),
        },
        attrs={
            "calibration": "Calibration.to_dict(): colour/depth intrinsics, distortion, depth_to_color (m)",
            "frame_ids": "list[int]: global frame indices, in order",
            "frame_blocks": "list[[start, stop)]: frame index ranges of the frame-block stores",
            "source": "dict: what was read (kind, path, settings)",
            "has_template": "bool: whether template/* was written",
            "skeleton_joint_names": "list[str]: names of the J joints of template/skeleton/* (absent without a skeleton)",
        },
    ),
    "frames": ArtifactSpec(
        description="RGB-D frames of one frame block, as recorded (after optional undistortion).",
        path="frames/block_{block}.zarr",
        arrays={
            "color": ArraySpec(("T", "Hc", "Wc", 3), "uint8", "sRGB", "colour images, RGB", (1, "Hc", "Wc", 3)),
            "depth": ArraySpec(("T", "Hd", "Wd"), "uint16", "mm", "depth images in the depth camera, 0 = invalid", (1, "Hd", "Wd")),
            "mask": ArraySpec(("T", "Hc", "Wc"), "bool", "1", "foreground masks supplied by the source (colour resolution)", (1, "Hc", "Wc"), required=False),
            "timestamps": ArraySpec(("T",), "float64", "s", "capture time of each frame"),
        },
        attrs={"frame_ids": "list[int]", "calibration": "as in scene"},
    ),
    "truth": ArtifactSpec(
        description="Synthetic ground truth of one frame block: the true appearance of the whole "
        "surface at each frame (a texture in the truth mesh's own atlas, so any render of a "
        "reconstruction can be scored, unseen regions included), and true masks and depth.",
        path="truth/block_{block}.zarr",
        arrays={
            "appearance": ArraySpec(("T", "W", "W", 3), "uint8", "sRGB", "true texture of the object at each frame, in template/texcoords", (1, "W", "W", 3)),
            "mask": ArraySpec(("T", "Hc", "Wc"), "bool", "1", "true object masks at colour resolution", (1, "Hc", "Wc")),
            "depth": ArraySpec(("T", "Hd", "Wd"), "float32", "m", "noise-free depth (the background wall where the object is absent)", (1, "Hd", "Wd")),
        },
        attrs={"frame_ids": "list[int]"},
    ),
    "masks": ArtifactSpec(
        description="Foreground masks of one frame block (GrabCut seeded from depth).",
        path="masks/block_{block}.zarr",
        arrays={
            "mask": ArraySpec(("T", "Hc", "Wc"), "bool", "1", "object foreground at colour resolution", (1, "Hc", "Wc")),
            "seed": ArraySpec(("T", "Hc", "Wc"), "uint8", "cv2.GC_*", "GrabCut seed labels from depth (0 bg, 1 fg, 2 probable bg, 3 probable fg)", (1, "Hc", "Wc")),
        },
        attrs={"frame_ids": "list[int]",
               "support_planes": "list (per frame) of [nx, ny, nz, offset m, fraction of the in-range depth points on it] "
                                 "or null: the support plane removed (masks.support_plane_tolerance_m > 0; null = none "
                                 "qualified, nothing removed); absent when the option is off or the masks are the source's"},
    ),
    "scan": ArtifactSpec(
        description="template.from_scan: the closed mesh fused from the scan capture of the motionless "
        "object (stex.scan: masks, frame-to-model coloured ICP, TSDF fusion, marching cubes, hole "
        "closing), in the depth-camera coordinates of the scan's first fused frame, and the pose of "
        "every scan frame tried. T = scan frames tried.",
        path="scan.zarr",
        arrays={
            "vertices": ArraySpec(("V", 3), "float32", "m", "fused mesh vertices, the scan's first depth frame's coordinates"),
            "faces": ArraySpec(("F", 3), "int32", "index", "triangles into vertices, counter-clockwise seen from outside; the mesh is closed"),
            "poses": ArraySpec(("T", 4, 4), "float64", "m", "rigid transform of each scan frame's depth-camera coordinates to the first frame's (identity for frames without object)"),
            "fitness": ArraySpec(("T",), "float32", "1", "fraction of the frame's points matched to the model by the ICP (0 for frames without object)"),
            "fused": ArraySpec(("T",), "bool", "1", "whether the frame was fused into the volume"),
        },
        attrs={
            "calibration": "dict: the scan capture's calibration",
            "frame_ids": "list[int]: the scan frames tried (template.scan.step apart)",
            "source": "dict: what the scan capture is (kind, path)",
            "turned_deg": "float: total rotation of the fused frames, summed frame to frame (degrees)",
            "fused_frames": "int: frames fused",
            "empty_frames": "int: frames without object in their mask, left out",
            "seconds": "float: wall time of reading, masking and fusing (s)",
        },
    ),
    "template": ArtifactSpec(
        description="The template mesh of the whole sequence (stex.template): the scene's template "
        "cleaned and decimated (vertices kept on the original surface, depth-camera coordinates), "
        "its UV atlas (xatlas, no mirrored UV triangles: signed UV area < 0 with v down), face "
        "adjacency, the texel -> face map of the atlas, and the embedding of each vertex in the "
        "original template surface (to carry per-frame meshes of the original topology over). "
        "E = adjacent face pairs.",
        path="template.zarr",
        arrays={
            "vertices": ArraySpec(("V", 3), "float32", "m", "template vertices, depth-camera coordinates"),
            "faces": ArraySpec(("F", 3), "int32", "index", "triangles into vertices, counter-clockwise seen from outside"),
            "texcoords": ArraySpec(("Vt", 2), "float32", "1", "atlas texture coordinates in [0,1]^2 (u right, v down)"),
            "texcoord_faces": ArraySpec(("F", 3), "int32", "index", "per-corner index into texcoords"),
            "face_chart": ArraySpec(("F",), "int32", "index", "UV chart of each face (faces sharing texcoords), numbered by first face"),
            "adjacency/pairs": ArraySpec(("E", 2), "int32", "index", "faces sharing a manifold edge (smaller id first); non-manifold edges give no pair"),
            "adjacency/edges": ArraySpec(("E", 2), "int32", "index", "the shared edge of each pair, vertex ids (smaller first)"),
            "texel/face_id": ArraySpec(("W", "W"), "int32", "index", "face whose UV triangle holds texel (r, c)'s centre ((c+.5)/W, (r+.5)/W); -1 = gutter/empty", (1024, 1024)),
            "texel/bary": ArraySpec(("W", "W", 3), "float32", "1", "barycentrics of the texel centre on texel/face_id (corners 0, 1, 2); 0 where empty", (1024, 1024, 3)),
            "embedding/face": ArraySpec(("V",), "int32", "index", "face of the ORIGINAL template (scene template/faces) on which each vertex lies"),
            "embedding/bary": ArraySpec(("V", 3), "float32", "1", "barycentrics of each vertex on embedding/face (stex.mesh.transfer_vertices)"),
            "skeleton/parents": ArraySpec(("J",), "int32", "index", "templates with a skeleton (a skinned source or template.rig): each joint's parent, -1 for the root; parents before children (stex.skeleton, docs/tracking.md)", required=False),
            "skeleton/bind": ArraySpec(("J", 4, 4), "float64", "m", "each joint's frame at the template's pose, template coordinates (its translation is the joint's pivot)", required=False),
            "skeleton/inverse_bind": ArraySpec(("J", 4, 4), "float64", "m", "inverse bind matrices (template coordinates -> joint frame)", required=False),
            "skeleton/vertex_joints": ArraySpec(("V", 4), "int32", "index", "up to 4 joints skinning each vertex: the source's weights blended over the vertex's embedding face, the 4 largest kept", required=False),
            "skeleton/vertex_weights": ArraySpec(("V", 4), "float32", "1", "their linear-blend-skinning weights (rows sum to 1; the template's vertices are the skinned mesh at the identity pose)", required=False),
        },
        attrs={
            "atlas_size": "int: atlas side W (texels)",
            "gutter_px": "int: xatlas padding around every chart (texels); charts end up >= 2*gutter_px+2 texels apart and >= gutter_px from the atlas border",
            "counts": "dict: vertices, faces, texcoords, charts, adjacent_pairs, covered_texels, faces_in",
            "clean_report": "dict: stex.template.clean_mesh report (duplicates, degenerates, non-manifold edges; closed parts turned round to face out (cavity walls into their cavity) and open parts to face the depth camera, edges between faces of opposite winding)",
            "decimated": "bool: whether quadric decimation ran",
            "subdivided": "int: midpoint subdivisions applied to a low-poly mesh",
            "uv": "str: 'xatlas' (a new atlas) or 'mesh' (the template mesh's own texture coordinates, template.uv)",
            "flipped_fixed": "int: UV triangles xatlas left mirrored that were fixed (0 with uv 'mesh')",
            "atlas": "dict: build_atlas statistics (mirrored charts, folds, texels per metre, utilization: the "
                     "fraction of texel centres covered, xatlas_utilization: xatlas' own figure, faces_without_texel, "
                     "timings); with uv 'mesh' keep_layout's (source 'mesh', charts, mirrored_faces, "
                     "degenerate_uv_faces, overlap_texels, utilization, faces_without_texel)",
            "gutter_conflicts": "int: texels closer than gutter_px to another chart (0 expected)",
            "border_gap_px": "int: empty texels between the atlas border and the nearest covered texel (>= gutter_px expected)",
            "embedding_max_distance_m": "float: largest move of a decimated vertex onto the original surface (m)",
            "origin": "str: 'source' (the scene's template/*; embedding/* refer to it) or 'depth of frame N' "
                      "(template.from_depth: built from that frame's depth inside its mask; embedding/* refer to that mesh) "
                      "or 'scan' (template.from_scan: the scan store's fused mesh; embedding/* refer to it)",
            "alignment": "dict or null: template.align / from_scan: the rigid transform (4x4, template -> depth camera "
                         "at the first frame), fitness (fraction of that frame's object points within 5 mm), rmse_m, "
                         "frame, rotation_deg, translation_m; null when the template was not aligned",
            "timings_s": "dict: wall time (s) of clean, decimate, embed, atlas, adjacency_texels",
            "skeleton_joint_names": "list[str] or null: names of the J joints of skeleton/* (null without a skeleton)",
        },
    ),
    "tracking": ArtifactSpec(
        description="Per-frame vertices of the template (stex.tracking): embedded deformation with "
        "the L0 motion regulariser tracked through the depth stream (mode 'track'), or the "
        "source's own per-frame meshes carried over to the template topology (mode 'given'); in "
        "both modes, how well each frame's mesh explains the frame (silhouette_iou, depth_fit_m) "
        "and the frames it explains poorly.",
        path="tracking.zarr",
        arrays={
            "vertices": ArraySpec(("T", "V", 3), "float32", "m", "template vertices at each frame, depth-camera coordinates (faces: template.zarr)", (1, "V", 3)),
            "residual_m": ArraySpec(("T",), "float32", "m", "RMS point-to-plane residual of the fit over its correspondences (-1: not tracked)"),
            "n_correspondences": ArraySpec(("T",), "int32", "1", "depth correspondences used at the last iteration"),
            "seconds": ArraySpec(("T",), "float32", "s", "solve time per frame"),
            "silhouette_iou": ArraySpec(("T",), "float32", "1", "intersection over union of the mesh's silhouette in the colour camera and the frame's mask; both modes"),
            "depth_fit_m": ArraySpec(("T",), "float32", "m", "mean |rendered - observed| depth over the union of the mesh's and the foreground's depth pixels, each clipped at 5 cm (a pixel only one covers counts 5 cm); both modes"),
            "lost": ArraySpec(("T",), "bool", "1", "the frame is judged lost by the tracking-quality signal (stex.tracking_quality: depth, silhouette, appearance, flow consistency); the labeling takes no texture from it", required=False),
            "vertex_lost": ArraySpec(("T", "V"), "bool", "1", "the vertex is judged lost at the frame (seen by the depth camera and off the depth, the mask or the appearance); the labeling takes no texture for a face with such a vertex from that frame", (1, "V"), required=False),
            "lost_share": ArraySpec(("T",), "float32", "1", "share of the vertices the depth camera sees judged lost (1 where it sees none)", required=False),
            "no_data": ArraySpec(("T",), "bool", "1", "no depth correspondence at the frame (no object depth under the mesh): the tracker kept the rigid solution; also judged lost", required=False),
        },
        attrs={"frame_ids": "list[int]", "mode": "'track' or 'given'",
               "poorly_fitted_frames": "list[int]: frames whose silhouette_iou is below tracking.min_silhouette_iou (a warning names them)",
               "lost_frames": "list[int]: frames judged lost (array lost; a warning names them)"},
    ),
    "poses": ArtifactSpec(
        description="Rigid poses between the frame pairs candidate pruning keeps (stex.poses, "
        "stex.pruning): per target frame its source frames (each face's poses.nearest_frames "
        "nearest in shape that see it; every frame with 0), and for every unordered pair of a "
        "target and one of its sources K_{i->j} (i < j) mapping frame i's mesh onto frame j "
        "(x' = R x + t, depth-camera coordinates), from RANSAC over same-index vertex pairs plus "
        "robust point-to-plane ICP; K_{j->i} is its exact inverse, K_{t->t} the identity. Used by E_glo.",
        path="poses.zarr",
        arrays={
            "pairs": ArraySpec(("P", 2), "int32", "index", "frame pairs (i, j), i < j, sequence positions, sorted lexicographically"),
            "poses": ArraySpec(("P", 4, 4), "float64", "m", "poses[p] = K_{i->j} of pairs[p] (4x4 rigid, translation in metres)"),
            "inlier_ratio": ArraySpec(("P",), "float32", "1", "fraction of vertices within poses.inlier_threshold_m of their partner after alignment"),
            "neighbours": ArraySpec(("T", "N"), "int32", "index", "source frames each target frame is compared with (sequence positions, ascending, -1 padding; the target itself when it is a source)"),
            "descriptors": ArraySpec(("T", "D"), "float32", "m", "per-frame shape descriptor: rigidly aligned vertex subset, PCA-reduced (stex.pruning.shape_descriptors)"),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each sequence position",
            "vertices_source": "str: the store the per-frame vertices were read from",
            "vertices_array": "str: the array read from it",
            "source_stride": "int: data_term.source_stride the sources were chosen with",
        },
    ),
    "projection": ArtifactSpec(
        description="The tracked mesh in every colour image (stex.projection): Φ, the vertices "
        "moved through depth_to_color and projected with the colour pinhole, and visibility "
        "decided in the colour camera (depth test against the colour-camera render of the mesh, "
        "facing, image margin, eroded foreground mask; a face is visible only with its 3 "
        "vertices). Cosines are stored for every vertex/face (0 = back-facing) so later stages "
        "apply their own threshold (θ_n). Rows are one frame per chunk: the stage writes one "
        "frame at a time, the texture-coordinate optimisation reads one frame at a time, and a "
        "whole [T, F] table (5 MB of bools, 21 MB of cosines on the paper scene) is read in one "
        "pass over the T chunks.",
        path="projection.zarr",
        arrays={
            "phi": ArraySpec(("T", "V", 2), "float32", "px", "colour-image coordinates (u column, v row; integer = pixel centre) of every vertex", (1, "V", 2)),
            "vertex_visible": ArraySpec(("T", "V"), "bool", "1", "vertex seen in the colour image (depth test, facing, margin, mask)", (1, "V")),
            "vertex_cos": ArraySpec(("T", "V"), "float32", "1", "cosine between the area-weighted vertex normal and the view ray (attr cos_mode), clipped to [0, 1], every vertex", (1, "V")),
            "face_visible": ArraySpec(("T", "F"), "bool", "1", "face seen: its own test (face normal, depth test of its corners against its plane) and its 3 vertices visible", (1, "F")),
            "face_cos": ArraySpec(("T", "F"), "float32", "1", "cosine between the face normal and the view ray from its centroid (attr cos_mode), clipped to [0, 1], every face", (1, "F")),
            "face_glimpsed": ArraySpec(("T", "F"), "bool", "1", "face_visible, or the face's own test passes and its 3 corners project inside the margin and the mask, not eroded (a face on a silhouette: the image shows it, a corner fails the vertex rule)", (1, "F")),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each row",
            "color_size": "[Wc, Hc]: colour image size (px)",
            "cos_mode": "'view_ray' (cosine to the ray to the camera centre) or 'optical_axis' (to the camera z axis, as the authors' code)",
            "visible_area_fraction": "list[float]: fraction of the surface area in visible faces, per frame",
        },
    ),
    "texcoords": ArtifactSpec(
        description="Optimised texture coordinates (stex.texcoords): ξ, every vertex's position on "
        "every colour image where it is visible, optimised from Φ so that all frames agree with "
        "per-sample proxy colours (Eq. 1; Kim et al. 2019 as accelerated in Kim et al. 2021: key "
        "frames coarse-to-fine over an image pyramid, displacements ξ − Φ interpolated to the "
        "other frames, refinement over all frames). Energy rows are stages: levels 0 (coarsest) .. "
        "L-1 on the key frames, then the all-frame refinement (attr energy_rows); columns are the "
        "energy at the stage's start and after each accepted step, NaN once the stage stopped; "
        "non-increasing along each row.",
        path="texcoords.zarr",
        arrays={
            "xi": ArraySpec(("T", "V", 2), "float32", "px", "optimised colour-image coordinates (u column, v row; integer = pixel centre); Φ where the vertex is not visible", (1, "V", 2)),
            "valid": ArraySpec(("T", "V"), "bool", "1", "vertex visible at that frame (projection vertex_visible): ξ is meaningful", (1, "V")),
            "energy": ArraySpec(("L", "I"), "float64", "(grey/255)^2", "Eq. 1, Σ ((g C − P)/255)² over the stage's frames, visible faces and samples (grey image blurred as the stage; g the frame's gain, 1 with texcoords.gain none), each (frame, face) sum e passed through ρ(e) = S c² e / (S c² + e) when texcoords.robust_grey c > 0; per stage (row) and accepted step (column); NaN-padded"),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each row",
            "keyframes": "list[int]: global frame indices of the key frames",
            "color_size": "[Wc, Hc]: colour image size (px)",
            "energy_rows": "list[str]: stage of each energy row ('level 0'.., 'refine')",
            "stages": "list[dict]: per stage: frames, blurs, iterations, seconds, crop_mb, energy_start, energy_end",
            "seconds": "float: wall time of the optimisation (s)",
        },
    ),
    "observations": ArtifactSpec(
        description="What every frame shows of every face (stex.observations), gathered in one "
        "pass over the colour frames at the texture coordinates (ξ, or Φ without the texcoords "
        "stage: attr coordinates): grey samples per face (E_temp) and along every shared edge "
        "(E_spa), the quality flags of E_qual, the SSIM dynamism S(f, t) and the SHOT "
        "descriptors of the tracked mesh (E_loc). E = adjacent face pairs (template "
        "adjacency/pairs, edge from adjacency/edges[e, 0] to [e, 1]).",
        path="observations.zarr",
        arrays={
            "face_samples": ArraySpec(("T", "F", 15), "uint8", "grey", "grey value (ITU-R 601 luma) at the authors' 15 barycentric samples of each face; 0 where the face is not visible", (1, "F", 15)),
            "edge_samples": ArraySpec(("T", "E", 9), "uint8", "grey", "grey value at 9 evenly spaced points along each shared edge (both ends included); 0 unless both edge vertices are visible", (1, "E", 9)),
            "face_visible": ArraySpec(("T", "F"), "bool", "1", "face visible in the frame (projection face_visible): the frame is a label candidate for the face", (1, "F")),
            "motion": ArraySpec(("T", "F"), "float32", "px", "mean move of the face's texture-coordinate centroid to frames l-1 and l+1 (px per frame); NaN where unknown: the face not visible at l, or (params.unseen_neighbours 'unknown', the authors' rule) not visible at l-1 or l+1, or l the first/last frame", (1, "F")),
            "blur_cost": ArraySpec(("T", "F"), "float32", "1", "blur part of E_qual (attr params.blur_rule): step = 1 where motion > theta_b_px or is NaN, else 0; graded = min(motion / theta_b_px, params.blur_cap), NaN motion costing blur_cap; 0 where not visible", (1, "F")),
            "slanted": ArraySpec(("T", "F"), "bool", "1", "E_qual view-angle step (attr params.angle_rule)", (1, "F")),
            "dynamism": ArraySpec(("T", "F"), "float32", "1", "S(f, t): mean SSIM of face f between the partial textures of frames t-1 and t (row 0 = row 1); NaN where not seen in both", (1, "F"), required=False),
            "descriptors": ArraySpec(("T", "V", 352), "float16", "1", "SHOT descriptor of every vertex of the tracked mesh (unit L2 norm, geodesic neighbourhoods)", (1, "V", 352), required=False),
            "strain": ArraySpec(("T", "F", 3), "float32", "1", "log stretch ln(|e_k(t)| / |e_k(rest)|) of each face's edges k = (v0 v1, v1 v2, v2 v0) on the tracked mesh, averaged strain_rings times over the faces sharing a vertex (E_str)", (1, "F", 3), required=False),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each row",
            "coordinates": "'texcoords' (ξ) or 'projection' (Φ): the texture coordinates sampled",
            "theta_b_px": "float: the θ_b applied (px per frame; params.theta_b_px, or the paper's 20 px scaled to the colour width when that is null)",
            "fractions": "dict: blurred (the blur step, whatever blur_rule) and slanted fractions of the visible (frame, face) pairs",
        },
    ),
    "data_term": ArtifactSpec(
        description="Label candidates of one block of target frames (stex.data_term): for every "
        "target t and face f the K best source frames l by the data term, with the terms of "
        "each candidate, and the global similarity rows. Candidates are positions in the "
        "sequence (0..T-1), sorted ascending, -1 = padding (a face visible in fewer than K "
        "frames, or never).",
        path="data_term/block_{block}.zarr",
        arrays={
            "glo": ArraySpec(("Tb", "N"), "float32", "1", "E_glo[t, glo_sources[t, n]]: clipped depth difference of K_{t->l}(M_t) and M_l rendered in the depth camera over the union of their silhouettes, divided by the clip (0..1; 1 at padding)"),
            "glo_sources": ArraySpec(("Tb", "N"), "int32", "index", "the source frames l of each target's E_glo row and candidates (poses neighbours: sequence positions, ascending, -1 padding)"),
            "candidates": ArraySpec(("Tb", "F", "K"), "int16", "index", "candidate source frames of face f at target t (sequence positions, ascending), -1 = none", (1, "F", "K")),
            "e_glo": ArraySpec(("Tb", "F", "K"), "float32", "1", "E_glo of each candidate", (1, "F", "K")),
            "e_loc": ArraySpec(("Tb", "F", "K"), "float32", "1", "E_loc of each candidate: -(1/3) sum of the SHOT similarities of the face's 3 vertices (-1..0)", (1, "F", "K")),
            "e_qual": ArraySpec(("Tb", "F", "K"), "float32", "1", "E_qual of each candidate: observations blur_cost + slanted (0, 1 or 2 with the blur step), times data_term.borrowed_qual_weight on faces the target does not see", (1, "F", "K")),
            "e_str": ArraySpec(("Tb", "F", "K"), "float32", "1", "E_str of each candidate: local strain difference of the tracked meshes less the tolerance (attr str_tolerance) on faces the target does not see, clipped (0..1; 0 when data_term.omega_str = 0)", (1, "F", "K")),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each target row",
            "sequence_frame_ids": "list[int]: global frame index of each sequence position (columns of glo, candidate values)",
            "source_frames": "list[int]: global frame indices allowed as sources (data_term.source_stride, without the frames tracking lost)",
            "lost_source_frames": "list[int]: frames of the source stride left out because tracking lost them (data_term.exclude_lost); not held out",
            "prefilter_exact": "list[float]: per target, fraction of faces whose candidate pruning is provably exact",
            "str_tolerance": "float: the E_str tolerance used on faces the target does not see (data_term.str_tolerance, auto: measured from the strain noise)",
            "seconds": "float: wall time of the block (s)",
        },
    ),
    "labels": ArtifactSpec(
        description="The frame labeling (stex.labeling): for every frame t and face f the "
        "source frame l_{f,t} whose image textures f at t (Eq. 2: data term + spatial and "
        "temporal smoothness with selective weighting), by α-expansion per frame and block "
        "coordinate descent over even and odd frames. Faces no frame sees but a source frame "
        "glimpses (projection face_glimpsed) get that frame at every t (glimpse_source); faces "
        "left without any source get -1 (the volume stage fills them in texture space).",
        path="labels.zarr",
        arrays={
            "labels": ArraySpec(("T", "F"), "int16", "index", "source frame (sequence position) of each face at each frame; -1 = no source (never_seen)", (1, "F")),
            "energy": ArraySpec(("R",), "float64", "1", "total energy of Eq. 2 after the initial per-frame solves (row 0) and after every BCD round"),
            "frame_energy": ArraySpec(("R", "T"), "float64", "1", "energy terms of each frame's MRF (its unary, spatial and its temporal links to the previous frame) per round"),
            "never_seen": ArraySpec(("F",), "bool", "1", "faces without any source: visible in no source frame and glimpsed by none (label -1)"),
            "glimpse_source": ArraySpec(("F",), "int32", "index", "for faces visible in no source frame: the source frame that glimpses them at the largest face_cos, their label at every frame; -1 = none or face visible somewhere"),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each row",
            "rounds": "list[dict]: per round: round, energy, seconds, changed (labels (frame, face) that changed in the round; round 0: the labels set)",
            "n_never_seen": "int: faces without any source (never_seen)",
            "n_glimpsed": "int: faces labelled with their glimpse_source",
            "coverage_of_seen_faces": "list[float]: per frame, the fraction of the faces some source frame sees that got a label (1.0 when no face is seen)",
        },
    ),
    "volume": ArtifactSpec(
        description="Texture volume of one frame block (stex.volume): for every frame t one W×W "
        "slice of the fixed template atlas, each covered texel sampled (bicubic, or bilinear: "
        "volume.interpolation) from the colour image of its face's label l_{f,t} at the "
        "optimised texture coordinates ξ_l; gutter texels dilated (attr gutter_px) so bilinear "
        "lookups and mip-maps do not bleed black. Slices are stored in compressed tiles. label_map holds the source frame of every texel.",
        path="volume/block_{block}.zarr",
        arrays={
            "texture": ArraySpec(("T", "W", "W", 3), "uint8", "sRGB", "texture slice of each frame in the template atlas (template.zarr texcoords), RGB, row 0 = v 0", (1, 1024, 1024, 3)),
            "label_map": ArraySpec(("T", "W", "W"), "int16", "index", "source frame (position in the sequence) each texel was sampled from; -1 = gutter, empty or filled", (1, 1024, 1024)),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each slice",
            "gutter_px": "int: rings of gutter texels filled around every chart",
            "first_position": "int: sequence position of the first slice (labels are sequence positions)",
            "never_seen_texels": "int: texels of never-seen faces, filled from the nearest seen surface point",
            "fill": "str: how never-seen texels were filled (volume.fill: nearest or harmonic; none when there are none)",
            "atlas_digest": "str: the template atlas the slices are in (stex.atlas.atlas_digest: 16 hex digits "
                            "of a hash of texcoords, texcoord_faces and atlas_size). Every reader of the store "
                            "(correction, evaluation, `stex evaluate --texture`, export) refuses it when the "
                            "template's differs: a texture of another atlas of the same side would read as noise. "
                            "Stores written before this attr pass unchecked",
        },
    ),
    "corrected": ArtifactSpec(
        description="Colour-corrected texture volume of one frame block (stex.correction): each "
        "volume slice after the gradient-domain correction (screened Poisson, gradients kept "
        "inside a source label, continued one-sidedly across label boundaries, chart seams "
        "coupled; texels sampled from the slice's own frame kept as they are, with "
        "correction.keep_own_frame).",
        path="corrected/block_{block}.zarr",
        arrays={
            "texture": ArraySpec(("T", "W", "W", 3), "uint8", "sRGB", "corrected texture slice of each frame in the template atlas, RGB", (1, 1024, 1024, 3)),
        },
        attrs={
            "frame_ids": "list[int]: global frame index of each slice",
            "gutter_px": "int: as in volume",
            "label_boundary_step": "list[[before, after]]: mean colour step across label boundaries per slice (grey levels)",
            "atlas_digest": "str: as in volume",
        },
    ),
    "global_texture": ArtifactSpec(
        description="The comparison baseline of Kim et al. 2019 (stex.stages.global_texture.write_global_texture): "
        "ONE texture for the whole sequence in the template atlas, every texel the weighted mean "
        "of the source frames (held-out protocol: sequence positions 0, k, 2k, ..., k = "
        "data_term.source_stride) that see its face, sampled at the texture coordinates of the volume "
        "(ξ or Φ), weight w_t(f) = projection face_cos, (t, f) with w_t(f) <= min_weight left out; "
        "texels of faces never used are filled from their neighbours, gutters dilated (template "
        "gutter_px). Read by the evaluation.",
        path="global_texture.zarr",
        arrays={
            "texture": ArraySpec(("W", "W", 3), "uint8", "sRGB", "the global texture in the template atlas (template.zarr texcoords), RGB, row 0 = v 0", (1024, 1024, 3)),
            "weight_sum": ArraySpec(("W", "W"), "float32", "1", "Σ_t w_t(f) over the used source frames of each texel's face; 0 = nothing observed (filled or empty texel)", (1024, 1024)),
            "face_textured": ArraySpec(("F",), "bool", "1", "face with at least one used observation (visible in a source frame with face_cos > min_weight)"),
        },
        attrs={
            "source_frames": "list[int]: global frame ids of the source frames blended (as the data_term stores' source_frames)",
            "sequence_frame_ids": "list[int]: every frame id of the scene, in order",
            "seconds": "float: wall time of the blend (s)",
            "atlas_digest": "str: as in volume",
        },
    ),
}


def artifacts_markdown() -> str:
    """The docs page describing every artifact (docs/artifacts.md)."""
    lines = [
        "# Artifacts",
        "",
        "Generated from `stex/artifacts.py` (`python -m stex.artifacts > docs/artifacts.md`); do not edit by hand.",
        "",
        "Every stage writes zarr v3 stores under `results/<scene>/`. Writes are atomic (built in "
        "`<path>.partial-<host>-<pid>`, one folder per writer, moved into place when complete). Every store has the attrs "
        "`stex_artifact`, `stex_version`, `libraries` (the versions of Python and of the libraries "
        "whose arithmetic enters the results), `complete`, `params`, `units`, `conventions` and "
        "`chunk_files` (per array, the chunk files it was written with: a reader refuses a store "
        "missing some, e.g. a partial copy, which zarr would read as zeros). Chunks are zstd "
        "with a content checksum: a reader names the store, array and chunk file of a chunk "
        "cut short or damaged in place (stores written before the checksum still read).",
        "",
        f"Conventions: {CONVENTIONS}",
        "",
        "Shape symbols: T frames (in that store), V vertices, F faces, Vt texture coordinates, "
        "Hc×Wc colour image, Hd×Wd depth image, W texture side, E adjacent face pairs, Tb target frames of a block, K candidates, R rounds, P frame pairs, N sources per target, D descriptor components. Per-frame arrays are chunked one "
        "frame per chunk.",
        "",
    ]
    for name, spec in ARTIFACTS.items():
        lines += [f"## `{name}` — `results/<scene>/{spec.path}`", "", spec.description, "",
                  "| array | shape | dtype | units | required | meaning |", "|---|---|---|---|---|---|"]
        for aname, a in spec.arrays.items():
            shape = "[" + ", ".join(str(s) for s in a.shape) + "]"
            lines.append(f"| `{aname}` | {shape} | {a.dtype} | {a.units} | {'yes' if a.required else 'no'} | {a.description} |")
        if spec.attrs:
            lines += ["", "attrs:", ""] + [f"- `{k}`: {v}" for k, v in spec.attrs.items()]
        lines.append("")
    lines += [
        "## Evaluation outputs (JSON, CSV and figures, not zarr)",
        "",
        "- `results/<scene>/evaluation_frames/block_<b>.json` — one frame block's scores "
        "(stex.stages.evaluation.score_frames), written atomically: `stex_artifact` "
        "\"evaluation_frames\", `params` (the evaluation settings without the figures' "
        "`figure_frame` and `dynamism_regions`, which only the merge reads: changing them "
        "re-draws the figures without re-scoring), `frame_ids` (every frame of "
        "the scene), `source_frames`, `scored_frames` (this block's), `seconds`, and `frames`: "
        "one record per scored frame, `{frame, position, held_out, motion_mm, methods: {method: "
        "{metric: value}}}` (metrics in docs/metrics.md; null where a score is undefined, e.g. the "
        "flicker of the first frame).",
        "- `results/<scene>/evaluation/` — the blocks' records merged "
        "(stex.stages.evaluation.write_evaluation): `evaluation.json` (the records, `summary`, `tables`), "
        "`per_frame.csv`, `table_<name>.csv`, `tables.rst` / `tables.html` and the PNG figures; "
        "with the sampling table, `sampling` in `evaluation.json` and `table_sampling.csv`.",
        "- `results/<scene>/texcoords_sampling.json` — the paper's sampling table "
        "(stex.stages.texcoords.write_sampling_table; rule texcoords_sampling, when ξ is optimised and "
        "`sampling_table.steps` is not empty), written atomically: `params` (the texcoords "
        "settings) and `steps`: one row per key-frame step, `{step, keyframes, energy (the final "
        "all-frame Eq. 1 energy), seconds, error_ratio (energy / that of step 1), speedup "
        "(seconds of step 1 / seconds)}`.",
        "- `stex evaluate RUN --texture NAME=PATH --out DIR` (stex.stages.evaluation.evaluate_results) "
        "writes the same files into DIR, but the timing table (the run's job times: `stex tables RUN`), "
        "with other methods beside ours (`methods` lists them; their records and table rows carry NAME). Their slices: `texture_<frame:05d>.png` "
        "(8-bit RGB, the run's atlas size) or a `corrected` / `volume` store. Slices in another UV "
        "layout: `--uv-mesh NAME=MESH` (that layout's mesh, in the template's coordinates; "
        "stex.resample carries each slice into the run's atlas).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    print(artifacts_markdown(), end="")
