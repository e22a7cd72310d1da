"""lungdeform.bench.cohort: the bench cohort and the throughput records (structure and invariants; timings
are never asserted)."""

from __future__ import annotations

import csv

import pytest

from lungdeform.bench.cohort import INSPIRATION_ML, bench_cohort, make_bench_cohort, throughput_record
from lungdeform.cohort.job import FitOptions
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.io.meshfile import load_surface

#: The cheapest fit that still runs every stage (one evaluation, no baselines, no alignment).
QUICK = FitOptions(max_evaluations=1, baselines=False, align="none", direction_degree=0, side_check=False)


def test_bench_cohort_files(tmp_path):
    # truth: each subject is an embedded lung scaled by 0.9–1.1 (volume ×0.729–1.331) and its second
    # scan is the model's displacement at one unit of INSPIRATION_ML, exact by the volume calibration
    manifest = make_bench_cohort(tmp_path / "c", 3, vertices=300, seed=1)
    rows = list(csv.DictReader(manifest.read_text().splitlines()))
    assert [(r["subject"], r["side"]) for r in rows] == [
        ("B000", "right"), ("B000", "right"), ("B001", "left"), ("B001", "left"), ("B002", "right"), ("B002", "right")]
    assert all(r["volume_ml"] == "" for r in rows)
    base = default_lungs()
    for r_ee, r_ei in zip(rows[::2], rows[1::2]):
        ee, _ = load_surface(manifest.parent / r_ee["path"])
        ei, _ = load_surface(manifest.parent / r_ei["path"])
        assert ee.n_vertices == ei.n_vertices and abs(ee.n_vertices - 300) <= 5
        assert ei.volume_ml - ee.volume_ml == pytest.approx(INSPIRATION_ML, rel=1e-6)
        assert 0.7 < ee.volume_ml / base[r_ee["side"]].volume_ml < 1.35  # 0.9³ … 1.1³, decimation aside
    with pytest.raises(InputError, match="subjects must be at least 1"):
        make_bench_cohort(tmp_path / "none", 0)


def test_throughput_record_arithmetic():
    # truth: hand-computed figures of a run of 4 subjects in 20 s on 2 workers, one failed fit,
    # against a serial loop of 30 s
    results = [{"subject": f"S{i}", "side": "left", "seconds": 6.0, "status": "ok"} for i in range(3)]
    results.append({"subject": "S3", "side": "right", "seconds": 2.0, "status": "failed",
                    "error_type": "FitError", "error": "no convergence"})
    r = throughput_record("dask", 2, 4, 20.0, results, 30.0)
    assert (r["subjects"], r["ok"], r["workers"]) == (4, 3, 2)
    assert r["subjects_per_min"] == 12.0 and r["ratio_to_serial"] == 20.0 / 30.0 and r["speedup_vs_serial"] == 1.5
    assert r["fit_seconds_sum"] == 20.0 and r["overhead_seconds"] == 10.0  # 20 s wall − 20 s of fits / 2 workers
    assert r["errors"] == ["S3/right: FitError: no convergence"]


def test_serial_run_is_its_own_yardstick(tmp_path):
    # truth: with no worker counts only the serial loop runs; it is measured against itself
    manifest = make_bench_cohort(tmp_path / "c", 1, vertices=200)
    rows = bench_cohort(manifest, tmp_path / "out", [], QUICK)
    assert len(rows) == 1
    (r,) = rows
    assert (r["method"], r["workers"], r["subjects"], r["ok"], r["errors"]) == ("serial", 1, 1, 1, [])
    assert r["ratio_to_serial"] == 1.0 and r["speedup_vs_serial"] == 1.0
    assert 0 < r["fit_seconds_sum"] <= r["seconds"]
    assert (tmp_path / "out" / "serial").is_dir()
    with pytest.raises(InputError, match="workers must be at least 1"):
        bench_cohort(manifest, tmp_path / "out2", [0], QUICK)


@pytest.mark.slow
def test_dask_run_is_measured_against_the_serial_loop_of_the_same_run(tmp_path):
    # truth: one record per worker count after the serial one, same subjects, every fit ok, and the
    # ratio is this run's Dask wall time over this run's serial wall time
    pytest.importorskip("distributed")
    manifest = make_bench_cohort(tmp_path / "c", 1, vertices=200)
    rows = bench_cohort(manifest, tmp_path / "out", [1], QUICK)
    assert [(r["method"], r["workers"]) for r in rows] == [("serial", 1), ("dask", 1)]
    serial, dask = rows
    assert serial["subjects"] == dask["subjects"] == 1 and serial["ok"] == dask["ok"] == 1
    assert dask["ratio_to_serial"] == dask["seconds"] / serial["seconds"]
    assert dask["speedup_vs_serial"] == serial["seconds"] / dask["seconds"]
