"""Held-out landmark errors of the landmark-informed fit: the k-fold protocol (docs/FITTING.md).

Surfaces constrain the constants only through the shape they predict, so a fit may add
corresponding interior landmarks to its objective (moved by the sliding interpolation of the
model's surface motion, :mod:`lungdeform.interior.sliding`) (:func:`lungdeform.fit.fitting.fit_lung` with ``landmarks_rest`` / ``landmarks_targets``). The
landmark error of such a fit is in-sample; :func:`cross_validate_landmarks` fits once per fold on
the surfaces and the other folds' landmarks, moves the fold's landmarks with that fit, and finally
fits on all landmarks (the model a user keeps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices
from lungdeform.interior.field import landmark_folds
from lungdeform.interior.sliding import checked_operator, surface_weights
from lungdeform.progress import Progress, silent

from .fitting import fit_lung

if TYPE_CHECKING:  # fit_lung is imported where used (fit.py's docstring refers to this module)
    from lungdeform.geometry.mesh import Surface

    from .fitting import FitResult
    from .objective import Target


@dataclass(frozen=True, eq=False)
class LandmarkCV:
    """Held-out landmark predictions of the landmark-informed fit (:func:`cross_validate_landmarks`).

    Attributes
    ----------
    final : FitResult
        The fit on all landmarks (the model a user keeps; its landmark error is in-sample).
    predicted : dict[int, (m, 3) float]
        Per target index: every landmark's position predicted by the fold that did **not** see
        it, mm (aligned frame).
    fold : (m,) int
        Fold of each landmark.
    fold_constants : (k, 9) float
        c1…c9 fitted in each fold (their spread shows how well the landmarks pin them down).
    """

    final: FitResult
    predicted: dict
    fold: np.ndarray
    fold_constants: np.ndarray


def cross_validate_landmarks(surface: Surface, side: str, targets: Sequence[Target], landmarks_rest,
                             landmarks_targets: dict, *, folds=5, seed: int = 0, initial=None,
                             max_evaluations: int = 200, progress: Progress | None = None,
                             landmark_matrix=None, **fit_kwargs) -> LandmarkCV:
    """k-fold protocol for the landmark-informed fit: for each fold, fit on the surfaces and the
    other folds' landmarks (:func:`fit_lung` with the landmark term), then move the fold's
    landmarks with that fit; finally fit on all landmarks.

    ``landmarks_rest : (m, 3)`` mm and ``landmarks_targets : {target index: (m, 3)}`` mm, aligned.
    ``folds``: a number of folds (split by :func:`landmark_folds` with ``seed``) or the index
    arrays themselves. ``initial``: c1…c6 to start every fold from (e.g. the surface-only fit).
    ``landmark_matrix : (m, k) operator``, optional: the sliding interpolation from the kept
    vertices to all of ``landmarks_rest`` (:func:`lungdeform.fit.baselines.landmark_matrix`),
    computed once here when not given; each fold uses its rows. Other keywords go to :func:`fit_lung`. Landmark errors computed from
    :attr:`LandmarkCV.predicted` are held out.
    """

    say = progress or silent
    rest = as_vertices(landmarks_rest, "landmarks_rest")
    if isinstance(folds, (int, np.integer)):
        parts = landmark_folds(len(rest), int(folds), seed)
    else:
        parts = [np.asarray(p, np.int64) for p in folds]
        if not np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(rest))):
            raise InputError(f"folds must partition the {len(rest)} landmarks")
    fold = np.zeros(len(rest), np.int64)
    predicted = {int(i): np.full_like(rest, np.nan) for i in landmarks_targets}
    consts = []
    kept = np.ones(surface.n_vertices, bool) if fit_kwargs.get("keep") is None else np.asarray(fit_kwargs["keep"], bool)
    # one interpolation operator for all landmarks: row j depends only on landmark j, so the folds take rows
    w_all = (surface_weights(surface, rest, kept) if landmark_matrix is None
             else checked_operator(landmark_matrix, (len(rest), int(kept.sum()))))
    for k, test in enumerate(parts):
        fold[test] = k
        train = np.setdiff1d(np.arange(len(rest)), test)
        r = fit_lung(surface, side, targets, initial=initial, max_evaluations=max_evaluations,
                     landmarks_rest=rest[train], landmarks_targets={i: np.asarray(v)[train] for i, v in landmarks_targets.items()},
                     landmark_matrix=w_all[train], progress=progress, **fit_kwargs)
        consts.append(r.constants)
        w = w_all[test]
        for i in predicted:
            s = r.scale_at(targets[i].volume_ml)
            predicted[i][test] = rest[test] + s * (w @ r.displacement[kept])
        say(f"landmark fold {k + 1}/{len(parts)}: surface RMS {r.surface_rms_mm:.2f} mm, "
            f"training landmarks RMS {r.landmark_rms_mm:.2f} mm")
    final = fit_lung(surface, side, targets, initial=initial, max_evaluations=max_evaluations,
                     landmarks_rest=rest, landmarks_targets=landmarks_targets, landmark_matrix=w_all,
                     progress=progress, **fit_kwargs)
    return LandmarkCV(final, predicted, fold, np.asarray(consts))
