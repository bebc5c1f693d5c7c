"""Template stage: cleaning, decimation, UV atlas (no mirrored charts, gutters), adjacency,
texel map, embedding in the original surface, and the stage's store."""
import numpy as np
import pytest
import trimesh

from stex.atlas import border_gap, build_atlas, gutter_conflicts, texel_map, uv_charts, uv_flipped, uv_signed_area
from stex.mesh import clean_mesh, decimate, embed_vertices, face_adjacency, nonmanifold_vertices, transfer_vertices
from stex.stages.template import write_template


@pytest.fixture(scope="module")
def sphere():
    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int32)


@pytest.fixture(scope="module")
def sphere_atlas(sphere):
    V, F = sphere
    return build_atlas(V, F, resolution=256, gutter_px=3, return_info=True)


def test_clean_report_counts_every_defect():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0],   # 0-3 quad
                  [1, 0, 0],                                     # 4 duplicate of 1
                  [0.5, 0.5, 1], [0.5, 0.5, -1],                 # 5, 6 two extra fins on edge 1-2
                  [2, 0, 0], [3, 0, 0],                          # 7, 8 collinear with 1
                  [9, 9, 9]], float)                             # 9 unreferenced
    F = np.array([[0, 1, 2], [4, 3, 2],   # quad, second triangle uses the duplicate of 1
                  [1, 2, 5], [2, 1, 6],   # edge 1-2 now has 4 faces: non-manifold
                  [1, 7, 8],              # zero area (collinear)
                  [0, 0, 2],              # repeated vertex
                  [2, 0, 1]])             # same triangle as face 0
    V2, F2, rep = clean_mesh(V, F)
    assert rep["duplicate_vertices"] == 1
    assert rep["degenerate_faces"] == 2
    assert rep["duplicate_faces"] == 1
    # vertices 7, 8 (only in the degenerate face) and 9 are dropped
    assert rep["unreferenced_vertices"] == 3
    assert rep["faces_out"] == len(F2) == 4 and rep["vertices_out"] == len(V2) == 6
    assert rep["nonmanifold_edges"] == 1
    (a, b), = rep["nonmanifold_examples"]
    assert {tuple(V2[a]), tuple(V2[b])} == {(1.0, 0.0, 0.0), (0.0, 1.0, 0.0)}
    # face order kept, geometry kept
    np.testing.assert_array_equal(V2[F2[0]], V[[0, 1, 2]])
    pairs, edges, nm = face_adjacency(F2, return_nonmanifold=True)
    assert len(nm) == 1 and not any(set(e) == {a, b} for e in edges.tolist())


def test_nonmanifold_vertices_are_the_bowties():
    # two closed tetrahedra touching at one vertex: every edge manifold, that vertex two fans
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                  [-1, 0, 0], [0, -1, 0], [0, 0, -1]], float)
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3],
                  [0, 4, 5], [0, 6, 4], [0, 5, 6], [4, 6, 5]])
    np.testing.assert_array_equal(nonmanifold_vertices(F), [0])
    _, _, rep = clean_mesh(V, F)
    assert rep["nonmanifold_vertices"] == 1 and rep["nonmanifold_edges"] == 0
    # a closed sphere and an open patch (boundary vertices are one open fan): none
    s = trimesh.creation.icosphere(subdivisions=2)
    assert len(nonmanifold_vertices(s.faces)) == 0
    assert len(nonmanifold_vertices(s.faces[: len(s.faces) // 2])) == 0
    # the two tetrahedra's vertices apart again: none
    F2 = F.copy()
    F2[4:][F2[4:] == 0] = 7
    assert len(nonmanifold_vertices(F2)) == 0



def test_edge_defects_of_meshes_small_enough_to_count_by_hand():
    """A quad of two triangles has its 4 sides as boundary edges (the diagonal is shared by both).
    A fin on an edge of a closed tetrahedron makes that edge non-manifold and each of its two ends
    two fans (the tetrahedron's and the fin's), whichever face comes first: a non-manifold edge
    joins no faces."""
    from stex.mesh import nonmanifold_edges
    nm, boundary = nonmanifold_edges([[0, 1, 2], [0, 2, 3]])
    assert len(nm) == 0
    np.testing.assert_array_equal(boundary, [[0, 1], [0, 3], [1, 2], [2, 3]])
    tet = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    for F in ([[0, 1, 4]] + tet, tet + [[0, 1, 4]]):
        nm, boundary = nonmanifold_edges(F)
        np.testing.assert_array_equal(nm, [[0, 1]])
        np.testing.assert_array_equal(boundary, [[0, 4], [1, 4]])
        np.testing.assert_array_equal(nonmanifold_vertices(F), [0, 1])


def test_degenerate_faces_are_measured_against_the_bounding_box_diagonal_squared():
    """A face is degenerate below area_tol x (bounding-box diagonal)^2: here the diagonal^2 is
    0.06^2 + 0.08^2 = 0.01 m^2, so at the default 1e-12 the limit is 1e-14 m^2; a sliver of
    2e-14 m^2 stays, one of 5e-15 m^2 goes."""
    V = np.array([[0, 0, 1], [0.06, 0, 1], [0, 0.08, 1],                        # sets the box
                  [0.02, 0.01, 1], [0.04, 0.01, 1], [0.03, 0.01 + 2e-12, 1],   # 0.5 * 0.02 * 2e-12
                  [0.02, 0.03, 1], [0.04, 0.03, 1], [0.03, 0.03 + 5e-13, 1]])  # 0.5 * 0.02 * 5e-13
    F = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    V2, F2, rep = clean_mesh(V, F)
    assert rep["degenerate_faces"] == 1 and rep["faces_out"] == 2
    assert {tuple(p) for p in V2} == {tuple(p) for p in V[:6]}


def test_inconsistent_winding_edges_are_counted_once_per_edge():
    """One face of a closed icosphere turned round: each of its three edges joins two faces of
    opposite winding (3 edges, not 6 face sides), and the part, whose facing is then undefined,
    is left as it is."""
    s = trimesh.creation.icosphere(1)
    F = np.array(s.faces)
    F[0] = F[0, ::-1]
    _, F1, r = clean_mesh(s.vertices + [0, 0, 3.0], F)
    assert r["inconsistent_winding_edges"] == 3 and r["inverted_parts_flipped"] == 0
    np.testing.assert_array_equal(F1, F)


def test_decimate_hits_target_and_stays_closed():
    m = trimesh.creation.icosphere(subdivisions=5)  # 20,480 faces
    V, F = decimate(m.vertices, m.faces, 5000)
    assert abs(len(F) - 5000) <= 50
    out = trimesh.Trimesh(V, F, process=False)
    assert out.is_watertight and out.is_winding_consistent and out.volume > 0
    assert V.dtype == np.float64 and F.dtype == np.int32
    # already small enough: unchanged
    V2, F2 = decimate(V, F, 6000)
    np.testing.assert_array_equal(F2, F)
    np.testing.assert_array_equal(V2, V)


def test_atlas_fixes_xatlas_mirrored_charts(sphere, sphere_atlas):
    V, F = sphere
    tc, tf, info = sphere_atlas
    assert info["flipped_xatlas"] > 0, "xatlas' packer no longer mirrors charts; the fix is untested"
    assert info["flipped_charts"] > 0
    assert tc.dtype == np.float32 and tf.dtype == np.int32 and tf.shape == F.shape
    assert not uv_flipped(tc, tf).any()
    assert (uv_signed_area(tc, tf) < 0).all()  # front-facing with v down
    assert tc.min() >= 0 and tc.max() <= 1
    # every face keeps its 3-D corners: texcoords of a face map to distinct points
    assert info["charts"] == uv_charts(tf).max() + 1


def test_atlas_front_facing_is_not_mirrored(sphere, sphere_atlas):
    """Along a face, moving in +u goes the same way on the surface as seen from outside as
    moving right on the image (v down): the outward normal is d3/du x d3/dv ... sign check."""
    V, F = sphere
    tc, tf, _ = sphere_atlas
    p = V[F]
    t = tc[tf].astype(np.float64)
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    # tangent frame of the parameterisation: dP/du, dP/dv
    D = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], 1)       # (F, 2, 2) rows: edge in uv
    E = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], 1)       # (F, 2, 3)
    J = np.linalg.solve(D, E)                                      # rows: dP/du, dP/dv
    # image right (u) x image down (v) points *into* the screen for an unmirrored picture,
    # i.e. opposite to the outward normal (the viewer looks at the outside).
    assert (np.einsum("fi,fi->f", np.cross(J[:, 0], J[:, 1]), n) < 0).all()


def test_charts_keep_the_gutter(sphere_atlas):
    tc, tf, _ = sphere_atlas
    face_id, _ = texel_map(tc, tf, 256)
    chart = uv_charts(tf)
    assert (face_id >= 0).mean() > 0.3
    assert gutter_conflicts(face_id, chart, 3) == 0
    assert gutter_conflicts(face_id, chart, 2 * 3) == 0  # xatlas pads both charts
    # the check does detect charts that touch
    assert gutter_conflicts(face_id, chart, 40) > 0
    # and the border: every chart keeps the gutter to it (xatlas alone packs up to 0.5 texel from it)
    assert 3 <= border_gap(face_id) <= 3 + 2
    touching = face_id.copy()
    touching[-1, 100] = 0
    assert border_gap(touching) == 0



def test_gutter_and_border_checks_on_hand_made_texel_maps():
    """gutter_conflicts measures Chebyshev distance in texels: two one-texel charts 4 texels apart
    (3 empty texels between) both conflict at a 4-texel gutter, not at 3, whether side by side or
    diagonal; texels of one chart never conflict. border_gap looks at all four borders."""
    for other in ((5, 9), (9, 8)):
        fid = np.full((20, 20), -1, np.int32)
        fid[5, 5], fid[other] = 0, 1
        assert gutter_conflicts(fid, np.array([0, 1]), 4) == 2
        assert gutter_conflicts(fid, np.array([0, 1]), 3) == 0
        assert gutter_conflicts(fid, np.array([0, 0]), 10) == 0
    assert border_gap(fid) == 5  # rows 5..9, columns 5..8 of 0..19
    for (r, c), gap in [((19, 7), 0), ((7, 19), 0), ((0, 7), 0), ((7, 0), 0), ((7, 17), 2), ((16, 7), 3)]:
        fid = np.full((20, 20), -1, np.int32)
        fid[r, c] = 0
        assert border_gap(fid) == gap, (r, c)


def test_face_adjacency_on_icosphere(sphere):
    V, F = sphere
    pairs, edges = face_adjacency(F)
    assert pairs.dtype == np.int32 and edges.dtype == np.int32
    assert len(pairs) == 3 * len(F) // 2
    np.testing.assert_array_equal(np.bincount(pairs.ravel(), minlength=len(F)), 3)
    assert (pairs[:, 0] < pairs[:, 1]).all() and (edges[:, 0] < edges[:, 1]).all()
    for k in (0, 1):
        fa = F[pairs[:, k]]
        assert ((fa == edges[:, :1]).any(1) & (fa == edges[:, 1:]).any(1)).all()
    assert len(np.unique(edges, axis=0)) == len(edges)


def test_texel_map_barycentrics_reproduce_texcoords(sphere_atlas):
    tc, tf, _ = sphere_atlas
    size = 256
    face_id, bary = texel_map(tc, tf, size)
    assert face_id.dtype == np.int32 and bary.dtype == np.float32
    r, c = np.nonzero(face_id >= 0)
    uv = np.einsum("nk,nkd->nd", bary[r, c].astype(np.float64), tc[tf[face_id[r, c]]].astype(np.float64))
    np.testing.assert_allclose(uv[:, 0], (c + 0.5) / size, atol=1e-5)
    np.testing.assert_allclose(uv[:, 1], (r + 0.5) / size, atol=1e-5)
    assert (bary[r, c] >= -1e-5).all()
    assert (bary[face_id < 0] == 0).all()


def test_transfer_vertices_rest_pose_and_rigid_motion():
    m = trimesh.creation.icosphere(subdivisions=4)
    V0 = np.asarray(m.vertices) * [0.3, 0.2, 0.25] + [0.0, 0.1, 1.2]
    F0 = np.asarray(m.faces, np.int32)
    V, F = decimate(V0, F0, 600)
    face, bary, closest, dist = embed_vertices(V, V0, F0)
    assert face.dtype == np.int32 and bary.dtype == np.float32 and face.shape == (len(V),)
    assert dist.max() < 0.01
    np.testing.assert_allclose(transfer_vertices(V0, F0, face, bary), closest, atol=1e-6)
    R = trimesh.transformations.rotation_matrix(0.7, [0.2, 1.0, -0.3])[:3, :3]
    t = np.array([0.05, -0.2, 0.3])
    moved = V0 @ R.T + t
    np.testing.assert_allclose(transfer_vertices(moved, F0, face, bary), closest @ R.T + t, atol=1e-6)
    # a batch of frames at once
    both = transfer_vertices(np.stack([V0, moved]), F0, face, bary)
    assert both.shape == (2, len(V), 3)
    np.testing.assert_allclose(both[1], closest @ R.T + t, atol=1e-6)


def _tiny_scene(tmp_path):
    from stex.config import load_config
    from stex.stages.ingest import write_scene
    cfg = load_config(overrides={"source": {"kind": "synthetic", "synthetic": {
        "n_frames": 2, "procedural": {"n_around": 32, "n_rings": 16}}}})
    path = tmp_path / "scene.zarr"
    write_scene(cfg["source"], 4, path)
    return cfg, path


def test_write_template_on_a_synthetic_scene(tmp_path):
    from stex.io import open_store
    cfg, scene_path = _tiny_scene(tmp_path)
    params = dict(cfg["template"], atlas_size=256, target_faces=500, min_faces=0)
    out = tmp_path / "template.zarr"
    write_template(scene_path, params, out)
    g = open_store(out, "template")
    scene = open_store(scene_path, "scene")
    V, F = g["vertices"][...], g["faces"][...]
    tc, tf = g["texcoords"][...], g["texcoord_faces"][...]
    assert abs(len(F) - 500) <= 5 and g.attrs["decimated"]
    assert not uv_flipped(tc, tf).any() and tc.min() >= 0 and tc.max() <= 1
    assert g["texel/face_id"].shape == (256, 256) and g["texel/bary"].shape == (256, 256, 3)
    assert g.attrs["atlas_size"] == 256 and g.attrs["gutter_conflicts"] == 0 and g.attrs["border_gap_px"] >= g.attrs["gutter_px"]
    assert g.attrs["counts"]["faces"] == len(F) and g.attrs["params"]["target_faces"] == 500
    assert g.attrs["clean_report"]["faces_in"] == scene["template/faces"].shape[0]
    pairs = g["adjacency/pairs"][...]
    assert len(pairs) > len(F)
    # the per-frame true meshes carry over to the decimated topology
    emb_f, emb_b = g["embedding/face"][...], g["embedding/bary"][...]
    orig_faces = scene["template/faces"][...]
    rest = transfer_vertices(scene["template/vertices"][...], orig_faces, emb_f, emb_b)
    np.testing.assert_allclose(rest, V, atol=1e-5)
    frame1 = transfer_vertices(scene["truth/vertices"][1], orig_faces, emb_f, emb_b)
    assert frame1.shape == V.shape and np.isfinite(frame1).all()

    from stex.stages.template import preview_template
    png = tmp_path / "previews" / "template_atlas.png"
    preview_template(out, png, size=256)
    assert png.stat().st_size > 1000

    # template.uv: mesh: the source's own layout (the procedural body's), face for face
    write_template(scene_path, dict(params, uv="mesh", decimate=False, min_faces=0), tmp_path / "own.zarr")
    own = open_store(tmp_path / "own.zarr", "template")
    assert own.attrs["uv"] == "mesh" and own.attrs["atlas"]["source"] == "mesh"
    np.testing.assert_allclose(own["texcoords"][...][own["texcoord_faces"][...]],
                               scene["template/texcoords"][...][scene["template/texcoord_faces"][...]], atol=1e-7)


def test_write_template_without_template_mesh(tmp_path):
    from stex.io import create_store
    scene = tmp_path / "scene.zarr"
    with create_store(scene, "scene", attrs={"has_template": False, "source": {"kind": "mkv"}}):
        pass
    with pytest.raises(ValueError, match=r"no template mesh; set source\.mkv\.template, or template\.from_depth"):
        write_template(scene, {"decimate": True, "target_faces": 100, "min_faces": 0, "atlas_size": 64, "gutter_px": 1},
                       tmp_path / "template.zarr")
    assert not (tmp_path / "template.zarr").exists()


def test_template_from_the_first_frames_depth(tmp_path):
    """template.from_depth on the tiny synthetic scene: the template lies on the true surface
    (within the depth noise), faces the camera, and covers what the camera sees of the object."""
    from scipy import ndimage

    from conftest import tiny_scene_config
    from stex.camera import Calibration
    from stex.stages.ingest import write_frames_block, write_scene
    from stex.io import open_store
    from stex.stages.masks import write_masks_block
    from stex.render import face_normals, rasterize

    cfg = tiny_scene_config()
    write_scene(cfg["source"], 4, tmp_path / "scene.zarr")
    write_frames_block(cfg["source"], 0, 4, tmp_path / "f.zarr", tmp_path / "t.zarr")
    write_masks_block(tmp_path / "scene.zarr", tmp_path / "f.zarr", cfg["masks"], tmp_path / "m.zarr")
    params = dict(cfg["template"], atlas_size=256, from_depth=True, from_depth_stride_px=1)
    with pytest.raises(ValueError, match="needs the first frame block"):
        write_template(tmp_path / "scene.zarr", params, tmp_path / "x.zarr")
    with pytest.raises(ValueError, match="uv: mesh keeps the source template's own UV layout"):
        write_template(tmp_path / "scene.zarr", dict(params, uv="mesh"), tmp_path / "x.zarr", tmp_path / "f.zarr",
                       tmp_path / "m.zarr")
    assert not (tmp_path / "x.zarr").exists()
    write_template(tmp_path / "scene.zarr", params, tmp_path / "template.zarr", tmp_path / "f.zarr", tmp_path / "m.zarr")
    g = open_store(tmp_path / "template.zarr", "template")
    assert g.attrs["origin"] == "depth of frame 0" and not uv_flipped(g["texcoords"][...], g["texcoord_faces"][...]).any()
    V, F = g["vertices"][...].astype(np.float64), g["faces"][...]
    scene = open_store(tmp_path / "scene.zarr", "scene")
    truth = trimesh.Trimesh(scene["truth/vertices"][0], scene["template/faces"][...], process=False)
    _, dist, _ = trimesh.proximity.closest_point(truth, V)
    assert np.median(dist) < 0.003 and np.percentile(dist, 95) < 0.01
    centres = V[F].mean(1)
    assert (np.einsum("ij,ij->i", face_normals(V, F), -centres) > 0).mean() > 0.99  # towards the camera
    # the background strip beside the object that lands inside the colour mask is left out
    assert dist.max() < 0.02
    cal = Calibration.from_dict(scene.attrs["calibration"])
    silhouette = rasterize(truth.vertices, truth.faces, cal.depth.K, *cal.depth.size).face_id >= 0
    covered = rasterize(V, F, cal.depth.K, *cal.depth.size).face_id >= 0
    # the template's vertices sit on depth pixel centres, so its outline runs through pixel
    # centres: compared inside the silhouette's outer pixel
    inner = ndimage.binary_erosion(silhouette)
    assert covered[inner].mean() > 0.9 and silhouette[covered].mean() > 0.98, (covered[inner].mean(), silhouette[covered].mean())
    # the source's per-frame meshes refer to its own template: 'given' tracking refuses this one
    from stex.stages.tracking import write_tracking
    with pytest.raises(ValueError, match="template.from_depth.*use tracking.mode track"):
        write_tracking(tmp_path / "scene.zarr", tmp_path / "template.zarr", [tmp_path / "f.zarr"],
                       [tmp_path / "m.zarr"], dict(cfg["tracking"], mode="given"), tmp_path / "tracking.zarr")
    assert not (tmp_path / "tracking.zarr").exists()



def test_a_template_from_depth_leaves_depth_jumps_open():
    """template_from_depth makes no triangle across a depth jump of max_jump_m (a nose in front of
    a chest): a 4 x 4 depth image at 1 m on its left half and 1.5 m on its right has 3 x 3 grid
    squares, of which the 3 across the step are left out: 12 triangles, each on one side. A step
    of 1 cm (under 2 cm) is bridged: all 18."""
    from stex.template import template_from_depth
    K = np.array([[100.0, 0, 1.5], [0, 100.0, 1.5], [0, 0, 1]])
    d = np.ones((4, 4))
    d[:, 2:] = 1.5
    V, F = template_from_depth(d, K, stride=1, max_jump_m=0.02)
    assert len(F) == 12 and len(V) == 16
    assert (np.ptp(V[F][:, :, 2], axis=1) == 0).all()
    d[:, 2:] = 1.01
    assert len(template_from_depth(d, K, stride=1, max_jump_m=0.02)[1]) == 18


def test_low_poly_meshes_are_subdivided_without_changing_shape():
    import trimesh as _tm

    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    from stex.mesh import subdivide_midpoint, transfer_vertices
    m = _tm.creation.icosphere(1)  # 80 faces
    V, F = subdivide_midpoint(m.vertices, m.faces)
    t = _tm.Trimesh(V, F, process=False)
    assert len(F) == 320 and t.is_watertight and t.is_winding_consistent and t.volume > 0
    assert abs(t.area - m.area) < 1e-12  # midpoints lie on the old faces
    out = prepare_template(Mesh(np.asarray(m.vertices), np.asarray(m.faces)),
                           {"target_faces": 20000, "min_faces": 1000, "decimate": True, "atlas_size": 256, "gutter_px": 2})
    assert len(out["faces"]) == 320 and out["attrs"]["subdivided"] == 1  # 1280 would exceed 1000
    # a decimation target below min_faces is refused: a mesh just over the target would end with
    # fewer faces than one just under it (target 1000, min_faces 4000: 1020 -> 1000, 980 -> 3920)
    with pytest.raises(ValueError, match=r"target_faces 1000, below template\.min_faces 4000"):
        prepare_template(Mesh(np.asarray(m.vertices), np.asarray(m.faces)), {"target_faces": 1000, "atlas_size": 256})
    # the embedding carries the original mesh's motion to the subdivided one exactly
    moved = np.asarray(m.vertices) * 1.5 + 0.1
    assert np.allclose(transfer_vertices(moved, m.faces, out["embedding/face"], out["embedding/bary"]),
                       out["vertices"] * 1.5 + 0.1, atol=1e-6)


def test_a_lone_triangle_the_repack_mirrors_is_mirrored_back(monkeypatch):
    """xatlas' repack can return a triangle that pass 1 flattened to a sliver as a chart of its own,
    mirrored (seen on a template from a real depth image): build_atlas mirrors it back inside its
    own box. Here the repack is made to mirror one of two separate triangles."""
    import stex.atlas as tm

    V = np.array([[0, 0, 1], [0.01, 0, 1], [0, 0.01, 1], [0.05, 0, 1], [0.06, 0, 1], [0.05, 0.01, 1.0]])
    F = np.array([[0, 2, 1], [3, 5, 4]])
    run = tm.call_in_child

    def mirroring(*args):  # xatlas still runs in its child; its best repack is mirrored here
        lay = run(*args)
        vmap, idx, uv, util = lay["best"]
        uv = uv.copy()
        c = idx[0]
        uv[c, 0] = uv[c, 0].min() + uv[c, 0].max() - uv[c, 0]
        lay["best"] = vmap, idx, uv, util
        return lay
    monkeypatch.setattr(tm, "call_in_child", mirroring)
    tc, tf, info = build_atlas(V, F, 64, 2, return_info=True)
    assert info["repack_mirrored_charts"] == 1 and not uv_flipped(tc, tf).any()


def test_small_charts_the_repack_mirrors_whole_are_mirrored_back(monkeypatch):
    """A noisy 500k-face scan's pole fans came back from the repack as wholly mirrored charts of
    2-4 faces ("38 UV triangles still mirrored"): each is mirrored back inside its own box, and
    its box, hence the packing and the gutters, stays where it was."""
    import stex.atlas as tm

    # two separate charts: a quad of 2 faces, and a triangle
    V = np.array([[0, 0, 1], [0.01, 0, 1], [0.01, 0.01, 1], [0, 0.01, 1], [0.05, 0, 1], [0.06, 0, 1], [0.05, 0.01, 1.0]])
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5]])
    run = tm.call_in_child
    boxes = {}

    def mirroring(*args):  # xatlas still runs in its child; its best repack is mirrored here
        lay = run(*args)
        vmap, idx, uv, util = lay["best"]
        uv = uv.copy()
        c = np.unique(idx[:2])  # the quad's corners
        boxes["before"] = (uv[c].min(0), uv[c].max(0))
        uv[c, 0] = uv[c, 0].min() + uv[c, 0].max() - uv[c, 0]
        lay["best"] = vmap, idx, uv, util
        return lay
    monkeypatch.setattr(tm, "call_in_child", mirroring)
    tc, tf, info = build_atlas(V, F, 64, 2, return_info=True)
    assert info["repack_mirrored_charts"] == 1 and not uv_flipped(tc, tf).any()
    quad = np.unique(tf[:2])
    lo, hi = ((x * (64 - 2 * 2) + 2) / 64 for x in boxes["before"])  # the packing's square in the atlas
    np.testing.assert_allclose(tc[quad, 0].min(), lo[0], atol=1e-6)
    np.testing.assert_allclose(tc[quad, 0].max(), hi[0], atol=1e-6)


def test_a_small_object_gets_an_atlas():
    """xatlas skips faces below ~1.2e-7 in area, so a 5 mm sphere of 5k faces (6e-8 m² each) had
    no chart at all (ZeroDivisionError in build_atlas); it is scaled to where xatlas works, and
    the texel density is still per metre."""
    import trimesh

    s = trimesh.creation.icosphere(4, radius=0.005)
    tc, tf, info = build_atlas(s.vertices + [0, 0, 0.5], s.faces, 256, 2, return_info=True)
    assert info["working_scale"] > 1 and info["charts"] < 50 and not uv_flipped(tc, tf).any()
    assert 0 <= tc.min() and tc.max() <= 1
    face_id, _ = texel_map(tc, tf, 256)
    assert len(np.unique(face_id[face_id >= 0])) > 0.95 * len(tf)
    # the same sphere at 1 m radius: the same layout density per unit of surface, in texels per metre
    _, _, big = build_atlas(s.vertices * 200 + [0, 0, 0.5], s.faces, 256, 2, return_info=True)
    assert big["working_scale"] == 1.0
    assert info["texels_per_unit"] == pytest.approx(200 * big["texels_per_unit"], rel=0.1)



def test_the_working_scale_brings_the_median_face_area_to_1e_4():
    """A mesh whose median face area is under 1e-6 m^2 is scaled by the factor k that makes it
    1e-4 (areas grow with k^2), measured here by trimesh on the scaled mesh; a mesh of larger
    faces is not scaled."""
    from stex.mesh import working_scale
    s = trimesh.creation.icosphere(3, radius=0.002)  # 1280 faces of ~4e-8 m^2
    k = working_scale(s.vertices, s.faces)
    area = trimesh.Trimesh(s.vertices * k, s.faces, process=False).area_faces
    assert np.median(area) == pytest.approx(1e-4, rel=1e-9)
    assert working_scale(s.vertices * 10, s.faces) == 1.0  # ~4e-6 m^2


def test_faces_turned_inwards_are_turned_round_and_mixed_winding_is_counted(caplog):
    import trimesh

    s = trimesh.creation.icosphere(3)
    s.vertices += [0, 0, 1.0]
    V, F, r = clean_mesh(s.vertices, s.faces)
    assert np.array_equal(F, s.faces) and r["inverted_parts_flipped"] == 0 and r["inconsistent_winding_edges"] == 0
    with caplog.at_level("WARNING", logger="stex.template"):
        V, F, r = clean_mesh(s.vertices, s.faces[:, ::-1])  # a closed mesh facing inwards
    assert r["inverted_parts_flipped"] == 1 and trimesh.Trimesh(V, F).volume > 0
    assert "faced inwards" in caplog.text
    mixed = s.faces.copy()
    mixed[::2] = mixed[::2, ::-1]
    V, F, r = clean_mesh(s.vertices, mixed)
    assert r["inconsistent_winding_edges"] > 0 and r["inverted_parts_flipped"] == 0 and np.array_equal(F, mixed)
    # an open surface has no inside: it is not turned round by volume; this one (the far half of
    # the sphere, which passes through the camera centre, seen from inside) already faces the camera
    cap = s.faces[s.triangles_center[:, 2] > 1.0][:, ::-1]
    V, F, r = clean_mesh(s.vertices, cap)
    assert r["inverted_parts_flipped"] == 0 and r["open_parts_flipped"] == 0
    assert np.array_equal(V[F], s.vertices[cap])


def _facing_camera(V, F):
    """(F,) bool: faces whose normal points to the side of their plane the camera centre (the
    origin) is on."""
    V = np.asarray(V, np.float64)
    v0 = V[F[:, 0]]
    return np.einsum("ij,ij->i", np.cross(V[F[:, 1]] - v0, V[F[:, 2]] - v0), -v0) > 0


def _grid(n=12, centre=(0.0, 0.0, 1.0), side=0.4):
    """An open, bumpy n x n height field at ``centre`` (metres), wound clockwise seen from the
    origin: every normal points away from a camera there (+z)."""
    x, y = np.meshgrid(np.linspace(-side / 2, side / 2, n), np.linspace(-side / 2, side / 2, n))
    z = 0.02 * np.sin(6 * x / side) * np.cos(5 * y / side)
    V = np.stack([x, y, z], -1).reshape(-1, 3) + centre
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    return V, F.astype(np.int32)


def _join(*meshes):
    Vs, Fs, offset = [], [], 0
    for V, F in meshes:
        Vs.append(np.asarray(V, np.float64))
        Fs.append(np.asarray(F, np.int64) + offset)
        offset += len(V)
    return np.concatenate(Vs), np.concatenate(Fs).astype(np.int32)


def test_open_parts_are_turned_to_face_the_camera(caplog):
    """A single-view scan (an open surface) wound clockwise seen from the depth camera has every
    normal pointing away from it, so every face it sees would be a back face: such parts are
    turned round; parts facing it, and parts it does not see, are left as they are."""
    from stex.camera import Intrinsics

    V, F = _grid()
    assert not _facing_camera(V, F).any()
    with caplog.at_level("WARNING", logger="stex.template"):
        V1, F1, r = clean_mesh(V, F)
    assert r["open_parts_flipped"] == 1 and r["inverted_parts_flipped"] == 0 and _facing_camera(V1, F1).all()
    assert np.array_equal(V1, V) and np.array_equal(F1, F[:, [0, 2, 1]])
    assert "1 open parts of the mesh faced away from the camera" in caplog.text
    V1, F1, r = clean_mesh(V, F[:, ::-1])  # already facing it
    assert r["open_parts_flipped"] == 0 and np.array_equal(F1, F[:, ::-1])
    # the near half of a sphere wound inwards: curved, its rim seen edge-on (faces there face away
    # whichever way it is wound), still turned round as a whole
    s = trimesh.creation.icosphere(3, radius=0.2)
    near = s.faces[s.triangles_center[:, 2] < 0][:, ::-1]
    V1, F1, r = clean_mesh(s.vertices + [0, 0, 1.0], near)
    assert r["open_parts_flipped"] == 1 and 0.8 < _facing_camera(V1, F1).mean() < 1
    # unseen parts stay as they are: hidden behind a larger surface, or behind the camera
    front = _grid(16, (0, 0, 1.0), 1.0)
    front = (front[0], front[1][:, ::-1])
    for hidden in (_grid(8, (0, 0, 2.0), 0.2), _grid(8, (0, 0, -1.0), 0.2)):
        V1, F1, r = clean_mesh(*_join(front, hidden))
        assert r["open_parts_flipped"] == 0 and np.array_equal(F1, _join(front, hidden)[1])
    # the depth camera given: a part outside its view is not seen, so not turned round (the default
    # camera frames every open part)
    camera = Intrinsics(np.array([[500.0, 0, 319.5], [0, 500.0, 287.5], [0, 0, 1]]), 640, 576)
    V2, F2 = _join(_grid(), _grid(centre=(3.0, 0, 1.0)))
    _, F3, r = clean_mesh(V2, F2, camera=camera)
    assert r["open_parts_flipped"] == 1 and _facing_camera(V2, F3)[: len(F)].all() and not _facing_camera(V2, F3)[len(F):].any()
    _, F3, r = clean_mesh(V2, F2)
    assert r["open_parts_flipped"] == 2 and _facing_camera(V2, F3).all()


def test_the_template_stage_turns_an_open_scan_towards_the_scenes_depth_camera(tmp_path):
    """write_template hands the scene's depth camera to the cleaning: of two clockwise open
    surfaces, the one in its view is turned to face it, the one outside it is not; the report
    says how many."""
    from stex.camera import Calibration, Intrinsics
    from stex.io import create_store, open_store

    camera = Intrinsics(np.array([[500.0, 0, 319.5], [0, 500.0, 287.5], [0, 0, 1]]), 640, 576)
    V, F = _join(_grid(), _grid(centre=(3.0, 0, 1.0)))
    scene = tmp_path / "scene.zarr"
    with create_store(scene, "scene", attrs={"has_template": True, "source": {"kind": "folder"},
                                             "calibration": Calibration(camera, camera).to_dict()}) as store:
        store.write("template/vertices", V.astype(np.float32))
        store.write("template/faces", F)
    write_template(scene, dict(decimate=False, min_faces=0, atlas_size=128, gutter_px=1), tmp_path / "template.zarr")
    g = open_store(tmp_path / "template.zarr", "template")
    assert g.attrs["clean_report"]["open_parts_flipped"] == 1 and g.attrs["clean_report"]["inverted_parts_flipped"] == 0
    Vt, Ft = g["vertices"][...].astype(np.float64), g["faces"][...]
    seen = Vt[Ft].mean(1)[:, 0] < 1.0
    assert _facing_camera(Vt, Ft)[seen].all() and not _facing_camera(Vt, Ft)[~seen].any()


def test_points_inside_a_closed_mesh_by_ray_parity():
    """points_inside against exact answers: a box, and a sphere's polygon (points off its surface
    by more than the polygon's sag), whatever the winding; a grid-like mesh (the box) does not
    catch the rays on its edges."""
    from stex.mesh import points_inside

    rng = np.random.default_rng(0)
    box = trimesh.creation.box((0.2, 0.3, 0.4))
    p = rng.uniform(-0.3, 0.3, (5000, 3))
    p[:100] = np.round(p[:100], 1)  # on the box's axis-aligned planes and edge lines' extensions
    inside = (np.abs(p) < [0.1, 0.15, 0.2]).all(1)
    clear = (np.abs(np.abs(p) - [0.1, 0.15, 0.2]) > 1e-9).all(1)
    assert (points_inside(box.vertices, box.faces, p) == inside)[clear].all() and clear.sum() > 4900
    assert (points_inside(box.vertices, box.faces[:, ::-1], p) == inside)[clear].all()
    s = trimesh.creation.icosphere(4, radius=0.3)
    r = np.linalg.norm(p, axis=1)
    sure = np.abs(r - 0.3) > 0.003  # the polygon lies within 0.4 mm inside the sphere
    assert (points_inside(s.vertices, s.faces, p) == (r < 0.3))[sure].all()
    assert not points_inside(s.vertices, s.faces, [[5.0, 0, 0], [0, 0, -5.0]]).any()


def test_a_cavity_wall_keeps_facing_into_its_cavity(caplog):
    """A closed part inside an odd number of other closed parts is the wall of a cavity (a hollow
    shell's inner surface) and faces into it (negative signed volume); inside an even number it
    faces out. Only parts wound the other way are turned round."""
    def shell(radius, sign, centre=(0.0, 0.0, 0.0), subdivisions=3):
        s = trimesh.creation.icosphere(subdivisions, radius=radius)
        return s.vertices + centre + [0, 0, 1.0], s.faces[:, ::sign]

    def volumes(V, F, sizes):
        ends = np.cumsum(sizes)
        return [trimesh.Trimesh(V, F[e - n:e], process=False).volume for n, e in zip(sizes, ends)]

    n_outer, n_inner = 1280, 320  # icosphere 3, 2
    for signs, flipped in [((1, -1), 0), ((1, 1), 1), ((-1, 1), 2), ((-1, -1), 1)]:
        V, F = _join(shell(0.3, signs[0]), shell(0.2, signs[1], subdivisions=2))
        with caplog.at_level("WARNING", logger="stex.template"):
            V1, F1, r = clean_mesh(V, F)
        outer, inner = volumes(V1, F1, (n_outer, n_inner))
        assert r["inverted_parts_flipped"] == flipped and outer > 0 and inner < 0, (signs, r, outer, inner)
    assert "faced inwards, into the solid" in caplog.text
    # a ball in the cavity lies inside two closed parts: it faces out
    for sign, flipped in [(1, 0), (-1, 1)]:
        V, F = _join(shell(0.3, 1), shell(0.2, -1, subdivisions=2), shell(0.1, sign, subdivisions=2))
        V1, F1, r = clean_mesh(V, F)
        assert r["inverted_parts_flipped"] == flipped
        assert [np.sign(v) for v in volumes(V1, F1, (n_outer, n_inner, n_inner))] == [1, -1, 1]
    # a part poking out of another (an eyeball set into a closed head) by 1.2 cm along a diagonal,
    # its bounding box inside the other's and 92 % of its vertices (its first too): not inside it,
    # it faces out
    head, eye = shell(0.3, 1), shell(0.1, 1, centre=(0.15, 0.15, 0.0), subdivisions=2)
    V, F = _join(head, eye)
    inside = trimesh.Trimesh(*head, process=False).contains(eye[0])
    assert inside[0] and 0.9 < inside.mean() < 1
    V1, F1, r = clean_mesh(V, F)
    assert r["inverted_parts_flipped"] == 0 and all(v > 0 for v in volumes(V1, F1, (n_outer, n_inner)))


def test_a_millimetre_object_is_decimated_onto_its_surface():
    """pymeshlab's quadric decimation has absolute thresholds too: a 1 mm sphere of 82k faces came
    out with vertices up to 0.7 radii off its surface (and the embedding then took 28 s)."""
    s = trimesh.creation.icosphere(6, radius=0.001)
    V, F = decimate(s.vertices, s.faces, 20000)
    assert len(F) <= 20000
    off = np.abs(np.linalg.norm(V, axis=1) - 0.001)
    assert off.max() < 0.02 * 0.001


def test_floating_fragments_are_kept_or_dropped_on_request():
    """A scan's floating fragments (here 5 small boxes beside a sphere) are kept by default, each
    a part of its own in the report; template.min_part_faces drops them, and the template then
    is the sphere alone."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template

    s = trimesh.creation.icosphere(3)
    boxes = [trimesh.creation.box((0.01, 0.01, 0.01)).apply_translation([1.3 + 0.05 * i, 0, 0]) for i in range(5)]  # beside the unit sphere, not in it
    m = trimesh.util.concatenate([s.copy().apply_translation([0, 0, 1.0])] +
                                 [b.apply_translation([0, 0, 1.0]) for b in boxes])
    params = dict(decimate=False, target_faces=20000, min_faces=0, atlas_size=256, gutter_px=2)
    kept = prepare_template(Mesh(np.asarray(m.vertices), np.asarray(m.faces)), params)
    assert kept["attrs"]["clean_report"]["parts"] == 6 and kept["attrs"]["clean_report"]["dropped_parts"] == 0
    assert len(kept["faces"]) == len(m.faces)
    dropped = prepare_template(Mesh(np.asarray(m.vertices), np.asarray(m.faces)), dict(params, min_part_faces=13))
    rep = dropped["attrs"]["clean_report"]
    assert rep["dropped_parts"] == 5 and rep["dropped_faces"] == 60 and len(dropped["faces"]) == len(s.faces)
    assert np.ptp(dropped["vertices"][:, 0]) < 2.1  # the sphere's width: no box left
    with pytest.raises(ValueError, match="every part of the mesh has fewer than 5000 faces"):
        prepare_template(Mesh(np.asarray(m.vertices), np.asarray(m.faces)), dict(params, min_part_faces=5000))


def _surface_at_texels(V, F, texcoords, texcoord_faces, size):
    """(size, size, 3) surface point each covered texel shows, and the (size, size) coverage."""
    face_id, bary = texel_map(texcoords, texcoord_faces, size)
    hit = face_id >= 0
    p = np.zeros((size, size, 3))
    p[hit] = np.einsum("nk,nkd->nd", bary[hit].astype(np.float64), np.asarray(V, np.float64)[np.asarray(F)[face_id[hit]]])
    return p, hit


def test_the_meshs_own_uv_layout_is_kept_through_cleaning_and_subdivision(sphere, sphere_atlas):
    """template.uv: mesh keeps the layout: every texel shows the same surface point as in the
    input, although the mesh was cleaned (a duplicated vertex, a degenerate face), turned round
    (it came wound inwards) and split at its edge midpoints."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    V, F = sphere
    tc, tf, _ = sphere_atlas
    # inward winding (the cleaning turns the closed sphere round, corners 1 and 2 swapped), a
    # duplicate of vertex 0 used by face 0, and a degenerate face with its own texcoords
    Vin = np.vstack([V, V[:1]])
    Fin = F[:, [0, 2, 1]].copy()
    Fin[0][Fin[0] == 0] = len(V)
    Fin = np.vstack([Fin, [[1, 1, 2]]])
    tfin = np.vstack([tf[:, [0, 2, 1]], [[0, 1, 2]]])
    mesh = Mesh(Vin, Fin, np.asarray(tc, np.float64), tfin)
    params = dict(target_faces=20000, decimate=True, min_faces=4 * len(F), atlas_size=256, gutter_px=3, uv="mesh")
    out = prepare_template(mesh, params)
    a = out["attrs"]
    assert a["uv"] == "mesh" and a["subdivided"] == 1 and a["clean_report"]["inverted_parts_flipped"] == 1
    assert a["clean_report"]["degenerate_faces"] == 1 and a["clean_report"]["duplicate_vertices"] == 1
    assert len(out["faces"]) == 4 * len(F) and a["atlas"]["overlap_texels"] == 0
    assert a["atlas"]["mirrored_faces"] == 0 and a["flipped_fixed"] == 0  # the xatlas layout was front-facing
    p_in, hit_in = _surface_at_texels(V, F, tc, tf, 256)
    p_out, hit_out = _surface_at_texels(out["vertices"], out["faces"], out["texcoords"], out["texcoord_faces"], 256)
    assert (hit_in == hit_out).mean() > 0.9999 and hit_out.sum() == a["counts"]["covered_texels"]
    both = hit_in & hit_out
    # the subdivided vertices were put back on the (faceted) input surface: the same points
    assert np.abs(p_in[both] - p_out[both]).max() < 1e-5
    np.testing.assert_array_equal(out["texel/face_id"] >= 0, hit_out)


def test_decimation_keeps_the_meshs_own_uv_layout(sphere, sphere_atlas):
    """Decimated with template.uv: mesh (MeshLab's texture-aware collapse), each texel still shows
    about the surface point it showed before: the layout follows the surface."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    V, F = sphere
    tc, tf, _ = sphere_atlas
    params = dict(target_faces=640, decimate=True, min_faces=0, atlas_size=256, gutter_px=3, uv="mesh")
    out = prepare_template(Mesh(V, F, np.asarray(tc, np.float64), tf), params)
    assert out["attrs"]["decimated"] and abs(len(out["faces"]) - 640) <= 4
    p_in, hit_in = _surface_at_texels(V, F, tc, tf, 256)
    p_out, hit_out = _surface_at_texels(out["vertices"], out["faces"], out["texcoords"], out["texcoord_faces"], 256)
    both = hit_in & hit_out
    assert both.sum() > 0.99 * hit_in.sum()
    # unit sphere, 1280 -> 640 faces, the vertices then put back on the input surface (measured:
    # every texel still covered, median 0.006, 99th percentile 0.017; with MeshLab's default
    # texture weight 1: 93 %, 0.008, 0.08; a layout not carried along is ~1 off)
    d = np.linalg.norm(p_in[both] - p_out[both], axis=1)
    assert np.median(d) < 0.01 and np.percentile(d, 99) < 0.04, (np.median(d), np.percentile(d, 99))


@pytest.mark.parametrize("case, match", [
    ("none", "has no texture coordinates"),
    ("outside", r"2 faces have texture coordinates outside \[0, 1\]"),
    ("overlap", r"UV triangles overlap at \d+ texels .*u 0\.\d+, v 0\.\d+"),
])
def test_layouts_that_cannot_hold_a_texture_per_face_are_refused(case, match):
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], float)
    F = np.array([[0, 1, 2], [1, 3, 2], [0, 4, 1]])
    tc = np.array([[0.1, 0.1], [0.4, 0.1], [0.1, 0.4], [0.6, 0.6], [0.9, 0.6], [0.6, 0.9]])
    tf = {"none": None, "outside": np.array([[0, 1, 2], [1, 3, 2], [3, 4, 5]]),
          "overlap": np.array([[0, 1, 2], [0, 1, 2], [3, 4, 5]])}[case]
    if case == "outside":
        tc[3] = [1.2, 0.6]
    mesh = Mesh(V, F, None if tf is None else tc, tf)
    with pytest.raises(ValueError, match=match):
        prepare_template(mesh, dict(target_faces=100, decimate=True, min_faces=0, atlas_size=64, gutter_px=1, uv="mesh"))
    # the default makes its own atlas for the same mesh
    out = prepare_template(mesh, dict(target_faces=100, decimate=True, min_faces=0, atlas_size=64, gutter_px=1))
    assert out["attrs"]["uv"] == "xatlas" and len(out["faces"]) == 3


def test_an_atlas_too_small_for_the_mesh_is_warned_about_and_named(caplog):
    """With atlas_size too small for the mesh most faces hold no texel centre: a warning names the
    count and template.atlas_size / gutter_px (at a fitting size: none, and no warning); when the
    charts cannot be packed at all the error names the settings and the chart count. The attr
    utilization is the texel map's covered fraction, not xatlas' own (higher) figure."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    s = trimesh.creation.icosphere(3, 0.1)
    mesh = Mesh(np.asarray(s.vertices) + [0, 0, 1], np.asarray(s.faces))
    params = dict(decimate=False, min_faces=0, gutter_px=2)
    with caplog.at_level("WARNING", logger="stex.template"):
        small = prepare_template(mesh, dict(params, atlas_size=64))
    a = small["attrs"]
    missing = len(s.faces) - len(np.unique(small["texel/face_id"][small["texel/face_id"] >= 0]))
    assert a["atlas"]["faces_without_texel"] == missing > 0.01 * len(s.faces)
    assert f"{missing} of the {len(s.faces)} faces" in caplog.text
    assert "raise template.atlas_size (or lower template.gutter_px, now 2)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="stex.template"):
        big = prepare_template(mesh, dict(params, atlas_size=512))
    assert big["attrs"]["atlas"]["faces_without_texel"] == 0 and "texel centre" not in caplog.text
    for out in (small, big):
        atlas = out["attrs"]["atlas"]
        assert atlas["utilization"] == pytest.approx((out["texel/face_id"] >= 0).mean(), abs=1e-12)
        assert atlas["xatlas_utilization"] > atlas["utilization"]
    # 60 separate boxes: 60+ charts with a 4-texel gutter each cannot share 56^2 texels
    boxes = trimesh.util.concatenate([trimesh.creation.box((0.01, 0.01, 0.01)).apply_translation([0.02 * i, 0, 1])
                                      for i in range(60)])
    with pytest.raises(RuntimeError, match=r"could not pack the \d+ charts into one 56\^2 atlas .*"
                                           r"raise template.atlas_size or lower template.gutter_px"):
        build_atlas(boxes.vertices, boxes.faces, 64, 4)


def test_a_layout_that_covers_no_texels_is_refused():
    """template.uv: mesh with every vt (0, 0) (an export without a real layout) covered no texel
    and was accepted; so is a layout most of whose faces have zero UV area, and one of triangles
    too small to hold a texel centre. A few collapsed faces are only warned about."""
    from stex.readers.meshes import Mesh
    from stex.atlas import MAX_COLLAPSED_UV_FRACTION
    from stex.template import prepare_template
    s = trimesh.creation.icosphere(2, 0.1)
    V, F = np.asarray(s.vertices) + [0, 0, 1], np.asarray(s.faces)
    params = dict(decimate=False, min_faces=0, atlas_size=64, gutter_px=1, uv="mesh")
    with pytest.raises(ValueError, match=r"320 of the 320 faces have zero area in the mesh's texture coordinates"
                                         r".*use template.uv: xatlas"):
        prepare_template(Mesh(V, F, np.zeros((1, 2)), np.zeros_like(F)), params)
    # each face its own tiny triangle inside one texel, between texel centres: no centre held
    k = np.arange(len(F))
    tc = np.stack([np.full(len(F), 0.1), 0.1 + 1e-6 * k], 1)
    corners = np.stack([tc, tc + [1e-7, 0], tc + [0, 1e-7]], 1)[:, [0, 2, 1]]  # front-facing
    with pytest.raises(ValueError, match=r"hold no texel centre of the 64\^2 atlas \(template.atlas_size\)"):
        prepare_template(Mesh(V, F, corners.reshape(-1, 2), np.arange(3 * len(F)).reshape(-1, 3)), params)
    # a good layout with more than half of its faces collapsed
    tc, tf = build_atlas(V, F, 64, 1)
    tc = np.asarray(tc, np.float64).copy()
    tf = np.asarray(tf).copy()
    n = int(MAX_COLLAPSED_UV_FRACTION * len(F)) + 1
    tf[:n] = tf[:n, :1]
    with pytest.raises(ValueError, match=rf"{n} of the 320 faces have zero area"):
        prepare_template(Mesh(V, F, tc, tf), params)


@pytest.mark.parametrize("params, match", [
    ({"uv": "UV-mesh"}, "uv"),
    ({"atlas_sise": 1024}, "atlas_sise"),
    ({"atlas_size": 32}, "atlas_size"),
])
def test_template_params_are_validated(tmp_path, params, match):
    """A misspelled uv was silently xatlas, unknown keys were ignored; both entry points now check
    the params against the schema (and fill in its defaults: a partial dict works)."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    s = trimesh.creation.icosphere(1, 0.1)
    mesh = Mesh(np.asarray(s.vertices) + [0, 0, 1], np.asarray(s.faces))
    with pytest.raises(ValueError, match=match):
        prepare_template(mesh, params)
    with pytest.raises(ValueError, match=match):  # before the (missing) scene is read
        write_template(tmp_path / "no_scene.zarr", params, tmp_path / "template.zarr")
    out = prepare_template(mesh, {"atlas_size": 128})
    assert out["attrs"]["uv"] == "xatlas" and len(out["faces"]) >= 4000 // 4  # schema min_faces 4000



def test_a_layout_with_exactly_the_allowed_fraction_of_collapsed_faces_is_kept():
    """keep_layout refuses more than MAX_COLLAPSED_UV_FRACTION of the faces with zero UV area, not
    that fraction itself: 4 of 8 collapsed faces are kept (and counted), 5 are refused."""
    from conftest import grid_atlas
    from stex.atlas import MAX_COLLAPSED_UV_FRACTION, keep_layout
    tc, tf = grid_atlas(3)  # 8 faces
    assert MAX_COLLAPSED_UV_FRACTION * len(tf) == 4
    corners = tc[tf].copy()
    corners[:4] = corners[:4, :1]  # all three corners on the first one
    _, _, info = keep_layout(corners, 64)
    assert info["degenerate_uv_faces"] == 4
    corners[4] = corners[4, :1]
    with pytest.raises(ValueError, match="5 of the 8 faces have zero area"):
        keep_layout(corners, 64)


def test_a_millimetre_mesh_embeds_like_the_same_mesh_scaled_up():
    """trimesh's closest point compares with an absolute tolerance: with ~1 mm faces (in metres)
    points snapped to edges that were not the closest (0.18 mm off). The same fine, bumpy mesh in
    metres and x1000 must give the same closest points, faces and distances."""
    m = trimesh.creation.icosphere(5, 0.02)  # 2 cm ball, 20k faces, ~0.8 mm edges
    m.vertices *= 1 + 0.05 * np.sin(300 * m.vertices[:, :1])
    V0, F0 = np.asarray(m.vertices) + [0, 0, 1], np.asarray(m.faces)
    rng = np.random.default_rng(0)
    pts = V0[rng.choice(len(V0), 1000, replace=False)] + rng.normal(0, 2e-4, (1000, 3))
    face, bary, closest, dist = embed_vertices(pts, V0, F0)
    face_k, bary_k, closest_k, dist_k = embed_vertices(pts * 1e3, V0 * 1e3, F0)
    np.testing.assert_allclose(dist, dist_k / 1e3, rtol=0, atol=1e-10)
    np.testing.assert_allclose(closest, closest_k / 1e3, rtol=0, atol=1e-10)
    # brute force over every face for a sample: no face is nearer than the one found
    for i in range(0, 1000, 50):
        c = trimesh.triangles.closest_point((V0[F0] - pts[i]) * 1e3, np.zeros((len(F0), 3)))
        assert dist[i] <= np.linalg.norm(c, axis=1).min() / 1e3 + 1e-10


def test_the_collapsed_uv_warning_names_small_parts_not_needles(caplog):
    """A 2 mm part of well-shaped faces on a 10 cm body falls below xatlas' area limit at the
    working scale (which follows the median face area): the warning says so, with the part, and
    does not call them needle-thin; the atlas-size warning does not blame the atlas for them."""
    from stex.readers.meshes import Mesh
    from stex.template import prepare_template
    body = trimesh.creation.icosphere(3, 0.1)
    eye = trimesh.creation.icosphere(2, 0.001).apply_translation([0.1, 0, 0])
    m = trimesh.util.concatenate([body, eye])
    with caplog.at_level("WARNING", logger="stex.template"):
        out = prepare_template(Mesh(np.asarray(m.vertices) + [0, 0, 1], np.asarray(m.faces)),
                               dict(decimate=False, min_faces=0, atlas_size=512, gutter_px=2))
    assert out["attrs"]["atlas"]["degenerate_uv_faces"] == len(eye.faces)
    assert (f"{len(eye.faces)} faces have no area in the atlas" in caplog.text
            and f"{len(eye.faces)} of them are below xatlas' area limit at the working scale x1" in caplog.text
            and "0 are needle-thin" in caplog.text and f"{len(eye.faces)} of the {len(eye.faces)} faces of part 1" in caplog.text)
    assert "hold no texel centre" not in caplog.text


def test_build_atlas_never_loads_xatlas_into_the_calling_process():
    """xatlas runs in a child that never destroys its atlas (xatlas::Destroy can hang joining its
    threads, see stex.isolated); the caller must not hold an xatlas atlas of its own."""
    import subprocess
    import sys

    code = ("import sys, trimesh; from stex.atlas import build_atlas; "
            "m = trimesh.creation.icosphere(2); tc, tf = build_atlas(m.vertices, m.faces, 256, 2); "
            "assert tf.shape == (320, 3), tf.shape; print(sorted(k for k in sys.modules if 'xatlas' in k))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_an_edge_through_texel_centres_is_no_overlap():
    """The rasteriser counts a texel centre on an edge as inside both triangles, so a square chart
    split along its diagonal with corners on the texel grid (a box's usual layout) had 32 texels
    counted as overlapping and keep_layout refused it; centres on a shared edge are not overlaps.
    Two triangles that do cover each other still are: (0, 1, 2) and (0, 1, 3) share the triangle
    of corners 0, 1 and the square's centre; in texel units (centres at integers) its base lies at
    v = 15.5 from u = 15.5 to 47.5 and its apex at (31.5, 31.5), so row v = 16..30 holds the
    62 - 2v centres u = v + 1 .. 62 - v strictly inside: 30 + 28 + ... + 2 = 240."""
    from stex.atlas import keep_layout, uv_overlaps
    tc = np.array([[.25, .25], [.75, .25], [.75, .75], [.25, .75]])
    tf = np.array([[0, 1, 2], [0, 2, 3]])
    assert uv_overlaps(tc, tf, 64) == (0, None)
    assert keep_layout(tc[tf], 64)[2]["overlap_texels"] == 0
    n, where = uv_overlaps(tc, np.array([[0, 1, 2], [0, 1, 3]]), 64)
    assert n == sum(62 - 2 * v for v in range(16, 31)) == 240 and where is not None
