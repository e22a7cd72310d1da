"""Population statistics and recovery of a synthetic truth, checked against numpy on hand-made
result records and against fabricated fits with known errors."""

import csv
import dataclasses
import json

import numpy as np
import pytest

from lungdeform.constants import TABLE_I
from lungdeform.errors import InputError
from lungdeform.population import (CONSTANTS, check_result, describe, population_statistics, recovery,
                                   table_comparison, table_i, write_population)


def record(subject, side, constants=None, *, status="ok", volumes=(1500.0, 1800.0, 2000.0), landmark=1.0, seconds=10.0):
    ok = status == "ok"
    return {"schema": "lungdeform.cohort.result", "version": 1, "subject": subject, "side": side,
            "status": status, "error": None if ok else "boom: no such file", "error_type": None if ok else "ReadError",
            "inputs": ["a.ply", "b.ply"], "volumes_ml": list(volumes) if ok else [],
            "constants": list(map(float, constants)) if ok else None,
            "metrics": {"surface_mean_mm": 1.0 + 0.1 * len(subject), "surface_rms_mm": 1.5, "surface_p95_mm": 3.0,
                        "landmark_mean_mm": landmark, "objective_rms_mm": 1.2} if ok else {},
            "seconds": seconds, "input_digest": "0" * 64}


@pytest.fixture
def cohort(rng):
    recs, values = [], {"left": [], "right": []}
    for i in range(5):
        side = "left" if i < 3 else "right"
        c = np.array(TABLE_I[side]) * rng.uniform(0.8, 1.2, 9)
        vols = (1400.0 + 100 * i, 1700.0 + 120 * i)
        recs.append(record(f"s{i}", side, c, volumes=vols, landmark=None if i == 0 else 0.5 * i, seconds=5.0 + i))
        values[side].append((c, vols))
    recs.append(record("s9", "right", status="failed"))
    return recs, values


def test_statistics_match_numpy_and_exclude_failed(cohort):
    recs, values = cohort
    st = population_statistics(recs)
    assert (st["n_results"], st["n_ok"], st["n_failed"]) == (6, 5, 1)
    assert st["failed"] == [{"subject": "s9", "side": "right", "error_type": "ReadError", "error": "boom: no such file"}]
    every = [c for side in ("left", "right") for c, _ in values[side]]
    for k, name in enumerate(CONSTANTS):
        col = np.array([c[k] for c in every])
        s = st["overall"][name]
        assert (s.mean, s.sd, s.min, s.max, s.n) == pytest.approx((col.mean(), col.std(ddof=1), col.min(), col.max(), 5))
        for side in ("left", "right"):
            col = np.array([c[k] for c, _ in values[side]])
            s = st["by_side"][side][name]
            assert (s.mean, s.sd, s.min, s.max, s.n) == pytest.approx(
                (col.mean(), col.std(ddof=1), col.min(), col.max(), len(col)))
    ee = np.array([v[0] for side in ("left", "right") for _, v in values[side]])
    dv = np.array([v[-1] - v[0] for side in ("left", "right") for _, v in values[side]])
    assert st["overall"]["volume_ee_ml"].mean == pytest.approx(ee.mean())
    assert st["overall"]["delta_volume_ml"].sd == pytest.approx(dv.std(ddof=1))
    # a missing landmark error is left out, not counted as 0
    lm = st["overall"]["landmark_mean_mm"]
    assert lm.n == 4 and lm.mean == pytest.approx(np.mean([0.5, 1.0, 1.5, 2.0]))


def test_describe_edge_cases():
    one = describe([3.0])
    assert one.n == 1 and one.mean == 3.0 and np.isnan(one.sd)  # sample SD undefined for one value
    none = describe([None, float("nan")])
    assert none.n == 0 and np.isnan(none.mean)
    assert describe([1.0, 2.0, None, 4.0]).as_dict() == {"mean": pytest.approx(7 / 3), "sd": pytest.approx(np.std([1, 2, 4], ddof=1)),
                                                         "min": 1.0, "max": 4.0, "n": 3}


def test_table_i_flags():
    left = table_i("left")
    # the fit's normalisation: Table I's c7…c9 = 0.01, 0.95, 0.07 divided by 0.95
    assert left[6:] == pytest.approx(np.array(TABLE_I["left"][6:]) / 0.95)
    # c1 spans the paper's value, c2 lies entirely above it, c3 exactly at its value (range closed),
    # c8 = 1 as every fit reports it: in range of the normalised Table I
    recs = []
    for i, f in enumerate((0.9, 1.1)):
        c = left.copy()
        c[0] = left[0] * f
        c[1] = left[1] * (2.0 + i)
        recs.append(record(f"s{i}", "left", c))
    t = table_comparison(population_statistics(recs)["by_side"])
    assert set(t) == {"left"}
    assert t["left"]["c1"]["in_range"] is True and t["left"]["c2"]["in_range"] is False
    assert t["left"]["c3"]["in_range"] is True and t["left"]["c3"]["sd_from_mean"] is None  # SD 0
    assert t["left"]["c8"]["in_range"] is True and t["left"]["c8"]["paper_as_printed"] == 0.95
    c2 = [left[1] * 2.0, left[1] * 3.0]
    assert t["left"]["c2"]["sd_from_mean"] == pytest.approx((left[1] - np.mean(c2)) / np.std(c2, ddof=1))
    assert t["left"]["c2"]["paper"] == TABLE_I["left"][1]


def test_bad_records_are_refused():
    with pytest.raises(InputError, match="result 1"):
        population_statistics([{"schema": "x"}])
    bad = record("s1", "left", TABLE_I["left"])
    bad["constants"] = [1.0, 2.0]
    with pytest.raises(InputError, match="s1/left.*constants"):
        check_result(bad)
    twice = [record("s1", "left", TABLE_I["left"])] * 2
    with pytest.raises(InputError, match="twice"):
        population_statistics(twice)


def _strict(path):
    def refuse(token):
        raise ValueError(f"non-standard JSON constant {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_write_population_files(cohort, tmp_path):
    recs, values = cohort
    s = write_population(recs, tmp_path, tmp_path)
    assert s["n_ok"] == 5 and s["n_failed"] == 1 and s["recovery"] is None
    doc = _strict(tmp_path / "population.json")
    assert doc["by_side"]["left"]["c1"]["mean"] == pytest.approx(np.mean([c[0] for c, _ in values["left"]]))
    assert doc["failed"][0]["subject"] == "s9"
    with open(tmp_path / "population_by_side.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    got = {(r["side"], r["quantity"]): r for r in rows}
    want = np.std([c[8] for c, _ in values["right"]], ddof=1)
    assert float(got[("right", "c9")]["sd"]) == pytest.approx(want, rel=1e-5)
    with open(tmp_path / "table1.csv", encoding="utf-8", newline="") as fh:
        t = list(csv.DictReader(fh))
    assert len(t) == 18 and {r["paper_in_range"] for r in t} <= {"true", "false"}
    for name in ("constants_by_side", "constants_vs_volume", "fit_errors"):
        assert (tmp_path / "plots" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*"))  # no temporary files left


# --------------------------------------------------------------------------- recovery
@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    from lungdeform.synthetic import synthetic_cohort, write_cohort

    folder = tmp_path_factory.mktemp("synthetic")
    lungs = synthetic_cohort(1, delta_ml=(200.0, 300.0), seed=2, law="linear", landmarks=0)
    write_cohort(lungs, folder, seed=2)
    return folder, lungs


def _fabricate(out, lung, offset, eps, translation=None):
    """A fitted model whose u is (1 + eps)·u_true and constants true + offset (known errors)."""
    from lungdeform.model import Model, build_lung
    from lungdeform.modelfile import save_model

    model = build_lung(lung.rest, lung.side, constants=lung.constants, calibration_ml=lung.unit_ml, unit_ml=lung.unit_ml)
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
    s = write_population(recs, tmp_path, folder)
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
    from lungdeform.synthetic import read_truth

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
    from lungdeform.synthetic import read_truth

    truth = read_truth(folder / "truth.json")
    recs = [record(lungs[0].subject, "left", lungs[0].constants), record(lungs[0].subject, "right", status="failed")]
    rec = recovery(recs, truth)
    assert rec["n_matched"] == 1 and rec["n_failed"] == 1
    assert rec["missing"] == [{"subject": lungs[0].subject, "side": "right"}]
    assert rec["constants"]["c5"]["mean_error"] == 0.0 and rec["lungs"][0]["field"] is None


def test_recovery_guards_zero_denominators(synthetic):
    # a fitted c3 of 0 makes c1/c3 undefined (null, no warning); a true value of 0 has no relative error
    folder, lungs = synthetic
    from lungdeform.synthetic import read_truth

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


def test_all_failed_still_reports(tmp_path):
    # nothing to summarise: counts and the failure list are written, statistics are null, no warning
    s = write_population([record("s1", "left", status="failed"), record("s2", "right", status="failed")], tmp_path, tmp_path)
    assert (s["n_ok"], s["n_failed"]) == (0, 2)
    doc = _strict(tmp_path / "population.json")
    assert doc["overall"]["c1"] == {"mean": None, "sd": None, "min": None, "max": None, "n": 0}
    assert [f["subject"] for f in doc["failed"]] == ["s1", "s2"] and doc["by_side"] == {}
