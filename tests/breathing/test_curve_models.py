"""lungdeform.breathing.curve_models: the Lujan and Fourier breathing curves, recovered from curves generated
with known parameters (Lujan et al. 1999's cos^{2n} shape; a K-harmonic Fourier series per cycle)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing import curve_models as rb
from lungdeform.errors import InputError


def _cycles(rng, k=6, fs=50.0):
    """``k`` cycles of 3.5–4.5 s from t = 0, sampled at ``fs`` Hz: (starts (k+1,), t (n,), idx, θ)."""
    starts = np.cumsum(np.r_[0.0, rng.uniform(3.5, 4.5, k)])
    t = np.arange(0.0, starts[-1], 1.0 / fs)
    idx, theta = rb.cycle_phase(t, starts)
    return starts, t, idx, theta


def test_cycle_phase_linear_and_warped():
    # truth: hand-computed phases; outside the cycles the index is −1; the warp sends onset → 0,
    # peak → peak_phase and the next onset → 1, linearly in between
    starts = np.array([1.0, 5.0, 9.0])
    peaks = np.array([2.0, 7.0])
    t = np.array([0.5, 1.0, 2.0, 3.0, 5.0, 7.0, 8.0, 9.0])
    idx, theta = rb.cycle_phase(t, starts)
    assert idx.tolist() == [-1, 0, 0, 0, 1, 1, 1, -1]
    np.testing.assert_allclose(theta[1:7], [0.0, 0.25, 0.5, 0.0, 0.5, 0.75])
    _, warped = rb.cycle_phase(t, starts, peaks, 0.4)
    # cycle 0: the peak (2 s) → 0.4; 3.0 s is a third of the way from the peak to the end (5 s) → 0.4 + 0.6/3;
    # cycle 1: 8 s is halfway from the peak (7 s) to the end (9 s) → 0.4 + 0.6/2
    np.testing.assert_allclose(warped[1:7], [0.0, 0.4, 0.6, 0.0, 0.4, 0.7])
    # the median end-inhale phase: (2 − 1)/4 = 0.25 and (7 − 5)/4 = 0.5 → 0.375
    assert rb.median_peak_phase(starts, peaks) == pytest.approx(0.375)


def test_lujan_shape_peaks_at_phi_over_pi():
    # |cos(πθ − φ)|^{2n} is 1 at θ = φ/π and lies in [0, 1]
    theta = np.linspace(0, 1, 101)
    s = rb.lujan_shape(theta, 2.5, 1.1)
    assert s.min() >= 0 and s.max() <= 1
    assert rb.lujan_shape(1.1 / np.pi, 2.5, 1.1) == pytest.approx(1.0)


def test_fit_lujan_recovers_n_and_phi(rng):
    # truth: every cycle is c0_c + b_c·|cos(πθ − 1.2)|^{2·2} with its own level and amplitude; the shared
    # fit and each per-cycle fit find n = 2, φ = 1.2, and the prediction reproduces the curve
    starts, t, idx, theta = _cycles(rng)
    c0, b = rng.uniform(-1, 1, 6), rng.uniform(5, 10, 6)
    values = c0[idx] + b[idx] * rb.lujan_shape(theta, 2.0, 1.2)
    fit = rb.fit_lujan(t, values, starts)
    assert fit.success
    assert fit.n == pytest.approx(2.0, abs=1e-3) and fit.phi == pytest.approx(1.2, abs=1e-3)
    assert fit.rms < 1e-3 * np.ptp(values)
    np.testing.assert_allclose(rb.predict_lujan(fit, t, values, starts), values, atol=1e-3 * np.ptp(values))
    per_cycle = rb.fit_lujan(t, values, starts, per_cycle=True)
    assert len(per_cycle) == 6
    for f in per_cycle:
        assert f.n == pytest.approx(2.0, abs=1e-3) and f.phi == pytest.approx(1.2, abs=1e-3)


def test_fit_lujan_needs_samples_in_the_cycles():
    t = np.linspace(0, 1, 50)
    with pytest.raises(InputError, match="no samples inside"):
        rb.fit_lujan(t, np.sin(t), [5.0, 9.0])


def test_fourier_design_columns():
    # K = 2 has five coefficients, as many as the PV driver's control parameters: [1, cos, sin, cos 2, sin 2]
    theta = np.array([0.0, 0.125, 0.25])
    X = rb.fourier_design(theta, 2)
    assert X.shape == (3, 5)
    c, s = np.cos(2 * np.pi * theta), np.sin(2 * np.pi * theta)
    np.testing.assert_allclose(X, np.column_stack([np.ones(3), c, s, np.cos(4 * np.pi * theta),
                                                   np.sin(4 * np.pi * theta)]), atol=1e-15)
    assert rb.fourier_design(theta, 3).shape == (3, 7)


def test_fourier_per_cycle_recovers_each_cycles_coefficients(rng):
    # truth: each cycle is its own K = 2 series with known coefficients; least squares gives them back
    starts, t, idx, theta = _cycles(rng)
    coef = rng.normal(size=(6, 5))
    values = np.einsum("ij,ij->i", rb.fourier_design(theta, 2), coef[idx])
    model, got = rb.fit_fourier_per_cycle(t, values, starts)
    assert got.shape == (6, 5)
    np.testing.assert_allclose(got, coef, atol=1e-10)
    np.testing.assert_allclose(model, values, atol=1e-10)


@pytest.mark.parametrize("drift", [False, True])
def test_fourier_shape_recovers_the_shared_shape(rng, drift):
    # truth: one shape (4 coefficients, no constant) times a per-cycle gain, plus a per-cycle offset (and a
    # linear drift across the cycle); the mean-cycle fit returns the shape scaled to unit peak-to-peak
    # (alternating least squares: the default 8 rounds suffice without drift, with drift it converges
    # more slowly, to 1e-15 in 100 rounds on these data)
    starts, t, idx, theta = _cycles(rng)
    shape = np.array([1.0, -0.5, 0.3, 0.2])
    gain, offset, slope = rng.uniform(0.5, 2.0, 6), rng.normal(size=6), rng.normal(size=6)
    values = gain[idx] * (rb.fourier_design(theta, 2)[:, 1:] @ shape) + offset[idx]
    if drift:
        values += slope[idx] * (theta - 0.5)
    got = rb.fit_fourier_shape(t, values, starts, drift=drift, n_iter=100 if drift else 8)
    assert got.shape == (4,)
    grid = rb.fourier_design(np.linspace(0, 1, 256, endpoint=False), 2)[:, 1:]
    np.testing.assert_allclose(got, shape / np.ptp(grid @ shape), atol=1e-9)
    assert np.ptp(grid @ got) == pytest.approx(1.0)


def test_calibrated_recovers_gain_offset_and_drift(rng):
    # truth: values built from a shape with a known gain, offset and drift per cycle are reproduced exactly
    starts, t, idx, theta = _cycles(rng, k=3)
    shape = np.sin(2 * np.pi * theta) ** 2
    values = rng.uniform(1, 2, 3)[idx] * shape + rng.normal(size=3)[idx] + rng.normal(size=3)[idx] * (theta - 0.5)
    np.testing.assert_allclose(rb.calibrated(idx, shape, values, theta, drift=True), values, atol=1e-10)
    assert np.max(np.abs(rb.calibrated(idx, shape, values, theta) - values)) > 1e-3  # no drift term: a misfit
