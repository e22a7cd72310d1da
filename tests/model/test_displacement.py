"""Volume calibration and playback: exact cubic volume, linear stepping, no per-frame allocation."""

import numpy as np
import pytest

from lungdeform.geometry.mesh import icosphere, signed_volume
from lungdeform.model.displacement import Playback, calibrate, scale_for_volume, volume_polynomial


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
    from lungdeform.errors import LungdeformError

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
