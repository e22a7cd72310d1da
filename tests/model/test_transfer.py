"""Local transfer (8)–(9) and the Green's matrix: invariants and a hand-computed case."""

import numpy as np
import pytest

from lungdeform.geometry.mesh import icosphere
from lungdeform.model.graph import spring_graph
from lungdeform.model.transfer import compliance, full_transfer, green_matrix, local_transfer, split_transfer


def _graph(k=2, r=60.0):
    s = icosphere(k, r)
    return s, spring_graph(s.vertices, s.edges)


def test_rows_sum_to_one_with_heterogeneous_stiffness(rng):
    # Every node hands on exactly what it receives: rows of T_e sum to 1 (paper eq. (3)).
    s, g = _graph()
    t = local_transfer(g, rng.uniform(0.2, 5.0, s.n_vertices))
    assert np.allclose(np.asarray(t.sum(axis=1)).ravel(), 1.0, atol=1e-14)
    assert np.all(t.data > 0)


def test_hand_computed_single_edge():
    # Two mass nodes 4 mm apart -> one spring node in the middle, 2 mm from each.
    # For mass node 0 (E=2, S=1/2): clique = {0, spring}; weights S/d: self (1/2)/1, spring E=1.5/2.
    v = np.array([[0.0, 0, 0], [4.0, 0, 0], [0, 0, 0]])[:2]
    g = spring_graph(v, np.array([[0, 1]]))
    t = local_transfer(g, np.array([2.0, 1.0]), d_min=1.0).toarray()
    w_self, w_spring = 0.5 / 1.0, 1.5 / 2.0
    assert t[0, 0] == pytest.approx(w_self / (w_self + w_spring))
    assert t[0, 2] == pytest.approx(w_spring / (w_self + w_spring))
    # spring node (S=E=1.5): neighbours S=1/2 and S=1 at 2 mm, self 1.5 at d_min
    w = np.array([0.5 / 2, 1.0 / 2, 1.5 / 1])
    assert np.allclose(t[2], w / w.sum())
    assert np.allclose(compliance(np.array([2.0, 1.0, 1.5]), 2), [0.5, 1.0, 1.5])


def test_d_min_clamps_short_distances():
    # With all links shorter than d_min, distances no longer matter: uniform E gives equal shares.
    s = icosphere(1, 0.5)
    g = spring_graph(s.vertices, s.edges)
    t = local_transfer(g, np.ones(s.n_vertices), d_min=1.0).toarray()
    spring_row = t[g.n_mass]
    assert np.allclose(spring_row[spring_row > 0], 1 / 3)


def test_green_matrix_conserves_force_and_matches_fixed_point(rng):
    # Columns of G sum to 1: a unit force at any node is fully kept somewhere (conservation).
    s, g = _graph(1)
    t = local_transfer(g, rng.uniform(0.5, 2.0, s.n_vertices))
    gm = green_matrix(t)
    assert np.allclose(gm.sum(axis=0), 1.0, atol=1e-12)
    assert np.all(gm >= -1e-15)
    # G is the fixed point: C = diag(keep) x with x = f + Qᵀx.
    keep, q = split_transfer(t)
    f = rng.uniform(size=g.n_nodes)
    c = gm @ f
    x = c / keep
    assert np.allclose(x, f + q.T @ x)


def test_full_transfer_eq7():
    s, g = _graph(1)
    t = local_transfer(g, np.ones(s.n_vertices))
    f = np.zeros(g.n_nodes)
    f[: g.n_mass] = 1.0
    kept = green_matrix(t) @ f
    tt = full_transfer(t, kept, f).toarray()
    assert np.allclose(tt[: g.n_mass].sum(axis=1), kept[: g.n_mass])  # row j scaled by F[j]/f[j]
    assert np.allclose(tt[g.n_mass:], 0)  # no applied force on spring nodes
