"""Sliding interpolation: the interior motion implied by the normal motion of a closed surface."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.mesh import Surface, icosphere
from lungdeform.sliding import checked_operator, sliding_field, sliding_weights, surface_weights


def _blob() -> Surface:
    # a closed surface with no symmetry (every affine motion changes its normal motion)
    s = icosphere(3, 1.0)
    u = s.vertices
    r = 50.0 * (1 + 0.25 * u[:, 0] * u[:, 1] + 0.2 * u[:, 2] ** 3 + 0.15 * u[:, 0])
    return Surface(u * r[:, None] * np.array([1.0, 0.8, 1.2]), s.faces)


A = np.array([[0.05, 0.01, 0.0], [0.0, -0.02, 0.03], [0.01, 0.0, 0.1]])
B = np.array([1.0, -2.0, 3.0])


@pytest.mark.parametrize("smoothing", [0.0, 100.0])
def test_any_affine_motion_is_reproduced(rng, smoothing):
    # truth: an affine field has zero bending energy and matches every normal datum, so it is the
    # interpolant, smoothed or not (the polynomial part), at any point inside
    s = _blob()
    field = sliding_field(s.vertices, s.vertex_normals, s.vertices @ A.T + B, smoothing=smoothing)
    q = rng.uniform(-15, 15, size=(40, 3))
    assert field(q) == pytest.approx(q @ A.T + B, abs=1e-8)


def test_tangential_motion_is_ignored(rng):
    # only the normal motion counts: adding any tangential field to the surface data changes nothing
    s = _blob()
    n = s.vertex_normals
    u = s.vertices @ A.T + B
    t = rng.normal(size=u.shape)
    t -= np.einsum("ij,ij->i", t, n)[:, None] * n
    q = rng.uniform(-15, 15, size=(20, 3))
    assert sliding_field(s.vertices, n, u + 5.0 * t)(q) == pytest.approx(sliding_field(s.vertices, n, u)(q), abs=1e-8)


def test_rotation_of_a_sphere_moves_nothing(rng):
    # a sphere turning about its centre has no normal motion: it is invisible, so no interior motion
    # (the rotations are left out of the polynomial part instead of making the system singular)
    s = icosphere(3, 50.0)
    w = np.array([[0.0, -0.1, 0.05], [0.1, 0.0, -0.02], [-0.05, 0.02, 0.0]])
    field = sliding_field(s.vertices, s.vertex_normals, s.vertices @ w.T)
    assert np.abs(field(rng.uniform(-30, 30, size=(30, 3)))).max() < 0.01


def test_normal_motion_is_matched_at_the_surface():
    # without smoothing the field interpolates the normal motion at every sample point (truth: the data)
    s = _blob()
    n = s.vertex_normals
    u = 3.0 * np.sin(s.vertices / 20.0)
    v = sliding_field(s.vertices, n, u, smoothing=0.0)(s.vertices)
    assert np.einsum("ij,ij->i", v, n) == pytest.approx(np.einsum("ij,ij->i", u, n), abs=1e-6)


def test_operator_equals_the_field(rng):
    # dense reference: the operator form and the fitted field are one interpolant (any data, any
    # smoothing), and row subsets of the operator are the same map for fewer queries
    s = _blob()
    u = rng.normal(size=s.vertices.shape)
    q = rng.uniform(-15, 15, size=(25, 3))
    for smoothing in (0.0, 50.0):
        w = sliding_weights(s.vertices, s.vertex_normals, q, smoothing=smoothing)
        ref = sliding_field(s.vertices, s.vertex_normals, u, smoothing=smoothing, max_points=10**6)(q)
        assert w.shape == (25, s.n_vertices)
        assert w @ u == pytest.approx(ref, abs=1e-8)
        assert w[3:7] @ u == pytest.approx(ref[3:7], abs=1e-8)
    keep = np.arange(s.n_vertices) % 3 != 0
    w = surface_weights(s, q, keep)
    assert w.shape == (25, int(keep.sum()))
    assert w @ (s.vertices[keep] @ A.T + B) == pytest.approx(q @ A.T + B, abs=1e-8)


def test_bad_input():
    s = icosphere(1, 10.0)
    v, n = s.vertices, s.vertex_normals
    with pytest.raises(InputError, match="at least 13"):
        sliding_field(v[:5], n[:5], v[:5])
    with pytest.raises(InputError, match="unit length"):
        sliding_weights(v, 0.5 * n, v[:2])
    with pytest.raises(InputError, match="smoothing"):
        sliding_weights(v, n, v[:2], smoothing=-1.0)
    with pytest.raises(InputError, match="NaN"):
        sliding_weights(v, n, np.array([[np.nan, 0.0, 0.0]]))
    w = sliding_weights(v, n, v[:2])
    with pytest.raises(InputError, match="displacement has shape"):
        w @ v[:-1]
    with pytest.raises(InputError, match="landmark_matrix has shape"):
        checked_operator(w, (3, len(v)))
    assert checked_operator(w, (2, len(v))) is w


def test_default_field_matches_the_documented_formula(rng):
    # dense reference written from docs/MODEL_FORMAT.md, independently of the module: kernel −r,
    # λ = 100 mm, all 12 affine columns (the blob sees every affine direction, so none is dropped)
    s = _blob()
    p, n = s.vertices, s.vertex_normals
    u = 2.0 * np.sin(p / 25.0)
    k = len(p)
    c = p.mean(axis=0)
    h = np.abs(p - c).max()
    xh = np.hstack([np.ones((k, 1)), (p - c) / h])
    P = np.einsum("ic,il->icl", n, xh).reshape(k, 12)
    r = np.linalg.norm(p[:, None] - p[None], axis=2)
    a = np.block([[-r * (n @ n.T) + 100.0 * np.eye(k), P], [P.T, np.zeros((12, 12))]])
    sol = np.linalg.solve(a, np.concatenate([np.einsum("ij,ij->i", n, u), np.zeros(12)]))
    alpha, beta = sol[:k], sol[k:].reshape(3, 4)
    q = rng.uniform(-15, 15, size=(20, 3))
    rq = np.linalg.norm(q[:, None] - p[None], axis=2)
    ref = (-rq * alpha) @ n + np.hstack([np.ones((20, 1)), (q - c) / h]) @ beta.T
    assert sliding_field(p, n, u)(q) == pytest.approx(ref, abs=1e-8)


def test_operator_indexing_and_thinning(rng):
    # one query keeps its axis; the operator is not a matrix; above max_points the operator and the
    # field use the same seeded subset (one interpolant), the other points get zero weight
    s = _blob()
    u = rng.normal(size=s.vertices.shape)
    q = rng.uniform(-15, 15, size=(6, 3))
    w = sliding_weights(s.vertices, s.vertex_normals, q, max_points=200)
    assert w[2].shape == (1, s.n_vertices) and w[2] @ u == pytest.approx((w @ u)[2:3], abs=1e-12)
    with pytest.raises(InputError, match="rows"):
        w[:, :3]
    with pytest.raises(InputError, match="not a matrix"):
        np.asarray(w)
    field = sliding_field(s.vertices, s.vertex_normals, u, max_points=200)
    assert len(field.points) == 200 and int((np.abs(w.weights).sum(axis=(0, 1)) > 0).sum()) == 200
    assert w @ u == pytest.approx(field(q), abs=1e-8)
