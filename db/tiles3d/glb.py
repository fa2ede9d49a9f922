"""A minimal glTF 2.0 binary (GLB) writer and reader, numpy + struct.

In: numpy arrays and PNG bytes, added to a `GltfBuilder` (each becomes a buffer view of the one
binary buffer, 8-byte aligned: the alignment `EXT_structural_metadata` asks of property table
buffers, and more than any accessor needs). Out: the GLB bytes (`GltfBuilder.glb`: 12-byte
header, JSON chunk padded with spaces, BIN chunk padded with zeros, both to 8 bytes as
`EXT_structural_metadata` asks, within glTF 2.0's "GLB File Format Specification"). `read_glb`
splits a GLB back into its JSON and binary chunk, `accessor_array` reads an accessor back as
numpy (tests).

Written by hand rather than with a library: the content needs a few dozen lines of bookkeeping,
and the extensions (`EXT_mesh_features`, `EXT_structural_metadata`) are plain JSON here.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

__all__ = ["ARRAY_BUFFER", "ELEMENT_ARRAY_BUFFER", "GltfBuilder", "accessor_array", "read_glb"]

ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963
_COMPONENT = {np.dtype(np.float32): 5126, np.dtype(np.uint32): 5125, np.dtype(np.uint16): 5123,
              np.dtype(np.uint8): 5121}  # fmt: skip
_DTYPE = {v: k for k, v in _COMPONENT.items()}
_TYPE = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}
_WIDTH = {v: k for k, v in _TYPE.items()}
_MAGIC, _JSON, _BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


class GltfBuilder:
    """Collects a glTF document and its binary buffer; `glb()` packs both."""

    def __init__(self, generator: str = "citytherm") -> None:
        self.doc: dict[str, Any] = {"asset": {"version": "2.0", "generator": generator}}
        self.blob = bytearray()
        self._samplers: dict[tuple[int, int], int] = {}

    def _add(self, key: str, item: dict[str, Any]) -> int:
        items = self.doc.setdefault(key, [])
        items.append(item)
        return len(items) - 1

    def use_extension(self, name: str, required: bool = False) -> None:
        """Declare an extension in `extensionsUsed` (and `extensionsRequired`)."""
        for key in ("extensionsUsed", "extensionsRequired") if required else ("extensionsUsed",):
            names = self.doc.setdefault(key, [])
            if name not in names:
                names.append(name)

    def view(self, data: bytes, target: int | None = None, stride: int | None = None) -> int:
        """A buffer view over `data` (appended 8-byte aligned) -> its index."""
        self.blob.extend(b"\0" * (-len(self.blob) % 8))
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        if stride is not None:
            view["byteStride"] = stride
        self.blob.extend(data)
        return self._add("bufferViews", view)

    def accessor(self, array: np.ndarray, target: int | None = None, bounds: bool = False) -> int:
        """An accessor over a `(N,)` or `(N, k)` float32 / uint8 / uint16 / uint32 array -> its
        index; `bounds` writes `min` / `max` (required for POSITION)."""
        a = np.ascontiguousarray(array)
        width = 1 if a.ndim == 1 else a.shape[1]
        acc: dict[str, Any] = {
            "bufferView": self.view(a.tobytes(), target),
            "componentType": _COMPONENT[a.dtype],
            "count": int(a.shape[0]),
            "type": _TYPE[width],
        }
        if bounds and len(a):
            m = a.reshape(len(a), width)
            cast = float if a.dtype == np.float32 else int
            acc["min"] = [cast(v) for v in m.min(axis=0)]
            acc["max"] = [cast(v) for v in m.max(axis=0)]
        return self._add("accessors", acc)

    def image(self, png: bytes) -> int:
        """A PNG image stored in the buffer -> image index."""
        return self._add("images", {"bufferView": self.view(png), "mimeType": "image/png"})

    def sampler(self, mag: int, min_: int, wrap: int = 33071) -> int:
        """A sampler (`mag`, `min` filters; wrap default CLAMP_TO_EDGE), shared -> its index."""
        key = (mag, min_)
        if key not in self._samplers:
            self._samplers[key] = self._add(
                "samplers", {"magFilter": mag, "minFilter": min_, "wrapS": wrap, "wrapT": wrap}
            )
        return self._samplers[key]

    def texture(self, image: int, sampler: int) -> int:
        """A texture of `image` with `sampler` -> its index."""
        return self._add("textures", {"source": image, "sampler": sampler})

    def add(self, key: str, item: dict[str, Any]) -> int:
        """Append `item` to the top-level array `key` (meshes, materials, nodes) -> its index."""
        return self._add(key, item)

    def glb(self) -> bytes:
        """The GLB bytes of the document and buffer."""
        self.blob.extend(b"\0" * (-len(self.blob) % 8))
        doc = dict(self.doc)
        if self.blob:
            doc["buffers"] = [{"byteLength": len(self.blob)}]
        js = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
        js += b" " * (-len(js) % 8)
        total = 12 + 8 + len(js) + (8 + len(self.blob) if self.blob else 0)
        out = bytearray(struct.pack("<III", _MAGIC, 2, total))
        out += struct.pack("<II", len(js), _JSON) + js
        if self.blob:
            out += struct.pack("<II", len(self.blob), _BIN) + self.blob
        return bytes(out)


def read_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    """GLB bytes -> (the glTF JSON, the BIN chunk). Raises `ValueError` on a malformed header."""
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _MAGIC or version != 2 or length != len(data):
        raise ValueError("not a glTF 2.0 binary")
    n, kind = struct.unpack_from("<II", data, 12)
    if kind != _JSON:
        raise ValueError("first GLB chunk is not JSON")
    doc = json.loads(data[20 : 20 + n])
    pos = 20 + n
    blob = b""
    if pos < len(data):
        m, kind = struct.unpack_from("<II", data, pos)
        blob = data[pos + 8 : pos + 8 + m] if kind == _BIN else b""
    return doc, blob


def accessor_array(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    """Accessor `index` of a GLB read by `read_glb` as a numpy array `(N,)` or `(N, k)`
    (tightly packed views only, as `GltfBuilder` writes them)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = _DTYPE[acc["componentType"]]
    width = _WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(blob, dtype=dtype, count=acc["count"] * width, offset=start)
    return a if width == 1 else a.reshape(-1, width)


def view_bytes(doc: dict[str, Any], blob: bytes, index: int) -> bytes:
    """The bytes of buffer view `index` of a GLB read by `read_glb`."""
    view = doc["bufferViews"][index]
    start = view.get("byteOffset", 0)
    return blob[start : start + view["byteLength"]]
