"""Fitting the model to a patient: alignment, ray correspondence, the objective, the search.

Owns: :mod:`~lungdeform.fit.config` (what a fit is given), :mod:`~lungdeform.fit.cycle` (a 4-D CT's
phases as one breathing cycle: volume order, hysteresis, the alignment chosen),
:mod:`~lungdeform.fit.align` (rigid alignment), :mod:`~lungdeform.fit.rays` (ray casting: where each
vertex's ray meets a target), :mod:`~lungdeform.fit.objective` (one lung's objective),
:mod:`~lungdeform.fit.fitting` (c1…c9, stiffness and direction correction), :mod:`~lungdeform.fit.search`
(optimiser and the paper's grid), :mod:`~lungdeform.fit.expandability` (the fitted stiffness field),
:mod:`~lungdeform.fit.direction_correction`, :mod:`~lungdeform.fit.refinement` (the smooth residual that
brings the fitted surface onto the targets), :mod:`~lungdeform.fit.registration` and
:mod:`~lungdeform.fit.cpd` (the smooth surface-to-surface map behind the surface-map interior field).
Reading the inputs, placing them, measuring a fit and the whole run (inputs to a saved model) are
:mod:`lungdeform.evaluate`'s.

May import: :mod:`lungdeform.data`, :mod:`lungdeform.io`,
:mod:`lungdeform.breathing`, :mod:`lungdeform.model`, :mod:`lungdeform.interior`,
:mod:`lungdeform.geometry` and the core modules; not :mod:`lungdeform.playback` (independent of it)
and nothing above.
"""

from .fitting import (
    DEFAULT_OPTIMIZER,
    DIRECTION_BOUNDS,
    DIRECTION_HI,
    DIRECTION_LO,
    MODES,
    UNUSABLE_MM,
    FitOutcome,
    FitSettings,
    fit_lung,
    to_lung_model,
)

__all__ = [
    "DEFAULT_OPTIMIZER",
    "DIRECTION_BOUNDS",
    "DIRECTION_HI",
    "DIRECTION_LO",
    "FitOutcome",
    "FitSettings",
    "MODES",
    "UNUSABLE_MM",
    "fit_lung",
    "to_lung_model",
]


def __getattr__(name: str):
    """``lungdeform.fit.FitResult`` (≤ 0.7) fails with one line naming ``FitOutcome`` (as
    :func:`lungdeform.fit.fitting.__getattr__`); other names are missing as usual."""
    if name == "FitResult":
        raise ImportError("lungdeform.fit.FitResult was renamed lungdeform.fit.FitOutcome in 0.8 (docs/CHANGELOG.md)")
    raise AttributeError(f"module 'lungdeform.fit' has no attribute {name!r}")
