"""The PV relation: integrator against analytic solutions, inversion against known parameters."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform import breathing as br
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


def test_invert_recovers_control_parameters_given_mechanics(rng):
    # truth: with E, R, I, ρ, κ known the inversion is linear in a_k; seeded noise of 2 mL
    truth = NORMAL
    curve = br.simulate(truth, n_cycles=6, fs_hz=25.0)
    noisy = curve.volume_ml + rng.normal(0.0, 2.0, curve.t_s.size)
    starts = np.arange(7) * truth.period_s
    fit = br.invert(curve.t_s, noisy, starts, elastance=10.0, relaxation_ml=truth.relaxation_ml,
                    fit_shape=False, init=truth)
    assert fit.success, fit.message
    assert np.allclose(fit.params.a, truth.a, atol=0.2)  # cmH2O; a_2 and a_3 (u, u²) correlate
    assert abs(np.std(fit.residual_ml) - 2.0) < 0.3  # the residual is the noise, nothing more


def test_invert_full_shape_fit_reproduces_the_curve(rng):
    # truth: the same simulated breath; with τ, I/E, ρ, κ searched as well, the fitted curve must
    # explain the data down to the noise. (From volume alone, a free 5-term P_mus can trade against
    # τ: the shape constants are not all identifiable, so the test checks the curve, and ρ.)
    truth = NORMAL
    curve = br.simulate(truth, n_cycles=6, fs_hz=25.0)
    noisy = curve.volume_ml + rng.normal(0.0, 2.0, curve.t_s.size)
    starts = np.arange(7) * truth.period_s
    fit = br.invert(curve.t_s, noisy, starts, elastance=10.0, relaxation_ml=truth.relaxation_ml)
    assert fit.success, fit.message
    assert np.std(fit.residual_ml) < 2.3
    clean = np.interp(fit.t_s, curve.t_s, curve.volume_ml)
    assert np.sqrt(np.mean((fit.model_ml - clean) ** 2)) < 1.0  # mL, on a 600 mL breath
    assert abs(fit.params.insp_fraction - truth.insp_fraction) < 0.02
    assert abs(fit.params.mechanics.time_constant_s - 0.25) < 0.05
    assert fit.residual_ml.shape == fit.t_s.shape


def test_invert_with_peaks_recovers_lag_and_shape(rng):
    # truth: cycles of varied length, each drive ending `lag` before the observed peak, per-cycle gain
    starts = np.concatenate([[0.0], np.cumsum([4.0, 3.6, 4.4, 3.8, 4.2, 4.0])])
    lag = 0.3
    rho_true = np.array([0.38, 0.42, 0.36, 0.40, 0.41, 0.39])
    peaks = starts[:-1] + rho_true * np.diff(starts) + lag
    t = np.arange(0.0, starts[-1], 0.04)
    idx, y, _ = br.cycle_design(t, starts, NORMAL.mechanics, rho_true, NORMAL.decay)
    gains = np.array([1.0, 0.8, 1.2, 0.9, 1.1, 1.0])
    v = 2400 + 1000 * (y @ NORMAL.a) * gains[idx] + rng.normal(0, 1.0, t.size)
    fit = br.invert(t, v, starts, peaks_s=peaks, elastance=10.0, per_cycle_calibration=True)
    assert abs(fit.peak_lag_s - lag) < 0.05
    assert fit.rms_percent < 1.0
    assert "offset" in fit.per_cycle and "a_1..a_5" in fit.shared


def test_estimate_mechanics_with_pressure():
    # truth: with the driving pressure measured, E, R, I are identifiable by linear least squares
    curve = br.simulate(NORMAL, n_cycles=3, fs_hz=200.0)
    mech, v_r, rms = br.estimate_mechanics(curve.t_s, curve.volume_ml, curve.pressure_cmH2O)
    assert abs(mech.elastance - 10.0) < 0.1
    assert abs(mech.resistance - 2.5) < 0.1
    assert abs(v_r - NORMAL.relaxation_ml) < 5.0
    theta = curve.t_s / NORMAL.period_s
    a = br.fit_control_to_pressure(theta, curve.pressure_cmH2O, NORMAL.insp_fraction, NORMAL.decay)
    assert np.allclose(a, NORMAL.a, atol=1e-6)


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
    t = np.linspace(0, 8, 200)
    v = np.sin(t)
    with pytest.raises(InputError, match="NaN"):
        br.invert(t, np.where(t > 4, np.nan, v), [0, 4, 8])
    with pytest.raises(InputError, match="cycle_starts_s"):
        br.invert(t, v, [0.0])
    with pytest.raises(InputError, match="one length"):
        br.invert(t, v[:-1], [0, 4, 8])
    with pytest.raises(InputError, match="control"):
        br.BreathingParams(br.Mechanics(10, 2), (1, 2, 3))
    with pytest.raises(InputError, match="elastance"):
        br.Mechanics(-1.0, 2.0)
    with pytest.raises(InputError, match="n_cycles"):
        br.simulate(NORMAL, n_cycles=0)
