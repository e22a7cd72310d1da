"""lungdeform.breathing.gating: the causal window, the decisions and the live gate."""

import math

import numpy as np
import pytest

from lungdeform.breathing.gating import (
    BeamGate,
    GateRule,
    GateWindow,
    WindowSpec,
    distance_outside,
    gate_interval,
    parse_window,
    window_probability,
)
from lungdeform.errors import InputError


def test_window_is_the_lowest_share_of_the_past_extremes():
    # a triangle wave 0..10 sampled at its extremes: after one span the end-exhale edge is
    # 0 + 0.3·10 = 3 exactly, the end-inhale edge 10 − 0.3·10 = 7; before any breath only what was seen
    t = np.arange(0, 40, 0.5)
    x = 10 * np.abs(((t / 4.0) % 1.0) * 2 - 1)
    low, high = GateWindow(WindowSpec("end-exhale", 30)), GateWindow(WindowSpec("end-inhale", 30))
    w_lo = [low.update(a, b) for a, b in zip(t, x)]
    w_hi = [high.update(a, b) for a, b in zip(t, x)]
    assert w_lo[0] == (-math.inf, 10.0) and w_lo[-1] == (-math.inf, pytest.approx(3.0))
    assert w_hi[-1] == (pytest.approx(7.0), math.inf)


def test_window_forgets_breaths_older_than_its_span():
    # a breath of amplitude 10 then 20 s of amplitude 2: after 15 s only the small breaths count
    g = GateWindow(WindowSpec(span_s=15.0))
    t = np.arange(0, 40, 0.25)
    x = np.where(t < 10, 10, 2) * np.abs(np.sin(np.pi * t / 4))
    w = [g.update(a, b) for a, b in zip(t, x)][-1]
    assert w[1] == pytest.approx(0.3 * 2.0, rel=1e-3)


def test_decisions_and_distances():
    w = (-math.inf, 3.0)
    assert gate_interval(w, 1.0, 3.0) and not gate_interval(w, 1.0, 3.5) and not gate_interval(w, -math.inf, math.inf)
    assert distance_outside(w, 5.0) == 2.0 and distance_outside(w, -5.0) == 0.0
    assert distance_outside((7.0, math.inf), 5.0) == 2.0
    # F(3) − F(−inf) for end-exhale, 1 − F(7) for end-inhale
    assert window_probability(w, lambda v: 0.8) == pytest.approx(0.8)
    assert window_probability((7.0, math.inf), lambda v: 0.8) == pytest.approx(0.2)


def test_parse_window_and_bad_rules():
    assert parse_window("end-inhale:25") == WindowSpec("end-inhale", 25.0)
    for bad in ("middle:30", "end-exhale:abc", "end-exhale:0", "end-exhale:100"):
        with pytest.raises(InputError, match="--window"):
            parse_window(bad)
    with pytest.raises(InputError, match="min_probability"):
        GateRule(min_probability=1.0)


def test_live_gate_decisions_never_use_later_samples(rng):
    # causality: the decisions and intervals before sample k do not depend on the samples from k on
    t = np.arange(0, 80, 0.1)
    x = np.abs(np.sin(np.pi * t / 4)) ** 3 + rng.normal(0, 0.02, t.size)
    y = x.copy()
    y[500:] = rng.normal(0, 1.0, t.size - 500)
    a = [BeamGate(0.3) for _ in range(2)]
    ra, rb = ([a[k].update(ti, xi) for ti, xi in zip(t, v)] for k, v in ((0, x), (1, y)))

    def rows(rs):
        return np.array([(r.predicted, r.lo, r.hi, *r.window, r.probability, r.beam_on) for r in rs])

    assert np.array_equal(rows(ra[:500]), rows(rb[:500]), equal_nan=True)
    assert not np.array_equal(rows(ra[500:]), rows(rb[500:]), equal_nan=True)
    assert any(r.beam_on for r in ra) and not all(r.beam_on for r in ra)
