"""lungdeform.validate.gating: the protocol on synthetic breaths (oracle, causality, metrics)."""

import json

import numpy as np
import pytest

from lungdeform.breathing.gating import GateRule
from lungdeform.errors import InputError
from lungdeform.validate import gating as G
from tests.breathing.test_trace import breath, write_marker_csv


def _breath(rng, seconds=120.0):
    t = np.arange(0, seconds, 0.1)
    return t, 8 * breath(t, period=4.0) + rng.normal(0, 0.1, t.size)


def test_oracle_has_no_beam_on_error_and_prediction_beats_no_compensation(rng):
    # the oracle gates on the true future position against the same window: by definition it is never
    # on outside the window (error 0, residual 0). On a regular breath the latency makes the newest
    # sample leave the window late, so no compensation errs more than the model with intervals
    t, x = _breath(rng)
    s = G.score_trace(t, x, G.GatingConfig())
    assert s["oracle"]["beam_on_error"] == 0.0 and s["oracle"]["residual_rms"] == 0.0
    assert 0.2 < s["oracle"]["duty_cycle"] < 0.8
    assert s["model_intervals"]["beam_on_error"] < 0.5 * s["none"]["beam_on_error"]
    assert s["none"]["residual_rms"] > 0


def test_metrics_follow_their_definitions():
    # 4 scored samples, beam on for 3 of which one is 2 units outside: duty 0.75, error 1/3,
    # residual sqrt(4/3)
    win = np.array([[-np.inf, 1.0]] * 4)
    m = G.gate_metrics(np.array([True, True, True, False]), np.array([0.0, 3.0, 1.0, 5.0]), win)
    assert m["duty_cycle"] == 0.75 and m["beam_on_error"] == pytest.approx(1 / 3)
    assert m["residual_rms"] == pytest.approx(np.sqrt(4 / 3))
    assert G.gate_metrics(np.zeros(3, bool), np.zeros(3), win[:3])["beam_on_error"] is None


def test_decisions_never_use_later_samples_except_the_oracle(rng):
    t, x = _breath(rng, 90.0)
    y = x.copy()
    y[500:] = rng.normal(0, 3.0, t.size - 500)
    a, b = G.gate_decisions(t, x, G.GatingConfig()), G.gate_decisions(t, y, G.GatingConfig())
    assert set(G.CAUSAL) == set(G.STRATEGIES) - {"oracle"}
    for k in G.CAUSAL:
        assert np.array_equal(a[k][:500], b[k][:500])
    assert np.array_equal(a["window"][:500], b["window"][:500])


def test_replayed_threshold_is_the_live_gate(rng):
    # leave-one-trace-out replays RiskThreshold on the recorded window probabilities; the predictor never
    # sees the beam, so with the live gate's own control the replay must give its decisions exactly
    t, x = _breath(rng, 90.0)
    cfg = G.GatingConfig()
    d = G.gate_decisions(t, x, cfg)
    on = G.replay_threshold(t, x, d, 0.3, cfg.rule.risk)
    assert np.array_equal(on, d["model_intervals"]) and on.any() and not on.all()


def test_leave_one_trace_out_picks_the_step_on_the_other_traces(rng):
    # each held-out trace's step comes from the others only: with the traces copied under other names
    # (every trace identical) the pick is the same everywhere and equals the pick on all traces
    t, x = _breath(rng, 90.0)
    cfg = G.GatingConfig()
    r = G.score_trace(t, x, cfg)
    r["_trace"] = (t, x)
    lo = G.leave_one_trace_out({"a": r, "b": r, "c": r}, cfg)
    assert {h["gamma"] for h in lo["traces"].values()} == {lo["gamma_all"]} and lo["gamma_all"] in G.GAMMA_GRID
    assert G.leave_one_trace_out({"a": r, "b": r}, G.GatingConfig(rule=GateRule(risk=None))) is None


def test_threshold_at_linear_duty_is_learned_on_the_other_traces(rng):
    # causality across traces: the threshold scored on a trace is chosen on the other traces only, so
    # replacing that trace's data changes neither its threshold nor anyone's but its own figures; and
    # on copies of one trace the threshold reaches the linear strategy's duty cycle there
    cfg = G.GatingConfig()
    t, x = _breath(rng, 90.0)
    r = G.score_trace(t, x, cfg)
    other = G.score_trace(*_breath(np.random.default_rng(7), 90.0), cfg)
    a = G.linear_duty_causal({"a": r, "b": r, "c": r})
    b = G.linear_duty_causal({"a": other, "b": r, "c": r})
    assert a["traces"]["a"]["threshold"] == b["traces"]["a"]["threshold"]
    lin = r["linear"]["duty_cycle"]
    tau = a["traces"]["a"]["threshold"]
    assert a["traces"]["a"]["duty_cycle"] >= lin  # the highest threshold whose duty reaches linear's
    if tau < G.THRESHOLD_GRID[-1]:
        nxt = G.THRESHOLD_GRID[G.THRESHOLD_GRID.index(tau) + 1]
        prob = np.nan_to_num(r["_decisions"]["probability"][r["_scored"]], nan=-1.0)
        assert np.mean(prob >= nxt) < lin
    assert G.linear_duty_causal({"a": r}) is None


def test_targets_use_causal_gates_only(rng):
    # the hindsight ranking (oracle_matched) and the oracle are reported, never a target: changing the
    # oracle's figures changes no target
    t, x = _breath(rng, 90.0)
    cfg = G.GatingConfig()
    r = G.score_trace(t, x, cfg)
    traces = {"a": {k: v for k, v in r.items() if not k.startswith("_")}}
    s = G.summary(traces)
    causal = G.linear_duty_causal({"a": r, "b": r})
    before = G.targets(s, causal)
    s["oracle"] = {"duty_cycle": 1.0, "beam_on_error": 1.0, "residual_rms": 9.0}
    s["oracle_matched"] = {k: 0.0 for k in s["oracle_matched"]}
    assert G.targets(s, causal) == before
    assert "better_than_linear_at_linear_duty_causal" in before and not any("matched" in k for k in before)


def test_confident_gate_is_stricter(rng):
    # the whole 90 % interval inside implies a predicted window probability of at least 0.95 > 0.5
    t, x = _breath(rng)
    loose = G.score_trace(t, x, G.GatingConfig())
    strict = G.score_trace(t, x, G.GatingConfig(rule=GateRule(confident=True)))
    assert strict["model_intervals"]["duty_cycle"] < loose["model_intervals"]["duty_cycle"]


def test_validate_gating_writes_the_layout_of_the_spec(tmp_path, rng):
    data = tmp_path / "data"
    data.mkdir()
    t, x = _breath(rng, 80.0)
    write_marker_csv(data / "201201010000-LAC-1-N-80-6.csv", t * 1000, x)
    m = G.validate_gating(data, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "metrics.json").read_text())
    row = doc["traces"]["201201010000-LAC-1-N-80-6.csv"]
    for k in G.STRATEGIES:
        assert set(G.METRICS) <= set(row[k]) and set(G.METRICS) <= set(doc["summary"][k])
    assert doc["summary"]["none"]["duty_cycle"] == pytest.approx(row["none"]["duty_cycle"])
    assert m["window"] == "end-exhale:30" and (tmp_path / "out" / "plots" / "duty_vs_error.png").stat().st_size > 5000
    with pytest.raises(InputError, match="latency"):
        G.GatingConfig(latency_ms=0)


@pytest.mark.realdata
@pytest.mark.slow
def test_shared_traces_meet_the_gating_targets(traces_validated):
    # issue 28, on the shared traces (medians, 300 ms, end-exhale 30 %): model with intervals has at most
    # half the beam-on error of no compensation at 0.9 × its duty cycle or more (the default run,
    # shared with tests/test_docs_figures.py)
    code, m, _ = traces_validated("lungdeform validate gating --data DATA --out OUT")
    assert code == 0
    t = m["targets"]
    assert m["n_traces"] == 16 and t["error_vs_none"]["met"] and t["duty_vs_none"]["met"]
    # with the same intervals and the same adaptive rule, the model gates more and errs less than the
    # tuned linear baseline (measured 0.465 / 0.044 against 0.459 / 0.056); at linear's duty cycle, with
    # a fixed threshold learned on the other traces (causal), it errs less (0.047 against 0.057 at duty
    # 0.468 against 0.467). Not met, and reported: its point gate's duty is below linear's
    assert t["better_than_linear_same_rule"]["met"]
    assert t["better_than_linear_at_linear_duty_causal"]["met"]
    assert not t["better_than_linear"]["met"]
    assert "oracle_matched" in m["summary"] and not any("matched" in k for k in t)
