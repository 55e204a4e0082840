"""Figures of studies: matplotlib's object API on the Agg canvas, written atomically.

No pyplot (no global figure state, safe in Dask worker threads and in the CLI).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from cdma_lidar.fileio import atomic_open

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["new_figure", "save_figure"]


def new_figure(width_in: float = 6.0, height_in: float = 4.0, nrows: int = 1,
               ncols: int = 1) -> tuple[Figure, Axes | list[Axes]]:
    """A figure on an Agg canvas and its axes (one Axes, or a flat list for a grid)."""
    # deferred: matplotlib costs 0.4 s, which `study list` and every start-up would pay
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure  # (deferred, as above)

    fig = Figure(figsize=(width_in, height_in))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    flat = [ax for row in axes for ax in row]
    return fig, (flat[0] if len(flat) == 1 else flat)


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int = 100) -> None:
    """Write ``fig`` as PNG to ``path`` atomically (tight layout)."""
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=dpi)
