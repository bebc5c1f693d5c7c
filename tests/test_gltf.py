"""Tests for stex.synth.gltf: a hand-built two-bone glTF (analytic poses) and the Khronos Fox."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from stex.synth.gltf import (
    GltfError,
    joint_matrices,
    load_skinned_gltf,
    node_global_transforms,
    pose_sequence,
    pose_vertices,
    skin_vertices,
)

# --------------------------------------------------------------------------------------------
# A tiny skinned bar, built by hand
# --------------------------------------------------------------------------------------------
#
# Nodes: 0 "armature" (matrix = translate(0, 1, 0)) -> 1 "root_bone" -> 2 "child_bone"
# (translation (1, 0, 0)); 3 "bar" holds the skinned mesh and has translation (5, 0, 0), which
# the glTF spec says must be ignored. In the scene frame the child joint sits at P = (1, 1, 0).
#
# Mesh (mesh frame): a flat bar x in {0, .5, 1, 1.5, 2}, y in {1, 1.25}, z = 0, four quads, as
# two primitives split at x = 1 (a UV seam: the x = 1 vertices appear in both with different
# UVs). Primitive 0 (x <= 1): interleaved POSITION+TEXCOORD_0 (byteStride 20), uint16 indices,
# uint8 joints, normalized uint8 weights, all bound to the root bone. Primitive 1 (x >= 1): a
# sparse POSITION accessor (two corrupted entries fixed by the sparse part), uint8 indices,
# uint16 joints, float weights un-normalised (x = 1.5: 0.25/0.25 -> 0.5/0.5, x = 2: child only,
# listed in a different slot order).

P = np.array([1.0, 1.0, 0.0])
XS = [0.0, 0.5, 1.0, 1.5, 2.0]
YS = [1.0, 1.25]  # float32-exact
EXPECTED_VERTICES = np.array([(x, y, 0.0) for x in XS for y in YS])  # first-occurrence order
CHILD_WEIGHT = np.array([0.0 if x <= 1.0 else (0.5 if x == 1.5 else 1.0) for x in XS for y in YS])
S45 = np.sin(np.pi / 4)


def _rot_z(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def expected_pose(deg, shift=(0.0, 0.0, 0.0)):
    """Analytic LBS: root-bound points fixed, child-bound points rotated about P, blended."""
    v = EXPECTED_VERTICES
    rotated = (v - P) @ _rot_z(deg).T + P
    w = CHILD_WEIGHT[:, None]
    return (1 - w) * v + w * rotated + np.asarray(shift)


def _quat_z(deg):
    a = np.deg2rad(deg) / 2
    return [0.0, 0.0, np.sin(a), np.cos(a)]


class _Builder:
    def __init__(self):
        self.bin = bytearray()
        self.views, self.accessors = [], []

    def view(self, data: bytes, stride=None) -> int:
        while len(self.bin) % 4:
            self.bin.append(0)
        bv = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if stride:
            bv["byteStride"] = stride
        self.bin += data
        self.views.append(bv)
        return len(self.views) - 1

    def accessor(self, view, ctype, count, atype, byte_offset=0, **extra) -> int:
        acc = {"componentType": ctype, "count": count, "type": atype, **extra}
        if view is not None:
            acc["bufferView"] = view
            acc["byteOffset"] = byte_offset
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def array(self, arr, ctype, atype, **extra) -> int:
        arr = np.ascontiguousarray(arr)
        count = arr.shape[0]
        return self.accessor(self.view(arr.tobytes()), ctype, count, atype, **extra)


def _png_bytes():
    from PIL import Image

    img = np.zeros((3, 4, 3), dtype=np.uint8)
    img[..., 0] = np.arange(4)[None, :] * 60
    img[..., 1] = np.arange(3)[:, None] * 100
    img[..., 2] = 7
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return img, buf.getvalue()


def make_bar(mode1=4, prim1_x1_weights=(1.0, 0.0), with_skin=True, image_in_buffer=False):
    """(doc, bin bytes, texture) of the bar asset; the buffer's uri is filled by the writers."""
    b = _Builder()
    # --- primitive 0, interleaved position (3 f32) + uv (2 f32)
    p0 = [(x, y, 0.0) for x in XS[:3] for y in YS]
    uv0 = [(0.25 * x, 0.2 if y == 1.0 else 0.0) for x in XS[:3] for y in YS]
    inter = b"".join(struct.pack("<3f2f", *p, *t) for p, t in zip(p0, uv0))
    v_inter = b.view(inter, stride=20)
    pos0 = b.accessor(v_inter, 5126, 6, "VEC3", 0, min=[0, 1, 0], max=[1, 1.25, 0])
    tex0 = b.accessor(v_inter, 5126, 6, "VEC2", 12)
    quads = lambda n: [t for i in range(n) for t in ((2 * i, 2 * i + 2, 2 * i + 3), (2 * i, 2 * i + 3, 2 * i + 1))]
    idx0 = b.array(np.array(quads(2), dtype="<u2").ravel(), 5123, "SCALAR")
    j0 = b.array(np.zeros((6, 4), dtype="u1"), 5121, "VEC4")
    w0 = b.array(np.tile(np.array([255, 0, 0, 0], dtype="u1"), (6, 1)), 5121, "VEC4", normalized=True)
    # --- primitive 1, sparse positions
    p1 = np.array([(x, y, 0.0) for x in XS[2:] for y in YS], dtype="<f4")
    corrupted = p1.copy()
    corrupted[[1, 4]] = 99.0
    v_p1 = b.view(corrupted.tobytes())
    sp_idx = b.view(np.array([1, 4], dtype="<u2").tobytes())
    sp_val = b.view(p1[[1, 4]].tobytes())
    pos1 = b.accessor(v_p1, 5126, 6, "VEC3", 0, min=[1, 1, 0], max=[2, 1.25, 0], sparse={
        "count": 2, "indices": {"bufferView": sp_idx, "componentType": 5123},
        "values": {"bufferView": sp_val}})
    uv1 = np.array([(0.5 + 0.25 * (x - 1), 0.2 if y == 1.0 else 0.0) for x in XS[2:] for y in YS], dtype="<f4")
    tex1 = b.array(uv1, 5126, "VEC2")
    idx1 = b.array(np.array(quads(2), dtype="u1").ravel(), 5121, "SCALAR")
    j1 = np.array([[0, 1, 0, 0]] * 2 + [[0, 1, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, dtype="<u2")
    w1 = np.array([list(prim1_x1_weights) + [0, 0]] * 2 + [[0.25, 0.25, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, dtype="<f4")
    j1a, w1a = b.array(j1, 5123, "VEC4"), b.array(w1, 5126, "VEC4")
    # --- skin
    ibm = np.stack([np.eye(4), np.eye(4)])
    ibm[0, :3, 3] = [0, -1, 0]
    ibm[1, :3, 3] = [-1, -1, 0]
    ibm_acc = b.array(np.ascontiguousarray(ibm.transpose(0, 2, 1)).astype("<f4"), 5126, "MAT4")
    # --- animations
    t01 = b.array(np.array([0.0, 1.0], dtype="<f4"), 5126, "SCALAR", min=[0], max=[1])
    t02 = b.array(np.array([0.0, 2.0], dtype="<f4"), 5126, "SCALAR", min=[0], max=[2])
    lin = b.array(np.array([_quat_z(0), _quat_z(90)], dtype="<f4"), 5126, "VEC4")
    step = b.array(np.round(np.array([_quat_z(0), _quat_z(90)]) * 32767).astype("<i2"), 5122, "VEC4",
                   normalized=True)
    zero4 = [0.0] * 4
    cub = b.array(np.array([zero4, _quat_z(0), zero4, zero4, _quat_z(90), zero4], dtype="<f4"), 5126, "VEC4")
    z3 = [0.0] * 3
    slide = b.array(np.array([z3, z3, [3, 0, 0], z3, [1, 0, 0], z3], dtype="<f4"), 5126, "VEC3")
    anims = [
        {"name": "bend_linear", "samplers": [{"input": t01, "output": lin}],
         "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]},
        {"name": "bend_step", "samplers": [{"input": t01, "output": step, "interpolation": "STEP"}],
         "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]},
        {"name": "bend_cubic", "samplers": [{"input": t01, "output": cub, "interpolation": "CUBICSPLINE"}],
         "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]},
        {"name": "slide_cubic", "samplers": [{"input": t02, "output": slide, "interpolation": "CUBICSPLINE"}],
         "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}]},
    ]
    texture, png = _png_bytes()
    image = ({"bufferView": b.view(png), "mimeType": "image/png"} if image_in_buffer else
             {"uri": "data:image/png;base64," + base64.b64encode(png).decode("ascii")})
    armature = np.eye(4)
    armature[1, 3] = 1.0
    bar_node = {"name": "bar", "mesh": 0, "translation": [5.0, 0.0, 0.0]}
    if with_skin:
        bar_node["skin"] = 0
    doc = {
        "asset": {"version": "2.0", "generator": "stex test"},
        "scene": 0,
        "scenes": [{"nodes": [0, 3]}],
        "nodes": [
            {"name": "armature", "matrix": armature.T.ravel().tolist(), "children": [1]},
            {"name": "root_bone", "children": [2]},
            {"name": "child_bone", "translation": [1.0, 0.0, 0.0]},
            bar_node,
        ],
        "meshes": [{"name": "bar", "primitives": [
            {"attributes": {"POSITION": pos0, "TEXCOORD_0": tex0, "JOINTS_0": j0, "WEIGHTS_0": w0},
             "indices": idx0, "material": 0},
            {"attributes": {"POSITION": pos1, "TEXCOORD_0": tex1, "JOINTS_0": j1a, "WEIGHTS_0": w1a},
             "indices": idx1, "material": 0, "mode": mode1},
        ]}],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": ibm_acc, "skeleton": 1}],
        "materials": [{"name": "m", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [image],
        "animations": anims,
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(b.bin)}],
    }
    return doc, bytes(b.bin), texture


def write_gltf(path: Path, doc, binary, external: str | None = None) -> Path:
    doc = json.loads(json.dumps(doc))
    if external:
        (path.parent / external).write_bytes(binary)
        doc["buffers"][0]["uri"] = external
    else:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    path.write_text(json.dumps(doc))
    return path


def write_glb(path: Path, doc, binary) -> Path:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    bn = binary + b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(bn)
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A)
                     + js + struct.pack("<II", len(bn), 0x004E4942) + bn)
    return path


@pytest.fixture(scope="module")
def bar_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bar")
    doc, binary, texture = make_bar()
    doc_glb, binary_glb, _ = make_bar(image_in_buffer=True)
    return {
        "gltf": write_gltf(d / "bar.gltf", doc, binary),
        "glb": write_glb(d / "bar.glb", doc_glb, binary_glb),
        "external": write_gltf(d / "bar_ext.gltf", doc, binary, external="bar ext.bin"),
        "texture": texture,
    }


@pytest.fixture(scope="module", params=["gltf", "glb", "external"])
def bar(request, bar_files):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the bar loads without any warning
        return load_skinned_gltf(bar_files[request.param])


def test_bar_geometry_and_merge(bar, bar_files):
    np.testing.assert_array_equal(bar.vertices, EXPECTED_VERTICES)
    assert bar.vertices.dtype == np.float64 and bar.faces.dtype == np.int32
    assert bar.faces.shape == (8, 3) and bar.texcoord_faces.shape == (8, 3)
    # 12 glTF vertices -> 10 merged; the seam column x = 1 is shared by both primitives
    np.testing.assert_array_equal(bar.gltf_to_vertex, [0, 1, 2, 3, 4, 5, 4, 5, 6, 7, 8, 9])
    edges = np.sort(bar.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    assert len(uniq) == 17 and (counts == 2).sum() == 7 and (counts == 1).sum() == 10
    assert counts[np.flatnonzero((uniq == [4, 5]).all(1))[0]] == 2  # seam edge is interior
    assert len(bar.vertices) - len(uniq) + len(bar.faces) == 1  # a disk
    # faces are CCW seen from +z (normals +z)
    v = bar.vertices[bar.faces]
    assert (np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, 2] > 0).all()
    # UVs stay split at the seam: 12 distinct texcoords, corners consistent with positions
    assert bar.texcoords.shape == (12, 2)
    uv = bar.texcoords[bar.texcoord_faces]
    pos = bar.vertices[bar.faces]
    u_expected = np.where(np.arange(8)[:, None] < 4, 0.25 * pos[..., 0], 0.5 + 0.25 * (pos[..., 0] - 1))
    np.testing.assert_allclose(uv[..., 0], u_expected, atol=1e-7)
    np.testing.assert_allclose(uv[..., 1], np.where(pos[..., 1] == 1.0, 0.2, 0.0), atol=1e-7)
    # skinning normalised, texture decoded
    np.testing.assert_allclose(bar.weights.sum(1), 1.0)
    child = np.where(bar.joints == 1, bar.weights, 0).sum(1)
    np.testing.assert_allclose(child, CHILD_WEIGHT)
    assert bar.texture.dtype == np.uint8
    np.testing.assert_array_equal(bar.texture, bar_files["texture"])
    # node tree
    assert bar.node_names == ["armature", "root_bone", "child_bone", "bar"]
    np.testing.assert_array_equal(bar.node_parents, [-1, 0, 1, -1])
    assert bar.joint_names == ["root_bone", "child_bone"]
    assert [(a.name, a.duration_s) for a in bar.animations] == [
        ("bend_linear", 1.0), ("bend_step", 1.0), ("bend_cubic", 1.0), ("slide_cubic", 2.0)]


def test_bar_rest_is_bind(bar):
    np.testing.assert_allclose(joint_matrices(bar), np.tile(np.eye(4), (2, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(pose_vertices(bar, None, 0.0), EXPECTED_VERTICES, atol=1e-12)
    glob = node_global_transforms(bar)
    np.testing.assert_allclose(glob[2][:3, 3], P)


def test_bar_linear_slerp(bar):
    for t, deg in [(0.0, 0), (0.5, 45), (0.25, 22.5), (1.0, 90)]:
        np.testing.assert_allclose(pose_vertices(bar, "bend_linear", t), expected_pose(deg), atol=1e-6)
    # mesh node translation (5, 0, 0) is ignored; animation by index works; clamping and looping
    np.testing.assert_allclose(pose_vertices(bar, 0, 0.5), expected_pose(45), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, 0, 7.0), expected_pose(90), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, 0, -1.0), expected_pose(0), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, 0, 1.5, loop=True), expected_pose(45), atol=1e-6)
    seq = pose_sequence(bar, "bend_linear", [0.0, 0.5, 1.0])
    assert seq.shape == (3, 10, 3) and seq.dtype == np.float64
    np.testing.assert_allclose(seq[1], expected_pose(45), atol=1e-6)


def test_bar_step(bar):
    for t, deg in [(0.0, 0), (0.5, 0), (0.999, 0), (1.0, 90), (3.0, 90)]:
        np.testing.assert_allclose(pose_vertices(bar, "bend_step", t), expected_pose(deg), atol=1e-4)


def test_bar_cubicspline(bar):
    # zero tangents: q(s) = normalise(q0 + (q1 - q0) * (3 s^2 - 2 s^3))
    for t in [0.25, 0.5, 0.8]:
        h = 3 * t * t - 2 * t ** 3
        q = (1 - h) * np.array(_quat_z(0)) + h * np.array(_quat_z(90))
        deg = np.rad2deg(2 * np.arctan2(q[2], q[3]))
        np.testing.assert_allclose(pose_vertices(bar, "bend_cubic", t), expected_pose(deg), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, "bend_cubic", 0.5), expected_pose(45), atol=1e-6)
    # translation with an out-tangent: keys t = 0, 2, v = 0 -> 1, b0 = 3/s; at t = 0.5 (s = 1/4)
    # p = h01 * 1 + td * h10 * 3 = 0.15625 + 2 * 0.140625 * 3 = 1.0
    np.testing.assert_allclose(pose_vertices(bar, "slide_cubic", 0.5), expected_pose(0, (1.0, 0, 0)), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, "slide_cubic", 2.0), expected_pose(0, (1.0, 0, 0)), atol=1e-6)
    np.testing.assert_allclose(pose_vertices(bar, "slide_cubic", 0.0), expected_pose(0), atol=1e-6)


def test_bar_formats_identical(bar_files):
    meshes = [load_skinned_gltf(bar_files[k]) for k in ("gltf", "glb", "external")]
    for m in meshes[1:]:
        for f in ("vertices", "faces", "texcoords", "texcoord_faces", "texture", "joints", "weights",
                  "inverse_bind"):
            np.testing.assert_array_equal(getattr(m, f), getattr(meshes[0], f))
        np.testing.assert_array_equal(pose_vertices(m, "bend_cubic", 0.3), pose_vertices(meshes[0], "bend_cubic", 0.3))


def test_errors(tmp_path, bar_files):
    with pytest.raises(FileNotFoundError, match="nope.gltf"):
        load_skinned_gltf(tmp_path / "nope.gltf")
    doc, binary, _ = make_bar()
    p = write_gltf(tmp_path / "missing_bin.gltf", doc, binary, external="gone.bin")
    (tmp_path / "gone.bin").unlink()
    with pytest.raises(FileNotFoundError, match="gone.bin"):
        load_skinned_gltf(p)
    doc, binary, _ = make_bar(mode1=5)
    with pytest.raises(GltfError, match=r"primitive 1 .*TRIANGLE_STRIP"):
        load_skinned_gltf(write_gltf(tmp_path / "strip.gltf", doc, binary))
    doc, binary, _ = make_bar(with_skin=False)
    with pytest.raises(GltfError, match="no skinned mesh"):
        load_skinned_gltf(write_glb(tmp_path / "noskin.glb", doc, binary))
    mesh = load_skinned_gltf(bar_files["gltf"])
    with pytest.raises(GltfError, match=r"unknown animation 'Dance'.*bend_linear.*slide_cubic"):
        pose_vertices(mesh, "Dance", 0.0)
    with pytest.raises(GltfError, match="out of range"):
        pose_vertices(mesh, 9, 0.0)
    doc, binary, _ = make_bar()
    binary = struct.pack("<f", float("nan")) + bytes(binary[4:])   # vertex 0's x (first interleaved view)
    with pytest.raises(GltfError, match=r"nan\.gltf: mesh 0 .* primitive 0: POSITION 0 is not finite"):
        load_skinned_gltf(write_gltf(tmp_path / "nan.gltf", doc, binary))
    (tmp_path / "junk.gltf").write_text("{not json")
    with pytest.raises(GltfError, match="junk.gltf"):
        load_skinned_gltf(tmp_path / "junk.gltf")


def test_skin_mismatch_detected(tmp_path):
    # the x = 1 vertices get different weights in primitive 1 than in primitive 0
    doc, binary, _ = make_bar(prim1_x1_weights=(0.5, 0.5))
    p = write_gltf(tmp_path / "mismatch.gltf", doc, binary)
    with pytest.warns(UserWarning, match="different skinning"):
        m = load_skinned_gltf(p)
    np.testing.assert_allclose(m.weights[4], [1, 0, 0, 0])  # first occurrence kept
    with pytest.raises(GltfError, match="different skinning"):
        load_skinned_gltf(p, on_skin_mismatch="raise")


def _append_accessor(doc, binary: bytes, arr, ctype, atype, **extra) -> tuple[bytes, int]:
    """Append ``arr`` (its bytes as they are) to the bar's buffer as a new bufferView +
    accessor of ``doc`` (changed in place); returns (new buffer bytes, accessor index)."""
    binary = bytes(binary) + b"\0" * (-len(binary) % 4)
    data = np.ascontiguousarray(arr).tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)})
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": ctype,
                             "count": int(np.shape(arr)[0]), "type": atype, **extra})
    binary += data
    doc["buffers"][0]["byteLength"] = len(binary)
    return binary, len(doc["accessors"]) - 1


def test_slerp_takes_the_shorter_arc_between_keyframes():
    """q and -q are the same rotation: LINEAR rotation keys stored with opposite signs are
    interpolated along the shorter arc, as scipy's Slerp (which interpolates rotations, not
    quaternions) does."""
    from scipy.spatial.transform import Rotation, Slerp

    from stex.synth.gltf import AnimationChannel, sample_channel

    r = Rotation.from_rotvec([[0.1, 0.2, 0.3], [-0.4, 1.1, 0.2]])
    q = r.as_quat()  # (x, y, z, w), scipy's order and glTF's
    q[1] *= -np.sign(np.dot(q[0], q[1]))  # the second key on the far hemisphere
    assert np.dot(q[0], q[1]) < 0
    ch = AnimationChannel(0, "rotation", "LINEAR", np.array([0.0, 2.0]), q)
    ref = Slerp([0.0, 2.0], r)
    for t in (0.3, 1.0, 1.6):
        got = Rotation.from_quat(sample_channel(ch, t))
        assert (got.inv() * ref(t)).magnitude() < 1e-9


def test_keyframe_times_hold_their_own_value():
    """At an interior keyframe time the sampler gives that keyframe's value: for STEP it holds
    over [t_k, t_k+1) (glTF spec), for LINEAR the segments meet there; between keys STEP keeps
    the earlier key, LINEAR mixes; outside the keys both clamp."""
    from stex.synth.gltf import AnimationChannel, sample_channel

    times = np.array([0.5, 1.0, 2.0])
    vals = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])
    step = AnimationChannel(0, "translation", "STEP", times, vals)
    lin = AnimationChannel(0, "translation", "LINEAR", times, vals)
    for t, s, l in [(0.0, 0, 0), (0.5, 0, 0), (0.75, 0, 0.5), (1.0, 1, 1), (1.5, 1, 3), (2.0, 5, 5), (9.0, 5, 5)]:
        np.testing.assert_allclose(sample_channel(step, t), [s, 0, 0], err_msg=f"STEP at {t}")
        np.testing.assert_allclose(sample_channel(lin, t), [l, 0, 0], err_msg=f"LINEAR at {t}")


def test_node_transform_is_translation_rotation_scale(tmp_path):
    """A node's TRS is the matrix T @ R @ S (glTF spec: scale first, then rotation, then
    translation), here with a non-uniform scale, built with scipy's Rotation; a node given by a
    (column-major) matrix keeps it and reports its translation, rotation (as scipy's quaternion,
    up to sign) and scale; the child's global transform is the parent's times its own."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_rotvec([0.3, -0.5, 0.9])
    arm = Rotation.from_rotvec(np.deg2rad(40) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14))
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = arm.as_matrix(), [0.5, 1.0, -2.0]
    doc, binary, _ = make_bar()
    doc["nodes"][0]["matrix"] = A.T.ravel().tolist()
    doc["nodes"][2].update(rotation=rot.as_quat().tolist(), scale=[2.0, 0.5, 1.5])
    mesh = load_skinned_gltf(write_gltf(tmp_path / "trs.gltf", doc, binary))
    expected = np.eye(4)
    expected[:3, :3] = rot.as_matrix() @ np.diag([2.0, 0.5, 1.5])
    expected[:3, 3] = [1.0, 0.0, 0.0]
    np.testing.assert_allclose(mesh.node_matrix[2], expected, atol=1e-12)
    np.testing.assert_allclose(mesh.node_matrix[0], A, atol=1e-12)
    np.testing.assert_allclose(mesh.node_translation[0], [0.5, 1.0, -2.0])
    q = mesh.node_rotation[0]
    np.testing.assert_allclose(q * np.sign(q[3]), arm.as_quat() * np.sign(arm.as_quat()[3]), atol=1e-12)
    np.testing.assert_allclose(mesh.node_scale[0], 1.0, atol=1e-12)
    np.testing.assert_allclose(node_global_transforms(mesh)[2], A @ expected, atol=1e-12)  # root_bone: identity


def test_normalized_integer_accessors_are_scaled_by_the_type_maximum(tmp_path):
    """Normalized integers (glTF spec, "Animations"/"Meshes"): unsigned k -> k / (2^n - 1),
    signed k -> max(k / (2^(n-1) - 1), -1). Texture coordinates as normalized UNSIGNED_SHORT
    read as k / 65535 exactly; a STEP rotation to -90 deg about z stored as normalized SHORT
    (negative components) reads back within 1 / 32767 and bends the bar by -90 deg."""
    doc, binary, _ = make_bar()
    prim = doc["meshes"][0]["primitives"][1]
    uv = np.array([(0.5 + 0.25 * (x - 1), 0.2 if y == 1.0 else 0.0) for x in XS[2:] for y in YS])
    k = np.round(uv * 65535).astype("<u2")
    binary, prim["attributes"]["TEXCOORD_0"] = _append_accessor(doc, binary, k, 5123, "VEC2", normalized=True)
    quats = np.array([_quat_z(0), _quat_z(-90)])
    binary, q_acc = _append_accessor(doc, binary, np.round(quats * 32767).astype("<i2"), 5122, "VEC4",
                                     normalized=True)
    t_acc = doc["animations"][1]["samplers"][0]["input"]  # times 0, 1
    doc["animations"].append({"name": "bend_back",
                              "samplers": [{"input": t_acc, "output": q_acc, "interpolation": "STEP"}],
                              "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]})
    mesh = load_skinned_gltf(write_gltf(tmp_path / "normalized.gltf", doc, binary))
    tris = np.array([t for i in range(2) for t in ((2 * i, 2 * i + 2, 2 * i + 3), (2 * i, 2 * i + 3, 2 * i + 1))])
    got, want = mesh.texcoords[mesh.texcoord_faces[4:]], (k / 65535.0)[tris]  # primitive 1's triangles
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mesh.animations[-1].channels[0].values, quats, atol=1 / 32767)
    np.testing.assert_allclose(pose_vertices(mesh, "bend_back", 1.0), expected_pose(-90), atol=1e-4)


def test_more_than_four_influences_keep_the_four_largest_weights(tmp_path):
    """With JOINTS_1/WEIGHTS_1 a vertex may have 8 influences; the 4 largest are kept (with a
    warning naming the largest dropped weight) and renormalised. By hand, the x = 1.5 vertices:
    influences (joint, weight) (1, .4) (0, .05) (0, 0) (0, 0) (0, .3) (1, .1) (0, .04) (1, .02)
    keep .4 + .1 on the child and .3 + .05 on the root: child weight .5 / .85 = 10 / 17; the x = 2
    vertices (only (1, 1)) stay on the child."""
    doc, binary, _ = make_bar()
    attrs = doc["meshes"][0]["primitives"][1]["attributes"]
    j0 = np.array([[0, 1, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, dtype="<u2")
    w0 = np.array([[1, 0, 0, 0]] * 2 + [[0.4, 0.05, 0, 0]] * 2 + [[1, 0, 0, 0]] * 2, dtype="<f4")
    j1 = np.array([[0, 0, 0, 0]] * 2 + [[0, 1, 0, 1]] * 2 + [[0, 0, 0, 0]] * 2, dtype="<u2")
    w1 = np.array([[0, 0, 0, 0]] * 2 + [[0.3, 0.1, 0.04, 0.02]] * 2 + [[0, 0, 0, 0]] * 2, dtype="<f4")
    for name, arr, ctype in (("JOINTS_0", j0, 5123), ("WEIGHTS_0", w0, 5126),
                             ("JOINTS_1", j1, 5123), ("WEIGHTS_1", w1, 5126)):
        binary, attrs[name] = _append_accessor(doc, binary, arr, ctype, "VEC4")
    with pytest.warns(UserWarning, match=r"more than 4 influences.*0\.04"):
        mesh = load_skinned_gltf(write_gltf(tmp_path / "eight.gltf", doc, binary))
    child = np.where(mesh.joints == 1, mesh.weights, 0).sum(1)
    np.testing.assert_allclose(child, [0] * 6 + [10 / 17] * 2 + [1] * 2, atol=1e-7)
    np.testing.assert_allclose(mesh.weights.sum(1), 1.0)


def test_animation_duration_is_its_longest_channel(tmp_path):
    """An animation whose channels end at different times lasts until the last one ends
    (2 s here, the translation; the rotation ends at 1 s and then holds)."""
    doc, binary, _ = make_bar()
    slide = doc["animations"][3]["samplers"][0]   # CUBICSPLINE, keys at 0 and 2 s
    bend = doc["animations"][0]["samplers"][0]    # LINEAR, keys at 0 and 1 s
    doc["animations"].append({"name": "both", "samplers": [slide, bend], "channels": [
        {"sampler": 0, "target": {"node": 1, "path": "translation"}},
        {"sampler": 1, "target": {"node": 2, "path": "rotation"}}]})
    mesh = load_skinned_gltf(write_gltf(tmp_path / "both.gltf", doc, binary))
    assert mesh.animations[-1].duration_s == 2.0
    np.testing.assert_allclose(pose_vertices(mesh, "both", 3.0, loop=True), pose_vertices(mesh, "both", 1.0),
                               atol=1e-12)


# --------------------------------------------------------------------------------------------
# The Khronos Fox sample (skipped when the data folder is absent)
# --------------------------------------------------------------------------------------------


def _data_samples() -> Path:
    env = os.environ.get("STEX_DATA_SAMPLES")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data_samples"


FOX_DIR = _data_samples() / "gltf_fox"
FOX_GLTF = FOX_DIR / "glTF" / "Fox.gltf"
FOX_GLB = FOX_DIR / "glTF-Binary" / "Fox.glb"
needs_fox = pytest.mark.skipif(not (FOX_GLTF.is_file() and FOX_GLB.is_file()),
                               reason=f"Fox sample not found under {FOX_DIR}")


@pytest.fixture(scope="module")
def fox():
    return load_skinned_gltf(FOX_GLTF)


@pytest.fixture(scope="module")
def fox_glb():
    return load_skinned_gltf(FOX_GLB)


def _diag(m):
    return float(np.linalg.norm(np.ptp(m.vertices, axis=0)))


@needs_fox
def test_fox_structure(fox):
    import trimesh
    from PIL import Image

    scene = trimesh.load(FOX_GLTF)
    geoms = list(scene.geometry.values()) if hasattr(scene, "geometry") else [scene]
    assert len(geoms) == 1
    tm = geoms[0]
    # same triangles (glTF vertices split at seams -> merged by position here)
    assert fox.faces.shape == tm.faces.shape == (576, 3)
    assert len(fox.vertices) == len(np.unique(np.asarray(tm.vertices), axis=0)) == 290
    np.testing.assert_allclose(fox.vertices[fox.faces], np.asarray(tm.vertices)[tm.faces], atol=1e-9)
    # UVs: trimesh flips v to the OBJ convention (origin bottom-left); stex keeps glTF's
    uv_tm = np.asarray(tm.visual.uv)[tm.faces]
    uv = fox.texcoords[fox.texcoord_faces]
    np.testing.assert_allclose(uv[..., 0], uv_tm[..., 0], atol=1e-6)
    np.testing.assert_allclose(uv[..., 1], 1.0 - uv_tm[..., 1], atol=1e-6)
    # texture, skin, animations
    assert fox.texture.shape == (1024, 1024, 3) and fox.texture.dtype == np.uint8
    with Image.open(FOX_DIR / "glTF" / "Texture.png") as im:
        np.testing.assert_array_equal(fox.texture, np.asarray(im.convert("RGB")))
    assert fox.joints.shape == (290, 4) and fox.inverse_bind.shape == (24, 4, 4)
    assert fox.joints.min() >= 0 and fox.joints.max() < 24
    np.testing.assert_allclose(fox.weights.sum(1), 1.0, atol=1e-12)
    names = [(a.name, round(a.duration_s, 2)) for a in fox.animations]
    assert names == [("Survey", 3.42), ("Walk", 0.71), ("Run", 1.16)]
    # centimetre-like units: about 0.8 units tall, 1.5 long -> scale by 0.01 for metres
    ext = np.ptp(fox.vertices, axis=0)
    assert 50 < ext[1] < 120 and 100 < ext[2] < 250
    assert abs(fox.vertices[:, 1].min()) < 1.0  # standing on y = 0


@needs_fox
def test_fox_bind_and_rest(fox):
    # synthetic bind state: joint globals = inverse(inverseBind); rebuild local matrices through
    # the node hierarchy, then pose through the full pipeline
    glob = node_global_transforms(fox)
    glob[fox.joint_nodes] = np.linalg.inv(fox.inverse_bind)
    local = fox.node_matrix.copy()
    for n in fox.node_order:
        p = fox.node_parents[n]
        local[n] = glob[n] if p < 0 else np.linalg.solve(glob[p], glob[n])
    bind = dataclasses.replace(fox, node_matrix=local)
    np.testing.assert_allclose(pose_vertices(bind, None, 0.0), fox.vertices, atol=1e-6)
    np.testing.assert_allclose(skin_vertices(fox, np.tile(np.eye(4), (24, 1, 1))), fox.vertices, atol=1e-9)
    # the Fox's rest node pose is its bind pose up to float32 rounding of the inverse binds
    rest = pose_vertices(fox, None, 0.0)
    assert np.abs(rest - fox.vertices).max() < 1e-6 * _diag(fox) * 10


@needs_fox
def test_fox_animations_plausible(fox):
    diag, lo, hi = _diag(fox), fox.vertices.min(0), fox.vertices.max(0)
    height = hi[1] - lo[1]
    report = {}
    for anim in fox.animations:
        times = np.linspace(0.0, anim.duration_s, 25)
        seq = pose_sequence(fox, anim.name, times)
        assert np.isfinite(seq).all()
        disp = np.linalg.norm(seq - fox.vertices, axis=2).max()
        report[anim.name] = disp
        assert 0.05 * diag < disp < 0.6 * diag, (anim.name, disp)
        assert (seq.min(axis=1) > lo - 0.3 * diag).all() and (seq.max(axis=1) < hi + 0.3 * diag).all()
        diags = np.linalg.norm(np.ptp(seq, axis=1), axis=1)
        assert (diags > 0.7 * diag).all() and (diags < 1.3 * diag).all()
        # the lowest vertex (a foot) stays near the ground plane y = 0
        ground = seq[:, :, 1].min(axis=1)
        if anim.name == "Walk":
            assert np.abs(ground).max() < 0.04 * height, ground
        if anim.name == "Run":  # airborne phases lift all four feet a little
            assert (ground > -0.06 * height).all() and (ground < 0.12 * height).all(), ground
            assert np.abs(ground).min() < 0.02 * height
    print("Fox max vertex displacement per animation (file units):",
          {k: round(float(v), 2) for k, v in report.items()})


@needs_fox
def test_fox_gltf_equals_glb(fox, fox_glb):
    for f in ("vertices", "faces", "texcoords", "texcoord_faces", "texture", "joints", "weights",
              "inverse_bind", "joint_nodes", "node_matrix"):
        np.testing.assert_array_equal(getattr(fox_glb, f), getattr(fox, f), err_msg=f)
    assert fox.animation_names == fox_glb.animation_names
    for name in fox.animation_names:
        times = [0.0, 0.37, 0.61, 2.0]
        np.testing.assert_array_equal(pose_sequence(fox, name, times, loop=True),
                                      pose_sequence(fox_glb, name, times, loop=True))


@needs_fox
def test_the_foxs_own_uv_layout_as_the_atlas_takes_its_own_texture(fox):
    """template.uv: mesh on a real asset: the Fox's layout passes the checks (no overlaps), and
    the Fox's own texture on the (subdivided) template looks as it does on the asset, so slices
    in this atlas drop into its material. The atlas xatlas makes does not take it (the control)."""
    from stex.readers.meshes import Mesh
    from stex.render import render_textured
    from stex.template import prepare_template

    V = fox.vertices - fox.vertices.mean(0)
    V = V / np.ptp(V, axis=0).max() * 0.6
    mesh = Mesh(V, fox.faces, fox.texcoords, fox.texcoord_faces)
    params = dict(target_faces=20000, decimate=True, min_faces=4000, atlas_size=1024, gutter_px=4, uv="mesh")
    own = prepare_template(mesh, params)
    a = own["attrs"]
    assert a["uv"] == "mesh" and a["subdivided"] == 1 and len(own["faces"]) == 4 * 576
    assert a["atlas"]["overlap_texels"] == 0 and a["atlas"]["charts"] == 14

    def side_view(vertices):  # glTF y up, the fox along z: seen from its side, 1 m away
        v = np.asarray(vertices, np.float64)
        return np.column_stack([v[:, 2], -v[:, 1], v[:, 0] + 1.0])

    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    ref, m_ref = render_textured(side_view(V), fox.faces, fox.texcoords, fox.texcoord_faces, fox.texture, K, 640, 480)
    img, m = render_textured(side_view(own["vertices"]), own["faces"], own["texcoords"], own["texcoord_faces"],
                             fox.texture, K, 640, 480)
    assert m_ref.sum() > 15000 and (m != m_ref).sum() < 0.005 * m_ref.sum()
    both = m & m_ref
    diff = np.abs(img - ref)[both]
    assert diff.mean() < 0.5 and np.percentile(diff, 99) < 4, (diff.mean(), np.percentile(diff, 99))
    new = prepare_template(mesh, dict(params, uv="xatlas"))
    img_x, m_x = render_textured(side_view(new["vertices"]), new["faces"], new["texcoords"], new["texcoord_faces"],
                                 fox.texture, K, 640, 480)
    assert np.abs(img_x - ref)[m_x & m_ref].mean() > 10 * diff.mean() + 5


def test_a_static_gltf_is_read_as_a_plain_mesh(tmp_path):
    """load_mesh reads a glTF without a skin (e.g. another method's UV layout, or stex's own
    export) as a plain mesh, its TEXCOORD_0 in glTF's (and stex's) v-down convention."""
    import trimesh
    from PIL import Image

    from stex.readers.meshes import load_mesh

    m = trimesh.creation.icosphere(subdivisions=1)
    uv = np.column_stack([np.linspace(0.1, 0.9, len(m.vertices)), np.linspace(0.2, 0.3, len(m.vertices))])
    m.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.new("RGB", (4, 4)))
    path = tmp_path / "static.glb"
    m.export(path)
    got = load_mesh(path)
    np.testing.assert_allclose(got.vertices, m.vertices, atol=1e-6)
    np.testing.assert_array_equal(got.faces, m.faces)
    # trimesh's uv points up (OBJ); the file and stex hold 1 - v
    np.testing.assert_allclose(got.texcoords, np.column_stack([uv[:, 0], 1 - uv[:, 1]]), atol=1e-6)
    np.testing.assert_array_equal(got.texcoord_faces, got.faces)
