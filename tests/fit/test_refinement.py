"""The surface refinement (lungdeform.fit.refinement) against analytic shapes and invariants."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.refinement import ITERATIONS, WIDTHS_MM, gaussian_smoother, refine_displacement
from lungdeform.geometry.distance import SurfaceDistance, symmetric_distance
from lungdeform.geometry.mesh import Surface, icosphere


def _mean_distance(rest: Surface, u, s, target: Surface) -> float:
    return symmetric_distance(Surface(rest.vertices + s * u, rest.faces), target).stats.mean


def test_smoother_is_symmetric_gaussian():
    # truth: W_ij = exp(-|p_i - p_j|^2 / 2w^2) within the cut-off, W_ii = 1, symmetric
    rng = np.random.default_rng(3)
    pts = rng.uniform(-30, 30, (200, 3))
    w = gaussian_smoother(pts, 8.0).toarray()
    d2 = np.sum((pts[:, None] - pts[None]) ** 2, axis=2)
    dense = np.where(d2 < (3 * 8.0) ** 2, np.exp(-d2 / (2 * 64.0)), 0.0)
    np.testing.assert_allclose(w, dense, atol=1e-12)


def test_refines_onto_a_larger_sphere_without_sliding():
    # truth: the target is the concentric sphere of radius 60 from 50; starting from a displacement
    # that reaches only half way, the refined surface lies on the target, and the motion is radial
    # (the closest point moves along the normal: no tangential sliding)
    rest = icosphere(3, radius=50.0)
    target = icosphere(4, radius=60.0)
    radial = rest.vertices / np.linalg.norm(rest.vertices, axis=1, keepdims=True)
    u0 = 5.0 * radial
    before = _mean_distance(rest, u0, 1.0, target)
    ref = refine_displacement(rest.vertices, u0, [target], [1.0])
    after = _mean_distance(rest, ref.displacement, 1.0, target)
    assert before > 4.5 and after < 0.15, (before, after)
    tangential = ref.displacement - np.sum(ref.displacement * radial, axis=1, keepdims=True) * radial
    assert np.abs(tangential).max() < 0.05
    np.testing.assert_allclose(ref.before, u0)  # the fitted displacement is kept for the ablation


def test_a_displacement_already_on_target_is_unchanged():
    # invariant: zero residual everywhere -> zero update (the sphere maps onto itself scaled; the
    # target is the same mesh moved, so every closest point is the vertex itself)
    rest = icosphere(3, radius=40.0)
    u = 0.1 * rest.vertices
    target = Surface(rest.vertices + 2.0 * u, rest.faces)
    ref = refine_displacement(rest.vertices, u, [target], [2.0])
    np.testing.assert_allclose(ref.displacement, u, atol=1e-9)
    assert ref.max_change_mm < 1e-8


def test_two_targets_are_fitted_jointly_linear_in_scale():
    # truth: spheres of radius 52 at s = 1 and 54 at s = 2 are both met by u = 2 mm per unit, radial;
    # from zero displacement the joint least-squares update finds it
    rest = icosphere(3, radius=50.0)
    targets = [icosphere(4, radius=52.0), icosphere(4, radius=54.0)]
    ref = refine_displacement(rest.vertices, np.zeros_like(rest.vertices), targets, [1.0, 2.0])
    radial = np.sum(ref.displacement * rest.vertices, axis=1) / 50.0
    assert np.median(radial) == pytest.approx(2.0, abs=0.05)
    for t, s in zip(targets, (1.0, 2.0)):
        assert _mean_distance(rest, ref.displacement, s, t) < 0.1


def _one_by_one(p, u, targets, s, kept):
    # the update of the module docstring written out target by target, every closest point searched
    # afresh and every residual smoothed alone (how it was computed before the batching)
    queries = [SurfaceDistance(t.vertices, t.faces) for t in targets]
    for width in WIDTHS_MM:
        smoother = gaussian_smoother(p, width)
        weight = smoother @ kept.astype(float)
        for _ in range(ITERATIONS):
            step = np.zeros_like(u)
            for query, st in zip(queries, s):
                x = p + st * u
                step += st * (smoother @ np.where(kept[:, None], query.query(x)[1] - x, 0.0))
            u = u + step / np.maximum(weight, 1e-9)[:, None] / float(np.sum(np.square(s)))
    return u


def test_batched_targets_equal_one_by_one_to_the_bit():
    # reference: the same update target by target with fresh searches; all targets smoothed in one
    # sparse product and each search started from its last faces give the same numbers exactly
    # (each column of the product sums in the same order; the bound only narrows an exact search)
    rng = np.random.default_rng(7)
    rest = icosphere(3, radius=50.0)
    sphere = icosphere(4)
    targets = [Surface(r * sphere.vertices * rng.uniform(0.95, 1.05, 3) + rng.normal(size=3), sphere.faces)
               for r in (53.0, 56.0, 56.5, 60.0)]
    s = np.array([0.4, 0.7, 0.75, 1.0])
    u0 = 0.1 * rest.vertices + rng.normal(scale=0.5, size=rest.vertices.shape)
    kept = rng.random(rest.n_vertices) < 0.9
    ref = refine_displacement(rest.vertices, u0, targets, s, kept, finest_mm=5.0)
    assert np.array_equal(ref.displacement, _one_by_one(rest.vertices, u0.copy(), targets, s, kept))


def test_crop_vertices_follow_their_neighbours():
    # a vertex that does not count (keep False: a crop face) gets no residual of its own but the
    # smooth average of its kept neighbours: on a uniformly growing sphere it grows like them
    rest = icosphere(3, radius=50.0)
    target = icosphere(4, radius=55.0)
    keep = rest.vertices[:, 2] < 40.0  # the top cap left out
    ref = refine_displacement(rest.vertices, np.zeros_like(rest.vertices), [target], [1.0], keep)
    radial = np.sum(ref.displacement * rest.vertices, axis=1) / 50.0
    assert radial[~keep].min() > 3.0  # moved out by most of the 5 mm, from the neighbours only


@pytest.mark.parametrize("kwargs, match", [
    ({"displacement": np.zeros((3, 3))}, "displacement must be"),
    ({"scales": [0.0]}, "scale"),
    ({"scales": [1.0, 2.0]}, "scale"),
    ({"finest_mm": 0.5}, "finest_mm"),
    ({"keep": np.ones(5, bool)}, "keep"),
])
def test_bad_arguments_are_refused_by_name(kwargs, match):
    rest = icosphere(2, radius=30.0)
    args = {"rest_vertices": rest.vertices, "displacement": np.zeros_like(rest.vertices),
            "targets": [icosphere(2, radius=33.0)], "scales": [1.0]}
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        refine_displacement(**args)
