"""Baselines: affine exact on an affinely deformed surface, apex scaling exact in volume, CPD, metrics."""

import numpy as np
import pytest

from lungdeform.evaluate import baselines as B
from lungdeform.evaluate.baselines import affine_fit, apex_scaling, cpd_deformable, measure, no_motion
from lungdeform.geometry.mesh import Surface
from tests.conftest import ellipsoid_lung


def test_affine_exact_on_affine_deformation():
    s = ellipsoid_lung("right", 3)
    a = np.array([[1.04, 0.02, 0.0], [0.0, 1.06, 0.01], [0.0, 0.03, 1.08]])
    c = s.vertices.mean(0)
    target = Surface((s.vertices - c) @ a.T + c + np.array([1.0, -2.0, -3.0]), s.faces)
    # closest-point ICP converges to the exact map only asymptotically: run it long
    pred, mat = affine_fit(s, target, B.IcpSettings(iterations=500, tol_mm=0.0))
    m, per_vertex, _ = measure(s, pred, target)
    assert m.surface_mean_mm < 0.01
    assert per_vertex.max() < 0.05
    assert mat[:3, :3] == pytest.approx(a, abs=5e-3)


def test_apex_scaling_volume_and_apex():
    s = ellipsoid_lung("left", 3)
    x = apex_scaling(s, 1.2 * s.volume_ml)
    assert Surface(x, s.faces).volume_ml == pytest.approx(1.2 * s.volume_ml, rel=1e-9)
    top = np.argmax(s.vertices[:, 2])
    assert x[top] == pytest.approx(s.vertices[top])


def test_measure_landmarks_and_no_motion():
    s = ellipsoid_lung("left", 3)
    lm = s.vertices.mean(0)[None] + np.array([[0.0, 0, 0], [10.0, 5, -20]])
    m, per_vertex, err = measure(s, no_motion(s), s, landmarks=B.LandmarkPairs(lm, lm + [0, 0, 3.0]))
    assert m.surface_mean_mm == pytest.approx(0.0, abs=1e-9)
    assert err == pytest.approx([3.0, 3.0], abs=1e-9)


def test_cpd_recovers_a_smooth_deformation():
    s = ellipsoid_lung("right", 3)
    c = s.vertices.mean(0)
    target = Surface(c + (s.vertices - c) * np.array([1.05, 1.08, 1.03]), s.faces)
    pred = cpd_deformable(s, target, B.CpdSettings(samples=600))
    m, _, _ = measure(s, pred, target)
    m0, _, _ = measure(s, no_motion(s), target)
    assert m.surface_mean_mm < 0.25 * m0.surface_mean_mm


def test_affine_with_landmarks_moves_toward_them():
    # the surfaces say "scale by a"; the landmarks say "translate by 3 mm in z": with no landmark
    # weight the surface affine comes back, with an overwhelming weight the landmarks' own affine
    from lungdeform.evaluate.baselines import affine_landmarks_cv
    from lungdeform.evaluate.folds import landmark_folds

    s = ellipsoid_lung("right", 3)
    c = s.vertices.mean(0)
    a = np.diag([1.03, 1.05, 1.04])
    target = Surface((s.vertices - c) @ a.T + c, s.faces)
    lm = c + np.random.default_rng(3).uniform(-20, 20, size=(12, 3))
    lm_t = lm + np.array([0.0, 0.0, 3.0])
    _, m0 = affine_fit(s, target, B.IcpSettings(iterations=300, tol_mm=0.0), landmarks=lm, landmarks_target=lm_t,
                       landmark_weight=0.0)
    assert m0[:3, :3] == pytest.approx(a, abs=5e-3)
    _, m1 = affine_fit(s, target, landmarks=lm, landmarks_target=lm_t, landmark_weight=1e8)
    assert lm @ m1[:3, :3].T + m1[:3, 3] == pytest.approx(lm_t, abs=1e-3)
    # held out: with landmarks that agree with the surfaces, every held-out landmark is exact
    lm_a = (lm - c) @ a.T + c
    _, held = affine_landmarks_cv(s, target, B.LandmarkPairs(lm, lm_a), landmark_folds(len(lm), 3),
                                  B.IcpSettings(iterations=300, tol_mm=0.0))
    assert held == pytest.approx(lm_a, abs=0.05)


def test_landmark_tps_cv_held_out():
    # an affine landmark motion is reproduced exactly by the spline of the other folds (truth);
    # a landmark whose own target is wrong does not help predict itself
    from lungdeform.evaluate.baselines import landmark_tps_cv
    from lungdeform.evaluate.folds import landmark_folds

    s = ellipsoid_lung("left", 2)
    rng = np.random.default_rng(5)
    lm = s.vertices.mean(0) + rng.uniform(-25, 25, size=(20, 3))
    lm_t = lm @ np.diag([1.02, 0.98, 1.05]).T + np.array([1.0, -2.0, 4.0])
    folds = landmark_folds(len(lm), 4)
    moved, held = landmark_tps_cv(s, lm, lm_t, folds)
    assert held == pytest.approx(lm_t, abs=1e-6)
    assert moved == pytest.approx(s.vertices @ np.diag([1.02, 0.98, 1.05]).T + np.array([1.0, -2.0, 4.0]), abs=1e-6)
    bad = lm_t.copy()
    bad[folds[0][0]] += 10.0
    _, held_bad = landmark_tps_cv(s, lm, bad, folds)
    assert held_bad[folds[0]] == pytest.approx(lm_t[folds[0]], abs=1e-6)  # its fold never saw it
    assert np.abs(held_bad[folds[1]] - lm_t[folds[1]]).max() > 0.01  # the others did


def test_measure_uses_kept_vertices_and_given_predictions():
    s = ellipsoid_lung("left", 3)
    lm = s.vertices.mean(0)[None] + np.array([[0.0, 0, 0], [10.0, 5, -20]])
    # a field that is a 3 mm z shift on kept vertices and garbage on the excluded ones: the
    # landmarks see only the kept part, so they move by exactly 3 mm
    keep = s.vertices[:, 0] < s.vertices[:, 0].max() - 10.0
    x = s.vertices + np.array([0.0, 0.0, 3.0])
    x[~keep] += 50.0
    m, _, err = measure(s, x, s, keep=keep, landmarks=B.LandmarkPairs(lm, lm + [0, 0, 3.0]))
    assert err == pytest.approx([0.0, 0.0], abs=1e-6)
    m, _, err = measure(s, x, s, keep=keep,
                        landmarks=B.LandmarkPairs(lm, lm + [0, 0, 3.0], predicted=lm + [0, 4.0, 3.0]))
    assert err == pytest.approx([4.0, 4.0]) and m.landmark_median_mm == pytest.approx(4.0)


def test_cpd_leaves_out_crop_faces():
    # a crop-face artefact (the target's cap pushed out 15 mm): registered from the kept vertices
    # only, CPD matches the true scaled surface on the kept part better than when it chases the cap
    s = ellipsoid_lung("right", 3)
    c = s.vertices.mean(0)
    true = c + (s.vertices - c) * np.array([1.05, 1.08, 1.03])
    cap = s.vertices[:, 0] > s.vertices[:, 0].max() - 12.0
    art = true.copy()
    art[cap] += np.array([15.0, 0.0, 0.0])
    target = Surface(art, s.faces)
    clean = Surface(true, s.faces)
    kept = measure(s, cpd_deformable(s, target, B.CpdSettings(samples=600), keep=~cap, keep_target=~cap), clean, keep=~cap)[0]
    chased = measure(s, cpd_deformable(s, target, B.CpdSettings(samples=600)), clean, keep=~cap)[0]
    assert kept.surface_mean_mm < 0.7 * chased.surface_mean_mm


def test_baselines_align_themselves_whatever_frame_the_target_arrives_in():
    # truth: a translated copy of the surface is found again by the translation ICP (from the
    # centroids, 40 mm away), and a baseline's prediction does not depend on the frame the target was
    # placed in (the model's alignment): moving the target by d moves every prediction by d exactly
    s = ellipsoid_lung("right", 3)
    shift = np.array([25.0, -30.0, 12.0])
    assert B.best_translation(s, Surface(s.vertices + shift, s.faces)) == pytest.approx(shift, abs=1e-6)
    c = s.vertices.mean(0)
    target = Surface(c + (s.vertices - c) * np.array([1.04, 1.07, 1.1]) + [0.0, 0.0, -6.0], s.faces)
    d = np.array([3.0, -8.0, 5.0])
    moved = Surface(target.vertices + d, target.faces)
    icp = B.IcpSettings(iterations=60, tol_mm=0.0)
    # (equal up to ICP's own noise: its result moves by up to 0.02 mm when the input moves by 1e-9 mm,
    # measured; a baseline that kept the placement's translation would be off by |d| = 9.9 mm)
    for fn in (lambda t: no_motion(s) + B.best_translation(s, t, icp),
               lambda t: B.self_aligned(s, apex_scaling(s, t.volume_ml), t, icp=icp),
               lambda t: affine_fit(s, t, icp)[0]):
        assert fn(moved) == pytest.approx(fn(target) + d, abs=0.05)
    # its own translation serves each baseline better than none (here the target's centroid moved 6 mm):
    # by the RMS surface distance, which the ICP minimises
    m_own, _, _ = measure(s, no_motion(s) + B.best_translation(s, target), target)
    m_none, _, _ = measure(s, no_motion(s), target)
    assert m_own.surface_rms_mm < 0.95 * m_none.surface_rms_mm
