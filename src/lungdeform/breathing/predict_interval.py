"""Prediction intervals for the causal breathing predictors, learned online from their own errors.

:class:`IntervalPredictor` wraps any point predictor of :mod:`lungdeform.breathing.predict` (an object
with ``update(t, x) -> x̂(t + h)``) and returns, per sample, the central prediction and a two-sided
interval ``[lo, hi]`` meant to hold ``x(t + h)`` with probability ``coverage`` (default 0.9).

Method: locally weighted split conformal prediction made online, with adaptive conformal inference
(ACI; Gibbs & Candès, NeurIPS 2021, eq. 2) so that the long-run coverage stays at the nominal level
even when the error distribution drifts:

1. At each sample the predictor gives ``x̂`` and a local scale ``s = |x̂ − x(t)| + m``: the predicted
   change (the signal moves fast → the error is larger) plus ``m``, the exponentially weighted mean
   absolute error of the recent scored predictions (floor: a still signal still has noise).
2. Once a sample at or after ``t_j + h`` has arrived, the prediction made at ``t_j`` is scored: the
   normalised signed error ``r_j = (x(t_j + h) − x̂_j) / s_j`` joins a store of the last ``memory_s`` seconds
   (at most one score per ``min_step_s``, so a 100 Hz stream keeps as many as a 20 Hz one), one store
   per direction of the predicted change (rising, falling: Mondrian conformal prediction, Vovk et al.
   2005, so that the interval is calibrated on each side of the breath; both stores together while
   one has fewer than ``min_scores``), signed (the interval may be asymmetric). Only errors
   whose truth is known at ``t`` ever enter: the interval at ``t`` is causal.
3. ACI: the working miscoverage ``α_t`` moves by ``γ·(α − miss_j)`` at each score, where ``miss_j`` says
   whether the interval given at ``t_j`` missed; ``q_t`` is the ``(1 − α_t)`` empirical quantile of the
   stored scores of the direction (with the finite-sample ``(n + 1)/n`` correction), one bound each
   side at ``α/2``; the interval is ``[x̂ + q_lo·s, x̂ + q_hi·s]``.
4. :meth:`IntervalPredictor.probability_below` reads the same stored scores as a predictive
   distribution (the share that would put the truth at or below a level), for a gate that asks how
   likely the window is.

Before ``min_scores`` scores have been stored the interval is infinite (``±inf``: the predictor does
not yet know how wrong it is; a gate must hold the beam).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from lungdeform.errors import InputError

from .predict import EPS_S, History, check_horizon


@dataclass(frozen=True)
class IntervalConfig:
    """coverage : nominal two-sided coverage in (0, 1); memory_s : s of scores kept; min_step_s : s
    between stored scores; gamma : ACI step per stored score; error_tau_s : s, time constant of the
    mean absolute error in the scale; min_scores : scores needed before the interval is finite."""

    coverage: float = 0.9
    memory_s: float = 120.0
    min_step_s: float = 0.05
    gamma: float = 0.005
    error_tau_s: float = 10.0
    min_scores: int = 20

    def __post_init__(self):
        if not (math.isfinite(self.coverage) and 0.0 < self.coverage < 1.0):
            raise InputError(f"coverage must be in (0, 1), got {self.coverage!r}")
        if not (self.memory_s > 0 and self.min_step_s >= 0 and self.gamma >= 0 and self.error_tau_s > 0
                and self.min_scores >= 1):
            raise InputError(f"interval settings out of range: {self!r}")


@dataclass(frozen=True)
class IntervalPrediction:
    """t_s : s, the sample time; value : the central prediction of x(t + h) (trace units); lo, hi :
    the interval (trace units; ±inf before it is learned); coverage : its nominal coverage."""

    t_s: float
    value: float
    lo: float
    hi: float
    coverage: float


class _Scores:
    """Scores ``(t_j, r_j)`` in time order in a numpy buffer: append at the end, forget from the front,
    read the kept values as one array view (no copy per sample)."""

    def __init__(self):
        self.t = np.zeros(256)
        self.r = np.zeros(256)
        self.start = self.end = 0

    def __len__(self) -> int:
        return self.end - self.start

    def append(self, t: float, r: float) -> None:
        if self.end == self.t.size:  # compact, and grow when more than half is in use
            n = len(self)
            size = self.t.size * (2 if 2 * n > self.t.size else 1)
            t_new, r_new = np.zeros(size), np.zeros(size)
            t_new[:n], r_new[:n] = self.t[self.start:self.end], self.r[self.start:self.end]
            self.t, self.r, self.start, self.end = t_new, r_new, 0, n
        self.t[self.end], self.r[self.end] = t, r
        self.end += 1

    def forget_before(self, t: float) -> bool:
        """Drop the scores older than ``t``; whether any was dropped."""
        k = self.start + int(np.searchsorted(self.t[self.start:self.end], t, side="left"))
        dropped, self.start = k > self.start, k
        return dropped

    @property
    def values(self) -> np.ndarray:
        return self.r[self.start:self.end]


class IntervalPredictor:
    """A point predictor with an online, causal conformal interval (module doc)."""

    def __init__(self, point, config: IntervalConfig | None = None):
        self.point = point
        self.horizon_s = check_horizon(point.horizon_s)
        self.config = config or IntervalConfig()
        half = 0.5 * (1.0 - self.config.coverage)
        self._alpha_target = half
        self._alpha = [half, half]  # working miscoverage of the lower and the upper bound (ACI)
        self._hist = History(keep_s=self.horizon_s + 2.0)
        self._queue: deque[tuple[float, float, float, int, tuple[float, float]]] = deque()
        self._scores = (_Scores(), _Scores())  # per direction: (t_j, signed r_j)
        self._t_store = -math.inf
        self._mae = math.nan
        self._t_mae = None
        self._q = [(-math.inf, math.inf), (-math.inf, math.inf)]  # per direction: (lower, upper) quantile
        self._last: tuple[float, float, int] | None = None  # newest (x̂, s, direction)
        self._r = [np.zeros(0), np.zeros(0)]  # per direction: the scores in use (see _stored)

    def _score(self, t: float) -> None:
        cfg, changed = self.config, False
        while self._queue and self._queue[0][0] + self.horizon_s <= t + EPS_S:
            tj, pj, sj, gj, (qlo, qhi) = self._queue.popleft()
            err = float(self._hist.at(np.array([tj + self.horizon_s]))[0]) - pj
            a = 1.0 if self._t_mae is None else 1.0 - math.exp(-(tj - self._t_mae) / cfg.error_tau_s)
            self._mae = abs(err) if math.isnan(self._mae) else (1.0 - a) * self._mae + a * abs(err)
            self._t_mae = tj
            if tj - self._t_store < cfg.min_step_s - EPS_S:
                continue
            self._t_store = tj
            r = err / sj if sj > 0 else 0.0
            if math.isfinite(qlo) and math.isfinite(qhi):
                self._alpha[0] += cfg.gamma * (self._alpha_target - float(r < qlo))
                self._alpha[1] += cfg.gamma * (self._alpha_target - float(r > qhi))
            self._scores[gj].append(tj, r)
            changed = True
        for store in self._scores:
            changed = store.forget_before(t - cfg.memory_s) or changed
        if changed:
            self._r = [self._stored(g) for g in range(len(self._scores))]
            self._q = [self._quantiles(r) for r in self._r]

    def _stored(self, group: int) -> np.ndarray:
        """The stored scores of a direction, or of both while that one has fewer than ``min_scores``."""
        store = self._scores[group]
        if len(store) < self.config.min_scores:
            return np.concatenate([st.values for st in self._scores])
        return store.values

    def _quantiles(self, r: np.ndarray) -> tuple[float, float]:
        """(lower, upper) bound of the normalised signed errors ``r``: the α_lo and 1 − α_hi empirical
        quantiles, widened by the finite-sample (n + 1)/n (the extreme stored score where ACI has
        pushed α to 0 or below: the interval stays finite); ∓inf while fewer than ``min_scores``."""
        n = r.size
        if n < self.config.min_scores:
            return -math.inf, math.inf
        out = []
        for alpha, sign in zip(self._alpha, (-1.0, 1.0)):
            k = min(n - 1, max(0, math.ceil((1.0 - alpha) * (n + 1)) - 1))
            out.append(float(np.partition(sign * r, k)[k]))
        return -out[0], out[1]

    def update(self, t: float, x: float) -> IntervalPrediction:
        """Take the sample ``(t, x)``; return the prediction of ``x(t + h)`` with its interval."""
        t, x = float(t), float(x)
        p = float(self.point.update(t, x))
        self._hist.add(t, x)
        self._score(t)
        mae = self._mae if math.isfinite(self._mae) else 0.0
        s = abs(p - x) + mae
        g = int(p >= x)  # direction of the predicted change: 0 falling, 1 rising
        qlo, qhi = self._q[g]
        self._last = (p, s, g)
        self._queue.append((t, p, s, g, (qlo, qhi)))
        return IntervalPrediction(t, p, p + qlo * s if math.isfinite(qlo) else -math.inf,
                                  p + qhi * s if math.isfinite(qhi) else math.inf, self.config.coverage)


    def probability_below(self, level: float) -> float:
        """The predicted probability that ``x(t + h) ≤ level`` at the newest sample (its conformal
        predictive distribution: the share of the stored normalised errors of the same direction that
        would put the truth at or below ``level``); NaN before ``min_scores`` scores."""
        if self._last is None:
            return math.nan
        p, s, g = self._last
        r = self._r[g]
        n = r.size
        if n < self.config.min_scores:
            return math.nan
        bound = (float(level) - p) / s if s > 0 else (math.inf if level >= p else -math.inf)
        return float(np.count_nonzero(r <= bound)) / (n + 1)


def interval_trace(t_s, x, point, config: IntervalConfig | None = None) -> np.ndarray:
    """Run :class:`IntervalPredictor` over a recorded trace, sample by sample (causal): ``(n, 3)`` float
    columns (prediction, lo, hi) of ``x(t_i + h)``, in the trace's units. ``point``: a fresh point
    predictor (its ``horizon_s`` sets h)."""
    t = np.asarray(t_s, float).ravel()
    v = np.asarray(x, float).ravel()
    if t.shape != v.shape or t.size < 2:
        raise InputError(f"t_s and x must be (n,) arrays of the same length >= 2, got {t.shape} and {v.shape}")
    p = IntervalPredictor(point, config)
    out = np.empty((t.size, 3))
    for i, (ti, xi) in enumerate(zip(t, v)):
        r = p.update(ti, xi)
        out[i] = (r.value, r.lo, r.hi)
    return out


def interval_score(lo, hi, truth, coverage: float) -> np.ndarray:
    """The interval score of Gneiting & Raftery (JASA 2007, Sec. 6.2) per sample, ``(n,)`` in the trace's
    units (lower is better): width plus ``2/α`` times the distance by which the truth misses, α = 1 − coverage."""
    lo, hi, y = (np.asarray(a, float) for a in (lo, hi, truth))
    alpha = 1.0 - float(coverage)
    return (hi - lo) + (2.0 / alpha) * (np.maximum(lo - y, 0.0) + np.maximum(y - hi, 0.0))
