"""The PV relation: integrator against analytic solutions (inversion: tests/breathing/test_inversion.py)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing import pv as br
from lungdeform.errors import InputError

NORMAL = br.BreathingParams(br.Mechanics(10.0, 2.5, 0.01), (0.5, 4.0, 2.0, -0.5, 1.0), period_s=4.0,
                            insp_fraction=0.4, decay=0.15, relaxation_ml=2400.0)


def test_first_order_step_matches_exponential():
    # truth: with I = 0 a pressure step P gives V(t) = P/E·(1 − exp(−t/τ)), τ = R/E
    mech = br.Mechanics(10.0, 2.5, 0.0)
    t = np.linspace(0.0, 2.0, 201)
    vol, flow = br.simulate_pressure(t, lambda _t: 5.0, mech)
    exact = 0.5 * (1.0 - np.exp(-t / 0.25))
    assert np.max(np.abs(vol - exact)) < 1e-6
    assert np.max(np.abs(flow - 2.0 * np.exp(-t / 0.25))) < 1e-4


def test_second_order_step_matches_closed_form():
    # truth: I·V'' + R·V' + E·V = P from rest; overdamped roots r1, r2 of I s² + R s + E
    mech = br.Mechanics(10.0, 2.5, 0.01)
    t = np.linspace(0.0, 1.5, 301)
    vol, _ = br.simulate_pressure(t, lambda _t: 5.0, mech)
    r1, r2 = np.roots([0.01, 2.5, 10.0])
    exact = 0.5 * (1.0 + (r2 * np.exp(r1 * t) - r1 * np.exp(r2 * t)) / (r1 - r2))
    assert np.max(np.abs(vol - exact)) < 1e-6


def test_sinusoidal_steady_state_matches_transfer_function():
    # truth: after the transient, V = Im(P̂/H(ω)·e^{iωt}) with H = E + iωR − ω²I
    mech = br.Mechanics(10.0, 2.5, 0.01)
    w = 2 * np.pi / 4.0
    t = np.linspace(0.0, 20.0, 2001)
    vol, _ = br.simulate_pressure(t, lambda tt: 3.0 * np.sin(w * tt), mech)
    h = br.transfer(w, mech)
    exact = np.imag(3.0 / h * np.exp(1j * w * t))
    late = t > 5.0  # τ = 0.25 s: the transient is gone (e^-20)
    assert np.max(np.abs(vol[late] - exact[late])) < 1e-6


def test_radau_simulation_agrees_with_fourier_periodic_solution():
    # two independent solvers of the same equation: cycle-by-cycle Radau vs the exact Fourier series
    curve = br.simulate(NORMAL, n_cycles=2, fs_hz=50.0)
    vol, flow = br.periodic_response(NORMAL.period_s, NORMAL.mechanics, NORMAL.insp_fraction, NORMAL.decay)
    theta = curve.t_s / NORMAL.period_s
    v_exact = NORMAL.relaxation_ml + 1000 * br.interp_periodic(vol @ NORMAL.a, theta)
    f_exact = 1000 * br.interp_periodic(flow @ NORMAL.a, theta)
    assert np.max(np.abs(curve.volume_ml - v_exact)) < 0.05  # mL, for a ≈ 600 mL breath
    assert np.max(np.abs(curve.flow_ml_s - f_exact)) < 0.01 * np.ptp(f_exact)  # grid interpolation
    # pressure column is P_mus of the control function
    assert np.allclose(curve.pressure_cmH2O, br.muscle_pressure(theta, NORMAL), atol=1e-9)


def test_flow_is_derivative_of_volume():
    curve = br.simulate(NORMAL, n_cycles=1, fs_hz=200.0)
    num = np.gradient(curve.volume_ml, curve.t_s)
    assert np.max(np.abs(num[2:-2] - curve.flow_ml_s[2:-2])) < 0.02 * np.ptp(curve.flow_ml_s)


def test_from_rest_converges_to_periodic_state():
    rest = br.simulate(NORMAL, n_cycles=6, fs_hz=50.0, start="rest")
    per = br.simulate(NORMAL, n_cycles=6, fs_hz=50.0)
    late = rest.t_s > 4 * NORMAL.period_s
    assert np.max(np.abs(rest.volume_ml[late] - per.volume_ml[late])) < 0.5
    assert abs(rest.volume_ml[0] - NORMAL.relaxation_ml) < 1e-9


def test_basis_continuous_and_periodic():
    th = np.linspace(0, 1, 20001)
    phi = br.basis(th, 0.4, 0.15)
    assert np.max(np.abs(np.diff(phi, axis=0))) < 1e-2  # no jumps
    assert np.allclose(phi[0], phi[-1], atol=1e-6)


def test_scale_and_curve_playback():
    curve = br.simulate(NORMAL, n_cycles=1, fs_hz=50.0)
    v_ee = curve.v_ee_ml
    assert br.scale_from_volume(v_ee + 15.0, v_ee, 1.5) == pytest.approx(10.0)
    s = curve.scale_at(curve.t_s, 1.5)
    assert s.min() == pytest.approx(0.0) and s.max() == pytest.approx(curve.tidal_volume_ml / 1.5)
    assert curve.volume_at(0.5 * (curve.t_s[3] + curve.t_s[4])) == pytest.approx(
        0.5 * (curve.volume_ml[3] + curve.volume_ml[4]))
    with pytest.raises(InputError, match="unit_ml"):
        br.scale_from_volume(1.0, 0.0, 0.0)


def test_bad_inputs_raise():
    with pytest.raises(InputError, match="control"):
        br.BreathingParams(br.Mechanics(10, 2), (1, 2, 3))
    with pytest.raises(InputError, match="elastance"):
        br.Mechanics(-1.0, 2.0)
    with pytest.raises(InputError, match="n_cycles"):
        br.simulate(NORMAL, n_cycles=0)
