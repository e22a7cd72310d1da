"""Cost per sample of the breathing predictors (``lungdeform bench predict``), against the linear
autoregressive baseline and no prediction timed in the same run, and against the 100 Hz budget.
Methods: ``model``, ``model_intervals`` (the model with its conformal interval,
:mod:`lungdeform.breathing.predict_interval`), ``gate`` (the live beam gate of ``stream --gate``:
window, interval, window probability and decision), ``linear``, ``none``.

The stream is a synthetic breath (a seeded, slightly irregular 0.25 Hz cycle with sensor noise) at
``rate_hz``; every sample goes through :meth:`update` of each predictor in turn, and the time of each
call is recorded after the first ``warm_s`` seconds (the predictors' stores are then filled as in
use). Records: ``{"method", "horizon_ms", "rate_hz", "samples", "seconds" (median per sample),
"mean_seconds", "p99_seconds", "ratio_to_linear", "budget_fraction"}``; ``budget_fraction`` is the
median cost over the time between samples (1 = the predictor alone would use the whole budget).
"""

from __future__ import annotations

import time

import numpy as np

from lungdeform.breathing.gating import BeamGate
from lungdeform.breathing.predict import BlendPredictor, LastSample, baseline_linear
from lungdeform.breathing.predict_interval import IntervalPredictor
from lungdeform.errors import InputError


def synthetic_breath(seconds: float, rate_hz: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, x)``: a breath of period 4 s ± 10 % (slow random walk of phase speed), amplitude 10 mm,
    inhale shorter than exhale (a squared cosine), white sensor noise 0.1 mm, at ``rate_hz``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, float(seconds), 1.0 / float(rate_hz))
    speed = 0.25 * (1.0 + 0.1 * np.tanh(np.cumsum(rng.normal(0.0, 0.02, t.size))))
    phase = np.cumsum(speed) / float(rate_hz)
    x = 10.0 * np.cos(np.pi * phase) ** 4 + rng.normal(0.0, 0.1, t.size)
    return t, x


def _time_updates(predictor, t: np.ndarray, x: np.ndarray, warm_s: float) -> np.ndarray:
    clock = time.perf_counter
    out = []
    for ti, xi in zip(t, x):
        start = clock()
        predictor.update(ti, xi)
        if ti >= warm_s:
            out.append(clock() - start)
    return np.array(out)


def bench_predict(seconds: float = 300.0, rate_hz: float = 100.0, horizon_ms: float = 400.0,
                  warm_s: float = 30.0) -> list[dict]:
    """Time the model, the linear baseline and the last sample on one synthetic stream (module doc)."""
    if not (seconds > warm_s + 10 and rate_hz > 0 and horizon_ms > 0):
        raise InputError(f"seconds must exceed warm_s + 10 ({warm_s + 10:g} s), rate_hz and horizon_ms be > 0; "
                         f"got {seconds!r}, {rate_hz!r}, {horizon_ms!r}")
    t, x = synthetic_breath(seconds, rate_hz)
    h = horizon_ms / 1000.0
    makers = {"model": lambda: BlendPredictor(h), "model_intervals": lambda: IntervalPredictor(BlendPredictor(h)),
              "gate": lambda: BeamGate(h), "linear": lambda: baseline_linear(h, dt_s=1.0 / rate_hz),
              "none": lambda: LastSample(h)}
    times = {name: _time_updates(make(), t, x, warm_s) for name, make in makers.items()}
    linear = float(np.median(times["linear"]))
    return [{"method": name, "horizon_ms": float(horizon_ms), "rate_hz": float(rate_hz), "samples": int(s.size),
             "seconds": float(np.median(s)), "mean_seconds": float(s.mean()),
             "p99_seconds": float(np.percentile(s, 99)), "ratio_to_linear": float(np.median(s)) / linear,
             "budget_fraction": float(np.median(s)) * rate_hz} for name, s in times.items()]
