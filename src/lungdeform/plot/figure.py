"""A Figure on its own Agg canvas, and writing it: the base of every figure of :mod:`lungdeform.plot`.

No pyplot and no ``matplotlib.use``: a Figure on its own Agg canvas needs no backend choice and
keeps no global state, so it is safe in library code, tests and Dask workers. :func:`save_png` writes
one atomically (:mod:`lungdeform.atomic`), :func:`png_bytes` returns its bytes (e.g. to embed in HTML).
"""

from __future__ import annotations

import io
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lungdeform.atomic import write_bytes


def new_figure(width_in: float, height_in: float, *, dpi: float = 110, layout: str | None = None) -> Figure:
    """A Figure of ``width_in × height_in`` inches on its own Agg canvas (no pyplot state)."""
    fig = Figure(figsize=(width_in, height_in), dpi=dpi, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def png_bytes(fig: Figure) -> bytes:
    """``fig`` as PNG bytes at the figure's own dpi."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi="figure")
    return buf.getvalue()


def save_png(fig: Figure, path) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically; returns the path."""
    return write_bytes(path, png_bytes(fig))
