"""A structure kept rigid inside a breathing field (lungdeform.playback.rigid) against analytic truth."""

import numpy as np
import pytest

from lungdeform.geometry.mesh import icosphere
from lungdeform.playback import displacement_field as D
from lungdeform.playback import rigid as RG


def _grid_and_expansion(s, c):
    shape = (40, 56, 56)
    grid = D.Grid(shape, np.array([1.5, 1.5, 2.0]), np.zeros(3), np.eye(3))
    k, j, i = np.indices(shape)
    x = grid.world(np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1))
    return grid, x.reshape(shape + (3,)), ((s - 1.0) * (x - c)).reshape(shape + (3,)).astype(np.float32)


def test_a_ball_in_a_uniform_expansion_moves_by_its_centre_and_keeps_its_volume():
    # why: under x → c + s(x − c) a ball at p inflates by s³ (+33 % for s = 1.1); its best rigid motion
    # is the translation (s − 1)(p − c) with no rotation, and the rigid field inside has Jacobian 1,
    # so the moved ball keeps its volume; beyond the border the field is untouched
    s, c, p, radius = 1.1, np.array([42.0, 42.0, 40.0]), np.array([45.0, 40.0, 38.0]), 9.0
    grid, x, u = _grid_and_expansion(s, c)
    ball = np.linalg.norm(x - p, axis=-1) <= radius
    result = D.FieldResult(u.copy(), False, 1.0, 1.0, {})
    rep = RG.rigid_field(result, grid, ball, border_mm=8.0)
    assert np.allclose(rep.motion.centroid, p, atol=0.05)  # the voxelised ball's centroid
    assert np.allclose(rep.motion.translation, (s - 1) * (rep.motion.centroid - c), atol=1e-4)
    assert np.allclose(rep.motion.rotation, np.eye(3), atol=1e-6)
    assert rep.elastic_ml == pytest.approx(s ** 3 * rep.volume_ml, rel=1e-3)
    assert abs(rep.rigid_ml / rep.volume_ml - 1) < 0.02
    jac = D.jacobian_determinant(result.field, grid.spacing, grid.direction)
    inner = np.linalg.norm(x - p, axis=-1) <= radius - 3
    assert np.allclose(jac[inner], 1.0, atol=1e-4) and jac.min() > 0
    far = np.linalg.norm(x - p, axis=-1) > radius + 8.0 + 3.0
    assert np.array_equal(result.field[far], u[far])


def test_the_inverse_field_keeps_the_structure_volume_too():
    # why: warp resamples through the inverse field w(y) = (1/s − 1)(y − c); the structure at the state
    # (where its voxels' sources lie in it) must measure its reference volume within 2 %, against s³
    s, c = 1.1, np.array([42.0, 42.0, 40.0])
    grid, x, _ = _grid_and_expansion(s, c)
    w = ((1.0 / s - 1.0) * (x - c)).astype(np.float32)
    sphere = icosphere(3, 9.0, center=(45.0, 40.0, 38.0))
    ball = RG.surface_mask(sphere.vertices, sphere.faces, grid)
    assert ball.sum() * 1.5 * 1.5 * 2.0 / 1000 == pytest.approx(4 / 3 * np.pi * 0.729, rel=0.05)  # 9 mm ball
    result = D.FieldResult(w, True, 1.0, 1.0, {})
    rep = RG.rigid_field(result, grid, ball)
    assert rep.elastic_ml == pytest.approx(s ** 3 * rep.volume_ml, rel=0.02)
    assert abs(rep.rigid_ml / rep.volume_ml - 1) < 0.02
    # at the state the ball sits at c + s(p − c); the inverse field there points back to p
    assert np.allclose(rep.motion.translation, (1 / s - 1) * (rep.motion.centroid - c), atol=0.05)
