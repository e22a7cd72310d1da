"""Lung surfaces drawn by a small painter (no GPU or display): faces facing the viewer are
Lambert-shaded by a headlight and drawn back to front, enough for a closed lung surface seen from
outside. Views are named in the patient frame (:data:`VIEWS`): ``anterior`` looks at the patient's
front (patient left on the image right), ``posterior`` at the back, ``lateral-left`` /
``lateral-right`` from the sides, ``superior`` from above. Coordinates are mm, LPS (+x patient left,
+y posterior, +z head). :func:`snapshot` draws layers of surfaces, :func:`error_map` one coloured by a
per-vertex error, its panels painted into images by :mod:`lungdeform.plot.raster` (one image
for many rows: the figure's cost hardly grows with them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize, to_rgb
from matplotlib.figure import Figure
from matplotlib.transforms import Affine2D

from .figure import Cell, PixelImage, grid_boxes, new_figure
from .raster import paint

#: view name → (direction from the patient to the viewer, image right, image up), unit vectors in LPS
VIEWS = {
    "anterior": ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "posterior": ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "lateral-left": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "lateral-right": ((-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
}
#: view name → (what lies toward the image right, toward the image top), for the axis labels
VIEW_DIRECTIONS = {
    "anterior": ("patient left", "head"),
    "posterior": ("patient right", "head"),
    "lateral-left": ("posterior", "head"),
    "lateral-right": ("anterior", "head"),
    "superior": ("patient left", "anterior"),
}


def unit_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(m, 3) float``: each face's unit normal (by its winding; zero for a face of no area), of
    ``vertices : (n, 3) float`` mm and ``faces : (m, 3) int``."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1)
    return n / np.where(length > 0, length, 1.0)[:, None]


def project(vertices: np.ndarray, faces: np.ndarray, view: str,
            normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces of a closed surface that face the viewer of ``view``, far first (painter's order).

    ``vertices : (n, 3) float`` mm LPS, ``faces : (m, 3) int`` wound outward; ``normals : (m, 3)
    float`` their :func:`unit_normals` if known (several views of one surface). Returns ``polygons
    (k, 3, 2) float`` (mm along the image right and up), ``cosine (k,) float`` in (0, 1] (the angle
    between each face's outward normal and the direction to the viewer: the headlight's Lambert term)
    and ``index (k,) int`` (which face of ``faces`` each polygon is)."""
    eye, right, up = (np.asarray(a) for a in VIEWS[view])
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    cosine = (unit_normals(v, f) if normals is None else normals) @ eye
    facing = np.nonzero(cosine > 0)[0]
    depth = (v @ eye)[f[facing]].sum(axis=1)  # three times the centroid's distance toward the viewer
    index = facing[np.argsort(depth, kind="stable")]  # far first
    xy = v @ np.stack([right, up], axis=1)
    return xy[f[index]], np.clip(cosine[index], 0.0, 1.0), index


def shade(rgb: np.ndarray, cosine: np.ndarray, ambient: float) -> np.ndarray:
    """Lambert shading: ``rgb (k, 3)`` in [0, 1] times ``ambient + (1 − ambient)·cosine (k,)``; a
    face turned straight at the light keeps its colour."""
    return np.asarray(rgb, float) * (ambient + (1.0 - ambient) * np.asarray(cosine, float))[:, None]


def _draw_faces(ax, polygons: np.ndarray, rgb: np.ndarray, alpha: float = 1.0) -> None:
    rgba = np.c_[rgb, np.full(len(rgb), alpha)]
    # opaque faces get a 1-point edge of their own colour: it closes the light seams anti-aliasing
    # leaves between neighbours (a nearer face, painted later, covers a farther one's edge)
    edges = rgba if alpha >= 1.0 else "none"
    ax.add_collection(PolyCollection(polygons, facecolors=rgba, edgecolors=edges, linewidths=1.0))


def _half_size(extents) -> np.ndarray:
    """``(2,) float`` mm: half of every panel's width and height, the largest of ``extents`` (each
    panel's surface's ``(lo (2,), hi (2,))`` mm) across and up, plus a 3 % margin on each side."""
    return np.max([0.5 * (np.asarray(hi) - np.asarray(lo)) for lo, hi in extents], axis=0) * 1.06


def _panel_title(r: int, c: int, view: str, row_titles: Sequence[str | None] | None) -> str:
    """The title of the panel in row ``r``, column ``c`` (showing ``view``): the row's title on the
    left column, the view on the top row ("row: view" where both), else ''."""
    name = [row_titles[r]] if row_titles is not None and c == 0 and row_titles[r] else []
    return ": ".join(name + ([view] if r == 0 else []))


def _frame_views(axes: np.ndarray, mids: np.ndarray, half: np.ndarray, views: Sequence[str],
                 row_titles: Sequence[str | None] | None = None) -> None:
    """Every panel of ``axes : (rows, len(views))`` shows ``mids : (rows · len(views), 2) float`` mm
    (row by row: each panel's surface's centre) ± ``half : (2,) float`` mm, so the same mm per inch in
    every panel; axes named by the patient direction they point to (the bottom row and the left
    column, every row and column showing the same views), each column's view on the top row,
    ``row_titles`` on the left column; mm ticks (one or two rows: :func:`error_maps` shows more
    rows as one image, :func:`_mosaic`)."""
    rows = axes.shape[0]
    for k, (ax, mid) in enumerate(zip(axes.ravel(), mids)):
        r, c = divmod(k, len(views))
        view = views[c]
        ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
        ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
        ax.set_aspect("equal")
        across, upward = VIEW_DIRECTIONS[view]
        ax.set_title(_panel_title(r, c, view, row_titles), fontsize=9 if rows > 1 else None)
        if r == rows - 1:
            ax.set_xlabel(f"mm, toward {across} →", fontsize=8)
        if c == 0:
            ax.set_ylabel(f"mm, toward {upward} →", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.locator_params(nbins=5)


def _extent(polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = polygons.reshape(-1, 2)
    return (pts.min(0), pts.max(0)) if len(pts) else (np.zeros(2), np.ones(2))


def merge_surfaces(surfaces: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Several ``(vertices (n, 3), faces (m, 3))`` as one mesh (faces renumbered), so that the painter
    sorts their faces together (a lung in front of the other covers it whatever the order given)."""
    vertices = [np.asarray(v, float).reshape(-1, 3) for v, _ in surfaces]
    offsets = np.cumsum([0] + [len(v) for v in vertices[:-1]])
    faces = [np.asarray(f).reshape(-1, 3) + o for (_, f), o in zip(surfaces, offsets)]
    return np.concatenate(vertices or [np.zeros((0, 3))]), np.concatenate(faces or [np.zeros((0, 3), int)])


def snapshot(layers: Sequence[tuple[Sequence[tuple[np.ndarray, np.ndarray]], str, float]], *,
             views: Sequence[str] = ("anterior", "lateral-right"), title: str | None = None) -> Figure:
    """One panel per view of shaded surfaces. ``layers = [(surfaces, colour, alpha), …]``, each
    ``surfaces`` a list of ``(vertices (n, 3) mm LPS, faces (m, 3) wound outward)`` painted together
    back to front; layers are drawn in order (a later opaque layer covers an earlier one: draw the
    larger surfaces first to see them as a rim around the smaller)."""
    merged = [(*merge_surfaces(surfaces), colour, alpha) for surfaces, colour, alpha in layers]
    fig = new_figure(4.2 * len(views), 4.8, layout="constrained")
    axes = fig.subplots(1, len(views), squeeze=False)[0]
    extents = []
    for ax, view in zip(axes, views):
        lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
        for vertices, faces, colour, alpha in merged:
            polygons, cosine, _ = project(vertices, faces, view)
            rgb = shade(np.tile(to_rgb(colour), (len(cosine), 1)), cosine, ambient=0.25)
            _draw_faces(ax, polygons, rgb, alpha)
            a, b = _extent(polygons)
            lo, hi = np.minimum(lo, a), np.maximum(hi, b)
        extents.append((lo, hi))
    _frame_views(axes[None, :], [0.5 * (lo + hi) for lo, hi in extents], _half_size(extents), views)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def error_colours(values: np.ndarray, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """``values (k,)`` (mm) → RGB ``(k, 3)`` on the colour scale ``[0, vmax]`` (above: the top colour;
    NaN: grey)."""
    scale = colormaps[cmap].with_extremes(bad="0.6")
    return scale(Normalize(0.0, vmax, clip=True)(np.asarray(values, float)))[:, :3]


@dataclass(frozen=True)
class PanelImages:
    """Panels painted to one scale (:func:`paint_panels`). ``images : (p, h, w, 4) uint8`` RGBA
    (alpha: the covered fraction of each pixel), one per panel, row by row of the views;
    ``origins : (p, 2) float`` mm, each image's top-left corner in its view's plane (x toward the
    image right, y up); ``mm_per_pixel`` the same in every panel."""

    images: np.ndarray
    origins: np.ndarray
    mm_per_pixel: float

    @property
    def size(self) -> np.ndarray:
        """``(2,) float`` mm: every panel's width and height."""
        return np.array(self.images.shape[2:0:-1], float) * self.mm_per_pixel

    def extent(self, k: int) -> tuple[float, float, float, float]:
        """Panel ``k``'s (left, right, bottom, top) in mm of its view's plane (``imshow``'s extent)."""
        (x0, y1), (w, h) = self.origins[k], self.size
        return x0, x0 + w, y1 - h, y1


def panel_frames(extents: np.ndarray, box_px: tuple[float, float]) -> tuple[float, tuple[int, int], np.ndarray]:
    """One scale for every panel: ``extents : (p, 2, 2) float`` mm (each panel's surface's lowest and
    highest x, y in its view's plane), ``box_px`` the pixels (across, up) a panel may take. Returns
    ``mm_per_pixel`` (the common panel size of :func:`_half_size` fitted in the box), the panels'
    ``shape (h, w)`` pixels and ``origins : (p, 2) float`` mm (each image's top-left corner, so that
    it is centred on its surface)."""
    ext = np.asarray(extents, float).reshape(-1, 2, 2)
    size = np.maximum(2.0 * _half_size(ext), 1e-6)  # a surface of one point: a panel of a nanometre
    mm_per_pixel = float(np.max(size / np.asarray(box_px, float)))
    w, h = (max(round(float(n)), 1) for n in size / mm_per_pixel)
    origins = ext.mean(axis=1) + np.array([-0.5 * w, 0.5 * h]) * mm_per_pixel
    return mm_per_pixel, (h, w), origins


def paint_panels(rows: Sequence[tuple[np.ndarray, np.ndarray]], faces: np.ndarray, views: Sequence[str],
                 vmax: float, box_px: tuple[float, float], supersample: int = 3) -> PanelImages:
    """The error map's panels as images (:func:`lungdeform.plot.raster.paint`): for each ``(vertices
    (n, 3) mm LPS, error (n,) mm)`` of ``rows`` and each view, the faces facing the viewer, coloured by
    their vertices' mean error on ``[0, vmax]`` (NaN grey) and Lambert-shaded, far first; all panels
    to the scale of :func:`panel_frames` in ``box_px`` pixels, ``supersample²`` samples a pixel."""
    faces = np.asarray(faces)
    drawn, extents = [], []
    for vertices, error in rows:
        face_error = np.asarray(error, float)[faces].mean(axis=1)
        normals = unit_normals(vertices, faces)
        for view in views:
            polygons, cosine, index = project(vertices, faces, view, normals)
            drawn.append((polygons, shade(error_colours(face_error[index], vmax), cosine, ambient=0.55)))
            extents.append(_extent(polygons))
    mm_per_pixel, shape, origins = panel_frames(extents, box_px)
    images = np.empty((len(drawn), *shape, 4), np.uint8)
    for k, ((polygons, rgb), origin) in enumerate(zip(drawn, origins)):
        images[k] = np.rint(paint(polygons, rgb, origin, mm_per_pixel, shape, supersample) * 255.0)
    return PanelImages(images, origins, mm_per_pixel)


def _panel_axes(fig: Figure, boxes: np.ndarray, panels: PanelImages, views: Sequence[str],
                row_titles: Sequence[str | None] | None) -> tuple[float, float, float]:
    """Few rows: one Axes per panel (``boxes : (rows, cols, 4)`` inches of :func:`grid_boxes`), the
    panel shown by ``imshow`` in mm, with ticks (:func:`_frame_views`). Returns the colour bar's
    anchor: the right, top and bottom of the last column's panels (figure fractions)."""
    size = np.array([fig.get_figwidth(), fig.get_figheight()] * 2)
    axes = np.empty(boxes.shape[:2], dtype=object)
    for k, box in enumerate(boxes.reshape(-1, 4)):
        axes.flat[k] = ax = fig.add_axes(tuple(box / size))
        ax.imshow(panels.images[k], extent=panels.extent(k), interpolation="nearest")
    mids = panels.origins + np.array([0.5, -0.5]) * panels.size
    _frame_views(axes, mids, 0.5 * panels.size, views, row_titles)
    top, bottom = axes[0, -1].get_position(), axes[-1, -1].get_position()
    return top.x1, top.y1, bottom.y0


def _mosaic(fig: Figure, boxes: np.ndarray, panels: PanelImages, views: Sequence[str],
            row_titles: Sequence[str | None] | None) -> tuple[float, float, float]:
    """Many rows: every panel in one image drawn pixel for pixel (:class:`PixelImage`; each panel
    centred in its box, ``boxes : (rows, cols, 4)`` inches of :func:`grid_boxes`), a frame around each,
    titles and axis directions as text, on the figure itself (no Axes: no ticks, and none of an Axes'
    cost). Returns the colour bar's anchor: the right, top and bottom of the last column's panels
    (figure fractions)."""
    dpi = fig.dpi
    width, height = fig.get_figwidth() * dpi, fig.get_figheight() * dpi
    h, w = panels.images.shape[1:3]
    left = np.rint(boxes[..., 0] * dpi + 0.5 * (boxes[..., 2] * dpi - w)).astype(int)
    top = np.rint(height - (boxes[..., 1] + boxes[..., 3]) * dpi + 0.5 * (boxes[..., 3] * dpi - h)).astype(int)
    r0, c0 = top.min(), left.min()
    image = np.zeros((top.max() + h - r0, left.max() + w - c0, 4), np.uint8)
    for k, (r, c) in enumerate(zip(top.ravel() - r0, left.ravel() - c0)):
        image[r:r + h, c:c + w] = panels.images[k]
    fig.add_artist(PixelImage(image, (c0, r0), dpi))
    # figure pixels at the figure's dpi, y down (scaled with the figure when drawn at another dpi)
    pixels = Affine2D().scale(1.0 / dpi, -1.0 / dpi).translate(0.0, fig.get_figheight()) + fig.dpi_scale_trans
    frames = [[(c, r), (c + w, r), (c + w, r + h), (c, r + h)] for r, c in zip(top.ravel(), left.ravel())]
    fig.add_artist(PolyCollection(frames, facecolors="none", edgecolors="black", linewidths=0.8, transform=pixels))
    _mosaic_labels(fig, pixels, top, left, (h, w), views, row_titles)
    return (left[0, -1] + w) / width, 1.0 - top[0, -1] / height, 1.0 - (top[-1, -1] + h) / height


def _mosaic_labels(fig: Figure, pixels, top: np.ndarray, left: np.ndarray, shape: tuple[int, int],
                   views: Sequence[str], row_titles: Sequence[str | None] | None) -> None:
    """The texts of :func:`_mosaic`, placed in figure pixels (the transform ``pixels``, y down): each
    column's view on the top row, ``row_titles`` above the left column, the patient direction along
    each axis under the bottom row and left of the left column, as an Axes would have them. ``top,
    left : (rows, cols) int`` each panel's top-left pixel, ``shape (h, w)`` pixels."""
    h, w = shape
    pad = 6.0 / 72.0 * fig.dpi  # matplotlib's title and label padding, 6 points
    for r in range(top.shape[0]):
        for c, view in enumerate(views):
            title = _panel_title(r, c, view, row_titles)
            if title:
                fig.text(left[r, c] + 0.5 * w, top[r, c] - pad, title, fontsize=9, ha="center", va="bottom",
                         transform=pixels)
    for c, view in enumerate(views):
        fig.text(left[-1, c] + 0.5 * w, top[-1, c] + h + pad, f"toward {VIEW_DIRECTIONS[view][0]} →", fontsize=8,
                 ha="center", va="top", transform=pixels)
    upward = VIEW_DIRECTIONS[views[0]][1]
    for r in range(top.shape[0]):
        fig.text(left[r, 0] - pad, top[r, 0] + 0.5 * h, f"toward {upward} →", fontsize=8, rotation=90,
                 ha="right", va="center", transform=pixels)


def error_map(vertices: np.ndarray, faces: np.ndarray, error: np.ndarray, *,
              views: Sequence[str] = ("anterior", "lateral-right", "posterior"), vmax: float | None = None,
              title: str | None = None, label: str = "distance to the target surface (mm)") -> Figure:
    """The surface rendered from ``views``, each face coloured by the mean ``error (n,) float`` (mm)
    of its three vertices and Lambert-shaded; one colour scale ``[0, vmax]`` (default: the 98th
    percentile, so that a few outliers do not wash it out) and one colour bar for all views.
    ``vertices : (n, 3) float`` mm LPS, ``faces : (m, 3) int`` wound outward. One row of
    :func:`error_maps`."""
    return error_maps([(vertices, error)], faces, views=views, vmax=vmax, title=title, label=label)


def error_maps(rows: Sequence[tuple[np.ndarray, np.ndarray]], faces: np.ndarray, *,
               views: Sequence[str] = ("anterior", "lateral-right", "posterior"), vmax: float | None = None,
               title: str | None = None, label: str = "distance to the target surface (mm)",
               row_titles: Sequence[str] | None = None) -> Figure:
    """Small multiples of :func:`error_map`, one figure: one row of ``views`` per ``(vertices (n, 3)
    mm LPS, error (n,) mm)`` of ``rows`` (surfaces of the same ``faces (m, 3)``, e.g. the predicted
    surface at each target of a 4-D CT), named by ``row_titles``; one colour scale ``[0, vmax]``
    (default: the 98th percentile of every row's errors) and one colour bar, the same mm per pixel in
    every panel (:func:`paint_panels`: each panel an image, painted here, not one matplotlib path per
    face). Laid out in inches (:func:`lungdeform.plot.figure.grid_boxes`); one or two rows: an Axes per
    panel with mm ticks; from three rows on, smaller panels, all in one image drawn on the figure
    itself (:func:`_mosaic`: no Axes, no ticks; the panels' common size is said in the title), so the figure costs about the same whatever the
    number of rows."""
    errors = [np.asarray(e, float) for _, e in rows]
    finite = np.concatenate([e[np.isfinite(e)] for e in errors] + [np.zeros(0)])
    if vmax is None:
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    many = len(rows) > 2
    cell = Cell(2.6, 2.6, left=0.6, bottom=0.25, top=0.3) if many else Cell(3.2, 3.4, left=0.6, bottom=0.5, top=0.35)
    dpi = 80 if many else 90
    width, height, boxes = grid_boxes(len(rows), len(views), cell, right_in=1.2,
                                      top_in=0.4 if title or many else 0.1)
    fig = new_figure(width, height, dpi=dpi)
    panels = paint_panels([(v, e) for (v, _), e in zip(rows, errors)], faces, views, vmax,
                          (cell.width * dpi, cell.height * dpi))
    anchor = (_mosaic if many else _panel_axes)(fig, boxes, panels, views, row_titles)
    _colour_bar(fig, anchor, vmax, bool(finite.size and finite.max() > vmax), label)
    if many:  # no ticks: the panels' common size said instead
        size = panels.size
        title = f"{title + '; ' if title else ''}every panel {size[0]:.0f} × {size[1]:.0f} mm"
    if title:
        fig.suptitle(title, fontsize=10, y=1.0 - 0.08 / fig.get_figheight(), va="top")
    return fig


def _colour_bar(fig: Figure, anchor: tuple[float, float, float], vmax: float, over: bool, label: str) -> None:
    """The error maps' colour bar, 0.25 inch right of the last column's panels (``anchor``: their
    right, top and bottom in figure fractions), from their top down, at most 4 inches tall."""
    right, top, bottom = anchor
    w = fig.get_figwidth()
    h = min(top - bottom, 4.0 / fig.get_figheight())
    cax = fig.add_axes((right + 0.25 / w, top - h, 0.18 / w, h))
    fig.colorbar(ScalarMappable(Normalize(0.0, vmax), colormaps["viridis"]), cax=cax, label=label,
                 extend="max" if over else "neither")
