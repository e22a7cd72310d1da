"""The DIR-Lab experiment of ``lungdeform validate dirlab`` (lungdeform.validate.dirlab_experiment)."""

from __future__ import annotations

import json

import pytest

from lungdeform.errors import InputError
from lungdeform.validate import dirlab as D
from lungdeform.validate.dirlab_experiment import run_dirlab, run_notes, write_metrics
from tests.validate.test_dirlab import make_case_folder


def test_run_evaluates_every_case_and_records_metrics(tmp_path, rng):
    make_case_folder(tmp_path / "data", rng, motion="one_scalar")
    run = run_dirlab(tmp_path / "data", folds=3)
    assert [r.case for r in run.results] == [1, 2]
    # the same numbers as evaluating each case by hand: the experiment adds no processing of its own
    for r in run.results:
        files = run.discovery.cases[r.case]
        assert r.to_dict() == D.evaluate_case(D.load_case(files), files.dims, folds=3).to_dict()
    m = run.metrics()
    assert list(m) == ["cases", "skipped", "model_selection", "hypotheses", "notes", "conventions", "source",
                       "elapsed_s"]
    # two cases: each one's default model is the best held-out model of the other case
    for case, other in (("1", "2"), ("2", "1")):
        c, o = m["cases"][case], m["cases"][other]
        assert c["default_model"] == min(o["heldout_mean_mm"], key=o["heldout_mean_mm"].get)
        assert c["default_model_heldout_mean_mm"] == c["heldout_mean_mm"][c["default_model"]]
        assert c["best_model_diagnostic"] == c["best_model"]
    assert m["model_selection"]["pooled"]["cases"] == [1, 2]
    assert "leave-one-case-out" in m["conventions"]["default_model"]
    # one-scalar motion without noise: the one-scalar model is exact in every case
    assert all(c["one_scalar_mean_mm"] < 1e-5 for c in m["cases"].values())
    assert m["cases"]["2"]["spacing_mm"] == [1.16, 1.16, 2.5]  # case 2's row of voxel_spacing.csv
    assert m["conventions"]["heldout"].endswith("other landmark folds (3)")  # the folds asked for
    assert m["source"] == str((tmp_path / "data").resolve())
    assert m["hypotheses"] == D.hypothesis_summary(list(run.results))


def test_notes_name_cases_off_the_published_mean(tmp_path, rng):
    _truth, pairs = make_case_folder(tmp_path / "data", rng)
    run = run_dirlab(tmp_path / "data")
    # the synthetic 300 pairs are random: a case gets a note exactly when its mean is off the
    # published one (case 1: 3.89 mm, case 2: 4.34 mm) by more than 0.05 mm
    off = {case for case, mean in pairs.items() if abs(mean - D.PUBLISHED_MEAN_300_MM[case]) > 0.05}
    flagged = [n for n in run.notes if ": 300-pair mean " in n]
    assert off and {int(n.split(":")[0].removeprefix("case ")) for n in flagged} == off and len(flagged) == len(off)
    spacing_csv = tmp_path / "data" / "voxel_spacing.csv"
    assert all(n.endswith(f"check its row in {spacing_csv}") for n in flagged)  # the spacing came from there
    assert run_notes(run.discovery, run.results) == list(run.notes)
    assert run.notes[0].startswith("voxel spacing from")  # discovery's notes come first


def test_folds_below_two_refused_before_reading(tmp_path):
    # the folder does not exist: the folds are checked first, so the error names them, not the folder
    with pytest.raises(InputError, match="folds must be ≥ 2, got 1"):
        run_dirlab(tmp_path / "nope", folds=1)


def test_write_metrics(tmp_path, rng):
    make_case_folder(tmp_path / "data", rng)
    run = run_dirlab(tmp_path / "data")
    path = write_metrics(run, tmp_path / "out")
    assert path == tmp_path / "out" / "metrics.json"
    # the file is the metrics as JSON (a round trip gives them back), written atomically: no temp file
    assert json.loads(path.read_text()) == json.loads(json.dumps(run.metrics()))
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["metrics.json"]
