"""Motion inside the lung, interpolated from the surface's motion.

Owns: :mod:`~lungdeform.interior.interpolate` (thin-plate splines), :mod:`~lungdeform.interior.sliding`
(the sliding interpolation of the surface's normal motion, and the landmark correction that keeps it),
:mod:`~lungdeform.interior.surface_map` (the field of a smooth surface-to-surface map: affine plus
Gaussian radial part, with any population prior on top, tapered to zero at the surface; the surface extension
of a built model; the interior kind ``"correspondence"``), :mod:`~lungdeform.interior.prior` (an affine
prior in the lung-normalised frame), :mod:`~lungdeform.interior.motion_prior` (that prior learned
across subjects, saved and read) and :mod:`~lungdeform.interior.field` (the interior field a lung
model plays back).

May import: :mod:`lungdeform.geometry` and the core modules (:mod:`lungdeform.atomic` for the prior file). It works on plain arrays (surface
points, unit displacements, landmarks), so the run-time model can carry a field without any fitting code.
"""

from .field import (
    CORRECTION_SMOOTHING_MM,
    KIND_TEXT,
    KINDS,
    MAX_SURFACE_POINTS,
    SMOOTHING_MM2,
    InteriorField,
    LandmarkCorrection,
    correction_per_unit,
    interior_field,
    spline_predict,
)
from .surface_map import SurfaceMapField

__all__ = [
    "CORRECTION_SMOOTHING_MM",
    "SurfaceMapField",
    "InteriorField",
    "KINDS",
    "KIND_TEXT",
    "LandmarkCorrection",
    "MAX_SURFACE_POINTS",
    "SMOOTHING_MM2",
    "correction_per_unit",
    "interior_field",
    "spline_predict",
]
