"""glTF 2.0 binary data (the specification's "Binary Data Storage" and "GLB File Format Specification"): one buffer
of accessors, packed into a .glb. ``deform``'s model writer and the command line's mesh outputs share it; host-side
numpy."""

from __future__ import annotations

import json
import struct

import numpy as np

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
FLOAT, UINT, USHORT = 5126, 5125, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


class BufferWriter:
    """Accumulates one binary buffer and the bufferViews / accessors that describe it."""

    def __init__(self):
        self.chunks, self.size, self.views, self.accessors = [], 0, [], []

    def accessor(self, data: np.ndarray, kind: str, target: int | None = None, bounds: bool = False) -> int:
        data = np.ascontiguousarray(data)
        ctype = {np.dtype("<f4"): FLOAT, np.dtype("<u4"): UINT, np.dtype("<u2"): USHORT}[data.dtype]
        raw = data.tobytes()
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.chunks.append(raw + b"\0" * (-len(raw) % 4))  # every view starts 4-byte aligned
        self.size += len(self.chunks[-1])
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": ctype, "count": len(data), "type": kind}
        if bounds:
            flat = data.reshape(len(data), -1)
            acc["min"], acc["max"] = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.chunks)


def glb_bytes(doc: dict, blob: bytes) -> bytes:
    """The .glb of a glTF JSON ``doc`` whose buffer 0 is ``blob``: the header, the JSON chunk (padded with spaces)
    and the binary chunk."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (
        struct.pack("<4sII", GLB_MAGIC, 2, total)
        + struct.pack("<II", len(text), CHUNK_JSON)
        + text
        + struct.pack("<II", len(blob), CHUNK_BIN)
        + blob
    )


def mesh_glb(V, F, name: str = "mesh") -> bytes:
    """A .glb of one triangle mesh: float32 POSITION with its bounds, UNSIGNED_INT indices, one node at the scene
    root. ``V`` (n, 3) finite, ``F`` (m, 3) indices into it (checked)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise ValueError(f"positions: expected finite (n, 3) positions, got {V.dtype} {V.shape}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"faces: indices must be in [0, {len(V)})")
    writer = BufferWriter()
    position = writer.accessor(V.astype("<f4"), "VEC3", ARRAY_BUFFER, bounds=True)
    indices = writer.accessor(F.reshape(-1).astype("<u4"), "SCALAR", ELEMENT_ARRAY_BUFFER)
    blob = writer.blob()
    doc = {
        "asset": {"version": "2.0", "generator": "jaxcga"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0}],
        "meshes": [
            {"name": name, "primitives": [{"attributes": {"POSITION": position}, "indices": indices, "mode": 4}]}
        ],
        "accessors": writer.accessors,
        "bufferViews": writer.views,
        "buffers": [{"byteLength": len(blob)}],
    }
    return glb_bytes(doc, blob)
