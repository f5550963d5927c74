"""Figures of the command line: matplotlib on its file-only backend (chosen here, once), 3-D axes set to a box,
and figures written through the atomic writer (an existing file survives a failed write)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")  # the command line writes figure files and never opens a window
import matplotlib.pyplot as plt

from _jaxcga_shared.output import replacing


def figure(width: float, height: float):
    """A new matplotlib figure of ``width`` x ``height`` inches."""
    return plt.figure(figsize=(width, height))


def axes_3d(fig, rows: int = 1, columns: int = 1, index: int = 1):
    """A 3-D axes at ``index`` of a ``rows`` x ``columns`` grid of ``fig``."""
    return fig.add_subplot(rows, columns, index, projection="3d")


def set_box(ax, lo, hi, title: str | None = None, floor: float = 1e-9) -> None:
    """The axes' limits to the box [``lo``, ``hi``] with the box's true aspect (each side at least ``floor``
    times the longest, so that a flat mesh still draws)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
    if title is not None:
        ax.set_title(title)
    ax.set_box_aspect(np.maximum(hi - lo, floor * (hi - lo).max()))
    readable_ticks(ax)


def readable_ticks(ax, count: int = 4, size: float = 7) -> None:
    """At most ``count`` ticks per axis of ``ax`` (2-D or 3-D), in ``size`` points: matplotlib's default crowds a
    small 3-D panel with overlapping labels."""
    from matplotlib.ticker import MaxNLocator

    axes = [ax.xaxis, ax.yaxis] + ([ax.zaxis] if hasattr(ax, "zaxis") else [])
    for axis in axes:
        axis.set_major_locator(MaxNLocator(count))
    ax.tick_params(labelsize=size, pad=0)


def save_figure(fig, path, **savefig) -> Path:
    """``fig.savefig`` (``savefig``: its keywords) to ``path`` through ``_jaxcga_shared.output.replacing``; the
    figure is closed, also when the write fails. Returns ``path`` as a Path."""
    try:
        with replacing(path) as (temp,):
            fig.savefig(temp, **savefig)
    finally:
        plt.close(fig)
    return Path(path)


def colormap(name: str):
    """matplotlib's colour map ``name``."""
    return plt.get_cmap(name)
