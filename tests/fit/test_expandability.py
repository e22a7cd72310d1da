"""The stiffness-field fit (inverse estimate of alveolar expandability) against synthetic truth: a
model built with a known soft region deforms a lung, the fitted field finds the soft region."""

import numpy as np
import pytest

from lungdeform.fit.expandability import (
    STIFFNESS_RANGE,
    fit_stiffness_field,
    fit_stiffness_if_better,
    smooth_observations,
)
from lungdeform.fit.objective import LungFitter, ObjectiveSettings, Target
from lungdeform.model.lung import BuildSettings, build_lung
from tests.conftest import ellipsoid_lung

TRUE = np.array([0.2, 1.5, 0.4, 0.8, 0.9, 1.8, 0.3, 1.0, 0.5])


def test_smooth_observations_fills_gaps_and_keeps_a_constant(rng):
    # normalised convolution: a constant field observed on a random half of the vertices comes back
    # as that constant everywhere (the gaps are filled from the neighbours, nothing is diluted by
    # the zero weights); a non-constant field keeps its mean within its range
    lung = ellipsoid_lung("left", 2)
    w = (rng.uniform(size=lung.n_vertices) < 0.5).astype(float)
    out = smooth_observations(np.full(lung.n_vertices, 3.5), w, lung.faces, 10)
    assert out == pytest.approx(np.full(lung.n_vertices, 3.5), abs=1e-9)
    v = rng.normal(size=lung.n_vertices)
    sm = smooth_observations(v, np.ones(lung.n_vertices), lung.faces, 10)
    assert v.min() <= sm.min() and sm.max() <= v.max() and sm.std() < 0.5 * v.std()


def test_stiffness_field_is_bounded_and_recovers_a_soft_region():
    # truth: a lung whose lower half is 3× softer; along the true directions the fitted field is
    # softer there, stays inside the bound, and lowers the objective below the uniform model's
    lung = ellipsoid_lung("right", 3)
    z = lung.vertices[:, 2]
    e = np.where(z < np.median(z), 1.0 / 3.0, 1.0)
    model = build_lung(lung, "right", constants=TRUE, stiffness=e, settings=BuildSettings(200.0, 200.0))
    target = lung.deformed(model.displacement).with_name("target")
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")])
    uniform_obj = fitter.evaluate(TRUE[:6])
    log_e = fit_stiffness_field(fitter, TRUE[:6])
    assert np.abs(log_e).max() <= np.log(STIFFNESS_RANGE) + 1e-12
    # the softer third of the lung comes out softer than the stiffer third (3× softer moves the
    # surface only ≈ 1.2× more, so the field is mild)
    assert log_e[z < np.quantile(z, 0.3)].mean() < log_e[z > np.quantile(z, 0.7)].mean() - 0.1
    fitter.set_stiffness(np.exp(log_e))
    assert fitter.evaluate(TRUE[:6]) < 0.75 * uniform_obj



def test_stiffness_field_is_kept_only_when_it_lowers_the_objective():
    # truth: the target is the uniform model's own deformation, so the uniform stiffness is already
    # the exact minimum (objective ~0): a fitted field cannot be better and must be rejected, with
    # the fitter left at uniform stiffness
    lung = ellipsoid_lung("right", 3)
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    target = lung.deformed(model.displacement).with_name("target")
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")], settings=ObjectiveSettings(samples=500))
    best = fitter.evaluate(TRUE[:6])
    said = []
    log_e, obj = fit_stiffness_if_better(fitter, TRUE[:6], best, said.append, iterations=3)
    assert log_e is None and obj == best and "kept the previous one" in said[0]
    assert np.all(fitter.stiffness == 1.0)
