"""Tracked points' displacement against volume or time (``lungdeform track``, :mod:`lungdeform.playback.trajectory`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from .figure import new_figure

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
