"""Exact point-to-surface and symmetric surface distances (mm).

A k-d tree to the nearest *vertex* is not a surface distance (LIBRARIES.md: off by up to 9.7 mm on
a real lung). Here the distance from a point to a triangle surface is exact:

1. each triangle is binned in a uniform grid (cell three times the median edge): once, in the cell
   that holds its bounding box's centre (a loose grid), unless its box reaches more than a quarter
   cell beyond that cell (the few long slivers of a decimated lung), then in every cell its box
   meets; so a box reaches at most the grid's overhang (≤ a quarter cell) beyond a cell that holds it;
2. a point's search visits its own cell, then the 26 around it, then the other cells within the best
   distance found so far plus the overhang (a triangle nearer than that has its box there), skipping
   a cell whose gap alone (from its index), or the union box of its triangles, is farther than the
   best so far, and a triangle whose own box is. The first sweeps hold the nearest triangles of a
   point near the surface, so the window shrinks early. The search starts from the caller's upper
   bound ``r`` on the distance if given, else from the nearest triangle in those first 27 cells; a
   point with none there (far from the surface) is searched again from its nearest vertex (k-d tree);
3. the exact closest point on each candidate triangle (Ericson, *Real-Time Collision Detection*
   5.1.5, written afresh here) in a numba kernel, parallel over the points (of one surface, or of
   several surfaces in one call: :class:`DistanceStack`); the smallest wins.
   Equally near triangles (a point nearest to an edge or a corner they share) are told apart by a
   fixed rank, the order in which the earlier raster scan of a grid of twice the median edge met
   them (the last one met won), so the face returned does not depend on the order of the visit or
   on the grid (the fit builds on it: another tie rule moved copd1 left's fitted surface 0.02 mm).

Symmetric surface distance between surfaces A and B: distances of A's sample points to B and of
B's sample points to A, pooled. Statistics are *area-weighted* (each vertex carries a third of the
area of its faces), so that a decimated mesh with uneven vertex density is measured fairly;
``mean``, ``rms``, ``p95`` (weighted percentile) and ``max`` in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
from scipy.spatial import cKDTree

from lungdeform.errors import InputError

from .mesh import Surface, as_faces, as_vertices, face_areas


@numba.njit(cache=True, inline="always")
def _closest_on_segment(p, a, b):
    """Closest point of segment ab to p and its squared distance (a == b allowed); points as
    tuples ``(x, y, z)``."""
    px, py, pz = p
    ax, ay, az = a
    bx, by, bz = b
    ux, uy, uz = bx - ax, by - ay, bz - az
    uu = ux * ux + uy * uy + uz * uz
    t = 0.0
    if uu > 0.0:
        t = min(max(((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / uu, 0.0), 1.0)
    qx, qy, qz = ax + t * ux, ay + t * uy, az + t * uz
    return qx, qy, qz, (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@numba.njit(cache=True)
def _closest_on_degenerate(p, a, b, c):
    """Closest point of a zero-area triangle abc (its corners on a line or at one point) to p: the
    nearest of its three edges as segments."""
    x1, y1, z1, e1 = _closest_on_segment(p, a, b)
    x2, y2, z2, e2 = _closest_on_segment(p, b, c)
    x3, y3, z3, e3 = _closest_on_segment(p, c, a)
    if e1 <= e2 and e1 <= e3:
        return x1, y1, z1
    if e2 <= e3:
        return x2, y2, z2
    return x3, y3, z3


@numba.njit(cache=True, inline="always")
def _closest_on_triangle(p, a, b, c):
    """Closest point of triangle abc to p, points as tuples ``(x, y, z)`` of scalars (no allocation
    in the hot loop)."""
    px, py, pz = p
    ax, ay, az = a
    bx, by, bz = b
    cx, cy, cz = c
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    if nx == 0.0 and ny == 0.0 and nz == 0.0:  # zero area (collinear or coincident corners)
        return _closest_on_degenerate(p, a, b, c)
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3) if d1 != d3 else 0.0  # d1 == d3 == 0: a == b, a degenerate edge
        return ax + t * abx, ay + t * aby, az + t * abz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6) if d2 != d6 else 0.0
        return ax + t * acx, ay + t * acy, az + t * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        e = (d4 - d3) + (d5 - d6)
        t = (d4 - d3) / e if e != 0.0 else 0.0
        return bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz)
    denom = va + vb + vc  # = |ab × ac|²: zero only for a zero-area triangle (rounding)
    if denom == 0.0:
        return _closest_on_degenerate(p, a, b, c)
    v = vb / denom
    w = vc / denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@numba.njit(cache=True)
def _face_cells(vertices, faces, lo, h, dims):
    """``(box (m, 6), cell (m,), reach (m,))``: each face's bounding box (lo, hi mm), the cell of the grid
    ``(lo, h, dims)`` holding its centre and how far (mm, ≥ 0) the box reaches beyond that cell."""
    m = faces.shape[0]
    box = np.empty((m, 6))
    cell = np.empty(m, np.int64)
    reach = np.zeros(m)
    for f in range(m):
        cell[f] = 0
        for k in range(3):
            a = vertices[faces[f, 0], k]
            b = vertices[faces[f, 1], k]
            c = vertices[faces[f, 2], k]
            box[f, k], box[f, 3 + k] = min(a, b, c), max(a, b, c)
            i = min(max(int(((box[f, k] + box[f, 3 + k]) / 2 - lo[k]) / h), 0), dims[k] - 1)
            reach[f] = max(reach[f], lo[k] + i * h - box[f, k], box[f, 3 + k] - (lo[k] + (i + 1) * h))
            cell[f] = cell[f] * dims[k] + i
    return box, cell, reach


@numba.njit(cache=True, inline="always")
def _cell_of(x, lo, h, n):
    """The cell (``0 .. n − 1``, clipped; ``x`` may be infinite) of one axis of a grid that holds ``x`` mm."""
    return int(min(max((x - lo) / h, 0.0), n - 1))


@numba.njit(cache=True, inline="always")
def _face_span(box, cell, once, lo, h, dims):
    """``(a0, a1, b0, b1, c0, c1)``: the cells (inclusive ranges along x, y, z) a face of bounding box
    ``box (6,)`` is binned in: ``once``, only ``cell``, the cell of its centre; else every cell its box meets."""
    if once:
        a, b, c = cell // (dims[1] * dims[2]), (cell // dims[2]) % dims[1], cell % dims[2]
        return a, a, b, b, c, c
    return (_cell_of(box[0], lo[0], h, dims[0]), _cell_of(box[3], lo[0], h, dims[0]),
            _cell_of(box[1], lo[1], h, dims[1]), _cell_of(box[4], lo[1], h, dims[1]),
            _cell_of(box[2], lo[2], h, dims[2]), _cell_of(box[5], lo[2], h, dims[2]))


@numba.njit(cache=True)
def _grid_fill(vertices, faces, lo, h, dims, cap):
    """Bin the faces in the grid ``(lo, h, dims)``: a face whose box reaches at most ``cap`` mm beyond
    the cell of its centre in that cell only (a loose grid), a longer one in every cell its box meets
    (so a few slivers do not widen every search). ``(ptr (cells + 1,), order (slots,) face per slot, cell
    by cell, records (slots, 15) per slot the face's box (lo, hi) and its corners a, b, c, content
    (cells, 6) the union of the cell's faces' boxes (empty: +inf, −inf), overhang mm)``, overhang the
    farthest a once-binned face's box reaches beyond its cell (≥ 0)."""
    m = faces.shape[0]
    n_cells = dims[0] * dims[1] * dims[2]
    box, cell, reach = _face_cells(vertices, faces, lo, h, dims)
    counts = np.zeros(n_cells + 1, np.int64)
    for f in range(m):
        a0, a1, b0, b1, c0, c1 = _face_span(box[f], cell[f], reach[f] <= cap, lo, h, dims)
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                for c in range(c0, c1 + 1):
                    counts[(a * dims[1] + b) * dims[2] + c + 1] += 1
    ptr = np.cumsum(counts)
    fill = ptr[:-1].copy()
    order = np.empty(ptr[-1], np.int64)
    records = np.empty((ptr[-1], 15))
    content = np.empty((n_cells, 6))
    content[:, :3], content[:, 3:] = np.inf, -np.inf
    overhang = 0.0
    for f in range(m):
        if reach[f] <= cap:
            overhang = max(overhang, reach[f])
        a0, a1, b0, b1, c0, c1 = _face_span(box[f], cell[f], reach[f] <= cap, lo, h, dims)
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                for c in range(c0, c1 + 1):
                    cc = (a * dims[1] + b) * dims[2] + c
                    slot = fill[cc]
                    fill[cc] += 1
                    order[slot] = f
                    for k in range(3):
                        records[slot, k], records[slot, 3 + k] = box[f, k], box[f, 3 + k]
                        content[cc, k] = min(content[cc, k], box[f, k])
                        content[cc, 3 + k] = max(content[cc, 3 + k], box[f, 3 + k])
                        for v in range(3):
                            records[slot, 6 + 3 * v + k] = vertices[faces[f, v], k]
    return ptr, order, records, content, overhang


@numba.njit(cache=True, inline="always")
def _box_gap2(px, py, pz, box):
    """Squared distance from the point ``(px, py, pz)`` to the box ``box[:6]`` = (lo x, y, z, hi x, y, z)."""
    gx = max(box[0] - px, px - box[3], 0.0)
    gy = max(box[1] - py, py - box[4], 0.0)
    gz = max(box[2] - pz, pz - box[5], 0.0)
    return gx * gx + gy * gy + gz * gz


@numba.njit(cache=True, inline="always")
def _slab_gap2(x, lo, h, i, overhang):
    """Squared distance (mm²) from ``x`` to cell ``i`` of one axis of a grid widened by ``overhang`` mm."""
    g = max(lo + i * h - overhang - x, x - (lo + (i + 1) * h + overhang), 0.0)
    return g * g


@numba.njit(cache=True, inline="always")
def _hint_bound(px, py, pz, rec, slot, r):
    """``min(r, d)`` mm, ``d`` the exact distance from ``(px, py, pz)`` to the face of the record ``rec[slot]``
    (any ``slot < 0``: ``r``): the same numbers as :func:`_face_bound` (the same corners, the same routine)."""
    if slot < 0:
        return r
    qx, qy, qz = _closest_on_triangle((px, py, pz), (rec[slot, 6], rec[slot, 7], rec[slot, 8]),
                                      (rec[slot, 9], rec[slot, 10], rec[slot, 11]),
                                      (rec[slot, 12], rec[slot, 13], rec[slot, 14]))
    return min(r, np.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2))


@numba.njit(cache=True, parallel=True)
def _closest_kernel(points, bound, hint, which, grids):
    """``(distance, closest, face)`` of ``points : (n, 3)`` within ``bound : (n,)`` (upper bounds on
    their distances) on the faces binned in grid ``which[i]`` of the stack ``grids`` (:func:`_stack`: per
    grid ``lo (g, 3)``, ``h (g,)``, ``dims (g, 3)``, the offsets ``pbase``, ``cbase``, ``fbase (g,)`` of its
    cells' slot pointers, its cells and its faces, ``overhang (g,)``; every grid's ``ptr`` (absolute slots),
    ``order`` (each slot's face, of its own surface), ``rank`` (its tie-break order), ``records``,
    ``content`` (:func:`_grid_fill`) and ``fslot`` (a slot of each face)). ``hint : (n,)``: a face of that
    surface whose distance bounds the search too (−1: none)."""
    lo, h, dims, pbase, cbase, fbase, overhang, ptr, order, rank, rec, content, fslot = grids
    n = points.shape[0]
    dist2 = np.empty(n)
    closest = np.zeros((n, 3))
    face = np.full(n, -1, np.int64)
    for i in numba.prange(n):
        g = which[i]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        r = _hint_bound(px, py, pz, rec, fslot[fbase[g] + hint[i]] if hint[i] >= 0 else -1, bound[i])
        best = r * r * (1.0 + 1e-12) + 1e-12
        wrank = -1
        lx, ly, lz, hg, ov, pb, cb = lo[g, 0], lo[g, 1], lo[g, 2], h[g], overhang[g], pbase[g], cbase[g]
        nx, ny, nz = dims[g, 0], dims[g, 1], dims[g, 2]
        ci, cj, ck = _cell_of(px, lx, hg, nx), _cell_of(py, ly, hg, ny), _cell_of(pz, lz, hg, nz)
        for sweep in range(3):  # the point's cell, its neighbours, then the rest of the window
            if best == np.inf and sweep == 2:
                break  # no bound and no face near: left to the caller (a miss)
            reach = np.sqrt(best) + ov
            i0, i1 = _cell_of(px - reach, lx, hg, nx), _cell_of(px + reach, lx, hg, nx)
            j0, j1 = _cell_of(py - reach, ly, hg, ny), _cell_of(py + reach, ly, hg, ny)
            k0, k1 = _cell_of(pz - reach, lz, hg, nz), _cell_of(pz + reach, lz, hg, nz)
            if sweep < 2:
                i0, i1, j0, j1 = max(i0, ci - sweep), min(i1, ci + sweep), max(j0, cj - sweep), min(j1, cj + sweep)
                k0, k1 = max(k0, ck - sweep), min(k1, ck + sweep)
            for a in range(i0, i1 + 1):
                ga = _slab_gap2(px, lx, hg, a, ov)
                if ga > best:
                    continue
                for b in range(j0, j1 + 1):
                    gb = ga + _slab_gap2(py, ly, hg, b, ov)
                    if gb > best:
                        continue
                    inner = sweep > 0 and abs(a - ci) < sweep and abs(b - cj) < sweep
                    for c in range(k0, k1 + 1):
                        if inner and abs(c - ck) < sweep:
                            continue  # seen in an earlier sweep
                        cell = (a * ny + b) * nz + c
                        if ptr[pb + cell] == ptr[pb + cell + 1] or _box_gap2(px, py, pz, content[cb + cell]) > best:
                            continue  # no face, or none nearer than the best so far
                        for m in range(ptr[pb + cell], ptr[pb + cell + 1]):
                            if _box_gap2(px, py, pz, rec[m]) > best:  # its bounding box is farther
                                continue
                            qx, qy, qz = _closest_on_triangle((px, py, pz), (rec[m, 6], rec[m, 7], rec[m, 8]),
                                                              (rec[m, 9], rec[m, 10], rec[m, 11]),
                                                              (rec[m, 12], rec[m, 13], rec[m, 14]))
                            d = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
                            if d < best or (d == best and rank[m] > wrank):
                                best = d
                                wrank = rank[m]
                                closest[i, 0] = qx
                                closest[i, 1] = qy
                                closest[i, 2] = qz
                                face[i] = order[m]
        dist2[i] = best
    return np.sqrt(dist2), closest, face


def _stack(grids: list) -> tuple:
    """One stack (:func:`_closest_kernel`) of the grids ``(lo, h, dims, ptr, order, rank, records, content,
    overhang, faces)`` of a few surfaces (:class:`SurfaceDistance`; ``faces``: its face count)."""
    cells = np.array([len(g[7]) for g in grids], np.int64)
    slots = np.array([len(g[4]) for g in grids], np.int64)
    faces = np.array([g[9] for g in grids], np.int64)
    base = [np.concatenate([[0], np.cumsum(x)[:-1]]).astype(np.int64) for x in (cells + 1, cells, faces, slots)]
    fslot = np.empty(int(faces.sum()), np.int64)
    for g, f0, s0 in zip(grids, base[2], base[3]):
        fslot[f0 + g[4]] = s0 + np.arange(len(g[4]))  # a slot of each face (any: its record is the same)
    return (np.array([g[0] for g in grids]), np.array([g[1] for g in grids]), np.array([g[2] for g in grids]),
            base[0], base[1], base[2], np.array([g[8] for g in grids]),
            np.concatenate([g[3] + s0 for g, s0 in zip(grids, base[3])]), np.concatenate([g[4] for g in grids]),
            np.concatenate([g[5] for g in grids]), np.concatenate([g[6] for g in grids]),
            np.concatenate([g[7] for g in grids]), fslot)


@numba.njit(cache=True, parallel=True)
def _face_bound(points, vertices, faces, hint):
    """``(n,)`` mm: the exact distance of each of ``points : (n, 3)`` to its face ``hint[i]`` of
    ``(vertices, faces)``, an upper bound on its distance to the surface; infinity where ``hint[i] < 0``."""
    n = points.shape[0]
    out = np.full(n, np.inf)
    for i in numba.prange(n):
        f = hint[i]
        if f < 0:
            continue
        a_, b_, c_ = faces[f, 0], faces[f, 1], faces[f, 2]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        qx, qy, qz = _closest_on_triangle(
            (px, py, pz), (vertices[a_, 0], vertices[a_, 1], vertices[a_, 2]),
            (vertices[b_, 0], vertices[b_, 1], vertices[b_, 2]), (vertices[c_, 0], vertices[c_, 1], vertices[c_, 2]))
        out[i] = np.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
    return out


@numba.njit(cache=True)
def _tie_rank(vertices, faces, lo, h, dims):
    """``(m,) int``: each face's rank among equally near faces (the higher wins): its position when the
    faces are sorted by the cell of their box centre in the grid ``(lo, h, dims)``, then by index, the
    order in which the raster-scan kernel before the shell search met them (the last met, nearest face
    won), so that ties (a point nearest to an edge or corner shared by faces) resolve as they did."""
    cell = _face_cells(vertices, faces, lo, h, dims)[1]
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for f in range(len(cell)):
        start[cell[f] + 1] += 1
    start = np.cumsum(start)
    rank = np.empty(len(cell), np.int64)
    for f in range(len(cell)):
        rank[f] = start[cell[f]]
        start[cell[f]] += 1
    return rank


@numba.njit(cache=True)
def _edges_and_box(vertices, faces):
    """``(edge (3m,) mm, lo (3,) mm, hi (3,) mm)``: the length of every face's three edges (each edge
    once per face it bounds) and the bounding box of the vertices the faces use, in one pass (the
    grid's cell side and extent, :class:`SurfaceDistance`; numpy's ``norm(e − roll(e))`` and
    ``min``/``max`` over the used vertices gave the same numbers at three times the cost)."""
    m = faces.shape[0]
    edge = np.empty(3 * m)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for f in range(m):
        for k in range(3):
            a, b = faces[f, k], faces[f, k - 1]  # k − 1 = −1: the face's last corner (numpy's roll by one)
            dx = vertices[a, 0] - vertices[b, 0]
            dy = vertices[a, 1] - vertices[b, 1]
            dz = vertices[a, 2] - vertices[b, 2]
            edge[3 * f + k] = np.sqrt(dx * dx + dy * dy + dz * dz)
            for c in range(3):
                lo[c] = min(lo[c], vertices[a, c])
                hi[c] = max(hi[c], vertices[a, c])
    return edge, lo, hi


#: Fewest query points for which the nearest-vertex bound is found with every core (scipy's threads).
THREADED_QUERY = 50_000


class SurfaceDistance:
    """Exact distances from points to one triangle surface; build once, query many times.

    Triangles are binned by the centres of their bounding boxes (the long ones in every cell they
    meet) into a uniform grid (cell three times the median edge); a query scans the cells within an
    upper bound on its distance plus the farthest a box overhangs its cell, nearest cells first, so no
    closer triangle can be missed (module docstring).

    Parameters
    ----------
    vertices : (n, 3) float
        Surface vertices, mm (any frame; queries in the same frame).
    faces : (m, 3) int
    """

    MAX_CELLS = 2_000_000
    #: A face whose box reaches farther than this many cells beyond the cell of its centre is binned in
    #: every cell it meets (a decimated lung has a few long slivers: 1 % of its faces reach 0.6 cell).
    CAP = 0.25
    #: Grid cell side in median edges: 3 cost the least kernel CPU on five of copd1 left's fit queries
    #: (2: +21 %, 4: +32 %; a finer grid visits more empty cells, a coarser one tests more boxes).
    CELL = 3.0

    def __init__(self, vertices, faces):
        self.vertices = as_vertices(vertices)
        self.faces = as_faces(faces, len(self.vertices))
        if len(self.faces) == 0:
            raise InputError("faces: a surface distance needs at least one triangle")
        if not np.all(np.isfinite(self.vertices)):
            raise InputError("vertices contain NaN or infinity")
        used = np.flatnonzero(np.bincount(self.faces.ravel(), minlength=len(self.vertices)))  # = np.unique, O(n)
        self._used = used
        edge, low, high = _edges_and_box(self.vertices, self.faces)
        lo = low - 1e-6
        span = high + 1e-6 - lo
        median = float(np.median(edge))
        rank = _tie_rank(self.vertices, self.faces, lo, *self._cells(span, 2.0 * median))
        h, dims = self._cells(span, self.CELL * median)
        ptr, order, records, content, overhang = _grid_fill(self.vertices, self.faces, lo, h, dims, self.CAP * h)
        self._parts = (lo, h, dims, ptr, order, rank[order], records, content, overhang, len(self.faces))

    @cached_property
    def _grid(self) -> tuple:
        """This surface's grid alone as a stack (:func:`_stack`), made on its first own query (a surface
        queried only within a :class:`DistanceStack` needs none)."""
        return _stack([self._parts])

    def _cells(self, span: np.ndarray, h: float) -> tuple[float, np.ndarray]:
        """``(h mm, dims (3,) int)``: a grid of cells of side ``h`` (grown to at most MAX_CELLS cells) over ``span``."""
        h = max(h, 1e-6, float(np.prod(span) / self.MAX_CELLS) ** (1.0 / 3.0))
        return h, np.maximum(np.ceil(span / h).astype(np.int64), 1)

    @cached_property
    def _tree(self) -> cKDTree:
        """The k-d tree of the surface's vertices (built on the first query that needs it: a query
        whose every point has a bound of its own needs none)."""
        return cKDTree(self.vertices[self._used])

    def face_distance(self, points, faces) -> np.ndarray:
        """``(k,) float`` mm: the exact distance of each of ``points : (k, 3)`` to its face ``faces[i]``
        of this surface (infinity where ``faces[i]`` is −1), an upper bound on its distance to the
        surface: a ``bound`` for :meth:`query`, e.g. from each point's closest face in an earlier query
        on a surface of the same faces whose vertices moved a little."""
        pts = as_vertices(points, "points")
        f = self._checked_faces(faces, len(pts), "this surface")
        return _face_bound(pts, self.vertices, self.faces, np.ascontiguousarray(f, np.int64))

    def _checked_faces(self, faces, n: int, name: str) -> np.ndarray:
        """``faces`` as an array, refused unless ``(n,)`` integer indices of this surface's faces (or −1),
        the message naming the surface as ``name``."""
        f = np.asarray(faces)
        if f.shape != (n,) or not np.issubdtype(f.dtype, np.integer) or (
                len(f) and (f.min() < -1 or f.max() >= len(self.faces))):
            raise InputError(f"faces must be ({n},) face indices of {name} (or -1), got shape {f.shape}, "
                             f"dtype {f.dtype}")
        return f

    def query(self, points, bound=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(distance (k,) mm, closest (k, 3) mm, face (k,) int)`` for ``points : (k, 3)``.

        ``bound : (k,) float`` mm, optional: the caller's upper bound on each point's distance (for
        example the distance to a node known to lie on the other side of the surface), used instead
        of the nearest triangle in the point's cell and the 26 around it; a point with no triangle
        within its bound (a bound too small, or not finite), or none in those cells, is searched again
        from its nearest vertex, so the answer is exact either way."""
        pts = as_vertices(points, "points")
        if len(pts) == 0:
            return np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
        if not np.all(np.isfinite(pts)):
            raise InputError("points contain NaN or infinity")
        if bound is None:
            b = np.full(len(pts), np.inf)
        else:
            b = np.asarray(bound, dtype=np.float64).reshape(-1)
            if len(b) != len(pts):
                raise InputError(f"bound: need one upper bound (mm) per point ({len(pts)}), got {len(b)}")
            b = np.where(np.isfinite(b) & (b >= 0.0), b, np.inf)
        found = self._search(pts, b)
        self._fill_misses(pts, np.flatnonzero(found[2] < 0), found)
        return found

    def _fill_misses(self, pts: np.ndarray, miss: np.ndarray, found: tuple) -> None:
        """Search the points ``pts[miss]`` (``miss : (k,) int``, those the grid's search left without a
        face: no bound and no face near) again from their nearest vertex, into ``found = (distance,
        closest, face)`` (:meth:`query`'s arrays) in place."""
        if len(miss):
            dist, closest, face = found
            dist[miss], closest[miss], face[miss] = self._search(pts[miss], self._vertex_bound(pts[miss]))

    def _vertex_bound(self, pts: np.ndarray) -> np.ndarray:
        """``(k,) float`` mm: each point's distance to the nearest vertex (an upper bound on its distance)."""
        # threads only for a large query: scipy starts and joins its workers on every call, which
        # cost a fit's objective (6000 and 3000 points, hundreds of calls) more than they saved
        return self._tree.query(pts, workers=-1 if len(pts) >= THREADED_QUERY else 1)[0]

    def _search(self, pts: np.ndarray, bound: np.ndarray):
        none = np.full(len(pts), -1, np.int64)
        return _closest_kernel(pts, bound, none, np.zeros(len(pts), np.int64), self._grid)

    def distance(self, points, bound=None) -> np.ndarray:
        """``(k,) float`` mm: exact unsigned distance of each point to the surface (``bound``: :meth:`query`)."""
        return self.query(points, bound)[0]


class DistanceStack:
    """Exact distances from points to several triangle surfaces, every surface's points in one kernel call.

    A fit measures a few thousand points against each of a 4-D CT's nine targets (and its model
    surface at each target's volume) per evaluation: one parallel call over all of them, not one per
    surface. The answers equal each surface's own :meth:`SurfaceDistance.query` (the same grids, the
    same kernel, the same tie rule).

    Parameters
    ----------
    surfaces : sequence of SurfaceDistance
        The surfaces, each in its own frame (mm); their grids are copied once into the stack.
    """

    def __init__(self, surfaces):
        self.surfaces = tuple(surfaces)
        if not self.surfaces:
            raise InputError("surfaces: a distance stack needs at least one surface")
        self._grid = _stack([sd._parts for sd in self.surfaces])

    def query(self, which, points, faces=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``[(distance (k_j,) mm, closest (k_j, 3) mm, face (k_j,) int), …]``: for each ``j``, the points
        ``points[j] : (k_j, 3)`` on surface ``which[j]`` (an index into :attr:`surfaces`), each search
        bounded by the distance to its face ``faces[j][i]`` (``faces[j] : (k_j,) int`` or None, −1: no
        bound; :meth:`SurfaceDistance.face_distance`); exact either way (:meth:`SurfaceDistance.query`)."""
        which = [int(w) for w in which]
        pts = [as_vertices(p, "points") for p in points]
        if not pts and not which:
            return []
        hints = [None] * len(pts) if faces is None else list(faces)
        if len(which) != len(pts) or len(hints) != len(pts) or any(w < 0 or w >= len(self.surfaces) for w in which):
            raise InputError(f"which, points and faces must be one per query, which indexing the "
                             f"{len(self.surfaces)} surfaces; got {len(which)}, {len(pts)}, {len(hints)}")
        hint = [np.full(len(p), -1, np.int64) if f is None
                else self.surfaces[w]._checked_faces(f, len(p), f"surface {w}") for p, f, w in zip(pts, hints, which)]
        allp = np.concatenate(pts)
        if not np.all(np.isfinite(allp)):
            raise InputError("points contain NaN or infinity")
        grid_of = np.repeat(np.asarray(which, np.int64), [len(p) for p in pts])
        found = _closest_kernel(allp, np.full(len(allp), np.inf), np.concatenate(hint).astype(np.int64),
                                grid_of, self._grid)
        dist, closest, face = found
        for w in np.unique(grid_of[face < 0]):  # no face near and no bound: from the nearest vertex, as query does
            self.surfaces[w]._fill_misses(allp, np.flatnonzero((face < 0) & (grid_of == w)), found)
        cut = np.cumsum([len(p) for p in pts])[:-1]
        return list(zip(np.split(dist, cut), np.split(closest, cut), np.split(face, cut)))


def barycentric(points, a, b, c) -> np.ndarray:
    """``(k, 3) float``: the barycentric coordinates of ``points : (k, 3)`` in the triangles with corners
    ``a, b, c : (k, 3)`` (mm; a point off a triangle's plane is projected onto it); a zero-area
    triangle gives (1, 0, 0)."""
    v0, v1, v2 = b - a, c - a, np.asarray(points, float) - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-18, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=1)


def point_to_surface(points, vertices, faces) -> np.ndarray:
    """One-shot: exact distances ``(k,) float`` mm from ``points`` to the surface (vertices, faces)."""
    return SurfaceDistance(vertices, faces).distance(points)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(n,) float`` mm²: a third of the area of each vertex's faces (sums to the surface area)."""
    a = face_areas(vertices, faces) / 3.0
    return np.bincount(faces.ravel(), weights=np.repeat(a, 3), minlength=len(vertices))


def weighted_percentile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The ``q``-th percentile (0–100) of ``values`` under ``weights`` (inverse of the weighted CDF)."""
    v = np.asarray(values, float)
    w = np.asarray(weights, float)
    if len(v) == 0:
        return float("nan")
    order = np.argsort(v)
    cdf = np.cumsum(w[order])
    cdf /= cdf[-1]
    return float(v[order][min(np.searchsorted(cdf, q / 100.0), len(v) - 1)])


@dataclass(frozen=True)
class DistanceStats:
    """Summary of a set of surface distances (mm), area-weighted."""

    mean: float
    rms: float
    p95: float
    max: float
    count: int

    def as_dict(self, prefix: str = "surface_") -> dict[str, float]:
        return {f"{prefix}mean_mm": self.mean, f"{prefix}rms_mm": self.rms,
                f"{prefix}p95_mm": self.p95, f"{prefix}max_mm": self.max}


def distance_stats(distances: np.ndarray, weights: np.ndarray | None = None) -> DistanceStats:
    """Weighted mean, RMS, 95th percentile and maximum of ``distances : (k,)`` mm."""
    d = np.asarray(distances, float)
    if len(d) == 0:
        raise InputError("no distances to summarise (every sample point was excluded)")
    w = np.ones_like(d) if weights is None else np.asarray(weights, float)
    if w.shape != d.shape or np.any(w < 0) or not w.sum() > 0:
        raise InputError(f"weights must be (k,) non-negative with a positive sum, got shape {w.shape}")
    return DistanceStats(float(np.average(d, weights=w)), float(np.sqrt(np.average(d**2, weights=w))),
                         weighted_percentile(d, w, 95.0), float(d.max()), int(len(d)))


@dataclass(frozen=True, eq=False)
class SymmetricDistance:
    """Both one-sided distance sets between surfaces A and B.

    Attributes
    ----------
    a_to_b : (na,) float
        Distance of each (kept) vertex of A to surface B, mm.
    b_to_a : (nb,) float
        Distance of each (kept) vertex of B to surface A, mm.
    a_weights, b_weights : (na,), (nb,) float
        Vertex areas, mm², used as weights.
    a_index, b_index : (na,), (nb,) int
        Which vertices of A and B were kept (the others were excluded by the caller's masks).
    """

    a_to_b: np.ndarray
    b_to_a: np.ndarray
    a_weights: np.ndarray
    b_weights: np.ndarray
    a_index: np.ndarray
    b_index: np.ndarray

    def restricted(self, keep_a=None, keep_b=None) -> SymmetricDistance:
        """The same distances of the vertices kept here that ``keep_a : (na_all,) bool`` and ``keep_b :
        (nb_all,) bool`` (one per vertex of A and of B; None: all) also keep: what
        :func:`symmetric_distance` with those masks measures, without measuring again (each
        distance is its own point's query)."""
        ia, ib = self._kept(keep_a, self.a_index, "keep_a"), self._kept(keep_b, self.b_index, "keep_b")
        return SymmetricDistance(self.a_to_b[ia], self.b_to_a[ib], self.a_weights[ia], self.b_weights[ib],
                                 self.a_index[ia], self.b_index[ib])

    @staticmethod
    def _kept(keep, index: np.ndarray, name: str) -> np.ndarray:
        """``(k,) bool``: which of the vertices ``index`` the mask ``keep`` keeps (all when None)."""
        if keep is None:
            return np.ones(len(index), bool)
        k = np.asarray(keep, bool)
        if k.ndim != 1 or (len(index) and len(k) <= index.max()):
            raise InputError(f"{name} must be one boolean per vertex (at least {index.max() + 1}), got shape {k.shape}")
        return k[index]

    @cached_property
    def stats(self) -> DistanceStats:
        """Pooled, area-weighted symmetric statistics (each side weighted by its own area)."""
        wa = self.a_weights / max(self.a_weights.sum(), 1e-300)
        wb = self.b_weights / max(self.b_weights.sum(), 1e-300)
        return distance_stats(np.concatenate([self.a_to_b, self.b_to_a]), np.concatenate([wa, wb]))


def symmetric_distance(a: Surface, b: Surface, *, keep_a=None, keep_b=None,
                       b_distance: SurfaceDistance | None = None) -> SymmetricDistance:
    """Symmetric surface distance between two surfaces (same frame, mm).

    ``keep_a : (na,) bool`` and ``keep_b : (nb,) bool`` select which vertices are measured (for
    example to leave out an artificial crop face); default all. ``b_distance`` reuses a prepared
    :class:`SurfaceDistance` for ``b`` (a fixed target measured many times).
    """
    ka = np.ones(a.n_vertices, bool) if keep_a is None else np.asarray(keep_a, bool)
    kb = np.ones(b.n_vertices, bool) if keep_b is None else np.asarray(keep_b, bool)
    if ka.shape != (a.n_vertices,) or kb.shape != (b.n_vertices,):
        raise InputError("keep_a / keep_b must be one boolean per vertex of a / b")
    bd = b_distance or SurfaceDistance(b.vertices, b.faces)
    ia, ib = np.nonzero(ka)[0], np.nonzero(kb)[0]
    ab = bd.distance(a.vertices[ia])
    ba = SurfaceDistance(a.vertices, a.faces).distance(b.vertices[ib])
    return SymmetricDistance(ab, ba, vertex_areas(a.vertices, a.faces)[ia],
                             vertex_areas(b.vertices, b.faces)[ib], ia, ib)
