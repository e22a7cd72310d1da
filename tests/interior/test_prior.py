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


def test_taper_is_a_c1_step_from_the_surface():
    # why: w must be 0 on and outside the surface (the interior field is the surface's own motion
    # there), 1 from the width on (the prior as learned), monotone and C¹ (no kink in the field)
    from lungdeform.interior.prior import taper
    d = np.linspace(-5.0, 25.0, 3001)
    w = taper(d, 20.0)
    assert np.all(w[d <= 0] == 0) and np.all(w[d >= 20] == 1) and np.all(np.diff(w) >= 0)
    slope = np.diff(w) / np.diff(d)
    assert abs(slope[0]) < 1e-12 and abs(slope[-1]) < 1e-12 and np.abs(np.diff(slope)).max() < 1e-3  # bounded curvature: 6/h² × 0.01 mm steps
    assert np.isclose(taper(10.0, 20.0), 0.5) and np.isclose(slope.max(), 1.5 / 20.0, rtol=1e-3)


def test_tapered_prior_vanishes_on_the_surface_and_is_the_prior_deep_inside(left_lung, rng):
    # why: the prior must not move the lung's own surface (w = 0 there, to the depth grid's accuracy at
    # the mesh's vertices) and must be the affine prior unchanged deeper than its width
    from lungdeform.interior.prior import PRIOR_TAPER_MM, TaperedPrior
    a = rng.normal(scale=0.01, size=(3, 4))
    p = TaperedPrior(a, left_lung.vertices, left_lung.faces)
    on = p(left_lung.vertices)
    full = left_lung.vertices @ a[:, :3].T + a[:, 3]
    assert np.abs(on).max() < 1e-3 * np.abs(full).max()
    centre = left_lung.vertices.mean(axis=0)
    deep = centre + rng.normal(scale=5.0, size=(50, 3))  # the ellipsoid's semi-axes are 45, 70, 110 mm
    assert np.allclose(p(deep), deep @ a[:, :3].T + a[:, 3], atol=1e-12)
    outside = centre + [200.0, 0.0, 0.0] + rng.normal(scale=5.0, size=(20, 3))
    assert np.all(p(outside) == 0) and p.width_mm == PRIOR_TAPER_MM
