"""lungdeform.playback.tracefeed: the trace the viewer plays, measured and predicted per sample."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

from lungdeform.breathing.gating import BeamGate
from lungdeform.breathing.stream import StreamingVolumeEstimator
from lungdeform.errors import InputError, ReadError
from lungdeform.playback.tracefeed import (
    LiveFeed,
    check_view_predict_ms,
    live_json,
    prediction_series,
    trace_payload,
    view_trace_json,
)
from tests.breathing.test_trace import breath, write_marker_csv


def noisy_breaths(rng, seconds=60.0, dt=0.1):
    t = np.arange(0.0, seconds, dt)
    return t, 8 * breath(t) + rng.normal(0.0, 0.05, t.size)


def test_series_is_causal_a_prefix_gives_a_prefix(rng):
    # predictions never use later samples: run on the first 350 of 600 samples, every value equals
    # the one the full run gave for that sample (exactly: the same float operations in the same order)
    t, x = noisy_breaths(rng)
    full = prediction_series(t, x, predict_ms=400)
    part = prediction_series(t[:350], x[:350], predict_ms=400)
    for key in ("t_s", "measured_ml", "predicted_ml", "ahead_s"):
        assert part[key] == full[key][:350], key


def test_series_is_the_streaming_estimator_sample_by_sample(rng):
    # one implementation: measured = StreamingVolumeEstimator() and predicted = (predict_ms=300) fed in
    # order, so both equal a fresh estimator's outputs; ahead_s is the horizon, 0.3 s
    t, x = noisy_breaths(rng, seconds=30)
    got = prediction_series(t, x, predict_ms=300)
    plain, ahead = StreamingVolumeEstimator(), StreamingVolumeEstimator(predict_ms=300)
    assert got["measured_ml"] == [plain.update(a, b).volume_ml for a, b in zip(t, x)]
    assert got["predicted_ml"] == [ahead.update(a, b).volume_ml for a, b in zip(t, x)]
    assert set(got["ahead_s"]) == {0.3} and got["predict_ms"] == 300.0
    # with prediction the curve differs (else the viewer would show no compensation at all)
    assert np.max(np.abs(np.subtract(got["predicted_ml"], got["measured_ml"]))) > 10


def test_without_predict_ms_measured_and_predicted_agree(rng):
    # predict_ms = 0: both runs are the same estimator, so the two series are identical, ahead 0
    t, x = noisy_breaths(rng, seconds=20)
    got = prediction_series(t, x)
    assert got["predicted_ml"] == got["measured_ml"] and set(got["ahead_s"]) == {0.0}


@pytest.mark.parametrize("bad", [-1, 2000.5, float("nan"), 5000])
def test_predict_ms_out_of_range_is_refused_by_name(bad):
    # the viewer compensates 0..2000 ms; the message names the option
    with pytest.raises(InputError, match=r"--predict-ms must be in \[0, 2000\] ms"):
        check_view_predict_ms(bad)


def test_payload_reads_the_trace_file(tmp_path, rng):
    # a marker CSV as `stream` reads it: one sample per row (terminator dropped), source named
    t = np.arange(0.0, 20.0, 0.1)
    path = write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t))
    doc = json.loads(json.dumps(trace_payload(path, 400)))
    assert doc["schema"] == "lungdeform.trace-prediction" and doc["trace"]["source"] == str(path)
    assert len(doc["trace"]["t_s"]) == t.size and doc["trace"]["unit"] == "mm"
    assert trace_payload()["trace"] is None  # no trace: the viewer plays presets


def test_view_options_are_checked_before_anything_is_read(tmp_path):
    # a trace with a .glb or with a curve, or --predict-ms without a trace: refused by option name,
    # even though none of the files exists (nothing is read first)
    with pytest.raises(InputError, match=r"--trace .*not an exported \.glb"):
        view_trace_json(tmp_path / "m.glb", tmp_path / "t.csv")
    with pytest.raises(InputError, match=r"--trace and --curve"):
        view_trace_json(tmp_path / "m.npz", tmp_path / "t.csv", curve=tmp_path / "c.csv")
    with pytest.raises(InputError, match=r"--predict-ms applies to a --trace"):
        view_trace_json(tmp_path / "m.npz", None, predict_ms=400)
    with pytest.raises(InputError, match=r"--predict-ms must be"):
        view_trace_json(tmp_path / "m.npz", tmp_path / "t.csv", predict_ms=-5)


def test_bad_trace_file_names_the_file(tmp_path):
    # the trace readers' own errors, naming the file
    bad = tmp_path / "t.csv"
    bad.write_text("Frame;Timestamp;x;y;z\n1;0;abc;0;0\n")
    with pytest.raises((ReadError, InputError), match=str(bad)):
        view_trace_json(tmp_path / "m.npz", bad)


def test_live_feed_events_are_the_recorded_series(rng):
    # one implementation: lines pushed live give, per sample, the same measured and predicted volume as
    # prediction_series on the same samples (both run the two estimators in the same order)
    t, x = noisy_breaths(rng, seconds=20)
    feed = LiveFeed(predict_ms=400)
    lines = ["t_s,amplitude", "# a comment", *(f"{float(a)!r},{float(b)!r}" for a, b in zip(t, x))]
    assert feed.push_lines(lines) == t.size and feed.ended
    chunks = b"".join(feed.events()).decode().split("\n\n")
    events = [json.loads(c[len("data: "):]) for c in chunks if c.startswith("data: ")]
    ref = prediction_series(t, x, predict_ms=400)
    assert [e["predicted_ml"] for e in events] == ref["predicted_ml"]
    assert [e["measured_ml"] for e in events] == ref["measured_ml"]
    assert chunks[-2] == "event: end\ndata: {}"  # the page learns the input ended
    assert json.loads(live_json(feed))["live"]["predict_ms"] == 400.0


def test_live_feed_bad_line_names_it_and_ends_the_feed():
    # a line that is not two numbers: InputError naming stdin and the line number (header is line 1)
    feed = LiveFeed()
    with pytest.raises(InputError, match="stdin line 3"):
        feed.push_lines(["t_s,amplitude", "0,1", "0.1,abc"])
    assert feed.ended
    with pytest.raises(InputError, match="stdin line 3: stream time must increase"):
        LiveFeed().push_lines(["0,1", "0.1,2", "0.1,3"])


def test_live_feed_reader_waits_for_new_samples():
    # a page connected before the samples arrive gets each as it comes, then the end
    feed = LiveFeed()
    got = []

    def read():
        got.extend(feed.events(poll_s=0.05))

    reader = threading.Thread(target=read)
    reader.start()
    feed.push(0.0, 1.0)
    feed.push(0.1, 2.0)
    feed.end()
    reader.join(5)
    text = b"".join(got).decode()
    assert not reader.is_alive() and text.count("data: {\"t_s\"") == 2 and text.endswith("event: end\ndata: {}\n\n")


def test_gate_fields_are_the_beam_gate_sample_by_sample(rng):
    # one implementation: with predict_ms the served gate fields are a BeamGate (300 ms, default rule)
    # fed the same samples in order; infinite bounds (the open side of the end-exhale window, the
    # interval before it is learned) become JSON null; the predicted volume is the ungated one's
    t, x = noisy_breaths(rng, seconds=40)
    got = json.loads(json.dumps(prediction_series(t, x, predict_ms=300), allow_nan=False))
    gate = BeamGate(0.3)
    ref = [gate.update(a, b) for a, b in zip(t, x)]
    g = got["gate"]
    assert g["window"] == "end-exhale:30" and g["coverage"] == 0.9 and g["latency_ms"] == 300.0
    assert g["amplitude"] == x.tolist() and g["beam_on"] == [r.beam_on for r in ref]
    assert g["predicted"] == [r.predicted for r in ref]
    assert g["lo"] == [r.lo if np.isfinite(r.lo) else None for r in ref]
    assert g["window_high"] == [r.window[1] for r in ref] and set(g["window_low"]) == {None}
    plain = StreamingVolumeEstimator(predict_ms=300)
    assert got["predicted_ml"] == [plain.update(a, b).volume_ml for a, b in zip(t, x)]
    # the interval is learned within the first seconds and then holds the prediction; the beam goes
    # both on and off over 40 s of breathing (else the viewer's indicator would never change)
    learned = [i for i, v in enumerate(g["lo"]) if v is not None]
    assert learned and learned[0] < 100 and len(learned) == t.size - learned[0]
    assert all(g["lo"][i] <= g["predicted"][i] <= g["hi"][i] for i in learned)
    assert 0 < sum(g["beam_on"]) < t.size
    assert prediction_series(t, x)["gate"] is None  # no prediction: no latency to gate for


def test_gate_window_is_the_last_15_s_of_raw_samples(rng):
    # against truth computed here with numpy: the end-exhale 30 % edge at sample i is
    # min + 0.3 (max - min) of the raw samples in [t_i - 15 s, t_i]
    t, x = noisy_breaths(rng, seconds=40)
    edge = prediction_series(t, x, predict_ms=400)["gate"]["window_high"]
    for i in range(0, t.size, 37):
        past = x[(t >= t[i] - 15.0 - 1e-9) & (t <= t[i])]
        assert edge[i] == pytest.approx(past.min() + 0.3 * np.ptp(past), rel=1e-12, abs=1e-12)


def test_gate_fields_are_causal_changing_the_future_changes_nothing_before(rng):
    # the gate at sample i uses samples 0..i only: replacing every sample after 350 by other values
    # leaves each gate field of samples 0..350 exactly as it was
    t, x = noisy_breaths(rng)
    y = x.copy()
    y[351:] = rng.normal(0.0, 5.0, y.size - 351)
    a = prediction_series(t, x, predict_ms=400)["gate"]
    b = prediction_series(t, y, predict_ms=400)["gate"]
    for key in ("predicted", "lo", "hi", "window_low", "window_high", "probability", "beam_on"):
        assert a[key][:351] == b[key][:351], key
        if key != "window_low":  # (open: None throughout) the change does reach the later samples
            assert a[key][351:] != b[key][351:], key


def test_live_feed_events_carry_the_gate(rng):
    # the live events hold the same gate fields as the recorded series, and the meta says the rule
    t, x = noisy_breaths(rng, seconds=20)
    feed = LiveFeed(predict_ms=400)
    events = [feed.push(a, b) for a, b in zip(t.tolist(), x.tolist())]
    ref = prediction_series(t, x, predict_ms=400)["gate"]
    for key in ("amplitude", "predicted", "lo", "hi", "window_high", "beam_on"):
        assert [e["gate"][key] for e in events] == ref[key], key
    assert json.loads(live_json(feed))["live"]["gate"]["window"] == "end-exhale:30"
    assert "gate" not in LiveFeed().push(0.0, 1.0)  # no prediction: no gate
