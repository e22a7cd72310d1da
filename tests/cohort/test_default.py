"""Learning a population default: the pooled constants and the interior prior recover what made the data."""

from dataclasses import replace

import numpy as np
import pytest

from lungdeform.cohort.default import DefaultSample, learn_default, pooled_constants
from lungdeform.errors import InputError
from lungdeform.interior.prior import taper_weights
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.model.population import paper_default
from tests.conftest import ellipsoid_lung


def _samples(offset_per_ml, rng):
    """Four synthetic lungs (two subjects × two sides) moved by one default with known constants, their
    landmarks at +dv moved by that model plus ``offset_per_ml (3,)`` mm per mL (a known interior prior
    with no linear part, in the mirrored lung frame) tapered to zero at the surface as a built lung
    plays a prior (:class:`lungdeform.interior.prior.TaperedPrior`)."""
    c = np.array([0.1, 1.5, 0.4, 1.0, 1.2, 2.5, 0.3, 0.33, 1.0])
    truth = replace(paper_default(), name="truth", constants={"left": c, "right": c})
    out = []
    for subject, dv in (("a", 300.0), ("b", 600.0)):
        for side in ("left", "right"):
            s = ellipsoid_lung(side, 3)
            lung = build_lung(s, side, default=truth, settings=BuildSettings(dv))
            q = s.vertices.mean(axis=0) + rng.normal(scale=15.0, size=(40, 3))
            moved = lung.points_at(q, lung.volume_ee_ml + dv, exact=True)
            mirror = np.array([-1.0, 1, 1]) if side == "left" else np.ones(3)
            fade = taper_weights(q, s)[:, None]
            assert 0 < fade.min() < 1 == fade.max()  # landmarks within the taper and deeper than it
            out.append(DefaultSample(subject, side, s, c * [1, 1, 1, 1, 1, 1, 2, 2, 2], lung.directions, lung.force,
                                     q, moved + dv * fade * offset_per_ml * mirror, dv))
    return c, out


def test_constants_and_prior_are_recovered(rng):
    # all lungs share the constants (c7…c9 given at twice the scale: the pool rescales them to max |c| = 1),
    # and their landmarks carry a known offset per mL: both must come back
    offset = np.array([0.004, -0.01, 0.006])
    c, samples = _samples(offset, rng)
    d = learn_default(samples, name="learned")
    assert np.allclose(d.constants_for("left"), c, atol=1e-12)
    assert np.allclose(d.interior_prior[0], offset, atol=1e-6)  # β₀ (mm per mL, mirrored frame)
    assert np.abs(d.interior_prior[1:]).max() < 1e-6  # no linear part in the data, none learned
    assert d.provenance["subjects"] == ["a", "b"] and len(d.provenance["lungs"]) == 4


def test_needs_two_lungs_and_nonzero_force(rng):
    _, samples = _samples(np.zeros(3), rng)
    with pytest.raises(InputError, match="at least 2 training lungs"):
        learn_default(samples[:1])
    with pytest.raises(InputError, match="c7…c9 are all zero"):
        pooled_constants([replace(samples[0], constants=np.r_[np.ones(6), np.zeros(3)])])
