"""Helpers shared by the test packages: a flat grid mesh, a closed tube mesh, a character of many connected parts, the
corpus of public rigged characters, a finite-difference gradient check, the comparison of two runs of one computation
(bitwise on the CPU), a script run on forced host devices, a glTF file read by pygltflib, the skips of tests that
need the host or the CPU formulations and the GPU formulations taken on the CPU (conftest.py), and the operations of
a program lowered for another platform."""

from __future__ import annotations

import collections
import functools
import importlib
import json
import pkgutil
import re
import struct
from pathlib import Path
from typing import TypeVar

import numpy as np
import pygltflib
import pytest
import trimesh

T = TypeVar("T")


def given(value: T | None) -> T:
    """A glTF field the file must give (pygltflib types every field as optional)."""
    assert value is not None, "the file lacks a field it must give"
    return value


def import_library() -> None:
    """Import every module of the library packages: a registry filled as modules load (the per-platform kernels)
    is then whole, though the packages import their modules on first use of a name (``_jaxcga_shared.lazy``)."""
    for package in ("_jaxcga_shared", "jaxcga", "deform", "cutting", "xfem"):
        root = importlib.import_module(package)
        for module in pkgutil.walk_packages(root.__path__, prefix=f"{package}."):
            if not module.name.endswith("_worker"):  # a subprocess's entry point
                importlib.import_module(module.name)


def read_gltf(path: str | Path) -> pygltflib.GLTF2:
    """The glTF file at ``path`` as pygltflib reads it (an independent reader of the format)."""
    gltf = pygltflib.GLTF2().load(str(path))
    if gltf is None:
        raise ValueError(f"path: pygltflib cannot read {path}")
    return gltf


def grid(n: int = 10):
    """The unit square in z = 0 as an n x n grid of quads, two triangles each."""
    x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    V = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def tube(max_edge: float = 0.1):
    """(V, F, start, end): a closed cylinder of radius 0.2 along z in [-1, 1], subdivided so it has rings along
    z, and the indices of its vertices on the bottom (start) and top (end) caps."""
    mesh = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=16)
    V, F = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)[:2]
    mesh = trimesh.Trimesh(V, F)
    mesh.merge_vertices()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    return V, F, np.flatnonzero(V[:, 2] < -1 + 1e-9), np.flatnonzero(V[:, 2] > 1 - 1e-9)


@functools.cache
def multipart_character() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(V, F, parts): CesiumMan's welded bind-pose mesh (one part, standing along +y, facing +z) with the parts a
    real character brings, and ``parts`` naming their vertex indices: ``body`` (CesiumMan), ``eyes`` (two
    spheres sunk into the face: attached), ``inner`` (a closed tube inside the torso: detached), ``nested`` (a
    sphere inside ``inner``: nearest only to it, a chain), ``isolated`` (two vertices on no face beside the right
    hand, the second nearest only to the first) and ``tiny`` (a triangle of edge 1e-4 above the head); ``feet``
    (y < 0.05) and ``crown`` (y > 1.45) are handle candidates on the body. Cached: do not modify the arrays."""
    import deform

    mesh = deform.load_model(DATA / "CesiumMan.glb", weld=True).mesh
    body_V, body_F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    pieces: list[tuple[np.ndarray, np.ndarray] | trimesh.Trimesh] = [(body_V, body_F)]
    names = ["body"]
    y = body_V[:, 1]
    head = body_V[(y > 1.35) & (np.abs(body_V[:, 0]) < 0.1)]
    face = head[np.argmax(head[:, 2])]  # the front of the head
    eye = trimesh.creation.icosphere(subdivisions=2, radius=0.015)
    eyes = trimesh.util.concatenate([eye.copy().apply_translation(face + [dx, 0.0, -0.01]) for dx in (-0.03, 0.03)])
    assert isinstance(eyes, trimesh.Trimesh)
    pieces.append(eyes)
    names.append("eyes")
    torso = body_V[(y > 0.95) & (y < 1.1)]
    centre = 0.5 * (torso.min(0) + torso.max(0))
    inner = trimesh.creation.cylinder(radius=0.03, height=0.15, sections=12).apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [1.0, 0.0, 0.0])
    )
    pieces += [inner.apply_translation(centre), trimesh.creation.icosphere(1, radius=0.01).apply_translation(centre)]
    names += ["inner", "nested"]
    hand = body_V[np.argmax(body_V[:, 0])]
    pieces.append((np.stack([hand + [0.05, 0.0, 0.0], hand + [0.08, 0.0, 0.0]]), np.zeros((0, 3), np.int64)))
    names.append("isolated")
    top = body_V[np.argmax(y)]
    pieces.append((top + [[0.0, 0.05, 0.0], [1e-4, 0.05, 0.0], [0.0, 0.05 + 1e-4, 0.0]], np.array([[0, 1, 2]])))
    names.append("tiny")
    V, F, parts, offset = [], [], {}, 0
    for name, piece in zip(names, pieces):
        pV, pF = (np.asarray(piece.vertices), np.asarray(piece.faces)) if isinstance(piece, trimesh.Trimesh) else piece
        V.append(pV)
        F.append(pF + offset)
        parts[name] = np.arange(offset, offset + len(pV))
        offset += len(pV)
    parts["feet"] = np.flatnonzero(y < 0.05)
    parts["crown"] = np.flatnonzero(y > 1.45)
    return np.concatenate(V), np.concatenate(F).astype(np.int64), parts


def write_multipart_character(path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """``multipart_character`` without its isolated vertices (a mesh file keeps only the vertices of faces),
    written to ``path`` (any trimesh format, e.g. .ply): (V, F, parts) as the command line reads them back."""
    from jaxcga_cli.models import load_mesh

    V, F, parts = multipart_character()
    used = np.zeros(len(V), bool)
    used[F] = True
    renumber = np.cumsum(used) - 1
    mesh = trimesh.Trimesh(V[used], renumber[F], process=False)
    mesh.export(path)
    V, F = load_mesh(path)
    return V, F, {name: renumber[index[used[index]]] for name, index in parts.items() if name != "isolated"}


DATA = Path(__file__).resolve().parent / "data"

# The corpus of public rigged characters nobody here made (sources and licences: tests/data/README.md), by name;
# tests/deform/test_corpus.py checks what they cover together (many joints, several skins, morph targets, an inner
# part, clothing layers, a coarse mesh, a large mesh).
CHARACTERS = {
    "RobotExpressive": DATA / "characters" / "RobotExpressive.glb",
    "Fox": DATA / "characters" / "Fox.glb",
    "MaleBaseMesh": DATA / "characters" / "MaleBaseMesh.glb",
    "QuaterniusCyberpunkCharacter": DATA / "characters" / "QuaterniusCyberpunkCharacter.glb",
    "QuaterniusWorker": DATA / "characters" / "QuaterniusWorker.glb",
    "QuaterniusWorkerDense": DATA / "characters" / "QuaterniusWorkerDense.glb",  # derived: see the README
    "CesiumMan": DATA / "CesiumMan.glb",
}


def character_params(fast: tuple[str, ...] = ("RobotExpressive", "Fox")) -> list:
    """``CHARACTERS``' names for ``pytest.mark.parametrize``: those in ``fast`` run in the fast suite, the others in
    the slow job (a check per character costs 5-10 s; the fast suite keeps the robot's several skins and rigid
    parts and the coarse fox)."""
    return [pytest.param(name, marks=() if name in fast else pytest.mark.slow) for name in CHARACTERS]


@functools.cache
def load_character(name: str, weld: bool = True):
    """The corpus character ``name`` (a key of ``CHARACTERS``) as a ``deform.RiggedModel``, welded by default (a
    tear or a drill walks across faces, and glTF splits vertices along UV seams). Cached: models are immutable."""
    import deform

    return deform.load_model(CHARACTERS[name], weld=weld)


# fTetWild's tets of a corpus character's rest surface, saved once (fTetWild is not deterministic): a body built on
# them, refined as character_body refines, is the same in every run (tests/data/README.md)
SAVED_TETS = {"Fox": DATA / "Fox_tets.npz", "CesiumMan": DATA / "CesiumMan_tets.npz"}


def saved_tets(name: str):
    """The saved unrefined tets of corpus character ``name`` (``SAVED_TETS``) as an ``xfem.TetMesh``."""
    import xfem

    with np.load(SAVED_TETS[name]) as saved:
        return xfem.tet_mesh(saved["X"], saved["T"])


@functools.cache
def _character_body(name: str, options: tuple):
    import xfem

    keywords = dict(options)
    if keywords.pop("saved", False):  # the saved tets, refined as the defaults refine fTetWild's
        keywords = {"tets": saved_tets(name), "refine": True, **keywords}
    return xfem.character_body(load_character(name), **keywords)


def character_body_of(name: str, **options):
    """``xfem.character_body`` of the corpus character ``name`` (a key of ``CHARACTERS``) with keyword ``options``
    (hashable values: numbers, strings, tuples), cached per (name, options): fTetWild takes seconds and is not
    deterministic, so tests that share a body share one tetrahedralization; ``saved=True`` builds it on the saved
    tets of ``SAVED_TETS`` instead (a deterministic body). Bodies are immutable; do not mutate their arrays."""
    return _character_body(name, tuple(sorted(options.items())))


def gltf_json(path) -> dict:
    """The JSON chunk of a .glb."""
    data = path.read_bytes()
    (length,) = struct.unpack("<I", data[12:16])
    return json.loads(data[20 : 20 + length])


def moving_mesh_nodes(document: dict) -> list[int]:
    """The mesh nodes deform reads, in node order: those with a skin, and those without one that are a joint of a
    used skin or lie below one (rigid attachments, which three.js draws with the node's matrixWorld)."""
    nodes = document["nodes"]
    joints = {j for n in nodes if "mesh" in n and "skin" in n for j in document["skins"][n["skin"]]["joints"]}
    parent = {c: p for p, n in enumerate(nodes) for c in n.get("children", [])}

    def moves(i):
        while i not in joints and i in parent:
            i = parent[i]
        return i in joints

    return [i for i, n in enumerate(nodes) if "mesh" in n and ("skin" in n or moves(i))]


def connected_parts(F, n: int) -> list[np.ndarray]:
    """The connected parts of the faces ``F`` (m, 3) over ``n`` vertices: one sorted array of vertex indices per
    part, largest first; vertices on no face belong to none."""
    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(F)
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])
    graph = scipy.sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    used = np.unique(F)
    parts = [used[labels[used] == label] for label in np.unique(labels[used])]
    return sorted(parts, key=len, reverse=True)


def check_gradient(loss, params, rtol: float = 1e-5, step: float = 1e-6):
    """jax.grad of ``loss`` at ``params`` against central finite differences, component by component."""
    import jax

    grad = jax.grad(loss)(params)
    numeric = np.array(
        [(loss(params.at[i].add(step)) - loss(params.at[i].add(-step))) / (2 * step) for i in range(len(params))]
    )
    np.testing.assert_allclose(grad, numeric, rtol=rtol, atol=1e-6 * float(np.abs(numeric).max()))


def assert_same_run(actual, expected, atol: float):
    """Two runs of one computation: bitwise equal on the CPU, where XLA sums a scatter-add in one order; equal to
    ``atol`` on a GPU, whose scatter-adds are atomic and sum in an order that varies from run to run."""
    import jax

    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(actual, expected)
    else:
        np.testing.assert_allclose(actual, expected, rtol=0, atol=atol)


def host_skip_reason(marker, backend: str) -> str | None:
    """Why a test marked ``@pytest.mark.host("why")`` is skipped on ``backend`` (None: it runs; on the CPU it
    always does). A mark without its reason is an error."""
    reason = _mark_reason(marker)
    return None if reason is None or backend == "cpu" else f"needs the host ({backend} backend): {reason}"


def cpu_formulation_skip_reason(marker, gpu_formulations: bool) -> str | None:
    """Why a test marked ``@pytest.mark.cpu_formulation("why")`` (it checks what the CPU formulations do: their
    lowering, their host calls) is skipped where the GPU formulations run (None: it runs). A mark without its
    reason is an error."""
    reason = _mark_reason(marker)
    return None if reason is None or not gpu_formulations else f"checks the CPU formulation, not run here: {reason}"


def _mark_reason(marker) -> str | None:
    """The one reason a skip mark (``host``, ``cpu_formulation``) must give; None without the mark."""
    if marker is None:
        return None
    if len(marker.args) != 1 or not isinstance(marker.args[0], str) or not marker.args[0].strip():
        raise ValueError(f"@pytest.mark.{marker.name}: expected one reason, got {marker.args!r}")
    return marker.args[0]


def gpu_branches(platform_dependent, *, keep_cpu: bool = True):
    """``jax.lax.platform_dependent`` that takes the non-CPU branch on the CPU (``pytest --gpu-variants``): the
    CPU branch is kept as TPU's, a platform never lowered for here, so traces still hold every branch; or, with
    ``keep_cpu=False``, dropped (nothing of it is traced)."""

    @functools.wraps(platform_dependent)
    def taking_the_gpu_branch(*args, default=None, **per_platform):
        if "cpu" in per_platform:
            cpu = per_platform.pop("cpu")
            if not keep_cpu:
                return platform_dependent(*args, default=default, **per_platform)
            if "tpu" in per_platform:
                raise ValueError("per_platform: a TPU branch leaves no platform to keep the CPU branch under")
            per_platform["tpu"] = cpu
        return platform_dependent(*args, default=default, **per_platform)

    return taking_the_gpu_branch


def run_on_host_devices(script: str, devices: int = 4, timeout: int = 600) -> str:
    """Run a Python ``script`` (dedented) from the repository root in a fresh process with ``devices`` forced CPU
    host devices (XLA_FLAGS must be set before JAX starts), and return its stdout; a failure shows its stderr."""
    import os
    import subprocess
    import sys
    import textwrap
    from pathlib import Path

    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        env=env,
        cwd=root,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def extended_tests() -> list[str]:
    """The node ids of ``tests/extended.txt``: the slow tests CI's slow job leaves out (``make test-extended``)."""
    lines = (Path(__file__).resolve().parent / "extended.txt").read_text().splitlines()
    return [line.strip() for line in lines if line.strip() and not line.startswith("#")]


# the tests' shared JAX compilation cache (conftest.py)
TESTS_JAX_CACHE_VARIABLES = ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")


def run_jaxcga(argv: list[str], cache: Path | None, env: dict[str, str] | None = None, timeout: int = 600):
    """``jaxcga ARGV`` in a fresh process from the repository root (its packages, not an installed copy), with
    the command's compilation cache in ``cache`` (None: as the environment has it, which the tests' conftest sets:
    the command's cache off, the tests' JAX cache on) and the environment variables ``env`` added; returns the
    ``subprocess.CompletedProcess`` (text)."""
    import os
    import subprocess
    import sys

    environment = dict(os.environ)
    if cache is not None:  # the command's own cache alone: the tests' JAX cache (conftest.py) would be the user's
        for name in ("JAXCGA_NO_CACHE", *TESTS_JAX_CACHE_VARIABLES):
            environment.pop(name, None)
        environment["JAXCGA_CACHE_DIR"] = str(cache)
    environment.update(env or {})
    return subprocess.run(
        [sys.executable, "-m", "jaxcga_cli", *argv],
        env=environment,
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def assert_checks_placed_per_platform(fn, *args) -> None:
    """``fn(*args)``'s runtime check (``checks.require_around``) on the CPU is made on a small operand before the
    computation (a conditional returning the large result would copy it), and on other platforms it is the last
    operation, made on the (single) result: on a GPU the check's host round trip then has nothing left to launch
    while it waits. Each platform's branch is traced alone."""
    from unittest import mock

    import jax
    import jax.extend.core

    def traced(platform):
        def one_branch(*operands, default, cpu=None, **_):
            return (cpu if platform == "cpu" and cpu is not None else default)(*operands)

        jax.clear_caches()  # a trace cached by an earlier call holds both branches
        with mock.patch.object(jax.lax, "platform_dependent", one_branch):
            jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
        jax.clear_caches()
        if len(jaxpr.eqns) == 1 and "jaxpr" in jaxpr.eqns[0].params:  # a function compiled on its own (filter_jit)
            inner = jaxpr.eqns[0].params["jaxpr"].jaxpr
            # filter_jit's constant outputs (literals) left out
            outvars = [v for v in inner.outvars if not isinstance(v, jax.extend.core.Literal)]
            jaxpr = inner.replace(outvars=outvars)
        checks = [i for i, eqn in enumerate(jaxpr.eqns) if "_Fail(" in str(eqn.params)]
        assert len(checks) == 1, [jaxpr.eqns[i].primitive for i in checks]
        return jaxpr, jaxpr.eqns[checks[0]]

    jaxpr, check = traced("gpu")
    assert check is jaxpr.eqns[-1] and check.outvars == jaxpr.outvars
    assert check.invars[0].aval.shape == jaxpr.outvars[0].aval.shape  # the result goes through the check
    jaxpr, check = traced("cpu")
    assert check is not jaxpr.eqns[-1]
    assert check.invars[0].aval.size < jaxpr.outvars[0].aval.size  # a small operand goes through it


def lowered_operations(fn, args, platform: str) -> collections.Counter:
    """The StableHLO operations of ``jax.jit(fn)`` on ``args`` lowered for ``platform`` (which need not be
    present), less a conditional's own (``case``, ``return``, ``constant``)."""
    import jax

    text = jax.jit(fn).trace(*args).lower(lowering_platforms=(platform,)).as_text()
    return collections.Counter(
        op for op in re.findall(r"stablehlo\.(\w+)", text) if op not in ("case", "return", "constant")
    )


@functools.cache
def _cuda_lowering_error() -> str | None:
    import jax
    import jax.numpy as jnp

    try:
        jax.jit(lambda x: x + 1).trace(jnp.zeros(2)).lower(lowering_platforms=("cuda",))
    except Exception as error:  # noqa: BLE001 (any failure means: this JAX cannot lower for CUDA here)
        return str(error)
    return None


def needs_cuda_lowering(test):
    """Decorator: skip the test where this JAX cannot lower for CUDA without a GPU (checked when it runs, not
    when this module is imported: conftest imports it before any backend starts)."""

    @functools.wraps(test)
    def run(*args, **kwargs):
        error = _cuda_lowering_error()
        if error is not None:
            pytest.skip(f"this JAX cannot lower for CUDA without a GPU: {error}")
        return test(*args, **kwargs)

    return run


def wild_surface():
    """An open, self-intersecting, multi-part triangle surface and the volume it bounds: two unit icospheres
    (subdivision 3) whose centres lie about 1 apart, so they cross each other (off any symmetry, so that no two
    vertices coincide), each with a hole of the 6 faces around the vertex farthest from the other, and a
    disjoint cube of side 1 (its own part); no vertex is on no face.

    Returns:
        V (v, 3), F (f, 3) int64, the volume of the closed parts' union (manifold3d, before the holes), the
        total area of the triangles.
    """
    import manifold3d

    sphere = trimesh.creation.icosphere(subdivisions=3)
    parts, solids = [], []
    for centre in ((-0.5, 0.0, 0.0), (0.51, 0.013, -0.007)):
        V = np.asarray(sphere.vertices) + centre
        F = np.asarray(sphere.faces)
        tip = int(np.argmax(V[:, 0] * np.sign(centre[0])))  # the pole away from the other sphere
        parts.append((V, F[~np.any(F == tip, axis=1)]))
        solids.append(manifold3d.Manifold(manifold3d.Mesh(V.astype(np.float32), F.astype(np.uint32))))
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    V = np.asarray(box.vertices) + [3.0, 0.0, 0.0]
    parts.append((V, np.asarray(box.faces)))
    solids.append(manifold3d.Manifold.cube((1.0, 1.0, 1.0), center=True).translate((3.0, 0.0, 0.0)))
    offsets = np.cumsum([0] + [len(V) for V, _ in parts])
    V = np.concatenate([V for V, _ in parts])
    F = np.concatenate([F + o for (_, F), o in zip(parts, offsets)]).astype(np.int64)
    used = np.unique(F)  # the holes' tips are on no face: drop them
    V, F = V[used], np.searchsorted(used, F)
    volume = (solids[0] + solids[1] + solids[2]).volume()
    area = float(trimesh.Trimesh(V, F, process=False).area)
    return V, F, volume, area
