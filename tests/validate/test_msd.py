"""Tests of the mass–spring–damper reference model (lungdeform.validate.msd)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.geometry.mesh import icosphere
from lungdeform.model.graph import spring_graph
from lungdeform.model.solve import ForceSolver
from lungdeform.model.transfer import green_matrix, local_transfer
from lungdeform.validate.msd import (
    MSDIntegrator,
    highest_frequency_bound,
    integrate_to_rest,
    lowest_frequency,
    spring_network,
    transfer_network,
)


def _sphere_graph(subdivisions=1, radius=30.0):
    s = icosphere(subdivisions, radius)
    return spring_graph(s.vertices, s.edges)


def test_two_springs_in_series_match_the_analytic_rest_state():
    # Truth: node 0 is grounded by k1, node 1 hangs from node 0 by k2 and is pulled by F.
    # Springs in series: u0 = F/k1, u1 = F/k1 + F/k2.
    k1, k2, force = 3.0, 0.5, 2.0
    net = spring_network([[0, 1]], [k2], [k1, 0.0], mass=[1.0, 2.5])
    res = integrate_to_rest(net, np.array([0.0, force]), tol=1e-11)
    np.testing.assert_allclose(res.displacement, [force / k1, force / k1 + force / k2], rtol=1e-9)
    # a real time integration: many steps, simulated time = steps·dt, velocity gone at rest
    assert res.steps > 10
    assert res.time == pytest.approx(res.steps * res.dt)
    assert res.residual <= 1e-11 and res.kinetic_ratio <= 1e-22
    assert len(res.residual_history) == res.steps + 1 and res.residual_history[0] == 1.0


def test_columns_are_independent_problems_sharing_the_springs():
    # Truth: a 3-node chain with ground springs; rest state is K⁻¹ f, column by column (dense solve).
    net = spring_network([[0, 1], [1, 2]], [1.0, 2.0], [0.5, 0.0, 1.5])
    f = np.array([[1.0, 0.0], [0.0, -2.0], [0.5, 1.0]])
    k = net.stiffness_matrix.toarray()
    np.testing.assert_allclose(k, k.T)
    res = integrate_to_rest(net, f, tol=1e-11)
    np.testing.assert_allclose(res.displacement, np.linalg.solve(k, f), rtol=1e-9, atol=1e-12)


def test_transfer_network_is_the_inverse_of_the_greens_matrix_for_unit_modulus():
    # The lead's algebra: with E = 1, K = I + L (ground 1, links d_min/d) and G = K⁻¹ exactly.
    g = _sphere_graph(1)
    t = local_transfer(g, np.ones(g.n_mass))
    gm = green_matrix(t)
    k = transfer_network(g).stiffness_matrix.toarray()
    np.testing.assert_allclose(k @ gm, np.eye(g.n_nodes), atol=1e-12)
    # Equivalent sparse statement: K = (I − Qᵀ) diag(1/T_e[i→i]) (ForceSolver's matrix).
    solver = ForceSolver(t, "direct")
    k2 = (solver.matrix @ sparse.diags(1.0 / solver.keep)).toarray()
    np.testing.assert_allclose(k, k2, atol=1e-12)


def test_uniform_modulus_other_than_one_is_not_symmetric():
    # S = 1/E on mass nodes and E on spring nodes: only E = 1 makes S uniform, so K is symmetric
    # (an MSD) only then. Guard the docstring's caveat against a silent change of reading.
    g = _sphere_graph(0)
    kinv = np.linalg.inv(green_matrix(local_transfer(g, np.full(g.n_mass, 2.0))))
    assert np.abs(kinv - kinv.T).max() > 0.1


def test_msd_at_rest_equals_the_transfer_model_on_a_closed_surface(rng):
    # Truth: green_matrix (dense) for uniform E = 1; the MSD must reach it up to its tolerance.
    g = _sphere_graph(1)
    f = np.zeros(g.n_nodes)
    f[: g.n_mass] = rng.uniform(0.2, 1.0, g.n_mass)
    expected = green_matrix(local_transfer(g, np.ones(g.n_mass))) @ f
    res = MSDIntegrator(transfer_network(g)).run(f, tol=1e-10, reference=expected)
    err = np.abs(res.displacement - expected).max() / np.abs(expected).max()
    assert err < 1e-8
    assert res.error_history[-1] == pytest.approx(err)
    # force is conserved at rest: Σ u = Σ f because K = I + L and L has zero column sums
    assert res.displacement.sum() == pytest.approx(f.sum(), rel=1e-8)


def test_default_damping_is_critical_for_the_lowest_mode():
    # Truth: K = I + L with a connected graph has smallest eigenvalue exactly 1 (L·1 = 0), so with
    # unit masses ω_min = 1 and critical damping c = 2. Large graph: the sparse eigsh path.
    small, large = _sphere_graph(0), _sphere_graph(2)
    assert large.n_nodes > 400 > small.n_nodes
    for g in (small, large):
        net = transfer_network(g)
        assert lowest_frequency(net) == pytest.approx(1.0, rel=1e-8)
        integ = MSDIntegrator(net)
        assert integ.damping == pytest.approx(2.0, rel=1e-8)
        assert integ.dt == pytest.approx(0.9 * 2.0 / highest_frequency_bound(net))


def test_gershgorin_bound_covers_the_highest_frequency(rng):
    n = 30
    links = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < 0.2])
    net = spring_network(links, rng.uniform(0.1, 3.0, len(links)), rng.uniform(0.0, 1.0, n),
                         rng.uniform(0.5, 2.0, n))
    m = net.mass
    lam = np.linalg.eigvalsh(net.stiffness_matrix.toarray() / np.sqrt(np.outer(m, m)))
    assert np.sqrt(lam[-1]) <= highest_frequency_bound(net) * (1 + 1e-12)
    assert lowest_frequency(net) == pytest.approx(np.sqrt(lam[0]), rel=1e-8)


def test_undamped_network_never_settles():
    # No damping: energy is conserved by the symplectic step, so it never comes to rest.
    net = spring_network([[0, 1]], [1.0], [1.0, 1.0])
    with pytest.raises(ConvergenceError, match="did not settle"):
        MSDIntegrator(net, damping=0.0).run(np.array([1.0, 0.0]), max_steps=2000)


def test_too_large_a_time_step_blows_up():
    net = spring_network([[0, 1]], [1.0], [1.0, 1.0])
    with pytest.raises(ConvergenceError, match="blew up"):
        MSDIntegrator(net, dt=5.0, damping=0.1).run(np.array([1.0, 0.0]), max_steps=5000)


def test_zero_force_is_at_rest_immediately():
    net = spring_network([[0, 1]], [1.0], [1.0, 1.0])
    res = integrate_to_rest(net, np.zeros(2))
    assert res.steps == 0 and not res.displacement.any()


def test_bad_inputs_are_refused():
    net = spring_network([[0, 1]], [1.0], [1.0, 1.0])
    with pytest.raises(InputError, match="force must have shape"):
        integrate_to_rest(net, np.ones(3))
    with pytest.raises(InputError, match="NaN"):
        integrate_to_rest(net, np.array([np.nan, 0.0]))
    with pytest.raises(InputError, match="stiffness"):
        spring_network([[0, 1]], [-1.0], [1.0, 1.0])
    with pytest.raises(InputError, match="anchored"):
        spring_network([[0, 1]], [1.0], [0.0, 0.0])
    with pytest.raises(InputError, match="outside"):
        spring_network([[0, 2]], [1.0], [1.0, 1.0])
