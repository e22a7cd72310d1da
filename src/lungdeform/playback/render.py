"""Offscreen PNG snapshots of lung surfaces (matplotlib, no GPU or display needed).

Faces are shaded by a headlight (Lambert) and drawn back to front, which is enough for a closed
lung surface seen from outside. Views are named in the patient frame: ``anterior`` looks at the
patient's front (patient left on the image right), ``lateral-left`` and ``lateral-right`` from the
sides, ``superior`` from above.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lungdeform.atomic import atomic_path
from lungdeform.geometry.mesh import Surface, face_normals

#: view name → (camera direction in LPS pointing from the patient to the viewer, image right, image up)
VIEWS = {
    "anterior": ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "posterior": ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "lateral-left": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "lateral-right": ((-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "superior": ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
}


def _projected_polygons(surface: Surface, view: str):
    eye, right, up = (np.asarray(a) for a in VIEWS[view])
    v = surface.vertices
    f = surface.faces
    n = face_normals(v, f)
    facing = n @ eye > 0
    shade = np.clip(n[facing] @ eye, 0.0, 1.0)
    ff = f[facing]
    depth = (v[ff].mean(axis=1)) @ eye
    order = np.argsort(depth)  # far first
    xy = np.stack([v @ right, v @ up], axis=1)
    return xy[ff[order]], shade[order]


def snapshot(
    path,
    layers: list[tuple[Surface, str, float]],
    *,
    views: tuple[str, ...] = ("anterior", "lateral-right"),
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """Write a PNG with one panel per view; ``layers`` = ``[(surface, colour, alpha), …]`` drawn in
    order (e.g. end-exhale opaque, end-inhale translucent on top). Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    fig, axes = plt.subplots(1, len(views), figsize=(4.2 * len(views), 4.6), squeeze=False)
    for ax, view in zip(axes[0], views):
        lo = np.array([np.inf, np.inf])
        hi = -lo
        for surface, colour, alpha in layers:
            polys, shade = _projected_polygons(surface, view)
            base = np.array(mcolors.to_rgb(colour))
            rgb = (0.25 + 0.75 * shade[:, None]) * base
            pc = PolyCollection(polys, facecolors=np.c_[rgb, np.full(len(rgb), alpha)], edgecolors="none")
            ax.add_collection(pc)
            if len(polys):
                pts = polys.reshape(-1, 2)
                lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
        pad = 0.05 * (hi - lo).max()
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.set_title(view)
        ax.set_xlabel("mm")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return Path(path)
