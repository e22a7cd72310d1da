"""Fitting the model to a patient: CT to lungs, alignment, correspondence, the objective, the search.

Owns: :mod:`~lungdeform.fit.ct` and :mod:`~lungdeform.fit.segment` (CT input, lungs without learned
weights), :mod:`~lungdeform.fit.lungsplit` (a mask holding both lungs in one label → left and right),
:mod:`~lungdeform.fit.align` (rigid alignment), :mod:`~lungdeform.fit.correspond` (ray
correspondence), :mod:`~lungdeform.fit.objective` (one lung's objective), :mod:`~lungdeform.fit.fitting`
(c1…c9, stiffness and direction correction), :mod:`~lungdeform.fit.search` (optimiser and the paper's
grid), :mod:`~lungdeform.fit.crossval` (landmark cross-validation), :mod:`~lungdeform.fit.expandability`
(the fitted stiffness field), :mod:`~lungdeform.fit.direction_correction`, :mod:`~lungdeform.fit.refinement`
(the smooth residual that brings the fitted surface onto the targets), :mod:`~lungdeform.fit.registration` (the smooth
surface-to-surface map behind the correspondence interior field), :mod:`~lungdeform.fit.motion_prior`
(the population prior of interior motion, learned across subjects), :mod:`~lungdeform.fit.baselines`
(comparison methods), :mod:`~lungdeform.fit.pipeline` (inputs to a saved model and its metrics, in
steps: :mod:`~lungdeform.fit.config` what a fit is given, :mod:`~lungdeform.fit.inputs` reading and
checking, :mod:`~lungdeform.fit.cycle` a 4-D CT's phases as one breathing cycle (volume order,
hysteresis, the alignment chosen), :mod:`~lungdeform.fit.placement` the model mesh and the targets in its frame,
:mod:`~lungdeform.fit.heldout` what landmarks give, held out, :mod:`~lungdeform.fit.scoring` every
method measured) and :mod:`~lungdeform.fit.report` (the HTML report).

May import: :mod:`lungdeform.data`, :mod:`lungdeform.io`, :mod:`lungdeform.breathing`,
:mod:`lungdeform.model`, :mod:`lungdeform.interior`, :mod:`lungdeform.geometry` and the core modules;
not :mod:`lungdeform.playback` (independent of it) and nothing above.
"""

from .fitting import (
    DEFAULT_OPTIMIZER,
    DIRECTION_BOUNDS,
    DIRECTION_HI,
    DIRECTION_LO,
    MODES,
    UNUSABLE_MM,
    FitResult,
    fit_lung,
    to_lung_model,
)

__all__ = [
    "DEFAULT_OPTIMIZER",
    "DIRECTION_BOUNDS",
    "DIRECTION_HI",
    "DIRECTION_LO",
    "FitResult",
    "MODES",
    "UNUSABLE_MM",
    "fit_lung",
    "to_lung_model",
]
