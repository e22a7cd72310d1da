"""lungdeform.breathing.predict_interval: calibration against known noise, causality, the score."""

import math

import numpy as np
import pytest

from lungdeform.breathing.predict import BlendPredictor, check_horizon
from lungdeform.breathing.predict_interval import IntervalConfig, IntervalPredictor, interval_score, interval_trace
from lungdeform.errors import InputError


class KnownSignal:
    """A point predictor that knows the clean signal: its errors are exactly the sensor noise at t + h."""

    def __init__(self, horizon_s, clean):
        self.horizon_s = check_horizon(horizon_s)
        self.clean = clean

    def update(self, t, x):
        return float(self.clean(t + self.horizon_s))


def _noisy(rng, sigma=0.5, seconds=600.0, rate_hz=10.0):
    t = np.arange(0.0, seconds, 1.0 / rate_hz)

    def clean(tt):
        return 5.0 * np.sin(2 * np.pi * np.asarray(tt) / 4.0)

    return t, clean(t) + rng.normal(0.0, sigma, t.size), clean


@pytest.mark.parametrize("coverage", [0.9, 0.5])
def test_coverage_on_known_gaussian_noise_is_near_nominal(rng, coverage):
    # the errors are N(0, σ²) white noise (KnownSignal): the share of truths inside the interval must be
    # the nominal coverage (±3 %, about 4 binomial standard errors over 5700 samples); at 0.5 as well, so
    # an interval that is merely wide cannot pass
    t, x, clean = _noisy(rng)
    band = interval_trace(t, x, KnownSignal(0.3, clean), IntervalConfig(coverage=coverage))
    ok = (t >= 30) & (t + 0.3 <= t[-1])
    truth = np.interp(t[ok] + 0.3, t, x)
    inside = (band[ok, 1] <= truth) & (truth <= band[ok, 2])
    assert inside.mean() == pytest.approx(coverage, abs=0.03)


def test_predictive_probability_is_calibrated(rng):
    # probability integral transform: P(x(t + h) <= truth) must be uniform on [0, 1] for a calibrated
    # predictive distribution, so its quartiles are near 0.25 / 0.5 / 0.75
    t, x, clean = _noisy(rng)
    p = IntervalPredictor(KnownSignal(0.3, clean))
    pit = []
    for i, (ti, xi) in enumerate(zip(t, x)):
        p.update(ti, xi)
        if ti >= 30 and ti + 0.3 <= t[-1]:
            pit.append(p.probability_below(float(np.interp(ti + 0.3, t, x))))
    assert np.quantile(pit, [0.25, 0.5, 0.75]) == pytest.approx([0.25, 0.5, 0.75], abs=0.04)


def test_intervals_never_use_later_samples(rng):
    # causality: changing every sample from index k on must not change any interval given before k
    t = np.arange(0, 90, 0.1)
    x = np.sin(2 * np.pi * t / 4) + rng.normal(0, 0.05, t.size)
    y = x.copy()
    y[600:] += rng.normal(0, 2.0, t.size - 600)
    a = interval_trace(t, x, BlendPredictor(0.4))
    b = interval_trace(t, y, BlendPredictor(0.4))
    assert np.array_equal(a[:600], b[:600]) and not np.array_equal(a[600:], b[600:])


def test_interval_is_infinite_until_learned_then_finite_even_after_many_misses():
    # no score yet: the predictor cannot know its error (±inf); after a jump that ACI answers by pushing
    # α below 0, the interval is the largest stored score, still finite
    t = np.arange(0, 120, 0.1)
    x = np.where(t < 60, 0.0, 10.0 * (t - 60))  # a ramp the still-signal scores never saw
    band = interval_trace(t, x, KnownSignal(0.3, lambda tt: 0.0))
    assert math.isinf(band[0, 1]) and math.isinf(band[0, 2])
    assert np.all(np.isfinite(band[t > 10, 1:]))


def test_interval_score_matches_its_definition():
    # Gneiting & Raftery 2007 Sec. 6.2: (u − l) + 2/α (l − y)+ + 2/α (y − u)+; α = 0.1 → 20 per unit miss
    s = interval_score([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, -0.5, 3.0], 0.9)
    assert s == pytest.approx([1.0, 1.0 + 20 * 0.5, 1.0 + 20 * 2.0])


def test_bad_settings_are_refused():
    with pytest.raises(InputError, match="coverage"):
        IntervalConfig(coverage=1.0)
    with pytest.raises(InputError, match="t_s and x"):
        interval_trace([0.0], [1.0], BlendPredictor(0.3))
