"""``lungdeform validate gating``: amplitude gating of a radiotherapy beam simulated on recorded traces.

Protocol, per trace (every trace :func:`lungdeform.validate.breathing.trace_files` finds, in its own
unit as :func:`lungdeform.breathing.trace.read_trace` gives it, inhale positive):

1. the window (:class:`lungdeform.breathing.gating.GateWindow`, default ``end-exhale:30``: the lowest
   30 % of the breath's amplitude over the last 15 s of samples) is known at each sample ``t_i`` from
   the samples up to ``t_i`` only;
2. the beam decision made at ``t_i`` acts at ``t_i + latency`` (default 300 ms). Strategies, all in
   the same run:

   - ``none``: no compensation, the newest sample ``x(t_i)`` inside the window;
   - ``linear``: the online linear baseline's prediction of ``x(t_i + latency)`` inside (the tuned
     baseline, :func:`lungdeform.breathing.predict.baseline_linear`); ``linear_plain``: the same with
     the untuned baseline of 0.7 (:func:`lungdeform.breathing.predict.baseline_linear_plain`);
   - ``model``: the model's (:class:`lungdeform.breathing.predict.BlendPredictor`) prediction inside;
   - ``model_intervals``: the model with its conformal predictive distribution
     (:mod:`lungdeform.breathing.predict_interval`): the predicted probability of the window at least
     a threshold adapted online to the tolerated beam-on error (``rule.risk``, α = 0.05;
     :class:`lungdeform.breathing.gating.RiskThreshold`), or fixed at ``min_probability`` without
     ``risk``; with ``confident``, instead the whole ``coverage`` interval inside;
   - ``linear_intervals``: the tuned linear baseline under the same intervals and the same rule (the
     comparison of the two predictors with everything else equal);
   - ``oracle``: the true ``x(t_i + latency)`` inside (knows the future: the ceiling, never a target);

3. scored for every ``t_i`` at least ``warm_s`` (30 s) after the first sample with ``t_i + latency``
   inside the trace (linear interpolation), against the window of ``t_i``: the duty cycle (share of
   scored samples with the beam on), the beam-on error (share of beam-on samples whose true position
   is outside the window) and the residual motion (RMS over beam-on samples of the distance outside
   the window, trace units). Summary: medians over traces.

Every strategy but ``oracle`` decides at ``t_i`` from the samples up to ``t_i`` (tests check it), and
so does every figure reported as a target. Two comparisons at the linear strategy's duty cycle:

- ``linear_duty_causal`` (a target): the model's window probability against a fixed threshold
  chosen on the *other* traces (leave one trace out), the highest of :data:`THRESHOLD_GRID` whose
  median duty cycle over them is at least the linear strategy's median there; scored on the trace
  left out. Nothing of that trace enters its threshold, and the threshold does not change during it.
- ``oracle_matched`` (per trace; not a gate, never a target): the beam-on error of the model's
  ``linear``-many samples of highest window probability, chosen after the fact with the whole
  trace known (a hindsight ranking: a comparison of the two trade-off curves). Until 0.8 it was
  ``matched`` and a target.

``leave_one_trace_out`` (with the adaptive rule): the check of the threshold's step γ, its only setting
besides the clinical α. For each trace, γ of :data:`GAMMA_GRID` is chosen on the other traces (the
highest median duty cycle among the steps whose median beam-on error is at most α) and scored on that
trace, replaying :class:`lungdeform.breathing.gating.RiskThreshold` on the recorded window
probabilities (the predictor never sees the beam, so the replay is what the live gate would decide).

``metrics.json``: ``{"traces": {NAME: {"none": {"duty_cycle", "beam_on_error", "residual_rms"}, …,
"oracle_matched": {…}}}, "summary": {STRATEGY: {…}, "oracle_matched": {…}}, "linear_duty_causal":
{…}, "leave_one_trace_out": {…}, "targets": {…}, "errors": {…}, …}``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.breathing.gating import (
    BeamGate,
    GateRule,
    RiskControl,
    RiskThreshold,
    distance_outside,
    gate_point,
)
from lungdeform.breathing.predict import baseline_linear, baseline_linear_plain, check_horizon
from lungdeform.breathing.trace import read_trace
from lungdeform.errors import InputError, LungdeformError
from lungdeform.plot.figure import new_figure, save_png

from .breathing import trace_files

STRATEGIES = ("none", "linear", "linear_plain", "model", "model_intervals", "linear_intervals", "oracle")
#: the strategies that decide from the samples up to the decision only (all but the oracle)
CAUSAL = tuple(k for k in STRATEGIES if k != "oracle")
METRICS = ("duty_cycle", "beam_on_error", "residual_rms")
WARM_S = 30.0
#: must show: model_intervals beam-on error ≤ this × none's, at a duty cycle ≥ DUTY_FLOOR × none's
TARGET_ERROR_OVER_NONE = 0.5
TARGET_DUTY_OVER_NONE = 0.9
#: the adaptive threshold's steps γ among which leave-one-trace-out chooses (the check of the default)
GAMMA_GRID = (0.002, 0.005, 0.01, 0.02, 0.05)
#: the fixed window-probability thresholds among which ``linear_duty_causal`` chooses
THRESHOLD_GRID = tuple(round(0.02 * k, 2) for k in range(1, 50))


@dataclass(frozen=True)
class GatingConfig:
    """latency_ms : ms between decision and beam (0, 2000]; rule : the window and the rule of
    model_intervals (:class:`lungdeform.breathing.gating.GateRule`); warm_s : s not scored."""

    latency_ms: float = 300.0
    rule: GateRule = field(default_factory=GateRule)
    warm_s: float = WARM_S

    def __post_init__(self):
        if not (math.isfinite(self.latency_ms) and 0.0 < self.latency_ms <= 2000.0):
            raise InputError(f"--latency-ms must be in (0, 2000] ms, got {self.latency_ms!r}")


def gate_decisions(t_s, x, config: GatingConfig) -> dict:
    """Every strategy's beam decision at every sample of one trace (causal except ``oracle``):
    ``{"window": (n, 2) float, "truth": (n,) float x(t + latency) (NaN past the end), STRATEGY: (n,)
    bool, "probability": (n,) float (the model's predicted window probability)}``."""
    t, v = np.asarray(t_s, float), np.asarray(x, float)
    lat = check_horizon(config.latency_ms / 1000.0)
    gate = BeamGate(lat, config.rule)
    dt = float(np.median(np.diff(t)))
    lin, plain = baseline_linear(lat, dt_s=dt), baseline_linear_plain(lat, dt_s=dt)
    lin_gate = BeamGate(lat, config.rule, point=baseline_linear(lat, dt_s=dt))
    n = t.size
    win, prob, top = np.empty((n, 2)), np.empty(n), np.empty(n)
    dec = {k: np.zeros(n, bool) for k in STRATEGIES}
    for i in range(n):
        g = gate.update(t[i], v[i])
        win[i], prob[i] = g.window, g.probability
        top[i] = gate.predictor.probability_below(math.inf)
        dec["none"][i] = gate_point(g.window, v[i])
        dec["linear"][i] = gate_point(g.window, lin.update(t[i], v[i]))
        dec["linear_plain"][i] = gate_point(g.window, plain.update(t[i], v[i]))
        dec["model"][i] = gate_point(g.window, g.predicted)
        dec["model_intervals"][i] = g.beam_on
        dec["linear_intervals"][i] = lin_gate.update(t[i], v[i]).beam_on
    truth = np.interp(t + lat, t, v)
    truth[t + lat > t[-1]] = np.nan
    dec["oracle"] = (win[:, 0] <= truth) & (truth <= win[:, 1])
    return {"window": win, "truth": truth, "probability": prob, "highest": top, **dec}


def replay_threshold(t_s, x, decisions: dict, latency_s: float, control: RiskControl) -> np.ndarray:
    """The adaptive gate's decisions ``(n,) bool`` with another ``control``, replayed on the recorded
    window probabilities of :func:`gate_decisions` (``probability``, ``highest``, ``window``): the
    predictor and its distribution never see the beam, so this is what :class:`BeamGate` would decide
    (tests check it equals the live gate for the default control)."""
    gate = RiskThreshold(latency_s, control)
    on = np.zeros(len(t_s), bool)
    for i, (ti, xi) in enumerate(zip(t_s, x)):
        gate.observe(ti, xi)
        on[i] = gate.decide(ti, decisions["probability"][i], decisions["highest"][i], tuple(decisions["window"][i]))
    return on


def _or_one(error: float | None) -> float:
    """A beam-on error for ranking: a gate never on (None) counts as always wrong."""
    return 1.0 if error is None else float(error)


def _pick_gamma(rows: dict, names, alpha: float) -> float:
    """The γ of GAMMA_GRID with the highest median duty cycle over ``names`` among those whose median
    beam-on error is at most ``alpha``; none such: the lowest median beam-on error."""
    def key(g):
        duty = np.median([rows[n][g]["duty_cycle"] for n in names])
        err = np.median([_or_one(rows[n][g]["beam_on_error"]) for n in names])
        return (err <= alpha, duty if err <= alpha else -err)
    return max(GAMMA_GRID, key=key)


def leave_one_trace_out(scores: dict, config: GatingConfig) -> dict | None:
    """Leave-one-trace-out check of the adaptive threshold's step γ (the only setting it has besides
    the clinical α): for each trace, γ of :data:`GAMMA_GRID` chosen on the other traces
    (:func:`_pick_gamma`), scored on that trace. None without the adaptive rule or with one trace."""
    risk = config.rule.risk
    if risk is None or config.rule.confident or len(scores) < 2:
        return None
    lat = config.latency_ms / 1000.0
    rows = {}
    for name, r in scores.items():
        t, x = r["_trace"]
        d, ok = r["_decisions"], r["_scored"]
        rows[name] = {g: gate_metrics(replay_threshold(t, x, d, lat, replace(risk, gamma=g))[ok], d["truth"][ok],
                                      d["window"][ok]) for g in GAMMA_GRID}
    held = {}
    for name in rows:
        g = _pick_gamma(rows, [n for n in rows if n != name], risk.target_error)
        held[name] = {"gamma": g, **{m: rows[name][g][m] for m in ("duty_cycle", "beam_on_error")}}
    med = {m: float(np.median([_or_one(h[m]) for h in held.values()])) for m in ("duty_cycle", "beam_on_error")}
    return {"traces": held, "summary": med, "gamma_grid": list(GAMMA_GRID), "gamma_all": _pick_gamma(rows, list(rows), risk.target_error),
            "gamma_default": risk.gamma, "target_error": risk.target_error}


def gate_metrics(on: np.ndarray, truth: np.ndarray, window: np.ndarray) -> dict:
    """Duty cycle, beam-on error and residual RMS (trace units) of beam decisions ``on : (m,) bool``
    against the true positions ``truth : (m,)`` and the windows ``(m, 2)``; None where undefined."""
    out = np.array([distance_outside(w, y) for w, y in zip(window, truth)])
    duty = float(on.mean()) if on.size else None
    if not on.any():
        return {"duty_cycle": duty, "beam_on_error": None, "residual_rms": None, "n_on": 0}
    return {"duty_cycle": duty, "beam_on_error": float(np.mean(out[on] > 0)),
            "residual_rms": float(np.sqrt(np.mean(out[on] ** 2))), "n_on": int(on.sum())}


def oracle_matched_error(probability: np.ndarray, truth: np.ndarray, window: np.ndarray, n_on: int) -> float | None:
    """Beam-on error of the ``n_on`` samples of highest predicted window probability, chosen with the
    whole trace known (``oracle_matched``, module doc: a hindsight ranking, not a gate)."""
    if n_on <= 0:
        return None
    top = np.argsort(-np.nan_to_num(probability, nan=-1.0), kind="stable")[:n_on]
    return float(np.mean([distance_outside(window[i], truth[i]) > 0 for i in top]))


def score_trace(t_s, x, config: GatingConfig) -> dict:
    """:func:`gate_decisions` scored (protocol step 3): ``{STRATEGY: metrics, "oracle_matched": …,
    "n_scored"}`` and ``"_decisions"``, ``"_scored"`` (for the plots and the leave-one-trace-out checks)."""
    t = np.asarray(t_s, float)
    if t.size < 2 or t[-1] - t[0] <= config.warm_s:
        raise InputError(f"trace of {t[-1] - t[0]:.1f} s is not longer than the {config.warm_s:g} s warm-up")
    d = gate_decisions(t, x, config)
    ok = (t >= t[0] + config.warm_s) & np.isfinite(d["truth"])
    out: dict = {k: gate_metrics(d[k][ok], d["truth"][ok], d["window"][ok]) for k in STRATEGIES}
    n_lin = out["linear"]["n_on"]
    out["oracle_matched"] = {"linear_duty_cycle": out["linear"]["duty_cycle"],
                             "linear_beam_on_error": out["linear"]["beam_on_error"],
                             "model_intervals_beam_on_error": oracle_matched_error(
                                 d["probability"][ok], d["truth"][ok], d["window"][ok], n_lin)}
    out["n_scored"] = int(ok.sum())
    out["_decisions"], out["_scored"] = d, ok
    return out


def _fixed_threshold_rows(scores: dict) -> dict:
    """Per trace and threshold of :data:`THRESHOLD_GRID`: the metrics of the fixed rule
    ``probability >= threshold`` on the recorded window probabilities (what the live gate with
    ``--min-probability`` would decide: the predictor never sees the beam)."""
    rows = {}
    for name, r in scores.items():
        d, ok = r["_decisions"], r["_scored"]
        prob = np.nan_to_num(d["probability"][ok], nan=-1.0)
        rows[name] = {tau: gate_metrics(prob >= tau, d["truth"][ok], d["window"][ok]) for tau in THRESHOLD_GRID}
    return rows


def linear_duty_causal(scores: dict) -> dict | None:
    """The model at the linear strategy's duty cycle, causally (module doc): for each trace the
    threshold chosen on the other traces, scored on it. None with fewer than two traces."""
    if len(scores) < 2:
        return None
    rows = _fixed_threshold_rows(scores)
    lin = {n: r["linear"]["duty_cycle"] for n, r in scores.items()}
    held = {}
    for name in rows:
        others = [n for n in rows if n != name]
        goal = float(np.median([lin[n] for n in others]))
        ok = [tau for tau in THRESHOLD_GRID if np.median([rows[n][tau]["duty_cycle"] for n in others]) >= goal]
        tau = max(ok) if ok else THRESHOLD_GRID[0]
        held[name] = {"threshold": tau, **{m: rows[name][tau][m] for m in ("duty_cycle", "beam_on_error")}}
    med = {m: float(np.median([_or_one(h[m]) for h in held.values()])) for m in ("duty_cycle", "beam_on_error")}
    return {"traces": held, "summary": med, "threshold_grid": [THRESHOLD_GRID[0], THRESHOLD_GRID[-1]],
            "linear": {m: float(np.median([_or_one(r["linear"][m]) for r in scores.values()]))
                       for m in ("duty_cycle", "beam_on_error")}}


def summary(traces: dict) -> dict:
    """Median over traces of each metric of each strategy (None where no trace has it), and of oracle_matched."""
    def med(vals):
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        return float(np.median(vals)) if vals else None

    out = {k: {m: med([r[k][m] for r in traces.values()]) for m in METRICS} for k in STRATEGIES}
    first = next(iter(traces.values()))["oracle_matched"]
    out["oracle_matched"] = {m: med([r["oracle_matched"][m] for r in traces.values()]) for m in first}
    return out


def targets(s: dict, causal_matched: dict | None) -> dict:
    """The must-show comparisons on the medians, each of causal gates only: against no compensation
    and against linear (its point gate; the linear baseline under the same intervals and rule; and,
    with two traces or more, at linear's duty cycle with a threshold learned on the other traces)."""
    none, mi, lin = s["none"], s["model_intervals"], s["linear"]

    def le(a, b, f=1.0):
        return a is not None and b is not None and a <= f * b

    out = {
        "error_vs_none": {"value": mi["beam_on_error"], "threshold": None if none["beam_on_error"] is None
                          else TARGET_ERROR_OVER_NONE * none["beam_on_error"],
                          "met": le(mi["beam_on_error"], none["beam_on_error"], TARGET_ERROR_OVER_NONE)},
        "duty_vs_none": {"value": mi["duty_cycle"], "threshold": None if none["duty_cycle"] is None
                         else TARGET_DUTY_OVER_NONE * none["duty_cycle"],
                         "met": le(TARGET_DUTY_OVER_NONE * (none["duty_cycle"] or 0.0), mi["duty_cycle"])},
        "better_than_linear": {"met": le(mi["beam_on_error"], lin["beam_on_error"])
                               and le(lin["duty_cycle"], mi["duty_cycle"]),
                               "beam_on_error": [mi["beam_on_error"], lin["beam_on_error"]],
                               "duty_cycle": [mi["duty_cycle"], lin["duty_cycle"]]},
        "better_than_linear_same_rule": {
            "met": le(mi["beam_on_error"], s["linear_intervals"]["beam_on_error"])
            and le(s["linear_intervals"]["duty_cycle"], mi["duty_cycle"]),
            "beam_on_error": [mi["beam_on_error"], s["linear_intervals"]["beam_on_error"]],
            "duty_cycle": [mi["duty_cycle"], s["linear_intervals"]["duty_cycle"]]},
    }
    if causal_matched is not None:
        c, cl = causal_matched["summary"], causal_matched["linear"]
        out["better_than_linear_at_linear_duty_causal"] = {
            "met": le(c["beam_on_error"], cl["beam_on_error"]) and le(cl["duty_cycle"], c["duty_cycle"]),
            "beam_on_error": [c["beam_on_error"], cl["beam_on_error"]],
            "duty_cycle": [c["duty_cycle"], cl["duty_cycle"]]}
    return out


def protocol(config: GatingConfig) -> str:
    rule, window = config.rule.text, config.rule.window
    return (f"window {window.text} of the breath, causal (extremes of the last {window.span_s:g} s); "
            f"decision at t_i for t_i + {config.latency_ms:g} ms; scored for t_i >= t_0 + {config.warm_s:g} s "
            f"against the window of t_i; model_intervals: {rule}; medians over traces")


def write_plots(scores: dict, config: GatingConfig, folder: Path) -> dict[str, str]:
    """Duty cycle against beam-on error per strategy (every trace, medians), and 30 s of one trace with
    the window and each strategy's beam."""
    folder.mkdir(parents=True, exist_ok=True)
    fig = new_figure(6.4, 4.6, layout="constrained")
    ax = fig.subplots()
    for j, k in enumerate(STRATEGIES):
        pts = np.array([(r[k]["duty_cycle"], r[k]["beam_on_error"]) for r in scores.values()
                        if r[k]["beam_on_error"] is not None], float).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=12, color=f"C{j}", alpha=0.5)
        if len(pts):
            ax.scatter(*np.median(pts, axis=0), s=90, marker="*", color=f"C{j}", label=f"{k} (median)")
    ax.set_xlabel("duty cycle")
    ax.set_ylabel("beam-on error (share of beam-on time outside the window)")
    ax.set_title(f"gating, {config.rule.window.text}, latency {config.latency_ms:g} ms", fontsize=10)
    ax.legend(fontsize=8)
    files = {"duty_vs_error.png": str(save_png(fig, folder / "duty_vs_error.png"))}
    name = next(iter(scores))
    t, x = scores[name]["_trace"]
    d = scores[name]["_decisions"]
    keep = (t >= t[0] + config.warm_s) & (t <= t[0] + config.warm_s + 30.0)
    fig = new_figure(10.0, 4.4, layout="constrained")
    ax = fig.subplots()
    lat = config.latency_ms / 1000.0
    ax.plot(t[keep], x[keep], color="black", lw=1.4, label="signal")
    edge = np.where(np.isinf(d["window"][:, 1]), d["window"][:, 0], d["window"][:, 1])
    ax.plot(t[keep] + lat, edge[keep], color="0.5", ls="--", lw=1.0, label="window edge (at the time it gates)")
    lo, hi = float(np.min(x[keep])), float(np.max(x[keep]))
    for j, k in enumerate(STRATEGIES):
        y0 = lo - (j + 1) * 0.08 * (hi - lo)
        on = keep & d[k]
        ax.plot(np.where(on, t + lat, np.nan), np.full(t.size, y0), color=f"C{j}", lw=4, label=f"beam on: {k}")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"signal ({scores[name]['unit']})")
    ax.set_title(f"{name}: beam on where each strategy gates (drawn at the time the beam acts)", fontsize=10)
    ax.legend(fontsize=7, ncols=3, loc="upper right")
    files["gated_trace.png"] = str(save_png(fig, folder / "gated_trace.png"))
    return files


def validate_gating(data: Path, out: Path, config: GatingConfig | None = None, progress=None) -> dict:
    """Gate every trace under ``data`` (module doc); write ``out/metrics.json`` and ``out/plots/*.png``."""
    config = config or GatingConfig()
    scores, errors = {}, {}
    for key, f in trace_files(Path(data)).items():
        if progress:
            progress(f"gating {key}")
        try:
            tr = read_trace(f)
            scores[key] = {"unit": tr.unit, **score_trace(tr.t_s, tr.amplitude, config),
                           "_trace": (tr.t_s, tr.amplitude)}
        except LungdeformError as exc:
            errors[key] = " ".join(str(exc).split())
    if not scores:
        raise InputError(f"data {data}: no trace could be gated ({len(errors)} failed"
                         + (f"; first: {next(iter(errors.values()))})" if errors else ")"))
    files = write_plots(scores, config, Path(out) / "plots")
    traces = {n: {k: v for k, v in r.items() if not k.startswith("_")} for n, r in scores.items()}
    s = summary(traces)
    causal = linear_duty_causal(scores)
    metrics = {"traces": traces, "summary": s, "targets": targets(s, causal), "n_traces": len(traces),
               "linear_duty_causal": causal, "leave_one_trace_out": leave_one_trace_out(scores, config),
               "errors": errors, "latency_ms": config.latency_ms, "window": config.rule.window.text,
               "confident": config.rule.confident, "min_probability": config.rule.min_probability,
               "target_error": None if config.rule.risk is None else config.rule.risk.target_error,
               "coverage": config.rule.interval.coverage, "plots": files, "protocol": protocol(config)}
    write_json(Path(out) / "metrics.json", metrics, strict=True)
    return metrics
