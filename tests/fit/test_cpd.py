"""The deformable Coherent Point Drift of lungdeform.fit.cpd against pycpd's own iteration."""

from __future__ import annotations

import numpy as np
import pycpd
import pytest

from lungdeform.fit.cpd import deformable_cpd


@pytest.mark.parametrize("w, alpha, beta", [(0.05, 2.0, 2.0), (0.0, 1000.0, 0.8)])
def test_same_weights_and_iterations_as_pycpd(w, alpha, beta):
    # truth: pycpd.DeformableRegistration, the iteration it replaces; the row scaling equals
    # diag(P1) @ G exactly, so the weights agree to rounding (bit for bit here) whatever the
    # settings (the baselines' w = 0.05, alpha = 2; the correspondence field's w = 0, alpha = 1000)
    rng = np.random.default_rng(7)
    y = rng.normal(size=(120, 3))
    x = 1.1 * rng.normal(size=(140, 3)) + np.array([0.2, -0.1, 0.05])
    ref = pycpd.DeformableRegistration(X=x, Y=y, alpha=alpha, beta=beta, w=w, max_iterations=60, tolerance=1e-6)
    ref.register()
    got = deformable_cpd(x, y, alpha=alpha, beta=beta, w=w, max_iterations=60, tolerance=1e-6)
    assert got.shape == (120, 3) and np.abs(ref.W).max() > 1e-3  # it moved the points
    np.testing.assert_allclose(got, ref.W, rtol=1e-10, atol=1e-12)
