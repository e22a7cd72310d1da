"""The smooth correction of the paper's directions: basis, field, and its fit against known truth."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.direction_correction import (
    CorrectionSearch,
    corrected_directions,
    fit_direction_correction,
    polynomial_basis,
)
from lungdeform.fit.fitting import FitSettings, fit_lung
from lungdeform.fit.objective import LungFitter, Target
from lungdeform.geometry.mesh import Surface
from lungdeform.model.displacement import calibrate
from lungdeform.model.lung import BuildSettings, build_lung
from tests.conftest import ellipsoid_lung

TRUE = np.array([0.2, 1.5, 0.4, 0.8, 0.9, 1.8, 0.3, 1.0, 0.5])


def test_polynomial_basis(rng):
    # all monomials of degree ≤ d in 3 variables: C(d + 3, 3) columns, the constant first; at
    # x̂ = 1/2 (the box centre) every non-constant monomial vanishes
    q = rng.uniform(0, 1, size=(50, 3))
    for degree, k in ((0, 1), (1, 4), (2, 10), (3, 20), (4, 35)):
        phi = polynomial_basis(q, degree)
        assert phi.shape == (50, k) and np.all(phi[:, 0] == 1.0)
        assert polynomial_basis(np.full((1, 3), 0.5), degree)[0, 1:] == pytest.approx(np.zeros(k - 1))
    assert np.linalg.matrix_rank(polynomial_basis(q, 3)) == 20  # independent columns
    with pytest.raises(InputError, match="degree must be 0…4"):
        polynomial_basis(q, 5)


def test_corrected_directions_are_unit_and_zero_is_the_paper(rng):
    d0 = rng.normal(size=(30, 3))
    d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
    phi = polynomial_basis(rng.uniform(0, 1, (30, 3)), 2)
    assert corrected_directions(d0, phi, np.zeros((10, 3))) == pytest.approx(d0)
    d = corrected_directions(d0, phi, 0.3 * rng.normal(size=(10, 3)))
    assert np.linalg.norm(d, axis=1) == pytest.approx(np.ones(30))


@pytest.fixture(scope="module")
def rotated():
    # truth outside the paper's form but inside the correction's: the true model (Table-like
    # constants) with its directions turned by a known degree-1 field, same force, same volume
    lung = ellipsoid_lung("right", 3)
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    fitter = LungFitter(lung, "right", [Target(lung, lung.volume_ml + 200.0)])  # for its frame and basis only
    c_true = np.zeros((4, 3))
    c_true[3] = [0.35, 0.0, 0.0]  # the x-component grows with the lung-frame ẑ
    d = corrected_directions(model.directions, polynomial_basis(fitter.xyz, 1), c_true)
    u = calibrate(lung.vertices, lung.faces, model.force[:, None] * d, calibration_ml=200.0, unit_ml=200.0)
    target = Surface(lung.vertices + u, lung.faces, "rotated target")
    return lung, model, target


def test_fit_recovers_a_rotated_field(rotated):
    # with the true constants, the paper's field misses the turned target; the correction brings
    # the objective down to a small fraction of it, and never reports an increase
    lung, model, target = rotated
    fitter = LungFitter(lung, "right", [Target(target, target.volume_ml)])
    c_force = model.constants[6:]
    r = fit_direction_correction(fitter, model.directions, c_force, degree=1, search=CorrectionSearch(steps=12))
    assert r.accepted and r.objective_mm < 0.25 * r.start_objective_mm
    assert r.start_objective_mm > 0.5  # the target is really off the paper's form
    assert r.coefficients[3] == pytest.approx([0.35, 0.0, 0.0], abs=0.02)  # the known field itself
    again = fit_direction_correction(fitter, model.directions, c_force, degree=1, initial=r.coefficients,
                                     search=CorrectionSearch(steps=2))
    assert again.objective_mm <= r.objective_mm + 1e-9
    with pytest.raises(InputError, match="expected \\(4, 3\\)"):
        fit_direction_correction(fitter, model.directions, c_force, degree=1, initial=np.zeros((10, 3)))


def test_paper_truth_needs_no_correction():
    # invariant: on a target made by the paper's own form, the correction cannot do much better
    # than the exact constants (objective ≈ 0) and an accepted one is always lower
    lung = ellipsoid_lung("right", 3)
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    target = lung.deformed(model.displacement)
    fitter = LungFitter(lung, "right", [Target(target, target.volume_ml)])
    r = fit_direction_correction(fitter, model.directions, model.constants[6:], degree=2,
                                 search=CorrectionSearch(steps=4))
    assert r.objective_mm <= r.start_objective_mm
    assert r.start_objective_mm < 0.1


def test_fit_lung_reports_both_fields(rotated):
    # fit_lung with a correction: the result's displacement is the corrected one (lower objective),
    # the paper's field is kept beside it, and the correction is in the metrics dictionary
    lung, _, target = rotated
    r = fit_lung(lung, "right", [Target(target, target.volume_ml)],
                 FitSettings(direction_degree=1, max_evaluations=60))
    assert r.direction_correction.accepted and r.paper_displacement is not None
    assert r.objective_mm < r.paper_objective_mm
    assert not np.allclose(r.displacement, r.paper_displacement)
    assert r.as_dict()["direction_correction"]["degree"] == 1
    plain = fit_lung(lung, "right", [Target(target, target.volume_ml)], FitSettings(max_evaluations=60))
    assert plain.direction_correction is None and plain.paper_displacement is None
