"""Displacement directions (15)–(17) (paper Sec. IV-B.1; docs/METHOD_NOTES.md §6).

``d_i = (c1·x̂_i^c2, c3·ŷ_i^c4, c5·ẑ_i^c6)`` in the lung frame, mapped to LPS with the lung's
axes and normalised. The direction of each node is constant over the breathing cycle. Normalised
coordinates outside [0, 1] (a point beyond the end-exhale box) are clipped to [0, 1] so that the
powers stay real.

Beyond the paper, a smooth correction rotates these directions (:func:`polynomial_basis`,
:func:`corrected_directions`): fitted per patient by :mod:`lungdeform.fit.direction_correction`, or
carried by a population default (:mod:`lungdeform.model.population`).
"""

from __future__ import annotations

import itertools

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.frame import LungFrame


def direction_field_frame(xyz_hat: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Unnormalised directions ``(n, 3)`` in the lung frame from ``xyz_hat : (n, 3)`` in [0, 1] and
    ``c : (6,)`` = c1…c6."""
    c = np.asarray(c, dtype=float)
    if c.shape[0] < 6:
        raise InputError(f"direction constants need c1…c6, got {c.shape[0]} values")
    q = np.clip(np.asarray(xyz_hat, float), 0.0, 1.0)
    return np.stack([c[0] * q[:, 0] ** c[1], c[2] * q[:, 1] ** c[3], c[4] * q[:, 2] ** c[5]], axis=1)


def directions(frame: LungFrame, vertices: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Unit displacement directions ``d : (n, 3) float`` in LPS for vertices ``(n, 3)`` mm LPS.

    A vertex at the frame origin corner (all three terms zero) gets a zero direction: it does not
    move, as the paper's fixed apex/posterior/medial corner.
    """
    raw = frame.to_world(direction_field_frame(frame.normalized(vertices), c))
    norm = np.linalg.norm(raw, axis=1, keepdims=True)
    return np.ascontiguousarray(np.divide(raw, norm, out=np.zeros_like(raw), where=norm > 0))


#: Highest polynomial degree of a direction correction (:func:`polynomial_basis`).
MAX_DEGREE = 4


def polynomial_basis(xyz_hat, degree: int) -> np.ndarray:
    """``φ : (n, K) float``: monomials of degree ≤ ``degree`` in ``2·x̂ − 1`` for lung-frame
    normalised coordinates ``xyz_hat : (n, 3)`` (unitless, [0, 1] inside the end-exhale box);
    ``K = C(degree + 3, 3)``; column 0 is the constant."""
    if not 0 <= int(degree) <= MAX_DEGREE:
        raise InputError(f"direction correction degree must be 0…{MAX_DEGREE}, got {degree!r}")
    q = 2.0 * np.asarray(xyz_hat, float) - 1.0
    cols = [np.ones(len(q))]
    for dg in range(1, int(degree) + 1):
        for combo in itertools.combinations_with_replacement(range(3), dg):
            cols.append(np.prod(q[:, list(combo)], axis=1))
    return np.ascontiguousarray(np.stack(cols, axis=1))


def corrected_directions(d0, basis, coefficients) -> np.ndarray:
    """Unit ``d : (n, 3)`` = normalise(``d0 (n, 3)`` + ``basis (n, K)`` @ ``coefficients (K, 3)``)."""
    raw = np.asarray(d0, float) + np.asarray(basis, float) @ np.asarray(coefficients, float)
    norm = np.linalg.norm(raw, axis=1, keepdims=True)
    return np.ascontiguousarray(np.divide(raw, norm, out=np.zeros_like(raw), where=norm > 0))
