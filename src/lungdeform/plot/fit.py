"""The fit report's figures: error distributions, ray hits, bounding boxes, the direction field and
the search's history (:mod:`lungdeform.evaluate.report`).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .figure import new_figure

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
