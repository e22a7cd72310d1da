"""Flat-coloured triangles filled into an RGBA image by a painter, anti-aliased by supersampling: the
pixels of :mod:`lungdeform.plot.surface`'s panels, drawn without a matplotlib Path per face.

The image frame: ``shape = (h, w)`` pixels, row 0 at the top; pixel ``(i, j)`` is the square of side
``mm_per_pixel`` whose top-left corner lies at ``origin + (j, −i) · mm_per_pixel`` in the panel's
plane (mm, x toward the image right, y toward the image top, as :func:`lungdeform.plot.surface.project`
returns them).

How: each pixel holds ``supersample²`` samples (the centres of a regular sub-grid). Triangles are
filled in the order given (far first: a later face covers an earlier one); a sample takes the colour
of the last triangle that contains it. Containment is decided exactly, on vertices snapped to 1/256
of a sample, with integer edge functions and one tie rule for samples on an edge (they count as
inside when the edge runs one fixed way; the same as moving every sample by an infinitesimal fixed
offset), so two faces that share an edge leave no seam and cover no sample twice. A pixel's colour is
the mean of its covered samples (straight, not premultiplied, alpha) and its alpha the fraction
covered: a box filter, so a triangle's covered area is right to within a sample per pixel along its
edges.
"""

from __future__ import annotations

import numba
import numpy as np

#: Fixed-point steps per sample: vertices are snapped to 1/SNAP of a sample.
SNAP = 256
#: Largest vertex coordinate kept, in samples from the image corner (farther ones are clamped: a
#: triangle reaching that far outside the image is drawn wrong, none of the panels' does); keeps
#: the integer edge functions far from overflow.
REACH = 1 << 20


@numba.njit(cache=True)
def _fill(fixed, height, width):  # pragma: no cover - compiled
    """Which triangle each sample shows: ``fixed : (k, 3, 2) int64`` the triangles' vertices in
    1/SNAP of a sample (column, row; row 0 at the top), painted in order onto a ``(height, width)``
    grid of samples at ``(j + 1/2, i + 1/2)``, a row of samples at a time (the span inside all three
    edges, :func:`_span`). Returns ``owner (height, width) int32``, −1 where none."""
    owner = np.full((height, width), -1, np.int32)
    half = SNAP // 2
    for t in range(fixed.shape[0]):
        ax, ay = fixed[t, 0, 0], fixed[t, 0, 1]
        bx, by = fixed[t, 1, 0], fixed[t, 1, 1]
        cx, cy = fixed[t, 2, 0], fixed[t, 2, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0:
            continue
        if area < 0:  # either winding: make the edge functions positive inside
            bx, by, cx, cy = cx, cy, bx, by
        i0 = max((min(ay, by, cy) - half) // SNAP, 0)
        i1 = min((max(ay, by, cy) - half) // SNAP + 1, height - 1)
        for i in range(i0, i1 + 1):
            py = i * SNAP + half
            lo, hi = _span(ax, ay, bx, by, py, 0, width - 1)
            lo, hi = _span(bx, by, cx, cy, py, lo, hi)
            lo, hi = _span(cx, cy, ax, ay, py, lo, hi)
            for j in range(lo, hi + 1):
                owner[i, j] = t
    return owner


@numba.njit(cache=True, inline="always")
def _span(ax, ay, bx, by, py, lo, hi):  # pragma: no cover - compiled
    """The columns ``lo..hi`` of the sample row at ``py`` narrowed to the samples on the inner side of
    the edge ``a → b`` (integers, 1/SNAP of a sample): the edge function
    ``e(j) = dx (py − ay) − dy (j·SNAP + SNAP/2 − ax)`` strictly positive, or zero when the edge runs
    down the rows, or along a row toward lower columns (``e`` at the sample moved by (−ε, −ε²), so
    exactly one of two faces sharing an edge takes a sample on it). Empty: ``lo > hi``. The bound is
    estimated in floating point (an integer division costs more than the rest of the row) and then
    made exact on the integers."""
    dx, dy = bx - ax, by - ay
    e0 = dx * (py - ay) - dy * (SNAP // 2 - ax)  # e(j) = e0 − dy·SNAP·j
    if dy == 0:
        if e0 < 0 or (e0 == 0 and dx > 0):
            return lo, lo - 1
        return lo, hi
    step = dy * SNAP
    j = np.int64(np.floor(e0 / step))
    if dy > 0:  # e falls with j: the last j with e(j) >= 0
        if e0 - step * j < 0:
            j -= 1
        elif e0 - step * (j + 1) >= 0:
            j += 1
        return lo, min(hi, j)
    j += 1  # e rises with j: the first j with e(j) > 0
    if e0 - step * j <= 0:
        j += 1
    elif e0 - step * (j - 1) > 0:
        j -= 1
    return max(lo, j), hi


@numba.njit(cache=True)
def _resolve(owner, rgb, supersample):  # pragma: no cover - compiled
    """Average ``supersample × supersample`` blocks of ``owner (H, W) int32`` (−1: none) into an RGBA
    ``(H / s, W / s, 4) float64`` image: colour the mean of ``rgb (k, 3)`` over the block's covered
    samples, alpha the covered fraction."""
    s = supersample
    h, w = owner.shape[0] // s, owner.shape[1] // s
    out = np.zeros((h, w, 4))
    for i in range(h):
        for j in range(w):
            r = g = b = 0.0
            n = 0
            for a in range(i * s, i * s + s):
                for c in range(j * s, j * s + s):
                    t = owner[a, c]
                    if t >= 0:
                        r += rgb[t, 0]
                        g += rgb[t, 1]
                        b += rgb[t, 2]
                        n += 1
            if n:
                out[i, j, 0], out[i, j, 1], out[i, j, 2] = r / n, g / n, b / n
                out[i, j, 3] = n / (s * s)
    return out


def sample_coordinates(points: np.ndarray, origin: np.ndarray, mm_per_pixel: float,
                       supersample: int) -> np.ndarray:
    """``points (..., 2) float`` mm in the panel's plane (x right, y up) → the same points in
    1/:data:`SNAP` of a sample (column, row from the image's top-left corner), ``(..., 2) int64``,
    clamped to ±:data:`REACH` samples. ``origin (2,)`` mm: the image's top-left corner."""
    p = np.asarray(points, float)
    scale = supersample / float(mm_per_pixel)
    cols = (p[..., 0] - origin[0]) * scale
    rows = (origin[1] - p[..., 1]) * scale
    samples = np.clip(np.stack([cols, rows], axis=-1), -REACH, REACH)
    return np.rint(samples * SNAP).astype(np.int64)


def paint(polygons: np.ndarray, rgb: np.ndarray, origin: np.ndarray, mm_per_pixel: float,
          shape: tuple[int, int], supersample: int = 3) -> np.ndarray:
    """Triangles ``polygons (k, 3, 2) float`` (mm in the panel's plane, far first: painted in order,
    a later one covers an earlier one) filled with ``rgb (k, 3) float`` in [0, 1] into an RGBA image
    ``(h, w, 4) float64`` of ``shape = (h, w)`` pixels, ``origin (2,)`` mm its top-left corner,
    ``mm_per_pixel`` the side of a pixel; ``supersample²`` samples per pixel. Alpha is the covered
    fraction of each pixel (0 off every triangle), colour the mean of the covered samples' colours."""
    h, w = (int(n) for n in shape)
    s = int(supersample)
    if h < 1 or w < 1 or s < 1 or not mm_per_pixel > 0:
        raise ValueError(f"paint: shape {shape}, supersample {supersample} and mm_per_pixel {mm_per_pixel} "
                         "must be positive")
    tri = np.asarray(polygons, float).reshape(-1, 3, 2)
    colours = np.ascontiguousarray(np.asarray(rgb, float).reshape(-1, 3))
    if len(colours) != len(tri):
        raise ValueError(f"paint: rgb has {len(colours)} rows for {len(tri)} triangles")
    fixed = np.ascontiguousarray(sample_coordinates(tri, np.asarray(origin, float), mm_per_pixel, s))
    return _resolve(_fill(fixed, h * s, w * s), colours, s)
