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

from lungdeform.errors import InputError

#: In-plane pixel of the signed-distance grid (mm), coarsened so a side has at most MAX_PIXELS (and
#: the grid at most MAX_GRID_VOXELS).
PIXEL_MM = 0.5
MAX_PIXELS = 384
#: Bounds on a contour stack, so that time and memory stay bounded: contours, points in all, slices and
#: the closest slice spacing (mm; CT slices are 0.5 mm apart or more), refused beyond; the signed-distance
#: grid's voxels (float32: 256 MiB), kept by coarser pixels
MAX_CONTOURS = 5000
MAX_POINTS = 250_000
MAX_SLICES = 1500
MIN_SPACING_MM = 0.1
MAX_GRID_VOXELS = 2**26
#: Largest coordinate (mm) of a contour point: 100 m, far beyond any patient
MAX_COORD_MM = 1e5
#: Evenly spaced slices: the largest gap within this fraction of the smallest (plus 0.02 mm of rounding)
SPACING_TOL = 0.05
#: A planar contour's points lie within this distance (mm) of its slice plane
PLANE_TOL_MM = 0.1


def plane_normal(contour, name: str = "contour") -> np.ndarray:
    """Unit normal ``(3,) float`` of a planar polygon ``contour : (k, 3)`` (Newell's method);
    ``name`` says which contour in the error for a polygon without area."""
    p = np.asarray(contour, float)
    q = np.roll(p, -1, axis=0)
    n = np.array([np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
                  np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
                  np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1]))])
    norm = np.linalg.norm(n)
    if not norm > 0:
        raise InputError(f"{name}: degenerate polygon (no area), cannot tell its plane")
    n = n / norm
    return n if n[np.argmax(np.abs(n))] > 0 else -n


def _frame(normal: np.ndarray) -> np.ndarray:
    """Rows ``u, v, n``: an orthonormal frame whose third axis is ``normal``."""
    a = np.eye(3)[np.argmin(np.abs(normal))]
    u = np.cross(normal, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u), normal])


def check_contours(contours, name: str = "structure", source: str | None = None, numbers=None) -> list[np.ndarray]:
    """``contours`` as ``(k, 3) float`` arrays after the checks a surface through them needs, each
    refused with :class:`InputError` naming ``source`` (the file, if given), ``name`` (e.g.
    ``"structure 'GTV'"``) and the contour (1-based, in the order given, or ``numbers[i]``: its number
    in the file when some were left out, :func:`enclosing`): at most :data:`MAX_CONTOURS` contours and
    :data:`MAX_POINTS` points, each of 3 or more finite points within :data:`MAX_COORD_MM`."""
    pre = f"{source}: " if source else ""
    contours = [np.asarray(c, float) for c in contours]
    numbers = list(numbers) if numbers is not None else list(range(1, len(contours) + 1))
    if not contours:
        raise InputError(f"{pre}{name}: no contours")
    if len(contours) > MAX_CONTOURS:
        raise InputError(f"{pre}{name}: {len(contours)} contours, more than {MAX_CONTOURS} (one structure of CT slices "
                         "has far fewer)")
    total = sum(len(c) for c in contours)
    if total > MAX_POINTS:
        raise InputError(f"{pre}{name}: {total} contour points, more than {MAX_POINTS}")
    for k, c in zip(numbers, contours):
        _check_points(c, f"{pre}contour {k} of {name}")
        if len(c) < 3:
            raise InputError(f"{pre}contour {k} of {name} has {len(c)} point(s); a closed contour needs 3 or more")
    return contours


def _check_points(c: np.ndarray, what: str) -> None:
    """Refuse a contour ``c`` that is no list of finite (x, y, z) points within :data:`MAX_COORD_MM`."""
    if c.ndim != 2 or c.shape[1] != 3:
        raise InputError(f"{what}: not a list of (x, y, z) points")
    if not np.all(np.isfinite(c)):
        raise InputError(f"{what} has non-finite coordinates")
    if c.size and np.abs(c).max() > MAX_COORD_MM:
        raise InputError(f"{what} has a coordinate of {np.abs(c).max():.3g} mm, beyond {MAX_COORD_MM:g} mm")


#: A contour enclosing less than this (mm²) encloses no area: its points on a line (float rounding)
MIN_AREA_MM2 = 1e-6


def enclosing(contours, name: str = "structure", source: str | None = None) -> tuple[list[int], list[str]]:
    """``(indices of the contours that enclose an area, one line per contour that does not)``.

    A contour encloses no area when it has fewer than 3 distinct points (a mask-to-contour tool's tip
    of 1 or 2 points, a repeated point) or its points lie on a line (area under :data:`MIN_AREA_MM2`):
    planning systems and 3D Slicer skip such a contour, and so does lungdeform, saying so (``source``,
    ``name``, the contour's number, 1-based in the order given, and its slice: z mm LPS). What is really
    broken is still refused (:class:`InputError`): a contour that is no list of points, a NaN or a
    coordinate beyond :data:`MAX_COORD_MM`."""
    pre = f"{source}: " if source else ""
    keep, lines = [], []
    for i, c in enumerate(np.asarray(c, float) for c in contours):
        _check_points(c, f"{pre}contour {i + 1} of {name}")
        distinct = len(np.unique(np.round(c, 6), axis=0)) if len(c) else 0
        if distinct >= 3 and _area(c) >= MIN_AREA_MM2:
            keep.append(i)
            continue
        why = (f"{len(c)} point(s)" if len(c) < 3 else f"{len(c)} points, {distinct} distinct" if distinct < 3
               else f"{len(c)} points on a line")
        at = f" on the slice at z = {c[:, 2].mean():.2f} mm" if len(c) else ""
        lines.append(f"{pre}{name}: contour {i + 1} ({why}){at} encloses no area: skipped")
    return keep, lines


def _area(c: np.ndarray) -> float:
    """Area (mm²) of the planar polygon ``c : (k, 3)``: half the length of its Newell vector."""
    q = np.roll(c, -1, axis=0)
    return 0.5 * float(np.linalg.norm(np.cross(c, q).sum(axis=0)))


def _heights(local: list[np.ndarray], name: str, pre: str, numbers: list[int]) -> np.ndarray:
    """Each contour's height along the frame's normal; every contour must lie flat in its plane
    (within :data:`PLANE_TOL_MM`) and have an area (``numbers``: each contour's number in messages)."""
    heights = np.array([c[:, 2].mean() for c in local])
    for i, (k, c) in enumerate(zip(numbers, local)):
        off = float(np.abs(c[:, 2] - heights[i]).max())
        if off > PLANE_TOL_MM:
            raise InputError(f"{pre}contour {k} of {name} is not on a slice parallel to the others (its points up to "
                             f"{off:.2f} mm off its plane)")
        xy = c[:, :2]
        area = 0.5 * abs(float(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])))
        if not area > 0:
            raise InputError(f"{pre}contour {k} of {name} is degenerate (no area)")
    seen: dict[bytes, int] = {}
    for k, c in zip(numbers, local):  # on one slice, a repeated contour would cancel it by parity
        key = np.round(np.asarray(contours_key(c)), 3).tobytes()
        if key in seen:
            raise InputError(f"{pre}contour {k} of {name} repeats contour {seen[key]} (on one slice they cancel)")
        seen[key] = k
    return heights


def contours_key(c: np.ndarray) -> np.ndarray:
    """A contour's points from its lowest (x, y, z) on, in the direction of its lesser neighbour:
    the same for one polygon listed from another start or backwards."""
    i = int(np.lexsort(c.T[::-1])[0])
    c = np.roll(c, -i, axis=0)
    back = np.roll(c[::-1], 1, axis=0)
    return min(c, back, key=lambda a: tuple(a[1]))


def _slice_levels(heights: np.ndarray, name: str, pre: str = "") -> tuple[np.ndarray, float]:
    """The distinct slice heights (mm, 0.01 mm apart or more) and their spacing: every gap the same
    within :data:`SPACING_TOL` (a gap twice another is a slice without a contour), at least
    :data:`MIN_SPACING_MM`, at most :data:`MAX_SLICES` slices."""
    levels = np.unique(np.round(heights, 2))
    if len(levels) < 2:
        raise InputError(f"{pre}{name}: contours on {len(levels)} slice(s); a closed surface needs two or more")
    if len(levels) > MAX_SLICES:
        raise InputError(f"{pre}{name}: contours on {len(levels)} slices, more than {MAX_SLICES}")
    gaps = np.diff(levels)
    if gaps.min() < MIN_SPACING_MM:
        raise InputError(f"{pre}{name}: contours {gaps.min():.2f} mm apart, closer than CT slices can be "
                         f"({MIN_SPACING_MM:g} mm)")
    if gaps.max() > (1 + SPACING_TOL) * gaps.min() + 0.02:
        i = int(np.argmax(gaps))
        raise InputError(f"{pre}{name}: contour slices not evenly spaced: gaps {gaps.min():.2f} to {gaps.max():.2f} mm "
                         f"({gaps[i]:.2f} mm between the slices at {levels[i]:.2f} and {levels[i + 1]:.2f} mm: "
                         "slices without a contour?)")
    step = float(np.median(gaps))
    return levels, step


def contours_to_mesh(contours, name: str = "structure", source: str | None = None,
                     numbers=None) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface ``(vertices (n, 3) float mm, faces (m, 3) int)`` through parallel planar
    ``contours`` (each ``(k, 3) float`` mm, k >= 3, on evenly spaced slices). Polygons on one slice
    are combined by parity (a hole drawn inside an outline is a hole); contours on a slice that
    enclose no pixel centre (smaller than a pixel) count as the pixel at each one's centre. Every
    bound and check of
    :func:`check_contours`, :func:`_heights` and :func:`_slice_levels` is an :class:`InputError`
    naming ``source`` (the file, if given), ``name`` and the contour (``numbers[i]``: the number of
    contour ``i`` in the file, when contours that enclose no area were left out first, :func:`enclosing`)."""
    pre = f"{source}: " if source else ""
    contours = check_contours(contours, name, source, numbers)
    numbers = list(numbers) if numbers is not None else list(range(1, len(contours) + 1))
    frame = _frame(plane_normal(max(contours, key=len), f"{pre}contour {numbers[_longest(contours) - 1]} of {name}"))
    local = [c @ frame.T for c in contours]
    heights = _heights(local, name, pre, numbers)
    levels, step = _slice_levels(heights, name, pre)
    allp = np.concatenate(local)
    lo, hi = allp[:, :2].min(axis=0), allp[:, :2].max(axis=0)
    side = min(MAX_PIXELS, int(np.sqrt(MAX_GRID_VOXELS / (len(levels) + 2))))  # pixels a side, grid bounded
    px = max(PIXEL_MM, float((hi - lo).max()) / (side - 8))
    lo = lo - 4 * px
    shape = tuple(int(n) for n in np.ceil((hi - lo) / px).astype(int) + 5)
    sdf = np.full((len(levels) + 2,) + shape, 4 * px, dtype=np.float32)  # one empty slice beyond each end
    at = np.clip(np.searchsorted(levels, np.round(heights, 2)), 0, len(levels) - 1)  # each contour's slice
    for k in range(len(levels)):
        on = np.flatnonzero(at == k)
        inside = parity_mask(shape, [(local[j][:, :2] - lo) / px for j in on])
        if not inside.any():  # contours smaller than a pixel: one pixel each, or the surface is cut in two
            for j in on:
                i = np.clip(np.rint((local[j][:, :2].mean(axis=0) - lo) / px).astype(int), 0, np.array(shape) - 1)
                inside[i[0], i[1]] = True
        sdf[k + 1] = px * (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside))
    v, f, _n, _vals = measure.marching_cubes(sdf, 0.0, spacing=(step, px, px))
    v = v.astype(np.float64)
    uvw = np.column_stack([lo[0] + v[:, 1], lo[1] + v[:, 2], levels[0] - step + v[:, 0]])
    # marching cubes of a field negative inside, on axes (n, u, v): read in (u, v, n), an even
    # permutation, its winding is outward (positive volume)
    return np.ascontiguousarray(uvw @ frame, dtype=np.float64), np.ascontiguousarray(f, dtype=np.int64)


def parity_mask(shape: tuple[int, int], polygons, chunk: int = 1 << 22) -> np.ndarray:
    """``(rows, cols) bool``: the pixel centres ``(i, j)`` inside an odd number of ``polygons`` (each
    ``(k, 2) float`` in pixel coordinates (row, column), closed implicitly): the polygons combined by
    parity, a hole inside an outline a hole. A scanline fill: each edge's crossings of the rows it
    spans (half-open, so a vertex on a row counts once), counted left of each centre; time and
    memory in the crossings and pixels, the edges taken about ``chunk`` crossings at a time."""
    rows, cols = shape
    count = np.zeros(rows * (cols + 1), np.int64)
    for poly in polygons:
        a = np.asarray(poly, float)
        b = np.roll(a, -1, axis=0)
        first = np.clip(np.ceil(np.minimum(a[:, 0], b[:, 0])), 0, rows).astype(np.int64)
        spans = np.clip(np.ceil(np.maximum(a[:, 0], b[:, 0])), 0, rows).astype(np.int64) - first
        edges = np.flatnonzero(spans > 0)
        for part in np.array_split(edges, max(1, int(spans[edges].sum()) // chunk + 1)):
            n = spans[part]
            e = np.repeat(part, n)
            r = first[e] + np.arange(len(e)) - np.repeat(np.cumsum(n) - n, n)  # each edge's rows in turn
            x = a[e, 1] + (r - a[e, 0]) * (b[e, 1] - a[e, 1]) / (b[e, 0] - a[e, 0])
            col = np.clip(np.ceil(x), 0, cols).astype(np.int64)
            count += np.bincount(r * (cols + 1) + col, minlength=count.size)
    return (np.cumsum(count.reshape(rows, cols + 1)[:, :cols], axis=1) & 1).astype(bool)


def _longest(contours: list[np.ndarray]) -> int:
    """1-based index of the contour with the most points (the one whose plane gives the frame)."""
    return int(np.argmax([len(c) for c in contours])) + 1


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
