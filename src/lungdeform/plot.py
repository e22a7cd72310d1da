"""Every figure the package draws: matplotlib's object-oriented API on the Agg canvas.

Each figure function builds and returns a :class:`matplotlib.figure.Figure` with its own
:class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`; :func:`save_png` writes one atomically
(:mod:`lungdeform.atomic`) and :func:`png_bytes` returns its bytes (e.g. to embed in HTML). No pyplot
and no ``matplotlib.use``: a Figure on its own Agg canvas needs no backend choice and keeps no global
state, so it is safe in library code, tests and Dask workers.

Surfaces are drawn by a small painter (no GPU or display): faces facing the viewer are Lambert-shaded
by a headlight and drawn back to front, enough for a closed lung surface seen from outside. Views are
named in the patient frame (:data:`VIEWS`): ``anterior`` looks at the patient's front (patient left on
the image right), ``posterior`` at the back, ``lateral-left`` / ``lateral-right`` from the sides,
``superior`` from above. Coordinates are mm, LPS (+x patient left, +y posterior, +z head).

Owns: figures of lung surfaces (:func:`snapshot`, :func:`error_map`), error distributions
(:func:`cumulative_errors`), the fit report's plots, the segmentation overlay, point motion, breathing
curves and their prediction, cohort statistics and the paper's Figs. 7–9. May import:
:mod:`lungdeform.atomic` only (and numpy, matplotlib): every layer above may draw.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PolyCollection
from matplotlib.colors import ListedColormap, Normalize, to_rgb
from matplotlib.figure import Figure

from lungdeform.atomic import write_bytes


# =========================================================================== figures and files
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


# =========================================================================== surfaces
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


def _frame_views(axes, extents: list[tuple[np.ndarray, np.ndarray]], views: Sequence[str]) -> None:
    """Same mm per inch in every panel (the largest extent across and up), each panel centred on its
    surface; axes named by the patient direction they point to."""
    half = np.max([0.5 * (hi - lo) for lo, hi in extents], axis=0) * 1.06
    for ax, (lo, hi), view in zip(axes, extents, views):
        mid = 0.5 * (lo + hi)
        ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
        ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
        ax.set_aspect("equal")
        across, upward = VIEW_DIRECTIONS[view]
        ax.set_title(view)
        ax.set_xlabel(f"mm, toward {across} →", fontsize=8)
        ax.set_ylabel(f"mm, toward {upward} →", fontsize=8)
        ax.tick_params(labelsize=7)


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
    _frame_views(axes, extents, views)
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
    ``vertices : (n, 3) float`` mm LPS, ``faces : (m, 3) int`` wound outward."""
    error = np.asarray(error, float)
    finite = error[np.isfinite(error)]
    if vmax is None:
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    face_error = error[np.asarray(faces)].mean(axis=1)
    fig = new_figure(3.6 * len(views) + 1.2, 4.6, dpi=90, layout="constrained")
    axes = fig.subplots(1, len(views), squeeze=False)[0]
    extents = []
    for ax, view in zip(axes, views):
        polygons, cosine, index = project(vertices, faces, view)
        _draw_faces(ax, polygons, shade(error_colours(face_error[index], vmax), cosine, ambient=0.55))
        extents.append(_extent(polygons))
    _frame_views(axes, extents, views)
    over = finite.size and finite.max() > vmax
    fig.colorbar(ScalarMappable(Normalize(0.0, vmax), colormaps["viridis"]), ax=axes, shrink=0.85,
                 label=label, extend="max" if over else "neither")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


# =========================================================================== distributions
#: line styles after the ten colours of the default cycle are used up
_STYLES = ("-", "--", ":", "-.")


def cumulative_errors(errors: dict[str, np.ndarray], *, xlabel: str = "distance to the target surface (mm)",
                      ylabel: str = "fraction of vertices", title: str | None = None) -> Figure:
    """One cumulative distribution per method (``name → errors (k,) mm``; NaN left out), the median
    of each marked by a dot and given in the legend, methods in order of their median. The x axis runs
    to the largest 99th percentile."""
    fig = new_figure(9.0, 4.2, dpi=90, layout="constrained")
    ax = fig.subplots()
    clean = {name: np.sort(e[np.isfinite(e)]) for name, e in ((n, np.asarray(e, float)) for n, e in errors.items())}
    ranked = sorted((name for name in clean if clean[name].size), key=lambda name: np.median(clean[name]))
    for k, name in enumerate(ranked):
        e = clean[name]
        colour, style = f"C{k % 10}", _STYLES[(k // 10) % len(_STYLES)]
        med = float(np.median(e))
        ax.step(np.r_[0.0, e], np.r_[0.0, np.arange(1, e.size + 1) / e.size], where="post", color=colour,
                linestyle=style, linewidth=1.4, label=f"{name} (median {med:.2f} mm)")
        ax.plot([med], [0.5], "o", color=colour, markersize=5)
    hi = max((float(np.percentile(clean[name], 99)) for name in ranked), default=1.0)
    ax.axhline(0.5, color="0.75", linewidth=0.8, zorder=0)
    ax.set_xlim(0.0, max(hi, 1e-3) * 1.05)
    ax.set_ylim(0.0, 1.01)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if ranked:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="method (dot: median)",
                  title_fontsize=8)
    if title:
        ax.set_title(title)
    return fig


# =========================================================================== fit report
def ray_histogram(counts: np.ndarray, edges: np.ndarray) -> Figure:
    """Counts of rays per bin of signed hit distance along the fitted direction (mm)."""
    fig = new_figure(7.0, 3.5, dpi=80, layout="constrained")
    ax = fig.subplots()
    ax.stairs(counts, edges, fill=True)
    ax.set_xlabel("signed ray hit distance along d (mm)")
    ax.set_ylabel("rays")
    return fig


def bounding_box(bb: dict) -> Figure:
    """Bounding-box dimensions (mm) and volume / box volume against lung volume (mL), model lines and
    observed dots (paper Fig. 4). ``bb``: ``{"model"|"observed": [{"volume_ml", "dims_mm", "ratio"}, …]}``."""
    fig = new_figure(11.0, 4.0, dpi=80, layout="constrained")
    a1, a2 = fig.subplots(1, 2)
    for key, style in (("model", "-"), ("observed", "o")):
        rows = bb[key]
        v = [r["volume_ml"] for r in rows]
        d = np.array([r["dims_mm"] for r in rows]).reshape(-1, 3)
        for k, lab in enumerate("xyz"):
            a1.plot(v, d[:, k], style, label=f"{lab} ({key})", color=f"C{k}")
        a2.plot(v, [r["ratio"] for r in rows], style, color="k", label=key)
    a1.set_xlabel("lung volume (mL)")
    a1.set_ylabel("bounding-box dimension (mm)")
    a1.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    a2.axhspan(0.32, 0.40, color="0.9", label="paper Fig. 4b range")
    a2.set_xlabel("lung volume (mL)")
    a2.set_ylabel("volume / bounding-box volume")
    a2.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    for ax in (a1, a2):
        ax.xaxis.get_major_locator().set_params(nbins=5)
    return fig


def direction_field(points: np.ndarray, directions: np.ndarray, magnitude: np.ndarray) -> Figure:
    """Arrows of unit ``directions (n, 3)`` at ``points (n, 3)`` mm LPS in a coronal and a sagittal
    projection (arrow length: the projected direction), coloured by ``magnitude (n,)`` (mm per unit);
    at most about 600 arrows."""
    fig = new_figure(11.0, 5.0, dpi=80, layout="constrained")
    axes = fig.subplots(1, 2)
    step = max(1, len(points) // 600)
    p, d, m = points[::step], directions[::step], magnitude[::step]
    # a unit direction is drawn 5 % of the lung's largest extent long (its projection shorter)
    length = 0.05 * float(np.ptp(p, axis=0).max()) if len(p) else 1.0
    for ax, (a, b, xl, title) in zip(axes, ((0, 2, "x (mm, toward patient left)", "coronal projection"),
                                            (1, 2, "y (mm, toward posterior)", "sagittal projection"))):
        q = ax.quiver(p[:, a], p[:, b], d[:, a], d[:, b], m, cmap="plasma", angles="xy", scale_units="xy",
                      scale=1.0 / length, width=0.004)
        ax.set_xlabel(xl)
        ax.set_ylabel("z (mm, toward head)")
        ax.set_title(title)
        ax.set_aspect("equal")
    fig.colorbar(q, ax=axes, label="|u| per unit (mm)", shrink=0.8)
    return fig


def fit_history(history: dict[str, np.ndarray]) -> Figure:
    """Best objective so far (RMS symmetric distance, mm) against evaluations, one line per fit."""
    fig = new_figure(7.0, 3.5, dpi=80, layout="constrained")
    ax = fig.subplots()
    for name, h in history.items():
        ax.plot(np.arange(1, len(h) + 1), h, label=name)
    ax.set_xlabel("objective evaluations")
    ax.set_ylabel("best RMS symmetric distance (mm)")
    if history:
        ax.legend()
    return fig


# =========================================================================== CT overlay
#: label → RGBA of the segmentation overlay: 0 none, 1 left lung blue, 2 right lung red, 3 airways yellow
OVERLAY_COLOURS = ((0, 0, 0, 0), (0.1, 0.4, 1.0, 0.4), (1.0, 0.15, 0.1, 0.4), (1.0, 0.9, 0.0, 0.7))


def label_overlay(panels: Sequence[tuple[np.ndarray, np.ndarray, float, str]], title: str) -> Figure:
    """CT slices (``(r, c)`` HU, window −1000…400) with labels over them (``(r, c)`` int, colours
    :data:`OVERLAY_COLOURS`), one panel per ``(ct, labels, aspect, panel title)``, drawn as given
    (radiological display: patient right on the image left, marked R and L)."""
    fig = new_figure(4.2 * len(panels), 4.6, dpi=90, layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    cmap = ListedColormap(OVERLAY_COLOURS)
    for ax, (img, lab, aspect, name) in zip(axes, panels):
        ax.imshow(img, cmap="gray", vmin=-1000, vmax=400, aspect=aspect, interpolation="nearest")
        ax.imshow(lab, cmap=cmap, vmin=0, vmax=3, aspect=aspect, interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.text(0.02, 0.5, "R", color="w", transform=ax.transAxes, fontsize=10)
        ax.text(0.95, 0.5, "L", color="w", transform=ax.transAxes, fontsize=10)
    fig.suptitle(title, fontsize=10)
    return fig


# =========================================================================== tracked points
_MOTION_AXES = ("LR", "AP", "SI")


def motion(displacement: np.ndarray, x: np.ndarray, xlabel: str, labels: Sequence[str], *,
           sort_x: bool = False, max_points: int = 12) -> Figure:
    """Displacement ``(f, q, 3)`` mm (LPS) of the first ``max_points`` points against ``x (f,)``, one
    panel per axis; ``sort_x``: draw in order of ``x`` (a volume, not a time)."""
    fig = new_figure(11.0, 3.4, layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    order = np.argsort(x) if sort_x else np.arange(len(x))
    for k, (ax, name) in enumerate(zip(axes, _MOTION_AXES)):
        for j in range(min(displacement.shape[1], max_points)):
            ax.plot(x[order], displacement[order, j, k], marker="." if len(x) < 20 else None, label=str(labels[j]))
        ax.set_title(f"{name} displacement (LPS {'xyz'[k]})")
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("displacement (mm)")
    if displacement.shape[1] <= max_points:
        axes[-1].legend(fontsize=7, loc="best")
    else:
        axes[-1].set_title(f"SI displacement (first {max_points} of {displacement.shape[1]} points)")
    return fig


# =========================================================================== breathing curves
def breathing_volume(t_s: np.ndarray, volume_ml: np.ndarray, title: str, *, data=None,
                     held_out_from: float | None = None) -> Figure:
    """Volume (mL) against time (s); ``data = (t_s, volume_ml)`` of a calibrated trace drawn under it;
    ``held_out_from``: shade the held-out cycles from that time on."""
    fig = new_figure(10.0, 3.6, layout="constrained")
    ax = fig.subplots()
    if data is not None:
        ax.plot(data[0], data[1], lw=0.7, color="0.5", label="trace (calibrated)")
    ax.plot(t_s, volume_ml, lw=1.0, color="C0", label="PV model")
    if held_out_from is not None:
        ax.axvspan(held_out_from, t_s[-1], color="C1", alpha=0.08, label="held-out cycles")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    return fig


def pv_loop(pressure_cmh2o: np.ndarray, volume_ml: np.ndarray, title: str) -> Figure:
    """Volume (mL) against muscle pressure (cmH2O) over the breath."""
    fig = new_figure(4.8, 4.2, layout="constrained")
    ax = fig.subplots()
    ax.plot(pressure_cmh2o, volume_ml, lw=0.8)
    ax.set_xlabel("muscle pressure P_mus (cmH2O)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title, fontsize=10)
    return fig


def residuals(t_s: np.ndarray, resid: np.ndarray, title: str, ylabel: str = "residual (mL)") -> Figure:
    """A residual against time (s) with the zero line."""
    fig = new_figure(10.0, 3.0, layout="constrained")
    ax = fig.subplots()
    ax.plot(t_s, resid, lw=0.7)
    ax.axhline(0.0, color="0.4", lw=0.5)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    return fig


def prediction_errors(horizons_ms: np.ndarray, model_over_linear: dict[str, Sequence[float]],
                      model_over_none: dict[str, Sequence[float]]) -> Figure:
    """Prediction error against horizon: per trace (thin lines) and their median (thick), as the
    model's RMS over the linear baseline's (left) and over no prediction (right); 1 = no better."""
    fig = new_figure(10.0, 3.8, layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    for ax, curves, title in ((axes[0], model_over_linear, "model / linear autoregression"),
                              (axes[1], model_over_none, "model / no prediction (last sample)")):
        rows = np.array([c for c in curves.values()], float)
        for c in rows:
            ax.plot(horizons_ms, c, color="0.7", lw=0.7)
        ax.plot(horizons_ms, np.nanmedian(rows, axis=0), "o-", color="C0", lw=2.0, label="median over traces")
        ax.axhline(1.0, color="0.3", lw=0.8, ls="--")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("prediction horizon (ms)")
        ax.set_ylabel("RMS ratio")
        ax.legend(loc="upper left", fontsize=8)
    return fig


def prediction_excerpt(t_s: np.ndarray, signal: np.ndarray, predictions: dict[str, np.ndarray],
                       horizon_s: float, *, start_s: float, title: str, unit: str = "",
                       length_s: float = 30.0) -> Figure:
    """``length_s`` of a trace from ``start_s`` with each predictor's predictions drawn at the time
    they predict (``t + horizon_s``), so a good prediction lies on the signal."""
    fig = new_figure(10.0, 3.6, layout="constrained")
    ax = fig.subplots()
    keep = (t_s >= start_s) & (t_s <= start_s + length_s)
    ax.plot(t_s[keep], signal[keep], color="black", lw=1.6, label="signal")
    styles = {"model": ("C0", "-"), "linear": ("C1", "--"), "none": ("0.55", ":")}
    for name, p in predictions.items():
        shown = keep & (t_s + horizon_s <= start_s + length_s)
        colour, ls = styles.get(name, (None, "-"))
        ax.plot(t_s[shown] + horizon_s, p[shown], color=colour, ls=ls, lw=1.0, label=f"{name} (made {horizon_s * 1000:.0f} ms earlier)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"signal ({unit})" if unit else "signal")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper right", fontsize=8, ncols=2)
    return fig


# =========================================================================== cohort statistics
def panel_grid(rows: int, cols: int, size=(3.2, 2.6)):
    """A Figure of ``rows × cols`` panels of ``size`` inches each and a title row; returns
    ``(figure, axes (rows, cols))``."""
    height = size[1] * rows
    fig = new_figure(size[0] * cols, height)
    # fixed margins in inches (constrained layout costs a second per figure): title, axis labels
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.6 / height, top=1 - 0.75 / height, hspace=0.75, wspace=0.35)
    return fig, fig.subplots(rows, cols, squeeze=False)


def _size(points: float | None) -> dict:
    """``fontsize`` only where one is given (``fontsize=None`` would not mean the default)."""
    return {} if points is None else {"fontsize": points}


@dataclass(frozen=True)
class StripPanel:
    """One panel of :func:`strip_boxes`: a group of values per tick, an optional reference per group."""

    title: str
    groups: list[np.ndarray]
    ticks: list[str]
    reference: list[float] | None = None
    title_size: float | None = None


def strip_boxes(panels: Sequence[StripPanel], colours: Sequence[str], *, rows: int, cols: int, title: str,
                rng: np.random.Generator, reference_label: str = "reference") -> Figure:
    """Per panel, a box (median, quartiles) and the jittered points of each group at x = 0, 1, …, and
    the reference of each group as a red bar (labelled in the first panel). ``rng``: the jitter."""
    fig, axes = panel_grid(rows, cols)
    for k, p in enumerate(panels):
        ax = axes.flat[k]
        for x, (vals, col) in enumerate(zip(p.groups, colours)):
            vals = vals[np.isfinite(vals)]
            if len(vals) == 0:
                continue
            if len(vals) > 1:
                ax.boxplot([vals], positions=[x], widths=0.5, showfliers=False, manage_ticks=False,
                           medianprops={"color": "black"})
            ax.scatter(x + rng.uniform(-0.12, 0.12, len(vals)), vals, s=14, color=col, alpha=0.8, zorder=3)
        for x, ref in enumerate(p.reference or []):
            ax.hlines(ref, x - 0.35, x + 0.35, colors="red", linewidth=2,
                      label=reference_label if x == 0 else None, zorder=4)
        ax.set_xticks(range(len(p.ticks)), p.ticks)
        ax.set_xlim(-0.6, len(p.ticks) - 0.4)
        ax.set_title(p.title, **_size(p.title_size))
        if k == 0 and p.reference:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle(title)
    return fig


@dataclass(frozen=True)
class ScatterPanel:
    """One panel of :func:`scatter_grid`: points ``(k, 2)`` per series, optional dashed level per series."""

    title: str
    series: dict[str, np.ndarray]
    levels: dict[str, float] = field(default_factory=dict)
    identity: bool = False
    xlabel: str | None = None
    ylabel: str | None = None
    xlabel_size: float | None = None
    title_size: float | None = None
    legend: bool = False


def scatter_grid(panels: Sequence[ScatterPanel], colours: dict[str, str], *, rows: int, cols: int,
                 title: str) -> Figure:
    """Scatter panels: one colour per series (:data:`colours`), a dashed line at each series' level,
    the identity line over the range of all points where asked, a legend where asked and non-empty."""
    fig, axes = panel_grid(rows, cols)
    for k, p in enumerate(panels):
        ax = axes.flat[k]
        for name, pts in p.series.items():
            pts = np.asarray(pts, float).reshape(-1, 2)
            ax.scatter(pts[:, 0], pts[:, 1], s=14, color=colours[name], label=name)
        for name, level in p.levels.items():
            ax.axhline(level, color=colours[name], linestyle="--", linewidth=1)
        vals = np.concatenate([np.asarray(s, float).ravel() for s in p.series.values()] or [np.zeros(0)])
        vals = vals[np.isfinite(vals)]
        if p.identity and len(vals):
            lo, hi = vals.min(), vals.max()
            pad = 0.05 * (hi - lo) or 0.05 * abs(hi) or 0.05
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="grey", linewidth=1)
        ax.set_title(p.title, **_size(p.title_size))
        if p.xlabel:
            ax.set_xlabel(p.xlabel, **_size(p.xlabel_size))
        if p.ylabel:
            ax.set_ylabel(p.ylabel)
        if p.legend and any(np.size(s) for s in p.series.values()):
            ax.legend(fontsize=7)
    fig.suptitle(title)
    return fig


# =========================================================================== the paper's Figs. 7-9
def planar_figure(vertices: np.ndarray, faces: np.ndarray, transfer_u: np.ndarray, msd_u: np.ndarray,
                  rms_percent: float) -> Figure:
    """Fig. 8: (a) the planar mesh (``vertices (n, 3)`` mm, ``faces (m, 3)``), (b) deformed by the
    out-of-plane transfer displacement ``transfer_u (n,)`` (exaggerated), (c) ``msd_u − transfer_u``
    as a % of the largest MSD displacement."""
    fig = new_figure(15.0, 4.8, dpi=100)
    v, f, u = vertices, faces, transfer_u
    span = float(np.ptp(v[:, :2], axis=0).max())
    exaggerate = 0.25 * span / max(float(np.abs(u).max()), 1e-300)
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=f, color="0.85", edgecolor="0.4", linewidth=0.2)
    ax.set_zlim(0, 0.3 * span)
    ax.set_title("(a) regular planar mesh, uniform E")
    ax = fig.add_subplot(1, 3, 2, projection="3d")
    ax.plot_trisurf(v[:, 0], v[:, 1], exaggerate * u, triangles=f, cmap="viridis", edgecolor="0.3", linewidth=0.1)
    ax.set_zlim(0, 0.3 * span)
    ax.set_title(f"(b) deformed by the transfer model (×{exaggerate:.3g})")
    for a in fig.axes:
        a.set_xlabel("x (mm)")
        a.set_ylabel("y (mm)")
    ax = fig.add_subplot(1, 3, 3)
    diff = 100.0 * (msd_u - u) / float(np.abs(msd_u).max())
    im = ax.tripcolor(v[:, 0], v[:, 1], f, diff, shading="gouraud", cmap="coolwarm")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"(c) MSD − transfer, % of max (RMS {rms_percent:.2g} %)")
    fig.colorbar(im, ax=ax, shrink=0.8, label="% of the largest MSD displacement")
    fig.subplots_adjust(left=0.02, right=0.95, wspace=0.15)
    return fig


def circular_figure(vertices: np.ndarray, faces: np.ndarray, moduli: np.ndarray, displacement: np.ndarray,
                    radial_displacement: np.ndarray, stiff_to_soft: float, position_controlled: float) -> Figure:
    """Fig. 9: (a) the disc mesh (``vertices (n, 3)`` mm), node size ∝ ``moduli (n,)``; (b) deformed
    by ``displacement (n, 3)`` (exaggerated by the largest ``radial_displacement (n,)``)."""
    fig = new_figure(12.0, 5.4, dpi=100)
    v, f, e = vertices, faces, moduli
    radius = float(np.linalg.norm(v[:, :2], axis=1).max())
    exaggerate = 0.25 * radius / max(float(np.abs(radial_displacement).max()), 1e-300)
    w = v + exaggerate * displacement
    sizes = 4 + 60 * (e - e.min()) / max(float(np.ptp(e)), 1e-300)
    lim = 1.3 * radius
    for k, (pts, title) in enumerate([(v, "(a) 2-D circular mesh, node size ∝ E"),
                                      (w, f"(b) deformed, unit radial force (×{exaggerate:.3g})")]):
        ax = fig.add_subplot(1, 2, k + 1)
        if k == 1:
            ax.triplot(v[:, 0], v[:, 1], f, color="0.8", linewidth=0.4)
        ax.triplot(pts[:, 0], pts[:, 1], f, color="0.35", linewidth=0.5)
        sc = ax.scatter(pts[:, 0], pts[:, 1], s=sizes, c=np.log10(e), cmap="plasma", zorder=3)
        ax.set_aspect("equal")
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title)
    fig.subplots_adjust(left=0.06, right=0.86, bottom=0.14, top=0.93, wspace=0.25)
    fig.colorbar(sc, cax=fig.add_axes((0.89, 0.2, 0.015, 0.65)), label="log10 E")
    fig.text(0.06, 0.03, f"stiff/soft mean radial displacement ratio {stiff_to_soft:.3f}"
             f" (position-controlled {position_controlled:.3f}); grey = original")
    return fig


def convergence_figure(push_sweeps: np.ndarray, push_residual: np.ndarray, msd_residual: np.ndarray,
                       msd_error: np.ndarray, *, tol: float, n_nodes: int, title: str) -> Figure:
    """Fig. 7: relative residual (log scale) against sweeps (node updates / ``n_nodes``): the push
    loop's ``push_residual`` at ``push_sweeps``, the MSD's residual and error per step (= sweep)."""
    fig = new_figure(8.0, 5.5, dpi=100, layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.semilogy(push_sweeps, np.maximum(push_residual, 1e-300), label="push loop: max|Pitcher| / max|f|")
    steps = np.arange(len(msd_residual))
    ax.semilogy(steps, np.maximum(msd_residual, 1e-300), label="MSD: max|f − K u| / max|f|")
    ax.semilogy(steps, np.maximum(msd_error, 1e-300), "--", label="MSD: max|u − C| / max|C|")
    ax.axhline(tol, color="0.5", linewidth=0.8, linestyle=":")
    ax.set_xlabel(f"sweeps (node updates / {n_nodes} graph nodes); 1 MSD step = 1 sweep")
    ax.set_ylabel("relative residual")
    ax.set_title(title)
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    return fig


# =========================================================================== grouped bars
def grouped_bars(values: dict[str, dict[str, float]], *, title: str, ylabel: str) -> Figure:
    """Bars of ``values[group][series]`` (e.g. lung → method → mean landmark error, mm): one
    cluster per series, one bar per group in it; missing or non-finite values are left out."""
    groups = list(values)
    series = list(dict.fromkeys(s for g in groups for s in values[g]))
    fig = new_figure(max(5.0, 0.75 * len(series) + 2.0), 3.2, layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / max(len(groups), 1)
    x = np.arange(len(series))
    for k, g in enumerate(groups):
        y = np.array([values[g].get(s, np.nan) for s in series], float)
        ax.bar(x + (k - (len(groups) - 1) / 2) * width, np.where(np.isfinite(y), y, 0.0), width, label=g)
    ax.set_xticks(x, series, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    return fig
