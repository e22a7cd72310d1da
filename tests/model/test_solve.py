"""Push iteration (12)–(14) against the sparse fixed point and the dense Green's matrix."""

import numpy as np
import pytest

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.geometry.mesh import icosphere
from lungdeform.model.graph import spring_graph
from lungdeform.model.solve import ForceSolver, push, solve_force
from lungdeform.model.transfer import green_matrix, local_transfer


@pytest.fixture
def system(rng):
    s = icosphere(2, 70.0)
    g = spring_graph(s.vertices, s.edges)
    t = local_transfer(g, rng.uniform(0.3, 3.0, s.n_vertices))
    f = rng.uniform(0.0, 1.0, s.n_vertices)
    return g, t, f


def test_push_conserves_force_and_converges(system):
    g, t, f = system
    r = push(t, f, tol=1e-12, record_every=10)
    # Conservation invariant: ΣC + ΣP = Σf.
    assert abs(r.kept.sum() + r.remaining.sum() - f.sum()) < 1e-10 * f.sum()
    assert np.abs(r.remaining).max() <= 1e-12 * f.max()
    # history is the convergence curve: it ends below the tolerance and decreases overall
    assert r.history[-1] <= 1e-12 * f.max() and r.history[0] == pytest.approx(f.max())


@pytest.mark.parametrize("method", ["bicgstab", "gmres", "direct"])
def test_sparse_solve_agrees_with_push(system, method):
    # docs/METHOD_NOTES.md §4: sparse solve and push loop agree to ≤ 1e-6 relative.
    g, t, f = system
    ref = push(t, f, tol=1e-13).kept
    c = ForceSolver(t, method).solve(f)
    assert np.abs(c - ref).max() <= 1e-6 * np.abs(ref).max()


def test_sparse_solve_agrees_with_dense_green(system):
    g, t, f = system
    fn = np.zeros(g.n_nodes)
    fn[: len(f)] = f
    assert np.allclose(solve_force(t, f), green_matrix(t) @ fn, rtol=1e-9, atol=1e-12)


def test_signed_forces_are_pushed_by_magnitude(system, rng):
    # An inverse fit may produce negative forces: the loop must still converge and conserve.
    g, t, f = system
    f2 = f - 0.5
    r = push(t, f2, tol=1e-12)
    assert np.abs(r.kept - ForceSolver(t).solve(f2)).max() < 1e-9


def test_linearity_lets_fields_be_combined(system, rng):
    # The solver is linear in f: the basis trick (4 precomputed fields) relies on it.
    g, t, f = system
    fs = ForceSolver(t)
    f2 = rng.uniform(size=len(f))
    assert np.allclose(fs.solve(2 * f + 3 * f2), 2 * fs.solve(f) + 3 * fs.solve(f2), rtol=1e-9)


def test_non_convergence_raises(system):
    g, t, f = system
    with pytest.raises(ConvergenceError):
        push(t, f, tol=1e-12, max_pushes=10)
    with pytest.raises(ConvergenceError):
        ForceSolver(t, "bicgstab", maxiter=1, tol=1e-15).solve(f)


def test_custom_linear_solver_is_used(system):
    from scipy.sparse.linalg import spsolve

    g, t, f = system
    calls = []

    def mine(a, b):
        calls.append(a.shape)
        return spsolve(a.tocsc(), b)

    c = ForceSolver(t, mine).solve(f)
    assert calls and np.allclose(c, ForceSolver(t).solve(f), rtol=1e-9)


def test_bad_force_rejected(system):
    g, t, f = system
    with pytest.raises(InputError, match="NaN"):
        ForceSolver(t).solve(np.full(len(f), np.nan))
    with pytest.raises(InputError, match="method"):
        ForceSolver(t, "magic").solve(f)


@pytest.mark.parametrize("method", ["bicgstab", "direct"])
def test_spring_node_elimination_is_exact(system, method, rng):
    # Eliminating spring nodes (Schur complement) must give the same kept force on every node,
    # including when a force is applied on spring nodes too.
    g, t, f = system
    full = ForceSolver(t, method)
    reduced = ForceSolver(t, method, n_mass=g.n_mass)
    assert reduced.n_mass == g.n_mass and reduced.matrix.shape == (g.n_mass, g.n_mass)
    f_all = rng.uniform(size=g.n_nodes)
    for applied in (f, f_all):
        assert np.allclose(reduced.solve(applied), full.solve(applied), rtol=1e-9, atol=1e-13)


def test_history_is_bounded_on_long_runs(system):
    # A long push run keeps at most 65 536 history samples (memory stays bounded at any size);
    # the recording interval grows instead, and the samples still describe the whole run.
    g, t, f = system
    r = push(t, f, tol=1e-12, record_every=1)
    assert len(r.history) <= 65536
    assert r.record_every >= 1 and (len(r.history) - 1) * r.record_every <= r.pushes + r.record_every
