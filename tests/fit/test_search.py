"""Search strategies over the constants (lungdeform.fit.search), on analytic objectives with a known
minimum."""

import numpy as np
import pytest

from lungdeform.fit.search import from_unbounded, grid_search, powell_search


def test_grid_search_reports_when_it_did_not_converge():
    # a coupled quadratic needs several coordinate cycles: with one cycle allowed the search says it
    # did not converge; with enough it stops where no single-coordinate grid step improves (the
    # definition of its convergence: on a strongly coupled quadratic that is near, not at, the minimum)
    def f(x):
        return (x[0] - 0.3) ** 2 + (x[1] - 0.7) ** 2 + 1.5 * (x[0] - 0.3) * (x[1] - 0.7)

    bounds = ((0.0, 1.0), (0.0, 1.0))
    _, _, cycles, converged = grid_search(f, [0.9, 0.1], bounds, 0.01, max_cycles=1)
    assert cycles == 1 and not converged
    x, best, _, converged = grid_search(f, [0.9, 0.1], bounds, 0.01, max_cycles=50)
    assert converged and best == pytest.approx(f(x))
    for k in range(2):
        for step in (-0.01, 0.01):
            y = np.array(x, float)
            y[k] += step
            assert f(y) >= best - 1e-12
    assert best < 1e-3 < f([0.9, 0.1])


def test_powell_search_stays_inside_the_box():
    # a quadratic with its minimum inside the box is found; one whose minimum lies outside ends on
    # the nearest face of the box, never outside (the sine map keeps every candidate inside)
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 2.0])
    seen = []

    def f(x):
        seen.append(np.array(x))
        return float(np.sum((x - np.array([0.3, 1.2])) ** 2))

    x, best, ok, msg = powell_search(f, np.array([0.9, 0.1]), lo, hi, 2000)
    assert ok and msg == "converged"
    assert x == pytest.approx([0.3, 1.2], abs=1e-3) and best < 1e-5
    assert all(np.all(s >= lo) and np.all(s <= hi) for s in seen)
    x, _, _, _ = powell_search(lambda x: float(np.sum((x - np.array([1.5, 1.0])) ** 2)), np.array([0.5, 0.5]),
                               lo, hi, 2000)
    assert x == pytest.approx([1.0, 1.0], abs=1e-3)
    assert from_unbounded(np.array([-np.pi / 2, np.pi / 2]), lo, hi) == pytest.approx([0.0, 2.0])
