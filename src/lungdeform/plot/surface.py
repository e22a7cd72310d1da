"""Lung surfaces drawn by a small painter (no GPU or display): faces facing the viewer are
Lambert-shaded by a headlight and drawn back to front, enough for a closed lung surface seen from
outside. Views are named in the patient frame (:data:`VIEWS`): ``anterior`` looks at the patient's
front (patient left on the image right), ``posterior`` at the back, ``lateral-left`` /
``lateral-right`` from the sides, ``superior`` from above. Coordinates are mm, LPS (+x patient left,
+y posterior, +z head). :func:`snapshot` draws layers of surfaces, :func:`error_map` one coloured by a
per-vertex error.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize, to_rgb
from matplotlib.figure import Figure

from .figure import Cell, grid_figure, new_figure

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


def project(vertices: np.ndarray, faces: np.ndarray, view: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces of a closed surface that face the viewer of ``view``, far first (painter's order).

    ``vertices : (n, 3) float`` mm LPS, ``faces : (m, 3) int`` wound outward. Returns ``polygons
    (k, 3, 2) float`` (mm along the image right and up), ``cosine (k,) float`` in (0, 1] (the angle
    between each face's outward normal and the direction to the viewer: the headlight's Lambert term)
    and ``index (k,) int`` (which face of ``faces`` each polygon is)."""
    eye, right, up = (np.asarray(a) for a in VIEWS[view])
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(n, axis=1)
    cosine = (n @ eye) / np.where(length > 0, length, 1.0)
    facing = np.nonzero(cosine > 0)[0]
    depth = v[f[facing]].mean(axis=1) @ eye
    index = facing[np.argsort(depth, kind="stable")]  # far first
    xy = np.stack([v @ right, v @ up], axis=1)
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


def _frame_views(axes: np.ndarray, extents: list[tuple[np.ndarray, np.ndarray]], views: Sequence[str],
                 row_titles: Sequence[str | None] | None = None) -> np.ndarray:
    """Same mm per inch in every panel of ``axes : (rows, len(views))`` (the largest extent across and
    up; ``extents`` row by row), each panel centred on its surface; axes named by the patient direction
    they point to (the bottom row and the left column, every row and column showing the same views),
    each column's view on the top row, ``row_titles`` on the left column; from three rows on, no
    ticks (each costs matplotlib a Tick object per panel, most of a 4-D CT's error map). Returns ``(2,)``
    mm: half of every panel's width and height."""
    half = np.max([0.5 * (hi - lo) for lo, hi in extents], axis=0) * 1.06
    rows = axes.shape[0]
    for k, (ax, (lo, hi)) in enumerate(zip(axes.ravel(), extents)):
        r, c = divmod(k, len(views))
        view = views[c]
        mid = 0.5 * (lo + hi)
        ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
        ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
        ax.set_aspect("equal")
        across, upward = VIEW_DIRECTIONS[view]
        name = [row_titles[r]] if row_titles is not None and c == 0 and row_titles[r] else []
        ax.set_title(": ".join(name + ([view] if r == 0 else [])), fontsize=9 if rows > 1 else None)
        if r == rows - 1:
            ax.set_xlabel(f"{'' if rows > 2 else 'mm, '}toward {across} →", fontsize=8)
        if c == 0:
            ax.set_ylabel(f"{'' if rows > 2 else 'mm, '}toward {upward} →", fontsize=8)
        if rows > 2:  # small multiples: no ticks (each panel is centred on its own surface, all to one scale)
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.tick_params(labelsize=7)
            ax.locator_params(nbins=5)
    return half


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
    _frame_views(axes[None, :], extents, views)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def error_colours(values: np.ndarray, vmax: float, cmap: str = "viridis") -> np.ndarray:
    """``values (k,)`` (mm) → RGB ``(k, 3)`` on the colour scale ``[0, vmax]`` (above: the top colour;
    NaN: grey)."""
    scale = colormaps[cmap].with_extremes(bad="0.6")
    return scale(Normalize(0.0, vmax, clip=True)(np.asarray(values, float)))[:, :3]


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
    (default: the 98th percentile of every row's errors) and one colour bar, the same mm per inch in
    every panel. Laid out in inches (:func:`lungdeform.plot.figure.grid_figure`), smaller panels and no
    ticks from three rows on (the panels' common scale is then said in the title)."""
    faces = np.asarray(faces)
    errors = [np.asarray(e, float) for _, e in rows]
    finite = np.concatenate([e[np.isfinite(e)] for e in errors] + [np.zeros(0)])
    if vmax is None:
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    many = len(rows) > 2
    cell = Cell(2.6, 2.6, left=0.6, bottom=0.25, top=0.3) if many else Cell(3.2, 3.4, left=0.6, bottom=0.5, top=0.35)
    fig, axes = grid_figure(len(rows), len(views), cell, right_in=1.2, top_in=0.4 if title or many else 0.1,
                            dpi=80 if many else 90)
    extents = []
    for r, ((vertices, _), error) in enumerate(zip(rows, errors)):
        face_error = error[faces].mean(axis=1)
        for ax, view in zip(axes[r], views):
            polygons, cosine, index = project(vertices, faces, view)
            _draw_faces(ax, polygons, shade(error_colours(face_error[index], vmax), cosine, ambient=0.55))
            extents.append(_extent(polygons))
    half = _frame_views(axes, extents, views, row_titles)
    over = finite.size and finite.max() > vmax
    top, bottom = axes[0, -1].get_position(), axes[-1, -1].get_position()
    w = fig.get_figwidth()
    h = min(top.y1 - bottom.y0, 4.0 / fig.get_figheight())  # at most 4 inches tall, from the top row down
    cax = fig.add_axes((top.x1 + 0.25 / w, top.y1 - h, 0.18 / w, h))
    fig.colorbar(ScalarMappable(Normalize(0.0, vmax), colormaps["viridis"]), cax=cax, label=label,
                 extend="max" if over else "neither")
    if many:  # no ticks: the panels' common size said instead
        width, height = 2.0 * half
        title = f"{title + '; ' if title else ''}every panel {width:.0f} × {height:.0f} mm"
    if title:
        fig.suptitle(title, fontsize=10, y=1.0 - 0.08 / fig.get_figheight(), va="top")
    return fig
