"""lungdeform.validate.prediction: the protocol on synthetic traces, and the targets on the shared ones."""

import json

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.validate import prediction as V
from tests.breathing.test_trace import breath, write_marker_csv


def _folder(tmp_path, rng, n=2, seconds=90):
    data = tmp_path / "data"
    data.mkdir()
    for i in range(n):
        t = np.arange(0, seconds, 0.1)
        s = 8 * breath(t + 0.7 * i, period=3.8 + 0.3 * i) + rng.normal(0, 0.1, t.size)
        write_marker_csv(data / f"20120101000{i}-LAC-1-N-{seconds}-6.csv", t * 1000, s)
    return data


def test_protocol_scores_only_after_the_warm_up_and_inside_the_trace():
    # a prediction equal to the truth has RMS 0; the count of scored samples follows step 2
    # (t_i >= t_0 + 30 s and t_i + h <= t_end): 0…59.9 s at 10 Hz, h = 0.5 s → samples 300…594
    t = np.arange(0, 60, 0.1)
    x = np.sin(t)
    rms, n = V.scored_rms(t, x, np.interp(t + 0.5, t, x), 0.5)
    assert rms == pytest.approx(0.0, abs=1e-12) and n == 295


def test_validate_prediction_writes_the_metrics_of_the_spec(tmp_path, rng):
    # metrics.json holds {"traces": {NAME: {"horizon_ms": {"400": {"model_rms", "none_rms",
    # "linear_rms"}}}}} and the medians; on a regular breath the model beats no prediction
    out = tmp_path / "out"
    m = V.validate_prediction(_folder(tmp_path, rng), out, horizons_ms=(200, 400))
    doc = json.loads((out / "metrics.json").read_text())
    assert set(doc["traces"]) == {"201201010000-LAC-1-N-90-6.csv", "201201010001-LAC-1-N-90-6.csv"}
    row = doc["traces"]["201201010000-LAC-1-N-90-6.csv"]["horizon_ms"]["400"]
    assert {"model_rms", "none_rms", "linear_rms", "linear_plain_rms"} <= set(row)
    assert row["model_rms"] / row["none_rms"] == pytest.approx(row["model_over_none"])
    assert doc["medians"]["400"]["model_over_none"] < 0.6 and m["n_quiet"] == 2
    # the 90 % intervals: coverage near nominal on a regular breath with white noise (60 s scored at
    # 10 Hz: ±0.1 is several binomial standard errors), a positive width and interval score
    for prefix in ("", "linear_"):
        assert 0.8 <= row[prefix + "coverage"] <= 0.98
        assert row[prefix + "width_over_none_rms"] > 0 and row[prefix + "interval_score"] > 0
    assert "coverage_every_horizon" in doc["targets"]
    assert (out / "plots" / "errors_vs_horizon.png").stat().st_size > 5000
    assert (out / "plots" / "predicted_trace.png").stat().st_size > 5000


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(InputError, match="horizons_ms"):
        V.check_horizons([400, 100])
    with pytest.raises(InputError, match="not a folder"):
        V.validate_prediction(tmp_path / "missing", tmp_path / "o")
    assert V.trace_tag("201205101534-UAC-1-NO-130-6.csv") == "NO" and V.trace_tag("PT01.vxp") is None


@pytest.mark.realdata
@pytest.mark.slow
def test_shared_traces_against_a_tuned_baseline_and_the_plain_one(traces_validated):
    # the calibration: the untuned baseline's RMS over no prediction at 400 ms has a median of 0.76 over
    # the 15 shared marker traces; linear_plain must be at least as strong (measured 0.739). The tuned
    # baseline was searched on these traces (scripts/tune_linear_baseline.py), so it must be at least
    # as strong as linear_plain at every horizon (median over traces; measured 0.693–0.749 against
    # 0.727–0.781). Targets: model <= 0.95 x linear at every horizon is NOT met against the tuned
    # baseline (measured 0.937–0.979: met at 400 and 500 ms only); the model still beats it on the
    # median trace at every horizon; quiet traces model <= 0.5 x none at 400 ms; coverage 87–93 %
    code, m, _ = traces_validated("lungdeform validate prediction --data DATA --out OUT")  # shared with tests/test_docs_figures.py
    assert code == 0
    markers = [r["horizon_ms"]["400"]["linear_plain_over_none"] for n, r in m["traces"].items() if n.endswith(".csv")]
    assert len(markers) == 15 and np.median(markers) <= 0.76
    for h, med in m["medians"].items():
        assert med["linear_over_none"] <= med["linear_plain_over_none"], h
        assert med["model_over_linear"] < 1.0, h
    assert not m["targets"]["model_over_linear_every_horizon"]["met"]
    assert m["medians"]["400"]["model_over_linear"] <= 0.95 and m["medians"]["500"]["model_over_linear"] <= 0.95
    assert all(med["model_over_linear_plain"] <= 0.95 for med in m["medians"].values())
    assert m["targets"]["quiet_model_over_none"]["met"]
    assert m["targets"]["coverage_every_horizon"]["met"]  # 90 % intervals cover 87–93 % at every horizon
