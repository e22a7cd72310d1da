"""Fused per-voxel passes over a displacement-field image (numba, parallel over z-slices).

Arrays: a field is ``(z, y, x, 3) float32`` mm LPS indexed ``[k, j, i]`` (components x, y, z), as in
:mod:`lungdeform.playback.displacement_field`, which owns the grid, the lattice and the meaning of the field; this
module only holds the loops that touch every voxel, so that no full-grid temporary is made:

- :func:`fill_field`: trilinear interpolation of lattice nodes to every voxel of a box plus an
  affine displacement at every voxel, in one pass (the lattice weights per index are precomputed
  along each axis, :func:`axis_weights`; per voxel row one bilinear row of nodes, then one lerp a
  voxel), added into a zeroed output and skipping the voxels it would leave at 0;
- :func:`blend_nodes`: the lungs' lattice fields blended into one (a lung's own field inside it,
  outside each faded and weighted by inverse squared distance), one pass over the nodes;
- :func:`jacobian_pass`: ``det(I + ∇u)`` by central differences in physical units (one-sided at the
  array's edges, as ``numpy.gradient``), written out or reduced to min, max and folded count; 1
  without arithmetic where nothing within a voxel moves.
"""

from __future__ import annotations

import mmap

import numba
import numpy as np


def zeroed(shape) -> np.ndarray:
    """``numpy.zeros(shape, float32)`` in its own private anonymous memory map, which the kernel
    zero-fills a 4 KiB page at a time as it is first written. ``numpy.zeros`` asks for transparent
    huge pages for a large array, and where memory is fragmented the kernel compacted memory at each
    first write (the bench field's fill and Jacobian pass: 0.38–0.90 s of system time that way,
    0.21–0.25 s with 4 KiB pages; 2 shared cores, load 14; docs/RADIOTHERAPY.md). Private, not shared:
    a shared anonymous map is shared memory (shmem), whose faults cost more, and whose pages a read
    allocates; here a page only read maps the kernel's one zero page. A page read before it is written
    faults twice (the zero page, then its copy), so a fresh output is written, not added to
    (:func:`fill_field`'s ``fresh``): 46 000 pages of the bench field 0.09–0.11 CPU-s so, against
    0.14–0.19 shared and added to."""
    size = int(np.prod(shape, dtype=np.int64)) * 4
    if size == 0:
        return np.zeros(shape, np.float32)
    buf = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    return np.frombuffer(buf, np.float32).reshape(shape)


def axis_weights(n_out: int, lo: int, stride: int, nodes: int, box_lo: int, box_hi: int):
    """Per voxel index ``0 … n_out − 1`` along one axis: ``(node (n_out,) int64, frac (n_out,) float32)``,
    the lattice node at or before the voxel and the voxel's fraction of the way to the next (nodes
    ``stride`` voxels apart, node 0 at voxel ``lo``); node −1 outside ``[box_lo, box_hi)``."""
    idx = np.arange(n_out)
    t = (idx - lo) / float(stride)
    node = np.clip(np.floor(t), 0, max(nodes - 2, 0)).astype(np.int64)
    frac = np.clip(t - node, 0.0, 1.0).astype(np.float32) if nodes > 1 else np.zeros(n_out, np.float32)
    node[(idx < box_lo) | (idx >= box_hi)] = -1
    return node, frac


@numba.njit(cache=True)
def _row(values, k0, fz, j0, fy, buf):
    """Write into ``buf : (nx, 3) float32`` the lattice row at (z, y) fractions ``fz``, ``fy`` past
    nodes ``k0``, ``j0`` (bilinear in z and y, every x node; float32 arithmetic)."""
    k1, j1 = min(k0 + 1, values.shape[0] - 1), min(j0 + 1, values.shape[1] - 1)
    gy, gz = np.float32(1.0) - fy, np.float32(1.0) - fz
    for n in range(values.shape[2]):
        for c in range(3):
            buf[n, c] = ((values[k0, j0, n, c] * gy + values[k0, j1, n, c] * fy) * gz
                         + (values[k1, j0, n, c] * gy + values[k1, j1, n, c] * fy) * fz)
    return buf


@numba.njit(cache=True)
def _lerp_row(out, k, j, row, still, axis_i, box_i, fresh):
    """Add into ``out[k, j, i]`` for i in ``box_i`` (i0, i1) the lattice ``row : (nx, 3) float32``
    (:func:`_row`) interpolated linearly (``axis_i`` = ``(nodes, frac)`` of axis i, :func:`axis_weights`:
    node ``nodes[i]`` ≥ 0, fraction ``frac[i]``), skipping the voxels
    between two ``still`` nodes (they would get exactly 0); the arithmetic of :func:`fill_field`'s
    general loop without its affine part (``fresh``: as there). Returns the first and last voxel
    touched (first > last: none)."""
    nodes_i, frac_i = axis_i
    i0, i1 = box_i
    last = row.shape[0] - 1
    lo, hi = i1, i0 - 1
    for i in range(i0, i1):
        n0 = nodes_i[i]
        if n0 < 0:
            continue
        n1 = min(n0 + 1, last)
        if still[n0] and still[n1]:
            continue
        lo, hi = min(lo, i), i
        f = frac_i[i]
        for c in range(3):
            x = row[n0, c] * (1 - f) + row[n1, c] * f
            if fresh:
                out[k, j, i, c] = x + 0.0
            else:
                out[k, j, i, c] += x
    return lo, hi


@numba.njit(cache=True, parallel=True)
def fill_field(out, values, axes, affine_part, ranges, spans, fresh=False):
    """Add into ``out : (z, y, x, 3) float32`` at voxels ``ranges`` (k0, k1, j0, j1, i0, i1): the
    lattice ``values : (nz, ny, nx, 3) float32`` interpolated trilinearly where all three axes' nodes
    are ≥ 0 (else 0), plus ``const + steps @ (i, j, k)``. ``axes`` = the ``(nodes, frac)`` pairs
    (:func:`axis_weights`) of axes k, j, i; ``affine_part`` = ``(const (3,) mm, steps (3, 3) mm per
    voxel)``, column a of ``steps`` along index axis a. Separable: per voxel row one bilinear lattice
    row (:func:`_row`, into a buffer per z-slice), then one lerp per voxel. A voxel that would get
    exactly 0 (outside the lattice, or between two row nodes that do not move, and no affine part)
    is not touched: a fresh ``numpy.zeros`` output is written, and paged in, only where the field moves.
    ``spans`` = ``(first, last)``, ``(z, y) int64`` each: per voxel row the first and last voxel this
    pass touched, widened in place (rows it leaves alone keep theirs; see :func:`no_spans`). ``fresh``:
    ``out`` is all zeros (:func:`zeroed`), so each touched voxel is written ``x + 0`` (the same bits
    as ``0 + x``) without reading it first (:func:`zeroed`: a read then a write faults a page twice).
    Returns ``out``."""
    (nodes_k, frac_k), (nodes_j, frac_j), (nodes_i, frac_i) = axes
    const, steps = affine_part
    first, final = spans
    last = values.shape[2] - 1
    affine = np.any(const != 0) or np.any(steps != 0)
    for k in numba.prange(ranges[0], ranges[1]):
        row = np.empty((values.shape[2], 3), np.float32)
        still = np.ones(values.shape[2], np.bool_)
        for j in range(ranges[2], ranges[3]):
            touched_lo, touched_hi = ranges[5], ranges[4] - 1
            lattice = nodes_k[k] >= 0 and nodes_j[j] >= 0
            if lattice:
                _row(values, nodes_k[k], frac_k[k], nodes_j[j], frac_j[j], row)
                for n in range(values.shape[2]):
                    still[n] = row[n, 0] == 0 and row[n, 1] == 0 and row[n, 2] == 0
            if not affine:
                if lattice:
                    touched_lo, touched_hi = _lerp_row(out, k, j, row, still, (nodes_i, frac_i), (ranges[4], ranges[5]),
                                                       fresh)
                if touched_lo <= touched_hi:
                    first[k, j], final[k, j] = min(first[k, j], touched_lo), max(final[k, j], touched_hi)
                continue
            for i in range(ranges[4], ranges[5]):
                n0 = nodes_i[i]
                inside = lattice and n0 >= 0
                n1 = min(n0 + 1, last)
                touched_lo, touched_hi = min(touched_lo, i), i
                f = frac_i[i]
                for c in range(3):
                    x = 0.0
                    if inside:
                        x = row[n0, c] * (1 - f) + row[n1, c] * f
                    x += const[c] + steps[c, 0] * i + steps[c, 1] * j + steps[c, 2] * k
                    if fresh:
                        out[k, j, i, c] = x + 0.0
                    else:
                        out[k, j, i, c] += x
            if touched_lo <= touched_hi:
                first[k, j], final[k, j] = min(first[k, j], touched_lo), max(final[k, j], touched_hi)
    return out


@numba.njit(cache=True, parallel=True)
def blend_nodes(fields, inside, distance, margin, out):
    """Write into ``out : (n, 3) float`` the blend of the per-lung node displacements ``fields : (L, n,
    3)`` mm: weight ``a_l · φ_l / Σ φ``, ``a_l`` 1 inside lung l (``inside : (L, n) bool``) and else the
    smoothstep ``1 − t²(3 − 2t)``, ``t = clip(d / margin, 0, 1)`` of its distance ``distance : (L, n)``
    mm; ``φ_l = 1 / (d_l + 1e-6)²`` with ``d_l`` 0 inside and at most 1e6 mm (inf: beyond every margin).
    The arithmetic of :func:`lungdeform.playback.displacement_field.blended_field`'s array form, in
    the same order (the same numbers), without its (L, n) temporaries."""
    nl, n = distance.shape
    for p in numba.prange(n):
        total = 0.0
        for m in range(nl):
            d = 0.0 if inside[m, p] else min(distance[m, p], 1e6)
            total += 1.0 / ((d + 1e-6) * (d + 1e-6))
        for c in range(3):
            out[p, c] = 0.0
        for m in range(nl):
            d = 0.0 if inside[m, p] else min(distance[m, p], 1e6)
            t = min(max(distance[m, p] / margin, 0.0), 1.0)
            a = 1.0 if inside[m, p] else 1.0 - t * t * (3.0 - 2.0 * t)
            w = a * (1.0 / ((d + 1e-6) * (d + 1e-6)) / total)
            for c in range(3):
                out[p, c] += w * fields[m, p, c]
    return out


def no_spans(shape) -> tuple[np.ndarray, np.ndarray]:
    """Row spans ``(first, last)`` of a field of ``shape`` (z, y, x[, 3]) that is zero everywhere (first > last
    in every row): to be widened by :func:`fill_field` and :func:`widen_spans`, read by :func:`jacobian_pass`."""
    nz, ny, nx = shape[:3]
    return np.full((nz, ny), nx, np.int64), np.full((nz, ny), -1, np.int64)


def widen_spans(spans, flat: np.ndarray, shape) -> None:
    """Widen, in place, the row ``spans`` (:func:`no_spans`) of a field of ``shape`` (z, y, x[, 3]) to the
    voxels ``flat : (p,) int`` (flat indices over z, y, x)."""
    k, j, i = np.unravel_index(np.asarray(flat, np.int64), tuple(shape[:3]))
    np.minimum.at(spans[0], (k, j), i)
    np.maximum.at(spans[1], (k, j), i)


@numba.njit(cache=True, inline="always")
def _grad_row(f, k, j, i, near, inv, c, diagonal):
    """Row ``c`` of ``I + ∇u`` at voxel (k, j, i): ``(∂u_c/∂x_r + δ_cr for r = 0, 1, 2)``; ``near`` =
    the neighbours' indices and the reciprocal index steps between them (:func:`_det_row`);
    ``diagonal``: ``inv`` is diagonal (index axes along x, y, z), so its zero terms are left out
    (the same numbers: a product with 0 adds nothing)."""
    kl, kh, jl, jh, il, ih, rk, rj, ri = near
    di = (np.float64(f[k, j, ih, c]) - np.float64(f[k, j, il, c])) * ri
    dj = (np.float64(f[k, jh, i, c]) - np.float64(f[k, jl, i, c])) * rj
    dk = (np.float64(f[kh, j, i, c]) - np.float64(f[kl, j, i, c])) * rk
    if diagonal:
        return di * inv[0, 0] + (c == 0), dj * inv[1, 1] + (c == 1), dk * inv[2, 2] + (c == 2)
    return (di * inv[0, 0] + dj * inv[0, 1] + dk * inv[0, 2] + (c == 0),
            di * inv[1, 0] + dj * inv[1, 1] + dk * inv[1, 2] + (c == 1),
            di * inv[2, 0] + dj * inv[2, 1] + dk * inv[2, 2] + (c == 2))


@numba.njit(cache=True, inline="always")
def _det_near(f, k, j, i, near, inv, diagonal):
    a11, a12, a13 = _grad_row(f, k, j, i, near, inv, 0, diagonal)
    a21, a22, a23 = _grad_row(f, k, j, i, near, inv, 1, diagonal)
    a31, a32, a33 = _grad_row(f, k, j, i, near, inv, 2, diagonal)
    return a11 * (a22 * a33 - a23 * a32) - a12 * (a21 * a33 - a23 * a31) + a13 * (a21 * a32 - a22 * a31)


@numba.njit(cache=True, inline="always")
def _det_edge(f, k, j, i, near_kj, inv, diagonal):
    """``det(I + ∇u)`` at a row's end voxel (k, j, i): the difference along i one-sided at the array's
    edge (as ``numpy.gradient``); ``near_kj`` = (kl, kh, jl, jh, rk, rj) as :func:`_det_row`."""
    kl, kh, jl, jh, rk, rj = near_kj
    il, ih = max(i - 1, 0), min(i + 1, f.shape[2] - 1)
    return _det_near(f, k, j, i, (kl, kh, jl, jh, il, ih, rk, rj, 0.5 if ih - il == 2 else 1.0), inv, diagonal)


@numba.njit(cache=True)
def _det_row(f, k, j, box_i, inv, dets, diagonal):
    """Write into ``dets[i − i0]`` ``det(I + ∇u)`` at the voxels (k, j, i) for i in ``box_i`` (i0, i1) of
    ``f : (z, y, x, 3)``; ``inv[r, a] = ∂index_a / ∂x_r`` (a = i, j, k). The differences central,
    one-sided at the array's edges (as ``numpy.gradient``): over 2 index steps or 1, so multiplying
    by the halves and wholes below is exact division; the row's inner voxels in one branch-free loop."""
    nz, ny, nx = f.shape[0], f.shape[1], f.shape[2]
    kl, kh, jl, jh = max(k - 1, 0), min(k + 1, nz - 1), max(j - 1, 0), min(j + 1, ny - 1)
    rk, rj = 0.5 if kh - kl == 2 else 1.0, 0.5 if jh - jl == 2 else 1.0
    i0, i1 = box_i
    lo, hi = max(i0, 1), min(i1, nx - 1)
    if diagonal:  # the flag a constant in each loop, so that the compiler drops the other branch
        for i in range(lo, hi):
            dets[i - i0] = _det_near(f, k, j, i, (kl, kh, jl, jh, i - 1, i + 1, rk, rj, 0.5), inv, True)
    else:
        for i in range(lo, hi):
            dets[i - i0] = _det_near(f, k, j, i, (kl, kh, jl, jh, i - 1, i + 1, rk, rj, 0.5), inv, False)
    for i in range(i0, min(lo, i1)):  # the voxels outside [lo, hi): at most one at each end of a row
        dets[i - i0] = _det_edge(f, k, j, i, (kl, kh, jl, jh, rk, rj), inv, diagonal)
    for i in range(max(hi, i0), i1):
        dets[i - i0] = _det_edge(f, k, j, i, (kl, kh, jl, jh, rk, rj), inv, diagonal)
    return dets


@numba.njit(cache=True)
def _column(ahead, behind, step, inv, identity, out):
    """Write into ``out : (3·m,) float`` column a of ``I + ∇u`` at m voxels of a row, interleaved
    (``out[3·i + c] = (u_c(ahead) − u_c(behind))·step·inv + δ_ac``): ``ahead``, ``behind`` the field's
    ``(3·m,) float32`` components at the neighbours along index axis a, ``step`` 1/2 or 1 (index steps
    between them), ``inv`` = ``∂index_a/∂x_a`` (an axis-aligned grid), ``identity[3·i + c] = δ_ac``. :func:`_grad_row`'s arithmetic, in its order, on an axis-aligned grid; unsigned
    indices, so that numba adds no negative-index wraparound and the loop is vectorised."""
    for q in range(np.uint64(out.shape[0])):
        out[q] = (np.float64(ahead[q]) - np.float64(behind[q])) * step * inv + identity[q]
    return out


@numba.njit(cache=True)
def _det_columns(c1, c2, c3, dets):
    """``dets[i] = det[c1 | c2 | c3]`` at each voxel i, the columns interleaved as :func:`_column`
    writes them (:func:`_det_near`'s cofactor expansion, in its order); vectorised (unsigned indices)."""
    for i in range(np.uint64(dets.shape[0])):
        q = i * np.uint64(3)
        a11, a21, a31 = c1[q], c1[q + np.uint64(1)], c1[q + np.uint64(2)]
        a12, a22, a32 = c2[q], c2[q + np.uint64(1)], c2[q + np.uint64(2)]
        a13, a23, a33 = c3[q], c3[q + np.uint64(1)], c3[q + np.uint64(2)]
        dets[i] = a11 * (a22 * a33 - a23 * a32) - a12 * (a21 * a33 - a23 * a31) + a13 * (a21 * a32 - a22 * a31)
    return dets


@numba.njit(cache=True)
def _det_row_aligned(g, k, j, box_i, inv, dets, work):
    """:func:`_det_row` on an axis-aligned grid (``inv`` diagonal) for ``g = f.reshape(z, y, 3·x)``: the
    row's inner voxels column by column (:func:`_column`; ``work = (columns (3, 3·x) float, identity
    (3, 3·x) float)``, ``identity[a, 3·i + c] = δ_ac``), then their determinants (:func:`_det_columns`);
    the same numbers as :func:`_det_row`, vectorised."""
    nz, ny, nx = g.shape[0], g.shape[1], g.shape[2] // 3
    kl, kh, jl, jh = max(k - 1, 0), min(k + 1, nz - 1), max(j - 1, 0), min(j + 1, ny - 1)
    rk, rj = 0.5 if kh - kl == 2 else 1.0, 0.5 if jh - jl == 2 else 1.0
    i0, i1 = box_i
    lo, hi = max(i0, 1), min(i1, nx - 1)
    if lo < hi:
        a, b, m = 3 * lo, 3 * hi, 3 * (hi - lo)
        cols, identity = work
        c1 = _column(g[k, j, a + 3:b + 3], g[k, j, a - 3:b - 3], 0.5, inv[0, 0], identity[0, :m], cols[0, :m])
        c2 = _column(g[k, jh, a:b], g[k, jl, a:b], rj, inv[1, 1], identity[1, :m], cols[1, :m])
        c3 = _column(g[kh, j, a:b], g[kl, j, a:b], rk, inv[2, 2], identity[2, :m], cols[2, :m])
        _det_columns(c1, c2, c3, dets[lo - i0:hi - i0])
    f = g.reshape((nz, ny, nx, 3))
    for i in range(i0, min(lo, i1)):  # the voxels outside [lo, hi): at most one at each end of a row
        dets[i - i0] = _det_edge(f, k, j, i, (kl, kh, jl, jh, rk, rj), inv, True)
    for i in range(max(hi, i0), i1):
        dets[i - i0] = _det_edge(f, k, j, i, (kl, kh, jl, jh, rk, rj), inv, True)
    return dets


@numba.njit(cache=True, parallel=True)
def row_spans(f, ranges):
    """Per voxel row (k, j) of ``f : (z, y, x, 3)`` within one voxel of the box ``ranges`` (k0, k1, j0,
    j1, i0, i1): ``(first, last) (z, y) int64``, its first and last voxel within one voxel of
    ``[i0, i1)`` with a non-zero displacement (first > last: none; rows beyond the box: none)."""
    nz, ny, nx = f.shape[0], f.shape[1], f.shape[2]
    lo, hi = max(ranges[4] - 1, 0), min(ranges[5] + 1, nx)
    first, last = np.full((nz, ny), hi, np.int64), np.full((nz, ny), lo - 1, np.int64)
    for k in numba.prange(max(ranges[0] - 1, 0), min(ranges[1] + 1, nz)):
        for j in range(max(ranges[2] - 1, 0), min(ranges[3] + 1, ny)):
            for i in range(lo, hi):
                if f[k, j, i, 0] != 0 or f[k, j, i, 1] != 0 or f[k, j, i, 2] != 0:
                    first[k, j] = i
                    break
            for i in range(hi - 1, first[k, j], -1):
                if f[k, j, i, 0] != 0 or f[k, j, i, 1] != 0 or f[k, j, i, 2] != 0:
                    last[k, j] = i
                    break
            last[k, j] = max(last[k, j], first[k, j]) if first[k, j] < hi else lo - 1
    return first, last


@numba.njit(cache=True, parallel=True)
def jacobian_pass(f, inv, ranges, out, spans):
    """Per z-slice ``(min, max, folded count)`` of :func:`_det_row` over the voxels ``ranges`` (k0, k1,
    j0, j1, i0, i1) of ``f : (z, y, x, 3)``; each determinant also written to ``out`` (same z, y, x
    shape) unless ``out`` is empty. A voxel more than one voxel from every non-zero displacement in
    its row and the four rows beside it has every difference 0: its determinant is exactly 1, without
    arithmetic; ``spans`` = ``(first, last) (z, y) int64``, per row a span of voxels outside which
    the row is zero (:func:`row_spans` measures it; :func:`fill_field` records the voxels it wrote, so
    that the field need not be read twice). Returns ``(n, 3) float`` rows, one per slice."""
    nz, ny = f.shape[0], f.shape[1]
    nk = ranges[1] - ranges[0]
    rows = np.empty((max(nk, 0), 3))
    write = out.size > 0
    i0, i1 = ranges[4], ranges[5]
    first, last = spans
    diagonal = (inv[0, 1] == 0 and inv[0, 2] == 0 and inv[1, 0] == 0 and inv[1, 2] == 0
                and inv[2, 0] == 0 and inv[2, 1] == 0)
    g = f.reshape((nz, ny, 3 * f.shape[2]))
    identity = np.zeros((3, g.shape[2]))
    for c in range(3):
        identity[c, c::3] = 1.0
    for s in numba.prange(nk):
        k = ranges[0] + s
        dets = np.empty(max(i1 - i0, 0))
        work = (np.empty((3, g.shape[2])), identity)
        lo, hi, folded = np.inf, -np.inf, 0
        for j in range(ranges[2], ranges[3]):
            kl, kh, jl, jh = max(k - 1, 0), min(k + 1, nz - 1), max(j - 1, 0), min(j + 1, ny - 1)
            a = min(first[k, j], first[kl, j], first[kh, j], first[k, jl], first[k, jh]) - 1
            b = max(last[k, j], last[kl, j], last[kh, j], last[k, jl], last[k, jh]) + 2
            a, b = max(a, i0), max(min(b, i1), max(a, i0))
            if a > i0 or b < i1:
                lo, hi = min(lo, 1.0), max(hi, 1.0)
            if a < b:
                if diagonal:  # the same numbers as _det_row's, vectorised
                    _det_row_aligned(g, k, j, (a, b), inv, dets, work)
                else:
                    _det_row(f, k, j, (a, b), inv, dets, diagonal)
                for m in range(b - a):
                    d = dets[m]
                    lo, hi = min(lo, d), max(hi, d)
                    folded += d <= 0.0
            if write:
                out[k, j, i0:i1] = 1.0
                out[k, j, a:b] = dets[:b - a]
        rows[s, 0], rows[s, 1], rows[s, 2] = lo, hi, folded
    return rows
