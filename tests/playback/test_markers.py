"""Tests of lungdeform.playback.markers: markers CSV and the glb's marker records (interior-field motion)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.playback import export as E
from lungdeform.playback import markers as M
from tests.browser.support import two_lungs


@pytest.fixture(scope="module")
def model():
    return two_lungs(3)


#: Markers inside the test ellipsoids (semi-axes 60, 80, 110 mm about x = ±90): deep, off-centre, near the wall.
INTERIOR = np.array([[90.0, 10.0, -20.0], [-90.0, 0.0, 50.0], [110.0, -40.0, 60.0], [-60.0, 30.0, -80.0]])


def _marker_at(a: dict, lam: float) -> np.ndarray:
    # the glb extras' formula (schema 2): position at weight λ of the lung's target 0
    return np.array(a["position_mm"]) + lam * np.array(a["tidal_mm"])


def test_marker_on_a_vertex_follows_its_normal_motion(model):
    # truth: the lung's own tidal target at that vertex, along the vertex normal. The interior field
    # is the sliding interpolation of the surface's normal motion (smoothing 100 mm), so a marker on
    # the surface stays on it to within 10 % of that vertex's own normal motion (the vertices chosen
    # are those that move most along their normal, where a wrong or zero field cannot pass)
    for name, lung in model.lungs.items():
        t0 = E.lung_targets(lung)[0][0]
        n = lung.surface.vertex_normals
        normal = np.einsum("ij,ij->i", t0, n)
        idx = np.argsort(-np.abs(normal))[:5]
        anchors = M.marker_anchors(model, lung.surface.vertices[idx])
        assert [a["lung"] for a in anchors] == [name] * 5
        for a, i in zip(anchors, idx):
            assert a["distance_mm"] == pytest.approx(0, abs=1e-9)
            np.testing.assert_allclose(_marker_at(a, 0.0), lung.surface.vertices[i], atol=1e-9)
            for lam in (0.4, 1.0, 1.7):
                moved = _marker_at(a, lam) - lung.surface.vertices[i]
                assert moved @ n[i] == pytest.approx(lam * normal[i], rel=0.1)


def test_interior_marker_moves_as_points_at(model):
    # truth: LungModel.points_at (the interior field of `lungdeform track`) at the scale that weight λ
    # of target 0 stands for, s = λ·calibration_ml/unit_ml
    anchors = M.marker_anchors(model, INTERIOR, ["a", "b", "c", "d"])
    assert [a["lung"] for a in anchors] == ["left", "right", "left", "right"]
    assert all(a["inside"] and a["distance_mm"] > 1 and not a["landmark_corrected"] for a in anchors)
    for a in anchors:
        lung = model.lungs[a["lung"]]
        for lam in (0.25, 1.0, 1.6):
            s = lam * lung.calibration_ml / lung.unit_ml
            np.testing.assert_allclose(_marker_at(a, lam), lung.points_at([a["position_mm"]], scale=s)[0], atol=1e-6)
    # and not the old nearest-wall reading: deep inside, the interior field differs from the
    # displacement of the nearest surface vertex by millimetres (so the check above can fail)
    lung = model.lungs["left"]
    t0 = E.lung_targets(lung)[0][0]
    nearest = np.argmin(np.linalg.norm(lung.surface.vertices - INTERIOR[0], axis=1))
    assert np.linalg.norm(np.array(anchors[0]["tidal_mm"]) - t0[nearest]) > 1.0


def test_landmark_corrected_markers_use_the_correction(model, rng):
    # a lung carrying a landmark correction: the markers' field includes it (truth: points_at)
    from dataclasses import replace

    from lungdeform.model.lung import Model

    lung = model.lungs["left"]
    lm = np.array([90.0, 0.0, 0.0]) + rng.uniform(-1, 1, (8, 3)) * [30.0, 40.0, 60.0]
    corrected = replace(lung, landmarks=lm, landmark_correction=rng.normal(0, 0.01, (8, 3)), landmark_smoothing=10.0)
    m2 = Model({"left": corrected, "right": model.lungs["right"]}, {"source": "test"})
    plain, fixed = M.marker_anchors(model, INTERIOR[:1]), M.marker_anchors(m2, INTERIOR[:1])
    assert fixed[0]["landmark_corrected"] and not plain[0]["landmark_corrected"]
    s = corrected.calibration_ml / corrected.unit_ml
    np.testing.assert_allclose(_marker_at(fixed[0], 1.0), corrected.points_at(INTERIOR[:1], scale=s)[0], atol=1e-6)
    assert np.linalg.norm(np.subtract(fixed[0]["tidal_mm"], plain[0]["tidal_mm"])) > 1e-3


def test_markers_refused_far_outside_or_malformed(model):
    with pytest.raises(InputError, match=r"^tumours\.csv: 1 point\(s\) lie more than 30 mm outside every lung.*2 \("):
        M.marker_anchors(model, np.array([[90.0, 0, 0], [0.0, 300.0, 0]]), source="tumours.csv")
    with pytest.raises(InputError, match="finite"):
        M.marker_anchors(model, np.array([[np.nan, 0, 0]]))
    with pytest.raises(InputError, match="1 labels for 2 markers"):
        M.marker_anchors(model, INTERIOR[:2], ["a"])
    with pytest.raises(InputError, match=r"\(p, 3\)"):
        M.marker_anchors(model, np.zeros((2, 2)))
