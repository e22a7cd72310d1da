"""A recorded breathing trace played in the viewer, with the latency it compensates (docs/PREDICTION.md).

The viewer never estimates or predicts anything itself: the one causal estimator,
:class:`lungdeform.breathing.stream.StreamingVolumeEstimator`, is run here over the trace one sample
at a time, exactly as ``lungdeform stream TRACE [--predict-ms H]`` runs it, twice: without prediction
(the *measured* volume) and with ``predict_ms`` (the *predicted* volume, for ``t_s + ahead_s``). The
viewer plays the samples by their time: at trace time ``t`` it shows the volume of the newest sample
with ``t_s <= t`` (:func:`trace_payload`, served as ``/trace.json`` by
:class:`lungdeform.playback.server.ViewerServer`).

With ``predict_ms`` > 0 the predicting estimator runs with a gate
(:class:`lungdeform.breathing.gating.BeamGate`, as ``lungdeform stream --gate``; its point
predictor is the same :class:`~lungdeform.breathing.predict.BlendPredictor`, so the predicted volume
is unchanged): per sample the series also carries, in the trace's units, the signal predicted for
``t_s + ahead_s`` with its conformal interval, the gating window known at ``t_s`` and the beam
decision (:func:`gate_fields`; JSON ``null`` where a bound is infinite or not yet learned).
"""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path

import numpy as np

from lungdeform.breathing.gating import GateRule, GateSample
from lungdeform.breathing.stream import MAX_PREDICT_MS, StreamingVolumeEstimator, parse_sample
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError

#: The longest latency the viewer compensates (ms): the estimator's, as for ``lungdeform stream``.
VIEW_MAX_PREDICT_MS = MAX_PREDICT_MS
TRACE_SCHEMA = "lungdeform.trace-prediction"
TRACE_SCHEMA_VERSION = 2
#: the per-sample gate fields (:func:`gate_fields`), in the order the viewer reads them
GATE_KEYS = ("amplitude", "predicted", "lo", "hi", "window_low", "window_high", "probability", "beam_on")


def check_view_predict_ms(predict_ms: float) -> float:
    """``predict_ms`` as a float in [0, :data:`VIEW_MAX_PREDICT_MS`], or InputError naming ``--predict-ms``."""
    h = float(predict_ms)
    if not (math.isfinite(h) and 0.0 <= h <= VIEW_MAX_PREDICT_MS):
        raise InputError(f"--predict-ms must be in [0, {VIEW_MAX_PREDICT_MS:g}] ms, got {predict_ms!r}")
    return h


def _finite(v: float) -> float | None:
    """``v``, or None (JSON null) where it is infinite or NaN: strict JSON has neither."""
    return v if math.isfinite(v) else None


def gate_fields(amplitude: float, g: GateSample) -> dict:
    """One sample's gate fields (:data:`GATE_KEYS`), trace units: ``amplitude`` the raw sample at
    ``t_s``; ``predicted``, ``lo``, ``hi`` the signal predicted for ``t_s + ahead_s`` and its interval
    (None before it is learned); ``window_low``, ``window_high`` the window known at ``t_s`` (None on
    its open side); ``probability`` the predicted probability of the window (None before it is
    learned); ``beam_on`` the decision for ``t_s + ahead_s``."""
    return {"amplitude": float(amplitude), "predicted": _finite(g.predicted), "lo": _finite(g.lo),
            "hi": _finite(g.hi), "window_low": _finite(g.window[0]), "window_high": _finite(g.window[1]),
            "probability": _finite(g.probability), "beam_on": bool(g.beam_on)}


def gate_meta(rule: GateRule, predict_ms: float) -> dict:
    """What the gate fields mean: the window, the decision rule, the interval's coverage, the latency."""
    return {"window": rule.window.text, "window_kind": rule.window.kind, "span_s": rule.window.span_s,
            "rule": rule.text, "coverage": rule.interval.coverage, "latency_ms": float(predict_ms)}


def _estimators(predict_ms: float, gate: GateRule | None, estimator: dict):
    """The measured (no prediction) and predicting estimators; the latter gated when ``predict_ms`` > 0."""
    rule = (gate or GateRule()) if predict_ms > 0 else None
    return (StreamingVolumeEstimator(predict_ms=0.0, **estimator),
            StreamingVolumeEstimator(predict_ms=predict_ms, gate=rule, **estimator), rule)


def prediction_series(t_s, amplitude, predict_ms: float = 0.0, gate: GateRule | None = None,
                      **estimator) -> dict:
    """The measured and predicted volume per sample, each from a causal estimator fed in order.

    t_s : (n,) float, s, increasing; amplitude : (n,) float, trace unit (inhalation positive);
    ``gate``: the gating rule with ``predict_ms`` > 0 (default :class:`GateRule`: end-exhale 30 %,
    90 % intervals); ``estimator``: the other :class:`StreamingVolumeEstimator` settings (tidal volume,
    V_EE, window). Returns ``t_s``, ``measured_ml`` (``predict_ms = 0``), ``predicted_ml``
    (``predict_ms``) and ``ahead_s`` (each (n,) lists; mL, s), the scalars ``predict_ms``,
    ``tidal_volume_ml``, ``v_ee_ml``, and ``gate``: None without prediction, else :func:`gate_meta`
    with one (n,) list per :data:`GATE_KEYS` entry (:func:`gate_fields`). Sample i uses samples
    0…i only, so a prefix of the trace gives a prefix of the series.
    """
    t = np.asarray(t_s, dtype=float)
    a = np.asarray(amplitude, dtype=float)
    if t.ndim != 1 or t.shape != a.shape or t.size < 2:
        raise InputError(f"t_s and amplitude must be (n,) of one length >= 2, got {t.shape} and {a.shape}")
    plain, ahead, rule = _estimators(predict_ms, gate, estimator)
    measured, predicted, ahead_s = [], [], []
    gated: dict[str, list] = {k: [] for k in GATE_KEYS}
    for ti, xi in zip(t.tolist(), a.tolist()):
        measured.append(plain.update(ti, xi).volume_ml)
        s = ahead.update(ti, xi)
        predicted.append(s.volume_ml)
        ahead_s.append(s.ahead_s)
        if s.gate is not None:
            for k, v in gate_fields(xi, s.gate).items():
                gated[k].append(v)
    return {"t_s": t.tolist(), "measured_ml": measured, "predicted_ml": predicted, "ahead_s": ahead_s,
            "predict_ms": ahead.predict_ms, "tidal_volume_ml": ahead.tidal_volume_ml, "v_ee_ml": ahead.v_ee_ml,
            "gate": None if rule is None else {**gate_meta(rule, ahead.predict_ms), **gated}}


def trace_payload(path=None, predict_ms: float = 0.0, gate: GateRule | None = None) -> dict:
    """What ``/trace.json`` holds: the trace at ``path`` (any file ``lungdeform stream`` reads) with
    :func:`prediction_series` (``gate``: its gating rule) under ``"trace"``, or ``"trace": null``
    without a path."""
    check_view_predict_ms(predict_ms)
    body = None
    if path is not None:
        tr = read_trace(Path(path))
        try:
            series = prediction_series(tr.t_s, tr.amplitude, predict_ms, gate)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
        body = {"source": str(path), "unit": tr.unit, "fixes": list(tr.fixes), **series}
    return {"schema": TRACE_SCHEMA, "schema_version": TRACE_SCHEMA_VERSION,
            "meaning": "per sample, in time order: measured_ml = the causal streaming volume estimate "
                       "(lungdeform stream), predicted_ml = the same with the signal predicted ahead_s "
                       "later; with prediction, gate: per sample in the trace's units the raw amplitude, "
                       "the signal predicted ahead_s later with its interval [lo, hi], the gating window "
                       "[window_low, window_high] known then (null: open or not yet learned) and the beam "
                       "decision for t_s + ahead_s; sample i uses samples 0..i only",
            "trace": body}


def check_view_options(model, trace=None, curve=None, predict_ms: float = 0.0, gate: GateRule | None = None) -> None:
    """Refuse, naming the options, a ``--trace`` (file or ``-``) with a ``.glb`` (play it from the model
    file) or with ``--curve`` (one source of the volume), ``--predict-ms`` without a trace or out
    of [0, 2000] ms, and a gating rule (``--window``, ``--confident``, ``--coverage``) without
    ``--predict-ms`` > 0 (the gate decides for the position that latency later)."""
    check_view_predict_ms(predict_ms)
    if gate is not None and not predict_ms > 0:
        raise InputError("--window, --confident and --coverage set the gate of --predict-ms H > 0: give the latency")
    if trace is None:
        if predict_ms:
            raise InputError("--predict-ms applies to a --trace; give the trace to predict")
        return
    if Path(model).suffix.lower() == ".glb":
        raise InputError(f"{model}: --trace plays through a model file (.npz), not an exported .glb")
    if curve is not None:
        raise InputError(f"--trace and --curve both give the breathing volume; pass one ({trace}, {curve})")


def view_trace_json(model, trace=None, curve=None, predict_ms: float = 0.0, gate: GateRule | None = None) -> bytes:
    """``/trace.json`` for ``lungdeform view MODEL [--trace TRACE] [--curve CSV] [--predict-ms H]``
    (:func:`check_view_options` first, so nothing is read on a bad combination)."""
    check_view_options(model, trace, curve, predict_ms, gate)
    return trace_json(trace, predict_ms, gate)


def trace_json(path=None, predict_ms: float = 0.0, gate: GateRule | None = None) -> bytes:
    """:func:`trace_payload` as UTF-8 JSON (strict: no NaN or Infinity, which browsers refuse)."""
    return json.dumps(trace_payload(path, predict_ms, gate), ensure_ascii=False, allow_nan=False).encode("utf-8")


class LiveFeed:
    """A live signal for the viewer (``lungdeform view MODEL --trace -``): ``t_s,amplitude`` lines in
    (:meth:`push_lines`, in the caller's thread, as they arrive), one Server-Sent Event per sample out
    (:meth:`events`, for ``/live``): ``{"t_s", "measured_ml", "predicted_ml", "ahead_s"}`` from the same
    two causal estimators as :func:`prediction_series` (with ``predict_ms`` > 0 also ``"gate"``: the
    sample's :func:`gate_fields`); ``event: end`` once the input ends.

    Every event is kept (about 110 bytes a sample, 340 with the gate: 40 MB and 290 MB for a 10 Hz
    day), so a page that connects late still draws the history.
    """

    def __init__(self, predict_ms: float = 0.0, gate: GateRule | None = None, **estimator):
        check_view_predict_ms(predict_ms)
        self._plain, self._ahead, self._rule = _estimators(predict_ms, gate, estimator)
        self._events: list[bytes] = []
        self._cond = threading.Condition()
        self.ended = False
        self.stopped = False

    def meta(self) -> dict:
        """What ``/trace.json`` says of a live feed (under ``"live"``)."""
        return {"source": "stdin", "url": "live", "predict_ms": self._ahead.predict_ms,
                "ahead_s": self._ahead.predict_ms / 1000.0, "tidal_volume_ml": self._ahead.tidal_volume_ml,
                "v_ee_ml": self._ahead.v_ee_ml,
                "gate": None if self._rule is None else gate_meta(self._rule, self._ahead.predict_ms)}

    def push(self, t_s: float, amplitude: float) -> dict:
        """One sample in; returns (and queues) its event."""
        m = self._plain.update(t_s, amplitude)
        p = self._ahead.update(t_s, amplitude)
        ev = {"t_s": p.t_s, "measured_ml": m.volume_ml, "predicted_ml": p.volume_ml, "ahead_s": p.ahead_s}
        if p.gate is not None:
            ev["gate"] = gate_fields(amplitude, p.gate)
        with self._cond:
            self._events.append(f"data: {json.dumps(ev, allow_nan=False)}\n\n".encode())
            self._cond.notify_all()
        return ev

    def push_lines(self, lines, source: str = "stdin") -> int:
        """Feed text lines (:func:`lungdeform.breathing.stream.parse_sample`) until they end; returns the
        number of samples. InputError names ``source`` and the line; the feed ends either way."""
        n = 0
        try:
            for lineno, line in enumerate(lines, 1):
                sample = parse_sample(line, lineno, source)
                if sample is None:
                    continue
                try:
                    self.push(*sample)
                except InputError as exc:
                    raise InputError(f"{source} line {lineno}: {exc}") from None
                n += 1
        finally:
            self.end()
        return n

    def end(self) -> None:
        with self._cond:
            self.ended = True
            self._cond.notify_all()

    def stop(self) -> None:
        """Release every :meth:`events` reader (the server is closing)."""
        with self._cond:
            self.stopped = True
            self._cond.notify_all()

    def events(self, poll_s: float = 0.5):
        """The SSE byte chunks: every event so far, then each new one as it comes; ``event: end`` last."""
        i = 0
        while True:
            with self._cond:
                while i >= len(self._events) and not (self.ended or self.stopped):
                    self._cond.wait(poll_s)
                chunk, i = self._events[i:], len(self._events)
                done = (self.ended and not chunk) or self.stopped
            if chunk:
                yield b"".join(chunk)
            if done:
                if not self.stopped:
                    yield b"event: end\ndata: {}\n\n"
                return


def live_json(feed: LiveFeed) -> bytes:
    """``/trace.json`` for a live feed: no recorded trace, and where the samples come from."""
    doc = trace_payload()
    doc["live"] = feed.meta()
    return json.dumps(doc, allow_nan=False).encode("utf-8")
