"""``lungdeform validate itk-pair``: the real right-lung pair (skips without LUNGDEFORM_DATA)."""

import json

import pytest

from lungdeform.cli.main import main
from tests.conftest import require_path


def test_missing_folder(tmp_path, capsys):
    assert main(["validate", "itk-pair", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not the ITK lung pair folder" in err[0]


def test_itk_pair_real_data(data_dir, tmp_path):
    require_path(data_dir, "itk-right-lung-two-volumes", "CT_3D_lung_fixed_mask.mha")
    out = tmp_path / "itk"
    rc = main(["validate", "itk-pair", "--data", str(data_dir), "--out", str(out), "--no-grid",
               "--no-stiffness", "--evaluations", "150", "--folds", "3", "--strict"])
    m = json.loads((out / "metrics.json").read_text())
    # --strict: exit code 3 exactly when a target is not met (0 otherwise)
    assert rc == (0 if all(m["targets_met"].values()) else 3)
    keys = {"surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm", "landmark_max_mm"}
    for name in ("model", "model_surface_only", "model_landmark_fit", "no_motion", "affine", "apex_scaling", "cpd",
                 "affine_landmarks", "landmarks_tps"):
        assert keys <= set(m[name]) and name in m["protocols"]
    # the headline model used landmarks (its interior correction), so its landmark errors are held
    # out (3-fold here)
    assert m["headline_fit"] == "optimizer" and m["interior_correction"] and m["landmark_cv"]["folds"] == 3
    assert "held-out" in m["protocols"]["model"] and "no landmark" in m["protocols"]["model_surface_only"]
    # what the fitted models do meet (measured 2026, 5-fold, 300 evaluations: landmark-informed
    # 4.5 mm held out, surface-only 5.2 mm, no motion 11.3 mm, apex scaling 8.0 mm): both beat no
    # motion and uniform scaling about the apex on landmarks, the surface-only fit on surfaces too
    for base in ("no_motion", "apex_scaling"):
        assert m["model"]["landmark_mean_mm"] < m[base]["landmark_mean_mm"]
        assert m["model_surface_only"]["landmark_mean_mm"] < m[base]["landmark_mean_mm"]
        assert m["model_surface_only"]["surface_mean_mm"] < m[base]["surface_mean_mm"]
    # the interior correction is what brings held-out landmarks below every surface baseline
    # (measured 2026-11-21, every default, 5-fold: 1.95 mm against CPD 4.6 mm, affine 5.6 mm, the
    # surface-driven sliding field alone 3.8 mm; 2026-11-28, CPD with the β 32 searched on COPDgene:
    # 1.82 mm against CPD 5.5 mm)
    for base in ("no_motion", "affine", "apex_scaling", "cpd", "model_surface_only"):
        assert m["model"]["landmark_mean_mm"] < m[base]["landmark_mean_mm"]
    # the direction correction lowers the surface error of the paper's directions (measured
    # 2026-11, with a stiffness field: 1.95 -> 1.26 mm)
    assert m["model"]["surface_mean_mm"] < m["model_paper_directions"]["surface_mean_mm"]
    assert m["fit"]["optimizer"]["direction_correction"]["accepted"]
    # the landmark-informed references are scored on the same held-out folds as the model
    assert m["affine_landmarks"]["landmark_mean_mm"] < m["affine"]["landmark_mean_mm"]
    assert set(m["targets_met"]) == {"model landmark_mean_mm < 2.0", "model landmark_mean_mm below every baseline",
                                     "model surface_mean_mm < 1.4",
                                     "model landmark_mean_mm below the landmark-informed references"}
    # the saved model's interior field leaves out the crop face (the mask touches the image's
    # medial face; the model's motion there was never fitted)
    from lungdeform.io.modelfile import load_model

    lung = load_model(out / "model.npz").lungs["right"]
    assert lung.interior_vertices is not None and 0 < (~lung.interior_vertices).sum() < 0.2 * lung.n_vertices
    # the sliding interpolation of the surface's normal motion moves the real landmarks better than
    # the thin-plate spline of the whole surface displacement (0.2's field; measured 2026-11-21 with
    # every default: 3.8 against 4.6 mm), the landmark correction left out of both
    from dataclasses import replace

    import numpy as np

    from lungdeform.io.landmarks import read_elastix_points

    folder = data_dir / "itk-right-lung-two-volumes"
    xf = np.array(m["alignment"][0]["applied"]["matrix"])
    lm0 = read_elastix_points(folder / "CT_3D_lung_fixed_point_set_corrected.txt")
    lm1 = read_elastix_points(folder / "CT_3D_lung_moving_point_set_corrected.txt") @ xf[:3, :3].T + xf[:3, 3]
    bare = replace(lung, landmarks=None, landmark_correction=None)
    err = {kind: np.linalg.norm(replace(bare, interior_kind=kind).points_at(lm0, m["volumes_ml"][1]) - lm1, axis=1).mean()
           for kind in ("sliding", "thin_plate")}
    assert err["sliding"] < err["thin_plate"] - 0.3
    # the sliding landmark correction (it keeps the surface's normal motion) predicts held-out
    # landmarks better than the thin-plate correction of schema 2, on every split tried (measured
    # 2026-11-21 with every default, ten 5-fold splits: 1.90-2.07 mm, mean 1.97, against 2.00-2.25,
    # mean 2.08; with this test's faster fit, seeds 0-2: 1.97/2.01/2.17 against 2.00/2.04/2.28)
    from lungdeform.evaluate.folds import correction_solvers, held_out_positions, held_out_sliding, landmark_folds

    on = lung.interior_vertices
    s = lung.scale_for(m["volumes_ml"][1])
    unit = bare.interior.displacement(lm0)
    solvers = correction_solvers(lung.surface.vertices[on], lung.surface.vertex_normals[on], lm0)
    errors = []
    for seed in range(3):
        folds = landmark_folds(len(lm0), 5, seed)
        sliding = held_out_sliding([lm1 - lm0], [s], unit, folds, solvers)[0]
        thin = held_out_positions(lm0, [lm1 - lm0], [s], unit, folds)[0]
        errors.append([np.linalg.norm(sliding - lm1, axis=1).mean(), np.linalg.norm(thin - lm1, axis=1).mean()])
    errors = np.array(errors)
    print("held-out landmark error, sliding / thin-plate correction (mm):", errors.round(3).tolist())
    assert np.all(errors[:, 0] < errors[:, 1]) and errors[:, 0].mean() < errors[:, 1].mean() - 0.03
    # and the headline is that sliding correction: recomputed here on the command's folds (3, seed
    # 0) it gives the reported figure; the saved model carries it (its smoothing one of the
    # candidates, in mm) and, in sample, moves the landmarks onto their observed positions
    from lungdeform.interior.field import CORRECTION_SMOOTHING_MM

    again = held_out_sliding([lm1 - lm0], [s], unit, landmark_folds(len(lm0), 3), solvers)[0]
    assert np.linalg.norm(again - lm1, axis=1).mean() == pytest.approx(m["model"]["landmark_mean_mm"], abs=1e-6)
    assert m["landmark_cv"]["interior_smoothing_mm"] == lung.landmark_smoothing in CORRECTION_SMOOTHING_MM
    assert lung.interior_kind == "sliding"
    assert np.abs(lung.points_at(lm0, m["volumes_ml"][1]) - lm1).max() < 1e-6
    # the table shift (≈ 40 mm in z) was removed and reported
    assert abs(m["alignment"][0]["apex"]["translation_mm"][2] + 40.0) < 3.0
