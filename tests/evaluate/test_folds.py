"""lungdeform.evaluate.folds: the k-fold landmark splits and the held-out choice of the landmark
correction's smoothing (no leaks: a landmark's own prediction never sees it)."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.evaluate.folds import (
    correction_solvers,
    held_out_positions,
    held_out_sliding,
    landmark_folds,
    select_correction_smoothing,
    select_smoothing,
)
from lungdeform.geometry.mesh import icosphere


def _inside(rng, n, radius):
    q = rng.normal(size=(n, 3))
    return q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0, radius, size=(n, 1))


def test_held_out_predictions_do_not_see_their_own_landmark(rng):
    # invariant of the k-fold protocol: changing the observation of one landmark leaves its own
    # held-out prediction unchanged (it moves the others of the same fold not at all either)
    lm = _inside(rng, 25, 40.0)
    unit = 0.02 * lm  # a surface-driven field: uniform expansion
    obs = 1.0 * (unit + 0.3 * np.sin(lm / 20.0))
    folds = [np.arange(i, 25, 5) for i in range(5)]
    a = held_out_positions(lm, [obs], [1.0], unit, folds)[0]
    obs2 = obs.copy()
    obs2[0] += 50.0
    b = held_out_positions(lm, [obs2], [1.0], unit, folds)[0]
    assert a[folds[0]] == pytest.approx(b[folds[0]], abs=1e-12)
    assert not np.allclose(a[folds[1]], b[folds[1]])
    # and the correction helps: held-out error below that of the surface-driven field alone
    truth = lm + obs
    assert np.linalg.norm(a - truth, axis=1).mean() < np.linalg.norm(lm + unit - truth, axis=1).mean()


def test_select_smoothing_follows_the_noise(rng):
    # noiseless smooth data: interpolation (0) predicts best; pure noise: the smoothest candidate
    p = _inside(rng, 40, 40.0)
    smooth = np.stack([np.sin(p[:, 0] / 15.0), np.cos(p[:, 1] / 20.0), p[:, 2] ** 2 / 800.0], axis=1)
    assert select_smoothing(p, smooth) == 0.0
    assert select_smoothing(p, rng.normal(size=(40, 3))) == 1000.0
    assert select_smoothing(p[:6], smooth[:6]) == 1000.0  # too few to judge


def test_sliding_correction_is_cross_validated_without_leaks(rng):
    # the k-fold protocol of the sliding correction: a landmark's own held-out prediction does not
    # depend on its observation, and the correction helps over the surface-driven field alone
    # (truth: a smooth interior slide the surface does not show)
    from lungdeform.interior.sliding import sliding_correction

    s = icosphere(3, 50.0)
    lm = _inside(rng, 25, 40.0)
    unit = 0.02 * lm
    obs = unit + np.stack([np.sin(lm[:, 2] / 30.0), 0.5 * np.cos(lm[:, 0] / 25.0), np.zeros(25)], axis=1)
    folds = [np.arange(i, 25, 5) for i in range(5)]
    solvers = correction_solvers(s.vertices, s.vertex_normals, lm)
    assert sorted(solvers) == [100.0, 300.0, 1000.0]
    a = held_out_sliding([obs], [1.0], unit, folds, solvers)[0]
    obs2 = obs.copy()
    obs2[0] += 50.0
    b = held_out_sliding([obs2], [1.0], unit, folds, solvers)[0]
    assert a[folds[0]] == pytest.approx(b[folds[0]], abs=1e-12)
    assert not np.allclose(a[folds[1]], b[folds[1]])
    truth = lm + obs
    assert np.linalg.norm(a - truth, axis=1).mean() < 0.5 * np.linalg.norm(lm + unit - truth, axis=1).mean()
    # fold 0 is the sliding correction through the other folds, at the smoothing chosen on them
    train, test = np.setdiff1d(np.arange(25), folds[0]), folds[0]
    lam = select_correction_smoothing(solvers, train, (obs - unit)[train])
    ref = sliding_correction(s.vertices, s.vertex_normals, lm[train], (obs - unit)[train], smoothing=lam)
    assert a[test] == pytest.approx(lm[test] + unit[test] + ref(lm[test]), abs=1e-9)
    assert select_correction_smoothing(solvers, np.arange(6), (obs - unit)[:6]) == 1000.0  # too few to judge
    with pytest.raises(InputError, match="one row per landmark"):
        held_out_sliding([obs], [1.0], unit[:-1], folds, solvers)


def test_landmark_folds_partition_the_indices():
    # a partition: every index once, sizes within 1, seeded (same seed, same split); bad counts refused
    parts = landmark_folds(23, 5, seed=3)
    assert sorted(np.concatenate(parts).tolist()) == list(range(23))
    assert {len(p) for p in parts} == {4, 5}
    assert all(np.array_equal(a, b) for a, b in zip(parts, landmark_folds(23, 5, seed=3)))
    with pytest.raises(InputError, match="--folds must be between 2"):
        landmark_folds(4, 5, parameter="--folds")
