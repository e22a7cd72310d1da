"""The applied force (18) and its four-field orientation basis: Table I by hand, the supine case,
the height against gravity."""

import numpy as np
import pytest

from lungdeform.constants import GRAVITY, table_constants
from lungdeform.geometry.frame import lung_frame
from lungdeform.model.force import FIELDS, applied_force, field_basis, force_weights, height_weights


def test_equation_18_by_hand_with_table_i():
    # Truth: (18) f = c7·x̂ + c8·ŷ + c9·ẑ with Table I, computed by hand. Left: c7, c8, c9 =
    # 0.01, 0.95, 0.07; right: 0.01, 0.96, 0.05.
    q = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.5],
                  [0.2, 0.4, 0.6]])
    left = [0.0, 0.01, 0.95, 0.07, 0.5 * (0.01 + 0.95 + 0.07), 0.01 * 0.2 + 0.95 * 0.4 + 0.07 * 0.6]
    right = [0.0, 0.01, 0.96, 0.05, 0.5 * (0.01 + 0.96 + 0.05), 0.01 * 0.2 + 0.96 * 0.4 + 0.05 * 0.6]
    assert applied_force(q, table_constants("left")) == pytest.approx(left, abs=1e-15)
    assert applied_force(q, table_constants("right")) == pytest.approx(right, abs=1e-15)
    # c7…c9 alone give the same force as the nine constants (only the last three are read)
    assert np.array_equal(applied_force(q, table_constants("left")[6:]), applied_force(q, table_constants("left")))


def test_field_basis_rows_are_one_x_y_z(rng):
    # Truth: the module's definition, rows 1, x̂, ŷ, ẑ in the order of FIELDS
    q = rng.uniform(size=(7, 3))
    b = field_basis(q)
    assert FIELDS == ("1", "x", "y", "z") and b.shape == (4, 7)
    assert np.array_equal(b[0], np.ones(7)) and np.array_equal(b[1:], q.T)


def test_supine_force_is_equation_18(left_lung):
    # Supine gravity (+y LPS) makes the height term equal ŷ, so Table I's (18) is reproduced.
    fr = lung_frame(left_lung.vertices, "left")
    q = fr.normalized(left_lung.vertices)
    c = table_constants("left")
    f = force_weights(fr, "supine", c) @ field_basis(q)
    assert np.allclose(f, applied_force(q, c))


def test_height_weights_by_hand(left_lung):
    # Truth, by hand from the frame's axes (Y = −y, Z = −z in LPS): supine gravity +y points along
    # −Y, so the height is ŷ (weights 0, 0, 1, 0); prone is its mirror 1 − ŷ; upright gravity −z
    # points along +Z (apex → base), so the height is 1 − ẑ (the apex, ẑ = 0, is the top).
    fr = lung_frame(left_lung.vertices, "left")
    assert height_weights(fr, "supine") == pytest.approx([0, 0, 1, 0], abs=1e-15)
    assert height_weights(fr, "prone") == pytest.approx([1, 0, -1, 0], abs=1e-15)
    assert height_weights(fr, "upright") == pytest.approx([1, 0, 0, -1], abs=1e-15)
    # force weights: c7 on x̂, c9 on ẑ, c8 on the height
    c = table_constants("left")
    assert force_weights(fr, "upright", c) == pytest.approx([0.95, 0.01, 0, 0.07 - 0.95], abs=1e-15)


@pytest.mark.parametrize("name", list(GRAVITY))
def test_height_is_zero_at_bottom_one_at_top(left_lung, name):
    fr = lung_frame(left_lung.vertices, "left")
    h = height_weights(fr, name) @ field_basis(fr.normalized(left_lung.vertices))
    up = -np.array(GRAVITY[name])
    elevation = left_lung.vertices @ up
    assert h[np.argmin(elevation)] == pytest.approx(0, abs=1e-12)
    assert h[np.argmax(elevation)] == pytest.approx(1, abs=1e-12)
    assert np.corrcoef(h, elevation)[0, 1] == pytest.approx(1)


def test_prone_mirrors_supine(left_lung):
    fr = lung_frame(left_lung.vertices, "left")
    q = fr.normalized(left_lung.vertices)
    hs = height_weights(fr, "supine") @ field_basis(q)
    hp = height_weights(fr, "prone") @ field_basis(q)
    assert np.allclose(hs + hp, 1)
