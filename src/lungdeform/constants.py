"""The paper's constants (Santhanam et al. 2008, Table I) and playback figures (Sec. V)."""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError

#: Table I: c1…c6 shape the displacement direction (15)–(17); c7…c9 the applied force (18).
TABLE_I: dict[str, tuple[float, ...]] = {
    "left": (0.09, 0.23, 0.4, 0.5, 0.1, 2.3, 0.01, 0.95, 0.07),
    "right": (0.09, 0.22, 0.39, 0.51, 0.11, 2.2, 0.01, 0.96, 0.05),
}

#: Paper Sec. V: 500 mL tidal volume, 5 s inhalation, 66.66 deformation steps per second.
TIDAL_VOLUME_ML = 500.0
INHALATION_S = 5.0
STEPS_PER_S = 1000.0 / 15.0
#: One paper "unit" of volume: 500 mL / (66.66 steps/s · 5 s) ≈ 1.5 mL.
PAPER_UNIT_ML = TIDAL_VOLUME_ML / (STEPS_PER_S * INHALATION_S)

#: Gravity directions in LPS (x → patient left, y → posterior, z → head).
GRAVITY = {
    "supine": (0.0, 1.0, 0.0),  # lying on the back: gravity points posterior
    "prone": (0.0, -1.0, 0.0),
    "upright": (0.0, 0.0, -1.0),  # standing or sitting: gravity points to the feet
    "left-decubitus": (1.0, 0.0, 0.0),  # lying on the left side
    "right-decubitus": (-1.0, 0.0, 0.0),
}


def table_constants(side: str) -> np.ndarray:
    """``c : (9,) float``, c1…c9 of Table I for ``side`` ('left' or 'right')."""

    if side not in TABLE_I:
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    return np.array(TABLE_I[side], dtype=float)


def gravity_vector(orientation) -> np.ndarray:
    """Unit gravity ``(3,) float`` in LPS from a name in :data:`GRAVITY` or a 3-vector."""

    if isinstance(orientation, str):
        key = orientation.strip().lower()
        if key not in GRAVITY:
            raise InputError(f"orientation must be one of {', '.join(GRAVITY)} or a vector, got {orientation!r}")
        g = np.array(GRAVITY[key])
    else:
        g = np.asarray(orientation, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.linalg.norm(g) > 0:
        raise InputError(f"gravity must be a non-zero finite 3-vector, got {orientation!r}")
    return g / np.linalg.norm(g)
