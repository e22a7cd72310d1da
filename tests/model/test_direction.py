"""Displacement directions (15)–(17): the formula by hand, unit length, the paper's values at the
corners of the lung's box."""

import numpy as np
import pytest

from lungdeform.constants import table_constants
from lungdeform.errors import InputError
from lungdeform.geometry.frame import lung_frame
from lungdeform.model.direction import direction_field_frame, directions


def _box(side):
    """The eight corners of a 100 × 200 × 300 mm box (LPS) on the patient's ``side``, and its frame."""
    x0 = 20.0 if side == "left" else -120.0
    corners = np.array([[x, y, z] for x in (x0, x0 + 100.0) for y in (0.0, 200.0) for z in (-300.0, 0.0)])
    return corners, lung_frame(corners, side)


def test_direction_field_frame_by_hand():
    # Truth: (15)–(17) d = (c1·x̂^c2, c3·ŷ^c4, c5·ẑ^c6), by hand with Table I (left: c1…c6 =
    # 0.09, 0.23, 0.4, 0.5, 0.1, 2.3); ŷ^0.5 at 0.25 is 0.5, ẑ^2.3 at 1 is 1.
    c = table_constants("left")
    q = np.array([[1.0, 1.0, 1.0], [0.5, 0.25, 1.0], [0.0, 0.0, 0.0]])
    d = direction_field_frame(q, c)
    assert d[0] == pytest.approx([0.09, 0.4, 0.1], abs=1e-15)
    assert d[1] == pytest.approx([0.09 * 0.5**0.23, 0.4 * 0.5, 0.1], abs=1e-15)
    assert np.array_equal(d[2], [0.0, 0.0, 0.0])
    # coordinates outside [0, 1] are clipped (module docstring): (2, −1, 0.5) reads as (1, 0, 0.5)
    out = direction_field_frame(np.array([[2.0, -1.0, 0.5]]), c)
    assert np.array_equal(out, direction_field_frame(np.array([[1.0, 0.0, 0.5]]), c))


@pytest.mark.parametrize("side", ["left", "right"])
def test_paper_values_at_the_box_corners(side):
    # Truth, by hand: the frame's origin corner is medial, posterior (largest y) and apical
    # (largest z); the opposite corner has x̂ = ŷ = ẑ = 1, so its direction is (c1, c3, c5) in the
    # frame, i.e. (±c1, −c3, −c5) in LPS (X lateral: +x left, −x right; Y = −y; Z = −z), normalised.
    # The origin corner has all three terms 0: a zero direction (it does not move).
    corners, fr = _box(side)
    c = table_constants(side)
    d = directions(fr, corners, c)
    lateral = 1.0 if side == "left" else -1.0
    far = np.array([lateral * c[0], -c[2], -c[4]]) / np.linalg.norm(c[[0, 2, 4]])
    medial_x = corners[:, 0].min() if side == "left" else corners[:, 0].max()
    lateral_x = corners[:, 0].max() if side == "left" else corners[:, 0].min()
    origin = np.flatnonzero((corners[:, 0] == medial_x) & (corners[:, 1] == 200.0) & (corners[:, 2] == 0.0))
    opposite = np.flatnonzero((corners[:, 0] == lateral_x) & (corners[:, 1] == 0.0) & (corners[:, 2] == -300.0))
    assert d[opposite[0]] == pytest.approx(far, abs=1e-15)
    assert np.array_equal(d[origin[0]], [0.0, 0.0, 0.0])


def test_directions_are_unit_length(rng):
    # Truth: directions() normalises every non-zero direction; random points inside the box miss
    # the origin corner (the only zero direction), so every one has length 1
    corners, fr = _box("right")
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pts = lo + (hi - lo) * rng.uniform(size=(200, 3))
    d = directions(fr, pts, rng.uniform(0.05, 2.0, 6))
    assert d.shape == (200, 3)
    assert np.linalg.norm(d, axis=1) == pytest.approx(np.ones(200), abs=1e-12)


def test_directions_point_lateral_anterior_inferior(left_lung, right_lung):
    # With positive c1, c3, c5 every direction has lateral, anterior (−y) and inferior (−z) parts.
    for lung in (left_lung, right_lung):
        fr = lung_frame(lung.vertices, lung.name)
        d = directions(fr, lung.vertices, table_constants(lung.name))
        n = np.linalg.norm(d, axis=1)
        assert np.allclose(n[n > 0], 1)
        lateral = 1 if lung.name == "left" else -1
        assert np.all(lateral * d[:, 0] >= 0)
        assert np.all(d[:, 1] <= 0) and np.all(d[:, 2] <= 0)


def test_direction_formula_by_hand(left_lung):
    fr = lung_frame(left_lung.vertices, "left")
    c = np.array([1.0, 1.0, 2.0, 1.0, 3.0, 1.0])
    q = fr.normalized(left_lung.vertices)
    d = directions(fr, left_lung.vertices, c)
    raw = np.stack([q[:, 0], -2 * q[:, 1], -3 * q[:, 2]], axis=1)  # lung axes X=+x, Y=−y, Z=−z
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    assert np.allclose(d, raw)


def test_too_few_constants_are_refused():
    # the message names what is missing
    with pytest.raises(InputError, match="c1…c6"):
        direction_field_frame(np.zeros((2, 3)), [1.0, 1.0, 1.0])
