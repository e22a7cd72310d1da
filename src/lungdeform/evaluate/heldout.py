"""What a fit's landmarks give, scored on held-out landmarks (step 5 of :func:`lungdeform.evaluate.pipeline.run_fit`).

With landmarks and ``landmark_fit``: the interior landmark correction of the surface fit
(:mod:`lungdeform.interior.field`), its landmark errors held out per fold; with
``landmark_comparisons`` also the landmark-informed fits of c1…c9
(:func:`lungdeform.evaluate.crossval.cross_validate_landmarks`, and again with a stiffness field). All
share one sliding interpolation from the kept model vertices to the landmarks
(:func:`lungdeform.evaluate.baselines.landmark_matrix`), which the metrics of every method use too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform import blas
from lungdeform.fit.config import FitConfig
from lungdeform.fit.fitting import FitOutcome, FitSettings
from lungdeform.fit.objective import LandmarkTerm
from lungdeform.interior.field import correction_per_unit
from lungdeform.interior.sliding import SMOOTHING_MM
from lungdeform.progress import Progress, silent

from . import baselines as B
from .crossval import LandmarkCV, cross_validate_landmarks
from .folds import correction_solvers, held_out_sliding, select_correction_smoothing
from .placement import Placement


@dataclass(frozen=True, eq=False)
class HeldOut:
    """The landmark step's results (:func:`held_out_landmarks`); every field None without landmarks.

    Attributes
    ----------
    matrix : (m, k) operator or None
        Sliding interpolation from the kept model vertices to the end-exhale landmarks.
    cv, cv_stiffness : LandmarkCV or None
        The landmark-informed fits (with ``landmark_comparisons``; the second with ``stiffness``).
    interior : dict or None
        The interior correction (with ``landmark_fit``): ``held_out`` (per target, (m, 3) float mm),
        ``correction`` ((m, 3) float mm per unit) and ``smoothing`` (mm).
    surface_unit : (m, 3) float or None
        The surface part of the interior field at the landmarks, mm per unit, when it is a
        correspondence field (None: the sliding interpolation, ``matrix @`` the kept displacement).
    """

    matrix: object = None
    cv: LandmarkCV | None = None
    cv_stiffness: LandmarkCV | None = None
    interior: dict | None = None
    surface_unit: np.ndarray | None = None


def held_out_landmarks(placed: Placement, landmarks, fit: FitOutcome, side: str, config: FitConfig, folds,
                       progress: Progress | None = None, surface_field=None) -> HeldOut:
    """The landmark step for the surface ``fit`` of the model mesh in ``placed``: ``landmarks : (m, 3)``
    mm are the end-exhale ones (None: no landmarks), ``folds`` their k-fold split
    (:func:`lungdeform.interior.field.landmark_folds`; None without ``landmark_fit``).
    ``surface_field``: the interior field's surface part when it is a correspondence field (None: sliding).
    Its dense solves run the BLAS on one thread (:func:`lungdeform.blas.limited`)."""

    if landmarks is None:
        return HeldOut()
    with blas.limited():
        return _held_out_landmarks(placed, landmarks, fit, side, config, folds, progress, surface_field)


def _held_out_landmarks(placed: Placement, landmarks, fit: FitOutcome, side: str, config: FitConfig, folds,
                        progress, surface_field) -> HeldOut:
    """:func:`held_out_landmarks` with ``landmarks`` given."""
    say = progress or silent
    # the landmark correction's solvers (one dense solve per candidate smoothing), with landmark_fit
    solvers = (correction_solvers(placed.rest.vertices[placed.keep], placed.rest.vertex_normals[placed.keep], landmarks)
               if config.landmark_fit else {})
    # the sliding interpolation from the kept model vertices to the landmarks, shared by every
    # landmark-informed fit (rows per fold) and by the metrics of every method: one dense solve, or
    # the by-product of the correction's solve at the same smoothing (the same system, the same columns)
    weights = (solvers[SMOOTHING_MM].surface_weights() if SMOOTHING_MM in solvers
               else B.landmark_matrix(placed.rest, landmarks, placed.keep))
    unit = weights @ fit.displacement[placed.keep] if surface_field is None else surface_field(landmarks)
    surface_unit = None if surface_field is None else unit
    if not config.landmark_fit:
        return HeldOut(weights, surface_unit=surface_unit)
    cv, cv_stiff = None, None
    if config.landmark_comparisons:
        say(f"landmark-informed fit ({config.folds}-fold cross-validation over {len(landmarks)} landmarks)")
        term = LandmarkTerm(landmarks, {ti: placed.landmarks[ti] for ti in range(len(placed.targets))},
                            config.landmark_weight, weights)
        cv = _landmark_fit(placed, term, fit, side, config, folds, stiffness=False, progress=say)
        if config.stiffness:
            say("landmark-informed fit with a stiffness field (cross-validated)")
            cv_stiff = _landmark_fit(placed, term, fit, side, config, folds, stiffness=True, progress=say)
    say("interior landmark correction (cross-validated)")
    interior = interior_correction(fit, landmarks, placed.landmarks, placed.targets, folds, unit, solvers)
    return HeldOut(weights, cv, cv_stiff, interior, surface_unit)


def _landmark_fit(placed: Placement, landmarks: LandmarkTerm, fit: FitOutcome, side: str, config: FitConfig, folds, *,
                  stiffness: bool, progress) -> LandmarkCV:
    """The cross-validated landmark-informed fit of c1…c9 (optionally with a stiffness field),
    started from the surface ``fit``."""

    settings = FitSettings(mode=config.mode, initial=fit.constants, fit_stiffness=stiffness,
                           max_evaluations=max(100, config.max_evaluations * 2 // 3))
    return cross_validate_landmarks(placed.rest, side, placed.targets, landmarks, settings, folds=folds,
                                    keep=placed.keep, progress=progress)


def interior_correction(fit, landmarks, aligned, targets, folds, unit, solvers) -> dict:
    """The interior field's landmark correction for ``fit`` (:mod:`lungdeform.interior.field`): held-out
    landmark positions per target (k-fold), and the correction and its smoothing from all landmarks.
    ``unit : (m, 3)`` mm per unit is the surface-driven part at the landmarks, the one the saved
    model plays back (the correspondence field, or the sliding interpolation from the kept vertices
    as the metrics' operator, :func:`lungdeform.evaluate.baselines.landmark_matrix`); the correction is
    the sliding correction through the kept vertices of the model mesh: ``solvers``, its
    :func:`~lungdeform.evaluate.folds.correction_solvers` through ``landmarks``."""

    observed = [np.asarray(a) - landmarks for a in aligned]
    scales = [fit.scale_at(tg.volume_ml) for tg in targets]
    correction = correction_per_unit(observed, scales, unit)
    return {"held_out": held_out_sliding(observed, scales, unit, folds, solvers),
            "correction": correction,
            "smoothing": select_correction_smoothing(solvers, np.arange(len(landmarks)), correction)}
