"""Held-out validation over a folder of traces (the CLI in tests/cli/test_validate_breathing.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.validate.breathing import find_traces, score_traces, summarise, validate_breathing
from tests.breathing.test_trace import breath, write_marker_csv

MODELS = ("model", "lujan", "fourier")
VARIANTS = ("shared_shape", "shared_shape_no_drift", "anchored", "per_cycle_refit_insample", "percent_of_trace_range",
            "regular_cycles")


def _scores(model: float, lujan: float, noise: float = 0.5) -> dict:
    """A trace's scores as holdout.evaluate reports them (only the keys the summary reads)."""
    per = {"model": model, "lujan": lujan, "fourier": 1.0}
    return {"model_rms_percent": model, "lujan_rms_percent": lujan, "fourier_insample_rms_percent": 1.0,
            "noise_floor_percent": noise, **{v: dict(per) for v in VARIANTS}}


def test_find_traces_recursive_any_case_no_hidden(tmp_path):
    # truth: the .vxp/.csv files in any case under any sub-folder, sorted by path; a resource fork
    # ('._x.csv') and other extensions are not traces
    for name in ("b/one.CSV", "a/two.vxp", "a/._two.csv", "notes.txt", "c.csv"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("")
    assert [p.relative_to(tmp_path).as_posix() for p in find_traces(tmp_path)] == ["a/two.vxp", "b/one.CSV", "c.csv"]


def test_summarise_medians_skip_undefined_and_pair_per_trace():
    # truth: medians over finite values only (NaN and None left out, all-NaN → None); the paired
    # comparison counts traces where PV < Lujan (2 of 3) and takes the median of the differences
    traces = {"p-N-1.csv": _scores(4.0, 6.0), "p-X-2.csv": _scores(8.0, 7.0, noise=float("nan")),
              "p-NO-3.vxp": _scores(2.0, 5.0, noise=float("nan"))}
    traces["p-X-2.csv"]["anchored"]["model"] = float("nan")
    m = summarise(traces, {"bad.csv": "no cycle"}, 500.0, 0.5)
    assert m["median_model_rms_percent"] == 4.0 and m["median_lujan_rms_percent"] == 6.0
    assert m["median_anchored"]["model"] == 3.0  # median of 4 and 2
    assert m["median_noise_floor_percent"] == 0.5
    assert m["median_model_rms_percent_regular_sessions"] == 3.0  # -N- and -NO- names: 4 and 2
    assert m["paired_model_vs_lujan"] == {"traces_model_better": 2, "traces": 3, "median_difference_percent": -2.0}
    assert m["n_traces"] == 3 and m["errors"] == {"bad.csv": "no cycle"}
    assert "500 mL tidal volume" in m["protocol"] and "the first 0.5 of each trace's duration" in m["protocol"]
    for key in traces:
        traces[key]["noise_floor_percent"] = float("nan")
    assert summarise(traces, {}, 500.0, 0.5)["median_noise_floor_percent"] is None


def test_score_traces_refuses_a_folder_without_traces(tmp_path):
    with pytest.raises(InputError, match="nowhere: not a folder"):
        score_traces(tmp_path / "nowhere")
    with pytest.raises(InputError, match="no .vxp or .csv trace found"):
        score_traces(tmp_path)
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(InputError, match=r"no trace could be scored \(1 failed; first: .*empty"):
        score_traces(tmp_path)


def test_validate_breathing_scores_good_and_reports_bad(tmp_path, rng):
    # truth: a regular synthetic breath is fitted well (< 5 % held-out RMS); a file with one breath
    # cannot be scored and is reported, not counted
    data = tmp_path / "data"
    data.mkdir()
    t = np.arange(0.0, 64.0, 0.1)
    write_marker_csv(data / "good.csv", t * 1000, 12.0 * breath(t) + rng.normal(0, 0.05, t.size))
    t1 = np.arange(0.0, 5.0, 0.1)
    write_marker_csv(data / "one_breath.csv", t1 * 1000, 12.0 * breath(t1))
    m = validate_breathing(data, tmp_path / "out")
    assert set(m["traces"]) == {"good.csv"} and set(m["errors"]) == {"one_breath.csv"}
    assert m["median_model_rms_percent"] == m["traces"]["good.csv"]["model_rms_percent"] < 5.0
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["n_traces"] == 1
