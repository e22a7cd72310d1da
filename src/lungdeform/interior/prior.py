"""An affine interior prior in the lung-normalised frame: ``r(q) = β₀ + B q̂`` (docs/FITTING.md, docs/DEFAULTS.md),
and that prior tapered to zero at the lung's surface (:class:`TaperedPrior`).

The lung-normalised position of a point ``q`` (mm LPS) is ``q̂ = (q − μ) / σ``, with ``μ`` the
centroid of the solid the lung's surface encloses and ``σ (3,)`` its standard deviations along x,
y, z, the x axis mirrored for a left lung so that lateral means the same on both sides. A prior's
``coefficients (4, 3)`` are ``β₀`` then the rows of ``B`` (for x̂, ŷ, ẑ), in that mirrored frame.
:mod:`lungdeform.interior.motion_prior` learns one for two-scan fits (mm at the largest volume);
:mod:`lungdeform.cohort.default` one for the population default (mm per mL).

A prior added inside a lung on top of its surface motion must vanish on the surface, or the lung
the interior field carries (a warped CT's lungs, a displacement field's) no longer has the surface
model's shape and volume: an affine ``r`` adds its divergence times the lung's volume to the volume
change (the population default's learned ``B`` contracts, −0.40 to −0.48 mL per mL on the POPI
lungs, so warped lungs breathed 52–59 % of the model's volume). :class:`TaperedPrior` therefore
plays ``w(δ(q)) r(q)``, with ``δ`` the depth below the lung's surface (0 on and outside it;
:mod:`lungdeform.geometry.depth`) and ``w`` :func:`taper`, the smoothstep from 0 at the surface to 1
at :data:`PRIOR_TAPER_MM` deep (C¹: the interior field keeps a continuous gradient across the
surface). A prior is learned with the same taper (:mod:`lungdeform.cohort.default`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.depth import DepthGrid, depth_grid
from lungdeform.geometry.mesh import Surface, as_faces, as_vertices
from lungdeform.geometry.moments import solid_moments

SIDES = ("left", "right")
#: Depth (mm) below the lung's surface at which a tapered prior reaches its full value (module
#: docstring; chosen on the landmarks of ``lungdeform validate single-scan``: docs/DEFAULTS.md).
PRIOR_TAPER_MM = 20.0


def lung_normaliser(surface: Surface) -> tuple[np.ndarray, np.ndarray]:
    """``(μ (3,) mm, σ (3,) mm)``: centroid and per-axis standard deviation of the solid ``surface`` encloses."""
    _, mu, cov = solid_moments(surface.vertices, surface.faces)
    return mu, np.sqrt(np.diag(cov))


def mirror(side: str) -> np.ndarray:
    """``(3,)``: the x mirror of a left lung (−1, 1, 1), identity for a right one."""
    if side not in SIDES:
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    return np.array([-1.0, 1.0, 1.0]) if side == "left" else np.ones(3)


def normalised(points, centroid, scale, side: str) -> np.ndarray:
    """``q̂ : (m, 3)`` of ``points : (m, 3)`` mm LPS for a lung of ``centroid (3,)`` and ``scale (3,)`` mm."""
    sd = np.asarray(scale, float).reshape(3)
    if not np.all(sd > 0):
        raise InputError(f"scale must be (3,) positive mm, got {sd.tolist()}")
    q = (as_vertices(points, "points") - np.asarray(centroid, float).reshape(3)) / sd
    return q * mirror(side)


def prior_displacement(coefficients, points, centroid, scale, side: str) -> np.ndarray:
    """``(m, 3)``: the prior ``β₀ + B q̂`` at ``points : (m, 3)`` mm, in LPS (the units of ``coefficients``)."""
    c = np.asarray(coefficients, float)
    q = normalised(points, centroid, scale, side)
    return (c[0] + q @ c[1:]) * mirror(side)


def prior_affine(coefficients, centroid, scale, side: str) -> np.ndarray:
    """``(3, 4)``: the same displacement as ``[M | b]`` in world mm, ``M q + b``."""
    c = np.asarray(coefficients, float)
    mir, sd, mu = mirror(side), np.asarray(scale, float), np.asarray(centroid, float)
    m = (c[1:] * (mir / sd)[:, None]).T * mir[:, None]  # (3, 3): out × in
    b = c[0] * mir - m @ mu
    return np.c_[m, b]


def taper(depth_mm, width_mm: float = PRIOR_TAPER_MM) -> np.ndarray:
    """``w : (q,) float``: the smoothstep ``3t² − 2t³`` of ``t = depth_mm / width_mm`` clipped to
    [0, 1]: 0 on and outside the surface (``depth_mm ≤ 0``), 1 from ``width_mm`` deep, C¹."""
    if not (np.isfinite(width_mm) and width_mm > 0):
        raise InputError(f"taper width must be > 0 mm, got {width_mm!r}")
    t = np.clip(np.asarray(depth_mm, float) / float(width_mm), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def taper_weights(points, surface: Surface, width_mm: float = PRIOR_TAPER_MM) -> np.ndarray:
    """``w : (q,) float`` at ``points : (q, 3)`` mm LPS of the lung ``surface``, as a
    :class:`TaperedPrior` over it plays them (the learning of a prior uses it: :mod:`lungdeform.cohort.default`)."""
    return TaperedPrior(np.zeros((3, 4)), surface.vertices, surface.faces, width_mm).weights(points)


@dataclass(frozen=True, eq=False)
class TaperedPrior:
    """An affine displacement per unit tapered to zero at a lung's surface: ``w(δ(q)) (M q + b)``
    (module docstring).

    Attributes
    ----------
    affine : (3, 4) float
        ``[M | b]``, mm per unit (:func:`prior_affine` times the unit), world mm LPS.
    vertices : (n, 3) float
        The lung's surface (end-exhale, or the scan's), mm LPS, closed and outward ...
    faces : (m, 3) int
        ... and its faces.
    width_mm : float
        Depth at which ``w`` reaches 1 (:func:`taper`), mm.
    """

    affine: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    width_mm: float = PRIOR_TAPER_MM

    def __post_init__(self):
        a = np.ascontiguousarray(self.affine, dtype=np.float64)
        if a.shape != (3, 4) or not np.all(np.isfinite(a)):
            raise InputError(f"prior affine must be a finite (3, 4) [M | b], got shape {a.shape}")
        if not (np.isfinite(self.width_mm) and self.width_mm > 0):
            raise InputError(f"prior taper width must be > 0 mm, got {self.width_mm!r}")
        v = as_vertices(self.vertices)
        object.__setattr__(self, "affine", a)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", as_faces(self.faces, len(v)))
        object.__setattr__(self, "width_mm", float(self.width_mm))

    @cached_property
    def depth(self) -> DepthGrid:
        """The lung's depth grid (:func:`lungdeform.geometry.depth.depth_grid`), sampled on first use."""
        return depth_grid(self.vertices, self.faces, self.width_mm)

    def weights(self, points) -> np.ndarray:
        """``w : (q,) float`` in [0, 1] at ``points : (q, 3)`` mm LPS (0 on and outside the surface)."""
        return taper(self.depth(points), self.width_mm)

    def __call__(self, points) -> np.ndarray:
        """``(q, 3) float`` mm per unit at ``points : (q, 3)`` mm LPS."""
        q = as_vertices(points, "points")
        # einsum, not a BLAS product: an (n, 3) × (3, 3) product gains nothing from BLAS threads (7x the CPU)
        return np.ascontiguousarray(self.weights(q)[:, None] * (np.einsum("nb,ab->na", q, self.affine[:, :3])
                                                                + self.affine[:, 3]))
