"""The single-scan experiment: its translation, its isotropic row, its rows on real data."""

import json

import numpy as np
import pytest

from lungdeform.fit.objective import Target
from lungdeform.geometry.mesh import Surface, icosphere
from lungdeform.validate.physiology import DIAPHRAGM_CM_PER_L, tidal_motion
from lungdeform.validate.single_scan import (
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
    assert set(row) == {"default", "paper", "isotropic"}
    for r in row.values():
        assert set(r) >= {"surface_mean_mm", "landmark_mean_mm", "translation_mm", "landmark_motion_mm"}
    assert m["summary"]["n_lungs"] == 1
    assert row["default"]["surface_mean_mm"] < row["paper"]["surface_mean_mm"]
    assert row["default"]["landmark_mean_mm"] < row["paper"]["landmark_mean_mm"]
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["default"]["surface_mean_mm"] > 0
    assert (tmp_path / "report.html").stat().st_size > 1000
