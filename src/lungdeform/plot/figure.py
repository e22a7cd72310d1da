"""A Figure on its own Agg canvas, and writing it: the base of every figure of :mod:`lungdeform.plot`.

No pyplot and no ``matplotlib.use``: a Figure on its own Agg canvas needs no backend choice and
keeps no global state, so it is safe in library code, tests and Dask workers. :func:`save_png` writes
one atomically (:mod:`lungdeform.atomic`), :func:`png_bytes` returns its bytes (e.g. to embed in HTML).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lungdeform.atomic import write_bytes


def new_figure(width_in: float, height_in: float, *, dpi: float = 110, layout: str | None = None) -> Figure:
    """A Figure of ``width_in × height_in`` inches on its own Agg canvas (no pyplot state)."""
    fig = Figure(figsize=(width_in, height_in), dpi=dpi, layout=layout)
    FigureCanvasAgg(fig)
    return fig


@dataclass(frozen=True)
class Cell:
    """One panel of :func:`grid_figure`, inches: the axes' ``width`` and ``height`` and the margins
    around them in its cell (for tick labels, axis labels, the title)."""

    width: float
    height: float
    left: float = 0.7
    right: float = 0.2
    bottom: float = 0.55
    top: float = 0.35


def grid_figure(rows: int, cols: int, cell: Cell, *, right_in: float = 0.0, top_in: float = 0.0,
                dpi: float = 80) -> tuple[Figure, np.ndarray]:
    """A Figure of ``rows × cols`` equal cells (:class:`Cell`) laid out in inches, ``right_in`` and
    ``top_in`` inches left free on the right (a colour bar) and at the top (a title); returns it and
    its ``(rows, cols)`` axes. No layout engine: matplotlib's constrained layout measures every text
    of every axes at every save, about 45 % of a report figure's CPU."""
    cw, ch = cell.left + cell.width + cell.right, cell.bottom + cell.height + cell.top
    width, height = cols * cw + right_in, rows * ch + top_in
    fig = new_figure(width, height, dpi=dpi)
    axes = np.empty((rows, cols), dtype=object)
    for r in range(rows):
        for c in range(cols):
            x0, y0 = c * cw + cell.left, height - top_in - (r + 1) * ch + cell.bottom
            axes[r, c] = fig.add_axes((x0 / width, y0 / height, cell.width / width, cell.height / height))
    return fig, axes


def png_bytes(fig: Figure) -> bytes:
    """``fig`` as PNG bytes at the figure's own dpi."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi="figure")
    return buf.getvalue()


def save_png(fig: Figure, path) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically; returns the path."""
    return write_bytes(path, png_bytes(fig))
