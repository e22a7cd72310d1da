"""The fit objective against synthetic ground truth: a model built with known constants deforms a
lung; at the true directions the objective vanishes and c7…c9 come back; the inverse force inverts
the solver exactly."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.objective import (
    LandmarkTerm,
    LungFitter,
    ObjectiveSettings,
    Target,
    inverse_force,
    least_squares_constants,
)
from lungdeform.model.graph import spring_graph
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.model.solve import ForceSolver
from lungdeform.model.transfer import local_transfer
from tests.conftest import ellipsoid_lung

TRUE = np.array([0.2, 1.5, 0.4, 0.8, 0.9, 1.8, 0.3, 1.0, 0.5])


@pytest.fixture(scope="module")
def truth():
    lung = ellipsoid_lung("right", 3)
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    target = lung.deformed(model.displacement).with_name("target")
    return lung, model, target


def test_inverse_force_exact(rng):
    lung = ellipsoid_lung("left", 2)
    g = spring_graph(lung.vertices, lung.edges)
    e = rng.uniform(0.5, 2.0, lung.n_vertices)
    t = local_transfer(g, e)
    f = rng.uniform(0, 1, lung.n_vertices)
    kept = ForceSolver(t, "direct").solve(f)
    # with the true kept force on every node the single sparse product recovers f exactly
    from lungdeform.model.transfer import split_transfer

    keep, q = split_transfer(t)
    x = kept / keep
    assert (x - q.T @ x)[: lung.n_vertices] == pytest.approx(f, abs=1e-10)
    # from mass nodes only (spring nodes = mean of ends) it is an approximation that keeps the trend
    approx = inverse_force(t, kept[: lung.n_vertices], g.spring_ends)[: lung.n_vertices]
    assert np.corrcoef(approx, f)[0, 1] > 0.5


def test_least_squares_constants(rng):
    fields = rng.normal(size=(3, 100))
    c = np.array([0.1, 0.9, -0.3])
    w = np.ones(100)
    w[:10] = 0.0
    vals = c @ fields
    vals[:10] = 1e6  # zero-weight rows are ignored
    assert least_squares_constants(fields, vals, w) == pytest.approx(c)


def test_true_directions_recover_force_constants_and_surface(truth):
    # rays along the true d hit the target at exactly k·F: c7…c9 come back and the surface matches
    lung, model, target = truth
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")])
    obj, parts = fitter.evaluate(TRUE[:6], full=True)
    assert parts["constants"][6:] == pytest.approx(TRUE[6:] / TRUE[6:].max(), abs=2e-3)
    assert obj < 0.05
    assert parts["u"] == pytest.approx(model.displacement, abs=0.02)


def test_bad_volumes(truth):
    lung, _, target = truth
    with pytest.raises(InputError, match="not larger"):
        LungFitter(lung, "right", [Target(target, lung.volume_ml - 1.0, name="t")])
    with pytest.raises(InputError, match="must not decrease"):
        LungFitter(lung, "right", [Target(target, lung.volume_ml + 300, name="a"),
                                    Target(target, lung.volume_ml + 200, name="b")])
    # equal volumes (an inhale and an exhale phase of one volume) are two targets at one volume
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 300, name="a"),
                                        Target(target, lung.volume_ml + 300, name="b")])
    assert [t.name for t in fitter.targets] == ["a", "b"]


def _interior_landmarks(lung, u, count=24, seed=1):
    """Interior points and their positions under the sliding interpolation of ``u`` (the
    metrics' interior motion): the truth a model with displacement ``u`` predicts exactly."""
    from lungdeform.interior.sliding import surface_weights

    rng = np.random.default_rng(seed)
    c = lung.vertices.mean(0)
    pts = c + rng.uniform(-1, 1, size=(count, 3)) * np.array([25.0, 40.0, 60.0])
    return pts, pts + surface_weights(lung, pts) @ u


def test_landmark_term_of_the_objective(truth):
    # at the true constants the landmarks (moved by the true field) are exact; shifting their
    # observed positions by 3 mm gives a landmark RMS of exactly 3 mm and objective² = surface² + w·9
    lung, model, target = truth
    lm, lm_t = _interior_landmarks(lung, model.displacement)
    tg = [Target(target, lung.volume_ml + 200.0, name="t")]
    plain = LungFitter(lung, "right", tg).evaluate(TRUE[:6])
    obj, parts = LungFitter(lung, "right", tg, landmarks=LandmarkTerm(lm, {0: lm_t})).evaluate(TRUE[:6], full=True)
    assert parts["landmark_rms"] < 0.05 and obj == pytest.approx(plain, abs=0.01)
    shifted = lm_t + np.array([0.0, 3.0, 0.0])
    obj, parts = LungFitter(lung, "right", tg, landmarks=LandmarkTerm(lm, {0: shifted}, weight=2.0)).evaluate(TRUE[:6], full=True)
    assert parts["landmark_rms"] == pytest.approx(3.0, abs=0.05)
    assert obj == pytest.approx(np.sqrt(parts["surface_rms"] ** 2 + 2.0 * parts["landmark_rms"] ** 2))
    with pytest.raises(InputError, match="rows must correspond"):
        LungFitter(lung, "right", tg, landmarks=LandmarkTerm(lm, {0: lm_t[:-1]}))


def test_crop_face_rays_do_not_enter_the_force_fit(truth):
    # an artefact on a face (the target's medial cap pushed out 0.8 mm, under the robust pass's
    # 1 mm floor, like an image-boundary crop) biases c7…c9 when its rays are used; left out on both
    # surfaces (keep), the true constants and a zero objective come back
    from lungdeform.geometry.mesh import Surface

    lung, model, target = truth
    face = lung.vertices[:, 0] > lung.vertices[:, 0].max() - 15.0  # the medial cap of the right lung
    bumped = target.vertices.copy()
    bumped[face] += np.array([0.8, 0.0, 0.0])
    art = Surface(bumped, target.faces, "artefact")
    good = LungFitter(lung, "right", [Target(art, lung.volume_ml + 200.0, keep=~face, name="t")], keep=~face)
    obj, parts = good.evaluate(TRUE[:6], full=True)
    assert parts["constants"][6:] == pytest.approx(TRUE[6:] / TRUE[6:].max(), abs=1e-3)
    assert obj < 0.01
    _, biased = LungFitter(lung, "right", [Target(art, lung.volume_ml + 200.0, name="t")]).evaluate(TRUE[:6], full=True)
    assert np.abs(biased["constants"][6:] - TRUE[6:] / TRUE[6:].max()).max() > 0.01


def test_c1_c3_c5_share_a_free_factor_the_gauge(truth):
    # why the least-squares mode holds c3 fixed: directions are normalised, so scaling c1, c3, c5
    # together gives the identical model (a zero singular value of the fit)
    lung, _, target = truth
    f = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")], settings=ObjectiveSettings(samples=500))
    c = TRUE[:6].copy()
    c2 = c * np.array([2.5, 1, 2.5, 1, 2.5, 1])
    d1 = f.displacement(f.evaluate(c, full=True)[1]["directions"], TRUE[6:])
    d2 = f.displacement(f.evaluate(c2, full=True)[1]["directions"], TRUE[6:])
    assert d2 == pytest.approx(d1, abs=1e-9)


def test_residual_jacobian_against_differences_of_the_residuals(truth):
    # truth: central differences of residual_vector itself (a dense reference for the closest-point
    # derivative): away from the true constants (residuals of a few mm), for a direction constant,
    # a force constant and the target's translation, with the landmark term; the distance is only
    # piecewise smooth (a closest point can jump to another face), so a few rows may differ: the
    # columns agree to 2 % in norm and 95 % of the rows to 1e-3 mm per unit
    lung, model, target = truth
    lm, lm_t = _interior_landmarks(lung, model.displacement)
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")],
                        landmarks=LandmarkTerm(lm, {0: lm_t}))
    c0, force = TRUE[:6] * np.array([1.3, 0.8, 1.0, 1.2, 0.7, 1.1]), TRUE[6:] * np.array([1.2, 1.0, 0.8])
    shift = np.array([[1.0, -0.5, 0.7]])

    def u_of(c, f):
        return fitter.displacement(fitter.directions(c), f)

    h = 1e-6
    params = [(0, None), (1, None), (None, 0)]  # c1, c2, c7
    du = np.zeros(lung.vertices.shape + (len(params),))
    for k, (ci, fi) in enumerate(params):
        c, f = c0.copy(), force.copy()
        if ci is not None:
            c[ci] += h
        else:
            f[fi] += h
        du[..., k] = (u_of(c, f) - u_of(c0, force)) / h
    jp, jt = fitter.residual_jacobian(u_of(c0, force), du, shift)
    # without the translation columns (a search that fits none): the same J, no J_shift
    jp_only, none = fitter.residual_jacobian(u_of(c0, force), du, shift, translations=False)
    assert none is None and np.array_equal(jp_only, jp)
    step = 1e-4
    for k, (ci, fi) in enumerate(params + [("t", a) for a in range(3)]):
        plus, minus = [], []
        for sign, out in ((1, plus), (-1, minus)):
            c, f, sh = c0.copy(), force.copy(), shift.copy()
            if ci == "t":
                sh[0, fi] += sign * step
            elif ci is not None:
                c[ci] += sign * step
            else:
                f[fi] += sign * step
            out.append(fitter.residual_vector(u_of(c, f), sh)[0])
        ref = (plus[0] - minus[0]) / (2 * step)
        got = jp[:, k] if ci != "t" else jt[:, fi]
        assert np.linalg.norm(ref) > 1e-3
        assert np.linalg.norm(got - ref) < 0.02 * np.linalg.norm(ref)
        assert np.quantile(np.abs(got - ref), 0.95) < 1e-3 * max(1.0, np.abs(ref).max())


def test_target_query_is_the_exact_query_and_reuses_the_objectives(truth):
    # reference: a fresh search of the target's own SurfaceDistance. The fitter's query of the model's
    # vertices at the displacement just evaluated returns what the objective found (no search again),
    # and equals the fresh search; another set of points is searched (from the last faces) and is exact too
    lung, model, target = truth
    fitter = LungFitter(lung, "right", [Target(target, lung.volume_ml + 200.0, name="t")])
    u = 0.9 * model.displacement
    r, residuals, _, _ = fitter.residual_vector(u)
    x = fitter.p + u
    fresh = fitter.prepared[0].distance.query(x[fitter.keep])
    got = fitter.target_query(0, x[fitter.keep])
    assert got is fitter.target_query(0, x[fitter.keep])  # the same answer object: no new search
    for a, b in zip(got, fresh):
        assert np.array_equal(a, b)
    assert np.array_equal(residuals["t"][:fitter.keep.sum()], fresh[0])
    other = x[fitter.keep] + 0.5
    for a, b in zip(fitter.target_query(0, other), fitter.prepared[0].distance.query(other)):
        assert np.array_equal(a, b)
