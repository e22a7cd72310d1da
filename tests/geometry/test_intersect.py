"""Self-intersection: crossing face pairs found, neighbours and valid surfaces never counted."""


import numpy as np

from lungdeform.geometry.intersect import self_intersections
from lungdeform.geometry.mesh import icosphere


def _cap_pushed_through(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A sphere of radius 60 mm whose cap z > 40 is reflected through the plane z = -30: the cap ends
    below the sphere (z in [-120, -100)), so the band of faces joining it to the rim passes through
    the lower wall."""
    s = icosphere(subdivisions, 60.0)
    v = s.vertices.copy()
    cap = v[:, 2] > 40
    v[cap, 2] = -60.0 - v[cap, 2]
    return v, s.faces


def test_valid_spheres_have_no_self_intersection():
    # A convex closed surface cannot cross itself; its neighbouring faces share edges and corners only.
    for k in (1, 3, 5):
        s = icosphere(k, 60.0)
        count, pairs = self_intersections(s.vertices, s.faces)
        assert count == 0 and pairs.shape == (0, 2)


def test_cap_pushed_through_is_found():
    v, f = _cap_pushed_through()
    count, pairs = self_intersections(v, f, limit=5)
    assert count > 0 and len(pairs) == 5  # all counted, the first five returned
    assert (pairs[:, 0] < pairs[:, 1]).all()
    # each reported pair is a band face (joining the moved cap to the rim) and one that stayed below
    below = v[:, 2] < -30
    for a, b in pairs:
        assert not set(f[a]) & set(f[b])  # non-adjacent
        moved = [bool(below[f[x]].any() and (v[f[x], 2] > 0).any()) for x in (a, b)]
        assert any(moved)


def test_local_wrinkle_is_not_a_self_intersection():
    # A vertex dragged past its neighbour folds its fan over the next ring of faces: those faces
    # cross (found with local_rings=0) but within LOCAL_RINGS edges of each other, a wrinkle that
    # leaves inside and outside as they were (as the model's own deformed synthetic lungs have).
    s = icosphere(3, 60.0)
    v = s.vertices.copy()
    fan = np.unique(s.faces[(s.faces == 100).any(axis=1)])
    v[100] += 2.0 * (v[fan[fan != 100][0]] - v[100])
    assert self_intersections(v, s.faces, local_rings=0)[0] > 0
    assert self_intersections(v, s.faces)[0] == 0


def test_crossing_found_in_every_grid_cell_layout():
    # Two separate triangles, one piercing the other: found once, wherever the grid puts them.
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [2, 2, -5], [3, 2, 5], [2, 3, 5]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    for shift in (0.0, 0.37, 1e3):
        count, pairs = self_intersections(v + shift, f)
        assert count == 1 and pairs.tolist() == [[0, 1]]
    # moved apart along x, the same two triangles no longer cross
    far = v.copy()
    far[3:, 0] += 20
    assert self_intersections(far, f)[0] == 0


def test_a_full_resolution_lung_sized_mesh_has_no_false_crossings():
    # 327 680 faces (a full-resolution marching-cubes lung has 300-450k) of a sphere, which cannot
    # self-intersect: at this size the grid's cells are small against the faces' neighbourhoods, so
    # every adjacent pair (shared edge or vertex) must be recognised as a neighbour, not a crossing.
    # Its speed is not asserted here (timed tests flake on shared machines).
    s = icosphere(7, 150.0)
    assert self_intersections(s.vertices, s.faces)[0] == 0
