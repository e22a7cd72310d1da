"""Force → response (model.response): the sparse solve against the dense Green's matrix, the
invariants of the transfer, the one-shot form, and the convergence failure."""

import numpy as np
import pytest

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.geometry.mesh import icosphere
from lungdeform.model.force import field_basis
from lungdeform.model.graph import spring_graph
from lungdeform.model.lung import build_lung
from lungdeform.model.response import RESPONSE_TOL, ResponseSolver, solve_response
from lungdeform.model.transfer import green_matrix, local_transfer


@pytest.fixture
def system(rng):
    s = icosphere(2, 70.0)
    e = rng.uniform(0.3, 3.0, s.n_vertices)
    return s, spring_graph(s.vertices, s.edges), e


@pytest.mark.parametrize("method", ["bicgstab", "gmres", "direct"])
def test_sparse_response_matches_the_dense_green_matrix(system, rng, method):
    # Truth independent of the sparse solver: the dense Green's matrix G = diag(keep)(I − Qᵀ)⁻¹
    # (transfer.green_matrix, one dense solve); the response to a force on the mass nodes is
    # G[:n, :n] f (spring nodes start at 0), exact to the solve's tolerance.
    s, g, e = system
    n = s.n_vertices
    f = rng.uniform(-1.0, 1.0, n)
    dense = green_matrix(local_transfer(g, e))
    solver = ResponseSolver(g, e, method=method)
    got = solver.response(f)
    assert got.shape == (n,)
    assert np.abs(got - dense[:n, :n] @ f).max() <= 1e-9 * np.abs(dense[:n, :n] @ f).max()
    # on all graph nodes, kept() is G f
    assert np.allclose(solver.kept(f), dense[:, :n] @ f, rtol=0, atol=1e-10)


def test_transfer_rows_sum_to_one_and_force_is_conserved(system, rng):
    # Invariants (paper (3), transfer module): every row of T_e sums to 1 (a node hands on all it
    # does not keep), so the kept force over all graph nodes equals the applied force, also with
    # heterogeneous stiffness and signed forces; the mass nodes keep part of it, the spring nodes
    # the rest.
    s, g, e = system
    solver = ResponseSolver(g, e)
    assert np.allclose(np.asarray(solver.transfer.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-14)
    assert np.all(solver.transfer.diagonal() > 0)
    f = rng.uniform(0.0, 1.0, s.n_vertices)
    kept = solver.kept(f)
    assert kept.sum() == pytest.approx(f.sum(), rel=1e-10)
    assert 0 < solver.response(f).sum() < f.sum()
    signed = rng.normal(size=s.n_vertices)
    assert solver.kept(signed).sum() == pytest.approx(signed.sum(), abs=1e-9 * np.abs(signed).sum())


def test_responses_are_linear_in_the_force(system, rng):
    # Truth: the solve is linear, which the model relies on to recombine the four fields
    # 1, x̂, ŷ, ẑ for any gravity (force module); responses() is response() row by row.
    s, g, e = system
    solver = ResponseSolver(g, e)
    fields = field_basis(rng.uniform(size=(s.n_vertices, 3)))
    basis = solver.responses(fields)
    assert basis.shape == (4, s.n_vertices)
    assert np.array_equal(basis[2], solver.response(fields[2]))
    w = np.array([0.3, -0.2, 0.9, 0.05])
    assert np.allclose(w @ basis, solver.response(w @ fields), rtol=0, atol=1e-11)


def test_one_shot_equals_the_solver_and_defaults_to_uniform(rng):
    # Truth: solve_response is ResponseSolver.from_surface(...).response(s); without a stiffness
    # it is the uniform field E = 1 (the reference tissue, stiffness.uniform).
    s = icosphere(1, 50.0)
    f = rng.uniform(size=s.n_vertices)
    one = solve_response(s, f)
    assert np.array_equal(one, ResponseSolver.from_surface(s).response(f))
    assert np.array_equal(one, solve_response(s, f, np.ones(s.n_vertices)))
    two = solve_response(s, np.stack([f, 2 * f]))
    assert two.shape == (2, s.n_vertices) and np.allclose(two[1], 2 * one, rtol=1e-10)


def test_build_lung_uses_the_response(left_lung):
    # Truth: the model's stored force basis is the response to the four fields (same solver,
    # same tolerance: identical numbers)
    model = build_lung(left_lung, "left")
    solver = ResponseSolver.from_surface(left_lung, model.stiffness)
    assert np.array_equal(model.force_basis, solver.responses(field_basis(model.frame.normalized(left_lung.vertices))))


def test_too_small_iteration_budget_raises(system, rng):
    # Truth: at the default tolerance (1e-12) one Krylov iteration is not enough on this graph
    # (tens are needed), so the solve must report it instead of returning a rough answer; a linear
    # solver that returns garbage fails the residual check the same way.
    s, g, e = system
    f = rng.uniform(size=s.n_vertices)
    assert RESPONSE_TOL == 1e-12
    with pytest.raises(ConvergenceError, match="did not converge in 1 iterations"):
        ResponseSolver(g, e, maxiter=1).response(f)
    with pytest.raises(ConvergenceError, match="residual"):
        ResponseSolver(g, e, method=lambda a, b: np.zeros_like(b)).response(f)
    # a generous budget converges, and a tighter tolerance is a parameter
    assert np.all(np.isfinite(ResponseSolver(g, e, tol=1e-13).response(f)))


def test_bad_stiffness_is_refused(system):
    s, g, e = system
    with pytest.raises(InputError, match=r"stiffness must have shape \(162,\)"):
        ResponseSolver(g, e[:-1])
    with pytest.raises(InputError, match="stiffness must be finite and > 0"):
        ResponseSolver(g, np.where(np.arange(len(e)) == 3, 0.0, e))
    with pytest.raises(InputError, match="d_min"):
        ResponseSolver(g, e, d_min=0.0)
