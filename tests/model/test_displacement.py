"""Volume calibration and playback: exact cubic volume (of one field and of morph targets), exact scales
for a volume in mL, linear stepping, no per-frame allocation."""

import numpy as np
import pytest

from lungdeform.errors import LungdeformError
from lungdeform.geometry.mesh import icosphere, signed_volume
from lungdeform.model.displacement import (
    MM3_PER_ML,
    Playback,
    calibrate,
    calibration_units,
    cubic_along,
    cubic_in_weight,
    enclosed_volume_ml,
    morph_targets,
    positions_at,
    scale_for_volume,
    scales_for_volumes,
    tidal_displacement,
    volume_change_ml,
    volume_polynomial,
    volume_tensors,
)


def test_volume_polynomial_is_exact(rng):
    # V(p + s·u) is a cubic in s: the polynomial must match direct evaluation at any s.
    s = icosphere(2, 50.0)
    u = rng.normal(size=s.vertices.shape)
    a = volume_polynomial(s.vertices, s.faces, u)
    assert a[0] == pytest.approx(s.volume, rel=1e-12)
    for t in (-3.0, 0.5, 2.0, 7.0):
        assert np.polyval(a[::-1], t) == pytest.approx(signed_volume(s.vertices + t * u, s.faces), rel=1e-10)


def test_uniform_scaling_polynomial_matches_sphere():
    # u = p/r on a sphere: V(s) = V0 (1 + s/r)^3, so a = V0·(1, 3/r, 3/r², 1/r³).
    r = 40.0
    s = icosphere(3, r)
    a = volume_polynomial(s.vertices, s.faces, s.vertices / r)
    assert np.allclose(a, s.volume * np.array([1, 3 / r, 3 / r**2, 1 / r**3]), rtol=1e-10)


def test_calibration_is_exact_at_the_tidal_volume(rng):
    s = icosphere(3, 60.0)
    raw = s.vertex_normals * rng.uniform(0.5, 1.5, (s.n_vertices, 1))
    u = calibrate(s.vertices, s.faces, raw, calibration_ml=300.0, unit_ml=1.5)
    grown = signed_volume(s.vertices + (300.0 / 1.5) * u, s.faces)
    assert grown - s.volume == pytest.approx(300.0 * 1000, rel=1e-10)
    a = volume_polynomial(s.vertices, s.faces, u)
    for ml in (10.0, 150.0, 300.0):
        k = scale_for_volume(a, ml)
        assert signed_volume(s.vertices + k * u, s.faces) - s.volume == pytest.approx(ml * 1000, rel=1e-9)


def test_shrinking_field_is_refused():
    s = icosphere(2, 60.0)
    with pytest.raises(LungdeformError, match="shrinks"):
        calibrate(s.vertices, s.faces, -s.vertex_normals)


def test_playback_steps_equal_seek(rng):
    # Stepping k times by Δs is the same frame as seeking to k·Δs (three additions per vertex).
    p = rng.normal(size=(500, 3))
    u = rng.normal(size=(500, 3))
    pb = Playback(p, u, dtype=np.float64)
    pb.set_step(0.25)
    buf = pb.positions
    for _ in range(8):
        out = pb.step()
    assert out is buf  # updated in place, no new allocation
    assert np.allclose(out, p + 2.0 * u)
    assert pb.scale == pytest.approx(2.0)
    assert np.allclose(pb.seek(-1.0), p - u) and pb.positions is buf


def test_volume_tensors_match_the_volume_polynomial(rng):
    # truth: volume_polynomial of the combined field, for random combinations of 5 targets; the cubic
    # along w (cubic_along) is the same polynomial without its constant term
    s = icosphere(2, 50.0)
    p, f = s.vertices, s.faces
    targets = np.stack([s.vertex_normals * rng.uniform(0.5, 2.0, (s.n_vertices, 1)) for _ in range(5)])
    targets += rng.normal(scale=0.3, size=targets.shape)
    a0, a1, a2, a3 = volume_tensors(p, f, targets)
    for _ in range(3):
        w = rng.normal(size=5)
        poly = volume_polynomial(p, f, np.tensordot(w, targets, axes=1))
        got = [a0, a1 @ w, w @ a2 @ w, np.einsum("ijk,i,j,k->", a3, w, w, w)]
        np.testing.assert_allclose(got, poly, rtol=1e-9, atol=1e-6 * abs(poly[0]))
        np.testing.assert_allclose(cubic_along(a1, a2, a3, w)[1:], poly[1:], rtol=1e-9, atol=1e-6 * abs(poly[0]))
        assert cubic_along(a1, a2, a3, w)[0] == 0.0


def test_scale_for_volume_inverts_the_sphere_cubic_both_ways():
    # u = p/r on a sphere of volume V0 (mm³): V(s) = V0 (1 + s/r)³, so the scale that adds Δ mL is
    # r·(((V0 + 1000 Δ)/V0)^(1/3) − 1), negative for a negative Δ
    r = 40.0
    s = icosphere(3, r)
    poly = volume_polynomial(s.vertices, s.faces, s.vertices / r)
    v0 = poly[0]
    deltas = np.array([-100.0, -5.0, 0.0, 20.0, 300.0])
    expect = r * (np.cbrt((v0 + MM3_PER_ML * deltas) / v0) - 1.0)
    np.testing.assert_allclose(scales_for_volumes(poly, deltas), expect, rtol=1e-10, atol=1e-12)
    assert scale_for_volume(poly, 0.0) == 0.0
    assert [scale_for_volume(poly, d) for d in deltas] == scales_for_volumes(poly, deltas).tolist()


def test_scale_for_volume_refuses_unreachable_volumes():
    # V(s) = −1000 s mm³ (a field that shrinks the lung): growing by 1 mL needs s < 0 and shrinking s > 0,
    # neither on the side asked for
    shrinking = np.array([0.0, -MM3_PER_ML, 0.0, 0.0])
    with pytest.raises(LungdeformError, match="no positive scale"):
        scale_for_volume(shrinking, 1.0)
    with pytest.raises(LungdeformError, match="no scale shrinks the lung by 1.0 mL"):
        scale_for_volume(shrinking, -1.0)
    # a growing linear field: V(s) = 1000 s mm³, so ±1 mL is s = ±1 exactly
    assert scale_for_volume(-shrinking, 1.0) == pytest.approx(1.0, rel=1e-12)
    assert scale_for_volume(-shrinking, -1.0) == pytest.approx(-1.0, rel=1e-12)


def test_volume_change_and_cubic_in_weight_match_the_measured_volume(rng):
    # truth: the volume enclosed by p + s·u measured on the mesh (mL); the cubic in the weight
    # λ = s/units gives the same volume at λ as the cubic in s at λ·units
    s = icosphere(2, 60.0)
    u = s.vertex_normals * rng.uniform(0.5, 1.5, (s.n_vertices, 1))
    poly = volume_polynomial(s.vertices, s.faces, u)
    v0 = enclosed_volume_ml(s.vertices, s.faces)
    assert v0 == pytest.approx(s.volume_ml, rel=1e-12)
    scales = np.array([-2.0, 0.5, 3.0])
    measured = [enclosed_volume_ml(s.vertices + k * u, s.faces) - v0 for k in scales]
    np.testing.assert_allclose(volume_change_ml(poly, scales), measured, rtol=1e-9)
    units = 2.5
    in_weight = cubic_in_weight(poly, units)
    for lam in (0.2, 1.0):
        assert np.polyval(in_weight[::-1], lam) == pytest.approx(np.polyval(poly[::-1], lam * units), rel=1e-12)


def test_morph_targets_recover_the_basis_factor(rng):
    # truth: the displacement is 2.5 × the force-weighted recombination of the basis, so target 0 is
    # units × displacement and the least-squares factor is 2.5 × units (exact up to rounding)
    n = 50
    basis = rng.normal(size=(4, n, 3))
    w = rng.normal(size=4)
    u = 2.5 * np.tensordot(w, basis, axes=1)
    units = calibration_units(300.0, 1.5)
    assert units == 200.0
    targets, kappa = morph_targets(u, basis, w, units)
    assert targets.shape == (5, n, 3)
    np.testing.assert_array_equal(targets[0], tidal_displacement(u, units))
    assert kappa == pytest.approx(2.5 * units, rel=1e-12)
    np.testing.assert_allclose(np.tensordot(w, targets[1:], axes=1), targets[0], rtol=1e-10)
    # no basis (all zero): the factor falls back to 1
    assert morph_targets(u, np.zeros_like(basis), w, units)[1] == 1.0


def test_positions_at_broadcasts_scales(rng):
    # truth: x = p + s·u per frame and per point, written out as a loop
    p, u = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    s = rng.normal(size=(6, 4))
    x = positions_at(p[None], u[None], s)
    assert x.shape == (6, 4, 3)
    for f in range(6):
        for j in range(4):
            np.testing.assert_allclose(x[f, j], p[j] + s[f, j] * u[j], rtol=1e-15)
