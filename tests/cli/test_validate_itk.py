"""``lungdeform validate itk-pair``: the real right-lung pair (skips without LUNGDEFORM_DATA)."""

import json

from lungdeform.cli.main import main
from tests.conftest import require_path


def test_missing_folder(tmp_path, capsys):
    assert main(["validate", "itk-pair", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not the ITK lung pair folder" in err[0]


def test_itk_pair_real_data(data_dir, tmp_path):
    require_path(data_dir, "itk-right-lung-two-volumes", "CT_3D_lung_fixed_mask.mha")
    out = tmp_path / "itk"
    assert main(["validate", "itk-pair", "--data", str(data_dir), "--out", str(out), "--no-grid",
                 "--no-stiffness", "--evaluations", "150"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    keys = {"surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm", "landmark_max_mm"}
    for name in ("model", "no_motion", "affine", "apex_scaling", "cpd"):
        assert keys <= set(m[name])
    # what the fitted model does meet (measured 2026: surface mean 2.5 mm, landmarks 5.4 mm):
    # it beats no motion and uniform scaling about the apex on both surface and landmarks
    for base in ("no_motion", "apex_scaling"):
        assert m["model"]["surface_mean_mm"] < m[base]["surface_mean_mm"]
        assert m["model"]["landmark_mean_mm"] < m[base]["landmark_mean_mm"]
    # the targets (landmarks < 2 mm and below every baseline, surface < 1.4 mm) are
    # reported in targets_met; they are not met by the paper-form model on this pair
    assert set(m["targets_met"]) == {"model landmark_mean_mm < 2.0", "model landmark_mean_mm below every baseline",
                                     "model surface_mean_mm < 1.4"}
    # the table shift (≈ 40 mm in z) was removed and reported
    assert abs(m["alignment"][0]["apex"]["translation_mm"][2] + 40.0) < 3.0
