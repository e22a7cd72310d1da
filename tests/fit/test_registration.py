"""Surface registration: the moment affine and the smooth map, on ellipsoids with known motion."""

import numpy as np

from lungdeform.fit import registration as R
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.geometry.moments import solid_moments


def _ellipsoid(axes, center, subdivisions=3):
    s = icosphere(subdivisions)
    return Surface(s.vertices * np.asarray(axes) + np.asarray(center), s.faces)


def test_moment_affine_maps_one_ellipsoid_onto_another():
    # an axis-aligned ellipsoid scaled per axis and moved: its moments give exactly that map
    small = _ellipsoid([40.0, 60.0, 90.0], [10.0, 20.0, -100.0], subdivisions=4)
    large = _ellipsoid([44.0, 69.0, 117.0], [12.0, 25.0, -120.0], subdivisions=4)
    a, t = R.moment_affine(*solid_moments(small.vertices, small.faces)[1:], *solid_moments(large.vertices, large.faces)[1:])
    np.testing.assert_allclose(a, np.diag([1.1, 1.15, 1.3]), atol=1e-6)
    np.testing.assert_allclose(a @ [10.0, 20.0, -100.0] + t, [12.0, 25.0, -120.0], atol=1e-6)


def test_surface_map_of_a_uniform_expansion_moves_interior_points_by_it():
    # a lung-sized ellipsoid expanded by 20 % about its centre: the map (affine + a smooth field that
    # has nothing left to do) carries interior points to 1.2 × their offset; the farthest-point
    # subsets of the two surfaces correspond (the subset is similarity-equivariant), so exactly
    small = _ellipsoid([45.0, 70.0, 110.0], [90.0, 20.0, -150.0], subdivisions=4)
    large = Surface((small.vertices - [90.0, 20.0, -150.0]) * 1.2 + [90.0, 20.0, -150.0], small.faces)
    m = R.surface_map(small, large, points=300)
    q = np.array([[90.0, 20.0, -150.0], [100.0, 30.0, -120.0], [80.0, 0.0, -200.0]])
    np.testing.assert_allclose(m(q), (q - [90.0, 20.0, -150.0]) * 1.2 + [90.0, 20.0, -150.0], atol=1e-6)


def test_field_per_unit_scales_the_displacement():
    # the model plays q + s·v(q): at the target's scale the field reproduces the map exactly
    small = _ellipsoid([45.0, 70.0, 110.0], [0.0, 0.0, 0.0], subdivisions=2)
    large = Surface(small.vertices * [1.1, 1.1, 1.25], small.faces)
    m = R.surface_map(small, large, points=200)
    q = np.array([[5.0, -10.0, 30.0], [0.0, 40.0, -60.0]])
    v = m.field(2.5)
    np.testing.assert_allclose(q + 2.5 * v(q), m(q), atol=1e-9)
