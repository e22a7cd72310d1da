"""Inversion of the PV relation against known parameters (simulated breaths, known truth)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing import inversion as inv
from lungdeform.breathing import pv as br
from lungdeform.errors import InputError

NORMAL = br.BreathingParams(br.Mechanics(10.0, 2.5, 0.01), (0.5, 4.0, 2.0, -0.5, 1.0), period_s=4.0,
                            insp_fraction=0.4, decay=0.15, relaxation_ml=2400.0)


def test_invert_recovers_control_parameters_given_mechanics(rng):
    # truth: with E, R, I, ρ, κ known the inversion is linear in a_k; seeded noise of 2 mL
    truth = NORMAL
    curve = br.simulate(truth, n_cycles=6, fs_hz=25.0)
    noisy = curve.volume_ml + rng.normal(0.0, 2.0, curve.t_s.size)
    starts = np.arange(7) * truth.period_s
    settings = inv.InversionSettings(elastance=10.0, relaxation_ml=truth.relaxation_ml, fit_shape=False)
    fit = inv.invert(curve.t_s, noisy, starts, settings=settings, init=truth)
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
    fit = inv.invert(curve.t_s, noisy, starts,
                     settings=inv.InversionSettings(elastance=10.0, relaxation_ml=truth.relaxation_ml))
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
    idx, y, _ = inv.cycle_design(t, starts, NORMAL.mechanics, rho_true, NORMAL.decay)
    gains = np.array([1.0, 0.8, 1.2, 0.9, 1.1, 1.0])
    v = 2400 + 1000 * (y @ NORMAL.a) * gains[idx] + rng.normal(0, 1.0, t.size)
    fit = inv.invert(t, v, starts, peaks_s=peaks,
                     settings=inv.InversionSettings(elastance=10.0, per_cycle_calibration=True))
    assert abs(fit.peak_lag_s - lag) < 0.05
    assert fit.rms_percent < 1.0
    assert "offset" in fit.per_cycle and "a_1..a_5" in fit.shared


def test_estimate_mechanics_with_pressure():
    # truth: with the driving pressure measured, E, R, I are identifiable by linear least squares
    curve = br.simulate(NORMAL, n_cycles=3, fs_hz=200.0)
    mech, v_r, rms = inv.estimate_mechanics(curve.t_s, curve.volume_ml, curve.pressure_cmH2O)
    assert abs(mech.elastance - 10.0) < 0.1
    assert abs(mech.resistance - 2.5) < 0.1
    assert abs(v_r - NORMAL.relaxation_ml) < 5.0
    theta = curve.t_s / NORMAL.period_s
    a = inv.fit_control_to_pressure(theta, curve.pressure_cmH2O, NORMAL.insp_fraction, NORMAL.decay)
    assert np.allclose(a, NORMAL.a, atol=1e-6)


def test_invert_bad_inputs_raise():
    t = np.linspace(0, 8, 200)
    v = np.sin(t)
    with pytest.raises(InputError, match="NaN"):
        inv.invert(t, np.where(t > 4, np.nan, v), [0, 4, 8])
    with pytest.raises(InputError, match="cycle_starts_s"):
        inv.invert(t, v, [0.0])
    with pytest.raises(InputError, match="one length"):
        inv.invert(t, v[:-1], [0, 4, 8])
