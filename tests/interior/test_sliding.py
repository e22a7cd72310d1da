"""Sliding interpolation: the interior motion implied by the normal motion of a closed surface."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.interior.sliding import checked_operator, sliding_field, sliding_weights, surface_weights


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


def test_correction_moves_the_anchors_and_not_the_boundary(rng):
    # truth, from its definition: without smoothing the correction interpolates the anchors' values
    # exactly and has zero normal motion at every surface sample; a thin-plate spline through the
    # same values moves the boundary (what the sliding correction is for)
    from lungdeform.interior.interpolate import displacement_field
    from lungdeform.interior.sliding import sliding_correction

    s = _blob()
    n = s.vertex_normals
    q = rng.uniform(-20, 20, size=(15, 3))
    values = rng.normal(size=(15, 3))
    field = sliding_correction(s.vertices, n, q, values, smoothing=0.0)
    assert field(q) == pytest.approx(values, abs=1e-8)
    assert np.abs(np.einsum("ij,ij->i", field(s.vertices), n)).max() < 1e-6
    tps = displacement_field(q, values, max_points=15)(s.vertices)
    assert np.abs(np.einsum("ij,ij->i", tps, n)).mean() > 0.1
    # smoothed, the boundary moves a little (soft), the anchors still exactly
    soft = sliding_correction(s.vertices, n, q, values, smoothing=100.0)
    assert soft(q) == pytest.approx(values, abs=1e-8)
    assert 1e-6 < np.abs(np.einsum("ij,ij->i", soft(s.vertices), n)).mean() < np.abs(np.einsum("ij,ij->i", tps, n)).mean()


def test_correction_solver_equals_the_dense_field(rng):
    # dense reference: the solver's Schur-complement prediction for any subset of the anchors is
    # the field solved directly through that subset, also when the surface is thinned
    from lungdeform.interior.sliding import CorrectionSolver, sliding_correction

    s = _blob()
    n = s.vertex_normals
    q = rng.uniform(-20, 20, size=(20, 3))
    values = rng.normal(size=(20, 3))
    for max_points in (4000, 300):
        solver = CorrectionSolver(s.vertices, n, q, smoothing=50.0, max_points=max_points, seed=2)
        train, test = rng.permutation(20)[:14], np.arange(20)[:6]
        ref = sliding_correction(s.vertices, n, q[train], values[train], smoothing=50.0, max_points=max_points, seed=2)
        assert solver.predict(train, values[train], test) == pytest.approx(ref(q[test]), abs=1e-9)
    with pytest.raises(InputError, match="anchor indices"):
        solver.predict([0, 25], values[:2], [1])
    with pytest.raises(InputError, match="one row per train anchor"):
        solver.predict([0, 1], values[:3], [2])
    with pytest.raises(InputError, match="anchors"):
        CorrectionSolver(s.vertices, n, np.full((2, 3), np.nan))
    with pytest.raises(InputError, match="landmarks. 2 and 4 coincide"):
        CorrectionSolver(s.vertices, n, q[[0, 1, 2, 1]])
    with pytest.raises(InputError, match="coincide"):
        sliding_correction(s.vertices, n, q[[0, 1, 2, 1]], values[:4])


def test_correction_solvers_for_smoothings_and_their_surface_weights(rng):
    # dense references: each solver of for_smoothings (shared blocks) predicts as the field solved
    # directly through the subset at its smoothing; its surface_weights are sliding_weights from the
    # (thinned) surface to the anchors, the same interpolant (same system, same columns)
    from lungdeform.interior.sliding import CorrectionSolver, sliding_correction, sliding_weights

    s = _blob()
    n = s.vertex_normals
    q = rng.uniform(-20, 20, size=(15, 3))
    values = rng.normal(size=(15, 3))
    train, test = rng.permutation(15)[:10], np.arange(15)[:5]
    solvers = CorrectionSolver.for_smoothings(s.vertices, n, q, (30.0, 300.0), max_points=250, seed=1)
    assert sorted(solvers) == [30.0, 300.0]
    u = rng.normal(size=s.vertices.shape)
    for lam, solver in solvers.items():
        ref = sliding_correction(s.vertices, n, q[train], values[train], smoothing=lam, max_points=250, seed=1)
        assert solver.predict(train, values[train], test) == pytest.approx(ref(q[test]), abs=1e-9)
        w = sliding_weights(s.vertices, n, q, smoothing=lam, max_points=250, seed=1)
        assert solver.surface_weights() @ u == pytest.approx(w @ u, abs=1e-9)
    assert np.abs(solvers[30.0].predict(train, values[train], test) - solvers[300.0].predict(train, values[train], test)).max() > 1e-3


def test_correction_matches_the_documented_formula(rng):
    # dense reference written from docs/MODEL_FORMAT.md ("landmark correction"), independently of
    # the module: kernel −r per component at the landmarks, −r n_j at the surface, zero normal data
    # with smoothing λ', the landmark values exactly, all 12 affine columns (the blob sees them all)
    from lungdeform.interior.sliding import sliding_correction

    s = _blob()
    p, n = s.vertices, s.vertex_normals
    k, m, lam = len(p), 8, 40.0
    q = rng.uniform(-20, 20, size=(m, 3))
    cval = rng.normal(size=(m, 3))
    c = p.mean(axis=0)
    h = np.abs(p - c).max()

    def xhat(x):
        return np.hstack([np.ones((len(x), 1)), (x - c) / h])

    rpp = np.linalg.norm(p[:, None] - p[None], axis=2)
    rpq = np.linalg.norm(p[:, None] - q[None], axis=2)
    rqq = np.linalg.norm(q[:, None] - q[None], axis=2)
    # unknowns: γ (k), β (m × 3, row i = β_i), affine (3 × 4); equations: surface, landmarks, orthogonality
    a = np.zeros((k + 3 * m + 12, k + 3 * m + 12))
    a[:k, :k] = -rpp * (n @ n.T) + lam * np.eye(k)
    for comp in range(3):
        cols = k + 3 * np.arange(m) + comp
        a[:k, cols] = -rpq * n[:, [comp]]  # n_j · (φ(|p_j − q_i|) e_comp)
        a[cols, :k] = (-rpq * n[:, [comp]]).T
        a[np.ix_(cols, cols)] = -rqq
        a[:k, k + 3 * m + 4 * comp:k + 3 * m + 4 * comp + 4] = n[:, [comp]] * xhat(p)
        a[cols, k + 3 * m + 4 * comp:k + 3 * m + 4 * comp + 4] = xhat(q)
    a[k + 3 * m:, :k + 3 * m] = a[:k + 3 * m, k + 3 * m:].T
    sol = np.linalg.solve(a, np.concatenate([np.zeros(k), cval.ravel(), np.zeros(12)]))
    gamma, beta, aff = sol[:k], sol[k:k + 3 * m].reshape(m, 3), sol[k + 3 * m:].reshape(3, 4)
    x = rng.uniform(-25, 25, size=(15, 3))
    rxp = np.linalg.norm(x[:, None] - p[None], axis=2)
    rxq = np.linalg.norm(x[:, None] - q[None], axis=2)
    ref = (-rxp * gamma) @ n + (-rxq) @ beta + xhat(x) @ aff.T
    assert sliding_correction(p, n, q, cval, smoothing=lam)(x) == pytest.approx(ref, abs=1e-8)


def test_fused_kernel_sum_equals_the_design_matrix(rng):
    # reference: the design matrix (3, q, k + 3a + r) @ coefficients, the field's definition; the
    # kernel sum regroups the same terms per centre, so they agree to rounding. A surface field plus
    # its correction (InteriorField.radial) shares the surface points: their merged sum is the sum
    from lungdeform.interior.field import InteriorField
    from lungdeform.interior.sliding import _design, sliding_correction

    s = _blob()
    n = s.vertex_normals
    surface = sliding_field(s.vertices, n, rng.normal(size=(s.n_vertices, 3)), smoothing=30.0)
    corr = sliding_correction(s.vertices, n, rng.uniform(-20, 20, (6, 3)), rng.normal(size=(6, 3)), smoothing=50.0)
    x = rng.uniform(-40, 40, size=(300, 3))
    for f in (surface, corr):
        ref = (_design(f.points, f.normals, x, f.center, f.scale, f.basis, f.anchors) @ f.coefficients).T
        assert f(x) == pytest.approx(ref, abs=1e-9)
    both = InteriorField(surface, corr)
    assert both.radial.centres.shape[1] == s.n_vertices + 6  # the shared surface points merged
    assert both.displacement(x) == pytest.approx(surface(x) + corr(x), abs=1e-9)


def test_correction_solver_without_smoothing_equals_the_dense_saddle_solve(rng):
    # dense reference: the (k + 3a + r)^2 saddle system solved by LU (sliding_correction); the solver
    # factors the projected surface block by Cholesky instead (positive definite on the polynomial
    # block's null space), also at smoothing 0 where the kernel block alone is indefinite
    from lungdeform.interior.sliding import CorrectionSolver, sliding_correction

    s = _blob()
    n = s.vertex_normals
    q = rng.uniform(-20, 20, size=(12, 3))
    values = rng.normal(size=(12, 3))
    solver = CorrectionSolver.for_smoothings(s.vertices, n, q, (0.0,), max_points=200, seed=3)[0.0]
    train, test = np.arange(12)[3:], np.arange(12)[:3]
    ref = sliding_correction(s.vertices, n, q[train], values[train], smoothing=0.0, max_points=200, seed=3)
    assert np.abs(ref(q[test])).max() > 1e-2  # the correction reaches the held-out anchors
    assert solver.predict(train, values[train], test) == pytest.approx(ref(q[test]), abs=1e-9)
