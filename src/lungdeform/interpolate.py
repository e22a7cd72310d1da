"""Surface-driven interpolation of a displacement field into the lung's interior.

The model (and every baseline) moves surface vertices only; interior points (landmarks) are moved
by interpolating the surface displacement. Reading chosen: a **thin-plate spline** radial basis
function (``scipy.interpolate.RBFInterpolator``, kernel ``thin_plate_spline``, degree-1 polynomial),
fitted to the displacement at the surface vertices, one component at a time. It reproduces any
affine displacement exactly (the polynomial part), so the affine baseline moves landmarks exactly as
its transform does; it is the minimal-bending smooth field through the surface data. Large surfaces
are thinned to ``max_points`` evenly chosen vertices to bound the dense solve (O(k³)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .mesh import as_vertices


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """A smooth displacement field ``R³ → R³`` fitted to displacements at sample points.

    Attributes
    ----------
    points : (k, 3) float
        Sample points (surface vertices at end-exhale), mm.
    displacements : (k, 3) float
        Displacement at each sample point, mm.
    """

    points: np.ndarray
    displacements: np.ndarray
    _rbf: object

    def __call__(self, query) -> np.ndarray:
        """Displacement ``(m, 3) float`` mm at ``query : (m, 3)`` mm."""
        q = as_vertices(query, "query")
        if not np.all(np.isfinite(q)):
            raise InputError("query points contain NaN or infinity")
        return np.ascontiguousarray(self._rbf(q))

    def move(self, query) -> np.ndarray:
        """``query + displacement(query)`` (mm)."""
        q = as_vertices(query, "query")
        return q + self(q)


def displacement_field(points, displacements, *, max_points: int = 2500, smoothing: float = 0.0,
                       kernel: str = "thin_plate_spline", seed: int = 0) -> DisplacementField:
    """Fit a thin-plate-spline field to ``displacements : (k, 3)`` mm at ``points : (k, 3)`` mm.

    ``smoothing`` (mm², scipy's meaning) trades exactness for smoothness; 0 interpolates.
    """
    from scipy.interpolate import RBFInterpolator

    p = as_vertices(points, "points")
    u = as_vertices(displacements, "displacements")
    if p.shape != u.shape:
        raise InputError(f"points {p.shape} and displacements {u.shape} must have the same shape")
    if len(p) < 5:
        raise InputError(f"a displacement field needs at least 5 points, got {len(p)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(u))):
        raise InputError("points and displacements must be finite")
    if len(p) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(len(p), max_points, replace=False))
        p, u = p[idx], u[idx]
    rbf = RBFInterpolator(p, u, kernel=kernel, degree=1, smoothing=smoothing)
    return DisplacementField(p, u, rbf)
