"""Motion inside the lung, interpolated from the surface's motion.

Owns: :mod:`~lungdeform.interior.interpolate` (thin-plate splines), :mod:`~lungdeform.interior.sliding`
(the sliding interpolation of the surface's normal motion, and the landmark correction that keeps it),
:mod:`~lungdeform.interior.correspondence` (the field of a smooth surface-to-surface map: affine plus
Gaussian radial part, with any population prior folded into its affine part; the surface extension
of a built model), :mod:`~lungdeform.interior.prior` (an affine prior in the lung-normalised frame) and
:mod:`~lungdeform.interior.field` (the interior field a lung model plays back, its landmark
correction's held-out selection, the landmark folds).

May import: :mod:`lungdeform.geometry` and the core modules. It works on plain arrays (surface
points, unit displacements, landmarks), so the run-time model can carry a field without any fitting code.
"""

from .correspondence import CorrespondenceField
from .field import (
    CORRECTION_SMOOTHING_MM,
    KIND_TEXT,
    KINDS,
    MAX_SURFACE_POINTS,
    SMOOTHING_MM2,
    InteriorField,
    correction_per_unit,
    correction_solvers,
    held_out_positions,
    held_out_sliding,
    interior_field,
    select_correction_smoothing,
    select_smoothing,
    spline_predict,
)

__all__ = [
    "CORRECTION_SMOOTHING_MM",
    "CorrespondenceField",
    "InteriorField",
    "KINDS",
    "KIND_TEXT",
    "MAX_SURFACE_POINTS",
    "SMOOTHING_MM2",
    "correction_per_unit",
    "correction_solvers",
    "held_out_positions",
    "held_out_sliding",
    "interior_field",
    "select_correction_smoothing",
    "select_smoothing",
    "spline_predict",
]
