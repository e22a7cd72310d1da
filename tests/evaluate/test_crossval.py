"""lungdeform.evaluate.crossval: the k-fold protocol of the landmark-informed fit."""

import numpy as np
import pytest

from lungdeform.evaluate.crossval import cross_validate_landmarks
from lungdeform.fit.fitting import FitSettings
from lungdeform.fit.objective import LandmarkTerm, Target
from tests.fit.test_objective import TRUE, _interior_landmarks, truth  # noqa: F401  (truth: a fixture)


def test_cross_validation_is_held_out(truth):
    # synthetic truth: held-out landmarks are predicted to within a fraction of a mm, and a fold's
    # predictions do not depend on that fold's own observations (corrupting them changes nothing)
    lung, model, target = truth
    lm, lm_t = _interior_landmarks(lung, model.displacement, count=15)
    tg = [Target(target, lung.volume_ml + 200.0, name="t")]
    settings = FitSettings(initial=TRUE[:6] + 0.03, max_evaluations=40)
    cv = cross_validate_landmarks(lung, "right", tg, LandmarkTerm(lm, {0: lm_t}), settings, folds=3)
    err = np.linalg.norm(cv.predicted[0] - lm_t, axis=1)
    assert err.max() < 0.5
    assert cv.fold_constants.shape == (3, 9) and cv.final.landmarks_used == 15
    first = cv.fold == 0
    bad = lm_t.copy()
    bad[first] += 15.0
    cv_bad = cross_validate_landmarks(lung, "right", tg, LandmarkTerm(lm, {0: bad}), settings, folds=3)
    assert cv_bad.predicted[0][first] == pytest.approx(cv.predicted[0][first], abs=1e-9)
    assert np.linalg.norm(cv_bad.predicted[0][first] - bad[first], axis=1).min() > 10.0
