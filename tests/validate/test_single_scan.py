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
    FittedLung,
    LungPair,
    SingleScanConfig,
    Training,
    best_translation,
    isotropic,
    run_single_scan,
    score,
    summarise,
)
from tests.conftest import require_path
from tests.validate.test_copd import phantom_case
from tests.validate.test_lung_pair import _cut_folder


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
    assert set(row) == {"default", "dome", "dome_scaling", "paper", "isotropic", "lung_info", "region_shares"}
    assert row["lung_info"] == {"landmarks": True, "cut": ["exp i-high", "insp i-high"],
                                "folder": "itk-right-lung-two-volumes"}  # the ITK crop cuts its medial face
    for r in (row[k] for k in ("default", "dome", "dome_scaling", "paper", "isotropic")):
        assert set(r) >= {"surface_mean_mm", "landmark_mean_mm", "translation_mm", "landmark_motion_mm", "regions_mm"}
    assert m["summary"]["n_lungs"] == 1 and m["summary"]["n_lungs_landmarks"] == 1
    assert row["dome"]["dome_mm"] == row["dome_scaling"]["dome_mm"] > 0  # measured from the two masks
    assert row["default"]["surface_mean_mm"] < row["paper"]["surface_mean_mm"]
    assert row["default"]["landmark_mean_mm"] < row["paper"]["landmark_mean_mm"]
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["default"]["surface_mean_mm"] > 0
    assert (tmp_path / "report.html").stat().st_size > 1000


def _lung(surface, landmark, folder="a", cut=(), rows=("default", "isotropic")):
    return {**{r: {"surface_mean_mm": surface * (1.0 if r == "default" else 2.0),
                   "landmark_mean_mm": None if landmark is None else landmark * (1.0 if r == "default" else 2.0),
                   "regions_mm": {"apex": surface, "base": None, "costal": surface, "mediastinal": surface}}
              for r in rows},
            "lung_info": {"landmarks": landmark is not None, "cut": list(cut), "folder": folder}}


def test_summary_counts_every_lung_and_the_landmarks_over_those_with_them():
    # truth, by hand: surfaces 1, 2, 3, 10 (median 2.5), landmarks only on the first two (median of 5 and 7);
    # the ratios to isotropic (twice the default here) are 0.5; a region without values is None; the subsets
    # split the same lungs by landmarks, cut and folder
    lungs = {"s1/left": _lung(1.0, 5.0), "s1/right": _lung(2.0, 7.0), "s2/left": _lung(3.0, None, "b", ("exp j-low",)),
             "s3/left": _lung(10.0, None, "b")}
    s = summarise(lungs)
    assert (s["n_lungs"], s["n_lungs_landmarks"], s["n_lungs_cut"], s["cut_lungs"]) == (4, 2, 1, ["s2/left"])
    d = s["default"]
    assert (d["surface_mean_mm"], d["landmark_mean_mm"], d["surface_mean_mm_landmark_lungs"]) == (2.5, 6.0, 1.5)
    assert (d["n_lungs"], d["n_lungs_landmarks"]) == (4, 2)
    assert d["surface_vs_isotropic"] == 0.5 and d["landmark_vs_isotropic"] == 0.5
    assert d["regions_mm"] == {"apex": 2.5, "base": None, "costal": 2.5, "mediastinal": 2.5}
    subsets = s["subsets"]
    assert set(subsets) == {"landmarks", "no_landmarks", "uncut", "folder a", "folder b"}
    assert subsets["no_landmarks"]["default"]["surface_mean_mm"] == 6.5
    assert subsets["no_landmarks"]["default"]["landmark_mean_mm"] is None
    assert subsets["uncut"]["n_lungs"] == 3 and subsets["folder a"]["default"]["landmark_mean_mm"] == 6.0


@pytest.mark.slow
def test_folders_with_and_without_landmarks_and_a_plugged_in_row(tmp_path):
    # truth: two folders, one of COPDgene-named subjects with landmarks, one of .mha masks without (its
    # lungs cut by the field of view): every lung is scored (4), the landmarks on the two that have them;
    # a row plugged in through the config is scored like the others (here the isotropic prediction under
    # another name: the same figures); report.html carries the per-lung and per-region figures
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    phantom_case(a, n=2)
    _cut_folder(b)
    seen = []

    def again(pair, training):
        seen.append(isinstance(training, Training) and training.default.name == "population")
        return isotropic(pair)

    config = SingleScanConfig(default="population", rows=(("again", again),))
    m = run_single_scan([a, b], tmp_path / "out", config)
    s = m["summary"]
    assert sorted(m["lungs"]) == ["copd2/left", "copd2/right", "cut/left", "cut/right"]
    assert (s["n_lungs"], s["n_lungs_landmarks"], s["n_lungs_cut"]) == (4, 2, 2) and seen == [True] * 4
    for k, v in m["lungs"].items():
        assert (v["default"]["landmark_mean_mm"] is None) == k.startswith("cut")
        assert v["again"]["surface_mean_mm"] == v["isotropic"]["surface_mean_mm"]
        assert set(v["default"]["regions_mm"]) == {"apex", "base", "costal", "mediastinal"}
    assert s["isotropic"]["landmark_mean_mm"] is not None and s["subsets"]["no_landmarks"]["n_lungs"] == 2
    text = (tmp_path / "out" / "report.html").read_text()
    assert text.count("<img") == 4 and "median distance per region" in text and "cut: exp j-low" in text


def test_leave_one_out_learns_from_the_defaults_own_other_subjects(tmp_path):
    # truth: a default learned from s1 and s2 (their scans' digests in its provenance) scores s1 with a default
    # learned from s2's lungs alone (not from s3, which it never saw: c1…c9 are then s2's median, here its
    # constants exactly), and s3 with the default as it is
    from lungdeform.model.population import PopulationDefault
    from lungdeform.validate.single_scan import _defaults_for, _learned_from
    from lungdeform.validate.subjects import Subject

    sphere = _sphere(40.0, np.zeros(3))
    subjects, pairs, fits = [], {}, {}
    for k, name in enumerate(("s1", "s2", "s3")):
        scan = tmp_path / f"{name}.nii"
        scan.write_bytes(name.encode())
        subjects.append(Subject(name, None, (scan, scan)))
        c = np.array([1.0 + k, 2, 0.39, 1, 1, 3, 0.5, 0.3, 1])
        for side in ("left", "right"):
            pairs[(name, side)] = LungPair(name, side, sphere, np.ones(sphere.n_vertices, bool),
                                           Target(sphere, sphere.volume_ml), sphere.volume_ml + 100.0)
            fits[(name, side)] = FittedLung(c, np.ones(sphere.n_vertices), np.zeros((sphere.n_vertices, 3)),
                                            np.zeros((sphere.n_vertices, 3)), np.ones(sphere.n_vertices), np.zeros(3),
                                            1.0, 100.0)
    base = PopulationDefault("mine", {"left": np.ones(9), "right": np.ones(9)},
                             provenance={"subject_digests": {"a": subjects[0].digest, "b": subjects[1].digest}})
    learned_from = _learned_from(subjects, base, True)
    assert learned_from == {"s1", "s2"} and _learned_from(subjects, base, False) == set()
    chosen = _defaults_for(subjects, base, learned_from, pairs, fits, lambda m: None)
    assert chosen["s3"][0] is base and chosen["s2"][0] is not base
    assert np.allclose(chosen["s1"][0].constants["left"], [2.0, 2, 0.39, 1, 1, 3, 0.5, 0.3, 1])
    assert np.allclose(chosen["s2"][0].constants["left"], [1.0, 2, 0.39, 1, 1, 3, 0.5, 0.3, 1])
