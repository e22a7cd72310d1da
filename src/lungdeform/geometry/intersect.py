"""Self-intersection of a triangle surface: pairs of faces that cross each other.

A closed surface that passes through itself (a cap pushed through the opposite wall, a fold left by
smoothing) has no inside: its signed volume is the difference of the pieces and its orientation
cannot be told, so it must be refused before the orientation diagnosis of
:func:`lungdeform.geometry.mesh.check_surface`.

Broad phase: face bounding boxes binned in a uniform grid (cell side about twice the mean box side,
grown until a face covers few cells); each candidate pair is tested once, in the cell holding the
lower corner of the two boxes' overlap. Narrow phase (numba): two triangles cross when an edge of
one passes strictly through the other (signs of 3-D orientation determinants, with a tolerance
relative to the face size so that coplanar faces are not counted). Only faces that share no vertex
are tested: neighbours meet along their shared edge or corner by construction. Crossings of faces
within :data:`LOCAL_RINGS` edges of each other are not counted either: a fold within a vertex's
fan (the embedded right lung has two) or a wrinkle the model's own deformation makes at a thin edge
of a lung (the synthetic cohort's targets) leaves inside and outside as they were, unlike a surface
that passes through another part of itself.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import sparse

#: Relative tolerance of the orientation determinants (times the cube of the pair's size, mm³).
_REL_TOL = 1e-10
#: The grid grows until the faces cover at most this many cells each on average.
_MAX_CELLS_PER_FACE = 8.0
#: Crossings between faces whose vertices are at most this many edges apart are local wrinkles, not a
#: surface passing through another part of itself; they are not counted. Three: the deformed synthetic
#: targets of :mod:`lungdeform.cohort.synthetic` (the model at 300-500 mL, vertex noise up to 1 mm)
#: have folds up to three edges across; a pushed-through cap is tens of edges from the wall it crosses.
LOCAL_RINGS = 3


@numba.njit(cache=True, inline="always")
def _orient(a, b, c, d):
    """Six times the signed volume of tetrahedron abcd (each a (3,) array)."""
    ax, ay, az = a[0] - d[0], a[1] - d[1], a[2] - d[2]
    bx, by, bz = b[0] - d[0], b[1] - d[1], b[2] - d[2]
    cx, cy, cz = c[0] - d[0], c[1] - d[1], c[2] - d[2]
    return ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)


@numba.njit(cache=True)
def _segment_crosses(p, q, a, b, c, tol):
    """True when segment pq crosses the plane of triangle abc strictly, inside the triangle."""
    s1 = _orient(a, b, c, p)
    s2 = _orient(a, b, c, q)
    if not ((s1 > tol and s2 < -tol) or (s1 < -tol and s2 > tol)):
        return False
    e1 = _orient(p, q, a, b)
    e2 = _orient(p, q, b, c)
    e3 = _orient(p, q, c, a)
    # through the triangle or exactly through one of its edges or corners (then the face beside
    # it counts as well): all three on one side, zero allowed
    return (e1 >= -tol and e2 >= -tol and e3 >= -tol) or (e1 <= tol and e2 <= tol and e3 <= tol)


@numba.njit(cache=True)
def _faces_cross(v, fa, fb, tol):
    """True when faces ``fa`` and ``fb`` (vertex index triples) share no vertex and an edge of one
    passes through the other."""
    for i in range(3):
        for j in range(3):
            if fa[i] == fb[j]:
                return False
    for k in range(3):
        if _segment_crosses(v[fa[k]], v[fa[(k + 1) % 3]], v[fb[0]], v[fb[1]], v[fb[2]], tol):
            return True
        if _segment_crosses(v[fb[k]], v[fb[(k + 1) % 3]], v[fa[0]], v[fa[1]], v[fa[2]], tol):
            return True
    return False


@numba.njit(cache=True)
def _register(cell_lo, cell_hi, dims, total):
    """(face, cell key) pairs for every cell each face's box covers."""
    face = np.empty(total, np.int64)
    key = np.empty(total, np.int64)
    r = 0
    for f in range(len(cell_lo)):
        for i in range(cell_lo[f, 0], cell_hi[f, 0] + 1):
            for j in range(cell_lo[f, 1], cell_hi[f, 1] + 1):
                for k in range(cell_lo[f, 2], cell_hi[f, 2] + 1):
                    face[r] = f
                    key[r] = (i * dims[1] + j) * dims[2] + k
                    r += 1
    return face, key


@numba.njit(cache=True)
def _narrow(mesh, grid, cells, limit):
    """Count crossing face pairs over the runs of equal cell key; keep the first ``limit``. ``mesh`` =
    ``(v, faces, lo, hi)`` (the faces' bounding-box corners ``lo, hi : (m, 3)``), ``grid`` = ``(origin,
    h, dims)``, ``cells`` = ``(face, key)`` the face of each cell entry and its cell, sorted by cell."""
    v, faces, lo, hi = mesh
    origin, h, dims = grid
    face, key = cells
    pairs = np.empty((limit, 2), np.int64)
    count = 0
    n = len(key)
    start = 0
    while start < n:
        end = start
        while end < n and key[end] == key[start]:
            end += 1
        ck = key[start]
        cell = (ck // (dims[1] * dims[2]), (ck // dims[2]) % dims[1], ck % dims[2])
        for x in range(start, end):
            a = face[x]
            for y in range(x + 1, end):
                b = face[y]
                overlap = True
                for d in range(3):
                    if lo[a, d] > hi[b, d] or lo[b, d] > hi[a, d]:
                        overlap = False
                if not overlap:
                    continue
                home = True  # test each pair once: in the cell of the overlap's lower corner
                for d in range(3):
                    c = int(np.floor((max(lo[a, d], lo[b, d]) - origin[d]) / h))
                    if min(max(c, 0), dims[d] - 1) != cell[d]:
                        home = False
                if not home:
                    continue
                size = 0.0
                for d in range(3):
                    size = max(size, hi[a, d] - lo[a, d], hi[b, d] - lo[b, d])
                if _faces_cross(v, faces[a], faces[b], _REL_TOL * size ** 3):
                    if count < limit:
                        pairs[count, 0], pairs[count, 1] = min(a, b), max(a, b)
                    count += 1
        start = end
    return count, pairs[:min(count, limit)]


def self_intersections(vertices: np.ndarray, faces: np.ndarray, limit: int = 100,
                       local_rings: int = LOCAL_RINGS) -> tuple[int, np.ndarray]:
    """Face pairs that cross each other: not along a shared edge or at a shared vertex, and not
    within ``local_rings`` edges of each other (a local wrinkle, :data:`LOCAL_RINGS`).

    Parameters
    ----------
    vertices : (n, 3) float
        Finite vertex positions, mm (any frame).
    faces : (m, 3) int
        Non-degenerate faces.
    limit : int
        How many pairs to return (all are counted).
    local_rings : int
        Crossings of faces with vertices this many edges apart or fewer are not counted (0: count
        every crossing of faces without a shared vertex).

    Returns
    -------
    count : int
        The number of crossing face pairs.
    pairs : (min(count, limit), 2) int64
        Face indices ``(a, b)`` with ``a < b``, in the order found.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if len(f) < 2:
        return 0, np.zeros((0, 2), np.int64)
    corners = v[f]
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    origin = lo.min(axis=0)
    h = max(2.0 * float((hi - lo).max(axis=1).mean()), 1e-9 * float(np.ptp(v, axis=0).max()), 1e-300)
    while True:
        cell_lo = np.floor((lo - origin) / h).astype(np.int64)
        cell_hi = np.floor((hi - origin) / h).astype(np.int64)
        total = int(np.prod(cell_hi - cell_lo + 1, axis=1).sum())
        if total <= _MAX_CELLS_PER_FACE * len(f):
            break
        h *= 2.0
    dims = cell_hi.max(axis=0) + 1
    face, key = _register(cell_lo, cell_hi, dims, total)
    order = np.argsort(key, kind="stable")
    kept = 4 * len(f) + 16  # beyond this many crossings all are counted, none found local
    count, pairs = _narrow((v, f, lo, hi), (origin, h, dims), (face[order], key[order]), kept)
    if local_rings > 0 and len(pairs):
        far = ~_within_rings(f, len(v), pairs, local_rings)
        count, pairs = count - len(pairs) + int(far.sum()), pairs[far]
    return count, pairs[:limit]


def _within_rings(faces: np.ndarray, n_vertices: int, pairs: np.ndarray, rings: int) -> np.ndarray:
    """``(p,) bool``: whether a vertex of face ``pairs[:, 1]`` is within ``rings`` edges of a vertex
    of face ``pairs[:, 0]`` (breadth-first through the edge graph, as sparse products)."""
    a, b = np.sort(faces, axis=1)[:, [0, 1, 1, 2, 0, 2]].reshape(-1, 2).T
    step = sparse.csr_matrix((np.ones(len(a) * 2), (np.r_[a, b], np.r_[b, a])), shape=(n_vertices,) * 2)
    step = (step + sparse.identity(n_vertices, format="csr")).astype(bool).astype(np.int8)
    p = len(pairs)
    reach = sparse.csr_matrix((np.ones(3 * p, np.int8), (faces[pairs[:, 0]].ravel(), np.repeat(np.arange(p), 3))),
                              shape=(n_vertices, p))
    for _ in range(rings):
        reach = (step @ reach).astype(bool).astype(np.int8)
    hit = reach[faces[pairs[:, 1]].ravel(), np.repeat(np.arange(p), 3)]
    return np.asarray(hit).reshape(p, 3).any(axis=1)
