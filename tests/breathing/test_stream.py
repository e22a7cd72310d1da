"""Streaming estimator: causal, calibrated, follows drift, refuses bad samples."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing.stream import StreamingVolumeEstimator, replay, signal_delay_s
from lungdeform.errors import InputError


def test_causal_no_look_ahead(rng):
    # truth: changing the future must not change any past estimate
    t = np.arange(0.0, 40.0, 0.04)
    x = np.sin(2 * np.pi * t / 4.0) + rng.normal(0, 0.02, t.size)
    y = x.copy()
    y[600:] += 5.0
    va, _ = replay(t, x, StreamingVolumeEstimator())
    vb, _ = replay(t, y, StreamingVolumeEstimator())
    assert np.array_equal(va[:600], vb[:600])
    assert not np.array_equal(va[600:], vb[600:])


def test_calibration_and_delay_on_a_sinusoid():
    # truth: a sinusoid maps to V_EE..V_EE+V_T after warm-up; the 2-stage smoother delays it by
    # about 2·smoothing_s at breathing frequencies
    t = np.arange(0.0, 60.0, 0.02)
    x = 3.0 + 0.7 * np.sin(2 * np.pi * t / 4.0)
    est = StreamingVolumeEstimator(tidal_volume_ml=500.0, v_ee_ml=2400.0, smoothing_s=0.05)
    vol, secs = replay(t, x, est)
    warm = t > 20.0
    assert vol[warm].min() == pytest.approx(2400.0, abs=5.0)
    assert vol[warm].max() == pytest.approx(2900.0, abs=5.0)
    ideal = 2400.0 + 500.0 * (x - x.min()) / np.ptp(x)
    delay = signal_delay_s(t[warm], ideal[warm], vol[warm])
    assert 0.06 <= delay <= 0.14
    assert secs.shape == t.shape and np.all(secs >= 0)


def test_follows_baseline_drift():
    t = np.arange(0.0, 120.0, 0.04)
    x = 0.5 * np.sin(2 * np.pi * t / 4.0) + 0.01 * t  # drift of 1.2 units over the run
    vol, _ = replay(t, x, StreamingVolumeEstimator(tidal_volume_ml=500.0, v_ee_ml=0.0))
    late = t > 20.0
    assert vol[late].min() > -60.0 and vol[late].max() < 560.0  # within ±12 % of V_T


def test_scale_and_warm_flag():
    est = StreamingVolumeEstimator(tidal_volume_ml=500.0, v_ee_ml=2400.0, unit_ml=1.5, window_s=2.0)
    s0 = est.update(0.0, 1.0)
    assert not s0.warm and s0.scale == pytest.approx(0.0)
    for i in range(1, 200):
        s = est.update(i * 0.02, np.sin(i * 0.05))
    assert s.warm
    assert s.scale == pytest.approx((s.volume_ml - 2400.0) / 1.5)


def test_bad_samples_refused():
    est = StreamingVolumeEstimator()
    est.update(1.0, 0.0)
    with pytest.raises(InputError, match="time must increase"):
        est.update(1.0, 0.1)
    with pytest.raises(InputError, match="not finite"):
        est.update(2.0, float("nan"))
    with pytest.raises(InputError, match="unit_ml"):
        StreamingVolumeEstimator(unit_ml=0.0)


def test_noncausal_twin_matches_stream_on_a_steady_sinusoid():
    # truth: on a steady breath the causal and non-causal estimators differ only by the small delay
    from lungdeform.breathing.stream import offline_volume

    t = np.arange(0.0, 60.0, 0.04)
    x = np.sin(2 * np.pi * t / 4.0)
    ref = offline_volume(t, x, 500.0, 2400.0, window_s=10.0)
    vol, _ = replay(t, x, StreamingVolumeEstimator(500.0, 2400.0, window_s=10.0))
    warm = t > 20.0
    assert ref[warm].min() == pytest.approx(2400.0, abs=3.0) and ref[warm].max() == pytest.approx(2900.0, abs=3.0)
    assert np.sqrt(np.mean((vol[warm] - ref[warm]) ** 2)) < 0.05 * 500.0


def test_prediction_moves_the_stream_ahead_by_the_horizon():
    # with predict_ms = 400 the estimate is for t + 0.4 s: against the signal 0.4 s in the future it lags
    # only by the smoother (2 × 0.05 s), the plain estimate by 0.4 s more (truth: signal_delay_s)
    from lungdeform.breathing.stream import StreamingVolumeEstimator, signal_delay_s

    t = np.arange(0, 90, 0.05)
    x = np.sin(2 * np.pi * t / 4.0)
    future = np.sin(2 * np.pi * (t + 0.4) / 4.0)
    plain = StreamingVolumeEstimator()
    ahead = StreamingVolumeEstimator(predict_ms=400)
    vp = np.array([plain.update(a, b).volume_ml for a, b in zip(t, x)])
    samples = [ahead.update(a, b) for a, b in zip(t, x)]
    va = np.array([s.volume_ml for s in samples])
    late = t > 40
    d_plain = signal_delay_s(t[late], future[late], vp[late])
    d_ahead = signal_delay_s(t[late], future[late], va[late])
    assert d_plain == pytest.approx(0.5, abs=0.06) and d_ahead == pytest.approx(0.1, abs=0.06)
    assert samples[-1].ahead_s == 0.4 and plain.update(91.0, 0.0).ahead_s == 0.0


def test_parse_sample_reads_live_lines_and_names_bad_ones():
    # blank lines, comments and a first-line header are skipped; separators , ; tab space all work
    from lungdeform.breathing.stream import parse_sample

    assert parse_sample("t_s,amplitude", 1) is None and parse_sample("  ", 5) is None
    assert parse_sample("# note", 3) is None
    assert parse_sample("1.5;2", 2) == (1.5, 2.0) and parse_sample("1.5\t2", 2) == (1.5, 2.0)
    with pytest.raises(InputError, match="feed line 7"):
        parse_sample("1.5,nan", 7, "feed")
    with pytest.raises(InputError, match="stdin line 2"):
        parse_sample("1.5", 2)
