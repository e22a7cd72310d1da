"""Solid moments of closed surfaces against the analytic moments of an ellipsoid."""

import numpy as np
import pytest

from lungdeform.errors import MeshError
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.geometry.moments import solid_moments


def _ellipsoid(axes, center, subdivisions=5):
    s = icosphere(subdivisions)
    return Surface(s.vertices * np.asarray(axes) + np.asarray(center), s.faces)


def test_ellipsoid_moments_match_the_analytic_ones():
    # a solid ellipsoid with semi-axes a, b, c has volume 4/3 π a b c, its centroid at its centre and
    # covariance diag(a², b², c²) / 5; the polyhedron inscribed in it is slightly smaller (about 0.3 %
    # of the volume at 5 subdivisions), hence the tolerances
    axes, center = np.array([40.0, 60.0, 90.0]), np.array([-80.0, 120.0, -300.0])
    s = _ellipsoid(axes, center)
    vol, mu, cov = solid_moments(s.vertices, s.faces)
    assert vol == pytest.approx(4.0 / 3.0 * np.pi * axes.prod(), rel=5e-3)
    np.testing.assert_allclose(mu, center, atol=1e-6)
    np.testing.assert_allclose(np.diag(cov), axes**2 / 5.0, rtol=1e-2)
    assert np.abs(cov - np.diag(np.diag(cov))).max() < 1e-6 * axes.max() ** 2


def test_volume_equals_the_divergence_theorem_volume(rng):
    # the zeroth moment is the mesh's own enclosed volume, whatever the shape
    s = _ellipsoid([30.0, 50.0, 70.0], rng.normal(size=3) * 50, subdivisions=3)
    moved = Surface(s.vertices + rng.normal(scale=1.0, size=s.vertices.shape), s.faces)
    assert solid_moments(moved.vertices, moved.faces)[0] == pytest.approx(moved.volume, rel=1e-12)


def test_rotated_solid_has_the_rotated_covariance(rng):
    # covariance transforms as R C Rᵀ under a rotation about the centroid
    s = _ellipsoid([20.0, 45.0, 80.0], [0.0, 0.0, 0.0], subdivisions=4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    _, _, cov = solid_moments(s.vertices, s.faces)
    _, _, cov_r = solid_moments(s.vertices @ q.T, s.faces)
    np.testing.assert_allclose(cov_r, q @ cov @ q.T, atol=1e-8 * 80.0**2)


def test_inward_facing_surface_is_refused():
    # reversed faces enclose a negative volume: no solid to take moments of
    s = icosphere(2, radius=10.0)
    with pytest.raises(MeshError, match="encloses"):
        solid_moments(s.vertices, s.faces[:, ::-1])
