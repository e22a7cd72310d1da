"""Statistics over lungs and methods: box-and-strip panels and scatter panels of a cohort, grouped
bars per method (cohort population and recovery, ``validate copd``, ``validate single-scan``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from matplotlib.figure import Figure

from .figure import new_figure


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


def grouped_bars(values: dict[str, dict[str, float]], *, title: str, ylabel: str) -> Figure:
    """Bars of ``values[group][series]`` (e.g. lung → method → mean landmark error, mm): one
    cluster per series, one bar per group in it; missing or non-finite values are left out. The
    legend sits under the axes in up to four columns, the figure as tall as its rows need (30 groups
    did not fit a legend inside the axes: matplotlib's layout gave up with a warning)."""
    groups = list(values)
    series = list(dict.fromkeys(s for g in groups for s in values[g]))
    columns = min(max(len(groups), 1), 4)  # the legend under the axes, its rows given their own height
    legend_rows = -(-len(groups) // columns)
    fig = new_figure(max(5.0, 0.75 * len(series) + 2.0), 3.2 + 0.2 * legend_rows, layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / max(len(groups), 1)
    x = np.arange(len(series))
    for k, g in enumerate(groups):
        y = np.array([values[g].get(s, np.nan) for s in series], float)
        ax.bar(x + (k - (len(groups) - 1) / 2) * width, np.where(np.isfinite(y), y, 0.0), width, label=g)
    ax.set_xticks(x, series, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    fig.legend(loc="outside lower center", ncol=columns, fontsize=7)
    return fig
