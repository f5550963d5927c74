"""The browser viewer: one self-contained HTML page (three.js r187 inlined, every model and frame embedded; no
network at view time) that shows skinned glTF files with their clips, mesh sequences and static meshes side by
side, with play / pause / scrub / speed / loop, a clip selector, orbit and zoom, reset view, wireframe, the
skeleton and the skin weights of a joint. ``deform.view`` and ``jaxcga view`` build it; notebooks show it inline
(``View._repr_html_``: an iframe of the same page).

Inputs, side by side along x in the order given (each by its bounding box):

* a glTF (.glb, or .gltf with its buffers and images embedded on reading), or an object with ``to_glb() ->
  bytes`` (``deform.RiggedModel``): embedded as it is and played by three.js's ``GLTFLoader`` and
  ``AnimationMixer`` (skinning on the GPU), an implementation of glTF independent of ``deform``'s;
* a mesh sequence: a .npy of frames (t, n, 3), or consecutive .npy files of (n, 3) (one frame each), with the
  triangles from ``mesh`` (a mesh file, or a (V, F) pair); a .vtu file or a folder of ``frame_XXXX.vtu`` (the runs
  of ``jaxcga fem``/``xfem``: triangles as they are, tetrahedra by their boundary faces); a (frames, F) pair of
  arrays, or a list of (V, F) pairs, one per frame (its triangles may change; in .vtu frames and such lists, the
  vertices that coincide in every frame of one topology are merged); a list of (V, F, groups) triples, groups (m,)
  int per triangle (the pieces of a cut body), draws each group in its own colour. Frames are stored as int16
  positions quantized in one bounding box of all frames (error at most diag / 131068), base64 in the page; between
  two frames the page interpolates linearly, and where the triangles change (XFEM pieces breaking apart) it
  switches mesh at the frame. Drawn with flat shading;
* a static mesh: a (V, F) pair.

The page's state, for tests and scripts, is ``window.jaxcgaViewer``::

    ready: bool                      every input decoded and drawn once
    errors: [str]                    every failure (also shown in a red box on the page; window.onerror and
                                     unhandled rejections included): a page never fails silently
    meshes: [{name, kind, vertexCount, triangleCount, source, offset}]   one per input; kind "skinned",
                                     "sequence" or "static"; offset: its x/y/z shift in the side-by-side layout;
                                     counts from three.js's geometry (a sequence's: at the current frame)
    clips: [{name, duration}]        the glTF clips by name (the same name plays in every input that has it), or
                                     one clip "frames" when the only motion is sequences
    clip, duration, time, frame      the clip index, the time span played (the longest of the clip and the
                                     sequences; a shorter one holds its end), the current time (s) and the frame
                                     of the first sequence at it (floor(time * sequenceFps), -1 without one)
    interpolation: "linear"          between the frames of a sequence
    playing, speed, loop, sequenceFps
    renderer, antialias              the WebGL renderer's name (e.g. SwiftShader's in headless Chromium) and whether
                                     the page multisamples (not on a software renderer)
    labels: [{name, x, y}]           each input's name, drawn under it: the label's anchor in CSS pixels of the
                                     drawing area (the middle of the bottom of the input's box, as projected)
    fps                              rendered frames per second over the last second
    rendered                         frames rendered since the page loaded
    frameChanges                     times the sequence frame shown (``frame``) changed since the page loaded
    decodeMs, loadMs                 milliseconds to read the embedded data (the config parsed, the blocks
                                     decoded, the geometries and glTF scenes built), and from the page's start
                                     (navigation) to ready
    updateMs                         milliseconds the last time step took on the page's thread (the glTF
                                     mixers, the sequences' positions decoded and interpolated), drawing excluded
    setTime(t), play(), pause(), setClip(i), setSpeed(s), setLoop(b), setWireframe(b), showSkeleton(b),
    showWeights(joint | null)        a joint name or index into the skin's joints; vertex colours blue (0) to
                                     red (1); returns the number of vertices with a weight > 0 on it
    resetView()
    vertexPositions(i) -> [x0, y0, z0, x1, ...]   input i's vertices as drawn at the current time, in the
                                     input's own world coordinates (the layout offset undone; a glTF's node
                                     transforms and skinning applied, its primitives in file order)
    boundingBox() -> {min: [3], max: [3]}          of the whole scene as drawn (layout included)
"""

from __future__ import annotations

import base64
import html
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from _jaxcga_shared.viewer._inputs import (
    GLTF_SUFFIXES,
    Gltf,
    Sequence,
    input_path,
    read_arrays,
    read_gltf,
    read_npy,
    read_vtu,
    vtu_files,
)

__all__ = ["View", "view"]

_HERE = Path(__file__).parent
_QUANTUM = 32767  # int16 positions: -32767..32767 across the bounding box of all frames
IFRAME_HEIGHT = 540


@dataclass(frozen=True)
class View:
    """A viewer page: ``html`` (one self-contained HTML file), with what was embedded (``meshes``: one
    ``{name, kind, vertexCount, triangleCount, source}`` per input; ``clips``: the glTF clips, ``{name,
    duration}``, with the durations that the files state) for checks. Renders inline in Jupyter
    (``_repr_html_``) and saves with ``save``."""

    html: str = field(repr=False)  # megabytes: the repr (a notebook's text/plain output) names the contents only
    title: str
    meshes: tuple[dict, ...]
    clips: tuple[dict, ...]

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write the page to ``path`` (.html), atomically (``_jaxcga_shared.output``); an existing file is replaced
        only with ``force``. Returns the path."""
        from _jaxcga_shared.output import check_output, write_bytes

        path = check_output(path, (".html", ".htm"), "path")
        if path.exists() and not force:
            raise ValueError(f"path: {path} exists; pass force=True (--force) to replace it")
        write_bytes(path, self.html)
        return path

    def _repr_html_(self) -> str:
        return (
            f'<iframe srcdoc="{html.escape(self.html, quote=True)}" title="{html.escape(self.title)}" '
            f'style="width: 100%; height: {IFRAME_HEIGHT}px; border: 1px solid #ccc" '
            'sandbox="allow-scripts"></iframe>'
        )


def _quantize(frames: np.ndarray, center: np.ndarray, half: np.ndarray) -> bytes:
    q = np.rint((frames - center) / half * _QUANTUM)
    return np.clip(q, -_QUANTUM, _QUANTUM).astype("<i2").tobytes()


def _sequence_json(sequence: Sequence, blocks: list[bytes], encoding: str) -> dict:
    """The page's description of a sequence; its arrays appended to ``blocks`` (referenced by index)."""
    every = np.concatenate([frames.reshape(-1, 3) for _, frames in sequence.segments])
    lo, hi = every.min(axis=0), every.max(axis=0)
    center = (lo + hi) / 2
    half = np.maximum((hi - lo) / 2, 1e-30 + 1e-12 * np.abs(hi - lo).max())  # a flat axis: any nonzero scale
    segments = []
    for k, (F, frames) in enumerate(sequence.segments):
        blocks.append(F.astype("<u4").tobytes())
        segment: dict = {"indices": len(blocks) - 1, "vertices": int(frames.shape[1]), "frames": int(len(frames))}
        if sequence.groups:
            blocks.append(sequence.groups[k].astype("<u4").tobytes())
            segment["groups"] = len(blocks) - 1
        if encoding == "json":  # the naive format, for the benchmark's baseline only
            segment["positions"] = frames.astype(np.float32).reshape(len(frames), -1).tolist()
        else:
            blocks.append(_quantize(frames, center, half))
            segment["positions"] = len(blocks) - 1
        segments.append(segment)
    return {
        "kind": "sequence",
        "name": sequence.name,
        "source": sequence.source,
        "center": center.tolist(),
        "half": half.tolist(),
        "quantum": _QUANTUM,
        "segments": segments,
    }


def _resolve_joint(joint, gltfs: list[Gltf]):
    """``joint`` (a name or an index into the skins' joints) checked against the glTF inputs."""
    if joint is None:
        return None
    skins = [names for g in gltfs for names in g.joints]
    if not skins:
        raise ValueError("joint: no input has a skin (a glTF with joints)")
    if isinstance(joint, (int, np.integer)) or (isinstance(joint, str) and joint.lstrip("-").isdigit()):
        index = int(joint)
        if not any(0 <= index < len(names) for names in skins):
            raise ValueError(f"joint: index {index} outside the skins' joints (at most {max(map(len, skins))})")
        return index
    if not any(joint in names for names in skins):
        known = sorted({n for names in skins for n in names})
        raise ValueError(
            f"joint: no joint called {joint!r}; joints are {known[:20]}{' ...' if len(known) > 20 else ''}"
        )
    return str(joint)


def _resolve_clip(clip, names: list[str]) -> int:
    if clip is None:
        return 0
    if isinstance(clip, (int, np.integer)) or (isinstance(clip, str) and clip.lstrip("-").isdigit()):
        index = int(clip)
        if not 0 <= index < max(len(names), 1):
            raise ValueError(f"clip: {len(names)} clips ({names}), no clip {index}")
        return index
    if clip not in names:
        raise ValueError(f"clip: no clip called {clip!r}; clips are {names}")
    return names.index(clip)


def _read_inputs(inputs: tuple, mesh) -> list[Gltf | Sequence]:
    """Every input read and checked; consecutive .npy files of single frames form one sequence."""
    items: list[Gltf | Sequence] = []
    pending: list[tuple[Path, str]] = []  # consecutive (n, 3) .npy files

    def flush():
        if pending:
            items.append(read_npy([p for p, _ in pending], mesh, pending[0][1]))
            pending.clear()

    for k, item in enumerate(inputs):
        what = f"inputs[{k}]"
        if isinstance(item, (str, os.PathLike)):
            path = input_path(item, what)
            suffix = path.suffix.lower()
            if suffix == ".npy" and not path.is_dir():
                shape = _npy_shape(path, what)
                if len(shape) == 2:
                    pending.append((path, what))
                    continue
                flush()
                items.append(read_npy([path], mesh, what))
                continue
            flush()
            if path.is_dir():
                items.append(read_vtu(vtu_files(path, what), what))
            elif suffix in GLTF_SUFFIXES:
                items.append(read_gltf(None, path, path.name, what))
            else:
                items.append(read_vtu([path], what))
            continue
        flush()
        if hasattr(item, "to_glb"):
            data = item.to_glb()
            if not isinstance(data, bytes):
                raise ValueError(f"{what}: to_glb() returned {type(data).__name__}, expected bytes")
            name = str(getattr(item, "name", None) or f"model {k}")
            items.append(read_gltf(data, None, name, what))
        elif isinstance(item, (tuple, list)):
            items.append(read_arrays(item, f"mesh {k}", what))
        else:
            raise ValueError(
                f"{what}: cannot show a {type(item).__name__}; expected a path, a (V, F) or (frames, F) pair, a "
                "list of (V, F) pairs, or an object with to_glb()"
            )
    flush()
    return items


def _npy_shape(path: Path, what: str) -> tuple[int, ...]:
    from _jaxcga_shared.meshfile import read_array_file

    try:
        return read_array_file(path, what, mmap=True).shape
    except OSError as error:
        raise ValueError(f"{what}: cannot read {path} as .npy ({error})") from None


def _template(name: str) -> str:
    return (_HERE / name).read_text(encoding="utf-8")


def page(
    items: list[Gltf | Sequence],
    *,
    joint: str | int | None = None,
    clip: str | int | None = None,
    fps: float = 30.0,
    title: str | None = None,
    encoding: str = "int16",
) -> View:
    """The page of read inputs (``view`` reads them); ``encoding="json"`` stores sequence frames as JSON arrays
    instead of int16 blocks, the naive format, for benchmarks/bench_viewer.py's baseline only."""
    if not items:
        raise ValueError("inputs: nothing to show; give at least one input")
    if encoding not in ("int16", "json"):
        raise ValueError(f"encoding: expected 'int16' or 'json', got {encoding!r}")
    if not (isinstance(fps, (int, float, np.integer, np.floating)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a positive frame rate, got {fps!r}")
    gltfs = [item for item in items if isinstance(item, Gltf)]
    clip_names: list[str] = []
    durations: dict[str, float | None] = {}
    for g in gltfs:
        for c in g.clips:
            if c["name"] not in durations:
                clip_names.append(c["name"])
                durations[c["name"]] = c["duration"]
            elif c["duration"] is not None:
                durations[c["name"]] = max(durations[c["name"]] or 0.0, c["duration"])
    joint = _resolve_joint(joint, gltfs)
    clip_index = _resolve_clip(clip, clip_names)
    title = title or ", ".join(item.name for item in items)

    blocks: list[bytes] = []
    described, meshes = [], []
    for item in items:
        if isinstance(item, Gltf):
            blocks.append(item.data)
            described.append({"kind": "gltf", "name": item.name, "source": item.source, "data": len(blocks) - 1})
            kind, vertices, triangles = (
                ("skinned" if item.skinned else "static"),
                item.vertex_count,
                item.triangle_count,
            )
        else:
            described.append(_sequence_json(item, blocks, encoding))
            F, frames = item.segments[0]
            kind = "sequence" if item.frame_count > 1 else "static"
            vertices, triangles = int(frames.shape[1]), len(F)
        meshes.append(
            {
                "name": item.name,
                "kind": kind,
                "vertexCount": vertices,
                "triangleCount": triangles,
                "source": item.source,
            }
        )
    config = {
        "title": title,
        "items": described,
        "sequenceFps": float(fps),
        "joint": joint,
        "clip": clip_index,
    }
    data_blocks = "\n".join(
        f'<script type="application/octet-stream" id="jaxcga-block-{k}">{base64.b64encode(b).decode("ascii")}</script>'
        for k, b in enumerate(blocks)
    )
    parts = {
        "TITLE": html.escape(title),
        "CONFIG": json.dumps(config).replace("<", "\\u003c"),  # no "</script>" or "<!--" inside the script
        "BLOCKS": data_blocks,
        "THREE": _template("vendor/three.bundle.min.js"),
        "PAGE": _template("page.js"),
    }
    # one pass: nothing inserted is scanned for placeholders again
    text = re.sub(r"@(TITLE|CONFIG|BLOCKS|THREE|PAGE)@", lambda m: parts[m.group(1)], _template("page.html"))
    clips = tuple({"name": n, "duration": durations[n]} for n in clip_names)
    return View(text, title, tuple(meshes), clips)


def view(
    *inputs,
    mesh: str | os.PathLike | tuple | None = None,
    joint: str | int | None = None,
    clip: str | int | None = None,
    fps: float = 30.0,
    title: str | None = None,
) -> View:
    """A viewer page of ``inputs``, side by side (module docstring).

    Args:
        *inputs (str | os.PathLike | tuple | list | object): paths (.glb, .gltf, .npy, .vtu, a folder of
            frame_XXXX.vtu), (V, F) or (frames, F) pairs of numpy or JAX arrays (V (n, 3), frames (t, n, 3), F
            (m, 3) integers), lists of (V, F) pairs (one per frame; the triangles may change between frames) or of
            (V, F, groups) triples (groups (m,) int >= 0 per triangle, e.g. pieces: a colour per group, a vertex
            taking the first group that uses it), objects with ``to_glb() -> bytes`` (a ``deform.RiggedModel``).
        mesh: the triangles of .npy frames: a mesh file (.obj, .ply, .stl, .off, .glb, ...; as it is, or welded
            as ``jaxcga deform`` reads it, whichever has the frames' vertex count) or a (V, F) pair.
        joint: show the skin weights of this joint (name, or index into a skin's joints); None: the materials.
        clip: the clip to play first (name or index); None: the first.
        fps: frame rate of the sequences (frames per second).
        title: the page's title; default: the inputs' names.

    Returns:
        A ``View``: ``.html``, ``.save(path)``, shown inline by Jupyter.

    Raises:
        ValueError: an input that cannot be shown (unknown suffix, a file that is no readable glTF, .npy or .vtu,
            a glTF without triangles, frames of the wrong shape or not matching the mesh's vertex count,
            non-finite positions, .npy frames without ``mesh``), an unknown joint or clip, a bad ``fps``; each
            naming the argument and the file.

    Examples:
        >>> import numpy as np
        >>> import deform
        >>> V = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
        >>> page = deform.view((V, np.array([[0, 1, 2]])), title="a triangle")
        >>> page.html.startswith("<!DOCTYPE html>"), page.title
        (True, 'a triangle')
    """
    return page(_read_inputs(inputs, mesh), joint=joint, clip=clip, fps=fps, title=title)
