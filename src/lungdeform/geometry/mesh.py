"""Closed triangle surfaces: the :class:`Surface` bundle and the free functions behind it.

Conventions used across lungdeform:

- ``vertices : (n, 3) float64``, millimetres, LPS world frame unless a docstring says otherwise,
  C-contiguous.
- ``faces : (m, 3) int64``, indices into ``vertices``, counter-clockwise seen from outside, so the
  signed volume of a valid lung surface is positive.

All the math lives in free functions on plain arrays; :class:`Surface` only bundles the two arrays,
caches derived data and delegates.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from lungdeform.errors import InputError, MeshError, UnitsError

from .intersect import self_intersections

#: A lung's bounding-box diagonal is 150–400 mm; anything outside this range is not in millimetres.
PLAUSIBLE_DIAGONAL_MM = (20.0, 2000.0)
#: No coordinate of a lung surface in mm (LPS world frame, scanner origin within a few metres) can be
#: beyond 100 m: a larger one is a corrupt value (1e30 written for a missing point), not a lung, and
#: left in, it makes every face around it look degenerate and every mm-scale tolerance meaningless.
PHYSICAL_BOUND_MM = 1e5


# --------------------------------------------------------------------------- normalisation
def as_vertices(vertices, name: str = "vertices") -> np.ndarray:
    """Return ``vertices`` as a C-contiguous ``(n, 3) float64`` array, or raise :class:`InputError`."""
    arr = np.ascontiguousarray(vertices, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (n, 3), got {arr.shape}")
    return arr


def thinned(n: int, count: int, seed: int = 0) -> np.ndarray:
    """Indices ``(min(n, count),) int`` into ``n`` items: all of them, or a seeded random subset of
    ``count`` (sorted; ``numpy.random.default_rng(seed).choice``), to bound a dense solve or a sample."""
    if n <= count:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, count, replace=False))


def farthest_points(points, count: int) -> np.ndarray:
    """Indices ``(min(n, count),) int`` (sorted) of a farthest-point subset of ``points : (n, 3)`` mm:
    the point farthest from their mean first, then each next the one farthest from those taken. The
    subset is deterministic (no seed), spreads evenly over the shape whatever the points' density
    (a decimated mesh packs vertices where the surface bends), and is equivariant under similarity:
    the subset of a scaled, moved copy is the copy of the subset."""
    p = as_vertices(points, "points")
    if int(count) < 1:
        raise InputError(f"count must be >= 1, got {count!r}")
    if len(p) <= count:
        return np.arange(len(p))
    start = int(np.argmax(np.sum((p - p.mean(axis=0)) ** 2, axis=1)))
    return np.sort(_farthest_kernel(p, int(count), start, FARTHEST_CELLS))


#: Cells along the longest side of the bounding box of :func:`farthest_points`' grid.
FARTHEST_CELLS = 16


@numba.njit(cache=True)
def _grid(p, cells):  # pragma: no cover - compiled
    """Points ``p : (n, 3)`` bucketed in a grid of cubes (side ``h``, ``cells`` along the longest side
    of the bounding box): ``lo (3,)``, ``h``, ``size (3,)``, the offsets ``first (C + 1,)`` of each
    cell's points in ``order (n,)`` (the original indices, ascending inside each cell), the occupied
    cells, and the points' coordinates in that order as three contiguous rows."""
    n = p.shape[0]
    lo, size = np.empty(3), np.empty(3, np.int64)
    ext = 0.0
    for c in range(3):
        lo[c] = p[:, c].min()
        ext = max(ext, p[:, c].max() - lo[c])
    h = max(ext / cells, 1e-300)
    for c in range(3):
        size[c] = int((p[:, c].max() - lo[c]) / h) + 1
    cell = np.empty(n, np.int64)
    for i in range(n):
        a = min(int((p[i, 0] - lo[0]) / h), size[0] - 1)
        b = min(int((p[i, 1] - lo[1]) / h), size[1] - 1)
        cell[i] = (a * size[1] + b) * size[2] + min(int((p[i, 2] - lo[2]) / h), size[2] - 1)
    first = np.zeros(size[0] * size[1] * size[2] + 1, np.int64)
    for i in range(n):
        first[cell[i] + 1] += 1
    first = np.cumsum(first)
    fill, order = first[:-1].copy(), np.empty(n, np.int64)
    for i in range(n):  # in index order: ascending inside each cell
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    xyz = np.empty((3, n))
    for t in range(n):
        xyz[0, t], xyz[1, t], xyz[2, t] = p[order[t], 0], p[order[t], 1], p[order[t], 2]
    return lo, h, size, first, order, np.nonzero(first[1:] > first[:-1])[0], xyz


@numba.njit(cache=True)
def _cell_top(d, order, a, b):  # pragma: no cover - compiled
    """The largest of ``d[a:b]`` and the smallest original index holding it."""
    best, arg = -1.0, -1
    for t in range(a, b):
        if d[t] > best or (d[t] == best and order[t] < arg):
            best, arg = d[t], order[t]
    return best, arg


@numba.njit(cache=True)
def _farthest_kernel(p, count, start, cells):  # pragma: no cover - compiled
    """The greedy farthest-point picks from ``start`` (the first point of largest distance to those
    taken, each time). Exact, pruned: a pick can only lower the distances of points nearer to it than
    the largest distance so far, so only the grid cells (:func:`_grid`) within that reach, plus one
    cell of margin, are visited; each cell keeps its largest distance and first index holding it."""
    lo, h, size, first, order, occupied, xyz = _grid(p, cells)
    d = np.full(p.shape[0], np.inf)
    top, arg = np.full(len(first) - 1, np.inf), np.empty(len(first) - 1, np.int64)
    for c in occupied:
        arg[c] = order[first[c]]
    out = np.empty(count, np.int64)
    out[0] = start
    j = start
    reach = np.inf
    for k in range(1, count):
        q = p[j]
        span = np.empty((3, 2), np.int64)
        for c in range(3):
            r = np.sqrt(reach)  # inf at the first pick: every cell
            span[c, 0] = 0 if r == np.inf else max(int((q[c] - r - lo[c]) / h) - 1, 0)
            span[c, 1] = size[c] - 1 if r == np.inf else min(int((q[c] + r - lo[c]) / h) + 1, size[c] - 1)
        for a in range(span[0, 0], span[0, 1] + 1):
            for b in range(span[1, 0], span[1, 1] + 1):
                for c in range(span[2, 0], span[2, 1] + 1):
                    cell = (a * size[1] + b) * size[2] + c
                    changed = False
                    for t in range(first[cell], first[cell + 1]):
                        e = (xyz[0, t] - q[0]) ** 2 + (xyz[1, t] - q[1]) ** 2 + (xyz[2, t] - q[2]) ** 2
                        if e < d[t]:
                            d[t] = e
                            changed = True
                    if changed:
                        top[cell], arg[cell] = _cell_top(d, order, first[cell], first[cell + 1])
        reach, j = -1.0, -1
        for c in occupied:  # the largest distance; on a tie, the smallest index
            if top[c] > reach or (top[c] == reach and arg[c] < j):
                reach, j = top[c], arg[c]
        out[k] = j
    return out


def as_faces(faces, n_vertices: int | None = None, name: str = "faces") -> np.ndarray:
    """Return ``faces`` as a C-contiguous ``(m, 3) int64`` array, or raise :class:`InputError`."""
    arr = np.asarray(faces)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (m, 3), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.mod(arr, 1) == 0):
            raise InputError(f"{name} must hold integer vertex indices")
    arr = np.ascontiguousarray(arr, dtype=np.int64)
    if n_vertices is not None and arr.size and (arr.min() < 0 or arr.max() >= n_vertices):
        raise InputError(f"{name} index a vertex outside 0..{n_vertices - 1}")
    return arr


# --------------------------------------------------------------------------- measures
def face_normals(vertices: np.ndarray, faces: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Face normals ``(m, 3) float``; unnormalised ones have length twice the face area (mm²)."""
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    if normalize:
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = n / np.where(length > 0, length, 1.0)
    return n


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Face areas ``(m,) float`` in mm²."""
    return 0.5 * np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=1)


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total area in mm²."""
    return float(face_areas(vertices, faces).sum())


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume in mm³ by the divergence theorem; positive for outward-oriented faces.

    Computed about the centroid of the vertices to limit cancellation far from the origin.
    """
    c = vertices.mean(axis=0) if len(vertices) else np.zeros(3)
    v = vertices[faces] - c
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals ``(n, 3) float``, unit length (zero for isolated vertices)."""
    fn = face_normals(vertices, faces, normalize=False)
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


@numba.njit(cache=True, parallel=True)
def _winding_kernel(points, vertices, faces):
    """Σ over faces of the solid angle's half-angle (Van Oosterom–Strackee), per point, over 2π."""
    out = np.empty(points.shape[0])
    for p in numba.prange(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        total = 0.0
        for f in range(faces.shape[0]):
            u, v, w = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = vertices[u, 0] - x, vertices[u, 1] - y, vertices[u, 2] - z
            bx, by, bz = vertices[v, 0] - x, vertices[v, 1] - y, vertices[v, 2] - z
            cx, cy, cz = vertices[w, 0] - x, vertices[w, 1] - y, vertices[w, 2] - z
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
                   + (cx * ax + cy * ay + cz * az) * lb)
            total += np.arctan2(det, den)
        out[p] = total / (2.0 * np.pi)
    return out


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number ``(q,) float`` of ``points : (q, 3)`` mm about a closed, outward
    surface: 1 inside, 0 outside (the solid angles of the faces seen from each point, over 4π;
    Van Oosterom–Strackee). O(q·m), a numba kernel parallel over the points (no ``(q, m)`` temporaries)."""
    q = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3))
    return _winding_kernel(q, np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(faces, dtype=np.int64))


@numba.njit(cache=True)
def _yz_bins(boxes, cells):
    """Bin triangles by their ``boxes : (m, 4)`` (y min, y max, z min, z max) in a ``cells × cells`` grid
    over the boxes' (y, z) extent, each in every cell its box meets: ``(ptr (cells² + 1,), members
    (slots,) triangle per slot, cell by cell, grid (4,) = (y0, z0, hy, hz))``. A point's cell (the
    same monotone rounding, :func:`_yz_cell`) holds every triangle whose box holds the point."""
    y0, z0 = boxes[:, 0].min(), boxes[:, 2].min()
    hy = max((boxes[:, 1].max() - y0) / cells, 1e-12)
    hz = max((boxes[:, 3].max() - z0) / cells, 1e-12)
    grid = np.array([y0, z0, hy, hz])
    counts = np.zeros(cells * cells + 1, np.int64)
    for f in range(boxes.shape[0]):
        a0, a1, b0, b1 = _yz_span(boxes[f], grid, cells)
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                counts[a * cells + b + 1] += 1
    ptr = np.cumsum(counts)
    fill = ptr[:-1].copy()
    members = np.empty(ptr[-1], np.int64)
    for f in range(boxes.shape[0]):
        a0, a1, b0, b1 = _yz_span(boxes[f], grid, cells)
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                members[fill[a * cells + b]] = f
                fill[a * cells + b] += 1
    return ptr, members, grid


@numba.njit(cache=True, inline="always")
def _yz_span(box, grid, cells):
    """``(a0, a1, b0, b1)``: the cells (inclusive ranges along y, z) of :func:`_yz_bins`' grid ``grid =
    (y0, z0, hy, hz)`` that a triangle's ``box (4,)`` (y min, y max, z min, z max) meets."""
    return (_yz_cell(box[0], grid[0], grid[2], cells), _yz_cell(box[1], grid[0], grid[2], cells),
            _yz_cell(box[2], grid[1], grid[3], cells), _yz_cell(box[3], grid[1], grid[3], cells))


@numba.njit(cache=True, inline="always")
def _yz_cell(x, lo, h, cells):
    """The cell (``0 .. cells − 1``, clipped) of one axis of :func:`_yz_bins`' grid that holds ``x``."""
    return min(max(int(np.floor((x - lo) / h)), 0), cells - 1)


@numba.njit(cache=True, parallel=True)
def _parity_kernel(points, tri, boxes, bins):
    """Per point: whether a ray along +x crosses the triangles ``tri : (m, 3 corners, 3)`` an odd number
    of times; ``boxes : (m, 4)`` each triangle's (y min, y max, z min, z max), checked first, for the
    triangles binned in the point's (y, z) cell (``bins``, :func:`_yz_bins`; every triangle whose box
    holds the point is there, so the count is the count over all triangles)."""
    ptr, members, grid = bins
    cells = int(np.sqrt(ptr.shape[0] - 1) + 0.5)
    out = np.zeros(points.shape[0], np.bool_)
    for p in numba.prange(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        cell = _yz_cell(y, grid[0], grid[2], cells) * cells + _yz_cell(z, grid[1], grid[3], cells)
        crossings = 0
        for slot in range(ptr[cell], ptr[cell + 1]):
            f = members[slot]
            if y < boxes[f, 0] or y > boxes[f, 1] or z < boxes[f, 2] or z > boxes[f, 3]:
                continue
            ay, az, by, bz, cy, cz = tri[f, 0, 1], tri[f, 0, 2], tri[f, 1, 1], tri[f, 1, 2], tri[f, 2, 1], tri[f, 2, 2]
            det = (by - ay) * (cz - az) - (cy - ay) * (bz - az)
            if det == 0.0:
                continue
            l1 = ((y - ay) * (cz - az) - (cy - ay) * (z - az)) / det
            l2 = ((by - ay) * (z - az) - (y - ay) * (bz - az)) / det
            if l1 < 0.0 or l2 < 0.0 or l1 + l2 > 1.0:
                continue
            if tri[f, 0, 0] + l1 * (tri[f, 1, 0] - tri[f, 0, 0]) + l2 * (tri[f, 2, 0] - tri[f, 0, 0]) > x:
                crossings += 1
        out[p] = crossings % 2 == 1
    return out


def inside_by_parity(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(q,) bool``: ``points : (q, 3)`` mm inside a closed surface, by the parity of a ray along +x
    (as :func:`winding_numbers` ``> 0.5`` for a closed surface and points off it, at a fraction of its
    cost: a point tests only the triangles binned in its (y, z) cell, and of those the ones whose (y, z)
    box holds it). A ray exactly through an edge or a vertex (measure zero for points not on a lattice
    of the mesh) may count a crossing twice."""
    q = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3))
    tri = np.ascontiguousarray(np.asarray(vertices, float)[np.asarray(faces, np.int64)])
    if len(tri) == 0:
        return np.zeros(len(q), bool)
    boxes = np.ascontiguousarray(np.stack([tri[:, :, 1].min(axis=1), tri[:, :, 1].max(axis=1),
                                           tri[:, :, 2].min(axis=1), tri[:, :, 2].max(axis=1)], axis=1))
    # about one triangle's box per cell: sqrt(m) cells a side over the surface's (y, z) extent
    return _parity_kernel(q, tri, boxes, _yz_bins(boxes, max(int(np.sqrt(len(tri))), 1)))


def inside_nodes(coords, faces, dims) -> np.ndarray:
    """``(nz, ny, nx) bool``: the nodes ``(i, j, k)`` (integers, ``i < nx``, ``j < ny``, ``k < nz``) of a
    regular grid inside a closed surface whose vertices lie at ``coords : (n, 3)`` in node units
    (continuous ``(i, j, k)``; ``dims = (nx, ny, nz)``), by the parity of a ray along each row (axis
    ``i``) crossing the triangles: one pass over the triangles, each visiting only the rows its
    ``(j, k)`` projection covers. The rays are shifted by 10⁻⁵ node so that none runs exactly through
    a vertex or an edge."""
    nx, ny, nz = (int(n) for n in dims)
    c = np.array(coords, dtype=float).reshape(-1, 3)
    c[:, 1] += 1.0e-5 * np.pi
    c[:, 2] += 1.0e-5 * np.e
    t = c[np.asarray(faces, np.int64)]  # (m, 3 corners, 3)
    jlo = np.maximum(np.ceil(t[:, :, 1].min(axis=1)), 0).astype(int)
    jhi = np.minimum(np.floor(t[:, :, 1].max(axis=1)), ny - 1).astype(int)
    klo = np.maximum(np.ceil(t[:, :, 2].min(axis=1)), 0).astype(int)
    khi = np.minimum(np.floor(t[:, :, 2].max(axis=1)), nz - 1).astype(int)
    nj, nk = np.maximum(jhi - jlo + 1, 0), np.maximum(khi - klo + 1, 0)
    tri = np.repeat(np.arange(len(t)), nj * nk)
    r = np.arange(len(tri)) - np.repeat(np.cumsum(nj * nk) - nj * nk, nj * nk)  # rank within a triangle
    j = jlo[tri] + r % nj[tri]
    k = klo[tri] + r // np.maximum(nj[tri], 1)
    a, b, cc = t[tri, 0], t[tri, 1], t[tri, 2]
    # barycentric coordinates of the row (j, k) in the triangle's (j, k) projection
    det = (b[:, 1] - a[:, 1]) * (cc[:, 2] - a[:, 2]) - (cc[:, 1] - a[:, 1]) * (b[:, 2] - a[:, 2])
    ok = det != 0
    det = np.where(ok, det, 1.0)
    l1 = ((j - a[:, 1]) * (cc[:, 2] - a[:, 2]) - (cc[:, 1] - a[:, 1]) * (k - a[:, 2])) / det
    l2 = ((b[:, 1] - a[:, 1]) * (k - a[:, 2]) - (j - a[:, 1]) * (b[:, 2] - a[:, 2])) / det
    hit = ok & (l1 > 0) & (l2 > 0) & (l1 + l2 < 1)
    x = (a[:, 0] + l1 * (b[:, 0] - a[:, 0]) + l2 * (cc[:, 0] - a[:, 0]))[hit]
    first = np.clip(np.floor(x).astype(int) + 1, 0, nx)  # the first node past the crossing
    counts = np.zeros((nz, ny, nx + 1), np.int32)
    np.add.at(counts, (k[hit], j[hit], first), 1)
    return (np.cumsum(counts, axis=2)[:, :, :nx] % 2).astype(bool)


def bounding_box(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(min, max)``, each ``(3,) float`` in the frame of ``vertices``."""
    return vertices.min(axis=0), vertices.max(axis=0)


# --------------------------------------------------------------------------- topology
def _edge_keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One int64 key per vertex pair ``(a, b)`` (order kept): sorting keys beats ``unique(axis=0)``."""
    return a.astype(np.int64) << np.int64(32) | b.astype(np.int64)


def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges and the face-edge map.

    Returns
    -------
    edges : (e, 2) int64
        Sorted vertex pairs ``(a, b)`` with ``a < b``, in lexicographic order.
    face_edges : (m, 3) int64
        ``face_edges[f, k]`` is the edge from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``.
    """
    f = np.asarray(faces, dtype=np.int64)
    a, b = f.ravel(), np.roll(f, -1, axis=1).ravel()
    keys, inverse = np.unique(_edge_keys(np.minimum(a, b), np.maximum(a, b)), return_inverse=True)
    edges = np.stack([keys >> np.int64(32), keys & np.int64(0xFFFFFFFF)], axis=1)
    return np.ascontiguousarray(edges), inverse.reshape(-1, 3)


def edge_face_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(edges (e, 2), counts (e,))``: how many faces share each undirected edge."""
    edges, face_edges = unique_edges(faces)
    counts = np.bincount(face_edges.ravel(), minlength=len(edges))
    return edges, counts


def vertex_adjacency(n_vertices: int, edges: np.ndarray) -> sparse.csr_matrix:
    """Symmetric ``(n, n)`` 0/1 adjacency of the edge graph."""
    data = np.ones(2 * len(edges))
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    return sparse.csr_matrix((data, (rows, cols)), shape=(n_vertices, n_vertices))


def face_components(faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of faces through shared vertices: ``(count, labels (m,))``."""

    m = len(faces)
    if m == 0:
        return 0, np.zeros(0, dtype=np.int64)
    n = int(faces.max()) + 1
    # bipartite face-vertex incidence: faces are nodes 0..m-1, vertices m..m+n-1
    rows = np.repeat(np.arange(m), 3)
    cols = m + faces.ravel()
    g = sparse.csr_matrix((np.ones(3 * m), (rows, cols)), shape=(m + n, m + n))
    count, labels = connected_components(g, directed=False)
    face_labels = labels[:m]
    uniq, relabelled = np.unique(face_labels, return_inverse=True)
    return len(uniq), relabelled


def distinct(values: np.ndarray) -> np.ndarray:
    """The distinct values of an integer array, sorted (``np.unique(values)``), found by a sort:
    NumPy 2's ``np.unique`` hashes, about 60 times slower on the 384 000 edge keys of a lung surface
    (256 ms against 4 ms CPU measured here)."""
    s = np.sort(np.asarray(values).ravel())
    return s[np.r_[True, s[1:] != s[:-1]]] if s.size else s


def orientation_consistent(faces: np.ndarray) -> bool:
    """True when every directed edge occurs once: neighbouring faces wind the same way."""
    f = np.asarray(faces, dtype=np.int64)
    keys = _edge_keys(f.ravel(), np.roll(f, -1, axis=1).ravel())
    return len(distinct(keys)) == len(keys)


def non_manifold_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Indices of vertices whose fan of faces is more than one disc (pinched vertices).

    Face corners at the same vertex are linked when their faces share an edge through that vertex;
    a manifold vertex has all its corners in one linked group.
    """

    m = len(faces)
    _, face_edges = unique_edges(faces)
    corner = np.arange(3 * m).reshape(m, 3)
    # each face edge k touches corner k (its start) and corner k+1 (its end)
    rec_edge = np.concatenate([face_edges.ravel(), face_edges.ravel()])
    rec_corner = np.concatenate([corner.ravel(), np.roll(corner, -1, axis=1).ravel()])
    rec_vertex = faces.ravel()[rec_corner]
    order = np.lexsort((rec_vertex, rec_edge))
    e, vv, c = rec_edge[order], rec_vertex[order], rec_corner[order]
    same = (e[1:] == e[:-1]) & (vv[1:] == vv[:-1])
    g = sparse.csr_matrix(
        (np.ones(int(same.sum())), (c[:-1][same], c[1:][same])), shape=(3 * m, 3 * m)
    )
    count, labels = connected_components(g, directed=False)
    # the distinct (vertex, fan) pairs, as one int64 key each (faster than unique(axis=1))
    fans = distinct(faces.ravel().astype(np.int64) * np.int64(count) + labels) // np.int64(count)
    per_vertex = np.bincount(fans, minlength=n_vertices)
    return np.nonzero(per_vertex > 1)[0].astype(np.int64)


# --------------------------------------------------------------------------- checks
@dataclass(frozen=True)
class SurfaceReport:
    """What :func:`check_surface` found and, with ``repair=True``, what it changed; ``warnings``:
    suspicious but usable input found by the caller (e.g. a mask cropped by the image border)."""

    n_vertices: int
    n_faces: int
    volume_mm3: float
    area_mm2: float
    repairs: tuple[str, ...] = field(default_factory=tuple)
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def volume_ml(self) -> float:
        return self.volume_mm3 / 1000.0


def check_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    source: str = "surface",
    repair: bool = False,
) -> tuple[np.ndarray, np.ndarray, SurfaceReport]:
    """Check that a surface can be a lung model; optionally repair what can be repaired.

    Checks, in order: finite coordinates within :data:`PHYSICAL_BOUND_MM`; no degenerate faces; closed (every edge in exactly two
    faces); 2-manifold (no pinched vertices); consistently oriented; a single component; outward
    orientation (positive signed volume); millimetre units (bounding-box diagonal within
    :data:`PLAUSIBLE_DIAGONAL_MM`).

    With ``repair=True`` these are fixed and reported: unreferenced vertices are dropped,
    degenerate and duplicate faces removed, all but the largest component dropped, and inward
    orientation flipped. Open, non-manifold, self-intersecting or non-physical surfaces and wrong
    units are never repaired.

    Returns ``(vertices (n, 3) float mm, faces (m, 3) int, report)``. Raises :class:`MeshError`
    (or :class:`UnitsError`) whose message starts with ``source``.
    """
    v = as_vertices(vertices, f"{source}: vertices")
    f = as_faces(faces, len(v), f"{source}: faces")
    repairs: list[str] = []
    _check_physical(v, f, source)
    if len(f) < 4:
        raise MeshError(f"{source}: a closed surface needs at least 4 faces, got {len(f)}")
    # unreferenced vertices are harmless for checks; drop them quietly only on repair
    if repair and len(np.unique(f)) < len(v):
        n_before = len(v)
        v, f = _compact(v, f)
        repairs.append(f"dropped {n_before - len(v)} unreferenced vertices")
    v, f = _without_degenerate_faces(v, f, source, repair, repairs)
    f = _without_duplicate_faces(v, f, source, repair, repairs)
    v, f = _largest_component(v, f, source, repair, repairs)
    _check_closed_manifold(v, f, source)
    if not orientation_consistent(f):
        if not repair:
            raise MeshError(f"{source}: faces are not consistently oriented")
        f = _orient_consistently(f)
        repairs.append("re-oriented faces consistently")
    _check_no_self_intersection(v, f, source)
    vol = signed_volume(v, f)
    if vol < 0:
        if not repair:
            raise MeshError(f"{source}: faces point inward (negative volume); pass repair to flip them")
        f = np.ascontiguousarray(f[:, ::-1])
        vol = -vol
        repairs.append("flipped inward-facing orientation")
    _check_millimetres(v, source)
    report = SurfaceReport(len(v), len(f), vol, surface_area(v, f), tuple(repairs))
    return v, f, report


def _check_physical(v, f, source: str) -> None:
    """Refuse NaN, infinite or non-physical coordinates (beyond :data:`PHYSICAL_BOUND_MM`) of the
    vertices the faces use, naming the first such vertex: before any other check, which they
    would confuse."""
    used = distinct(f)
    if not np.isfinite(v[used]).all():
        raise MeshError(f"{source}: vertex coordinates contain NaN or infinity")
    beyond = np.abs(v[used]) > PHYSICAL_BOUND_MM
    if beyond.any():
        rows = np.nonzero(beyond.any(axis=1))[0]
        i = int(used[rows[0]])
        value = float(v[i][np.argmax(np.abs(v[i]))])
        raise MeshError(
            f"{source}: vertex {i} has coordinate {value:.6g} mm, beyond the physical bound of "
            f"±{PHYSICAL_BOUND_MM:g} mm ({len(rows)} such vertices): not a lung surface"
        )


def _check_no_self_intersection(v, f, source: str) -> None:
    """Refuse a surface that passes through itself (never repaired: its inside is undefined, so
    its volume and orientation mean nothing)."""
    count, pairs = self_intersections(v, f, limit=1)
    if count:
        a, b = (int(x) for x in pairs[0])
        raise MeshError(
            f"{source}: surface intersects itself ({count} pairs of faces cross, e.g. faces {a} and {b}); "
            "a lung surface must not: fix the segmentation or the mesh"
        )


def _without_degenerate_faces(v, f, source: str, repair: bool, repairs: list[str]):
    """``(v, f)`` without faces that repeat a vertex or have (near) zero area: refused, or with
    ``repair`` removed (noted in ``repairs``) and the vertices compacted."""
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    degenerate |= face_areas(v, f) <= 1e-12 * max(1.0, float(np.ptp(v, axis=0).max()) ** 2)
    if not degenerate.any():
        return v, f
    if not repair:
        raise MeshError(
            f"{source}: {int(degenerate.sum())} degenerate (zero-area) faces; pass repair to remove them"
        )
    repairs.append(f"removed {int(degenerate.sum())} degenerate faces")
    return _compact(v, f[~degenerate])


def _without_duplicate_faces(v, f, source: str, repair: bool, repairs: list[str]) -> np.ndarray:
    """``f`` without faces on the same three vertices as an earlier one: refused, or with
    ``repair`` removed (noted in ``repairs``)."""
    key = np.sort(f, axis=1)
    if len(v) < 2_000_000:  # one int64 per face (n³ < 2⁶³): much faster than unique(axis=0)
        n = np.int64(len(v))
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
    _, first = np.unique(key, axis=0, return_index=True)
    if len(first) == len(f):
        return f
    if not repair:
        raise MeshError(f"{source}: {len(f) - len(first)} duplicate faces")
    repairs.append(f"removed {len(f) - len(first)} duplicate faces")
    return f[np.sort(first)]


def _largest_component(v, f, source: str, repair: bool, repairs: list[str]):
    """``(v, f)`` as one piece: several components are refused, or with ``repair`` all but the
    largest dropped (noted in ``repairs``) and the vertices compacted."""
    n_comp, labels = face_components(f)
    if n_comp <= 1:
        return v, f
    if not repair:
        raise MeshError(
            f"{source}: {n_comp} separate components; a lung surface must be one piece "
            "(pass repair to keep the largest, or select one label)"
        )
    sizes = np.bincount(labels)
    keep = int(np.argmax(sizes))
    repairs.append(f"kept the largest of {n_comp} components ({sizes[keep]} of {len(f)} faces)")
    return _compact(v, f[labels == keep])


def _check_closed_manifold(v, f, source: str) -> None:
    """Refuse an open surface (an edge in one face) or a non-manifold one (an edge in 3+ faces, a
    pinched vertex): never repaired."""
    _, counts = edge_face_counts(f)
    if (counts == 1).any():
        raise MeshError(f"{source}: surface is open ({int((counts == 1).sum())} boundary edges)")
    if (counts > 2).any():
        raise MeshError(
            f"{source}: surface is not 2-manifold ({int((counts > 2).sum())} edges shared by 3+ faces)"
        )
    pinched = non_manifold_vertices(f, len(v))
    if len(pinched):
        raise MeshError(f"{source}: surface is not 2-manifold ({len(pinched)} pinched vertices)")


def _check_millimetres(v, source: str) -> None:
    """Refuse a surface whose bounding-box diagonal is outside :data:`PLAUSIBLE_DIAGONAL_MM`
    (:class:`UnitsError`): not a lung in millimetres."""
    lo, hi = PLAUSIBLE_DIAGONAL_MM
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    if not lo <= diag <= hi:
        hint = " (looks like metres: use --units m)" if diag < lo else " (use --units to rescale)"
        raise UnitsError(
            f"{source}: bounding-box diagonal is {diag:.4g}, not a lung in millimetres "
            f"(expected {lo:g}–{hi:g} mm){hint}"
        )


def _compact(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inverse = np.unique(f, return_inverse=True)
    return np.ascontiguousarray(v[used]), inverse.reshape(f.shape).astype(np.int64)


def _orient_consistently(f: np.ndarray) -> np.ndarray:
    """Flip faces so that neighbours agree, by breadth-first search over the face graph."""

    edges, face_edges = unique_edges(f)
    m = len(f)
    owners: dict[int, list[int]] = {}
    for fi in range(m):
        for e in face_edges[fi]:
            owners.setdefault(int(e), []).append(fi)
    f = f.copy()
    seen = np.zeros(m, dtype=bool)
    for start in range(m):
        if seen[start]:
            continue
        seen[start] = True
        queue = deque([start])
        while queue:
            a = queue.popleft()
            da = {(f[a, k], f[a, (k + 1) % 3]) for k in range(3)}
            for e in face_edges[a]:
                for b in owners[int(e)]:
                    if seen[b]:
                        continue
                    db = {(f[b, k], f[b, (k + 1) % 3]) for k in range(3)}
                    if da & db:  # same directed edge: b winds the other way
                        f[b] = f[b, ::-1]
                    seen[b] = True
                    queue.append(b)
    return f


# --------------------------------------------------------------------------- the bundle
@dataclass(frozen=True, eq=False)
class Surface:
    """A closed triangle surface.

    Attributes
    ----------
    vertices : (n, 3) float64
        Vertex positions, mm, LPS world frame (unless ``frame`` says otherwise).
    faces : (m, 3) int64
        Counter-clockwise seen from outside.
    name : str
        Where the surface came from (a file name, ``"left"``); used in messages.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = "surface"

    def __post_init__(self):
        v = as_vertices(self.vertices, f"{self.name}: vertices")
        f = as_faces(self.faces, len(v), f"{self.name}: faces")
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    # derived data, cached
    @cached_property
    def volume(self) -> float:
        """Enclosed volume, mm³."""
        return signed_volume(self.vertices, self.faces)

    @property
    def volume_ml(self) -> float:
        """Enclosed volume, mL."""
        return self.volume / 1000.0

    @cached_property
    def area(self) -> float:
        """Surface area, mm²."""
        return surface_area(self.vertices, self.faces)

    @cached_property
    def edges(self) -> np.ndarray:
        """``(e, 2) int64`` undirected edges, sorted."""
        e = unique_edges(self.faces)[0]
        e.setflags(write=False)
        return e

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """``(n, 3) float`` unit outward normals."""
        return vertex_normals(self.vertices, self.faces)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min (3,), max (3,))`` in mm."""
        return bounding_box(self.vertices)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def checked(self, repair: bool = False) -> tuple["Surface", SurfaceReport]:
        """Run :func:`check_surface`; return the (possibly repaired) surface and the report."""
        v, f, report = check_surface(self.vertices, self.faces, source=self.name, repair=repair)
        if not report.repairs:
            return self, report
        return Surface(v, f, self.name), report

    def deformed(self, displacement: np.ndarray) -> "Surface":
        """A new surface with ``vertices + displacement`` (``(n, 3) float`` mm)."""
        d = as_vertices(displacement, "displacement")
        if d.shape != self.vertices.shape:
            raise InputError(f"displacement must have shape {self.vertices.shape}, got {d.shape}")
        return Surface(self.vertices + d, self.faces, self.name)

    def scaled(self, factor: float, about: np.ndarray | None = None) -> "Surface":
        """A new surface scaled by ``factor`` about ``about`` (default: the vertex centroid)."""
        c = self.vertices.mean(axis=0) if about is None else np.asarray(about, dtype=float)
        return Surface(c + factor * (self.vertices - c), self.faces, self.name)

    def transformed(self, matrix: np.ndarray) -> "Surface":
        """A new surface under a 4×4 homogeneous transform (orientation kept if det > 0)."""
        m = np.asarray(matrix, dtype=float)
        if m.shape != (4, 4):
            raise InputError(f"matrix must be 4×4, got {m.shape}")
        v = self.vertices @ m[:3, :3].T + m[:3, 3]
        f = self.faces if np.linalg.det(m[:3, :3]) > 0 else self.faces[:, ::-1]
        return Surface(v, f, self.name)

    def with_name(self, name: str) -> "Surface":
        return Surface(self.vertices, self.faces, name)

    def __repr__(self) -> str:
        return f"Surface({self.name!r}, {self.n_vertices} vertices, {len(self.faces)} faces)"


def icosphere(subdivisions: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Surface:
    """An outward-oriented geodesic sphere (for tests and analytic checks)."""
    t = (1.0 + 5**0.5) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=float)
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    for _ in range(subdivisions):
        v, f = subdivide(v, f)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    return Surface(np.asarray(center, float) + radius * v, f, "icosphere")


def subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Loop-free midpoint subdivision: every face becomes four (shape unchanged, 4× faces)."""
    edges, face_edges = unique_edges(faces)
    mid = 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]])
    n = len(vertices)
    v = np.vstack([vertices, mid])
    a, b, c = faces.T
    ab, bc, ca = (n + face_edges[:, k] for k in range(3))
    f = np.concatenate(
        [np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
         np.stack([ab, bc, ca], 1)]
    )
    return np.ascontiguousarray(v), np.ascontiguousarray(f, dtype=np.int64)
