"""The DIR-Lab COPDgene experiment (lungdeform.validate.copd): case discovery, the calibrated
mask-only baselines on a two-lung phantom, and the real cases (slow, LUNGDEFORM_DATA)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.errors import InputError, ReadError
from lungdeform.fit.config import FitConfig
from lungdeform.io.landmarks import write_elastix_points
from lungdeform.validate import copd as C
from tests.conftest import require_path
from tests.segment.test_split import LEFT, RIGHT, two_lungs

#: the inspiration phantom: both ellipsoids' semi-axes scaled by this (x, y, z)
SCALE = np.array([1.06, 1.06, 1.12])


def write_image(image, path):
    im = sitk.GetImageFromArray(np.asarray(image.array))
    im.SetSpacing(image.spacing.tolist())
    im.SetOrigin(image.origin.tolist())
    sitk.WriteImage(im, str(path))


def phantom_case(folder, n=1, shift=(3.0, -2.0, 4.0), seed=3):
    """Case ``n`` named like the DIR-Lab files in ``folder``: two separate ellipsoids at expiration,
    the same scaled by :data:`SCALE` about each centre at inspiration, whose frame is shifted by
    ``shift`` mm (an unknown translation, as in the real data); 8 landmarks per lung, each moved by its
    lung's scaling and the shift."""
    exp, _, _ = two_lungs(bridge=False, source=f"copd{n}_exp_mask.nii.gz")
    insp, _, _ = two_lungs(bridge=False, source=f"copd{n}_insp_mask.nii.gz", scale=tuple(SCALE))
    insp = type(insp)(insp.array, insp.spacing, insp.origin + np.asarray(shift), insp.direction, insp.source)
    write_image(exp, folder / f"copd{n}_exp_mask.nii.gz")
    write_image(insp, folder / f"copd{n}_insp_mask.nii.gz")
    rng = np.random.default_rng(seed)
    a, b = [], []
    for cx, axes in (LEFT, RIGHT):
        centre = np.array([cx, 0.0, 0.0])
        pts = centre + rng.uniform(-0.5, 0.5, (8, 3)) * axes
        a.append(pts)
        b.append(centre + (pts - centre) * SCALE + shift)
    write_elastix_points(folder / f"copd{n}_exp_landmarks.txt", np.concatenate(a))
    write_elastix_points(folder / f"copd{n}_insp_landmarks.txt", np.concatenate(b))
    return folder


def test_find_cases_and_parse_cases(tmp_path):
    # truth: a case counts when its four files are there; a case asked for must be complete
    for name in C.FILES:
        (tmp_path / name.format(n=2)).write_text("x")
    (tmp_path / "copd4_exp_mask.nii.gz").write_text("x")
    assert list(C.find_cases(tmp_path)) == ["copd2"]
    with pytest.raises(ReadError, match=r"case 4 is missing copd4_insp_mask\.nii\.gz"):
        C.find_cases(tmp_path, [2, 4])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReadError, match="no DIR-Lab COPDgene case"):
        C.find_cases(tmp_path / "empty")
    assert C.parse_cases("3,1, 3") == [1, 3] and C.parse_cases(None) is None
    with pytest.raises(InputError, match="cases must be case numbers"):
        C.parse_cases("one")


def test_mask_baselines_on_scaled_ellipsoids(tmp_path):
    # truth: inspiration = each ellipsoid scaled about its centre, then shifted; the moment affine
    # maps an ellipsoid's voxels onto the scaled one exactly up to voxelisation, so it moves the
    # landmarks to within a voxel; centroids alone leave the scaling (6-12 % of offsets up to 25 mm:
    # about 1.5 mm on average)
    rows = C.mask_baselines(C.find_cases(phantom_case(tmp_path))["copd1"])
    for side in ("left", "right"):
        r = rows[side]
        assert r["affine_moments"]["landmark_mean_mm"] < 0.5 * r["no_motion_centroids"]["landmark_mean_mm"]
        assert r["cpd_moments"]["landmark_mean_mm"] < 0.75 * r["no_motion_centroids"]["landmark_mean_mm"]
        assert r["no_motion_centroids"]["landmark_mean_mm"] > 1.2


def test_case_seconds_and_their_medians():
    # truth: a case's fit is the sum of its lungs' fits; its mask-only baselines were computed once
    # for both lungs (each lung records that one time); medians over the cases; None when not recorded
    # the model's own fit is the sum of its lungs' fits less their pipeline baselines (the outputs'
    # writing stays in; None when a lung did not record its baselines' time)
    lung = lambda s, m, b=None: {"seconds": s, "mask_baselines_seconds": m, "baseline_seconds": b}  # noqa: E731
    cases = {"copd1": {"left": lung(10.0, 4.0, 3.0), "right": lung(12.0, 4.0, 4.0)},
             "copd2": {"left": lung(20.0, None), "right": lung(30.0, None)}}
    assert C.case_seconds(cases["copd1"]) == {"fit_seconds": 22.0, "model_fit_seconds": 15.0,
                                              "mask_baselines_seconds": 4.0}
    assert C.case_seconds(cases["copd2"]) == {"fit_seconds": 50.0, "model_fit_seconds": None,
                                              "mask_baselines_seconds": None}
    summary = C.summarise(cases)
    assert summary["fit_seconds"] == 36.0 and summary["mask_baselines_seconds"] == 4.0 and summary["seconds"] == 16.0
    assert summary["model_fit_seconds"] == 15.0


@pytest.mark.slow
def test_run_copd_structure_and_resume(tmp_path):
    # truth: one fit per lung into copd1/<side>/, the figures of fit's metrics collected per lung,
    # medians over the 2 lungs; a second run with the same settings re-fits nothing and leaves the
    # lungs' files untouched, a changed budget re-fits
    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=1)
    out = tmp_path / "out"
    config = FitConfig(max_evaluations=8, align="joint", folds=3, command=C.COMMAND)
    res = C.run_copd(data, out, config)
    assert res["refitted"] == ["copd1/left", "copd1/right"]
    for side in ("left", "right"):
        row = res["cases"]["copd1"][side]
        assert set(row["model"]) == {"surface_mean_mm", "landmark_mean_mm"}
        assert set(row["landmarks_tps"]) == {"landmark_mean_mm"}
        assert {"cpd", "affine", "no_motion", "model_surface_only", *C.MASK_ROWS} <= set(row)
        assert np.isfinite(row["model"]["surface_mean_mm"]) and row["seconds"] > 0
        assert (out / "copd1" / side / "model.npz").is_file() and (out / "copd1" / side / "report.html").is_file()
    assert res["summary"]["n_lungs"] == 2
    # the case's fit time is its two lungs' fits; the mask-only baselines are timed apart, once
    timing = res["timing"]["copd1"]
    assert timing["fit_seconds"] == pytest.approx(sum(res["cases"]["copd1"][s]["seconds"] for s in ("left", "right")))
    assert timing["mask_baselines_seconds"] > 0 and res["summary"]["fit_seconds"] == timing["fit_seconds"]
    # the model's own fit leaves out the pipeline's baselines, which took some time, and keeps the
    # writing of its outputs (the pipeline's model_seconds stops before them)
    rows = [res["cases"]["copd1"][s] for s in ("left", "right")]
    assert all(0 < r["model_seconds"] < r["seconds"] and r["baseline_seconds"] > 0 for r in rows)
    assert timing["model_fit_seconds"] == pytest.approx(sum(r["seconds"] - r["baseline_seconds"] for r in rows))
    assert timing["model_fit_seconds"] > sum(r["model_seconds"] for r in rows)
    assert "Time per case" in (out / "report.html").read_text(encoding="utf-8")
    assert res["summary"]["model"]["surface_mean_mm"] == pytest.approx(
        np.median([res["cases"]["copd1"][s]["model"]["surface_mean_mm"] for s in ("left", "right")]))
    assert json.loads((out / "metrics.json").read_text(encoding="utf-8"))["cases"] == res["cases"]
    assert (out / "report.html").read_text(encoding="utf-8").count("data:image/png;base64") == 1
    stamp = (out / "copd1" / "left" / "model.npz").stat().st_mtime_ns
    again = C.run_copd(data, out, config)
    assert again["refitted"] == [] and again["cases"] == res["cases"]
    assert (out / "copd1" / "left" / "model.npz").stat().st_mtime_ns == stamp
    other = FitConfig(max_evaluations=9, align="joint", folds=3, command=C.COMMAND)
    # the changed budget re-fits both lungs, here at once in two worker processes: the masks split
    # once in this process, the case's wall time is the split and the slower lung (less its
    # baselines), not more than the sum a serial run reports
    third = C.run_copd(data, out, other, [1], workers=2)
    assert third["refitted"] == ["copd1/left", "copd1/right"]
    timing, rows = third["timing"]["copd1"], [third["cases"]["copd1"][s] for s in ("left", "right")]
    slower = max(r["seconds"] - r["baseline_seconds"] for r in rows)
    assert slower < timing["model_fit_wall_seconds"] < timing["model_fit_seconds"]
    assert timing["model_fit_seconds"] == pytest.approx(
        sum(r["seconds"] - r["baseline_seconds"] for r in rows) + timing["model_fit_wall_seconds"] - slower)
    assert all(np.isfinite(r["model"]["surface_mean_mm"]) for r in rows)
    assert third["summary"]["model_fit_wall_seconds"] == timing["model_fit_wall_seconds"]
    assert "both lungs at once, wall" in (out / "report.html").read_text(encoding="utf-8")


def test_settings_digest_follows_the_cpd_baselines_settings(tmp_path, monkeypatch):
    # truth (issue 39): the `cpd` rows are part of a finished lung's metrics, so a run with other CPD
    # settings must not read an earlier run's lung back; the same settings give the same digest
    from dataclasses import replace

    files = [tmp_path / "a.nii.gz", tmp_path / "b.nii.gz"]
    for i, f in enumerate(files):
        f.write_bytes(bytes([i]) * 16)
    config = FitConfig(max_evaluations=8, align="joint", folds=3, command=C.COMMAND)
    before = C.settings_digest(files, "left", config)
    assert C.settings_digest(files, "left", config) == before
    untuned = replace(C.B.CpdSettings(), beta=2.0, w=0.05)
    monkeypatch.setattr(C.B, "CpdSettings", lambda: untuned)
    assert C.settings_digest(files, "left", config) != before


@pytest.mark.slow
@pytest.mark.realdata
def test_real_case_model_surface_below_no_motion(data_dir, tmp_path):
    # truth: the fitted surface (with its fitted translation) is closer to the inspiration surface
    # than the expiration surface left where it is; DIR-Lab COPDgene case 1, a reduced budget (40
    # evaluations was not enough: 11.0 against 10.7 mm; 300 gives 3.0 and 2.6 against 12.4 and 12.6 mm)
    folder = require_path(data_dir, "dirlab-copd-lung-masks")
    res = C.run_copd(folder, tmp_path / "out", C.copd_config(120), [1])
    assert list(res["cases"]) == ["copd1"] and res["summary"]["n_lungs"] == 2
    for side in ("left", "right"):
        row = res["cases"]["copd1"][side]
        assert np.isfinite(row["model"]["surface_mean_mm"])
        assert row["model"]["surface_mean_mm"] < row["no_motion"]["surface_mean_mm"]


@pytest.fixture(scope="module")
def big_lungs():
    # a model of two 90 mm spheres about the origin: every landmark of _landmark_file (within about
    # 50 mm of it) lies deeper than the motion prior's taper (30 mm), so the prior plays at full weight there
    from lungdeform.geometry.mesh import icosphere
    from lungdeform.model.lung import build_model
    return build_model({side: icosphere(3, 90.0) for side in ("left", "right")})


def _landmark_file(folder, rng, offset, own, model):
    # what a correspondence fit writes (lungdeform.evaluate.pipeline.write_landmark_motion, and the
    # model file beside it, whose surface the prior tapers over): residual = a shared offset plus the
    # subject's own part
    from lungdeform.io.modelfile import save_model
    folder.mkdir(parents=True)
    save_model(folder / "model.npz", model)
    pts = rng.normal(scale=10.0, size=(20, 3))
    pts -= pts.mean(axis=0)  # centred on the lung: a constant residual leaves the prior's linear part at 0
    surface_only = pts + rng.normal(size=(20, 3))
    np.savez(folder / "landmarks.npz", landmarks=pts, observed=(surface_only + offset + own)[None],
             surface_only=surface_only[None], volumes_ml=np.array([3000.0]), centroid=np.zeros(3),
             scale=np.array([30.0, 30.0, 30.0]))


def test_motion_prior_is_scored_leave_one_subject_out(tmp_path, rng, big_lungs):
    # truth: every lung's residual is a shared offset (0, -5, 2) mm plus a subject's own offset; a case
    # is scored by the prior of the other cases only, so its own offset is never learned from it:
    # the error left on case A is |own_A - mean(own of the others)| exactly, and priors/A.json names
    # only the others
    shared = np.array([0.0, -5.0, 2.0])
    own = {"copdA": np.array([3.0, 0.0, 0.0]), "copdB": np.array([0.0, 1.0, 0.0]), "copdC": np.array([0.0, -1.0, 0.0])}
    cases = {}
    for name, o in own.items():
        for side in ("left", "right"):
            mirrored = o * ([-1.0, 1.0, 1.0] if side == "left" else 1.0)
            _landmark_file(tmp_path / name / side, rng, shared * ([-1.0, 1.0, 1.0] if side == "left" else 1.0), mirrored,
                           big_lungs)
            cases.setdefault(name, {})[side] = {"model_surface_only": {"landmark_mean_mm": -1.0}}
    done = C.apply_loso_priors(tmp_path, cases)
    assert done["applied"]
    for name, o in own.items():
        others = np.mean([v for k, v in own.items() if k != name], axis=0)
        for side in ("left", "right"):
            row = cases[name][side]
            assert row["model_surface_noprior"] == {"landmark_mean_mm": -1.0}
            assert row["model_surface_only"]["landmark_mean_mm"] == pytest.approx(np.linalg.norm(o - others), abs=1e-6)
        saved = json.loads((tmp_path / "priors" / f"{name}.json").read_text())
        assert name not in saved["subjects"] and len(saved["subjects"]) == 2
    assert json.loads((tmp_path / "motion_prior.json").read_text())["subjects"] == sorted(own)


def test_motion_prior_needs_two_cases(tmp_path, rng, big_lungs):
    # one case has no other subject to learn from: nothing is scored, and the rows stay as they were
    _landmark_file(tmp_path / "copd1" / "left", rng, np.zeros(3), np.zeros(3), big_lungs)
    cases = {"copd1": {"left": {"model_surface_only": {"landmark_mean_mm": 4.0}}}}
    done = C.apply_loso_priors(tmp_path, cases)
    assert not done["applied"] and "at least 2 cases" in done["reason"]
    assert cases["copd1"]["left"] == {"model_surface_only": {"landmark_mean_mm": 4.0}}


def test_cohort_manifest_reads_back_as_the_cases(tmp_path):
    # truth: read by the cohort's own manifest reader, the manifest gives one left and one right job per
    # case, expiration then inspiration (row order: volumes are measured), each phase with its own
    # landmark file; a data folder whose path holds a comma still reads back (the cells are quoted)
    from lungdeform.cohort.manifest import read_manifest

    data = tmp_path / "dir-lab, copd"
    data.mkdir()
    for n in (1, 3):
        for name in C.FILES:
            (data / name.format(n=n)).write_bytes(b"")  # only existence is read by the manifest check
    (tmp_path / "elsewhere").mkdir()
    path = C.write_cohort_manifest(C.find_cases(data), tmp_path / "elsewhere" / "manifest.csv")
    m = read_manifest(path)
    assert [j.key for j in m.jobs] == ["copd1/left", "copd1/right", "copd3/left", "copd3/right"]
    for job in m.jobs:
        n = job.subject[-1]
        assert job.ordered_by == "row" and job.volumes_ml is None
        assert job.inputs == [data / f"copd{n}_exp_mask.nii.gz", data / f"copd{n}_insp_mask.nii.gz"]
        assert job.landmarks == [data / f"copd{n}_exp_landmarks.txt", data / f"copd{n}_insp_landmarks.txt"]


def test_an_interrupted_case_fitted_at_once_leaves_no_case_folder(tmp_path):
    # why: with --workers 2 each worker made the case folder for its lung's hidden folder; stopped
    # together, the one that made it could not remove it (the other's hidden folder was still in it)
    # and an empty copd1/ was left. The parent makes it now, and removes it when the workers stop.
    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=1)
    out = tmp_path / "out"

    class Stopped:
        count = 2

        def map(self, fn, tasks):
            for _files, _side, folder, *_ in tasks:
                assert folder.parent.is_dir()  # made before the workers start
            raise KeyboardInterrupt

    config = FitConfig(max_evaluations=2, align="joint", folds=3, command=C.COMMAND)
    with pytest.raises(KeyboardInterrupt):
        C.fit_case_lungs("copd1", C.find_cases(data)["copd1"], out, config, Stopped())
    assert not (out / "copd1").exists()


def test_an_interrupted_lung_fit_leaves_no_folder(tmp_path, monkeypatch):
    # why: a fit stopped (SIGTERM, which the CLI turns into Ctrl-C) after run_fit wrote its files but
    # before the settings digest was added left a lung folder that looked finished; the lung is now
    # fitted into a hidden folder renamed at the end: complete with its digest, or absent (and the case
    # folder it made for it removed with it: nothing is left)
    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=1)
    out = tmp_path / "out"

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(C.CaseBaselines, "__call__", stopped)  # after run_fit, before the digest
    config = FitConfig(max_evaluations=2, align="joint", folds=3, command=C.COMMAND)
    with pytest.raises(KeyboardInterrupt):
        C.run_copd(data, out, config)
    assert [p.relative_to(out) for p in out.rglob("*")] == []
