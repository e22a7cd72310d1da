"""Population statistics, checked against numpy on hand-made result records."""

import csv
import json

import numpy as np
import pytest

from lungdeform.cohort.population import (
    CONSTANTS,
    check_result,
    describe,
    population_statistics,
    table_comparison,
    table_i,
    write_population,
)
from lungdeform.constants import TABLE_I
from lungdeform.errors import InputError


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


def test_all_failed_still_reports(tmp_path):
    # nothing to summarise: counts and the failure list are written, statistics are null, no warning
    s = write_population([record("s1", "left", status="failed"), record("s2", "right", status="failed")], tmp_path, tmp_path)
    assert (s["n_ok"], s["n_failed"]) == (0, 2)
    doc = _strict(tmp_path / "population.json")
    assert doc["overall"]["c1"] == {"mean": None, "sd": None, "min": None, "max": None, "n": 0}
    assert [f["subject"] for f in doc["failed"]] == ["s1", "s2"] and doc["by_side"] == {}


def test_time_per_lung_and_departures(cohort, tmp_path):
    # truth: the ok records' seconds are 5…9 s (the failed one is left out), so the median is numpy's
    # median of them; the departures are exactly the Table I rows flagged outside the observed range,
    # and a constant set ten times the paper's on every left lung is one of them
    recs, _ = cohort
    for r in recs[:3]:  # every left lung far above the paper's c2: Table I lies below the range
        r["constants"][1] = 10.0 * TABLE_I["left"][1] * (1 + 0.01 * len(r["subject"]))
    s = write_population(recs, tmp_path, tmp_path)
    ok_seconds = [r["seconds"] for r in recs if r["status"] == "ok"]
    t = s["time_per_lung"]
    assert t["median_s"] == pytest.approx(np.median(ok_seconds)) and t["n"] == 5
    assert (t["min_s"], t["max_s"], t["total_s"]) == pytest.approx((5.0, 9.0, sum(ok_seconds)))
    doc = _strict(tmp_path / "population.json")
    assert [p["subject"] for p in doc["time_per_lung"]["per_lung"]] == ["s0", "s1", "s2", "s3", "s4"]
    outside = {(d["side"], d["constant"]) for d in s["table_i_departures"]}
    assert ("left", "c2") in outside
    assert outside == {(side, c) for side, rows in s["table_i"].items() for c, v in rows.items() if not v["in_range"]}
    with open(tmp_path / "times.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["seconds"]) for r in rows] == pytest.approx(ok_seconds)
