"""scripts/tune_linear_baseline.py: its replay of the online linear predictor, and its search.

The search that tuned the linear baseline (docs/PREDICTION.md "The linear baseline, tuned") scores
thousands of runs through a replay of :class:`lungdeform.breathing.predict.LinearPredictor`; the
replay must be that predictor (a faster way to run it), or the search tuned something else."""

from __future__ import annotations


import numpy as np
import pytest

from lungdeform.breathing.predict import LINEAR_PLAIN, LINEAR_TUNED
from tests.script_support import loaded_script

@pytest.fixture(scope="module")
def tune():
    yield from loaded_script("tune_linear_baseline")


@pytest.mark.parametrize("setting", [("sliding", 15.0, 5.0, 0.0), ("sliding", 30.0, 0.5, 1e-3),
                                     ("forget", 10.0, 1.0, 1e-4), ("forget", 60.0, 5.0, 1e-2),
                                     ("all", None, 1.0, 0.0)])
def test_replay_is_the_online_predictor(tune, rng, setting):
    # truth: the online predictor, one sample at a time. A drifting, irregular breath with noise and
    # irregular sampling (so that refits fall between samples), at two horizons and two windows
    memory, memory_s, refit, ridge = setting
    t = np.cumsum(rng.uniform(0.08, 0.12, 700))
    x = 4 * np.sin(2 * np.pi * t / 3.9) + 0.05 * t + np.sin(2 * np.pi * t / 13.0) + rng.normal(0, 0.1, t.size)
    dt = float(np.median(np.diff(t)))
    for window in (1.0, 2.0):
        s = tune.Setting(window, memory, memory_s, refit, ridge)
        for h in (0.1, 0.5):
            # equal up to rounding: the replay sums a block of outer products where the online predictor
            # adds one at a time, and an unridged normal matrix amplifies that (measured up to 1.3e-7
            # of the range); a different refit or pair would differ by a sizeable share of the range
            np.testing.assert_allclose(tune.replay(t, x, h, s, dt), tune.online(t, x, h, s, dt), rtol=0,
                                       atol=1e-6 * np.ptp(x))


def test_settings_map_to_the_library_and_the_plain_baseline_is_searched(tune):
    # the search's settings are LinearPredictor's; the baseline of <= 0.7 (linear_plain) is among the
    # settings the script scores, and the tuned one is a point of its grid
    plain = tune.Setting(2.0, "sliding", 30.0, 5.0, 0.0)
    assert plain.linear == LINEAR_PLAIN
    grid = {s.linear for s in tune.stage1()} | {s.linear for s in tune.stage1(LINEAR_TUNED.refit_s, LINEAR_TUNED.ridge)}
    assert LINEAR_TUNED in grid
    # every setting says what it is (the search prints them)
    assert {s.text for s in tune.stage1()} >= {"window 1 s, all pairs, refit 1 s, ridge 0.001",
                                                "window 2 s, last 30 s, refit 1 s, ridge 0.001",
                                                "window 2 s, half-life 60 s, refit 1 s, ridge 0.001"}


def test_search_picks_the_best_and_leave_one_out_uses_the_others(tune):
    # criterion: the geometric mean over traces and horizons; leave-one-trace-out chooses on the other
    # traces only (truth: hand-made ratios where one trace alone prefers the other setting)
    a, b = tune.Setting(1.0, "all", None, 1.0, 0.0), tune.Setting(2.0, "all", None, 1.0, 0.0)
    results = {a: {"p": [0.5, 0.5], "q": [0.6, 0.6], "r": [0.9, 0.9]},
               b: {"p": [0.7, 0.7], "q": [0.7, 0.7], "r": [0.2, 0.2]}}
    names = ["p", "q", "r"]
    assert tune.criterion(results[a], names) == pytest.approx((0.5 * 0.6 * 0.9) ** (1 / 3))
    assert tune.criterion(results[b], names) == pytest.approx((0.7 * 0.7 * 0.2) ** (1 / 3))
    loto = tune.leave_one_trace_out(results, names)
    assert loto["r"]["setting"] == a and loto["r"]["ratios"] == [0.9, 0.9]  # chosen on p and q
    assert loto["p"]["setting"] == b  # on q and r: b (0.374) beats a (0.735)
