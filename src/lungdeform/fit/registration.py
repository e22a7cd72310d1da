"""Smooth registration of one lung surface onto another: the map behind the correspondence field.

A point ``x`` (mm) of the smaller lung goes to ``f(x) = A x + t + Σ_j exp(−|A x + t − c_j|² / (2 w²)) g_j``:
first the affine of the solid moments (:func:`moment_affine`: ``x' = μ_l + C_l^½ C_s^−½ (x − μ_s)``,
``μ`` and ``C`` the centroid and covariance of each lung's solid), then Coherent Point Drift's
Gaussian field (Myronenko & Song 2010, ``pycpd``, MIT; no outlier weight) fitted from the affine
image of the smaller surface's points to the larger surface's points, with strong smoothness: on
coordinates centred on the larger surface and scaled by its RMS radius ``s`` (about 100 mm),
``α`` = :data:`ALPHA`, kernel width ``β`` = :data:`BETA_MM` / ``s``. Smaller ``α`` lets points slide
tens of mm along the surface (56 mm on DIR-Lab COPDgene case 1 with ``α`` = 2), which the surface
distance cannot see but the interior does. Calibrated on the DIR-Lab COPDgene masks
(docs/FITTING.md, "Interior from the surfaces alone"): the mask-only baseline ``cpd_moments`` and
the model's correspondence field are this one map.

:func:`register_points` fits the map on point sets; :func:`surface_map` on two closed surfaces
(moments of the solids, points from the kept vertices); :func:`surface_map_field` turns a map
into the per-unit :class:`~lungdeform.interior.surface_map.SurfaceMapField` a model plays back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface, as_vertices, farthest_points
from lungdeform.geometry.moments import solid_moments
from lungdeform.interior.surface_map import SurfaceMapField

from .cpd import deformable_cpd

#: CPD's smoothness weight and kernel width (mm; divided by the RMS radius of the larger surface).
ALPHA = 1000.0
BETA_MM = 80.0
#: CPD's M-step through a pivoted-Cholesky factor of its kernel, stopped at this remaining diagonal
#: (:func:`lungdeform.fit.cpd.deformable_cpd`): the map's points within 10⁻⁸ mm of the dense solve's.
RANK_TOLERANCE = 1e-10
#: Surface points per surface (a farthest-point subset, :func:`lungdeform.geometry.mesh.farthest_points`).
POINTS = 1500
#: How those points are chosen (recorded where a fit's settings are digested).
SAMPLING = "farthest points of the full-resolution surfaces"


@dataclass(frozen=True, eq=False)
class SurfaceMap:
    """``f(x) = A x + t + Σ_j exp(−|A x + t − c_j|² / (2 w²)) g_j`` (module docstring).

    Attributes
    ----------
    warp : (3, 4) float
        ``[A | t]``, mm.
    centers : (k, 3) float
        Gaussian centres ``c_j``, mm (the affine image of the smaller surface's points).
    weights : (k, 3) float
        ``g_j``, mm.
    width_mm : float
        ``w``, mm.
    """

    warp: np.ndarray
    centers: np.ndarray
    weights: np.ndarray
    width_mm: float

    def field(self, scale: float = 1.0) -> SurfaceMapField:
        """The map's displacement ``f(x) − x`` divided by ``scale`` (units), as a field."""
        if not (np.isfinite(scale) and scale != 0):
            raise InputError(f"scale must be finite and not 0, got {scale!r}")
        linear = self.warp - np.c_[np.eye(3), np.zeros(3)]
        return SurfaceMapField(linear / scale, self.warp, self.centers, self.weights / scale, self.width_mm)

    def __call__(self, points) -> np.ndarray:
        """``f(x) : (q, 3)`` mm at ``points : (q, 3)`` mm."""
        q = as_vertices(points, "points")
        return q + self.field()(q)


def _sym_power(c: np.ndarray, power: float) -> np.ndarray:
    val, vec = np.linalg.eigh(c)
    if not np.all(val > 0):
        raise InputError("moments: a covariance is not positive definite (a flat or degenerate lung)")
    return (vec * val**power) @ vec.T


def moment_affine(mean_small, cov_small, mean_large, cov_large) -> tuple[np.ndarray, np.ndarray]:
    """``(A (3, 3), t (3,))``: ``x' = μ_l + C_l^½ C_s^−½ (x − μ_s)`` from the centroids ``(3,)`` mm and
    covariances ``(3, 3)`` mm² of the smaller and the larger lung."""
    m = _sym_power(np.asarray(cov_large, float), 0.5) @ _sym_power(np.asarray(cov_small, float), -0.5)
    return m, np.asarray(mean_large, float) - m @ np.asarray(mean_small, float)


def register_points(affine: tuple[np.ndarray, np.ndarray], points_small, points_large, *, alpha: float = ALPHA,
                    beta_mm: float = BETA_MM, max_iterations: int = 150, tolerance: float = 1e-5) -> SurfaceMap:
    """The map from ``affine`` ``(A, t)`` then CPD's Gaussian field fitted from the affine image of
    ``points_small : (n, 3)`` mm to ``points_large : (k, 3)`` mm (module docstring)."""
    mat, t = (np.asarray(a, float) for a in affine)
    big = as_vertices(points_large, "points_large")
    c = big.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((big - c) ** 2, axis=1))))
    moved = as_vertices(points_small, "points_small") @ mat.T + t
    weights = deformable_cpd((big - c) / s, (moved - c) / s, alpha=alpha, beta=beta_mm / s, w=0.0,
                             max_iterations=max_iterations, tolerance=tolerance, rank_tolerance=RANK_TOLERANCE)
    return SurfaceMap(np.c_[mat, t], moved, s * weights, float(beta_mm))


def surface_map(small: Surface, large: Surface, *, keep_small=None, keep_large=None,
                points: int = POINTS) -> SurfaceMap:
    """:func:`register_points` between two closed surfaces (mm, one frame): the affine of their
    solids' moments, the points a farthest-point subset of ``points`` kept vertices of each
    (:func:`lungdeform.geometry.mesh.farthest_points`: deterministic and even, so a region dense in
    vertices does not weigh more; ``keep_* : (n,) bool`` leaves crop faces out; None: all)."""
    _, mu_s, cov_s = solid_moments(small.vertices, small.faces)
    _, mu_l, cov_l = solid_moments(large.vertices, large.faces)
    pts = []
    for surf, keep in ((small, keep_small), (large, keep_large)):
        v = surf.vertices if keep is None else surf.vertices[np.asarray(keep, bool)]
        pts.append(v[farthest_points(v, points)])
    return register_points(moment_affine(mu_s, cov_s, mu_l, cov_l), *pts)


def surface_map_field(small: Surface, large: Surface, scale: float, *, keep_small=None,
                      keep_large=None) -> SurfaceMapField:
    """The per-unit field of :func:`surface_map` from ``small`` (the model's end-exhale surface) to
    ``large`` (a target at ``scale`` units of the model)."""
    return surface_map(small, large, keep_small=keep_small, keep_large=keep_large).field(scale)
