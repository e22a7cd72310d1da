"""``lungdeform bench fit`` (lungdeform.bench.fit): Par0011's settings, elastix on a phantom with a cut
schedule, and the command's record on a phantom case. No timing is asserted (times are the bench's
output, not a test's); elastix runs one resolution of 20 iterations only."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from lungdeform.bench import fit as F
from lungdeform.cli.main import main
from lungdeform.io.image import read_image

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


@pytest.mark.slow
def test_bench_fit_command_records_both_sides(tmp_path, capsys):
    # truth: the record holds one time per repeat for each side, their medians' ratio, the model's
    # surface distance per lung (a fit of scaled ellipsoids: well below the scaling's few mm) and
    # elastix's; ITK runs its pool threader with the threads asked for
    case = F.write_phantom_case(tmp_path / "src")
    data = tmp_path / "data"
    data.mkdir()
    for src, name in ((case.exp_mask, "exp_mask.nii.gz"), (case.insp_mask, "insp_mask.nii.gz"),
                      (case.exp_landmarks, "exp_landmarks.txt"), (case.insp_landmarks, "insp_landmarks.txt")):
        shutil.copy(src, data / f"copd3_{name}")
    out = tmp_path / "b.json"
    assert main(["bench", "fit", "--data", str(data), "--case", "copd3", "--repeats", "1", "--threads", "2",
                 "--evaluations", "12", "--elastix-resolutions", "1", "--elastix-iterations", "20",
                 "--json", str(out)]) == 0
    r = json.loads(out.read_text())["results"][0]
    # elastix's own figure against the masks before any registration: inspiration is expiration
    # scaled by 6-12 % about each lung's centre, so their surfaces lie a few mm apart
    unregistered = F.warped_surface_distance(np.asarray(read_image(case.exp_mask).array, np.float32), case.insp_mask)
    assert r["case"] == "copd3" and r["threads"] == 2 and r["itk_threader"].lower() == "pool"
    assert len(r["model_seconds"]) == len(r["elastix_seconds"]) == 1
    assert r["ratio"] == pytest.approx(r["model_median_s"] / r["elastix_median_s"])
    assert set(r["model_surface_mean_mm"]) == {"left", "right"}
    assert all(0 < v < 1.5 for v in r["model_surface_mean_mm"].values())
    assert set(r["elastix_surface_mean_mm"]) == {"left", "right"}
    for side, v in r["elastix_surface_mean_mm"].items():
        assert unregistered[side] > 2.0 and 0 < v < 0.5 * unregistered[side]
    assert "ratio model / elastix" in capsys.readouterr().out


def test_bench_fit_refuses_a_bad_case(tmp_path, capsys):
    # the case is checked before anything runs; the message names the option
    assert main(["bench", "fit", "--data", str(tmp_path), "--case", "lung"]) == 2
    assert "--case must be a COPDgene case" in capsys.readouterr().err
