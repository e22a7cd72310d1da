"""Lung frame (Sec. IV-B.1), sides and orientations (the force (18) and directions (15)–(17) that use
it are tested in tests/model/test_force.py and tests/model/test_direction.py)."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.frame import lung_frame


def test_frame_origin_is_apex_posterior_medial(left_lung, right_lung):
    # Paper Sec. IV-B.1: Z from the apex, Y from the posterior side, X from the heart (medial).
    for lung in (left_lung, right_lung):
        fr = lung_frame(lung.vertices, lung.name)
        q = fr.normalized(lung.vertices)
        assert np.allclose(q.min(axis=0), 0) and np.allclose(q.max(axis=0), 1)
        v = lung.vertices
        apex = np.argmax(v[:, 2])  # highest z (head) in LPS
        posterior = np.argmax(v[:, 1])  # largest y in LPS
        medial = np.argmin(np.abs(v[:, 0]))  # nearest the midline x = 0
        assert q[apex, 2] == pytest.approx(0)
        assert q[posterior, 1] == pytest.approx(0)
        assert q[medial, 0] == pytest.approx(0)


def test_bad_side_and_gravity():
    with pytest.raises(InputError, match="side"):
        lung_frame(np.eye(3), "middle")
    with pytest.raises(InputError, match="orientation"):
        from lungdeform.constants import gravity_vector

        gravity_vector("sideways")


def test_side_from_shape_reads_the_medial_face():
    # truth: the embedded lungs (segmented from CT, LPS) are the sides they are named; their mirror
    # images (x → −x, faces reversed to stay outward: a surface in RAS) read as the other side and
    # are refused for their names; a convex ellipsoid has no medial face and says nothing
    from lungdeform.data import default_lungs
    from lungdeform.geometry.frame import SIDE_SCORE_MIN, check_side, side_from_shape
    from tests.conftest import ellipsoid_lung

    for name, s in default_lungs().items():
        side, score = side_from_shape(s.vertices, s.faces)
        assert side == name and abs(score) > 2 * SIDE_SCORE_MIN
        check_side(s.vertices, s.faces, name, "lung.ply")
        mirrored = s.vertices * np.array([-1.0, 1.0, 1.0])
        flipped = s.faces[:, ::-1]
        assert side_from_shape(mirrored, flipped)[0] != name
        with pytest.raises(InputError, match=r"mirror\.ply: the lung's shape says"):
            check_side(mirrored, flipped, name, "mirror.ply")
        # the shape, not the position: moved 300 mm across (where the other lung would be), the
        # lung still reads as itself
        across = s.vertices + np.array([300.0 if name == "right" else -300.0, 0.0, 0.0])
        assert side_from_shape(across, s.faces) == pytest.approx(side_from_shape(s.vertices, s.faces))
    e = ellipsoid_lung("left")
    assert abs(side_from_shape(e.vertices, e.faces)[1]) < SIDE_SCORE_MIN
    with pytest.raises(InputError, match="no convex hull"):
        side_from_shape(np.c_[np.random.default_rng(0).normal(size=(20, 2)), np.zeros(20)], np.zeros((0, 3), int))
    check_side(e.vertices, e.faces, "right", "ellipsoid.stl")  # unclear: passes


def test_side_from_shape_on_real_lobe_maps(data_dir):
    # real data: both lungs of a CT lobe map (Coronacases 002, full resolution; its right lung has
    # the weakest score measured, +0.053) read as the sides the lobe labels say
    from lungdeform.evaluate.inputs import read_input
    from lungdeform.geometry.frame import SIDE_SCORE_MIN, side_from_shape
    from tests.conftest import require_path

    path = require_path(data_dir, "coronacases-lung-lobes", "Coronacases_002_lobes.nii.gz")
    for side in ("left", "right"):
        s = read_input(path, side)[0]
        got, score = side_from_shape(s.vertices, s.faces)
        assert got == side and abs(score) > SIDE_SCORE_MIN


def test_resolve_sides_refuses_swapped_sides_by_parameter_name():
    # in LPS the left lung lies at larger x: given sides the other way round are refused (truth: the
    # centroids), and a wrong count names the parameter, not a command-line flag
    from types import SimpleNamespace

    from lungdeform.errors import InputError
    from lungdeform.geometry.frame import resolve_sides

    a = SimpleNamespace(name="a", vertices=np.array([[100.0, 0, 0], [120, 0, 0]]), faces=None)
    b = SimpleNamespace(name="b", vertices=np.array([[-100.0, 0, 0], [-120, 0, 0]]), faces=None)
    assert resolve_sides([a, b], ["left", "right"], check=False) == ["left", "right"]
    assert resolve_sides([a, b], None, check=False) == ["left", "right"]  # from position
    with pytest.raises(InputError, match="lies to the patient's right"):
        resolve_sides([a, b], ["right", "left"], check=False)
    with pytest.raises(InputError, match="^sides: 1 given for 2 surfaces"):
        resolve_sides([a, b], ["left"], check=False)


def test_hull_depth_equals_the_dense_plane_distances():
    # dense reference: every point's signed distance to every facet plane of its hull (the (n, f)
    # matrix), the depth being minus the largest, floored at 0; checked on a cube, whose depths are
    # known: a point at (x, y, z) inside [0, 10]^3 lies min(x, 10 - x, y, ...) mm deep
    from scipy.spatial import ConvexHull

    from lungdeform.geometry.frame import _hull_depth

    rng = np.random.default_rng(9)
    corners = np.array([[i, j, k] for i in (0.0, 10.0) for j in (0.0, 10.0) for k in (0.0, 10.0)])
    inside = rng.uniform(0.0, 10.0, size=(200, 3))
    eq = ConvexHull(np.vstack([corners, inside])).equations
    dense = np.maximum(-(inside @ eq[:, :3].T + eq[:, 3]).max(axis=1), 0.0)
    got = _hull_depth(inside, np.ascontiguousarray(eq.T))
    np.testing.assert_allclose(got, dense, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got, np.minimum(inside, 10.0 - inside).min(axis=1), atol=1e-9)
    assert _hull_depth(corners, np.ascontiguousarray(eq.T)).max() < 1e-9  # on the hull: depth 0
