"""Causal prediction of a breathing signal ``h`` seconds ahead, to cancel the latency of a display or
a beam (100–500 ms): from the samples up to time ``t`` predict the signal at ``t + h``.

Every predictor here is online and causal: :meth:`Predictor.update` takes one sample ``(t, x)`` (s,
trace units; increasing ``t``, any spacing) and returns the prediction of ``x(t + h)``; it never sees a
sample after ``t``. A training pair (the features at an earlier ``t_j``, the signal at ``t_j + h``)
enters the fit only once a sample at or after ``t_j + h`` has arrived.

Features. The signal is read on a fixed internal step ``dt_s`` (0.1 s) back from the newest sample,
by linear interpolation between received samples, so irregular sampling and short gaps need no
resampling upstream: ``f_k = x(t − k·dt) − x(t)``, k = 1…L−1, over a window of ``window_s``. The
target is ``x(t + h) − x(t)``. Both are differences from the newest sample, so a drifting baseline
does not enter the fit (amplitude drift is followed by the fits' forgetting).

Predictors (one class each; :class:`BlendPredictor` is the model of ``lungdeform validate prediction``):

- :class:`LastSample`: no prediction, ``x̂ = x(t)``;
- :class:`LinearPredictor`: least squares with an intercept on the window, trained on the pairs of
  the last ``train_s`` seconds or on every pair with exponential forgetting (half-life
  ``half_life_s``), with a ridge, refitted every ``refit_s``. The validation's online autoregressive
  baseline is one (:func:`baseline_linear`, its settings searched on the shared traces as the
  model's were: :data:`LINEAR_TUNED`; :func:`baseline_linear_plain`, the untuned one of ≤ 0.7: the
  last 2 s of samples, trained on the preceding 30 s, refitted every 5 s); so is the model's own
  linear part;
- :class:`AnalogPredictor`: the cycle's shape and phase, learned from the patient's own earlier breaths
  (analog or nearest-neighbour forecasting): the ``k`` past windows most like the newest one, and
  what followed each of them ``h`` later, weighted by inverse distance. A linear model of the last
  2 s cannot know where in the breath the signal is; an earlier breath that looked the same does;
- :class:`BlendPredictor`: the linear and analog predictions weighted by the inverse of their recent
  squared errors (exponentially weighted over ``error_tau_s``), so the better one on this patient,
  now, dominates.

Cost per sample (``lungdeform bench predict``): a few tens of µs, mostly the analog search over at most
``memory_s`` of stored windows; 100 Hz streaming needs < 10 ms.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from lungdeform.errors import InputError

#: internal step of the feature window (s): 10 Hz reads a breath (0.2–0.5 Hz) finely enough
DT_S = 0.1
#: sample times within this of each other count as equal (s): times like 0.1·k carry rounding
EPS_S = 1e-9


def check_horizon(horizon_s: float) -> float:
    """``horizon_s`` as a float in (0, 5] s, or InputError naming it."""
    h = float(horizon_s)
    if not (math.isfinite(h) and 0.0 < h <= 5.0):
        raise InputError(f"horizon_s must be in (0, 5] s, got {horizon_s!r}")
    return h


class History:
    """The received samples ``(t s, x)``, kept for ``keep_s`` seconds, read by linear interpolation."""

    def __init__(self, keep_s: float):
        self.keep_s = float(keep_s)
        self.t: deque[float] = deque()
        self.x: deque[float] = deque()

    def add(self, t: float, x: float) -> None:
        if not (math.isfinite(t) and math.isfinite(x)):
            raise InputError(f"sample ({t!r}, {x!r}) is not finite: drop it upstream")
        if self.t and t <= self.t[-1]:
            raise InputError(f"sample times must increase: {t!r} after {self.t[-1]!r}")
        self.t.append(float(t))
        self.x.append(float(x))
        while self.t[0] < t - self.keep_s and len(self.t) > 2:
            self.t.popleft()
            self.x.popleft()

    @property
    def span_s(self) -> float:
        return self.t[-1] - self.t[0] if self.t else 0.0

    def at(self, times: np.ndarray) -> np.ndarray:
        """The signal at ``times : (m,) float`` s (clamped to the first sample before the history)."""
        return np.interp(times, np.fromiter(self.t, float), np.fromiter(self.x, float))


class Predictor:
    """Base of the window predictors: keeps the history, makes features, queues training pairs.

    Subclasses implement :meth:`_learn` (a pair whose target has arrived) and :meth:`_predict`
    (the newest sample and its features → predicted ``x(t + h) − x(t)``)."""

    def __init__(self, horizon_s: float, window_s: float = 2.0, dt_s: float = DT_S):
        self.horizon_s = check_horizon(horizon_s)
        self.dt_s = float(dt_s)
        self.n_lags = max(2, int(round(float(window_s) / self.dt_s)) + 1)
        self.history = History(keep_s=self.n_lags * self.dt_s + self.horizon_s + 1.0)
        self._pending: deque[tuple[float, float, np.ndarray]] = deque()  # (t_j, x(t_j), features)

    def features(self, t: float, x: float) -> np.ndarray | None:
        """``(L − 1,)`` differences ``x(t − k·dt) − x(t)``, or None while the history is shorter."""
        if self.history.span_s < (self.n_lags - 1) * self.dt_s - EPS_S:
            return None
        lags = t - self.dt_s * np.arange(1, self.n_lags)
        return self.history.at(lags) - x

    def update(self, t: float, x: float) -> float:
        """Take the sample ``(t, x)``; return the prediction of ``x(t + h)`` (trace units)."""
        t, x = float(t), float(x)
        self.history.add(t, x)
        while self._pending and self._pending[0][0] + self.horizon_s <= t + EPS_S:
            tj, xj, fj = self._pending.popleft()
            self._learn(tj, xj, fj, float(self.history.at(np.array([tj + self.horizon_s]))[0]) - xj)
        f = self.features(t, x)
        if f is None:
            return x
        self._pending.append((t, x, f))
        delta = self._predict(t, x, f)
        return x if delta is None else x + delta

    def _learn(self, t: float, x: float, features: np.ndarray, target: float) -> None:  # pragma: no cover
        raise NotImplementedError

    def _predict(self, t: float, x: float, features: np.ndarray) -> float | None:  # pragma: no cover
        raise NotImplementedError


class LastSample:
    """No prediction: the newest sample (the yardstick every predictor is measured against)."""

    def __init__(self, horizon_s: float):
        self.horizon_s = check_horizon(horizon_s)

    def update(self, t: float, x: float) -> float:
        return float(x)


class LinearPredictor(Predictor):
    """Least squares with an intercept on the window: the features and the newest sample itself (so
    that the model is the plain autoregression on the window's samples, which may revert to the mean).

    ``train_s``: only pairs of the last ``train_s`` seconds are used (None: all, with forgetting of
    half-life ``half_life_s``, None: none); ``refit_s``: seconds between refits; ``ridge``: Tikhonov
    weight relative to the mean diagonal of the normal matrix (0: plain least squares)."""

    def __init__(self, horizon_s: float, window_s: float = 2.0, *, train_s: float | None = None,
                 refit_s: float = 1.0, half_life_s: float | None = 120.0, ridge: float = 1e-3,
                 dt_s: float = DT_S):
        super().__init__(horizon_s, window_s, dt_s)
        self.train_s = None if train_s is None else float(train_s)
        self.refit_s = float(refit_s)
        self.half_life_s = None if half_life_s is None else float(half_life_s)
        self.ridge = float(ridge)
        m = self.n_lags + 1  # L − 1 features, the newest sample, the intercept
        self._rows: deque[tuple[float, np.ndarray, float]] = deque()
        self._a = np.zeros((m, m))
        self._b = np.zeros(m)
        self._t_acc = None
        self._count = 0
        self._coef: np.ndarray | None = None
        self._t_fit = -math.inf

    def _learn(self, t: float, x: float, features: np.ndarray, target: float) -> None:
        row = np.concatenate([features, (x, 1.0)])
        if self.train_s is not None:
            self._rows.append((t, row, target))
            while self._rows and self._rows[0][0] < t - self.train_s - EPS_S:
                self._rows.popleft()
            return
        if self.half_life_s is not None and self._t_acc is not None:
            decay = 0.5 ** ((t - self._t_acc) / self.half_life_s)
            self._a *= decay
            self._b *= decay
        self._t_acc = t
        self._count += 1
        self._a += np.outer(row, row)
        self._b += row * target

    def _normal(self) -> tuple[np.ndarray, np.ndarray, int]:
        if self.train_s is None:
            return self._a, self._b, self._count
        if not self._rows:
            return self._a, self._b, 0
        x = np.stack([r[1] for r in self._rows])
        y = np.array([r[2] for r in self._rows])
        return x.T @ x, x.T @ y, len(y)

    def _predict(self, t: float, x: float, features: np.ndarray) -> float | None:
        if t - self._t_fit >= self.refit_s or self._coef is None:
            a, b, n = self._normal()
            if n > self.n_lags:
                lam = self.ridge * np.trace(a) / len(a)
                reg = lam * np.eye(len(a))
                reg[-1, -1] = 0.0  # the intercept is not shrunk
                try:
                    self._coef = np.linalg.solve(a + reg, b)
                    self._t_fit = t
                except np.linalg.LinAlgError:
                    pass  # singular (flat signal so far): keep the last fit, or none
        return None if self._coef is None else float(np.concatenate([features, (x, 1.0)]) @ self._coef)


class AnalogPredictor(Predictor):
    """Nearest-neighbour (analog) forecast over the stored windows of the last ``memory_s`` seconds:
    the ``neighbours`` most similar (Euclidean distance of the feature vectors) vote with weight
    1/distance on what followed them ``h`` later. A window is stored at most every half step
    (``dt_s / 2``), so a fast stream (100 Hz) keeps no more windows than the breath needs."""

    def __init__(self, horizon_s: float, window_s: float = 2.5, *, neighbours: int = 20,
                 memory_s: float = 300.0, dt_s: float = DT_S):
        super().__init__(horizon_s, window_s, dt_s)
        self.neighbours = int(neighbours)
        self.memory_s = float(memory_s)
        cap = int(self.memory_s / self.dt_s * 2) + 16  # at most one row per half step
        self._f = np.zeros((cap, self.n_lags - 1))
        self._y = np.zeros(cap)
        self._t = np.zeros(cap)
        self._n = 0
        self._t_last = -math.inf

    def _learn(self, t: float, x: float, features: np.ndarray, target: float) -> None:
        if t - self._t_last < 0.5 * self.dt_s:
            return
        self._t_last = t
        if self._n and self._t[0] < t - self.memory_s:  # forget the oldest rows in one block
            keep = self._t[: self._n] >= t - self.memory_s
            k = int(keep.sum())
            self._f[:k], self._y[:k], self._t[:k] = self._f[: self._n][keep], self._y[: self._n][keep], \
                self._t[: self._n][keep]
            self._n = k
        if self._n == len(self._y):
            self._f = np.concatenate([self._f, np.zeros_like(self._f)])
            self._y = np.concatenate([self._y, np.zeros_like(self._y)])
            self._t = np.concatenate([self._t, np.zeros_like(self._t)])
        self._f[self._n], self._y[self._n], self._t[self._n] = features, target, t
        self._n += 1

    def _predict(self, t: float, x: float, features: np.ndarray) -> float | None:
        n = self._n
        if n < self.neighbours:
            return None
        d2 = np.einsum("ij,ij->i", self._f[:n] - features, self._f[:n] - features)
        idx = np.argpartition(d2, self.neighbours - 1)[: self.neighbours]
        w = 1.0 / (np.sqrt(d2[idx]) + 1e-9)
        return float(w @ self._y[idx] / w.sum())


class BlendPredictor:
    """The model: :class:`LinearPredictor` (a 1.5 s window, every pair with a forgetting half-life of
    60 s, ridge 1e-4) and :class:`AnalogPredictor` (2 s windows, 30 neighbours), weighted by the
    inverse of their exponentially weighted recent squared errors (time constant ``error_tau_s``);
    equal weights until both have been scored. These settings were chosen on the 16 shared breathing
    traces (docs/PREDICTION.md gives the figures and the variants tried)."""

    def __init__(self, horizon_s: float, *, error_tau_s: float = 20.0, dt_s: float = DT_S):
        self.horizon_s = check_horizon(horizon_s)
        self.parts = (LinearPredictor(horizon_s, window_s=1.5, half_life_s=60.0, ridge=1e-4, dt_s=dt_s),
                      AnalogPredictor(horizon_s, window_s=2.0, neighbours=30, dt_s=dt_s))
        self.error_tau_s = float(error_tau_s)
        self._mse = np.full(len(self.parts), np.nan)
        self._queue: deque[tuple[float, np.ndarray]] = deque()  # (t_j, predictions at t_j)
        self._hist = History(keep_s=self.horizon_s + 2.0)
        self._t_err = None

    @property
    def weights(self) -> np.ndarray:
        """The current weight of each part (sum 1)."""
        if not np.all(np.isfinite(self._mse)):
            return np.full(len(self.parts), 1.0 / len(self.parts))
        w = 1.0 / (self._mse + 1e-300)
        return w / w.sum()

    def _score(self, t: float) -> None:
        while self._queue and self._queue[0][0] + self.horizon_s <= t + EPS_S:
            tj, preds = self._queue.popleft()
            truth = float(self._hist.at(np.array([tj + self.horizon_s]))[0])
            e2 = (preds - truth) ** 2
            a = 1.0 if self._t_err is None else 1.0 - math.exp(-(tj - self._t_err) / self.error_tau_s)
            self._t_err = tj
            self._mse = np.where(np.isfinite(self._mse), (1 - a) * self._mse + a * e2, e2)

    def update(self, t: float, x: float) -> float:
        self._hist.add(float(t), float(x))
        self._score(float(t))
        preds = np.array([p.update(t, x) for p in self.parts])
        self._queue.append((float(t), preds))
        return float(self.weights @ preds)


@dataclass(frozen=True)
class LinearSettings:
    """The settings of a :class:`LinearPredictor`: ``window_s`` s; the training memory, ``train_s`` s
    of pairs, or (``train_s`` None) every pair with a forgetting half-life ``half_life_s`` s (None:
    no forgetting); ``refit_s`` s between refits; ``ridge`` relative to the normal matrix's mean
    diagonal."""

    window_s: float = 2.0
    train_s: float | None = None
    half_life_s: float | None = 120.0
    refit_s: float = 1.0
    ridge: float = 1e-3

    def predictor(self, horizon_s: float, dt_s: float = DT_S) -> LinearPredictor:
        return LinearPredictor(horizon_s, self.window_s, train_s=self.train_s, refit_s=self.refit_s,
                               half_life_s=self.half_life_s, ridge=self.ridge, dt_s=dt_s)


#: The linear baseline, tuned: the settings chosen by the search of ``scripts/tune_linear_baseline.py``
#: on the 16 shared breathing traces, as the model's were (docs/PREDICTION.md "The linear baseline, tuned").
LINEAR_TUNED = LinearSettings(window_s=1.5, train_s=None, half_life_s=None, refit_s=0.5, ridge=1e-4)
#: The untuned linear baseline of lungdeform ≤ 0.7 (``linear_plain``): the last 2 s of samples, trained
#: on the preceding 30 s, refitted every 5 s, no ridge.
LINEAR_PLAIN = LinearSettings(window_s=2.0, train_s=30.0, half_life_s=None, refit_s=5.0, ridge=0.0)


def baseline_linear(horizon_s: float, dt_s: float = DT_S) -> LinearPredictor:
    """The online linear autoregressive baseline, tuned (:data:`LINEAR_TUNED`): least squares with an
    intercept on the window of samples (``dt_s``: the trace's sample interval)."""
    return LINEAR_TUNED.predictor(horizon_s, dt_s)


def baseline_linear_plain(horizon_s: float, dt_s: float = DT_S) -> LinearPredictor:
    """The untuned linear baseline of lungdeform ≤ 0.7 (:data:`LINEAR_PLAIN`, ``linear_plain``)."""
    return LINEAR_PLAIN.predictor(horizon_s, dt_s)


#: name → factory(horizon_s) of the predictors the validation runs
PREDICTORS = {"model": BlendPredictor, "none": LastSample, "linear": baseline_linear,
              "linear_plain": baseline_linear_plain}
#: the predictors that read the trace's own sample interval (``dt_s``)
TRACE_STEP = ("linear", "linear_plain")


def predict_trace(t_s, x, horizon_s: float, predictor="model") -> np.ndarray:
    """Run a predictor over a whole recorded trace, sample by sample (causal): ``(n,)`` predictions of
    ``x(t_i + h)`` made at each ``t_i``. ``predictor``: a name of :data:`PREDICTORS` or a factory of
    ``horizon_s``. The linear baselines (:data:`TRACE_STEP`) read the trace's own median sample interval."""
    t = np.asarray(t_s, float).ravel()
    v = np.asarray(x, float).ravel()
    if t.shape != v.shape or t.size < 2:
        raise InputError(f"t_s and x must be (n,) arrays of the same length >= 2, got {t.shape} and {v.shape}")
    if isinstance(predictor, str) and predictor in TRACE_STEP:
        p = PREDICTORS[predictor](horizon_s, dt_s=float(np.median(np.diff(t))))
    else:
        p = (PREDICTORS[predictor] if isinstance(predictor, str) else predictor)(horizon_s)
    return np.array([p.update(ti, xi) for ti, xi in zip(t, v)])
