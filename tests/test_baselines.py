"""Baselines: affine exact on an affinely deformed surface, apex scaling exact in volume, CPD, metrics."""

import numpy as np
import pytest

from lungdeform.baselines import affine_fit, apex_scaling, cpd_deformable, measure, no_motion
from lungdeform.mesh import Surface
from tests.conftest import ellipsoid_lung


def test_affine_exact_on_affine_deformation():
    s = ellipsoid_lung("right", 3)
    a = np.array([[1.04, 0.02, 0.0], [0.0, 1.06, 0.01], [0.0, 0.03, 1.08]])
    c = s.vertices.mean(0)
    target = Surface((s.vertices - c) @ a.T + c + np.array([1.0, -2.0, -3.0]), s.faces)
    # closest-point ICP converges to the exact map only asymptotically: run it long
    pred, mat = affine_fit(s, target, iterations=500, tol_mm=0.0)
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
    m, per_vertex, err = measure(s, no_motion(s), s, landmarks=lm, landmarks_target=lm + [0, 0, 3.0])
    assert m.surface_mean_mm == pytest.approx(0.0, abs=1e-9)
    assert err == pytest.approx([3.0, 3.0], abs=1e-9)


def test_cpd_recovers_a_smooth_deformation():
    pytest.importorskip("pycpd")
    s = ellipsoid_lung("right", 3)
    c = s.vertices.mean(0)
    target = Surface(c + (s.vertices - c) * np.array([1.05, 1.08, 1.03]), s.faces)
    pred = cpd_deformable(s, target, samples=600)
    m, _, _ = measure(s, pred, target)
    m0, _, _ = measure(s, no_motion(s), target)
    assert m.surface_mean_mm < 0.25 * m0.surface_mean_mm
