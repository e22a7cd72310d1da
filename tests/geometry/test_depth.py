"""Depth below a closed surface on a grid, against the sphere's analytic depth ``r − |q − c|``."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.depth import crossing_bound, depth_grid
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import icosphere

CENTER = np.array([12.0, -40.0, 100.0])


def _sphere(radius=30.0):
    return icosphere(4, radius, center=CENTER)


def test_depth_of_a_sphere_is_analytic(rng):
    # why: inside a sphere of radius r the depth is r − |q − c|; the mesh's chordal sag (a 5120-face
    # icosphere of 30 mm: under 0.12 mm) and trilinear interpolation between 2 mm nodes (the depth is
    # smooth away from the centre: under h²/(8R) ≈ 0.02 mm) bound the difference, except within a
    # node diagonal (3.5 mm) of the cap, where the capped depth has a kink that the nodes round off
    # (by less than a quarter node)
    s = _sphere()
    g = depth_grid(s.vertices, s.faces, reach_mm=12.0)
    d = rng.normal(size=(4000, 3))
    r = rng.uniform(0.0, 40.0, size=len(d))
    q = CENTER + d / np.linalg.norm(d, axis=1)[:, None] * r[:, None]
    exact = np.clip(30.0 - r, -4.0, 12.0)  # the cap, and the floor two 2 mm nodes outside
    near = r < 30.5  # inside, or outside with every neighbouring node measured
    got = g(q)
    smooth = near & (np.abs(exact - 12.0) > 3.5)
    assert np.abs(got - exact)[smooth].max() < 0.2 and np.abs(got - exact)[near].max() < 0.5
    assert np.all(got[~near] < 0)  # farther out: outside (how far is not kept)
    assert np.abs(g(s.vertices)).max() < 0.2  # the zero level is the surface
    assert g(CENTER[None] + 500.0)[0] == g.floor_mm == -4.0  # beyond the grid: outside, at the floor


def test_depth_reaches_its_cap_deep_inside():
    # why: nodes deeper than the reach are not measured and take the cap, which must be what a
    # measurement would have given after capping
    s = _sphere()
    g = depth_grid(s.vertices, s.faces, reach_mm=5.0, spacing_mm=3.0)
    assert g(CENTER[None])[0] == 5.0
    assert g.values.max() == 5.0 and g.values.min() == -6.0


def test_bad_reach_is_refused():
    s = _sphere()
    with pytest.raises(InputError, match="reach_mm"):
        depth_grid(s.vertices, s.faces, reach_mm=0.0)


def test_crossing_bound_never_cuts_the_closest_point(rng):
    # why: the distance from a point to any point on the surface's other side bounds its distance to
    # the surface from above (the segment crosses it); the bound must stay above it after rounding,
    # and a search within it gives the exact (unbounded) distance, also when it is met exactly
    s = _sphere()
    d = rng.normal(size=(500, 3))
    q = CENTER + d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(5.0, 55.0, size=(len(d), 1))
    exact = SurfaceDistance(s.vertices, s.faces).distance(q)
    bound = crossing_bound(exact)  # the tightest a caller can give: the distance itself
    assert np.all(bound > exact) and np.all(bound - exact < 1e-6)
    assert np.array_equal(SurfaceDistance(s.vertices, s.faces).distance(q, bound), exact)
    assert crossing_bound([0.0]).tolist() == [1e-9]
