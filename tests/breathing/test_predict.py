"""lungdeform.breathing.predict: causal prediction of a breathing signal h seconds ahead."""

import numpy as np
import pytest

from lungdeform.breathing import predict as P
from lungdeform.errors import InputError


def _rms_after(t, x, p, h, warm=30.0):
    ok = (t >= warm) & (t + h <= t[-1])
    return float(np.sqrt(np.mean((p[ok] - np.interp(t[ok] + h, t, x)) ** 2)))


def test_predictions_never_use_later_samples(rng):
    # causality: two streams equal up to sample m give the same predictions up to m (truth: a
    # prediction made at t_i may depend only on samples at or before t_i), for every predictor
    t = np.arange(0, 60, 0.1)
    x = np.sin(2 * np.pi * t / 4) + rng.normal(0, 0.05, t.size)
    y = x.copy()
    m = 450
    y[m:] = rng.normal(0, 5, t.size - m)
    for name in P.PREDICTORS:
        a, b = P.predict_trace(t, x, 0.4, name), P.predict_trace(t, y, 0.4, name)
        np.testing.assert_array_equal(a[:m], b[:m])
        assert not np.array_equal(a[m:], b[m:])  # and the later samples do matter


def test_model_predicts_a_clean_breath_almost_exactly():
    # a sinusoid is exactly an order-2 autoregression: the linear part learns it, so 400 ms ahead the
    # model's error is a small fraction of no prediction's (truth: x(t + h) = 2cos(ωΔ)… exactly linear)
    t = np.arange(0, 90, 0.1)
    x = 5 * np.sin(2 * np.pi * t / 4.2)
    p = P.predict_trace(t, x, 0.4, "model")
    assert _rms_after(t, x, p, 0.4) < 0.02 * _rms_after(t, x, P.predict_trace(t, x, 0.4, "none"), 0.4)


def test_irregular_sampling_and_a_gap_are_read_by_interpolation(rng):
    # jittered sample times (8–12 Hz) and a 1.5 s gap: features are read on the fixed internal step by
    # interpolation, so the prediction stays close (truth: the same smooth breath sampled regularly)
    dt = rng.uniform(0.08, 0.12, 1200)
    t = np.cumsum(dt)
    t = t[(t < 50) | (t > 51.5)]
    x = 5 * np.sin(2 * np.pi * t / 4.0)
    p = P.predict_trace(t, x, 0.3, "model")
    none = _rms_after(t, x, P.predict_trace(t, x, 0.3, "none"), 0.3)
    assert _rms_after(t, x, p, 0.3) < 0.1 * none


def test_linear_baseline_is_the_least_squares_autoregression_of_the_spec(rng):
    # dense reference: at each time, least squares with an intercept on the raw last 2 s of samples
    # (21 samples at 10 Hz), trained on the pairs of the preceding 30 s whose target has arrived,
    # solved by numpy's lstsq; the predictor refitted at every sample must give the same prediction
    t = np.arange(0, 60, 0.1)
    x = np.sin(2 * np.pi * t / 3.7) + 0.3 * np.sin(2 * np.pi * t / 11) + rng.normal(0, 0.05, t.size)
    k, h = 4, 0.4
    lin = P.LinearPredictor(h, window_s=2.0, train_s=30.0, refit_s=0.0, half_life_s=None, ridge=0.0)
    got = np.array([lin.update(ti, xi) for ti, xi in zip(t, x)])
    for i in (350, 420, 599):
        rows = [j for j in range(20, i - k + 1) if t[j] >= t[i - k] - 30.0 - 1e-9]
        a = np.array([np.r_[x[j - 20:j + 1], 1.0] for j in rows])
        coef = np.linalg.lstsq(a, x[np.array(rows) + k], rcond=None)[0]
        assert got[i] == pytest.approx(np.r_[x[i - 20:i + 1], 1.0] @ coef, abs=1e-8)


def test_analog_forecast_repeats_an_exactly_repeated_cycle():
    # a periodic but non-sinusoidal cycle (not a short autoregression): after two cycles every window
    # has an identical earlier twin, whose future is the answer (truth: periodicity)
    t = np.arange(0, 40, 0.1)
    ph = np.mod(t, 4.0) / 4.0
    x = np.where(ph < 0.7, np.sin(np.pi * ph / 0.7) ** 2, 0.0)  # flat for 1.2 s, shorter than a window
    a = P.AnalogPredictor(0.5, window_s=2.0, neighbours=5)
    p = np.array([a.update(ti, xi) for ti, xi in zip(t, x)])
    ok = (t > 12) & (t + 0.5 <= t[-1])
    assert np.max(np.abs(p[ok] - np.interp(t[ok] + 0.5, t, x))) < 1e-6


def test_blend_weights_are_the_inverse_recent_squared_errors(rng):
    # reference: run the two parts on their own, score each prediction when its target arrives
    # (k = 5 samples later at 10 Hz, h = 0.5 s), average the squared errors exponentially over
    # τ = 20 s, weights ∝ 1/mean — the blend's weights must equal that (truth: the documented rule)
    t = np.arange(0, 80, 0.1)
    x = np.sin(2 * np.pi * t / 3.9) ** 3 + rng.normal(0, 0.05, t.size)
    b = P.BlendPredictor(0.5)
    parts = (P.LinearPredictor(0.5, window_s=1.5, half_life_s=60.0, ridge=1e-4),
             P.AnalogPredictor(0.5, window_s=2.0, neighbours=30))
    preds = np.array([[p.update(ti, xi) for p in parts] for ti, xi in zip(t, x)])
    for ti, xi in zip(t, x):
        b.update(ti, xi)
    mse, t_prev = None, None
    for j in range(t.size - 5):
        e2 = (preds[j] - x[j + 5]) ** 2
        a = 1.0 if t_prev is None else 1 - np.exp(-(t[j] - t_prev) / 20.0)
        mse, t_prev = (e2 if mse is None else (1 - a) * mse + a * e2), t[j]
    np.testing.assert_allclose(b.weights, (1 / mse) / np.sum(1 / mse), rtol=1e-9)
    assert b.weights.sum() == pytest.approx(1.0)


def test_bad_input_is_refused_by_name():
    p = P.BlendPredictor(0.4)
    p.update(0.0, 1.0)
    with pytest.raises(InputError, match="increase"):
        p.update(0.0, 1.0)
    with pytest.raises(InputError, match="not finite"):
        p.update(0.1, float("nan"))
    with pytest.raises(InputError, match="horizon_s"):
        P.BlendPredictor(0.0)
    with pytest.raises(InputError, match="same length"):
        P.predict_trace([0, 1, 2], [1, 2], 0.4)
