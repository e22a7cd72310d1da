"""The lung-normalised affine prior and the surface extension of a built model's interior."""

import numpy as np

from lungdeform.interior.prior import lung_normaliser, normalised, prior_affine, prior_displacement
from lungdeform.interior.surface_map import surface_extension


def test_affine_form_equals_the_normalised_form(left_lung, rng):
    # the (3, 4) world affine is the same displacement as β₀ + B q̂ in the mirrored frame, both sides
    coef = rng.normal(size=(4, 3))
    mu, sd = lung_normaliser(left_lung)
    q = mu + rng.normal(scale=30, size=(50, 3))
    for side in ("left", "right"):
        a = prior_affine(coef, mu, sd, side)
        assert np.allclose(q @ a[:, :3].T + a[:, 3], prior_displacement(coef, q, mu, sd, side))
    # the left lung's frame is mirrored in x: lateral is +x for a left lung, −x for a right one
    assert normalised(mu[None] + [10, 0, 0], mu, sd, "left")[0, 0] < 0 < normalised(mu[None] + [10, 0, 0], mu, sd, "right")[0, 0]


def test_extension_of_an_affine_displacement_is_exact_inside(left_lung, rng):
    # a surface displacement that is affine is carried inside exactly (the Gaussians get nothing)
    m = rng.normal(scale=0.01, size=(3, 3))
    b = rng.normal(size=3)
    u = left_lung.vertices @ m.T + b
    field = surface_extension(left_lung.vertices, u)
    q = left_lung.vertices.mean(axis=0) + rng.normal(scale=20, size=(30, 3))
    assert np.allclose(field(q), q @ m.T + b, atol=1e-8)


def test_extension_follows_a_local_bulge(left_lung):
    # a smooth non-affine surface motion (a bulge at the base) is reproduced on the surface to a few
    # per cent of its size, and decays inside rather than being extrapolated linearly
    v = left_lung.vertices
    base = v[:, 2].min()
    u = np.zeros_like(v)
    u[:, 2] = -5.0 * np.exp(-((v[:, 2] - base) / 30.0) ** 2)
    field = surface_extension(v, u)
    assert np.abs(field(v) - u).max() < 0.25 * 5.0
    centre = v.mean(axis=0)[None]
    assert abs(field(centre)[0, 2]) < 2.5
