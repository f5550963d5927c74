"""The ``jaxcga xfem SCENE`` command (called by ``jaxcga.cli``): one of the XFEM paper's cutting scenes of sec. 5
(``xfem._scenes``: sticks, thin, cheese, accordion, mouth; parameters of sec. 5 and Table 1), simulated with
the timings of Table 2.

Writes into OUT, every ``every`` frames, on every frame with a cut, and for the last frame (with a cut latency,
a frame shows the cuts that have taken effect):

* ``frame_XXXX.png``: the deformed surfaces of the pieces (mesh boundary and cut faces, ``piece_surfaces``),
  coloured by connected piece, fixed axes;
* ``frame_XXXX.vtu``: the same triangles (each with its own three vertices) with the cell data ``piece``, for
  ParaView or meshio;

and ``summary.json``: ``SceneRun.summary()`` (pieces, DOFs, Booleans, timings) plus the run's settings, the
cut frames and the per-frame pieces, DOFs and times. OUT holds one run, as for ``jaxcga fem``
(``xfem._fem_commands``): empty unless ``force``, filled when the run ends, ``summary.json`` last.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxcga._output import check_run_folder, run_folder, save_figure, write_json
from xfem._fem_commands import RUN_DESCRIBED, RUN_FILES
from xfem._scenes import SCENES, SIZES, FrameRecord, piece_surfaces, run_scene, scene
from xfem._xfem import XFEMModel


def _frame(V: np.ndarray, F: np.ndarray, piece: np.ndarray, limits, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    colours = plt.get_cmap("tab20")(piece % 20)
    ax.add_collection3d(Poly3DCollection(V[F], facecolors=colours, edgecolors="k", linewidths=0.05, alpha=0.95))
    lo, hi = limits
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), title=title)
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3 * (hi - lo).max()))
    save_figure(fig, path, dpi=80, bbox_inches="tight")


def xfem_command(name: str, out: Path, steps: int | None = None, *, size: str = "paper", every: int = 10,
                 figures: bool = True, progress: bool = True, cut_latency: int = 0, force: bool = False) -> dict:
    """Run scene ``name`` for ``steps`` frames (None: the scene's default) and write frames into ``out``; returns
    the summary (module docstring). ``cut_latency``: as ``run_scene``; ``force``: as ``fem_command``'s."""
    if name not in SCENES:
        raise ValueError(f"SCENE: expected one of {SCENES}, got {name!r}")
    if size not in SIZES:
        raise ValueError(f"size: expected one of {SIZES}, got {size!r}")
    if steps is not None and (not isinstance(steps, int) or steps < 1):
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if not isinstance(cut_latency, int) or cut_latency < 0:
        raise ValueError(f"cut_latency: expected an int >= 0, got {cut_latency!r}")
    out = check_run_folder(out, RUN_FILES, force, RUN_DESCRIBED)
    import meshio

    sc = scene(name, size)
    steps = sc.steps if steps is None else steps
    X = np.asarray(sc.mesh.X)
    extent = X.max(0) - X.min(0)
    # room to fall: the body's size below it, half of it around
    limits = (X.min(0) - np.array([0.5, 0.5, 1.0]) * extent.max(), X.max(0) + 0.5 * extent.max())
    written = []

    with run_folder(out, RUN_FILES, "summary.json") as staging:
        def write(frame: int, model: XFEMModel):
            V, F, piece = piece_surfaces(model)
            meshio.write(staging / f"frame_{frame:04d}.vtu",
                         meshio.Mesh(V, [("triangle", F)], cell_data={"piece": [piece]}))
            if figures:
                _frame(V, F, piece, limits, staging / f"frame_{frame:04d}.png",
                       f"{name}: frame {frame}, t = {frame * sc.h:.3f} s, {int(piece.max()) + 1} pieces")
            written.append(frame)

        def on_frame(record: FrameRecord, model: XFEMModel):
            if record.cuts or record.frame % every == 0 or record.frame == steps:
                write(record.frame, model)

        write(0, sc.model())
        run = run_scene(sc, steps, progress=progress, on_frame=on_frame, cut_latency=cut_latency)
        summary = run.summary()
        summary.update({
            "steps": steps, "dt": sc.h, "young": sc.young, "poisson": sc.poisson, "density": sc.density,
            "epsilon": sc.epsilon, "newton_iterations": sc.newton_iterations, "fixed_nodes": int(len(sc.fixed)),
            "cut_latency": cut_latency,
            "cut_frames": sorted({c.frame for c in sc.cuts if c.frame <= steps}), "frames_written": written,
            "frame_pieces": [r.pieces for r in run.records], "frame_dofs": [r.dofs for r in run.records],
            "frame_seconds": [r.seconds for r in run.records],
            "max_displacement": float(np.abs(np.asarray(run.model.state.x) - X[run.model.dof_node]).max()),
        })
        write_json(staging / "summary.json", summary)
    return summary
