"""A Figure on its own Agg canvas, and writing it: the base of every figure of :mod:`lungdeform.plot`.

No pyplot and no ``matplotlib.use``: a Figure on its own Agg canvas needs no backend choice and
keeps no global state, so it is safe in library code, tests and Dask workers. :func:`save_png` writes
one atomically (:mod:`lungdeform.atomic`), :func:`png_bytes` returns its bytes (e.g. to embed in HTML),
written by Pillow (matplotlib's own PNG writer) from the drawn canvas. :class:`PixelImage` draws an
image pixel for pixel (the error maps' panels, :mod:`lungdeform.plot.surface`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.artist import Artist
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.transforms import Affine2D
from PIL import Image
from PIL.PngImagePlugin import PngInfo

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


def grid_boxes(rows: int, cols: int, cell: Cell, *, right_in: float = 0.0,
               top_in: float = 0.0) -> tuple[float, float, np.ndarray]:
    """The layout of :func:`grid_figure` in inches: the figure's width and height and each cell's
    axes box ``(rows, cols, 4) float`` (left, bottom, width, height; inches from the figure's
    lower-left corner)."""
    cw, ch = cell.left + cell.width + cell.right, cell.bottom + cell.height + cell.top
    width, height = cols * cw + right_in, rows * ch + top_in
    boxes = np.empty((rows, cols, 4))
    for r in range(rows):
        for c in range(cols):
            boxes[r, c] = (c * cw + cell.left, height - top_in - (r + 1) * ch + cell.bottom, cell.width, cell.height)
    return width, height, boxes


def grid_figure(rows: int, cols: int, cell: Cell, *, right_in: float = 0.0, top_in: float = 0.0,
                dpi: float = 80) -> tuple[Figure, np.ndarray]:
    """A Figure of ``rows × cols`` equal cells (:class:`Cell`) laid out in inches, ``right_in`` and
    ``top_in`` inches left free on the right (a colour bar) and at the top (a title); returns it and
    its ``(rows, cols)`` axes. No layout engine: matplotlib's constrained layout measures every text
    of every axes at every save, about 45 % of a report figure's CPU."""
    width, height, boxes = grid_boxes(rows, cols, cell, right_in=right_in, top_in=top_in)
    fig = new_figure(width, height, dpi=dpi)
    axes = np.empty((rows, cols), dtype=object)
    for r in range(rows):
        for c in range(cols):
            axes[r, c] = fig.add_axes(tuple(boxes[r, c] / [width, height, width, height]))
    return fig, axes


class PixelImage(Artist):
    """An RGBA image drawn pixel for pixel: ``rgba : (h, w, 4) uint8`` (row 0 at the top) with its
    top-left corner ``top_left = (column, row)`` pixels from the figure's top-left corner, pixels of
    the figure at ``dpi`` (its own, when the image is made). matplotlib's images are resampled at
    every draw, even one to one (about 0.1 s for a figure-sized image); this one is copied. Drawn at
    another dpi (``savefig(dpi=...)``) it is scaled with the figure: by the renderer where it can
    (vector backends), else to the nearest pixel."""

    def __init__(self, rgba: np.ndarray, top_left: tuple[int, int], dpi: float):
        super().__init__()
        self._rgba = np.ascontiguousarray(np.asarray(rgba, np.uint8)[::-1])  # draw_image: row 0 at the bottom
        self._top_left = top_left
        self._dpi = float(dpi)

    def draw(self, renderer) -> None:
        """Draw on ``renderer``."""
        if not self.get_visible():
            return
        fig = self.get_figure(root=True)
        scale = fig.dpi / self._dpi  # the figure's dpi while drawn: savefig's, or 72 for PDF and SVG
        h, w = self._rgba.shape[:2]
        x = self._top_left[0] * scale
        y = (fig.get_figheight() * self._dpi - self._top_left[1] - h) * scale
        gc = renderer.new_gc()
        if renderer.option_scale_image():  # vector: the unit square mapped onto the image's place
            renderer.draw_image(gc, x, y, self._rgba, Affine2D().scale(w * scale, h * scale))
        elif scale == 1.0:
            renderer.draw_image(gc, x, y, self._rgba)
        else:
            rows = (np.arange(round(h * scale)) / scale).astype(int).clip(0, h - 1)
            cols = (np.arange(round(w * scale)) / scale).astype(int).clip(0, w - 1)
            renderer.draw_image(gc, x, y, np.ascontiguousarray(self._rgba[rows][:, cols]))
        gc.restore()
        self.stale = False


#: zlib level of :func:`png_bytes`: 3 writes a report's error map of a 4-D CT (912 × 2300 pixels) in
#: about 0.1 s where matplotlib's 6 took 0.25 s, the file no larger than matplotlib's RGBA at 6
#: (1.03 MB against 1.04 MB), being RGB.
PNG_COMPRESS_LEVEL = 3


def png_bytes(fig: Figure) -> bytes:
    """``fig`` as PNG bytes at the figure's own dpi, drawn on its Agg canvas: RGB where every pixel
    is opaque (every figure here: its pixels as matplotlib's RGBA PNG has them, a quarter fewer bytes
    to compress), else RGBA; zlib level :data:`PNG_COMPRESS_LEVEL`; the dpi and matplotlib's
    ``Software`` text recorded as matplotlib records them."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    opaque = bool((rgba[..., 3] == 255).all())
    image = Image.fromarray(np.ascontiguousarray(rgba[..., :3]) if opaque else rgba.copy())
    info = PngInfo()
    info.add_text("Software", f"Matplotlib version{matplotlib.__version__}, https://matplotlib.org/")
    buf = io.BytesIO()
    image.save(buf, format="png", compress_level=PNG_COMPRESS_LEVEL, dpi=(fig.dpi, fig.dpi), pnginfo=info)
    return buf.getvalue()


def save_png(fig: Figure, path) -> Path:
    """Write ``fig`` as a PNG to ``path`` atomically; returns the path."""
    return write_bytes(path, png_bytes(fig))
