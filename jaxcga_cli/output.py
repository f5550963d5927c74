"""The command line's outputs: which file suffixes each kind of result takes, and the one writer that picks the
format by the suffix (positions as .npy, a mesh in a trimesh format, or a figure of the rest and result)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deform import GLTF_OUTPUTS

MESH_OUTPUTS = GLTF_OUTPUTS + (".obj", ".ply", ".stl")
POSITION_OUTPUTS = (".npy",) + MESH_OUTPUTS
FIGURE_OUTPUTS = (".png",)
DEFORM_OUTPUTS = POSITION_OUTPUTS + FIGURE_OUTPUTS


def write_result(out: Path, positions, F, rest=None, title: str = "") -> None:
    """Write ``positions`` ((n, 3)) of the mesh with faces ``F`` ((m, 3)) to ``out``, by its suffix: .npy float64
    (n, 3); a mesh (.glb, .gltf with its buffers embedded, .obj, .ply, .stl); .png, a figure of the ``rest``
    positions beside these under ``title``. Every file goes through ``_jaxcga_shared.output``: an existing file
    survives a failed write."""
    from _jaxcga_shared.output import replacing, write_bytes

    suffix = Path(out).suffix.lower()
    if suffix == ".png":
        if rest is None:
            raise ValueError(f"out: a figure needs the rest positions; write {Path(out).with_suffix('.npy')} instead")
        result_figure(np.asarray(rest), np.asarray(positions), np.asarray(F), out, title)
    elif suffix == ".npy":
        with replacing(out) as (temp,), open(temp, "wb") as file:  # np.save on a name would append .npy
            np.save(file, np.asarray(positions, np.float64))
    elif suffix == ".glb":  # written here: trimesh's import takes longer than a skinning run's work
        from _jaxcga_shared.gltf import mesh_glb

        write_bytes(out, mesh_glb(positions, F, Path(out).stem))
    else:
        import trimesh

        file_type = suffix[1:]
        mesh = trimesh.Trimesh(np.asarray(positions), np.asarray(F), process=False)
        if file_type == "gltf":
            data = mesh.export(file_type=file_type, embed_buffers=True)
        else:
            data = mesh.export(file_type=file_type)
        write_bytes(out, data["model.gltf"] if isinstance(data, dict) else data)


def result_figure(V, positions, F, path: Path, title: str) -> Path:
    """Rest and deformed mesh side by side, on the same axes' scale."""
    from jaxcga_cli import figures

    both = np.concatenate([V, positions])
    lo, hi = both.min(axis=0), both.max(axis=0)
    fig = figures.figure(10, 4.5)
    for k, (X, label, color) in enumerate(((V, "rest", "tab:gray"), (positions, title, "tab:orange"))):
        ax = figures.axes_3d(fig, 1, 2, k + 1)
        ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=F, color=color, linewidth=0, alpha=0.9)
        figures.set_box(ax, lo, hi, label)
        ax.set_axis_off()
    return figures.save_figure(fig, path, dpi=90, bbox_inches="tight")


def check_files(
    args, inputs: tuple[str, ...], outputs: dict[str, Path], suffixes: tuple[str, ...], gltf: bool = False
) -> None:
    """Every input and output path of a command, before anything is loaded or computed: the ``inputs`` (names
    of ``args``' attributes; None skipped) are files; the ``outputs`` ({name: path}) have one of ``suffixes``,
    are no folder and lie in a folder this process may write in; no output is an input or another output; with
    ``gltf``, a .gltf written with its .bin does not replace an unrelated .bin."""
    import deform
    from _jaxcga_shared.output import check_distinct, check_input, check_output

    given = {name: check_input(getattr(args, name), name) for name in inputs if getattr(args, name) is not None}
    for name, path in outputs.items():
        check_output(path, suffixes, name)
        if gltf:
            deform.buffer_file(path, name)
    check_distinct(outputs, given)
