"""Interior field: surface-driven sliding motion plus the landmark correction."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import icosphere
from lungdeform.interior.field import LandmarkCorrection, correction_per_unit, interior_field


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

    field = interior_field(s.vertices, np.zeros_like(s.vertices), LandmarkCorrection(lm, slide(lm), 0.0),
                           normals=s.vertex_normals)
    assert field.corrected
    assert field.displacement(lm) == pytest.approx(slide(lm), abs=1e-6)
    q = _inside(rng, 50, 30.0)
    err = np.linalg.norm(field.displacement(q) - slide(q), axis=1)
    assert err.mean() < 0.2 * np.linalg.norm(slide(q), axis=1).mean()


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
        interior_field(v, v, LandmarkCorrection(v[:3], v[:3]), normals=n, kind="sliding_thin_plate")
    with pytest.raises(InputError, match="values must be finite with the anchors' shape"):
        interior_field(v, v, LandmarkCorrection(v[:3], v[:2]), normals=n)
    with pytest.raises(InputError, match="smoothing"):
        interior_field(v, v, LandmarkCorrection(smoothing=-1.0), normals=n)
    with pytest.raises(InputError, match="interior kind"):
        interior_field(v, v, normals=n, kind="spline")
    with pytest.raises(InputError, match="NaN"):
        interior_field(v, v, normals=n).displacement(np.array([[np.nan, 0.0, 0.0]]))
