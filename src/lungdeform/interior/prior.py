"""An affine interior prior in the lung-normalised frame: ``r(q) = β₀ + B q̂`` (docs/FITTING.md, docs/DEFAULTS.md).

The lung-normalised position of a point ``q`` (mm LPS) is ``q̂ = (q − μ) / σ``, with ``μ`` the
centroid of the solid the lung's surface encloses and ``σ (3,)`` its standard deviations along x,
y, z, the x axis mirrored for a left lung so that lateral means the same on both sides. A prior's
``coefficients (4, 3)`` are ``β₀`` then the rows of ``B`` (for x̂, ŷ, ẑ), in that mirrored frame.
:mod:`lungdeform.interior.motion_prior` learns one for two-scan fits (mm at the largest volume);
:mod:`lungdeform.cohort.default` one for the population default (mm per mL).
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface, as_vertices
from lungdeform.geometry.moments import solid_moments

SIDES = ("left", "right")


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
