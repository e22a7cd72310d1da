"""lungdeform.fit.config: a fit's inputs and settings are validated once, on construction, and an
error names the field (never a command-line option)."""

from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.model.direction import MAX_DEGREE


def test_fit_inputs_are_checked_and_normalised():
    # two paths and the side are the minimum; volumes become a tuple of floats, an empty landmark
    # list means no landmarks (the CLI's repeatable option gives [] when absent)
    inputs = FitInputs([Path("ee.ply"), "ei.ply"], "left", [np.int64(1000), 1300.5], [])
    assert inputs.paths == (Path("ee.ply"), "ei.ply") and inputs.landmarks is None
    assert inputs.volumes_ml == (1000.0, 1300.5) and type(inputs.volumes_ml[0]) is float
    bad = [(dict(paths=["ee.ply"]), "paths: a fit needs inputs at two or more volumes"),
           (dict(side="middle"), "side must be 'left' or 'right'"),
           (dict(volumes_ml=[1000.0]), "volumes_ml has 1 values for 2 inputs"),
           (dict(volumes_ml=[-5.0, 10.0]), "volumes_ml must be positive mL, got -5, 10"),
           (dict(volumes_ml=[float("nan"), 10.0]), "volumes_ml must be positive mL"),
           (dict(landmarks=["ee.txt"]), r"landmarks needs one file per input \(2\), got 1")]
    for change, match in bad:
        args = {"paths": ["ee.ply", "ei.ply"], "side": "right", **change}
        with pytest.raises(InputError, match=match):
            FitInputs(**args)


def test_fit_config_names_the_field_and_never_an_option():
    # every bad value is refused with the field's name first (the CLI maps it to its option);
    # the defaults are the library's: no grid, no stiffness field, alignment chosen on the inputs
    # ("auto": none for one DICOM Frame of Reference, else apex), 5 folds
    config = FitConfig()
    assert (config.grid, config.stiffness, config.align, config.folds) == (False, False, "auto", 5)
    assert config.command == "fit"
    bad = [({"folds": 1}, "folds must be a whole number >= 2"), ({"folds": 2.9}, "folds"),
           ({"max_evaluations": 0}, "max_evaluations must be a whole number >= 1"),
           ({"max_evaluations": True}, "max_evaluations"),
           ({"direction_degree": MAX_DEGREE + 1}, f"direction_degree must be a whole number 0…{MAX_DEGREE}"),
           ({"align": "sideways"}, "align must be one of auto, apex, joint, none"),
           ({"mode": "grid"}, "mode must be one of optimizer, least_squares, powell"),
           ({"align": "joint", "mode": "powell"}, "align 'joint' needs the least-squares optimiser"),
           ({"landmark_weight": -1.0}, "landmark_weight must be a finite number >= 0"),
           ({"grid": "yes"}, "grid must be True or False")]
    for change, match in bad:
        with pytest.raises(InputError, match=match) as info:
            FitConfig(**change)
        assert "--" not in str(info.value)
    # numpy numbers are accepted and stored as plain Python ones
    c = FitConfig(folds=np.int64(3), stiffness=np.bool_(True), landmark_weight=np.float32(0.5))
    assert type(c.folds) is int and c.stiffness is True and type(c.landmark_weight) is float
