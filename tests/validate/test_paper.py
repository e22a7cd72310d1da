"""Tests of the paper's validation experiments (lungdeform.validate.paper; Sec. IV-A, Figs. 7–9)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.model.transfer import green_matrix, local_transfer
from lungdeform.validate import paper as P


@pytest.fixture(scope="module")
def planar():
    return P.planar_experiment(9, 9, 3.0)


@pytest.fixture(scope="module")
def circular():
    return P.circular_experiment(4, 3.0)


def test_planar_mesh_is_a_regular_triangulated_grid():
    v, f = P.planar_mesh(4, 3, 2.0)
    assert v.shape == (12, 3) and f.shape == (2 * 3 * 2, 3)
    assert np.all(v[:, 2] == 0)
    # every triangle is half a 2 mm square, counter-clockwise seen from +z
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    np.testing.assert_allclose(np.cross(e1, e2)[:, 2], 4.0)


def test_bending_force_is_a_dome_zero_on_the_border():
    v, _ = P.planar_mesh(9, 9, 3.0)
    f = P.bending_force(v)
    border = (v[:, 0] == 0) | (v[:, 1] == 0) | (v[:, 0] == 24) | (v[:, 1] == 24)
    assert np.all(f[border] == 0) and np.all(f[~border] > 0)
    assert f.max() == pytest.approx(1.0) and np.argmax(f) == 40  # the centre vertex


def test_planar_msd_matches_the_transfer_model_within_the_papers_figure(planar):
    # The paper: < 0.1 % RMS. The MSD (a time integration) and the transfer model (a sparse solve
    # and the push loop) share one fixed point for uniform E = 1, so we expect integration tolerance.
    assert planar.rms_percent < 0.1
    assert planar.rms_percent < 1e-6
    assert planar.rms_percent_push < 1e-5
    assert planar.msd.steps > 10  # it really was integrated
    # truth independent of ForceSolver: the dense Green's matrix
    n = len(planar.vertices)
    g = P.mesh_graph(planar.vertices, planar.faces)
    dense = green_matrix(local_transfer(g, np.ones(n)))[:, :n] @ planar.force
    assert P.rms_percent(dense[:n], planar.msd_displacement[:n]) < 1e-6
    # force is conserved: everything applied is kept somewhere
    assert planar.transfer_displacement.sum() == pytest.approx(planar.force.sum(), rel=1e-10)
    assert planar.push_displacement.sum() == pytest.approx(planar.force.sum(), rel=1e-8)
    # the dome: the centre moves most
    assert np.argmax(planar.transfer_displacement[:n]) == 40


def test_planar_agreement_holds_when_d_min_clips_the_links():
    # spacing 1 mm < 2·d_min: every link is clipped to d_min; the MSD uses the same weights.
    res = P.planar_experiment(7, 7, 1.0)
    assert res.rms_percent < 1e-6


def test_circular_stiff_nodes_move_less_and_every_node_moves_outward(circular):
    c = circular
    assert c.stiff_to_soft_displacement_ratio < 1
    assert c.position_controlled_ratio < 1
    assert c.min_radial_displacement > 0
    rim = np.arange(1, len(c.vertices))
    outward = np.einsum("ij,ij->i", c.displacement[rim], c.vertices[rim])
    assert np.all(outward > 0)
    assert not c.displacement[0].any()  # the centre has no radius to move along
    assert np.all(c.moduli[c.stiff].min() > c.moduli[c.soft].max())
    assert c.correlation_log_modulus < -0.5


def test_circular_with_random_moduli(rng):
    c = P.circular_experiment(4, 3.0, pattern="random", rng=rng)
    assert c.stiff_to_soft_displacement_ratio < 1 and c.position_controlled_ratio < 1
    assert c.min_radial_displacement > 0


def test_circular_mesh_is_a_disc_of_rings():
    v, f = P.circular_mesh(3, 2.0)
    assert len(v) == 1 + 6 + 12 + 18
    r = np.linalg.norm(v[:, :2], axis=1)
    np.testing.assert_allclose(np.sort(np.unique(np.round(r, 9))), [0, 2, 4, 6])
    p = v[f]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]
    assert np.all(cross > 0)
    # the triangles tile the 18-gon exactly
    hexagon = 0.5 * 18 * 6.0**2 * np.sin(2 * np.pi / 18)
    assert 0.5 * cross.sum() == pytest.approx(hexagon)


def test_convergence_push_reaches_the_tolerance_and_both_are_reported():
    res = P.convergence_experiment(9, 9, 3.0, tol=1e-6, curve_tol=1e-10)
    assert res.push_history[-1] <= 1e-10 and res.push_history[0] == pytest.approx(1.0)
    assert res.msd_residual_history[-1] <= 1e-10 and res.msd_error_history[-1] < 1e-8
    assert 0 < res.push_iterations and 0 < res.msd_iterations < len(res.msd_residual_history)
    # the counts are where each curve crosses tol
    assert res.msd_residual_history[res.msd_iterations] <= 1e-6
    assert res.push_history_sweeps[-1] > res.push_sweeps
    d = res.to_dict()
    assert d["push_sweeps"] == pytest.approx(res.push_iterations / res.n_nodes)
    assert d["msd_node_updates"] == res.msd_iterations * res.n_nodes
    assert "sweeps" in d["definition"]


def test_bad_parameters_are_refused():
    with pytest.raises(InputError, match="nx"):
        P.planar_mesh(1, 5)
    with pytest.raises(InputError, match="pattern"):
        P.circular_experiment(3, pattern="stripes")
    with pytest.raises(InputError, match="curve_tol"):
        P.convergence_experiment(5, 5, tol=1e-12, curve_tol=1e-6)
