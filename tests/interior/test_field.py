"""Interior field: surface-driven sliding motion plus the landmark correction."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.evaluate.folds import held_out_positions, select_smoothing
from lungdeform.geometry.mesh import icosphere
from lungdeform.interior.field import correction_per_unit, interior_field


def _inside(rng, n, radius):
    q = rng.normal(size=(n, 3))
    return q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0, radius, size=(n, 1))


def test_correction_recovers_the_missing_motion(rng):
    # truth: observed_i = s_i·(p + c) at two scales, so least squares gives c back exactly
    p = rng.normal(size=(20, 3))
    c = rng.normal(size=(20, 3))
    scales = [0.6, 1.0]
    assert correction_per_unit([s * (p + c) for s in scales], scales, p) == pytest.approx(c, abs=1e-12)
    with pytest.raises(InputError, match="scales"):
        correction_per_unit([p], [0.0], p)
    with pytest.raises(InputError, match="one per observed"):
        correction_per_unit([p, p], [1.0], p)


def test_affine_surface_motion_moves_interior_points_exactly(rng):
    # the sliding interpolation reproduces affine fields: a sphere whose surface moves by
    # u = A·x + b (A symmetric: a sphere's rotation is invisible to its normals) moves every
    # interior point by the same law (no correction)
    s = icosphere(3, 50.0)
    a = np.array([[0.05, 0.01, 0.0], [0.01, -0.02, 0.03], [0.0, 0.03, 0.1]])
    b = np.array([1.0, -2.0, 3.0])
    field = interior_field(s.vertices, s.vertices @ a.T + b, normals=s.vertex_normals)
    q = _inside(rng, 40, 45.0)
    assert not field.corrected
    assert field.positions(q, 2.0) == pytest.approx(q + 2.0 * (q @ a.T + b), abs=1e-6)


def test_correction_adds_the_landmark_motion(rng):
    # landmarks that slide by a smooth field the surface does not show (surface at rest): the
    # corrected field moves them (in sample, no smoothing) exactly, and points near them close to it
    s = icosphere(3, 50.0)
    lm = _inside(rng, 30, 40.0)

    def slide(x):
        return np.stack([np.sin(x[:, 2] / 30.0), 0.5 * np.cos(x[:, 0] / 25.0), np.zeros(len(x))], axis=1)

    field = interior_field(s.vertices, np.zeros_like(s.vertices), lm, slide(lm), 0.0, normals=s.vertex_normals)
    assert field.corrected
    assert field.displacement(lm) == pytest.approx(slide(lm), abs=1e-6)
    q = _inside(rng, 50, 30.0)
    err = np.linalg.norm(field.displacement(q) - slide(q), axis=1)
    assert err.mean() < 0.2 * np.linalg.norm(slide(q), axis=1).mean()


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


def test_bad_input():
    s = icosphere(1, 10.0)
    v, n = s.vertices, s.vertex_normals
    with pytest.raises(InputError, match="shape"):
        interior_field(v, v[:-1], normals=n)
    with pytest.raises(InputError, match="shape"):
        interior_field(v, v, normals=n[:-1])
    with pytest.raises(InputError, match="unit length"):
        interior_field(v, v, normals=2.0 * n)
    with pytest.raises(InputError, match="at least 5 points"):
        interior_field(v, v, v[:3], v[:3], normals=n, kind="sliding_thin_plate")
    with pytest.raises(InputError, match="values must be finite with the anchors' shape"):
        interior_field(v, v, v[:3], v[:2], normals=n)
    with pytest.raises(InputError, match="smoothing"):
        interior_field(v, v, smoothing=-1.0, normals=n)
    with pytest.raises(InputError, match="interior kind"):
        interior_field(v, v, normals=n, kind="spline")
    with pytest.raises(InputError, match="NaN"):
        interior_field(v, v, normals=n).displacement(np.array([[np.nan, 0.0, 0.0]]))


def test_sliding_correction_is_cross_validated_without_leaks(rng):
    # the k-fold protocol of the sliding correction: a landmark's own held-out prediction does not
    # depend on its observation, and the correction helps over the surface-driven field alone
    # (truth: a smooth interior slide the surface does not show)
    from lungdeform.evaluate.folds import correction_solvers, held_out_sliding, select_correction_smoothing
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
