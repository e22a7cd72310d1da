"""scripts/tune_cpd_baseline.py: the search of the CPD surface baseline's β and w, leave one
subject out (issue 39: every baseline tuned with the same effort as the model).

Checked here: the leave-one-subject-out choice never sees the scored case, an earlier search's figures
are kept only when the CPD settings it did not search agree, and the script runs end to end (every lung,
every setting) and resumes without refitting a finished lung, running only the settings a widened grid
adds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lungdeform.evaluate import baselines as B
from tests.script_support import loaded_script

@pytest.fixture(scope="module")
def tune():
    yield from loaded_script("tune_cpd_baseline")


def _lungs(table):
    return {lung: {s: {"landmark_mean_mm": v, "surface_mean_mm": 1.0} for s, v in row.items()}
            for lung, row in table.items()}


def test_leave_one_subject_out_never_sees_the_scored_case(tune):
    # truth by construction: "a" is best on copd1 alone, "b" on copd2 and on copd3 alone. copd1's pick
    # comes from copd2 and copd3 ("b"); copd2's from copd1 and copd3, whose median favours "a" (3.0
    # against 5.5), though copd2 itself favours "b": had it seen copd2 it would pick "b"
    lungs = _lungs({"copd1/left": {"a": 1.0, "b": 9.0}, "copd1/right": {"a": 1.0, "b": 9.0},
                    "copd2/left": {"a": 5.0, "b": 2.0}, "copd2/right": {"a": 5.0, "b": 2.0},
                    "copd3/left": {"a": 5.0, "b": 2.0}, "copd3/right": {"a": 5.0, "b": 2.0}})
    loso = tune.leave_one_subject_out(lungs)
    assert loso["copd1"]["setting"] == "b" and loso["copd1"]["copd1/left"]["landmark_mean_mm"] == 9.0
    assert loso["copd2"]["setting"] == "a" and loso["copd2"]["copd2/left"]["landmark_mean_mm"] == 5.0
    assert loso["copd3"]["setting"] == "a"
    assert set(loso["copd2"]) == {"setting", "copd2/left", "copd2/right"}


def test_an_earlier_search_is_reused_only_where_it_measured_the_same_cpd(tune, monkeypatch):
    # truth by construction: figures measured with other samples (a CPD setting the search does not
    # vary) are not this search's; with the same fixed settings, the settings in both grids are kept,
    # one the grid dropped is left out, whatever default beta and w the earlier run had
    monkeypatch.setattr(tune, "BETAS", (2.0, 4.0))
    monkeypatch.setattr(tune, "WS", (0.0,))
    cpd = {"samples": 1500, "alpha": 2.0, "beta": 2.0, "w": 0.05}
    row = {"2,0": {"landmark_mean_mm": 3.0}, "2,0.2": {"landmark_mean_mm": 4.0}}
    doc = {"grid": {"cpd": cpd}, "lungs": {"copd1/left": row}}
    now = {"cpd": {**cpd, "beta": 8.0, "w": 0.0}}
    assert tune.reusable(doc, now) == {"copd1/left": {"2,0": {"landmark_mean_mm": 3.0}}}
    assert tune.reusable(doc, {"cpd": {**cpd, "samples": 600}}) == {}
    assert tune.reusable({}, now) == {}


@pytest.mark.slow
def test_search_on_a_phantom_scores_the_pipelines_baseline(tune, tmp_path, monkeypatch):
    # the script end to end on a two-lung phantom (the real search takes ~15 minutes): every lung,
    # every setting, finite figures, nothing left out with one case, a finished lung is not refitted,
    # and a widened grid runs only its new settings; a one-by-two grid and a small CPD keep it short
    from tests.validate.test_copd import phantom_case

    data = tmp_path / "data"
    data.mkdir()
    phantom_case(data, 1)
    monkeypatch.setattr(tune, "BETAS", (B.CpdSettings().beta,))
    monkeypatch.setattr(tune, "WS", (B.CpdSettings().w, 0.2))
    small = B.CpdSettings(samples=300, max_iterations=20)
    monkeypatch.setattr(B, "CpdSettings", lambda: small)
    out = tmp_path / "search.json"
    assert tune.main(["--data", str(data), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["lungs"]) == {"copd1/left", "copd1/right"}
    names = {tune.setting_name(B.CpdSettings().beta, w) for w in (B.CpdSettings().w, 0.2)}
    for row in doc["lungs"].values():
        assert set(row) == names
        assert all(np.isfinite(v["landmark_mean_mm"]) and v["surface_mean_mm"] >= 0 for v in row.values())
    assert doc["leave_one_subject_out"] == {}  # one case: nothing to leave out
    # widened: a second run with one more beta runs that beta only, keeping the figures measured
    runs = []
    scored = B.cpd_deformable
    monkeypatch.setattr(B, "cpd_deformable", lambda *a, **k: runs.append(a[2].beta) or scored(*a, **k))
    monkeypatch.setattr(tune, "BETAS", (B.CpdSettings().beta, 0.5))
    assert tune.main(["--data", str(data), "--out", str(out)]) == 0
    assert runs == [0.5] * 4  # two lungs, two w each
    wider = json.loads(out.read_text())
    assert all(wider["lungs"][k][n] == doc["lungs"][k][n] for k in doc["lungs"] for n in names)
    # resumable: a third run reads the lungs back instead of fitting them again
    monkeypatch.setattr(tune, "lung_scores", lambda *a, **k: pytest.fail("refitted a finished lung"))
    assert tune.main(["--data", str(data), "--out", str(out)]) == 0
