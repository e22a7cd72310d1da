"""Exact surface distances: analytic spheres, a brute-force reference, and the vertex pitfall."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.distance import (
    DistanceStack,
    SurfaceDistance,
    _closest_on_triangle,
    _edges_and_box,
    _face_bound,
    distance_stats,
    point_to_surface,
    symmetric_distance,
    vertex_areas,
    weighted_percentile,
)
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.geometry.remesh import decimate
from lungdeform.io.image import read_image
from lungdeform.io.mask import extract_surface
from tests.conftest import require_path


def _brute(points, v, f):
    # dense reference: the same exact triangle routine over every face (tests the grid culling)
    out = []
    for p in points:
        best = np.inf
        for tri in f:
            q = np.array(_closest_on_triangle(tuple(p), *(tuple(v[k]) for k in tri)))
            best = min(best, float(np.linalg.norm(p - q)))
        out.append(best)
    return np.array(out)


def _raster_rank(v, f):
    # the order in which the raster-scan kernel (before the shell search) met the faces: by the cell of
    # their box centre in a grid of side twice the median edge over the used vertices' box, then by index
    used = np.unique(f)
    lo = v[used].min(axis=0) - 1e-6
    span = v[used].max(axis=0) + 1e-6 - lo
    e = v[f]
    h = max(2.0 * float(np.median(np.linalg.norm(e - np.roll(e, 1, axis=1), axis=2))), 1e-6,
            float(np.prod(span) / SurfaceDistance.MAX_CELLS) ** (1 / 3))
    dims = np.maximum(np.ceil(span / h).astype(np.int64), 1)
    idx = np.clip(((e.min(axis=1) + e.max(axis=1)) / 2 - lo) / h, 0, dims - 1).astype(np.int64)
    rank = np.empty(len(f), np.int64)
    rank[np.argsort((idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2], kind="stable")] = np.arange(len(f))
    return rank


def _dense_faces(points, v, f):
    # dense reference with the raster scan's tie rule: every face's exact distance (the kernel's own
    # per-face routine), the nearest; among equally near faces the one the raster scan met last
    n, m = len(points), len(f)
    d = _face_bound(np.repeat(points, m, axis=0), v, f, np.tile(np.arange(m), n)).reshape(n, m)
    rank = _raster_rank(v, f)
    best = d.min(axis=1)
    face = np.array([c[np.argmax(rank[c])] for c in (np.flatnonzero(row == b) for row, b in zip(d, best))])
    return best, face


def _tie_points(v, f, rng):
    # points with many exact ties: on the vertices (distance 0 to every face around them), off them
    # along the axes, above edge midpoints, and a random cloud near and far
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    at = v[np.unique(f)]
    mid = (v[f[:, 0]] + v[f[:, 1]]) / 2
    return np.vstack([at[:60], at[60:120] + [0.0, 0.0, 2.5], mid[:60] + 1.5 * normal[:60] / np.linalg.norm(
        normal[:60], axis=1, keepdims=True), at[:40] + rng.normal(size=(40, 3)) * 8, rng.normal(size=(20, 3)) * 300])


def test_ties_resolve_as_the_raster_scan(rng):
    # a flat triangulated sheet (every point above a vertex is exactly as near to its six faces) and a
    # sphere: the face returned is the dense reference's under the raster scan's tie rule (the face it
    # chose is what the fit builds on: another choice moved copd1's fitted surface by 0.02 mm)
    g = np.stack(np.meshgrid(np.arange(12.0), np.arange(9.0), indexing="ij"), axis=-1).reshape(-1, 2) * 4.0
    sheet = np.column_stack([g, np.zeros(len(g))])
    q = np.arange(12 * 9).reshape(12, 9)[:-1, :-1].ravel()
    faces = np.vstack([np.column_stack([q, q + 9, q + 1]), np.column_stack([q + 1, q + 9, q + 10])])
    sphere = icosphere(3, 30.0)
    for v, f in ((sheet, faces), (sphere.vertices, sphere.faces)):
        pts = _tie_points(v, f, rng)
        d, _, face = SurfaceDistance(v, f).query(pts)
        best, ref = _dense_faces(pts, v, f)
        assert d == pytest.approx(best, abs=1e-9)
        np.testing.assert_array_equal(face, ref)


def test_real_lung_matches_dense_reference_and_its_ties(data_dir, rng):
    # a real decimated lung (long slivers binned in every cell they meet, the rest once): distances
    # and faces, ties included, equal the dense reference's, with no bound, a loose one and a tight one
    image = read_image(require_path(data_dir, "itk-right-lung-two-volumes", "CT_3D_lung_fixed_mask.mha"))
    v, f, _ = decimate(*(lambda s: (s.vertices, s.faces))(extract_surface(image).surface), 3000)
    pts = _tie_points(v, f, rng)
    best, ref = _dense_faces(pts, v, f)
    sd = SurfaceDistance(v, f)
    for bound in (None, best * 3.0 + 2.0, best):
        d, closest, face = sd.query(pts, bound)
        assert d == pytest.approx(best, abs=1e-9)
        np.testing.assert_array_equal(face, ref)
        assert np.linalg.norm(closest - pts, axis=1) == pytest.approx(d, abs=1e-9)


def test_single_triangle_regions():
    # analytic: above the interior → height; beyond a vertex → distance to it; beyond an edge → to the line
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    f = np.array([[0, 1, 2]])
    pts = np.array([[2.0, 2, 5], [-3, -4, 0], [5, -2, 1], [6, 6, 0]])
    expected = [5.0, 5.0, np.hypot(2, 1), np.hypot(1, 1) * np.sqrt(2) * np.sqrt(2) / np.sqrt(2)]
    d = point_to_surface(pts, v, f)
    assert d[:3] == pytest.approx(expected[:3], abs=1e-12)
    assert d[3] == pytest.approx(abs(6 + 6 - 10) / np.sqrt(2), abs=1e-12)


def test_degenerate_triangles(rng):
    # a predicted surface can collapse faces (two or three corners coincide): the distance is then
    # to the remaining segment or point, analytic, and never a division by zero
    seg = np.array([[0.0, 0, 0], [0, 0, 0], [10, 0, 0]])  # a == b: the segment a–c
    pts = np.array([[5.0, 3, 4], [-3, 0, 4], [13, 4, 0]])
    for order in ([0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1]):
        assert point_to_surface(pts, seg, np.array([order])) == pytest.approx([5.0, 5.0, 5.0], abs=1e-12)
    dot = np.zeros((3, 3))  # all three corners at the origin
    q = rng.normal(size=(5, 3))
    assert point_to_surface(q, dot, np.array([[0, 1, 2]])) == pytest.approx(np.linalg.norm(q, axis=1), abs=1e-12)


def test_matches_brute_force(rng):
    s = icosphere(2, 30.0)
    pts = rng.normal(size=(60, 3)) * 25
    d = SurfaceDistance(s.vertices, s.faces).distance(pts)
    assert d == pytest.approx(_brute(pts, s.vertices, s.faces), abs=1e-9)


def test_long_triangles_match_brute_force(rng):
    # triangles binned once by their box centres: slivers reaching far beyond their cell (the grid's
    # overhang) must still be found, near and far; the face returned holds the closest point
    s = icosphere(2, 30.0)
    v = s.vertices * rng.uniform(0.8, 1.2, size=(len(s.vertices), 1))
    slivers = np.array([[-60.0, 0, 0], [60, 0.5, 0], [0, 0, 0.4], [0, -70, 5], [0.3, 70, 5], [0, 0, 45]])
    vv = np.vstack([v, slivers])
    ff = np.vstack([s.faces, len(v) + np.array([[0, 1, 2], [3, 4, 5]])])
    pts = np.vstack([rng.normal(size=(50, 3)) * 20, rng.normal(size=(50, 3)) * 80])
    d, closest, face = SurfaceDistance(vv, ff).query(pts)
    assert d == pytest.approx(_brute(pts, vv, ff), abs=1e-9)
    on_face = [np.linalg.norm(np.array(_closest_on_triangle(tuple(p), *(tuple(vv[k]) for k in ff[i]))) - p)
               for p, i in zip(pts, face)]
    assert np.linalg.norm(closest - pts, axis=1) == pytest.approx(d, abs=1e-9)
    assert on_face == pytest.approx(d, abs=1e-9)


def test_caller_bound_is_exact_either_way(rng):
    # a bound is only where the search starts: a loose one, one too small (nothing within it: searched
    # again from the nearest vertex), and a missing one (NaN, inf, negative) all give the dense reference
    s = icosphere(2, 30.0)
    pts = rng.normal(size=(40, 3)) * 30
    sd = SurfaceDistance(s.vertices, s.faces)
    exact = _brute(pts, s.vertices, s.faces)
    for bound in (exact * 1.5 + 1.0, exact * 0.2, np.full(len(pts), np.nan), np.full(len(pts), np.inf),
                  np.where(np.arange(len(pts)) % 2 == 0, -1.0, exact + 3.0)):
        d, closest, face = sd.query(pts, bound)
        assert d == pytest.approx(exact, abs=1e-9)
        assert np.all(face >= 0)
    with pytest.raises(InputError, match="bound"):
        sd.query(pts, exact[:-1])


def test_face_distance_bounds_give_the_same_exact_distances(rng):
    # dense reference: a face's distance only bounds the search (any face's distance is an upper
    # bound), so the distances equal the brute force's whatever the faces: the right ones, random
    # ones, none (-1: infinity, searched from the nearest vertex)
    s = icosphere(2, 30.0)
    pts = rng.normal(size=(60, 3)) * 25
    sd = SurfaceDistance(s.vertices, s.faces)
    truth = _brute(pts, s.vertices, s.faces)
    _, _, faces = sd.query(pts)
    moved = SurfaceDistance(s.vertices * 1.05, s.faces)  # the same faces, the vertices moved
    for hint in (faces, rng.integers(-1, len(s.faces), len(pts))):
        d, closest, face = sd.query(pts, sd.face_distance(pts, hint))
        assert d == pytest.approx(truth, abs=1e-9)
        assert np.linalg.norm(pts - closest, axis=1) == pytest.approx(truth, abs=1e-9)
        assert moved.query(pts, moved.face_distance(pts, hint))[0] == pytest.approx(_brute(pts, s.vertices * 1.05, s.faces), abs=1e-9)
    with pytest.raises(InputError, match="faces must be"):
        sd.face_distance(pts, np.full(len(pts), len(s.faces)))
    with pytest.raises(InputError, match="faces must be"):
        sd.face_distance(pts, faces[:-1])


def test_edges_and_box_equal_numpys_bit_for_bit(rng):
    # reference: the numpy the grid was sized with before (norm of e − roll(e), min/max over the used
    # vertices); equal to the last bit, so the cell side, the grid and the tie ranks are unchanged.
    # Moved, scaled and sheared spheres, and a surface that leaves vertices unused (they must not count)
    s = icosphere(3, 30.0)
    extra = rng.normal(size=(5, 3)) * 500.0  # unused, far outside the box
    for k in range(20):
        v = s.vertices @ (np.eye(3) + 0.3 * rng.normal(size=(3, 3))) + rng.normal(size=3) * 50
        v = np.vstack([v, extra]) if k % 2 else v
        e = v[s.faces]
        edge, lo, hi = _edges_and_box(v, s.faces)
        assert np.array_equal(edge, np.linalg.norm(e - np.roll(e, 1, axis=1), axis=2).ravel())
        used = np.unique(s.faces)
        assert np.array_equal(lo, v[used].min(axis=0)) and np.array_equal(hi, v[used].max(axis=0))


def test_restricted_equals_measuring_with_the_masks(rng):
    # reference: symmetric_distance measured with the masks; restricting the unmasked measurement
    # gives the same distances, weights and indices exactly (each distance is its own point's query)
    a, b = icosphere(2, 30.0), icosphere(3, 33.0)
    b = Surface(b.vertices + rng.normal(size=3), b.faces)
    ka, kb = rng.random(a.n_vertices) < 0.7, rng.random(b.n_vertices) < 0.6
    full = symmetric_distance(a, b)
    direct, cut = symmetric_distance(a, b, keep_a=ka, keep_b=kb), full.restricted(ka, kb)
    for name in ("a_to_b", "b_to_a", "a_weights", "b_weights", "a_index", "b_index"):
        assert np.array_equal(getattr(direct, name), getattr(cut, name)), name
    assert cut.stats == direct.stats
    assert full.restricted().stats == full.stats
    twice = direct.restricted(np.ones(a.n_vertices, bool), kb & (rng.random(b.n_vertices) < 0.5))
    assert len(twice.b_to_a) < len(direct.b_to_a) and np.array_equal(twice.a_to_b, direct.a_to_b)
    with pytest.raises(InputError, match="keep_a"):
        full.restricted(ka[:-1], kb)


def test_stack_equals_each_surfaces_own_query_to_the_bit(rng):
    # reference: each surface's own query (itself checked against the dense reference above). One
    # kernel call over several surfaces gives the same distances, closest points and faces exactly,
    # with and without the faces of an earlier query as bounds, for points near and far (far from a
    # surface with no bound: searched again from its nearest vertex), in any order, a surface twice
    surfaces = [icosphere(3, 30.0), icosphere(2, 20.0), Surface(icosphere(3, 40.0).vertices * [1.0, 0.8, 1.2],
                                                                 icosphere(3).faces)]
    sds = [SurfaceDistance(x.vertices, x.faces) for x in surfaces]
    stack = DistanceStack(sds)
    which = [2, 0, 1, 0]
    pts = [rng.normal(size=(k, 3)) * sc for k, sc in ((50, 35.0), (40, 25.0), (30, 200.0), (0, 1.0))]
    got = stack.query(which, pts)
    hints = [rng.integers(-1, len(sds[w].faces), len(p)) for w, p in zip(which, pts)]
    hinted = stack.query(which, [p * 1.01 for p in pts], hints)
    for w, p, h, a, b in zip(which, pts, hints, got, hinted):
        for x, y in zip(a, sds[w].query(p)):
            assert np.array_equal(x, y)
        bound = sds[w].face_distance(p * 1.01, h)
        for x, y in zip(b, sds[w].query(p * 1.01, bound)):
            assert np.array_equal(x, y)
    assert stack.query([], []) == []
    with pytest.raises(InputError, match="faces must be"):
        stack.query([1], [pts[0]], [np.full(len(pts[0]), len(sds[1].faces))])
    with pytest.raises(InputError, match="one per query"):
        stack.query([3], [pts[0]])
    with pytest.raises(InputError, match="NaN"):
        stack.query([0], [np.full((2, 3), np.nan)])


def test_concentric_spheres_radius_difference():
    # outer sphere vertices to the inner sphere: the radius difference, up to the inner mesh's
    # faceting (sagitta of an edge ≈ e²/8r ≈ 0.03 mm here)
    inner, outer = icosphere(4, 40.0), icosphere(4, 50.0)
    d = SurfaceDistance(inner.vertices, inner.faces).distance(outer.vertices)
    assert d.min() >= 10.0 - 1e-9
    assert d.max() == pytest.approx(10.0, abs=0.05)
    sym = symmetric_distance(inner, outer).stats
    assert sym.mean == pytest.approx(10.0, abs=0.05)
    assert sym.p95 == pytest.approx(10.0, abs=0.05)


def test_not_nearest_vertex():
    # a face centre lies on the surface: distance 0, while its nearest vertex is far away
    s = icosphere(0, 100.0)
    c = s.vertices[s.faces[0]].mean(axis=0)
    d = point_to_surface(c[None], s.vertices, s.faces)[0]
    assert d == pytest.approx(0.0, abs=1e-9)
    assert np.linalg.norm(s.vertices - c, axis=1).min() > 30.0


def test_stats_weighted():
    st = distance_stats(np.array([1.0, 3.0]), np.array([3.0, 1.0]))
    assert st.mean == pytest.approx(1.5)
    assert st.rms == pytest.approx(np.sqrt((3 * 1 + 9) / 4))
    assert weighted_percentile(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 8.0]), 50) == 3.0
    with pytest.raises(InputError):
        distance_stats(np.zeros(0))


def test_vertex_areas_sum_to_area():
    s = icosphere(3, 10.0)
    assert vertex_areas(s.vertices, s.faces).sum() == pytest.approx(s.area)
