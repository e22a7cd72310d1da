"""lungdeform.breathing.gating: the causal window, the decisions and the live gate."""

import math

import numpy as np
import pytest

from lungdeform.breathing.gating import (
    BeamGate,
    GateRule,
    GateWindow,
    RiskControl,
    RiskThreshold,
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
    for kw, word in (({"target_error": 0.0}, "target_error"), ({"gamma": 0.0}, "gamma"), ({"start": 1.0}, "start")):
        with pytest.raises(InputError, match=word):
            RiskControl(**kw)


def _risk_run(rng, control, n=100_000, sigma_claimed=0.7):
    """A synthetic gate with a known noise: at sample j the prediction of x(t_j + 0.3 s) is m_j ~ U(−3, 3)
    and the truth, the sample 3 steps later (10 Hz), is m_j + N(0, 1); the window is x ≤ 0. The claimed
    predictive distribution N(m_j, 0.7²) is overconfident (the true σ is 1), so a fixed threshold does
    not give the error it suggests. Returns the threshold's state and the fixed-0.5 gate's error."""
    m = rng.uniform(-3, 3, n)
    x = np.concatenate([rng.normal(0, 1, 3), m[:-3] + rng.normal(0, 1, n - 3)])  # x_k = m_{k−3} + ε
    p = np.array([0.5 * math.erfc(mj / (sigma_claimed * math.sqrt(2))) for mj in m])  # P(x ≤ 0)
    gate, w = RiskThreshold(0.3, control), (-math.inf, 0.0)
    for k in range(n):
        gate.observe(k / 10.0, x[k])
        gate.decide(k / 10.0, p[k], 1.0, w)
    fixed = p[:-3] >= 0.5
    return gate, float(np.mean(x[3:][fixed] > 0))


def test_adaptive_gate_beam_on_error_converges_to_the_target(rng):
    # the telescoping identity of adaptive conformal inference (Gibbs & Candès 2021, Prop. 4.1): every
    # scored beam-on decision moves the threshold by γ(e_j − α), so while it stays in [0, 1],
    # |realised beam-on error − α| ≤ (1 + γ)/(γ N_on) whatever the noise: ~0.0025 here. The fixed 0.5
    # threshold on the same distribution errs 0.13 whatever α is, so the test can fail
    for alpha in (0.05, 0.1):
        gate, fixed_error = _risk_run(rng, RiskControl(target_error=alpha, gamma=0.01))
        err = gate.n_missed / gate.n_on
        assert gate.n_on > 10_000 and 0.0 < gate.threshold < 1.0
        assert abs(err - alpha) <= (1 + 0.01) / (0.01 * gate.n_on)
        assert abs(fixed_error - alpha) > 0.03


def test_adaptive_gate_threshold_is_capped_so_the_beam_can_come_back():
    # after a run of misses the threshold reaches 1, above any probability the conformal distribution
    # gives (n/(n + 1) < 1); capped at that highest probability, a prediction with every stored error
    # inside the window still turns the beam on, and its outcome steers the threshold down again
    gate = RiskThreshold(0.3, RiskControl(target_error=0.05, gamma=0.5))
    w = (-math.inf, 0.0)
    for k in range(10):  # every beam-on decision misses (the truth, 3 samples later, is 1 > 0)
        gate.observe(k / 10.0, 1.0)
        gate.decide(k / 10.0, 0.99, 0.99, w)
    for k in range(10, 13):  # the last three decisions' outcomes arrive
        gate.observe(k / 10.0, 1.0)
    assert gate.threshold == 1.0 and gate.n_missed == gate.n_on == 10
    assert not gate.decide(1.2, 0.98, 0.99, w) and gate.decide(1.2, 0.99, 0.99, w)
    for k in range(13, 16):  # that decision hits (truth −1 at 1.5 s): the threshold comes down by γα
        gate.observe(k / 10.0, -1.0)
    assert gate.n_on == 11 and gate.threshold == pytest.approx(1.0 - 0.5 * 0.05)


def test_fixed_threshold_rule_is_the_probability_gate(rng):
    # risk=None: the decision is exactly "window probability >= min_probability"; the default is adaptive
    t = np.arange(0, 60, 0.1)
    x = np.abs(np.sin(np.pi * t / 4)) ** 3 + rng.normal(0, 0.02, t.size)
    g = BeamGate(0.3, GateRule(risk=None, min_probability=0.6))
    rs = [g.update(a, b) for a, b in zip(t, x)]
    assert all(r.beam_on == (r.probability >= 0.6) for r in rs) and any(r.beam_on for r in rs)
    assert BeamGate(0.3).risk is not None and g.risk is None


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
