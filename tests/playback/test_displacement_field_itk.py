"""The DVF and warp on the real ITK right-lung pair (skips without LUNGDEFORM_DATA).

Checks of docs/RADIOTHERAPY.md: the forward field of scan 1 carries the 51 fixed landmarks through
SimpleITK's DisplacementFieldTransform onto ``track``'s positions (in scan 1's frame) and near the
moving landmarks; the resampled end-exhale mask overlaps the real end-inhale mask (Dice) better than
the fit's alignment alone; no voxel folds.
"""

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.evaluate.pipeline import run_fit
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.io.image import read_image, resample_image, to_sitk
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.io.modelfile import load_model
from lungdeform.playback import displacement_field as D
from tests.conftest import require_path


@pytest.fixture(scope="module")
def itk(data_dir, tmp_path_factory):
    """A quick fit of the pair (no grid search, no stiffness, no baselines, 60 evaluations, 3 folds)."""
    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    files = [folder / f"CT_3D_lung_{n}" for n in ("fixed_mask.mha", "moving_mask.mha", "fixed_point_set_corrected.txt",
                                                   "moving_point_set_corrected.txt")]
    out = tmp_path_factory.mktemp("itk-dvf")
    run_fit(FitInputs(files[:2], "right", landmarks=files[2:]), out,
            FitConfig(baselines=False, max_evaluations=60, folds=3))
    return load_model(out / "model.npz"), files


def _dice(a, b):
    a, b = a > 0, b > 0
    return 2.0 * (a & b).sum() / (a.sum() + b.sum())


def test_itk_pair_field_landmarks_dice_and_folding(itk):
    model, (fixed, moving, lm_fixed, lm_moving) = itk
    ref = read_image(fixed)
    grid = D.Grid.of(ref)
    state = D.scan_state(model, 1)
    assert state.delta_ml > 300 and state.alignment is not None  # the apex alignment of scan 1
    fwd = D.displacement_field(model, grid, state.delta_ml, alignment=state.alignment)
    assert fwd.jacobian_min > 0.1  # no folding anywhere (measured 0.37 on the full fit)
    # landmarks through SimpleITK: track's positions (LungModel.points_at at the lung's exact scale)
    # taken into scan 1's frame by the inverse alignment, to 0.1 mm; and near the moving landmarks
    # (the model carries the fit's landmark correction: measured 0.04 mm on the full fit)
    lf, lm = read_elastix_points(lm_fixed), read_elastix_points(lm_moving)
    t = sitk.DisplacementFieldTransform(to_sitk(fwd.field.astype(np.float64), grid.spacing, grid.origin, grid.direction))
    got = np.array([t.TransformPoint(tuple(map(float, p))) for p in lf])
    lung = model.lungs["right"]
    track = lung.points_at(lf, scale=D.state_scales(model, state.delta_ml)["right"])
    a = state.alignment
    track_k = (track - a[:3, 3]) @ np.linalg.inv(a[:3, :3]).T
    assert np.linalg.norm(got - track_k, axis=1).max() < 0.1
    assert np.linalg.norm(got - lm, axis=1).mean() < 2.0
    # the warped end-exhale mask against the real end-inhale mask, on the reference grid; the
    # alignment alone (the rest mask moved rigidly) is the yardstick (measured 0.969 against 0.901)
    inv = D.displacement_field(model, grid, state.delta_ml, alignment=a, inverse=True)
    assert inv.jacobian_min > 0.1 and inv.info["inversion_residual_mm"] < 0.5
    warped = resample_image(ref, inv.field, label=True)
    assert set(np.unique(warped.array)) <= set(np.unique(ref.array))
    mov = sitk.ReadImage(str(moving))
    on_ref = sitk.GetArrayFromImage(sitk.Resample(mov, to_sitk(ref.array, grid.spacing, grid.origin, grid.direction),
                                                  sitk.Transform(), sitk.sitkNearestNeighbor, 0))
    rigid = resample_image(ref, D.add_affine(np.zeros(ref.array.shape + (3,), np.float32), grid, a), label=True)
    dice, dice_rigid = _dice(warped.array, on_ref), _dice(rigid.array, on_ref)
    assert dice >= 0.93 and dice > dice_rigid
