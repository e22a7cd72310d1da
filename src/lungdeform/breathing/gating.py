"""Amplitude gating: the beam is on only while the breathing signal is inside a window of each breath.

The window (:class:`WindowSpec`): ``end-exhale:30`` is the lowest 30 % of the breath's amplitude,
``end-inhale:30`` the highest 30 % (the signal oriented inhale-positive, as
:func:`lungdeform.breathing.trace.read_trace` gives it). :class:`GateWindow` defines it causally from
the past breaths: over the samples of the last ``span_s`` seconds (15 s: three breaths or more) the
lowest value ``a`` and the highest ``b`` (monotone-deque sliding minimum and maximum, O(1) amortised
per sample, any sample spacing) give the edge ``a + p·(b − a)`` (end-exhale; ``b − p·(b − a)``
end-inhale); the window is open on its far side (a breath deeper than the past ones is still
end-exhale).

Decisions at time ``t`` for the position at ``t + latency`` (:func:`gate_point`,
:func:`gate_interval`, :func:`gate_probability`): a predicted value inside the window; a whole
interval inside; or a predicted probability of being inside at least a threshold.

The threshold (:class:`RiskThreshold`, the default) adapts online to a stated clinical tolerance
``target_error`` (α, default 0.05) on the beam-on error, the share of beam-on time with the target
outside the window. A decision's outcome is known ``latency`` after it: the threshold then moves by
``γ·(e_j − α)`` for every beam-on decision ``j`` (``e_j`` = 1 when the true position missed the
window), up after a miss, down after a hit. This is adaptive conformal inference (Gibbs & Candès,
NeurIPS 2021, eq. 2) applied to the gate's risk instead of an interval's coverage: summed over ``N``
scored beam-on decisions the updates telescope, ``Σ (e_j − α) = (τ_N − τ_0)/γ``, so while the
threshold stays in ``[0, 1]`` the realised beam-on error is within ``1/(γ N)`` of α, whatever the
predictor or the breathing, and the beam is on as much as that allows. The threshold is capped at
the highest probability the predictive distribution can give (``n/(n + 1)`` with ``n`` stored
errors), so a run of misses cannot hold the beam off for ever: with every stored error putting the
target inside, the beam may come on, and its outcome steers the threshold again.
With ``target_error=None`` the threshold is fixed at ``min_probability``.

:class:`BeamGate` is the live gate: one sample in, the window, the model's prediction of the
position ``latency`` later with its interval (:mod:`lungdeform.breathing.predict_interval`) and the
beam decision out (``lungdeform stream --gate``, ``lungdeform validate gating``).

Arrays: ``t_s : (n,) float`` s, values in the trace's units.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from lungdeform.errors import InputError

from .predict import EPS_S, BlendPredictor, check_horizon
from .predict_interval import IntervalConfig, IntervalPredictor

#: window kinds: the name and whether the window is the low end of the breath
WINDOW_KINDS = {"end-exhale": True, "end-inhale": False}


@dataclass(frozen=True)
class WindowSpec:
    """kind : ``end-exhale`` or ``end-inhale``; percent : share of the breath's amplitude (0, 100);
    span_s : s of past samples that define the breath's extremes."""

    kind: str = "end-exhale"
    percent: float = 30.0
    span_s: float = 15.0

    def __post_init__(self):
        if self.kind not in WINDOW_KINDS:
            raise InputError(f"window kind must be one of {', '.join(WINDOW_KINDS)}, got {self.kind!r}")
        if not (math.isfinite(self.percent) and 0.0 < self.percent < 100.0):
            raise InputError(f"window percent must be in (0, 100), got {self.percent!r}")
        if not (math.isfinite(self.span_s) and self.span_s > 0.0):
            raise InputError(f"window span_s must be > 0 s, got {self.span_s!r}")

    @property
    def text(self) -> str:
        return f"{self.kind}:{self.percent:g}"


def parse_window(text: str) -> WindowSpec:
    """``KIND:PERCENT`` (``end-exhale:30``) as a :class:`WindowSpec`; InputError naming ``--window``."""
    kind, sep, pct = str(text).strip().partition(":")
    try:
        percent = float(pct) if sep else 30.0
    except ValueError:
        raise InputError(f"--window must be KIND:PERCENT (e.g. end-exhale:30), got {text!r}") from None
    try:
        return WindowSpec(kind.strip(), percent)
    except InputError as exc:
        raise InputError(f"--window {text!r}: {exc}") from None


class GateWindow:
    """The window as known at each sample (module doc): :meth:`update` takes ``(t, x)`` and returns
    ``(low, high)``, the window's bounds in the trace's units (one of them infinite)."""

    def __init__(self, spec: WindowSpec | None = None):
        self.spec = spec or WindowSpec()
        self._min: deque[tuple[float, float]] = deque()
        self._max: deque[tuple[float, float]] = deque()
        self._t = None

    def update(self, t: float, x: float) -> tuple[float, float]:
        t, x = float(t), float(x)
        if not (math.isfinite(t) and math.isfinite(x)):
            raise InputError(f"gate sample ({t!r}, {x!r}) is not finite")
        if self._t is not None and t <= self._t:
            raise InputError(f"gate sample times must increase: {t!r} after {self._t!r}")
        self._t = t
        while self._min and self._min[-1][1] >= x:
            self._min.pop()
        self._min.append((t, x))
        while self._max and self._max[-1][1] <= x:
            self._max.pop()
        self._max.append((t, x))
        for q in (self._min, self._max):
            while q[0][0] < t - self.spec.span_s:
                q.popleft()
        a, b = self._min[0][1], self._max[0][1]
        share = self.spec.percent / 100.0
        if WINDOW_KINDS[self.spec.kind]:
            return -math.inf, a + share * (b - a)
        return b - share * (b - a), math.inf


def inside(window: tuple[float, float], value: float) -> bool:
    """Whether ``value`` lies in ``window = (low, high)`` (edges included)."""
    return window[0] <= value <= window[1]


def gate_point(window: tuple[float, float], predicted: float) -> bool:
    """Beam on: the predicted position is inside the window."""
    return inside(window, predicted)


def gate_interval(window: tuple[float, float], lo: float, hi: float) -> bool:
    """Beam on: the whole interval ``[lo, hi]`` is inside the window (an infinite interval never is)."""
    return window[0] <= lo and hi <= window[1]


def window_probability(window: tuple[float, float], probability_below) -> float:
    """The predicted probability of the window, ``F(high) − F(low)`` with ``probability_below`` the
    predictive distribution function F (F(−inf) = 0, F(inf) = 1); NaN while F is not yet known."""
    lo, hi = window
    return (1.0 if math.isinf(hi) else probability_below(hi)) - (0.0 if math.isinf(lo) else probability_below(lo))


def gate_probability(probability: float, min_probability: float) -> bool:
    """Beam on: the predicted probability of the window is at least ``min_probability`` (NaN: off)."""
    return bool(probability >= min_probability)


@dataclass(frozen=True)
class RiskControl:
    """target_error : α, the tolerated beam-on error (share of beam-on time outside the window), in
    (0, 1); gamma : the threshold's step per scored beam-on decision, > 0; start : the threshold
    before any outcome is known, in (0, 1)."""

    target_error: float = 0.05
    gamma: float = 0.01
    start: float = 0.5

    def __post_init__(self):
        for name, v in (("target_error", self.target_error), ("start", self.start)):
            if not (math.isfinite(v) and 0.0 < v < 1.0):
                raise InputError(f"{name} must be in (0, 1), got {v!r}")
        if not (math.isfinite(self.gamma) and self.gamma > 0.0):
            raise InputError(f"gamma must be > 0, got {self.gamma!r}")


class RiskThreshold:
    """The adaptive window-probability threshold (module doc). Per sample: :meth:`observe` ``(t, x)``
    first (scores every queued decision whose time ``t_j + latency`` has come, the true position read
    by linear interpolation between the samples around it), then :meth:`decide`."""

    def __init__(self, latency_s: float, control: RiskControl | None = None):
        self.latency_s = check_horizon(latency_s)
        self.control = control or RiskControl()
        self.threshold = self.control.start
        self._queue: deque[tuple[float, tuple[float, float]]] = deque()  # beam-on decisions: (t_j, window_j)
        self._prev: tuple[float, float] | None = None
        self.n_on = 0  # scored beam-on decisions
        self.n_missed = 0  # of which the true position was outside the window

    def observe(self, t: float, x: float) -> None:
        c = self.control
        while self._queue and self._queue[0][0] + self.latency_s <= t + EPS_S:
            tj, w = self._queue.popleft()
            due = tj + self.latency_s
            if self._prev is None or due >= t - EPS_S:
                truth = x
            else:
                t0, x0 = self._prev
                truth = x0 + (x - x0) * (due - t0) / (t - t0)
            missed = not inside(w, truth)
            self.n_on += 1
            self.n_missed += missed
            self.threshold = min(1.0, max(0.0, self.threshold + c.gamma * (float(missed) - c.target_error)))
        self._prev = (t, x)

    def decide(self, t: float, probability: float, highest: float, window: tuple[float, float]) -> bool:
        """Beam on at ``t``: ``probability`` of the window at least the threshold, capped at
        ``highest`` (the largest probability the predictive distribution can give); NaN: off."""
        on = gate_probability(probability, min(self.threshold, highest))
        if on:
            self._queue.append((t, window))
        return on


def distance_outside(window: tuple[float, float], value: float) -> float:
    """How far ``value`` lies outside ``window`` (0 inside), in the trace's units."""
    return max(window[0] - value, value - window[1], 0.0)


@dataclass(frozen=True)
class GateRule:
    """window : the gating window; confident : the whole interval must be inside; min_probability :
    otherwise, with ``risk`` None, the fixed predicted probability of the window needed, in (0, 1);
    interval : the intervals' settings (coverage 0.9); risk : the threshold adapted to a tolerated
    beam-on error (:class:`RiskControl`, default α = 0.05), or None for the fixed threshold."""

    window: WindowSpec = field(default_factory=WindowSpec)
    confident: bool = False
    min_probability: float = 0.5
    interval: IntervalConfig = field(default_factory=IntervalConfig)
    risk: RiskControl | None = field(default_factory=RiskControl)

    def __post_init__(self):
        if not (math.isfinite(self.min_probability) and 0.0 < self.min_probability < 1.0):
            raise InputError(f"min_probability must be in (0, 1), got {self.min_probability!r}")

    @property
    def text(self) -> str:
        if self.confident:
            return f"whole {self.interval.coverage:g} interval inside"
        if self.risk is None:
            return f"predicted window probability >= {self.min_probability:g}"
        return (f"predicted window probability >= a threshold adapted online to a beam-on error of "
                f"{self.risk.target_error:g} (step {self.risk.gamma:g}, start {self.risk.start:g})")


@dataclass(frozen=True)
class GateSample:
    """t_s : s; predicted : the model's x(t + latency) (trace units); lo, hi : its interval (±inf before
    it is learned); window : (low, high) bounds known at t_s; probability : the predicted probability
    of the window (NaN before it is learned); beam_on : the decision for t_s + latency."""

    t_s: float
    predicted: float
    lo: float
    hi: float
    window: tuple[float, float]
    probability: float
    beam_on: bool


class BeamGate:
    """The live gate (module doc): :meth:`update` takes a sample ``(t s, x)`` and returns a
    :class:`GateSample` for the position ``latency_s`` later."""

    def __init__(self, latency_s: float, rule: GateRule | None = None, point=None):
        """``point``: the point predictor under the intervals (default: a fresh
        :class:`~lungdeform.breathing.predict.BlendPredictor` for ``latency_s``)."""
        self.latency_s = check_horizon(latency_s)
        self.rule = rule or GateRule()
        self.window = GateWindow(self.rule.window)
        point = BlendPredictor(self.latency_s) if point is None else point
        self.predictor = IntervalPredictor(point, self.rule.interval)
        self.risk = RiskThreshold(self.latency_s, self.rule.risk) if self.rule.risk is not None else None

    def update(self, t: float, x: float) -> GateSample:
        w = self.window.update(t, x)
        r = self.predictor.update(t, x)
        prob = window_probability(w, self.predictor.probability_below)
        if self.rule.confident:
            on = gate_interval(w, r.lo, r.hi)
        elif self.risk is not None:
            self.risk.observe(t, x)
            on = self.risk.decide(t, prob, self.predictor.probability_below(math.inf), w)
        else:
            on = gate_probability(prob, self.rule.min_probability)
        return GateSample(r.t_s, r.value, r.lo, r.hi, w, prob, on)
