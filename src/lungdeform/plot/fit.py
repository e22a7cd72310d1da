"""The fit report's figures: error distributions, ray hits, bounding boxes, the direction field and
the search's history (:mod:`lungdeform.evaluate.report`).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .figure import Cell, grid_figure

#: line styles after the ten colours of the default cycle are used up
_STYLES = ("-", "--", ":", "-.")


def cumulative_errors(errors: dict[str, np.ndarray], *, xlabel: str = "distance to the target surface (mm)",
                      ylabel: str = "fraction of vertices", title: str | None = None) -> Figure:
    """One cumulative distribution per method (``name → errors (k,) mm``; NaN left out), the median
    of each marked by a dot and given in the legend, methods in order of their median. The x axis runs
    to the largest 99th percentile. One panel of :func:`cumulative_panels`."""
    return cumulative_panels({title: errors}, xlabel=xlabel, ylabel=ylabel)


def _clean(panels: dict) -> dict:
    """``title → {name → errors}`` with each ``errors`` sorted and its NaNs left out."""
    return {t: {n: np.sort(np.asarray(e, float)[np.isfinite(np.asarray(e, float))]) for n, e in errors.items()}
            for t, errors in panels.items()}


def _colour_rank(clean: dict) -> dict[str, int]:
    """A method's colour index in every panel: its rank by median in the last panel (the headline)."""
    last = list(clean.values())[-1] if clean else {}
    return {n: k for k, n in enumerate(sorted((n for n in last if last[n].size), key=lambda n: np.median(last[n])))}


def _method_style(k: int) -> tuple[str, str]:
    """The colour and line style of the method of colour index ``k``."""
    return f"C{k % 10}", _STYLES[(k // 10) % len(_STYLES)]


def cumulative_panels(panels: dict[str | None, dict[str, np.ndarray]], *,
                      xlabel: str = "distance to the target surface (mm)",
                      ylabel: str = "fraction of vertices") -> Figure:
    """Small multiples of :func:`cumulative_errors`, one figure: a panel per ``title → {name → errors
    (k,) mm}`` (a title of None: no title), two panels a row from two on, each with its own legend
    (methods in order of their median there); a method keeps its colour in every panel (its rank in
    the last panel, the headline target). Laid out in inches (:func:`lungdeform.plot.figure.grid_figure`).
    For many targets :func:`target_errors` draws two panels instead of one each."""
    clean = _clean(panels)
    colour_rank = _colour_rank(clean)
    cols = 1 if len(clean) == 1 else 2
    rows = -(-len(clean) // cols)
    one = Cell(5.4, 3.3, left=0.7, right=2.9, bottom=0.55, top=0.3)
    cell = one if cols == 1 else Cell(4.2, 2.6, right=3.3, top=0.3)
    fig, axes = grid_figure(rows, cols, cell, dpi=90 if cols == 1 else 80)
    for ax, (title, errors) in zip(axes.ravel(), clean.items()):
        _cumulative_panel(ax, errors, colour_rank, 8 if cols == 1 else 7)
        ax.set_xlabel(xlabel, fontsize=None if cols == 1 else 8)
        ax.set_ylabel(ylabel, fontsize=None if cols == 1 else 8)
        if title:
            ax.set_title(title, fontsize=None if cols == 1 else 9, y=1.0)
    for ax in axes.ravel()[len(clean):]:
        ax.set_visible(False)
    return fig


def target_errors(panels: dict[str, dict[str, np.ndarray]], *, xlabel: str = "distance to the target surface (mm)",
                  ylabel: str = "fraction of vertices") -> Figure:
    """The errors of many targets in two panels (a 4-D CT's phases): the cumulative distribution of each
    method at the last target of ``panels`` (``title → {name → errors (k,) mm}``, the headline, as in
    :func:`cumulative_panels`), and beside it each method's median (solid, dots) and 95th percentile
    (dashed) at every target, targets along x in the order given; a method has the same colour in both."""
    clean = _clean(panels)
    colour_rank = _colour_rank(clean)
    fig, axes = grid_figure(1, 2, Cell(4.2, 2.9, left=0.7, right=3.3, bottom=0.75, top=0.3), dpi=80)
    headline, spread = axes[0]
    box = spread.get_position()  # the second panel wider: its legend is two short lines
    spread.set_position((box.x0, box.y0, box.width + 2.0 / fig.get_figwidth(), box.height))
    title = list(clean)[-1]
    _cumulative_panel(headline, clean[title], colour_rank, 7)
    headline.set_xlabel(xlabel, fontsize=8)
    headline.set_ylabel(ylabel, fontsize=8)
    headline.set_title(f"at {title} (the last target)", fontsize=9, y=1.0)
    x = np.arange(len(clean))
    for name, k in colour_rank.items():
        colour, _ = _method_style(k)
        stats = np.array([np.percentile(e[name], (50, 95)) if e.get(name, np.zeros(0)).size else (np.nan, np.nan)
                          for e in clean.values()])
        spread.plot(x, stats[:, 0], "o-", color=colour, linewidth=1.4, markersize=3)
        spread.plot(x, stats[:, 1], "--", color=colour, linewidth=1.0)
    spread.plot([], [], "k-", label="median")
    spread.plot([], [], "k--", label="95th percentile")
    spread.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    spread.set_xticks(x, list(clean), rotation=45 if max(map(len, clean), default=0) > 3 else 0, fontsize=7)
    spread.set_ylim(bottom=0.0)
    spread.set_ylabel(xlabel, fontsize=8)
    spread.set_xlabel("target", fontsize=8)
    spread.set_title("every target", fontsize=9, y=1.0)
    spread.grid(alpha=0.3)
    return fig


def _cumulative_panel(ax, clean: dict[str, np.ndarray], colour_rank: dict[str, int], fontsize: float) -> None:
    """One panel of :func:`cumulative_panels`: the sorted, finite ``clean`` errors (mm) per method."""
    ranked = sorted((name for name in clean if clean[name].size), key=lambda name: np.median(clean[name]))
    extra = len(colour_rank)
    for name in ranked:
        k = colour_rank.get(name)
        k, extra = (extra, extra + 1) if k is None else (k, extra)
        e = clean[name]
        colour, style = _method_style(k)
        med = float(np.median(e))
        ax.step(np.r_[0.0, e], np.r_[0.0, np.arange(1, e.size + 1) / e.size], where="post", color=colour,
                linestyle=style, linewidth=1.4, label=f"{name} (median {med:.2f} mm)")
        ax.plot([med], [0.5], "o", color=colour, markersize=5)
    hi = max((float(np.percentile(clean[name], 99)) for name in ranked), default=1.0)
    ax.axhline(0.5, color="0.75", linewidth=0.8, zorder=0)
    ax.set_xlim(0.0, max(hi, 1e-3) * 1.05)
    ax.set_ylim(0.0, 1.01)
    ax.grid(alpha=0.3)
    if ranked:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=fontsize, title="method (dot: median)",
                  title_fontsize=fontsize)


def ray_histogram(counts: np.ndarray, edges: np.ndarray) -> Figure:
    """Counts of rays per bin of signed hit distance along the fitted direction (mm)."""
    fig, axes = grid_figure(1, 1, Cell(6.0, 2.75, left=0.8, bottom=0.6, top=0.15))
    ax = axes[0, 0]
    ax.stairs(counts, edges, fill=True)
    ax.set_xlabel("signed ray hit distance along d (mm)")
    ax.set_ylabel("rays")
    return fig


def bounding_box(bb: dict) -> Figure:
    """Bounding-box dimensions (mm) and volume / box volume against lung volume (mL), model lines and
    observed dots (paper Fig. 4). ``bb``: ``{"model"|"observed": [{"volume_ml", "dims_mm", "ratio"}, …]}``."""
    fig, axes = grid_figure(1, 2, Cell(3.6, 3.25, left=0.8, right=1.6, bottom=0.6, top=0.15))
    a1, a2 = axes[0]
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
    fig, grid = grid_figure(1, 2, Cell(4.1, 4.1, left=0.8, right=0.1, bottom=0.6, top=0.3), right_in=1.0)
    axes = grid[0]
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
    box = axes[-1].get_position()
    cax = fig.add_axes((box.x1 + 0.15 / fig.get_figwidth(), box.y0 + 0.1 * box.height, 0.15 / fig.get_figwidth(),
                        0.8 * box.height))
    fig.colorbar(q, cax=cax, label="|u| per unit (mm)")
    return fig


def fit_history(history: dict[str, np.ndarray]) -> Figure:
    """Best objective so far (RMS symmetric distance, mm) against evaluations, one line per fit."""
    fig, axes = grid_figure(1, 1, Cell(6.0, 2.75, left=0.8, bottom=0.6, top=0.15))
    ax = axes[0, 0]
    for name, h in history.items():
        ax.plot(np.arange(1, len(h) + 1), h, label=name)
    ax.set_xlabel("objective evaluations")
    ax.set_ylabel("best RMS symmetric distance (mm)")
    if history:
        ax.legend()
    return fig
