"""Displacement directions (15)–(17) (paper Sec. IV-B.1; docs/METHOD_NOTES.md §6).

``d_i = (c1·x̂_i^c2, c3·ŷ_i^c4, c5·ẑ_i^c6)`` in the lung frame, mapped to LPS with the lung's
axes and normalised. The direction of each node is constant over the breathing cycle. Normalised
coordinates outside [0, 1] (a point beyond the end-exhale box) are clipped to [0, 1] so that the
powers stay real.
"""

from __future__ import annotations

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
