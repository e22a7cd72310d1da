"""The single-scan experiment: its translation, its isotropic row, its rows on real data."""

import json

import numpy as np
import pytest

from lungdeform.fit.objective import Target
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.validate.physiology import DIAPHRAGM_CM_PER_L, tidal_motion
from lungdeform.validate.single_scan import (
    COARSE_POINTS,
    LungPair,
    SingleScanConfig,
    best_translation,
    isotropic,
    run_single_scan,
    score,
)
from tests.conftest import require_path


def _sphere(radius, centre, subdivisions=4):
    s = icosphere(subdivisions, 1.0)
    return Surface(s.vertices * radius + centre, s.faces, "sphere")


def test_best_translation_recovers_a_shift():
    # a surface and its translated copy: the translation that best fits one onto the other is the shift
    a = _sphere(50.0, np.zeros(3))
    shift = np.array([3.0, -7.0, 11.0])
    b = _sphere(50.0, shift, subdivisions=5)
    t = best_translation(a.vertices, a.faces, np.ones(a.n_vertices, bool), Target(b, b.volume_ml))
    assert np.allclose(t, shift, atol=0.05)


def _ellipsoid(axes, centre=(0.0, 0.0, 0.0), subdivisions=5):
    s = icosphere(subdivisions, 1.0)
    return Surface(s.vertices * np.asarray(axes, float) + centre, s.faces, "ellipsoid")


def _plain_icp(vertices, faces, keep, target, tol=1e-6, iterations=1000):
    # the reference: iterated closest points with exact closest points on all kept vertices, each step the
    # mean residual of both directions (pooled), run until the step is 1e-6 mm
    to_target = SurfaceDistance(target.surface.vertices, target.surface.faces)
    own = SurfaceDistance(vertices, faces)
    pts, tpts = vertices[keep], target.surface.vertices[target.keep]
    t = np.zeros(3)
    for _ in range(iterations):
        _, a, _ = to_target.query(pts + t)
        _, b, _ = own.query(tpts - t)
        step = np.concatenate([a - (pts + t), tpts - (b + t)]).mean(axis=0)
        t = t + step
        if np.linalg.norm(step) < tol:
            return t
    raise AssertionError("the plain reference did not converge")


def test_best_translation_recovers_a_known_translation_exactly():
    # an ellipsoid (more vertices than the coarse stage keeps, so both stages run) and its copy moved by a
    # known t: the distance is zero there and nowhere else, so t is the answer, to the stopping tolerance
    a = _ellipsoid((60.0, 45.0, 90.0))
    assert a.n_vertices > COARSE_POINTS
    shift = np.array([4.0, -9.0, 13.0])
    b = Surface(a.vertices + shift, a.faces, "moved")
    t = best_translation(a.vertices, a.faces, np.ones(a.n_vertices, bool), Target(b, b.volume_ml))
    assert np.linalg.norm(t - shift) < 1e-3


def test_best_translation_is_the_plain_icp_fixed_point():
    # a randomly deformed ellipsoid against another ellipsoid, moved, its top cropped (not measured): the
    # coarse-to-fine Gauss-Newton answer is the fixed point plain iterated closest points converges to
    rng = np.random.default_rng(7)
    a = _ellipsoid((60.0, 45.0, 90.0))
    k, phase = rng.normal(0.0, 0.06, (3, 3)), rng.uniform(0.0, 2 * np.pi, 3)
    bumps = 3.0 * np.sin(a.vertices @ k + phase)
    a = Surface(a.vertices + bumps, a.faces, "deformed")
    b = _ellipsoid((63.0, 44.0, 95.0), centre=(2.0, -6.0, 9.0))
    keep_b = b.vertices[:, 2] < 9.0 + 70.0
    keep_a = rng.random(a.n_vertices) < 0.5
    target = Target(b, b.volume_ml, keep_b)
    t = best_translation(a.vertices, a.faces, keep_a, target)
    ref = _plain_icp(a.vertices, a.faces, keep_a, target)
    assert np.linalg.norm(ref) > 5.0  # a real move, not the start
    assert np.linalg.norm(t - ref) < 1e-3


def test_isotropic_row_is_exact_on_a_sphere():
    # a sphere inflated about its centre is isotropic scaling: that row scores ~0 on both measures,
    # whatever translation the target carries (the score removes it)
    rest = _sphere(50.0, np.array([10.0, 20.0, 30.0]))
    big = Surface((rest.vertices - [10, 20, 30]) * 1.2 + [10, 20, 30] + [5, 0, 0], rest.faces, "big")
    lm = np.array([[10.0, 20, 30], [30, 20, 30], [10, 0, 40]])
    target_lm = (lm - [10, 20, 30]) * 1.2 + [15, 20, 30]
    pair = LungPair("s", "right", rest, np.ones(rest.n_vertices, bool), Target(big, big.volume_ml), big.volume_ml,
                    lm, target_lm)
    row = score(pair, *isotropic(pair))
    assert row["surface_mean_mm"] < 0.2 and row["landmark_mean_mm"] < 0.2
    assert np.allclose(row["translation_mm"], [5, 0, 0], atol=0.1)


def test_embedded_lungs_breathe_with_the_diaphragm():
    # physiology of a tidal breath (+500 mL) with the shipped default: the base moves more SI than AP,
    # and the diaphragm descends within the published range per litre (validate/physiology.py);
    # Table I fails both (its force is gravity-dominated: the lungs move front to back)
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    lo, hi = DIAPHRAGM_CM_PER_L
    for name, m in tidal_motion(build_model(default_lungs())).items():
        _, ap, si = m["base_mm"]
        assert si > ap, name
        assert lo <= m["diaphragm_cm_per_l"] <= hi, name
    for name, m in tidal_motion(build_model(default_lungs(), default="paper")).items():
        assert m["base_mm"][1] > m["base_mm"][2] and m["diaphragm_cm_per_l"] < lo, name


@pytest.mark.realdata
def test_itk_pair_rows_and_layout(data_dir, tmp_path):
    # real data, the given default (no fit needed): the metrics layout of the issue, and the
    # population default beating Table I on the ITK right lung (surface and landmarks)
    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    m = run_single_scan(folder, tmp_path, SingleScanConfig(default="population"))
    row = m["lungs"]["itk/right"]
    assert set(row) == {"default", "paper", "isotropic", "dome", "dome_scaling"}
    assert row["dome"]["dome_mm"] == row["dome_scaling"]["dome_mm"] > 0  # measured from the two masks
    for r in row.values():
        assert set(r) >= {"surface_mean_mm", "landmark_mean_mm", "translation_mm", "landmark_motion_mm"}
    assert m["summary"]["n_lungs"] == 1
    assert row["default"]["surface_mean_mm"] < row["paper"]["surface_mean_mm"]
    assert row["default"]["landmark_mean_mm"] < row["paper"]["landmark_mean_mm"]
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["default"]["surface_mean_mm"] > 0
    assert (tmp_path / "report.html").stat().st_size > 1000
