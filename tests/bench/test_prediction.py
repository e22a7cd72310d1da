"""lungdeform.bench.prediction: the records of ``bench predict`` (structure and invariants, never timings)."""

import numpy as np
import pytest

from lungdeform.bench.prediction import bench_predict, synthetic_breath
from lungdeform.errors import InputError


def test_records_compare_every_predictor_with_the_linear_baseline_of_the_same_run():
    rows = bench_predict(seconds=45.0, rate_hz=10.0, horizon_ms=300.0, warm_s=30.0)
    assert [r["method"] for r in rows] == ["model", "model_intervals", "gate", "linear", "none"]
    by = {r["method"]: r for r in rows}
    # the yardstick is the linear baseline measured in this run: its own ratio is exactly 1
    assert by["linear"]["ratio_to_linear"] == 1.0
    for r in rows:
        # samples after the 30 s warm-up at 10 Hz: 150; the budget fraction is cost × rate
        assert r["samples"] == 150 and r["seconds"] > 0
        assert r["budget_fraction"] == pytest.approx(r["seconds"] * 10.0)
        assert r["p99_seconds"] >= r["seconds"]


def test_synthetic_breath_is_seeded_and_breathes():
    t, x = synthetic_breath(60.0, 10.0)
    t2, x2 = synthetic_breath(60.0, 10.0)
    np.testing.assert_array_equal(x, x2)  # seeded: the same stream every run
    assert t.size == 600 and 9.0 < np.ptp(x) < 11.5  # amplitude 10 mm plus noise


def test_bad_sizes_are_refused():
    with pytest.raises(InputError, match="seconds"):
        bench_predict(seconds=20.0)
