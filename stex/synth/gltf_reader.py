"""glTF 2.0 containers, read with numpy only: the JSON document (``.gltf`` or ``.glb``), its
buffers (external files or ``data:`` URIs), typed views of its accessors and its images.

:mod:`stex.synth.gltf` builds the skinned mesh and its animations on top of this.
"""

from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np
from PIL import Image


class GltfError(ValueError):
    """A glTF file is malformed or uses a feature this reader does not support."""


class GltfNoSkinError(GltfError):
    """A glTF file has no skinned mesh (a static asset: :func:`stex.readers.meshes.load_mesh`
    reads it as a plain mesh)."""


# --------------------------------------------------------------------------------------------
# File and buffer reading
# --------------------------------------------------------------------------------------------

_GLB_MAGIC = 0x46546C67  # b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942

_COMPONENT_DTYPES = {
    5120: np.dtype("<i1"),
    5121: np.dtype("<u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
_TYPE_SHAPES = {
    "SCALAR": (1,),
    "VEC2": (2,),
    "VEC3": (3,),
    "VEC4": (4,),
    "MAT2": (2, 2),
    "MAT3": (3, 3),
    "MAT4": (4, 4),
}
UNSUPPORTED_EXTENSIONS = {
    "KHR_draco_mesh_compression": "Draco-compressed geometry",
    "EXT_meshopt_compression": "meshopt-compressed buffers",
}
MODE_NAMES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
               5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}


def read_document(path: Path) -> tuple[dict, bytes | None]:
    """Return the JSON document and, for .glb, the BIN chunk (or None)."""
    data = path.read_bytes()
    if data[:4] == b"glTF":
        if len(data) < 12:
            raise GltfError(f"{path}: truncated GLB header")
        magic, version, length = struct.unpack_from("<III", data, 0)
        if magic != _GLB_MAGIC:
            raise GltfError(f"{path}: not a GLB file (bad magic)")
        if version != 2:
            raise GltfError(f"{path}: GLB container version {version}, only glTF 2 is supported")
        if length > len(data):
            raise GltfError(f"{path}: GLB header says {length} bytes but the file has {len(data)}")
        pos, doc, bin_chunk = 12, None, None
        while pos + 8 <= length:
            chunk_len, chunk_type = struct.unpack_from("<II", data, pos)
            chunk = data[pos + 8: pos + 8 + chunk_len]
            if len(chunk) != chunk_len:
                raise GltfError(f"{path}: truncated GLB chunk at byte {pos}")
            if chunk_type == _CHUNK_JSON and doc is None:
                doc = json.loads(chunk.decode("utf-8"))
            elif chunk_type == _CHUNK_BIN and bin_chunk is None:
                bin_chunk = chunk
            pos += 8 + chunk_len
        if doc is None:
            raise GltfError(f"{path}: GLB file has no JSON chunk")
        return doc, bin_chunk
    try:
        doc = json.loads(data.decode("utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GltfError(f"{path}: neither a GLB file nor valid glTF JSON ({exc})") from exc
    return doc, None


def _decode_data_uri(uri: str, what: str, path: Path) -> bytes:
    header, sep, payload = uri.partition(",")
    if not sep:
        raise GltfError(f"{path}: malformed data URI in {what}")
    if header.endswith(";base64"):
        try:
            return base64.b64decode(payload, validate=False)
        except (ValueError, TypeError) as exc:
            raise GltfError(f"{path}: bad base64 data URI in {what}: {exc}") from exc
    return unquote(payload).encode("latin-1")


def _read_uri(uri: str, what: str, path: Path) -> bytes:
    """Bytes behind a glTF URI: a ``data:`` URI or a file relative to the glTF file."""
    if uri.startswith("data:"):
        return _decode_data_uri(uri, what, path)
    if "://" in uri:
        raise GltfError(f"{path}: {what} refers to a remote URI {uri!r}; only local files are read")
    target = path.parent / unquote(uri)
    if not target.is_file():
        raise FileNotFoundError(f"{path}: {what} file {uri!r} not found (looked for {target})")
    return target.read_bytes()


def load_buffers(doc: dict, bin_chunk: bytes | None, path: Path) -> list[bytes]:
    buffers = []
    for i, b in enumerate(doc.get("buffers", [])):
        what = f"buffer {i}" + (f" ({b['name']!r})" if "name" in b else "")
        if "uri" in b:
            data = _read_uri(b["uri"], what, path)
        elif i == 0 and bin_chunk is not None:
            data = bin_chunk
        else:
            raise GltfError(f"{path}: {what} has no uri and there is no GLB binary chunk for it")
        n = int(b.get("byteLength", len(data)))
        if len(data) < n:
            raise GltfError(f"{path}: {what} holds {len(data)} bytes, byteLength says {n}")
        buffers.append(data[:n])
    return buffers


class GltfReader:
    """Resolves accessors, buffer views and images of one glTF document."""

    def __init__(self, doc: dict, buffers: list[bytes], path: Path):
        self.doc, self.buffers, self.path = doc, buffers, path
        self._cache: dict[int, np.ndarray] = {}

    def get(self, kind: str, index) -> dict:
        items = self.doc.get(kind, [])
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise GltfError(f"{self.path}: {kind} index {index!r} out of range (file has {len(items)})")
        return items[index]

    def buffer_view_bytes(self, index: int) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, start offset, byte length, byteStride or None) of a buffer view."""
        bv = self.get("bufferViews", index)
        buf_index = bv.get("buffer")
        if not isinstance(buf_index, int) or not 0 <= buf_index < len(self.buffers):
            raise GltfError(f"{self.path}: bufferView {index} refers to missing buffer {buf_index!r}")
        buf = self.buffers[buf_index]
        start, length = int(bv.get("byteOffset", 0)), int(bv["byteLength"])
        if start + length > len(buf):
            raise GltfError(f"{self.path}: bufferView {index} (bytes {start}..{start + length}) "
                            f"runs past the end of buffer {buf_index} ({len(buf)} bytes)")
        return buf, start, length, bv.get("byteStride")

    def _strided(self, view: int, byte_offset: int, count: int, dtype: np.dtype,
                 shape: tuple[int, ...], what: str, use_stride: bool = True) -> np.ndarray:
        """(count, *shape) array read from a buffer view, honouring stride and matrix padding.

        ``use_stride=False`` ignores the view's byteStride (sparse data is tightly packed).
        """
        buf, start, length, stride = self.buffer_view_bytes(view)
        if not use_stride:
            stride = None
        size = dtype.itemsize
        if len(shape) == 2:  # matrices: column-major, each column aligned to 4 bytes
            cols, rows = shape[1], shape[0]
            col_stride = -(-rows * size // 4) * 4
            elem_size = col_stride * cols
            inner_shape, inner_strides = (cols, rows), (col_stride, size)
        else:
            elem_size = size * shape[0]
            inner_shape, inner_strides = shape, (size,)
        stride = int(stride) if stride else elem_size
        if stride < elem_size:
            raise GltfError(f"{self.path}: {what}: byteStride {stride} is smaller than an element "
                            f"({elem_size} bytes)")
        if count == 0:
            return np.zeros((0, *shape), dtype=dtype)
        needed = byte_offset + (count - 1) * stride + elem_size
        if needed > length:
            raise GltfError(f"{self.path}: {what} needs {needed} bytes of bufferView {view}, "
                            f"which has {length}")
        arr = np.ndarray((count, *inner_shape), dtype=dtype, buffer=buf, offset=start + byte_offset,
                         strides=(stride, *inner_strides))
        arr = np.array(arr)  # own, aligned copy
        if len(shape) == 2:
            arr = np.swapaxes(arr, 1, 2)  # column-major storage -> [row, col]
        return arr

    def accessor(self, index: int) -> np.ndarray:
        """Decoded accessor: float64 for float or normalized data, int64 otherwise.

        Shape (count,) for SCALAR, (count, n) for VECn, (count, n, n) for MATn ([row, col]).
        """
        if index in self._cache:
            return self._cache[index]
        acc = self.get("accessors", index)
        what = f"accessor {index}" + (f" ({acc['name']!r})" if "name" in acc else "")
        ctype, atype = acc.get("componentType"), acc.get("type")
        if ctype not in _COMPONENT_DTYPES:
            raise GltfError(f"{self.path}: {what} has unknown componentType {ctype!r}")
        if atype not in _TYPE_SHAPES:
            raise GltfError(f"{self.path}: {what} has unknown type {atype!r}")
        dtype, shape, count = _COMPONENT_DTYPES[ctype], _TYPE_SHAPES[atype], int(acc["count"])
        if "bufferView" in acc:
            data = self._strided(acc["bufferView"], int(acc.get("byteOffset", 0)), count, dtype,
                                 shape, what)
        else:
            data = np.zeros((count, *shape), dtype=dtype)
        sparse = acc.get("sparse")
        if sparse:
            n = int(sparse["count"])
            ind, val = sparse["indices"], sparse["values"]
            idt = _COMPONENT_DTYPES.get(ind.get("componentType"))
            if idt is None or idt.kind != "u":
                raise GltfError(f"{self.path}: {what}: sparse indices need an unsigned componentType")
            idx = self._strided(ind["bufferView"], int(ind.get("byteOffset", 0)), n, idt, (1,),
                                what + " sparse indices", use_stride=False)[:, 0].astype(np.int64)
            if n and (idx.min() < 0 or idx.max() >= count):
                raise GltfError(f"{self.path}: {what}: sparse index out of range [0, {count})")
            vals = self._strided(val["bufferView"], int(val.get("byteOffset", 0)), n, dtype, shape,
                                 what + " sparse values", use_stride=False)
            data = data.copy()
            data[idx] = vals
        if acc.get("normalized", False):
            if ctype == 5126:
                raise GltfError(f"{self.path}: {what}: float accessors cannot be normalized")
            info = np.iinfo(dtype)
            out = data.astype(np.float64) / float(info.max)
            if info.min < 0:
                out = np.maximum(out, -1.0)
        elif ctype == 5126:
            out = data.astype(np.float64)
        else:
            out = data.astype(np.int64)
        if shape == (1,):
            out = out[:, 0]
        out.setflags(write=False)
        self._cache[index] = out
        return out

    def image(self, index: int) -> np.ndarray:
        """Image ``index`` as (H, W, 3) uint8 RGB (alpha dropped)."""
        img = self.get("images", index)
        what = f"image {index}" + (f" ({img['name']!r})" if "name" in img else "")
        if "uri" in img:
            data = _read_uri(img["uri"], what, self.path)
        elif "bufferView" in img:
            buf, start, length, _ = self.buffer_view_bytes(img["bufferView"])
            data = buf[start:start + length]
        else:
            raise GltfError(f"{self.path}: {what} has neither uri nor bufferView")
        try:
            with Image.open(io.BytesIO(data)) as im:
                rgb = np.asarray(im.convert("RGB"), dtype=np.uint8)
        except Exception as exc:  # Pillow raises several types for undecodable data
            raise GltfError(f"{self.path}: cannot decode {what} "
                            f"({img.get('mimeType', 'unknown type')}): {exc}") from exc
        return np.ascontiguousarray(rgb)
