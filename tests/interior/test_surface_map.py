"""The correspondence field: its affine and Gaussian parts against a dense evaluation."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.interior.surface_map import SurfaceMapField


def _field(rng, k=50):
    warp = np.c_[np.eye(3) + 0.05 * rng.normal(size=(3, 3)), rng.normal(size=3)]
    return SurfaceMapField(0.01 * rng.normal(size=(3, 4)), warp, rng.normal(scale=40.0, size=(k, 3)),
                               rng.normal(size=(k, 3)), 30.0)


def _dense(f, q):
    y = q @ f.warp[:, :3].T + f.warp[:, 3]
    d2 = ((y[:, None, :] - f.centers[None, :, :]) ** 2).sum(axis=2)
    return q @ f.linear[:, :3].T + f.linear[:, 3] + np.exp(-d2 / (2 * f.width_mm**2)) @ f.weights


def test_fused_evaluation_equals_the_dense_formula(rng):
    # the field is evaluated by a fused numba loop (no kernel matrix); it must equal the dense formula
    f = _field(rng)
    q = rng.normal(scale=50.0, size=(37, 3))
    np.testing.assert_allclose(f(q), _dense(f, q), rtol=1e-12, atol=1e-12)


def test_zero_weights_leave_the_affine_part(rng):
    # with no Gaussian weight the displacement is exactly L [q; 1]
    f = _field(rng)
    g = SurfaceMapField(f.linear, f.warp, f.centers, np.zeros_like(f.weights), f.width_mm)
    q = rng.normal(scale=50.0, size=(10, 3))
    np.testing.assert_allclose(g(q), q @ f.linear[:, :3].T + f.linear[:, 3], atol=1e-12)


@pytest.mark.parametrize("change, match", [({"linear": np.zeros((3, 3))}, "linear"),
                                           ({"warp": np.full((3, 4), np.nan)}, "warp"),
                                           ({"weights": np.zeros((4, 3))}, "weights"),
                                           ({"width_mm": 0.0}, "width_mm")])
def test_malformed_fields_are_refused_by_name(rng, change, match):
    f = _field(rng, k=5)
    args = {"linear": f.linear, "warp": f.warp, "centers": f.centers, "weights": f.weights, "width_mm": 30.0}
    with pytest.raises(InputError, match=match):
        SurfaceMapField(**{**args, **change})


@pytest.mark.parametrize("width", [30.0, 4.0])
def test_rows_equal_the_point_evaluation(rng, width):
    # along_rows builds each Gaussian along a row by multiplying ratios (three exponentials a row and
    # centre); it must give __call__ at the same points: each value carries at most m²/2 roundings
    # after m steps (m < 60 here), so 1e-12 of the weights' sum bounds the difference. Rows of 0 and
    # 1 point and a row whose peak lies past either end are among them.
    f = SurfaceMapField(*[getattr(_field(rng), a) for a in ("linear", "warp", "centers", "weights")], width)
    starts = rng.normal(scale=60.0, size=(40, 3))
    step = rng.normal(scale=3.0, size=3)
    counts = rng.integers(0, 60, size=40)
    counts[:2] = (0, 1)
    a = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    q = np.repeat(starts, counts, axis=0) + a[:, None] * step
    np.testing.assert_allclose(f.along_rows(starts, step, counts), _dense(f, q), rtol=0,
                               atol=1e-12 * np.abs(f.weights).sum())
    with pytest.raises(InputError, match="counts"):
        f.along_rows(starts, step, counts[:-1])


def test_a_tapered_prior_adds_on_top_in_rows_and_points(left_lung, rng):
    # why: the prior on top of a map is added by __call__ and by along_rows alike (the displacement
    # field evaluates rows, track evaluates points): both must be the map plus w(δ)(M q + b)
    from lungdeform.interior.prior import TaperedPrior
    f = _field(rng)
    prior = TaperedPrior(0.01 * rng.normal(size=(3, 4)), left_lung.vertices, left_lung.faces)
    g = f.with_prior(prior)
    starts = left_lung.vertices.mean(axis=0) + rng.normal(scale=30.0, size=(20, 3))
    step = np.array([2.0, 0.5, -1.0])
    counts = rng.integers(0, 40, size=20)
    a = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    q = np.repeat(starts, counts, axis=0) + a[:, None] * step
    expected = _dense(f, q) + prior.weights(q)[:, None] * (q @ prior.affine[:, :3].T + prior.affine[:, 3])
    np.testing.assert_allclose(g(q), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(g.along_rows(starts, step, counts), expected, rtol=0, atol=1e-10)
    assert 0 < prior.weights(q).max() and f.prior is None and g.with_prior(None).prior is None
