"""Surface checks against analytic shapes and deliberately broken meshes."""

import numpy as np
import pytest

from lungdeform.errors import InputError, MeshError, UnitsError
from lungdeform.geometry.mesh import (
    Surface,
    check_surface,
    distinct,
    icosphere,
    non_manifold_vertices,
    signed_volume,
    subdivide,
    surface_area,
)


def test_sphere_volume_and_area_converge_to_analytic():
    # A geodesic sphere is inscribed: its volume and area approach 4/3·π·r³ and 4·π·r² from below.
    r = 100.0
    errors = []
    for k in (2, 3, 4):
        s = icosphere(k, r)
        vol_err = 1 - s.volume / (4 / 3 * np.pi * r**3)
        area_err = 1 - s.area / (4 * np.pi * r**2)
        assert 0 < vol_err < 0.05 and 0 < area_err < 0.05
        errors.append(vol_err)
    assert errors[0] > errors[1] > errors[2]  # refinement converges
    assert errors[-1] < 0.003


def test_volume_is_translation_invariant_far_from_origin():
    # The divergence-theorem volume must not depend on where the lung sits in LPS space.
    s = icosphere(3, 50.0)
    far = s.vertices + np.array([1e5, -2e5, 3e5])
    assert signed_volume(far, s.faces) == pytest.approx(s.volume, rel=1e-9)


def test_transforms_return_new_surfaces():
    s = icosphere(2, 10.0)
    big = s.scaled(2.0)
    assert big.volume == pytest.approx(8 * s.volume, rel=1e-12)
    assert s.volume == pytest.approx(icosphere(2, 10.0).volume)  # original untouched
    mirrored = s.transformed(np.diag([-1.0, 1.0, 1.0, 1.0]))
    assert mirrored.volume == pytest.approx(s.volume, rel=1e-12)  # orientation kept on reflection
    moved = s.deformed(np.ones_like(s.vertices))
    assert np.allclose(moved.vertices - s.vertices, 1.0)
    with pytest.raises(ValueError):
        s.vertices[0, 0] = 1.0  # arrays are read-only


def test_subdivide_keeps_shape_and_quadruples_faces():
    s = icosphere(2, 80.0)
    v, f = subdivide(s.vertices, s.faces)
    assert len(f) == 4 * len(s.faces)
    assert signed_volume(v, f) == pytest.approx(s.volume, rel=1e-12)  # midpoints lie on the flat faces
    assert surface_area(v, f) == pytest.approx(s.area, rel=1e-12)


def test_check_accepts_a_closed_outward_sphere():
    s = icosphere(3, 100.0)
    v, f, report = check_surface(s.vertices, s.faces)
    assert report.repairs == ()
    assert report.volume_ml == pytest.approx(s.volume / 1000)


def test_check_refuses_open_surface():
    s = icosphere(2, 100.0)
    with pytest.raises(MeshError, match="open"):
        check_surface(s.vertices, s.faces[1:], source="lung.stl")


def test_check_refuses_nan():
    s = icosphere(2, 100.0)
    v = s.vertices.copy()
    v[3] = np.nan
    with pytest.raises(MeshError, match="lung.stl: .*NaN"):
        check_surface(v, s.faces, source="lung.stl")


def test_check_refuses_metres_and_suggests_units():
    s = icosphere(2, 0.1)
    with pytest.raises(UnitsError, match="--units"):
        check_surface(s.vertices, s.faces)


def test_inward_orientation_refused_or_repaired():
    s = icosphere(2, 100.0)
    inward = s.faces[:, ::-1]
    with pytest.raises(MeshError, match="inward"):
        check_surface(s.vertices, inward)
    v, f, report = check_surface(s.vertices, inward, repair=True)
    assert signed_volume(v, f) > 0
    assert any("flipped" in r for r in report.repairs)


def test_inconsistent_winding_repaired(rng):
    s = icosphere(2, 100.0)
    f = s.faces.copy()
    flip = rng.choice(len(f), 10, replace=False)
    f[flip] = f[flip, ::-1]
    with pytest.raises(MeshError, match="consistently"):
        check_surface(s.vertices, f)
    v, f2, report = check_surface(s.vertices, f, repair=True)
    assert signed_volume(v, f2) == pytest.approx(s.volume, rel=1e-12)


def test_two_components_refused_or_largest_kept():
    a = icosphere(2, 100.0)
    b = icosphere(1, 20.0, center=(500.0, 0, 0))
    v = np.vstack([a.vertices, b.vertices])
    f = np.vstack([a.faces, b.faces + len(a.vertices)])
    with pytest.raises(MeshError, match="2 separate components"):
        check_surface(v, f)
    v2, f2, report = check_surface(v, f, repair=True)
    assert len(f2) == len(a.faces)


def test_pinched_vertex_is_not_manifold():
    # Two tetrahedra sharing one vertex: every edge has two faces, but the shared vertex's fan is
    # two discs, so the surface is not a 2-manifold.
    t = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100]], float)
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v = np.vstack([t, -t[1:]])
    f2 = tf.copy()
    f2 = np.where(f2 == 0, 0, f2 + 3)
    f = np.vstack([tf, f2[:, ::-1]])
    assert list(non_manifold_vertices(f, len(v))) == [0]
    with pytest.raises(MeshError, match="manifold"):
        check_surface(v, f)


def test_bad_shapes_are_input_errors():
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        Surface(np.zeros((4, 2)), np.zeros((1, 3), int))
    with pytest.raises(InputError, match="outside"):
        Surface(np.zeros((3, 3)), np.array([[0, 1, 5]]))


def test_winding_numbers_of_a_sphere(rng):
    # analytic: 1 inside a closed outward surface, 0 outside (points kept 1 mm off the faceted
    # sphere of radius 50, whose facets lie within 0.3 mm of it), -1 inside a reversed surface
    from lungdeform.geometry.mesh import winding_numbers

    s = icosphere(3, 50.0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.concatenate([rng.uniform(0, 48.5, 100), rng.uniform(51, 200, 100)])
    w = winding_numbers(d * r[:, None], s.vertices, s.faces)
    assert w[:100] == pytest.approx(np.ones(100), abs=1e-9)
    assert w[100:] == pytest.approx(np.zeros(100), abs=1e-9)
    assert winding_numbers(np.zeros((1, 3)), s.vertices, s.faces[:, ::-1])[0] == pytest.approx(-1.0)


def test_thinned_is_all_or_a_seeded_sorted_subset():
    # invariants: every index when few enough; otherwise `count` distinct indices, sorted, the same
    # for the same seed (the interior fields rely on playback and fitting picking the same points)
    from lungdeform.geometry.mesh import thinned

    assert thinned(5, 10).tolist() == [0, 1, 2, 3, 4]
    a = thinned(1000, 40, seed=3)
    assert len(a) == len(set(a.tolist())) == 40 and np.all(np.diff(a) > 0) and a.max() < 1000
    assert np.array_equal(a, thinned(1000, 40, seed=3)) and not np.array_equal(a, thinned(1000, 40, seed=4))


def test_check_refuses_non_physical_coordinates_first():
    # One vertex at 1e30 mm (100 m is beyond any lung in a scanner frame) is named, before its
    # neighbouring faces would be called degenerate; repair does not get to hide it.
    s = icosphere(3, 60.0)
    v = s.vertices.copy()
    v[5] = [1e30, 0.0, 0.0]
    for repair in (False, True):
        with pytest.raises(MeshError, match=r"lung.ply: vertex 5 has coordinate 1e\+30 mm, beyond"):
            check_surface(v, s.faces, source="lung.ply", repair=repair)


def test_check_refuses_self_intersection_before_orientation():
    # The cap z > 40 reflected through z = -30 passes through the lower wall: the signed volume
    # is negative but "faces point inward" would be wrong, and flipping them (repair) builds nonsense.
    s = icosphere(3, 60.0)
    v = s.vertices.copy()
    cap = v[:, 2] > 40
    v[cap, 2] = -60.0 - v[cap, 2]
    assert signed_volume(v, s.faces) < 0
    for repair in (False, True):
        with pytest.raises(MeshError, match=r"lung.ply: surface intersects itself \(\d+ pairs .*faces \d+ and \d+"):
            check_surface(v, s.faces, source="lung.ply", repair=repair)


def test_farthest_points_even_deterministic_and_equivariant():
    # truth: points on a 100 x 100 mm square, 90 % of them crowded in its left half: a farthest-point
    # subset takes about as many from each half (a random one: 90 % from the left); the subset of a
    # scaled, moved copy is the same indices (similarity-equivariant); all points when n <= count
    from lungdeform.geometry.mesh import farthest_points

    rng = np.random.default_rng(4)
    pts = np.vstack([rng.uniform([0, 0, 0], [50, 100, 0], (9000, 3)), rng.uniform([50, 0, 0], [100, 100, 0], (1000, 3))])
    idx = farthest_points(pts, 400)
    assert len(idx) == 400 and np.all(np.diff(idx) > 0)
    assert 0.4 < np.mean(pts[idx, 0] < 50.0) < 0.6
    np.testing.assert_array_equal(farthest_points(pts * 1.3 + [5.0, -7.0, 2.0], 400), idx)
    # the subset is spread: every point lies within the subset's covering radius, which is small
    from scipy.spatial import cKDTree
    assert cKDTree(pts[idx]).query(pts)[0].max() < 6.0
    np.testing.assert_array_equal(farthest_points(pts[:50], 400), np.arange(50))
    with pytest.raises(InputError, match="count"):
        farthest_points(pts, 0)



@pytest.mark.parametrize("grid", [False, True])
def test_farthest_points_equal_the_dense_greedy_reference(grid):
    # dense reference: the greedy rule written with NumPy (the full distance matrix, np.argmax's first
    # maximum); the pruned kernel picks the same points in the same order, ties included (a regular
    # grid has many equal distances)
    from lungdeform.geometry.mesh import _farthest_kernel

    rng = np.random.default_rng(6)
    pts = (np.stack(np.meshgrid(*[np.arange(8.0)] * 3), -1).reshape(-1, 3) if grid
           else rng.normal(size=(700, 3)) * [40.0, 30.0, 60.0])
    dist = np.sum((pts[:, None] - pts[None]) ** 2, axis=2)
    start = int(np.argmax(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1)))
    ref, nearest = [start], dist[start].copy()
    for _ in range(149):
        ref.append(int(np.argmax(nearest)))
        nearest = np.minimum(nearest, dist[ref[-1]])
    for cells in (1, 4, 16):  # one cell: no pruning; more: pruned to the cells within reach
        np.testing.assert_array_equal(_farthest_kernel(pts, 150, start, cells), ref)

def test_inside_by_parity_is_the_winding_number_test_and_the_sphere():
    # why: for a closed surface and points off it, the parity of a ray's crossings and the winding
    # number > 0.5 are the same inside test; on a sphere both are |p − c| < r (up to the mesh's
    # chordal sag, so points within 0.3 mm of the sphere are left out of that comparison)
    from lungdeform.geometry.mesh import icosphere, inside_by_parity, winding_numbers
    rng = np.random.default_rng(11)
    s = icosphere(4, 20.0, center=(5.0, -3.0, 40.0))
    q = rng.uniform(-20.0, 30.0, size=(3000, 3)) + [0.0, -8.0, 35.0]
    inside = inside_by_parity(q, s.vertices, s.faces)
    assert np.array_equal(inside, winding_numbers(q, s.vertices, s.faces) > 0.5)
    r = np.linalg.norm(q - [5.0, -3.0, 40.0], axis=1)
    clear = np.abs(r - 20.0) > 0.3
    assert np.array_equal(inside[clear], r[clear] < 20.0) and 0 < inside.sum() < len(q)


def test_binned_parity_counts_every_triangle_whose_box_holds_the_point():
    # reference: the same kernel with every triangle in one cell (the unbinned loop over all
    # triangles); binned in its (y, z) cell, a point must get the same answer, also on vertices and
    # on cell borders (the bins' own coordinates), and beyond the surface's (y, z) extent
    from lungdeform.geometry.mesh import _parity_kernel, _yz_bins, icosphere, inside_by_parity
    rng = np.random.default_rng(12)
    s = icosphere(3, 15.0, center=(1.0, 2.0, -3.0))
    q = rng.uniform(-25.0, 25.0, size=(4000, 3))
    q[:40] = s.vertices[:40]
    tri = np.ascontiguousarray(s.vertices[s.faces])
    boxes = np.ascontiguousarray(np.stack([tri[:, :, 1].min(axis=1), tri[:, :, 1].max(axis=1),
                                           tri[:, :, 2].min(axis=1), tri[:, :, 2].max(axis=1)], axis=1))
    ptr, members, grid = _yz_bins(boxes, 18)
    q[40:80, 1] = grid[0] + grid[2] * rng.integers(0, 19, 40)  # on the cells' borders in y
    q[80:120, 2] = grid[1] + grid[3] * rng.integers(0, 19, 40)
    ref = _parity_kernel(q, tri, boxes, _yz_bins(boxes, 1))
    assert np.array_equal(_parity_kernel(q, tri, boxes, (ptr, members, grid)), ref)
    assert np.array_equal(inside_by_parity(q, s.vertices, s.faces), ref) and 0 < ref.sum() < len(q)
    assert len(members) > len(s.faces)  # boxes across cell borders are binned in every cell they meet


def test_inside_nodes_is_the_parity_test_on_a_grid():
    # why: the row-parity voxelisation (one pass over the triangles) must answer exactly as the
    # per-point parity test at every node of a grid, here an oblique sphere in node units
    from lungdeform.geometry.mesh import icosphere, inside_by_parity, inside_nodes
    s = icosphere(3, 7.3, center=(10.2, 8.7, 6.1))
    dims = (21, 18, 14)  # (nx, ny, nz): the sphere crosses the grid's last faces
    inside = inside_nodes(s.vertices, s.faces, dims)
    assert inside.shape == (14, 18, 21)
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    nodes = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(float) + [0.0, 1e-5 * np.pi, 1e-5 * np.e]
    assert np.array_equal(inside.ravel(), inside_by_parity(nodes, s.vertices, s.faces))
    assert 0 < inside.sum() < inside.size


def test_distinct_is_numpys_unique(rng):
    # reference: np.unique (sorted distinct values), on large keys with repeats, small ints, one value, none
    for values in (rng.integers(0, 2**40, 5000).repeat(2), rng.integers(-3, 4, (20, 3)), np.array([7]),
                   np.zeros(0, np.int64)):
        assert np.array_equal(distinct(values), np.unique(values))
