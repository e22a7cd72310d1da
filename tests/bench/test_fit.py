"""``lungdeform bench fit`` (lungdeform.bench.fit): Par0011's settings, elastix on a phantom with a cut
schedule and a cheap fit on a phantom case, and the command's wiring. No timing is asserted (times are
the bench's output, not a test's); elastix runs one resolution of 20 iterations only."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from lungdeform.bench import fit as F
from lungdeform.cli import bench_fit as cli_bench_fit
from lungdeform.cli.main import main
from lungdeform.fit.config import FitConfig
from lungdeform.io.image import read_image
from lungdeform.validate.copd import copd_config

itk = pytest.importorskip("itk", reason="itk-elastix is the optional extra 'bench' (requirements.lock installs it)")


def test_par0011_settings_are_the_model_zoo_entry():
    # truth: the model zoo's Parameters.Par0011.affine and .bspline1_s: five resolutions 16…1,
    # 1000 iterations, 2000 random samples, NCC (+ 0.05 × bending energy), a 10 mm final grid
    affine, bspline = F.ElastixSchedule().maps()
    for m in (affine, bspline):
        assert m["NumberOfResolutions"] == ("5",) and m["MaximumNumberOfIterations"] == ("1000",)
        assert m["ImagePyramidSchedule"][:3] == ("16",) * 3 and m["ImagePyramidSchedule"][-3:] == ("1",) * 3
        assert m["NumberOfSpatialSamples"] == ("2000",) and m["Optimizer"] == ("AdaptiveStochasticGradientDescent",)
    assert affine["Transform"] == ("AffineTransform",) and affine["Metric"] == ("AdvancedNormalizedCorrelation",)
    assert bspline["Metric"] == ("AdvancedNormalizedCorrelation", "TransformBendingEnergyPenalty")
    assert bspline["Metric1RelativeWeight"] == ("0.05",) and bspline["FinalGridSpacingInPhysicalUnits"] == ("10.0",) * 3
    assert bspline["GridSpacingSchedule"] == ("8.0", "8.0", "4.0", "2.0", "1.0")
    # a cut schedule keeps the finest resolutions of each schedule, consistently
    a2, b2 = F.ElastixSchedule(resolutions=2, iterations=30).maps()
    assert a2["ImagePyramidSchedule"] == ("2",) * 3 + ("1",) * 3 and b2["GridSpacingSchedule"] == ("2.0", "1.0")
    assert a2["MaximumNumberOfIterations"] == ("30",) and F.PAR0011_AFFINE["MaximumNumberOfIterations"] == ("1000",)


def test_bench_fit_records_both_sides(tmp_path):
    # truth: the record holds one time per repeat for each side, their medians' ratio, the model's
    # surface distance per lung (a fit of scaled ellipsoids: well below the scaling's few mm) and
    # elastix's per lung, which must beat the masks as they lie (inspiration is expiration scaled by
    # 6-12 % about each lung's centre: their surfaces a few mm apart); ITK runs its pool threader.
    # A cheap fit (no baselines, sliding interior, few evaluations) and elastix cut to one
    # resolution of 20 iterations: the command's own settings are checked below, without running
    case = F.write_phantom_case(tmp_path / "case")
    config = FitConfig(max_evaluations=8, align="joint", folds=3, baselines=False, interior="sliding",
                       direction_degree=0)
    r = F.bench_fit(case, config, F.BenchSettings(1, 2, F.ElastixSchedule(1, 20)))
    assert r["case"] == "phantom" and r["threads"] == 2 and r["itk_threader"].lower() == "pool"
    # with two threads the model's lungs were fitted at once in two worker processes: the same fits
    # as one after the other in this process (the fit is deterministic)
    assert r["model_workers"] == 2
    _, _, serial = F.model_fit(case, config, tmp_path / "serial")
    assert r["model_surface_mean_mm"] == serial
    assert len(r["model_seconds"]) == len(r["elastix_seconds"]) == 1
    assert r["ratio"] == pytest.approx(r["model_median_s"] / r["elastix_median_s"])
    # CPU seconds beside the wall ones: positive, one per repeat, their medians' ratio
    assert len(r["model_cpu_seconds"]) == len(r["elastix_cpu_seconds"]) == 1
    assert r["model_cpu_median_s"] > 0 and r["elastix_cpu_median_s"] > 0
    assert r["cpu_ratio"] == pytest.approx(r["model_cpu_median_s"] / r["elastix_cpu_median_s"])
    assert r["blas_threads"].startswith("at most 2 ")
    assert set(r["model_surface_mean_mm"]) == {"left", "right"}
    assert all(0 < v < 1.5 for v in r["model_surface_mean_mm"].values())
    unregistered = F.warped_surface_distance(np.asarray(read_image(case.exp_mask).array, np.float32), case.insp_mask)
    assert set(r["elastix_surface_mean_mm"]) == {"left", "right"}
    for side, v in r["elastix_surface_mean_mm"].items():
        assert unregistered[side] > 2.0 and 0 < v < 0.5 * unregistered[side]


def test_bench_fit_command_runs_validate_copds_fit(tmp_path, monkeypatch, capsys):
    # truth: the command benches the case asked for with validate copd's own settings (copd_config
    # at --evaluations) and elastix's full Par0011 unless cut; it prints both times and the ratio
    # and writes the record (bench_fit itself is the test above)
    seen = {}

    def fake(case, config, settings, progress=None):
        seen.update(case=case, config=config, settings=settings)
        return {"case": case.name, "repeats": 1, "threads": 2, "itk_threader": "Pool", "model_workers": 2, "model_seconds": [3.0],
                "elastix_seconds": [60.0], "model_median_s": 3.0, "elastix_median_s": 60.0, "ratio": 0.05,
                "model_surface_mean_mm": {"left": 1.0, "right": 0.9}, "elastix_surface_mean_mm": {"left": 1.2, "right": 1.1},
                "model_cpu_median_s": 2.5, "elastix_cpu_median_s": 100.0, "cpu_ratio": 0.025, "blas_threads": "2",
                "elastix_schedule": {"resolutions": None, "iterations": None},
                "load_average_1min": {"start": 1.0, "end": 1.0}}

    monkeypatch.setattr(cli_bench_fit, "bench_fit", fake)
    case = F.write_phantom_case(tmp_path / "src")
    data = tmp_path / "data"
    data.mkdir()
    for src, name in ((case.exp_mask, "exp_mask.nii.gz"), (case.insp_mask, "insp_mask.nii.gz"),
                      (case.exp_landmarks, "exp_landmarks.txt"), (case.insp_landmarks, "insp_landmarks.txt")):
        shutil.copy(src, data / f"copd3_{name}")
    out = tmp_path / "b.json"
    assert main(["bench", "fit", "--data", str(data), "--case", "3", "--repeats", "1", "--threads", "2",
                 "--evaluations", "40", "--json", str(out)]) == 0
    assert seen["case"].name == "copd3" and seen["case"].exp_mask == data / "copd3_exp_mask.nii.gz"
    assert seen["config"] == copd_config(40) and seen["settings"].schedule == F.ElastixSchedule()
    assert seen["settings"].at_once and seen["settings"].workers == 2
    assert json.loads(out.read_text())["results"][0]["ratio"] == 0.05
    printed = capsys.readouterr().out
    assert "ratio model / elastix: 0.050" in printed and "ratio 0.025" in printed
    assert "the model's lungs at once in 2 worker processes" in printed
    main(["bench", "fit", "--data", str(data), "--case", "3", "--repeats", "1", "--threads", "2", "--one-lung-at-a-time"])
    assert not seen["settings"].at_once and seen["settings"].workers == 0


def test_bench_fit_refuses_a_bad_case(tmp_path, capsys):
    # the case is checked before anything runs; the message names the option
    assert main(["bench", "fit", "--data", str(tmp_path), "--case", "lung"]) == 2
    assert "--case must be a COPDgene case" in capsys.readouterr().err
