"""Regions of a lung's surface: apex, base, costal and mediastinal faces (docs/DEFAULTS.md, "Third round").

A lung's surface moves by where it faces: the diaphragmatic face down, the costal face out, the
mediastinal face little. :func:`surface_regions` labels each vertex, in the lung frame of Sec. IV-B.1
(:mod:`lungdeform.geometry.frame`: X lateral from the heart, Y anterior, Z apex → base, over the lung's
own bounding box):

- **apex**: the top :data:`APEX_HEIGHT` of the lung's height (``ẑ < 0.15``);
- **base** (the diaphragmatic face): the lower half (``ẑ > 0.5``) where the outward normal points to the
  feet (its lung-frame Z component above :data:`FACING`);
- **mediastinal**: elsewhere, where the normal points to the heart (its X component below ``−FACING``);
- **costal**: the rest (lateral, anterior and posterior faces against the ribs; about half the area).

:func:`region_means` gives the area-weighted mean of a per-vertex quantity (a distance, mm) per region.
"""

from __future__ import annotations

import numpy as np

from .distance import vertex_areas
from .frame import lung_frame
from .mesh import as_vertices, vertex_normals

#: The regions, in table order (label k of :func:`surface_regions` is ``REGIONS[k]``).
REGIONS = ("apex", "base", "costal", "mediastinal")
#: The apex: this top share of the lung's height (apex → base).
APEX_HEIGHT = 0.15
#: The base lies below this share of the height.
BASE_BELOW = 0.5
#: A face points along an axis when its unit normal's component along it exceeds this (60°).
FACING = 0.5


def surface_regions(vertices, faces, side: str) -> np.ndarray:
    """``labels : (n,) int`` in ``0 … len(REGIONS) − 1`` for each vertex of the closed lung surface
    ``(vertices (n, 3) mm LPS, faces (m, 3))`` of ``side`` (module docstring)."""
    v = as_vertices(vertices)
    frame = lung_frame(v, side)
    z = frame.normalized(v)[:, 2]
    n = vertex_normals(v, np.asarray(faces)) @ frame.axes.T  # outward normals in the lung frame
    labels = np.full(len(v), REGIONS.index("costal"), np.int64)
    medial = n[:, 0] < -FACING
    labels[medial] = REGIONS.index("mediastinal")
    labels[(z > BASE_BELOW) & (n[:, 2] > FACING)] = REGIONS.index("base")
    labels[z < APEX_HEIGHT] = REGIONS.index("apex")
    return labels


def region_shares(vertices, faces, labels) -> dict[str, float]:
    """``{region: share of the surface area}`` of the ``labels`` of :func:`surface_regions`."""
    a = vertex_areas(as_vertices(vertices), np.asarray(faces))
    total = float(a.sum())
    return {r: float(a[np.asarray(labels) == k].sum() / total) for k, r in enumerate(REGIONS)}


def region_means(labels, values, weights, index=None) -> dict[str, float | None]:
    """``{region: weighted mean}`` of ``values : (k,)`` (e.g. distances, mm) with ``weights : (k,)``
    (e.g. vertex areas, mm²) at the vertices ``index : (k,) int`` (all vertices when None) of a surface
    labelled ``labels : (n,)`` (:func:`surface_regions`); None for a region without any of them."""
    lab = np.asarray(labels)
    lab = lab if index is None else lab[np.asarray(index)]
    vals, w = np.asarray(values, float), np.asarray(weights, float)
    out = {}
    for k, r in enumerate(REGIONS):
        m = lab == k
        out[r] = float(np.average(vals[m], weights=w[m])) if m.any() and w[m].sum() > 0 else None
    return out
