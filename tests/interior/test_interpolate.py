"""Thin-plate-spline interpolation of surface displacements into the interior."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import icosphere
from lungdeform.interior.interpolate import displacement_field


def test_affine_field_reproduced_exactly(rng):
    # the degree-1 polynomial part makes any affine displacement exact, inside and outside
    s = icosphere(3, 50.0)
    a = np.array([[0.05, 0.01, 0.0], [0.0, -0.02, 0.03], [0.01, 0.0, 0.1]])
    b = np.array([1.0, -2.0, 3.0])
    field = displacement_field(s.vertices, s.vertices @ a.T + b)
    q = rng.uniform(-40, 40, size=(50, 3))
    assert field(q) == pytest.approx(q @ a.T + b, abs=1e-6)


def test_smooth_field_approximated(rng):
    # a harmonic quadratic field (|u| ≤ 5 mm on the sphere) is recovered at interior points to a
    # fraction of its size (thin-plate splines are not harmonic, so not exactly), and exactly at the samples
    s = icosphere(4, 50.0)

    def u(p):
        return np.stack([p[:, 0] * p[:, 1], p[:, 1] * p[:, 2], p[:, 0] ** 2 - p[:, 1] ** 2], axis=1) / 500.0

    field = displacement_field(s.vertices, u(s.vertices), max_points=20000)
    q = rng.normal(size=(200, 3))
    q = q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0, 35, size=(200, 1))
    err = np.linalg.norm(field(q) - u(q), axis=1)
    assert err.max() < 0.15 * 5.0
    assert err.mean() < 0.5 * np.linalg.norm(u(q), axis=1).mean()
    assert field(s.vertices[:50]) == pytest.approx(u(s.vertices[:50]), abs=1e-6)


def test_bad_input():
    with pytest.raises(InputError):
        displacement_field(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(InputError):
        displacement_field(np.zeros((10, 3)), np.zeros((9, 3)))


def test_interpolation_weights_equal_the_field(rng):
    # the matrix form is the same interpolant as RBFInterpolator (truth: scipy), for any data and
    # with smoothing; rows reproduce constants and affine fields exactly (degree-1 polynomial)
    from lungdeform.interior.interpolate import interpolation_weights

    s = icosphere(3, 50.0)
    u = rng.normal(size=s.vertices.shape)
    q = rng.uniform(-35, 35, size=(30, 3))
    for smoothing in (0.0, 5.0):
        w = interpolation_weights(s.vertices, q, smoothing=smoothing)
        ref = displacement_field(s.vertices, u, max_points=10**6, smoothing=smoothing)(q)
        assert w @ u == pytest.approx(ref, abs=1e-7)
    w = interpolation_weights(s.vertices, q)
    assert w.sum(axis=1) == pytest.approx(np.ones(len(q)), abs=1e-10)
    assert w @ s.vertices == pytest.approx(q, abs=1e-8)
    with pytest.raises(InputError, match="max_points"):
        interpolation_weights(s.vertices, q, max_points=100)
    with pytest.raises(InputError, match="smoothing"):
        interpolation_weights(s.vertices, q, smoothing=-1.0)
