"""The deformable Coherent Point Drift of lungdeform.fit.cpd against pycpd's own iteration."""

from __future__ import annotations

import numpy as np
import pycpd
import pytest

from lungdeform.fit import cpd
from lungdeform.fit.cpd import deformable_cpd


@pytest.mark.parametrize("w, alpha, beta", [(0.05, 2.0, 2.0), (0.0, 1000.0, 0.8)])
def test_same_weights_and_iterations_as_pycpd(w, alpha, beta):
    # truth: pycpd.DeformableRegistration, the iteration it replaces; the row scaling equals
    # diag(P1) @ G exactly and the shifted E-step gives the same posteriors, so the weights agree to
    # rounding whatever the settings (the baselines' w = 0.05, alpha = 2; the correspondence field's w = 0, alpha = 1000)
    rng = np.random.default_rng(7)
    y = rng.normal(size=(120, 3))
    x = 1.1 * rng.normal(size=(140, 3)) + np.array([0.2, -0.1, 0.05])
    ref = pycpd.DeformableRegistration(X=x, Y=y, alpha=alpha, beta=beta, w=w, max_iterations=60, tolerance=1e-6)
    ref.register()
    got = deformable_cpd(x, y, alpha=alpha, beta=beta, w=w, max_iterations=60, tolerance=1e-6)
    assert got.shape == (120, 3) and np.abs(ref.W).max() > 1e-3  # it moved the points
    np.testing.assert_allclose(got, ref.W, rtol=1e-10, atol=1e-12)


def test_low_rank_m_step_moves_the_points_as_the_dense_solve():
    # truth: the dense M-step (the test above ties it to pycpd). The pivoted-Cholesky factor of the
    # kernel leaves a remainder whose diagonal is below the tolerance, so Woodbury's solve differs
    # from the dense one by about tolerance / (alpha sigma^2) relative: the moved points agree to
    # 1e-6 of their spread here (the correspondence field's settings on a lung-like cloud), and the
    # factor is much smaller than the kernel (a wide Gaussian has few large eigenvalues)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    y = u / np.linalg.norm(u, axis=1)[:, None] * [0.6, 0.8, 1.2]  # points on an ellipsoid, as on a lung
    x = 1.08 * y[rng.permutation(400)[:350]] + rng.normal(scale=0.02, size=(350, 3))
    kw = dict(alpha=1000.0, beta=0.8, w=0.0, max_iterations=80, tolerance=1e-7)
    dense = cpd.FastDeformable(X=x, Y=y, **kw)
    dense.register()
    low = cpd.FastDeformable(X=x, Y=y, rank_tolerance=1e-10, **kw)
    low.register()
    assert low._factor.shape[1] < 200 and low.iteration == dense.iteration
    moved = dense.G @ dense.W
    assert np.abs(moved).max() > 1e-2  # the field did something
    np.testing.assert_allclose(low.G @ low.W, moved, atol=1e-6 * np.ptp(y))


def test_kernel_factor_leaves_a_small_positive_remainder():
    # invariants of a pivoted Cholesky stopped at a tolerance: G - L L^T is positive semi-definite
    # with every diagonal entry below the tolerance
    rng = np.random.default_rng(5)
    u = rng.normal(size=(300, 3))
    p = u / np.linalg.norm(u, axis=1)[:, None]
    g = np.exp(-np.sum((p[:, None] - p[None]) ** 2, axis=2) / 2.0)
    f = cpd.kernel_factor(g, 1e-8)
    rest = g - f @ f.T
    assert f.shape[1] < 150 and np.diag(rest).max() < 1e-8
    assert np.linalg.eigvalsh(rest).min() > -1e-10


def test_first_variance_in_closed_form():
    # truth: pycpd's own starting variance (the explicit (M, N, D) sum)
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(50, 3)) + 3.0, rng.normal(size=(40, 3))
    assert np.isclose(cpd.first_variance(x, y), pycpd.emregistration.initialize_sigma2(x, y), rtol=1e-12)


@pytest.mark.parametrize("w, sigma2", [(0.0, 0.5), (0.05, 0.5), (0.0, 2e-3), (0.05, 2e-3)])
def test_shifted_e_step_equals_pycpds_dense_posteriors(w, sigma2):
    # truth: pycpd's own E-step (the dense (M, N) matrix P, unshifted); the shifted exponents give the
    # same P1, Pt1 and P @ X to rounding, here too where a small sigma^2 underflows most of exp(-a)
    rng = np.random.default_rng(11)
    y = rng.normal(size=(90, 3))
    x = y[rng.permutation(90)[:80]] + rng.normal(scale=0.05, size=(80, 3))
    ref = pycpd.DeformableRegistration(X=x, Y=y, alpha=2.0, beta=2.0, w=w, sigma2=sigma2)
    ref.expectation()
    got = cpd.FastDeformable(X=x, Y=y, alpha=2.0, beta=2.0, w=w, max_iterations=1, tolerance=1e-6)
    got.sigma2 = sigma2
    got.expectation()
    assert sigma2 > 1e-2 or np.mean(ref.P < 1e-300) > 0.5  # the small variance does underflow
    np.testing.assert_allclose(got.P1, ref.P1, rtol=1e-10, atol=1e-300)
    np.testing.assert_allclose(got.Pt1, ref.Pt1, rtol=1e-10)
    np.testing.assert_allclose(got._px, ref.P @ x, rtol=1e-10, atol=1e-300)


def test_e_step_of_a_column_far_from_every_point_is_its_limit():
    # truth: exact arithmetic. With w = 0 every target point's posteriors sum to 1 however far it lies
    # (sigma^2 so small that exp(-a) underflows to 0 for the whole column, where the unshifted E-step
    # gave that point no weight at all): the nearest source point takes it
    y = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    x = np.array([[0.01, 0, 0], [10, 0, 0]])
    reg = cpd.FastDeformable(X=x, Y=y, alpha=2.0, beta=2.0, w=0.0, max_iterations=1, tolerance=1e-6)
    reg.sigma2 = 1e-3
    reg.expectation()
    np.testing.assert_allclose(reg.Pt1, [1.0, 1.0], rtol=1e-12)
    np.testing.assert_allclose(reg.P1, [1.0, 1.0, 0.0, 0.0], atol=1e-12)
