"""The applied force (18) and its four-field orientation basis (docs/METHOD_NOTES.md §5).

Equation (18): ``f_i = c7·x̂_i + c8·ŷ_i + c9·ẑ_i`` (Table I, supine: c8 dominates, gravity acts along
the anterior–posterior axis). Reading chosen for other orientations: the c8 term is the normalised
*height against gravity* ``ĥ`` (0 at the lowest point of the end-exhale box along gravity, 1 at the
highest), and c7, c9 keep their anatomical terms. Supine gravity (+y LPS, posterior) gives
``ĥ = ŷ`` exactly, so Table I is reproduced.

``ĥ`` over the bounding box is an affine function of ``(x̂, ŷ, ẑ)``, so every orientation's force is
a combination of the four fields ``1, x̂, ŷ, ẑ`` with weights ``w : (4,)``; the solver is linear in
f, so the responses to the four fields are precomputed once and any gravity direction costs a
4-term combination per vertex at run time.
"""

from __future__ import annotations

import numpy as np

from lungdeform.constants import gravity_vector
from lungdeform.geometry.frame import LungFrame

FIELDS = ("1", "x", "y", "z")


def field_basis(xyz_hat: np.ndarray) -> np.ndarray:
    """``(4, n) float``: the fields 1, x̂, ŷ, ẑ at each vertex."""
    q = np.asarray(xyz_hat, dtype=float)
    return np.ascontiguousarray(np.vstack([np.ones(len(q)), q.T]))


def applied_force(xyz_hat: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Equation (18) as printed: ``f : (n,) = c7·x̂ + c8·ŷ + c9·ẑ`` (``c`` = c1…c9 or c7…c9)."""
    c = np.asarray(c, dtype=float)
    c7, c8, c9 = c[-3:]
    q = np.asarray(xyz_hat, dtype=float)
    return c7 * q[:, 0] + c8 * q[:, 1] + c9 * q[:, 2]


def height_weights(frame: LungFrame, gravity) -> np.ndarray:
    """``(4,)`` weights on (1, x̂, ŷ, ẑ) giving the normalised height against ``gravity`` (LPS)."""
    g = frame.axes @ gravity_vector(gravity)  # gravity in the lung frame
    span = frame.upper - frame.lower
    a = -g * span  # height = Σ a_k · q̂_k + const
    lo = np.minimum(a, 0.0).sum()
    hi = np.maximum(a, 0.0).sum()
    if hi - lo <= 0:
        return np.zeros(4)
    return np.concatenate([[-lo / (hi - lo)], a / (hi - lo)])


def force_weights(frame: LungFrame, gravity, c: np.ndarray) -> np.ndarray:
    """``w : (4,)`` so that ``f = w @ field_basis(x̂ŷẑ)`` = c7·x̂ + c8·ĥ(gravity) + c9·ẑ."""
    c = np.asarray(c, dtype=float)
    c7, c8, c9 = c[-3:]
    return np.array([0.0, c7, 0.0, c9]) + c8 * height_weights(frame, gravity)
