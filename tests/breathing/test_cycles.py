"""Breathing-cycle detection: period, turning points, cycle anchors against truth, flags and noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from lungdeform.breathing import cycles
from lungdeform.breathing.cycles import (
    _breaths,
    cycle_anchors,
    cycle_flags,
    dominant_period,
    noise_level,
    turning_points,
)
from lungdeform.breathing.trace import Trace, read_trace, resample
from lungdeform.errors import InputError
from tests.breathing.test_trace import breath, write_marker_csv


def test_too_short_for_one_cycle(tmp_path):
    t = np.arange(0.0, 3.0, 0.1)
    f = write_marker_csv(tmp_path / "short.csv", t * 1000, 10 * breath(t), terminator=False)
    with pytest.raises(InputError, match="short.csv: .*too short to hold one breathing cycle"):
        cycle_anchors(read_trace(f))


def test_detected_cycles_match_truth(tmp_path, rng):
    # truth: onsets at k·4 s (+ seeded noise); peak of each breath at onset + 1.8 s
    t = np.arange(0.0, 60.0, 0.1)
    s = 10 * breath(t) + rng.normal(0, 0.05, t.size)
    f = write_marker_csv(tmp_path / "c.csv", t * 1000, s, terminator=False)
    an = cycle_anchors(resample(read_trace(f), 10.0))
    k = np.rint(an.starts_s / 4.0)
    # the 5 % onset level sits a little after the true onset (the rise is smooth): < 0.4 s
    assert np.all((an.starts_s - 4.0 * k >= 0) & (an.starts_s - 4.0 * k < 0.4))
    assert np.allclose(np.diff(an.starts_s), 4.0, atol=0.15)
    assert np.allclose(an.peaks_s - 4.0 * k[:-1], 1.2, atol=0.15)


def test_dominant_period_ignores_drift_and_multiples(rng):
    # truth: 5.4 s breaths under a slow baseline wander 4× larger than a breath and noise; the
    # strongest autocorrelation peak of the raw signal is the wander, not the breath
    t = np.arange(0.0, 200.0, 0.1)
    wander = np.cumsum(rng.normal(0, 0.35, t.size))
    a = breath(t, 5.4) + wander / np.ptp(wander) * 4.0 + rng.normal(0, 0.02, t.size)
    assert dominant_period(t, a) == pytest.approx(5.4, rel=0.03)


def test_a_signal_faster_than_any_breath_is_refused(rng):
    # why: a 4 Hz oscillation sampled at 10 Hz (a vibrating marker, a signal of another kind) used to be
    # read at a multiple of its period inside the breathing range (1.5 s) and fitted as 40 breaths a
    # minute without a word. Truth: its autocorrelation rises again within 0.3 s, so it is refused; a
    # breath of 5.4 s carrying a cardiac ripple (1.2 Hz, a tenth of its amplitude) and noise, and the
    # fastest breathing kept (1.2 s, 50 a minute, panting), keep their periods
    t = np.arange(0.0, 150.0, 0.1)
    with pytest.raises(InputError, match=r"repeats every 0.2[0-9]* s, faster than any breath"):
        dominant_period(t, 5 * np.sin(2 * np.pi * 4.0 * t) + rng.normal(0, 0.05, t.size))
    ripple = breath(t, 5.4) + 0.1 * np.sin(2 * np.pi * 1.2 * t) + rng.normal(0, 0.02, t.size)
    assert dominant_period(t, ripple) == pytest.approx(5.4, rel=0.03)
    t = np.arange(0.0, 60.0, 0.04)
    assert dominant_period(t, breath(t, 1.2) + rng.normal(0, 0.02, t.size)) == pytest.approx(1.2, rel=0.03)


def test_turning_points_keep_breaths_and_drop_wiggles():
    # truth: 6 big oscillations (excursion 2) with 40 small wiggles (excursion 0.1) on top
    x = np.linspace(0, 6 * 2 * np.pi, 3000)
    s = -np.cos(x) + 0.05 * np.sin(40 * x)
    idx, kind = turning_points(s, 0.5)
    assert (kind == 1).sum() == 6 and np.all(np.diff(kind) != 0)
    peaks = x[idx[kind == 1]]
    assert np.allclose(np.mod(peaks, 2 * np.pi), np.pi, atol=0.1)


def test_cycles_found_around_large_events_and_drift(tmp_path, rng):
    # truth: 4-s breaths (onsets at k·4 s) on a drifting baseline, with a 25-mm non-breathing excursion
    # (5× a breath) at 60–66 s; every breath away from the event must be found, none added
    t = np.arange(0.0, 120.0, 0.1)
    event = 25.0 * np.exp(-0.5 * ((t - 63.0) / 1.5) ** 2)
    s = 5.0 * breath(t) + 0.05 * t + event + rng.normal(0, 0.03, t.size)
    f = write_marker_csv(tmp_path / "e.csv", t * 1000, s, terminator=False)
    an = cycle_anchors(resample(read_trace(f), 10.0))
    true_onsets = np.arange(4.0, 117.0, 4.0)
    away = (true_onsets < 56.0) | (true_onsets > 72.0)
    offset = np.array([an.starts_s[np.argmin(np.abs(an.starts_s - x))] - x for x in true_onsets[away]])
    # the onset is where the (low-passed) rise crosses 5 % of the breath: a near-constant offset
    assert np.all(np.abs(offset) < 0.35) and np.ptp(offset) < 0.15
    assert an.n_cycles <= true_onsets.size


def test_peaks_refined_below_the_sample_interval(tmp_path):
    # truth: a symmetric breath (peak at onset + 0.3 × period) with a period that puts the peaks off
    # the 10-Hz grid; the parabolic refinement must beat the 0.05-s rounding of a sample argmax
    period = 4.03
    t = np.arange(0.0, 60.0, 0.1)
    f = write_marker_csv(tmp_path / "p.csv", t * 1000, 10 * breath(t, period), terminator=False)
    an = cycle_anchors(resample(read_trace(f), 10.0))
    k = np.floor(an.peaks_s / period)
    err = an.peaks_s - (k * period + 0.3 * period)
    assert np.max(np.abs(err)) < 0.02


def test_cycle_flags_mark_the_irregular_cycles(rng):
    # truth: regular 4-s breaths except a double breath (cycle 5: two inhalations with an 80 % partial
    # exhalation between), a 9-s cycle (cycle 8) and a 3×-deep breath (cycle 11); the flags must
    # name exactly those cycles
    durations = np.full(15, 4.0)
    durations[8] = 9.0
    starts = np.concatenate([[0.0], np.cumsum(durations)])
    t = np.arange(0.0, starts[-1], 0.1)
    c = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, 14)
    ph = (t - starts[c]) / 4.0
    a = np.where(ph < 0.6, np.sin(np.pi * ph / 0.6) ** 2, 0.0)
    a[c == 11] *= 3.0
    sel = c == 5
    dip = 1.0 - 0.8 * np.exp(-0.5 * ((ph[sel] - 0.4) / 0.1) ** 2)
    a[sel] = np.where(ph[sel] < 0.8, np.sin(np.pi * ph[sel] / 0.8) ** 2 * dip, 0.0)
    tr = Trace(t, a + rng.normal(0, 0.01, t.size), "mm", np.full(t.size, ""), source="flags")
    an = cycle_anchors(tr)
    flags = cycle_flags(tr, an)
    mids = 0.5 * (an.starts_s[:-1] + an.starts_s[1:])
    flagged: dict = {}
    for i, f in enumerate(flags):
        if f:
            flagged.setdefault(int(np.searchsorted(starts, mids[i]) - 1), set()).update(f)
    assert set(flagged) == {5, 8, 11}, flagged
    assert "multi-peak" in flagged[5] and "duration" in flagged[8] and "amplitude" in flagged[11]


def test_noise_level_finds_injected_white_noise(rng):
    # truth: a 12-mm breath at 10 Hz with white noise of known σ
    t = np.arange(0.0, 120.0, 0.1)
    for sigma in (0.02, 0.1):
        a = 12.0 * breath(t) + rng.normal(0, sigma, t.size)
        est = noise_level(Trace(t, a, "mm", np.full(t.size, ""), source="n"))
        assert est == pytest.approx(sigma, rel=0.2)


def test_onset_of_a_rise_too_small_to_place_a_level_in():
    # why: found by tests/fuzz/fuzz_trace_csv.py (read_trace -> orient_inhale_positive): a rise of one
    # ulp above the trough puts the onset level (5 % of it) back on the trough itself, so no sample
    # lay strictly below it and indexing the empty set raised IndexError. The onset is now the last
    # trough sample, one 0.1 s step before each peak.
    t = np.arange(0.0, 40.0, 0.1)
    fine = np.ones_like(t)
    fine[np.isclose(np.mod(t, 4.0), 1.0)] = np.nextafter(1.0, 2.0)
    peaks, onsets = _breaths(t, np.sin(2 * np.pi * t / 4.0), fine, 4.0, 0.05)
    assert peaks.tolist() == list(range(10, 400, 40))
    assert np.allclose(onsets, t[peaks[1:]] - 0.1)


def test_smoothing_filter_is_designed_once_per_cutoff(rng):
    # why: the trace readers orient every trace they read (inspiratory_shares), and designing the
    # Butterworth sections cost more than filtering; a second smooth at the same rate and cutoff must
    # reuse the cached design and give what a fresh scipy design gives (the same filter, bit for bit).
    a = rng.normal(0.0, 1.0, 200)
    cycles._butter_design.cache_clear()
    first = cycles.smooth(a, 25.0, 0.7)
    second = cycles.smooth(a, 25.0, 0.7)
    assert cycles._butter_design.cache_info().misses == 1 and cycles._butter_design.cache_info().hits == 1
    np.testing.assert_array_equal(first, sosfiltfilt(butter(2, 0.7 / 12.5, output="sos"), a))
    np.testing.assert_array_equal(second, first)
