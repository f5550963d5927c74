"""The ``jaxcga fem SCENE`` command (called by ``jaxcga.cli``): backward Euler (XFEM paper eq. 10) of a
stable neo-Hookean body under gravity, with the paper's parameters by default (Young 1e6, Poisson 0.4,
density 1e3, h = 0.033 s, one Newton iteration).

Scenes:

* ``bar``: a 2 x 0.5 x 0.5 bar (16 x 4 x 4 cells, 6 tets each), clamped at x = 0: a cantilever.
* ``cube``: a unit cube (8^3 cells) hanging from its top face.
* a file: a tet mesh read by meshio (``.msh``, ``.vtu``, ``.vtk``, ...), or a closed triangle mesh (``.obj``,
  ``.ply``, ``.stl``, ``.off``, glTF) tetrahedralized by TetGen; the nodes within ``fix_fraction`` of the top
  (largest z) are clamped.

Writes into OUT: ``frame_XXXX.png`` (the boundary surface, fixed axes) and ``frame_XXXX.vtu`` (the tet mesh
with its displacement and velocity, for ParaView or meshio) every ``every`` steps and for the last one,
and ``summary.json`` (nodes, DOFs, elements, steps, step times, energies). OUT holds one run: it must be empty
unless ``force``, and the files appear when the run ends (written beside, in a private folder), replacing the
previous run's files (only those), ``summary.json`` last; a failed run leaves OUT as it was.
"""

from __future__ import annotations

import contextlib
import io
import re
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxcga._meshfile import read_mesh_file
from jaxcga._output import check_run_folder, run_folder, save_figure, write_json
from xfem._backward_euler import State, backward_euler_step, fem_from_mesh, mechanical_energy
from xfem._material import Material
from xfem._tetmesh import TetMesh, box_tets, read_tet_mesh, tetrahedralize

SCENES = ("bar", "cube")
RUN_FILES = re.compile(r"frame_\d{4,}\.(png|vtu)|summary\.json")  # one run's files in its OUT folder
RUN_DESCRIBED = "frame_XXXX.png, frame_XXXX.vtu and summary.json"
SURFACE_FORMATS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def scene_mesh(scene: str, fix_fraction: float = 0.02):
    """(TetMesh, fixed node indices) of a named scene or a mesh file (module docstring)."""
    if scene == "bar":
        mesh = box_tets((16, 4, 4), size=(2.0, 0.5, 0.5))
        return mesh, np.flatnonzero(np.asarray(mesh.X)[:, 0] <= 1e-12)
    if scene == "cube":
        mesh = box_tets((8, 8, 8))
        return mesh, np.flatnonzero(np.asarray(mesh.X)[:, 2] >= 1.0 - 1e-12)
    path = Path(scene)
    if not path.exists():
        raise FileNotFoundError(f"SCENE: expected one of {SCENES} or a mesh file, got {scene!r} (no such file)")
    if path.suffix.lower() in SURFACE_FORMATS:
        mesh = tetrahedralize(*read_mesh_file(path, "SCENE"))
    else:
        try:
            # meshio prints its readers' complaints before giving up: the error below says it on one line
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                mesh = read_tet_mesh(path)
        except ValueError as error:  # it names its argument "path"
            raise ValueError(f"SCENE: {str(error).removeprefix('path: ')}") from None
    if not 0 < fix_fraction < 1:
        raise ValueError(f"fix_fraction: expected a fraction in (0, 1), got {fix_fraction}")
    z = np.asarray(mesh.X)[:, 2]
    return mesh, np.flatnonzero(z >= z.max() - fix_fraction * (z.max() - z.min()))


def _frame(mesh: TetMesh, faces, x, limits, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    ax.plot_trisurf(x[:, 0], x[:, 1], x[:, 2], triangles=faces, color="tab:orange", linewidth=0.1,
                    edgecolor="k", alpha=0.95)
    lo, hi = limits
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), title=title)
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3 * (hi - lo).max()))
    save_figure(fig, path, dpi=80, bbox_inches="tight")


def fem_command(scene: str, steps: int, out: Path, *, h: float = 0.033, young: float = 1e6, poisson: float = 0.4,
                density: float = 1e3, gravity=(0.0, 0.0, -9.81), newton_iterations: int = 1, every: int = 10,
                fix_fraction: float = 0.02, figures: bool = True, progress: bool = True, force: bool = False) -> dict:
    """Simulate ``scene`` for ``steps`` backward Euler steps and write frames into ``out``; returns the summary.
    ``out`` must be empty unless ``force``; the run's files replace the previous run's when it ends
    (``jaxcga._output.run_folder``)."""
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if not h > 0:
        raise ValueError(f"dt: expected a positive time step, got {h}")
    if not density > 0:
        raise ValueError(f"density: expected a positive density, got {density}")
    if len(gravity) != 3 or not np.isfinite(max(abs(float(g)) for g in gravity) * float(density)):
        raise ValueError(f"gravity: expected three numbers whose product with the density is finite, got {gravity}")
    out = check_run_folder(out, RUN_FILES, force, RUN_DESCRIBED,
                           inputs=None if scene in SCENES else {"SCENE": Path(scene)})
    material = Material(young, poisson)
    mesh, fixed = scene_mesh(scene, fix_fraction)
    system = fem_from_mesh(mesh, density, gravity, fixed)
    faces = mesh.boundary_faces()
    X = np.asarray(mesh.X)
    extent = X.max(0) - X.min(0)
    limits = (X.min(0) - 0.6 * extent.max(), X.max(0) + 0.6 * extent.max())
    energies = jax.jit(lambda state: mechanical_energy(system, state, material))

    with run_folder(out, RUN_FILES, "summary.json") as staging:
        def write(k: int, state: State):
            x = np.asarray(state.x)
            import meshio

            meshio.write(staging / f"frame_{k:04d}.vtu", meshio.Mesh(
                x, [("tetra", np.asarray(mesh.T))],
                point_data={"displacement": x - X, "velocity": np.asarray(state.v)}))
            if figures:
                _frame(mesh, faces, x, limits, staging / f"frame_{k:04d}.png",
                       f"{scene}: step {k}, t = {k * h:.3f} s")

        from tqdm import tqdm

        state = State(mesh.X, jnp.zeros_like(mesh.X))
        write(0, state)
        times, kinetic, potential = [], [], []
        for k in tqdm(range(1, steps + 1), desc=f"fem {Path(scene).name}", unit="step", disable=not progress):
            start = time.perf_counter()
            state = jax.block_until_ready(backward_euler_step(system, state, h, material,
                                                              newton_iterations=newton_iterations))
            times.append(time.perf_counter() - start)
            if not bool(jnp.all(jnp.isfinite(state.x))):
                raise RuntimeError(f"fem: non-finite positions at step {k}; try a smaller --dt or more --newton")
            e_kin, e_elastic, e_external = energies(state)
            kinetic.append(float(e_kin))
            potential.append(float(e_elastic + e_external))
            if k % every == 0 or k == steps:
                write(k, state)
        summary = {
            "scene": scene, "nodes": int(mesh.n_nodes), "dofs": 3 * (int(mesh.n_nodes) - len(fixed)),
            "elements": int(mesh.n_elements), "fixed_nodes": len(fixed), "steps": steps, "dt": h,
            "young": young, "poisson": poisson, "density": density, "newton_iterations": newton_iterations,
            "first_step_s": times[0], "step_avg_s": float(np.mean(times[1:])) if steps > 1 else times[0],
            "step_max_s": float(np.max(times[1:])) if steps > 1 else times[0],
            "kinetic_energy": kinetic, "potential_energy": potential,
            "max_displacement": float(np.abs(np.asarray(state.x) - X).max()),
        }
        write_json(staging / "summary.json", summary)
    return summary
