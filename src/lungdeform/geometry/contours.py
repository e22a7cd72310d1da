"""Planar contours and closed surfaces: a surface through a stack of contours, contours of a surface.

Radiotherapy structures (docs/RADIOTHERAPY.md) are stacks of closed polygons drawn on parallel image
slices. :func:`contours_to_mesh` turns such a stack into a closed triangle surface by shape-based
interpolation: each slice's in-plane signed distance to its polygons (negative inside), linear along
the slice normal, its zero level set by marching cubes; one empty slice beyond each end closes the
surface half a slice spacing past the first and last contour. :func:`section_mesh` cuts a closed
surface with parallel planes (the slices of a CT series) and chains the crossings into closed
polygons, so that every contour of a deformed structure lies on a slice again.

Arrays: ``contours`` are ``(k, 3) float`` mm (LPS world), each on one plane; ``vertices : (n, 3)
float`` mm, ``faces : (m, 3) int``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage import measure
from skimage.draw import polygon2mask

from lungdeform.errors import InputError

#: In-plane pixel of the signed-distance grid (mm), coarsened so a side has at most MAX_PIXELS.
PIXEL_MM = 0.5
MAX_PIXELS = 384


def plane_normal(contour) -> np.ndarray:
    """Unit normal ``(3,) float`` of a planar polygon ``contour : (k, 3)`` (Newell's method)."""
    p = np.asarray(contour, float)
    q = np.roll(p, -1, axis=0)
    n = np.array([np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
                  np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
                  np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1]))])
    norm = np.linalg.norm(n)
    if not norm > 0:
        raise InputError("contour: degenerate polygon (no area), cannot tell its plane")
    n = n / norm
    return n if n[np.argmax(np.abs(n))] > 0 else -n


def _frame(normal: np.ndarray) -> np.ndarray:
    """Rows ``u, v, n``: an orthonormal frame whose third axis is ``normal``."""
    a = np.eye(3)[np.argmin(np.abs(normal))]
    u = np.cross(normal, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u), normal])


def _slice_levels(heights: np.ndarray, name: str) -> tuple[np.ndarray, float]:
    """The distinct slice heights (mm, 0.01 mm apart or more) and their spacing (median gap)."""
    levels = np.unique(np.round(heights, 2))
    if len(levels) < 2:
        raise InputError(f"{name}: contours on {len(levels)} slice(s); a closed surface needs two or more")
    gaps = np.diff(levels)
    step = float(np.median(gaps))
    if gaps.max() > 1.5 * step + 0.01 or gaps.min() < 0.5 * step - 0.01:
        raise InputError(f"{name}: slices are not evenly spaced (gaps {gaps.min():.2f} to {gaps.max():.2f} mm)")
    return levels, step


def contours_to_mesh(contours, name: str = "structure") -> tuple[np.ndarray, np.ndarray]:
    """A closed surface ``(vertices (n, 3) float mm, faces (m, 3) int)`` through parallel planar
    ``contours`` (each ``(k, 3) float`` mm, k >= 3, on evenly spaced slices). Polygons on one slice
    are combined by parity (a hole drawn inside an outline is a hole)."""
    contours = [np.asarray(c, float) for c in contours if len(c) >= 3]
    if not contours:
        raise InputError(f"{name}: no closed contour with 3 or more points")
    frame = _frame(plane_normal(max(contours, key=len)))
    local = [c @ frame.T for c in contours]
    levels, step = _slice_levels(np.array([c[:, 2].mean() for c in local]), name)
    allp = np.concatenate(local)
    lo, hi = allp[:, :2].min(axis=0), allp[:, :2].max(axis=0)
    px = max(PIXEL_MM, float((hi - lo).max()) / (MAX_PIXELS - 8))
    lo = lo - 4 * px
    shape = tuple(np.ceil((hi - lo) / px).astype(int) + 5)
    sdf = np.full((len(levels) + 2,) + shape, 4 * px)  # one empty slice beyond each end
    for k, z in enumerate(levels):
        inside = np.zeros(shape, bool)
        for c in local:
            if abs(c[:, 2].mean() - z) < 0.5 * step:
                inside ^= polygon2mask(shape, (c[:, :2] - lo) / px)
        if inside.any():
            sdf[k + 1] = px * (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside))
    v, f, _n, _vals = measure.marching_cubes(sdf, 0.0, spacing=(step, px, px))
    uvw = np.column_stack([lo[0] + v[:, 1], lo[1] + v[:, 2], levels[0] - step + v[:, 0]])
    # marching cubes of a field negative inside, on axes (n, u, v): read in (u, v, n), an even
    # permutation, its winding is outward (positive volume)
    return np.ascontiguousarray(uvw @ frame), np.ascontiguousarray(f, dtype=np.int64)


def section_mesh(vertices, faces, origin, normal) -> list[np.ndarray]:
    """Closed polygons ``(k, 3) float`` mm where the plane through ``origin : (3,)`` with unit
    ``normal : (3,)`` cuts the closed surface ``vertices``/``faces`` (vertices exactly on the plane
    count as above it, so every crossing is a proper one)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    d = (v - np.asarray(origin, float)) @ np.asarray(normal, float)
    above = d >= 0
    cut = f[above[f].any(axis=1) & ~above[f].all(axis=1)]
    if len(cut) == 0:
        return []
    # each cut face crosses two of its edges: a segment from one edge's crossing to the other's
    edges = np.stack([cut[:, [0, 1]], cut[:, [1, 2]], cut[:, [2, 0]]], axis=1)  # (c, 3, 2)
    crosses = above[edges[..., 0]] != above[edges[..., 1]]
    pairs = np.sort(edges[crosses].reshape(-1, 2, 2), axis=2)  # (c, 2 edges, 2 vertices)
    keys = pairs[..., 0] * len(v) + pairs[..., 1]
    return [_edge_points(v, d, loop) for loop in _loops(keys)]


def _loops(keys: np.ndarray) -> list[np.ndarray]:
    """Chain segments ``keys : (c, 2)`` (edge ids; on a closed manifold each id is in two segments)
    into closed loops of edge ids."""
    link: dict[int, list[int]] = {}
    for a, b in keys.tolist():
        link.setdefault(a, []).append(b)
        link.setdefault(b, []).append(a)
    seen: set[int] = set()
    loops = []
    for start in link:
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            options = [n for n in link[cur] if n != prev] or link[cur]
            prev, cur = cur, options[0]
            if cur == start or cur in seen:
                break
            loop.append(cur)
            seen.add(cur)
        if len(loop) >= 3:
            loops.append(np.array(loop))
    return loops


def _edge_points(v: np.ndarray, d: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Where the plane crosses each edge (id ``a * n + b``) of ``loop``: ``(k, 3) float`` mm."""
    a, b = np.divmod(loop, len(v))
    t = d[a] / (d[a] - d[b])
    return v[a] + t[:, None] * (v[b] - v[a])
