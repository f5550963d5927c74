"""The viewer's inputs, read and checked on the host: glTF files (embedded as they are, with what the page will show
collected for its state), mesh sequences (.npy, .vtu, arrays) and static meshes. Every bad input is a ``ValueError``
naming the argument or the file."""

from __future__ import annotations

import json
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from _jaxcga_shared.mesh import tet_boundary_faces

GLTF_SUFFIXES = (".glb", ".gltf")
SEQUENCE_SUFFIXES = (".npy", ".vtu")
_TRIANGLES = 4  # glTF primitive mode
_FRAME_FILE = re.compile(r"frame_(\d+)\.vtu")
_UNDECODED = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_texture_basisu"}


@dataclass
class Gltf:
    """A glTF to show as it is: its bytes (a .glb, or a .gltf with every buffer and image embedded) and what the
    page must report for it."""

    name: str
    source: str
    data: bytes
    vertex_count: int
    triangle_count: int
    skinned: bool
    clips: list[dict]  # {"name", "duration"}
    joints: list[list[str]]  # each skin's joints' node names, in skin order


@dataclass
class Sequence:
    """Frames of vertex positions: ``segments`` of consecutive frames that share one triangle list F (one segment
    unless the topology changes, as when XFEM pieces break apart); a static mesh is one frame."""

    name: str
    source: str
    segments: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (F (m, 3), frames (t, n, 3))
    # none, or one (n,) int array per segment: each vertex's group (a piece), drawn in its own colour
    groups: list[np.ndarray] = field(default_factory=list)

    @property
    def frame_count(self) -> int:
        return sum(len(frames) for _, frames in self.segments)


def _glb_json(data: bytes, what: str) -> tuple[dict, bytes]:
    import pygltflib

    if len(data) < 12 or data[:4] != b"glTF":
        raise ValueError(f"{what}: not a glTF binary (no glTF header)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise ValueError(f"{what}: a glTF binary of version {version}; only version 2 is read")
    if length > len(data):
        raise ValueError(f"{what}: truncated: {len(data)} of the {length} bytes its header states")
    try:
        gltf = pygltflib.GLTF2.load_from_bytes(data)
    except Exception as error:  # noqa: BLE001 (pygltflib raises anything from struct.error to KeyError)
        raise ValueError(f"{what}: not a readable glTF binary ({type(error).__name__}: {error})") from None
    if gltf is None or gltf.asset is None:
        raise ValueError(f"{what}: not a readable glTF binary")
    blob = gltf.binary_blob() or b""
    document = json.loads(gltf.gltf_to_json())
    for buffer in document.get("buffers", [])[:1]:
        if "uri" not in buffer and len(blob) < buffer.get("byteLength", 0):
            raise ValueError(f"{what}: truncated: its buffer holds {len(blob)} of {buffer['byteLength']} bytes")
    return document, blob


def _buffer_files(document: dict, folder: Path, what: str) -> None:
    """Every buffer a glTF refers to by a file name exists beside it (``deform.load_model`` refuses it otherwise;
    the page would show nothing)."""
    from urllib.parse import unquote

    for k, buffer in enumerate(document.get("buffers", [])):
        uri = buffer.get("uri")
        if uri is not None and not uri.startswith("data:") and not (folder / unquote(uri)).is_file():
            raise ValueError(f"{what}: buffer {k} refers to {uri!r}, no such file {folder / unquote(uri)}")


_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT = 5126  # glTF componentType


def _finite_data(document: dict, blob: bytes, what: str) -> None:
    """Every float accessor and node transform of a glTF is finite, as ``deform.load_model`` checks (three.js
    draws nothing, silently, where a position is NaN)."""
    import base64

    def buffer(index: int) -> bytes:
        uri = document["buffers"][index].get("uri")
        if uri is None:
            return blob
        if uri.startswith("data:"):
            return base64.b64decode(uri.split(",", 1)[1])
        return b""  # a file beside a .glb (rare): checked to exist, its values left to three.js

    cache: dict[int, bytes] = {}
    for k, accessor in enumerate(document.get("accessors", [])):
        if accessor.get("componentType") != _FLOAT or accessor.get("bufferView") is None:
            continue
        view = document["bufferViews"][accessor["bufferView"]]
        if view["buffer"] not in cache:
            cache[view["buffer"]] = buffer(view["buffer"])
        data = cache[view["buffer"]]
        width = _COMPONENTS[accessor["type"]]
        count, stride = accessor["count"], view.get("byteStride") or 4 * width
        offset = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
        if not data or count == 0:
            continue
        if offset + (count - 1) * stride + 4 * width > len(data):
            raise ValueError(f"{what}: accessor {k} reaches past the end of its buffer ({len(data)} bytes)")
        values = np.ndarray((count, width), "<f4", buffer=data, offset=offset, strides=(stride, 4))
        bad = int((~np.isfinite(values)).sum())
        if bad:
            raise ValueError(
                f"{what}: accessor {k} ({_accessor_use(document, k)}) holds {bad} non-finite values (NaN or "
                f"infinity) of {values.size}; the page would show nothing"
            )
    for k, node in enumerate(document.get("nodes", [])):
        for key in ("matrix", "translation", "rotation", "scale"):
            if key in node and not np.isfinite(np.asarray(node[key], np.float64)).all():
                raise ValueError(f"{what}: node {k}'s {key} holds a NaN or infinity")


def _accessor_use(document: dict, index: int) -> str:
    """What a glTF uses accessor ``index`` for, in words (the first use found)."""
    for m, mesh in enumerate(document.get("meshes", [])):
        for p, primitive in enumerate(mesh.get("primitives", [])):
            for name, a in primitive.get("attributes", {}).items():
                if a == index:
                    return f"mesh {m} primitive {p} {name}"
    for s, skin in enumerate(document.get("skins", [])):
        if skin.get("inverseBindMatrices") == index:
            return f"skin {s}'s inverse bind matrices"
    for a, animation in enumerate(document.get("animations", [])):
        for sampler in animation.get("samplers", []):
            if index in (sampler.get("input"), sampler.get("output")):
                return f"animation {a}'s keys"
    return "unused"


def _embedded_gltf(path: Path, what: str) -> tuple[dict, bytes]:
    """A .gltf with its buffers and images turned into data URIs, as JSON bytes the page's loader reads."""
    import pygltflib

    try:
        gltf = pygltflib.GLTF2().load_json(str(path))
    except Exception as error:  # noqa: BLE001 (a malformed file fails anywhere inside pygltflib)
        raise ValueError(f"{what}: not a readable glTF file ({type(error).__name__}: {error})") from None
    _buffer_files(json.loads(gltf.gltf_to_json()), path.parent, what)
    try:
        with warnings.catch_warnings():  # "the .bin file is left orphaned": it is left as it is, unused
            warnings.simplefilter("ignore", UserWarning)
            gltf.convert_buffers(pygltflib.BufferFormat.DATAURI)
            gltf.convert_images(pygltflib.ImageFormat.DATAURI, path=str(path.parent))
        text = gltf.gltf_to_json()
    except Exception as error:  # noqa: BLE001 (a malformed file fails anywhere inside pygltflib)
        raise ValueError(f"{what}: not a readable glTF file ({type(error).__name__}: {error})") from None
    return json.loads(text), text.encode("utf-8")


def read_gltf(data: bytes | None, path: Path | None, name: str, what: str) -> Gltf:
    """A glTF from ``path`` (.glb or .gltf) or from glb ``data``, checked: readable, and at least one triangle mesh
    in its scene."""
    what = f"{what}: {path}" if path is not None else what
    if data is None:
        assert path is not None
        try:
            data = path.read_bytes()
        except OSError as error:
            raise ValueError(f"{what}: cannot read it ({error.strerror})") from None
        if path.suffix.lower() == ".gltf" and data[:4] != b"glTF":
            document, data = _embedded_gltf(path, what)
            blob = b""
        else:
            document, blob = _glb_json(data, what)
            _buffer_files(document, path.parent, what)
    else:
        document, blob = _glb_json(data, what)
    # three.js's loader decodes these only with decoders the page does not carry
    undecoded = sorted(set(document.get("extensionsRequired", [])) & _UNDECODED)
    if undecoded:
        raise ValueError(f"{what}: needs {', '.join(undecoded)}, which the viewer does not decode")
    nodes = document.get("nodes", [])
    meshes = document.get("meshes", [])
    accessors = document.get("accessors", [])
    scenes = document.get("scenes", [])
    roots = scenes[document.get("scene", 0)].get("nodes", []) if scenes else range(len(nodes))
    vertices = triangles = 0
    skinned = False
    try:
        stack = list(roots)
        while stack:
            node = nodes[stack.pop()]
            stack.extend(node.get("children", []))
            if "mesh" not in node:
                continue
            skinned |= "skin" in node
            for primitive in meshes[node["mesh"]]["primitives"]:
                if primitive.get("mode", _TRIANGLES) != _TRIANGLES or "POSITION" not in primitive["attributes"]:
                    continue
                count = accessors[primitive["attributes"]["POSITION"]]["count"]
                vertices += count
                indices = primitive.get("indices")
                triangles += (accessors[indices]["count"] if indices is not None else count) // 3
        clips = []
        for k, animation in enumerate(document.get("animations", [])):
            inputs = [accessors[animation["samplers"][c["sampler"]]["input"]] for c in animation["channels"]]
            ends = [a["max"][0] for a in inputs if a.get("max")]
            # three.js's GLTFLoader names an unnamed animation so
            clips.append({"name": animation.get("name") or f"animation_{k}", "duration": max(ends) if ends else None})
        joints = [[nodes[j].get("name", f"node_{j}") for j in skin["joints"]] for skin in document.get("skins", [])]
        _finite_data(document, blob, what)
    except (KeyError, IndexError, TypeError) as error:
        raise ValueError(f"{what}: a malformed glTF (a missing or out-of-range {error})") from None
    if not vertices:
        raise ValueError(f"{what}: holds no triangle mesh to show")
    source = str(path) if path is not None else name
    return Gltf(name, source, data, vertices, triangles, skinned, clips, joints)


def _positions(V, what: str, frames: bool) -> np.ndarray:
    """Float64 positions (n, 3), or (t, n, 3) frames when ``frames``, all finite."""
    V = np.asarray(V)
    if V.dtype.kind not in "fiu":
        raise ValueError(f"{what}: expected numbers, got dtype {V.dtype}")
    shape = "(t, n, 3)" if frames else "(n, 3)"
    if V.ndim != (3 if frames else 2) or V.shape[-1] != 3 or V.shape[-2] == 0 or (frames and not len(V)):
        raise ValueError(f"{what}: expected positions of shape {shape}, got {V.shape}")
    V = V.astype(np.float64)
    if not np.isfinite(V).all():
        bad = np.argwhere(~np.isfinite(V).all(axis=-1))[0]
        raise ValueError(f"{what}: non-finite position at index {tuple(int(i) for i in bad)}")
    return V


def _faces(F, n: int, what: str) -> np.ndarray:
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3 or not len(F) or F.dtype.kind not in "iu":
        raise ValueError(f"{what}: expected integer triangles of shape (m, 3), got {F.dtype} {F.shape}")
    if F.min() < 0 or F.max() >= n:
        raise ValueError(f"{what}: a triangle index outside [0, {n}) (the vertices given)")
    return F.astype(np.int64)


def read_topology(mesh, n: int, frames: str, what: str = "mesh") -> np.ndarray:
    """The triangles F of ``mesh`` (a mesh file, or a (V, F) pair) for frames of ``n`` vertices: the file as it is,
    or welded as the command line's ``deform``/``arap`` read it, whichever has ``n`` vertices (those of the
    ``frames``, named in messages)."""
    from _jaxcga_shared.meshfile import read_mesh_file

    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        V = _positions(mesh[0], f"{what}[0]", frames=False)
        F = _faces(mesh[1], len(V), f"{what}[1]")
        if len(V) != n:
            raise ValueError(f"{what}: {len(V)} vertices, but the frames {frames} have {n}")
        return F
    if not isinstance(mesh, (str, os.PathLike)):
        raise ValueError(f"{what}: expected a mesh file or a (V, F) pair, got a {type(mesh).__name__}")
    counts = []
    for weld in (False, True):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            V, F = read_mesh_file(os.fspath(mesh), what, weld=weld)
        if len(V) == n:
            return F
        counts.append(len(V))
    raise ValueError(
        f"{what}: {mesh} has {counts[0]} vertices ({counts[1]} welded), but the frames {frames} have {n}; give the "
        "mesh the frames were computed on"
    )


def read_npy(paths: list[Path], mesh, what: str) -> Sequence:
    """One sequence from .npy files: one (t, n, 3) file, or several (n, 3) files, one per frame."""
    frames = []
    for path in paths:
        from _jaxcga_shared.meshfile import read_array_file

        try:
            array = read_array_file(path, what)
        except OSError as error:
            raise ValueError(f"{what}: cannot read {path} as .npy ({error})") from None
        if len(paths) == 1 and array.ndim == 3:
            frames.append(_positions(array, f"{what}: {path}", frames=True))
        else:
            frames.append(_positions(array, f"{what}: {path}", frames=False)[None])
    if len({f.shape[1] for f in frames}) > 1:
        raise ValueError(f"{what}: the frames {[str(p) for p in paths]} have different vertex counts")
    source = ", ".join(str(p) for p in paths)
    if mesh is None:
        raise ValueError(
            f"{what}: {source}: .npy frames hold positions only; give the mesh they belong to (mesh= / --mesh)"
        )
    stacked = np.concatenate(frames)
    F = read_topology(mesh, stacked.shape[1], source)
    name = paths[0].name if len(paths) == 1 else f"{paths[0].name} .. {paths[-1].name}"
    return Sequence(name, source, [(F, stacked)])


def vtu_files(path: Path, what: str) -> list[Path]:
    """The frame_XXXX.vtu files of a folder in frame order (a number, not a string, order)."""
    found = [(int(m.group(1)), p) for p in path.iterdir() if (m := _FRAME_FILE.fullmatch(p.name))]
    if not found:
        raise ValueError(f"{what}: the folder {path} holds no frame_XXXX.vtu files")
    return [p for _, p in sorted(found)]


def _vtu_triangles(path: Path, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Positions and surface triangles of one .vtu: its triangles, and the boundary faces of its tetrahedra (faces
    of one tet only, oriented outward as the tet's vertex order gives)."""
    import meshio

    try:
        mesh = meshio.read(path)
    # meshio raises SystemExit on a file it cannot parse
    except (meshio.ReadError, OSError, KeyError, ValueError, SystemExit) as error:
        raise ValueError(f"{what}: meshio cannot read {path} ({error})") from None
    points = np.asarray(mesh.points, np.float64)
    if points.ndim == 2 and points.shape[1] == 2:
        points = np.concatenate([points, np.zeros((len(points), 1))], axis=1)
    points = _positions(points, f"{what}: {path}", frames=False)
    faces = []
    for block in mesh.cells:
        if block.type == "triangle":
            faces.append(block.data)
        elif block.type == "tetra":
            try:
                faces.append(tet_boundary_faces(np.asarray(block.data, np.int64)))
            except ValueError as error:
                raise ValueError(f"{what}: {path}: {error}") from None
    if not faces or not sum(len(f) for f in faces):
        raise ValueError(f"{what}: {path} holds no triangles or tetrahedra to show")
    return points, _faces(np.concatenate(faces), len(points), f"{what}: {path}")


def _welded(F: np.ndarray, frames: np.ndarray, groups: np.ndarray | None = None):
    """The segment with the vertices that coincide in every frame (and are in one group) merged, in the order they
    first appear: XFEM writes each triangle with its own three vertices, six times the data the page needs.
    Returns (F, frames, groups)."""
    t, n, _ = frames.shape
    key = frames.transpose(1, 0, 2).reshape(n, 3 * t)
    if groups is not None:
        key = np.concatenate([key, groups[:, None].astype(np.float64)], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    if len(first) == n:
        return F, frames, groups
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inverse.ravel()][F], frames[:, first[order]], None if groups is None else groups[first[order]]


def _segments(meshes) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """(F, frames) segments of consecutive (V, F) or (V, F, vertex groups) frames, and the segments' vertex groups
    (empty without groups): frames with the same triangles (and groups) share a segment, whose vertices that
    coincide in all its frames are merged (``_welded``)."""
    runs: list[tuple[np.ndarray, list[np.ndarray], np.ndarray | None]] = []
    for V, F, *rest in meshes:
        groups = rest[0] if rest else None
        last = runs[-1] if runs else None
        if (
            last is not None
            and last[0].shape == F.shape
            and (last[0] == F).all()
            and len(last[1][0]) == len(V)
            and (groups is None or (last[2] == groups).all())
        ):
            last[1].append(V)
        else:
            runs.append((F, [V], groups))
    welded = [_welded(F, np.stack(frames), groups) for F, frames, groups in runs]
    return [(F, frames) for F, frames, _ in welded], [g for _, _, g in welded if g is not None]


def read_vtu(paths: list[Path], what: str) -> Sequence:
    """One sequence from .vtu frames; consecutive frames with the same triangles share a segment."""
    folder = paths[0].parent
    name = folder.name if len(paths) > 1 else paths[0].name
    source = str(folder) if len(paths) > 1 else str(paths[0])
    return Sequence(name, source, _segments(_vtu_triangles(path, what) for path in paths)[0])


def _vertex_groups(F: np.ndarray, face_groups, n: int, what: str) -> np.ndarray:
    """(n,) the group of each vertex: that of the first triangle using it (0 for a vertex no triangle uses)."""
    face_groups = np.asarray(face_groups)
    if face_groups.shape != (len(F),) or face_groups.dtype.kind not in "iu" or (face_groups < 0).any():
        raise ValueError(
            f"{what}: expected one integer group >= 0 per triangle, shape ({len(F)},), got {face_groups.dtype} "
            f"{face_groups.shape}"
        )
    groups = np.zeros(n, np.int64)
    groups[F[::-1].ravel()] = np.repeat(face_groups[::-1], 3)  # the first triangle's assignment is written last
    return groups


def read_frame_meshes(item, name: str, what: str) -> Sequence:
    """A sequence from a list of (V, F) pairs, one per frame, whose triangles may change (pieces breaking apart),
    or of (V, F, groups) triples (groups (m,) int >= 0 per triangle, e.g. the pieces of a cut body: each vertex
    drawn in the colour of the first triangle's group that uses it)."""
    meshes = []
    arity = len(item[0]) if isinstance(item[0], (tuple, list)) and len(item[0]) in (2, 3) else 2
    kind = "(V, F) pair" if arity == 2 else "(V, F, groups) triple"
    for k, entry in enumerate(item):
        if not isinstance(entry, (tuple, list)) or len(entry) != arity:
            raise ValueError(f"{what}[{k}]: expected a {kind}, like the frames before it")
        V = _positions(entry[0], f"{what}[{k}][0]", frames=False)
        F = _faces(entry[1], len(V), f"{what}[{k}][1]")
        meshes.append((V, F) if arity == 2 else (V, F, _vertex_groups(F, entry[2], len(V), f"{what}[{k}][2]")))
    segments, groups = _segments(meshes)
    return Sequence(name, "arrays", segments, groups)


def read_arrays(item, name: str, what: str) -> Sequence:
    """A (V, F) pair (a static mesh), a (frames, F) pair (a sequence of one topology) of numpy or JAX arrays, or a
    list of (V, F) pairs or (V, F, groups) triples (one per frame)."""
    if len(item) and isinstance(item[0], (tuple, list)):
        return read_frame_meshes(item, name, what)
    if len(item) != 2:
        raise ValueError(
            f"{what}: expected a (V, F) or (frames, F) pair, or a list of (V, F) pairs, got a sequence of "
            f"{len(item)} items"
        )
    V = np.asarray(item[0])
    V = _positions(V, f"{what}[0]", frames=V.ndim == 3)
    frames = V if V.ndim == 3 else V[None]
    F = _faces(item[1], frames.shape[1], f"{what}[1]")
    return Sequence(name, "arrays", [(F, frames)])


def input_path(item, what: str) -> Path:
    """``item`` as an existing input path, with a suffix the viewer reads (or a folder of frame_XXXX.vtu)."""
    path = Path(os.fspath(item))
    if not path.exists():
        raise ValueError(f"{what}: no such file or folder {path}")
    if path.is_dir():
        return path
    if path.suffix.lower() not in GLTF_SUFFIXES + SEQUENCE_SUFFIXES:
        raise ValueError(
            f"{what}: {path}: cannot show a {path.suffix or 'suffix-less'} file; expected .glb, .gltf, .npy, .vtu "
            "or a folder of frame_XXXX.vtu"
        )
    return path
