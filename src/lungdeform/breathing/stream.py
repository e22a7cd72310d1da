"""Streaming breathing driver: one surrogate sample in, one volume estimate out, no look-ahead.

The estimator is causal and O(1) per sample (amortised):

1. A critically damped second-order low-pass: two cascaded exponential smoothers with time constant
   ``smoothing_s``, each step using the actual Δt (so uneven sampling is fine). Its group delay at low
   frequency is 2·smoothing_s (0.1 s by default).
2. A running calibration over the last ``window_s`` seconds (monotone-deque sliding minimum and
   maximum): end-exhale level = window minimum, tidal excursion = window maximum − minimum. The window
   spans two or more breaths, so baseline drift of the surrogate is followed.
3. volume = V_EE + V_T·(filtered − min)/(max − min), mL; scale s = (V − V_EE)/ΔV for playback.

With ``predict_ms`` > 0, each raw sample is first replaced by the causal prediction of the signal
``predict_ms`` later (:class:`lungdeform.breathing.predict.BlendPredictor`; with ``gate``, the same
model inside :class:`lungdeform.breathing.gating.BeamGate`, which also gives the interval and the beam
decision for ``predict_ms`` later), so the volume shown when a
frame reaches the eye (or a beam) is the one the patient then has; ``StreamSample.ahead_s`` says how far
ahead it is.

Before one full window has been seen, the calibration uses what has been seen (``warm`` is False).
Samples must come in increasing time; NaN samples, and times or amplitudes beyond ±:data:`MAX_SAMPLE`,
are refused (InputError) — drop them upstream.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d

from lungdeform.errors import InputError

from .cycles import smooth
from .gating import BeamGate, GateRule, GateSample
from .predict import BlendPredictor

#: The longest prediction horizon (ms) the estimator, ``lungdeform stream`` and ``lungdeform view``
#: accept: past 2 s the prediction error nears a half breath.
MAX_PREDICT_MS = 2000.0
#: Largest magnitude of a sample's time (s) and amplitude (the trace's unit): beyond it the
#: calibration's differences overflow or lose every digit (a corrupt or mis-scaled feed).
MAX_SAMPLE = 1e9
#: Largest end-exhale or tidal volume (mL) the estimator accepts: above any total lung capacity.
MAX_VOLUME_ML = 20000.0


@dataclass(frozen=True)
class StreamSample:
    """t_s : s; amplitude : the filtered surrogate (trace unit); volume_ml : mL; scale : (V − V_EE)/ΔV
    (NaN without ``unit_ml``); warm : True once a full calibration window has been seen; ahead_s : s,
    the time after ``t_s`` the estimate is for (the prediction horizon; 0 without prediction); gate :
    with ``gate``, the beam decision for ``t_s + ahead_s`` with the prediction's interval (raw signal
    units)."""

    t_s: float
    amplitude: float
    volume_ml: float
    scale: float
    warm: bool
    ahead_s: float = 0.0
    gate: GateSample | None = None


class StreamingVolumeEstimator:
    """Causal amplitude → volume estimator (see module doc). Call :meth:`update` once per sample."""

    def __init__(self, tidal_volume_ml: float = 500.0, v_ee_ml: float = 2400.0, window_s: float = 10.0,
                 smoothing_s: float = 0.05, unit_ml: float | None = None, predict_ms: float = 0.0,
                 gate: GateRule | None = None):
        if not (math.isfinite(float(tidal_volume_ml)) and 0 < float(tidal_volume_ml) <= MAX_VOLUME_ML):
            raise InputError(f"tidal_volume_ml must be a finite volume in (0, {MAX_VOLUME_ML:g}] mL, "
                             f"got {tidal_volume_ml!r}")
        if not (math.isfinite(float(v_ee_ml)) and 0 <= float(v_ee_ml) <= MAX_VOLUME_ML):
            raise InputError(f"v_ee_ml must be a finite volume in [0, {MAX_VOLUME_ML:g}] mL (0: volumes above "
                             f"end-exhale), got {v_ee_ml!r}")
        if not (math.isfinite(float(window_s)) and window_s > 0
                and math.isfinite(float(smoothing_s)) and smoothing_s >= 0):
            raise InputError(f"window_s must be finite and > 0 and smoothing_s finite and >= 0, got "
                             f"{window_s!r} and {smoothing_s!r}")
        if unit_ml is not None and not (np.isfinite(unit_ml) and unit_ml != 0):
            raise InputError(f"unit_ml must be a finite non-zero volume in mL, got {unit_ml!r}")
        self.tidal_volume_ml = float(tidal_volume_ml)
        self.v_ee_ml = float(v_ee_ml)
        self.window_s = float(window_s)
        self.smoothing_s = float(smoothing_s)
        self.unit_ml = unit_ml
        if not (math.isfinite(float(predict_ms)) and 0.0 <= float(predict_ms) <= MAX_PREDICT_MS):
            raise InputError(f"predict_ms must be in [0, {MAX_PREDICT_MS:g}] ms, got {predict_ms!r}")
        self.predict_ms = float(predict_ms)
        if gate is not None and self.predict_ms <= 0:
            raise InputError("gating needs predict_ms > 0: the beam's latency, the horizon its decision is for")
        self.gate = gate
        self.reset()

    def reset(self) -> None:
        self._t = None
        self._t0 = None
        self._s1 = self._s2 = 0.0
        self._min: deque = deque()
        self._max: deque = deque()
        self._predictor = BlendPredictor(self.predict_ms / 1000.0) if self.predict_ms > 0 and self.gate is None \
            else None
        self._gate = BeamGate(self.predict_ms / 1000.0, self.gate) if self.gate is not None else None

    def update(self, t_s: float, amplitude: float) -> StreamSample:
        """Feed one sample (time s, amplitude in the trace unit); returns the estimate for it."""
        t = float(t_s)
        x = float(amplitude)
        if not (math.isfinite(t) and math.isfinite(x)):
            raise InputError(f"stream sample at t={t_s!r} is not finite (amplitude {amplitude!r})")
        if not (abs(t) <= MAX_SAMPLE and abs(x) <= MAX_SAMPLE):
            raise InputError(f"stream sample at t={t:g} s, amplitude {x:g}: beyond ±{MAX_SAMPLE:g} (a corrupt "
                             f"or mis-scaled feed)")
        if (self._predictor is not None or self._gate is not None) and self._t is not None and t <= self._t:
            raise InputError(f"stream time must increase: got t={t:.6g} s after t={self._t:.6g} s")
        gate = self._gate.update(t, x) if self._gate is not None else None
        if gate is not None:
            x = gate.predicted
        elif self._predictor is not None:
            x = self._predictor.update(t, x)
        if self._t is None:
            self._t0 = t
            self._s1 = self._s2 = x
        else:
            dt = t - self._t
            if dt <= 0:
                raise InputError(f"stream time must increase: got t={t:.6g} s after t={self._t:.6g} s")
            alpha = 1.0 - math.exp(-dt / self.smoothing_s) if self.smoothing_s > 0 else 1.0
            self._s1 += alpha * (x - self._s1)
            self._s2 += alpha * (self._s1 - self._s2)
        self._t = t
        y = self._s2
        # sliding-window extrema (monotone deques of (t, value))
        for dq, better in ((self._min, lambda a, b: a <= b), (self._max, lambda a, b: a >= b)):
            while dq and better(y, dq[-1][1]):
                dq.pop()
            dq.append((t, y))
            while dq[0][0] < t - self.window_s:
                dq.popleft()
        lo, hi = self._min[0][1], self._max[0][1]
        span = hi - lo
        frac = (y - lo) / span if span > 0 else 0.0
        volume = self.v_ee_ml + self.tidal_volume_ml * frac
        scale = (volume - self.v_ee_ml) / self.unit_ml if self.unit_ml else float("nan")
        return StreamSample(t, y, volume, scale, t - self._t0 >= self.window_s, self.predict_ms / 1000.0, gate)


def replay(t_s, amplitude, estimator: StreamingVolumeEstimator, clock=time.perf_counter):
    """Drive ``estimator`` with a recorded trace one sample at a time (as a live feed would).

    Returns (volume_ml (n,) float, seconds (n,) float: the wall time each update took).
    """
    t = np.asarray(t_s, dtype=float)
    a = np.asarray(amplitude, dtype=float)
    if t.shape != a.shape or t.ndim != 1:
        raise InputError(f"t_s and amplitude must be (n,) of one length, got {t.shape} and {a.shape}")
    vol = np.empty_like(t)
    secs = np.empty_like(t)
    for i in range(t.size):
        c0 = clock()
        vol[i] = estimator.update(t[i], a[i]).volume_ml
        secs[i] = clock() - c0
    return vol, secs


def parse_sample(line: str, lineno: int, source: str = "stdin") -> tuple[float, float] | None:
    """One live sample from a text line ``t_s,amplitude`` (comma, semicolon, tab or space separated);
    None for a blank line, a ``#`` comment or a header; InputError naming ``source`` and the line
    number for anything else that is not two finite numbers."""
    text = line.strip()
    if not text or text.startswith("#"):
        return None
    parts = [p for p in text.replace(";", ",").replace("\t", ",").replace(" ", ",").split(",") if p]
    try:
        t, x = (float(v) for v in parts[:2]) if len(parts) >= 2 else (None, None)
    except ValueError:
        if lineno == 1:  # a header line
            return None
        raise InputError(f"{source} line {lineno}: expected 't_s,amplitude', got {text[:60]!r}") from None
    if t is None or not (math.isfinite(t) and math.isfinite(x)):
        raise InputError(f"{source} line {lineno}: expected two finite numbers 't_s,amplitude', got {text[:60]!r}")
    return t, x


def stream_lines(lines, estimator: StreamingVolumeEstimator, source: str = "stdin"):
    """Drive ``estimator`` with text lines as they arrive (:func:`parse_sample`); yields one
    :class:`StreamSample` per sample, at once (no look-ahead, no buffering)."""
    for lineno, line in enumerate(lines, 1):
        sample = parse_sample(line, lineno, source)
        if sample is not None:
            try:
                yield estimator.update(*sample)
            except InputError as exc:
                raise InputError(f"{source} line {lineno}: {exc}") from None


def signal_delay_s(t_s, reference, estimate, max_lag_s: float = 1.0) -> float:
    """Lag (s) of ``estimate`` behind ``reference`` maximising their correlation (uniform t_s)."""
    t = np.asarray(t_s, float)
    dt = float(np.median(np.diff(t)))
    r = np.asarray(reference, float) - np.mean(reference)
    e = np.asarray(estimate, float) - np.mean(estimate)
    best, lag_best = -np.inf, 0
    for lag in range(0, int(max_lag_s / dt) + 1):
        c = float(np.dot(r[: r.size - lag], e[lag:]))
        if c > best:
            best, lag_best = c, lag
    return lag_best * dt


def offline_volume(t_s, amplitude, tidal_volume_ml: float = 500.0, v_ee_ml: float = 2400.0,
                   window_s: float = 10.0, cutoff_hz: float = 1.5) -> np.ndarray:
    """The non-causal twin of the streaming estimator: zero-phase low-pass and a *centred* sliding
    min/max window (uniform t_s). Comparing the stream against it isolates what causality costs."""


    t = np.asarray(t_s, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    y = smooth(np.asarray(amplitude, float), fs, cutoff_hz)
    size = max(3, int(round(window_s * fs)))
    lo = minimum_filter1d(y, size, mode="nearest")
    hi = maximum_filter1d(y, size, mode="nearest")
    span = np.where(hi > lo, hi - lo, 1.0)
    return v_ee_ml + tidal_volume_ml * (y - lo) / span
