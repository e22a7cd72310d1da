"""Held-out landmark errors of the landmark-informed fit: the k-fold protocol (docs/FITTING.md).

Surfaces constrain the constants only through the shape they predict, so a fit may add
corresponding interior landmarks to its objective (moved by the sliding interpolation of the
model's surface motion, :mod:`lungdeform.interior.sliding`) (:func:`lungdeform.fit.fitting.fit_lung` with a
:class:`~lungdeform.fit.objective.LandmarkTerm`). The
landmark error of such a fit is in-sample; :func:`cross_validate_landmarks` fits once per fold on
the surfaces and the other folds' landmarks, moves the fold's landmarks with that fit, and finally
fits on all landmarks (the model a user keeps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from lungdeform.errors import InputError
from lungdeform.fit.fitting import FitSettings, fit_lung
from lungdeform.fit.objective import LandmarkTerm
from lungdeform.geometry.mesh import as_vertices
from lungdeform.interior.sliding import checked_operator, surface_weights
from lungdeform.progress import Progress, silent

from .folds import landmark_folds

if TYPE_CHECKING:
    from lungdeform.fit.fitting import FitOutcome
    from lungdeform.fit.objective import Target
    from lungdeform.geometry.mesh import Surface


@dataclass(frozen=True, eq=False)
class LandmarkCV:
    """Held-out landmark predictions of the landmark-informed fit (:func:`cross_validate_landmarks`).

    Attributes
    ----------
    final : FitOutcome
        The fit on all landmarks (the model a user keeps; its landmark error is in-sample).
    predicted : dict[int, (m, 3) float]
        Per target index: every landmark's position predicted by the fold that did **not** see
        it, mm (aligned frame).
    fold : (m,) int
        Fold of each landmark.
    fold_constants : (k, 9) float
        c1…c9 fitted in each fold (their spread shows how well the landmarks pin them down).
    """

    final: FitOutcome
    predicted: dict
    fold: np.ndarray
    fold_constants: np.ndarray


def cross_validate_landmarks(surface: Surface, side: str, targets: Sequence[Target], landmarks: LandmarkTerm,
                             settings: FitSettings = FitSettings(max_evaluations=200), *, folds=5, keep=None,
                             progress: Progress | None = None) -> LandmarkCV:
    """k-fold protocol for the landmark-informed fit: for each fold, fit on the surfaces and the
    other folds' landmarks (:func:`fit_lung` with the landmark term), then move the fold's
    landmarks with that fit; finally fit on all landmarks.

    ``landmarks``: the landmark term (:class:`~lungdeform.fit.objective.LandmarkTerm`: ``rest : (m, 3)``
    mm and ``targets : {target index: (m, 3)}`` mm, aligned; its ``matrix``, the sliding
    interpolation from the kept vertices to all of ``rest``
    (:func:`lungdeform.evaluate.baselines.landmark_matrix`), is computed once here when not given;
    each fold uses its rows). ``settings``: every fit's search (:class:`~lungdeform.fit.fitting.FitSettings`;
    its ``initial``, e.g. the surface-only fit, starts every fold). ``folds``: a number of folds
    (split by :func:`landmark_folds`, seed 0) or the index arrays themselves. ``keep``: the model
    vertices measured. Landmark errors computed from :attr:`LandmarkCV.predicted` are held out.
    """

    say = progress or silent
    rest = as_vertices(landmarks.rest, "landmarks_rest")
    landmarks_targets, landmark_matrix = landmarks.targets, landmarks.matrix
    if isinstance(folds, (int, np.integer)):
        parts = landmark_folds(len(rest), int(folds), 0)
    else:
        parts = [np.asarray(p, np.int64) for p in folds]
        if not np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(rest))):
            raise InputError(f"folds must partition the {len(rest)} landmarks")
    fold = np.zeros(len(rest), np.int64)
    predicted = {int(i): np.full_like(rest, np.nan) for i in landmarks_targets}
    consts = []
    kept = np.ones(surface.n_vertices, bool) if keep is None else np.asarray(keep, bool)
    # one interpolation operator for all landmarks: row j depends only on landmark j, so the folds take rows
    w_all = (surface_weights(surface, rest, kept) if landmark_matrix is None
             else checked_operator(landmark_matrix, (len(rest), int(kept.sum()))))
    for k, test in enumerate(parts):
        fold[test] = k
        train = np.setdiff1d(np.arange(len(rest)), test)
        term = LandmarkTerm(rest[train], {i: np.asarray(v)[train] for i, v in landmarks_targets.items()},
                            landmarks.weight, w_all[train])
        r = fit_lung(surface, side, targets, settings, landmarks=term, keep=keep, progress=progress)
        consts.append(r.constants)
        w = w_all[test]
        for i in predicted:
            s = r.scale_at(targets[i].volume_ml)
            predicted[i][test] = rest[test] + s * (w @ r.displacement[kept])
        say(f"landmark fold {k + 1}/{len(parts)}: surface RMS {r.surface_rms_mm:.2f} mm, "
            f"training landmarks RMS {r.landmark_rms_mm:.2f} mm")
    final = fit_lung(surface, side, targets, settings, landmarks=LandmarkTerm(rest, landmarks_targets, landmarks.weight,
                                                                               w_all), keep=keep, progress=progress)
    return LandmarkCV(final, predicted, fold, np.asarray(consts))
