"""The segmentation overlay: CT slices with the lung and airway labels over them (``lungdeform segment``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from .figure import new_figure

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
