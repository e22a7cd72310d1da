"""Recovery of a synthetic truth, checked against fabricated fits with known errors and against
hand-made result records."""

import csv
import dataclasses
import json

import numpy as np
import pytest

from lungdeform.cohort.population import CONSTANTS, write_population
from lungdeform.cohort.recovery import add_recovery, recovery
from lungdeform.constants import TABLE_I
from tests.cohort.test_population import _strict, record


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    from lungdeform.cohort.synthetic import SyntheticLungSpec, synthetic_cohort, write_cohort

    folder = tmp_path_factory.mktemp("synthetic")
    lungs = synthetic_cohort(1, delta_ml=(200.0, 300.0), seed=2, spec=SyntheticLungSpec(law="linear"))
    write_cohort(lungs, folder, seed=2)
    return folder, lungs


def _fabricate(out, lung, offset, eps, translation=None):
    """A fitted model whose u is (1 + eps)·u_true and constants true + offset (known errors)."""
    from lungdeform.io.modelfile import save_model
    from lungdeform.model.lung import BuildSettings, Model, build_lung

    model = build_lung(lung.rest, lung.side, constants=lung.constants, settings=BuildSettings(lung.unit_ml, lung.unit_ml))
    model = dataclasses.replace(model, displacement=model.displacement * (1.0 + eps))
    folder = out / "subjects" / lung.subject / lung.side
    save_model(folder / "model.npz", Model({lung.side: model}))
    if translation is not None:
        m = np.eye(4)
        m[:3, 3] = translation
        (folder / "metrics.json").write_text(json.dumps({"alignment": [{"apex": {"matrix": m.tolist()}}] * 2}))
    return record(lung.subject, lung.side, lung.constants + offset, volumes=lung.volumes_ml.tolist())


def test_recovery_against_fabricated_fits(synthetic, tmp_path):
    folder, lungs = synthetic
    left, right = lungs
    off_l = np.array([0.01, -0.02, 0.03, 0.0, 0.0, 0.1, 0.02, 0.0, -0.01])
    off_r = np.array([0.03, 0.02, -0.01, 0.0, 0.0, -0.3, 0.0, 0.0, 0.05])
    shift = np.array([1.0, -2.0, 2.0])
    recs = [_fabricate(tmp_path, left, off_l, 0.05, translation=shift), _fabricate(tmp_path, right, off_r, 0.0),
            record("stranger", "left", TABLE_I["left"])]
    s = add_recovery(write_population(recs, tmp_path, folder), recs, tmp_path, folder)
    rec = _strict(tmp_path / "recovery.json")
    assert rec["n_matched"] == 2 and rec["unmatched"] == [{"subject": "stranger", "side": "left"}]
    # c1, c3, c5 by hand: against the truth rescaled by fitted c3 / true c3 (c3's error is then 0);
    # the raw offsets are kept under constants_raw. The other constants are gauge-free: raw offsets
    gauged = []
    for lung, off in ((left, off_l), (right, off_r)):
        true, fit = lung.constants, lung.constants + off
        gauged.append(fit - np.where(np.isin(np.arange(9), [0, 2, 4]), true * fit[2] / true[2], true))
    gauged = np.array(gauged)
    assert gauged[:, 2] == pytest.approx(0.0, abs=1e-15)  # c3 is the gauge: 0 up to rounding
    for k, name in enumerate(CONSTANTS):
        e = gauged[:, k]
        got = rec["constants"][name]
        assert got["mean_error"] == pytest.approx(e.mean(), abs=1e-12)
        assert got["max_abs_error"] == pytest.approx(np.abs(e).max(), abs=1e-12)
        assert got["sd_error"] == pytest.approx(e.std(ddof=1), abs=1e-12)
        if k in (0, 2, 4):
            raw = np.array([off_l[k], off_r[k]])
            assert rec["constants_raw"][name]["mean_error"] == pytest.approx(raw.mean(), abs=1e-12)
            assert rec["constants_raw"][name]["max_abs_error"] == pytest.approx(np.abs(raw).max(), abs=1e-12)
        else:
            assert e == pytest.approx([off_l[k], off_r[k]], abs=1e-12)
    assert set(rec["constants_raw"]) == {"c1", "c3", "c5"} and "fitted c3 / true c3" in rec["notes"]
    # the scale-free ratio c1/c3 by hand
    true, fit = left.constants, left.constants + off_l
    assert rec["lungs"][0]["error"]["c1/c3"] == pytest.approx(fit[0] / fit[2] - true[0] / true[2])
    # field: pred − true = eps·s·u at the largest volume (linear law, s = 1.5); by numpy
    d = 0.05 * left.scales[-1] * left.displacement
    field = rec["lungs"][0]["field"][-1]
    assert field["point_rms_mm"] == pytest.approx(np.sqrt(np.mean(np.sum(d**2, axis=1))), rel=1e-9)
    n = left.rest.deformed(left.scales[-1] * left.displacement).vertex_normals
    dn = np.einsum("ij,ij->i", d, n)
    assert field["normal_rms_mm"] == pytest.approx(np.sqrt(np.mean(dn**2)), rel=1e-9)
    assert field["tangential_rms_mm"] ** 2 + field["normal_rms_mm"] ** 2 == pytest.approx(field["point_rms_mm"] ** 2, rel=1e-9)
    # the fit saw a target shifted by the alignment: errors against the shifted truth are d − shift
    assert field["alignment_translation_mm"] == pytest.approx(np.linalg.norm(shift))
    assert field["point_rms_aligned_mm"] == pytest.approx(np.sqrt(np.mean(np.sum((d - shift) ** 2, axis=1))), rel=1e-9)
    # the exact right-lung model: no error at all
    exact = rec["lungs"][1]["field"][-1]
    assert exact["point_rms_mm"] < 1e-9 and exact["surface_to_truth_rms_mm"] < 1e-6
    assert "alignment_translation_mm" not in exact
    assert s["recovery"]["constants"]["c6"]["max_abs_error"] == pytest.approx(0.3)
    with open(tmp_path / "recovery.csv", encoding="utf-8", newline="") as fh:
        rows = {r["quantity"]: r for r in csv.DictReader(fh)}
    assert float(rows["c9"]["mean_error"]) == pytest.approx(0.02)
    assert float(rows["c3"]["mean_error"]) == pytest.approx(0.0, abs=1e-12) and "fitted c3 / true c3" in rows["c3"]["note"]
    assert float(rows["c3_raw"]["mean_error"]) == pytest.approx(0.01) and "raw" in rows["c3_raw"]["note"]
    with open(tmp_path / "recovery_by_lung.csv", encoding="utf-8", newline="") as fh:
        by_lung = list(csv.DictReader(fh))
    assert float(by_lung[0]["gauge_factor"]) == pytest.approx((left.constants[2] + off_l[2]) / left.constants[2])
    assert (tmp_path / "plots" / "recovery.png").read_bytes()[:4] == b"\x89PNG"


def test_recovery_common_factor_of_c1_c3_c5_is_no_error(synthetic, tmp_path):
    # truth: directions are normalised, so c1, c3, c5 times any common factor is the same model.
    # A fit that returns the truth's c1, c3, c5 times 1.7 (others exact) has zero gauge-corrected
    # error for every constant and ratio, while its raw errors are the 0.7·true offsets
    folder, lungs = synthetic
    from lungdeform.cohort.synthetic import read_truth

    truth = read_truth(folder / "truth.json")
    scale = np.array([1.7, 1, 1.7, 1, 1.7, 1, 1, 1, 1])
    recs = [record(lu.subject, lu.side, lu.constants * scale, volumes=lu.volumes_ml.tolist()) for lu in lungs]
    rec = recovery(recs, truth)
    assert rec["n_matched"] == 2
    for name, got in rec["constants"].items():
        assert got["n"] == 2 and got["max_abs_error"] == pytest.approx(0.0, abs=1e-12), name
    assert [lu["gauge_factor"] for lu in rec["lungs"]] == pytest.approx([1.7, 1.7])
    for name, k in (("c1", 0), ("c3", 2), ("c5", 4)):
        raw = 0.7 * np.array([lu.constants[k] for lu in lungs])
        assert rec["constants_raw"][name]["max_abs_error"] == pytest.approx(np.abs(raw).max(), rel=1e-12)
        assert rec["constants_raw"][name]["max_abs_error"] > 0.0


def test_recovery_missing_and_failed(synthetic):
    folder, lungs = synthetic
    from lungdeform.cohort.synthetic import read_truth

    truth = read_truth(folder / "truth.json")
    recs = [record(lungs[0].subject, "left", lungs[0].constants), record(lungs[0].subject, "right", status="failed")]
    rec = recovery(recs, truth)
    assert rec["n_matched"] == 1 and rec["n_failed"] == 1
    assert rec["missing"] == [{"subject": lungs[0].subject, "side": "right"}]
    assert rec["constants"]["c5"]["mean_error"] == 0.0 and rec["lungs"][0]["field"] is None


def test_recovery_guards_zero_denominators(synthetic):
    # a fitted c3 of 0 makes c1/c3 undefined (null, no warning); a true value of 0 has no relative error
    folder, lungs = synthetic
    from lungdeform.cohort.synthetic import read_truth

    truth = read_truth(folder / "truth.json")
    key = (lungs[0].subject, "left")
    truth[key] = dict(truth[key], constants=[0.1, 0.3, 0.4, 0.5, 0.1, 2.0, 0.0, 1.0, 0.1])
    c = [0.1, 0.3, 0.0, 0.5, 0.1, 2.0, 0.02, 1.0, 0.1]
    rec = recovery([record(lungs[0].subject, "left", c)], truth)
    assert np.isnan(rec["lungs"][0]["fitted"]["c1/c3"]) and rec["constants"]["c1/c3"]["n"] == 0
    # a fitted c3 of 0 also leaves the gauge undefined: no gauge-corrected c1, c3, c5 error (raw kept)
    assert np.isnan(rec["lungs"][0]["gauge_factor"]) and rec["constants"]["c1"]["n"] == 0
    assert rec["constants_raw"]["c3"]["mean_error"] == pytest.approx(-0.4)
    assert rec["constants"]["c7"]["mean_error"] == pytest.approx(0.02)
    assert rec["constants"]["c7"]["mean_relative_error"] is None
