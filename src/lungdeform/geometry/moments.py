"""Solid moments of a closed surface: the volume, centroid and covariance of the region it encloses.

The region's moments follow from the divergence theorem as sums over the tetrahedra that each
(outward-oriented) face spans with a reference point ``c``: a tetrahedron with corners ``0, a, b, d``
(relative to ``c``) has volume ``V = det[a b d] / 6``, first moment ``V (a + b + d) / 4`` and second
moment ``V / 20 · (a aᵀ + b bᵀ + d dᵀ + s sᵀ)`` with ``s = a + b + d``. These are the moments of the
solid, not of the surface points, so they match the moments of a mask's voxel positions.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import MeshError

from .mesh import as_faces, as_vertices


def solid_moments(vertices, faces) -> tuple[float, np.ndarray, np.ndarray]:
    """``(volume mm³, centroid (3,) mm, covariance (3, 3) mm²)`` of the solid bounded by the closed,
    outward-oriented surface ``vertices : (n, 3)`` mm, ``faces : (m, 3)`` int (any frame; the
    results are in the same frame). Raises :class:`MeshError` when the enclosed volume is not positive."""
    v = as_vertices(vertices)
    f = as_faces(faces, len(v))
    c = v.mean(axis=0)
    a, b, d = (v[f[:, k]] - c for k in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, d)) / 6.0
    total = float(vol.sum())
    if not total > 0:
        raise MeshError(f"solid moments: the surface encloses a volume of {total:.3g} mm³ (open or inward-facing)")
    s = a + b + d
    first = (vol[:, None] * s).sum(axis=0) / 4.0
    second = np.einsum("i,ij,ik->jk", vol / 20.0, a, a) + np.einsum("i,ij,ik->jk", vol / 20.0, b, b)
    second += np.einsum("i,ij,ik->jk", vol / 20.0, d, d) + np.einsum("i,ij,ik->jk", vol / 20.0, s, s)
    mean = first / total
    cov = second / total - np.outer(mean, mean)
    return total, c + mean, 0.5 * (cov + cov.T)
