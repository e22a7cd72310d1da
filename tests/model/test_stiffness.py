"""Stiffness (Young's modulus) fields: documented values and shapes, validation, spring nodes."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.model.stiffness import as_moduli, gravity_gradient, node_moduli, sphere_override, uniform


def test_uniform_values_and_shape():
    # Truth: the docstring, the same modulus everywhere, one per mass node
    e = uniform(5, 2.5)
    assert e.shape == (5,) and e.dtype == np.float64 and np.all(e == 2.5)
    assert np.all(uniform(3) == 1.0)  # default: the reference tissue
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(InputError, match="modulus must be a finite modulus > 0"):
            uniform(3, bad)


def test_gravity_gradient_is_linear_from_dependent_to_nondependent():
    # Truth, by hand: supine gravity +y (LPS, posterior); vertices at y = 0, 25, 50, 100 mm: the
    # lowest point along gravity (largest y) gets `dependent`, the highest (y = 0) `nondependent`,
    # linear in between (y = 25: a quarter of the way).
    v = np.array([[0.0, 0.0, 0.0], [5.0, 25.0, 1.0], [-3.0, 50.0, 7.0], [0.0, 100.0, 0.0]])
    e = gravity_gradient(v, np.array([0.0, 3.0, 0.0]), dependent=3.0, nondependent=1.0)
    assert e == pytest.approx([1.0, 1.5, 2.0, 3.0], abs=1e-15)
    # prone gravity (−y) swaps the ends
    assert gravity_gradient(v, np.array([0.0, -1.0, 0.0]), 3.0, 1.0) == pytest.approx([3.0, 2.5, 2.0, 1.0])
    # no extent along gravity: the non-dependent modulus everywhere
    flat = np.array([[0.0, 1.0, 0.0], [5.0, 1.0, 2.0]])
    assert np.array_equal(gravity_gradient(flat, np.array([0.0, 1.0, 0.0]), 3.0, 1.0), [1.0, 1.0])


def test_gravity_gradient_refuses_bad_input():
    v = np.zeros((2, 3))
    with pytest.raises(InputError, match="gravity must be a non-zero"):
        gravity_gradient(v, np.zeros(3))
    with pytest.raises(InputError, match="gravity must be a non-zero"):
        gravity_gradient(v, np.ones(2))
    with pytest.raises(InputError, match="dependent"):
        gravity_gradient(v, np.array([0.0, 1.0, 0.0]), dependent=0.0)


def test_sphere_override_sets_the_inside_only():
    # Truth, by hand: points at 0, 10 (on the sphere: inclusive) and 11 mm from the centre, radius
    # 10 mm; the input array is left unchanged (a copy is returned).
    v = np.array([[0.0, 0, 0], [10.0, 0, 0], [0, 11.0, 0]])
    e = np.array([1.0, 2.0, 3.0])
    out = sphere_override(e, v, np.zeros(3), 10.0, 20.0)
    assert np.array_equal(out, [20.0, 20.0, 3.0])
    assert np.array_equal(e, [1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="modulus"):
        sphere_override(e, v, np.zeros(3), 10.0, 0.0)


def test_as_moduli_names_the_parameter_and_shape():
    assert as_moduli([1, 2], 2).dtype == np.float64
    with pytest.raises(InputError, match=r"stiffness must have shape \(3,\) \(one modulus per vertex\), got \(2,\)"):
        as_moduli([1.0, 2.0], 3)
    with pytest.raises(InputError, match="moduli must be finite and > 0"):
        as_moduli([1.0, 0.0], 2, name="moduli")
    with pytest.raises(InputError, match="finite"):
        as_moduli([1.0, np.nan], 2)


def test_spring_nodes_take_the_mean_of_their_ends():
    # Truth, by hand: mass moduli 1, 3, 5; springs on edges (0, 1) and (1, 2) → 2 and 4, appended
    # after the mass nodes (graph numbering).
    e = node_moduli(np.array([1.0, 3.0, 5.0]), np.array([[0, 1], [1, 2]]))
    assert np.array_equal(e, [1.0, 3.0, 5.0, 2.0, 4.0])


def test_parse_stiffness_reads_the_three_forms_and_names_the_parameter():
    # "uniform" is no field (None); "sphere:X,Y,Z,R,E" puts E inside the sphere and 1 outside (truth:
    # sphere_override on a uniform field); a bad spec names the parameter, not a command-line flag
    from lungdeform.errors import InputError
    from lungdeform.model.stiffness import parse_stiffness

    v = np.array([[0.0, 0, 0], [50.0, 0, 0], [0, 0, 100.0]])
    assert parse_stiffness("uniform", v, np.array([0.0, 1, 0])) is None
    e = parse_stiffness("sphere:0,0,0,10,3", v, np.array([0.0, 1, 0]))
    assert e[0] == 3.0 and e[1] == 1.0 and e[2] == 1.0
    g = parse_stiffness("gradient:0.5,1.5", v, np.array([0.0, 0, -1]))  # gravity toward the feet
    assert g.shape == (3,) and g[2] > g[0]  # the top (non-dependent) is stiffer than the bottom
    with pytest.raises(InputError, match="^stiffness must be"):
        parse_stiffness("soft", v, np.array([0.0, 1, 0]))
