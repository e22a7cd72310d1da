"""One cohort job (lungdeform.cohort.job): its result record (schema, truth), failure as a result, the
input digest; and the test cohort the runner tests share (tests/cohort/test_runner.py).

Subjects are tiny ellipsoid lungs (162 vertices) whose second scan is the same lung moved by the
model with known constants (+200 mL): a fit must explain that motion much better than no motion.
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from lungdeform.cohort import job as J
from lungdeform.cohort.job import FitOptions, fit_job, input_digest, job_folder
from lungdeform.cohort.manifest import read_manifest
from lungdeform.errors import InputError
from tests.conftest import ellipsoid_lung

TRUE = np.array([0.2, 1.5, 0.4, 0.8, 0.9, 1.8, 0.3, 1.0, 0.5])
INSPIRATION_ML = 200.0
#: Enough optimiser steps for the 162-vertex ellipsoid to beat no motion clearly, still ~1 s a fit.
FAST = FitOptions(max_evaluations=60, baselines=False)
RESULT_KEYS = {"schema", "version", "subject", "side", "status", "error", "error_type", "inputs", "volumes_ml",
               "constants", "fit_kind", "metrics", "seconds", "input_digest"}
METRIC_KEYS = {"surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm", "objective_rms_mm"}


def make_cohort(folder: Path, broken: str | None = "S2") -> Path:
    """Three one-lung subjects S0 (right), S1 (left, volumes given), S2 (right); ``broken``'s
    second scan is garbage with a valid name (it passes the manifest check, fails in the fit)."""
    from lungdeform.io.meshfile import write_mesh
    from lungdeform.model.lung import BuildSettings, build_lung

    rows = ["subject,side,volume_ml,path"]
    for i, side in enumerate(("right", "left", "right")):
        name = f"S{i}"
        lung = ellipsoid_lung(side, subdivisions=2)
        model = build_lung(lung, side, constants=TRUE, settings=BuildSettings(INSPIRATION_ML, INSPIRATION_ML))
        write_mesh(folder / name / "ee.ply", lung.vertices, lung.faces)
        write_mesh(folder / name / "ei.ply", lung.vertices + model.displacement, lung.faces)
        if name == broken:
            (folder / name / "ei.ply").write_text("not a mesh\n")
        if name == "S1":  # given volumes (measured here from the true surfaces), the others measured
            v = lung.volume_ml
            rows += [f"{name},{side},{v + INSPIRATION_ML!r},{name}/ei.ply", f"{name},{side},{v!r},{name}/ee.ply"]
        else:
            rows += [f"{name},{side},,{name}/ee.ply", f"{name},{side},,{name}/ei.ply"]
    manifest = folder / "manifest.csv"
    manifest.write_text("\n".join(rows) + "\n")
    return manifest


def no_motion_mean_mm(job) -> float:
    """Mean symmetric distance between the two scans as given (no motion, no alignment), mm."""
    from lungdeform.geometry.distance import symmetric_distance
    from lungdeform.io.meshfile import load_surface

    a, b = (load_surface(p)[0] for p in job.inputs)
    return symmetric_distance(a, b).stats.mean


@pytest.fixture
def cohort(tmp_path):
    return make_cohort(tmp_path / "cohort")


@pytest.fixture
def quick_report(monkeypatch):
    """run_fit's HTML report takes ~2 s of matplotlib per fit (the fit itself ~0.3 s here); the
    runner tests are about orchestration, so they get a one-line report. The real report is
    written in test_fit_job_result_schema_and_truth and tested in tests/cli/test_fit.py."""
    from lungdeform.atomic import write_text

    monkeypatch.setattr("lungdeform.evaluate.pipeline.write_report",  # where run_fit looks it up
                        lambda path, **_: write_text(path, "<html>report skipped in this test</html>"))


def _hidden(out: Path) -> list[Path]:
    return [p for p in (out / "subjects").glob("*/.*")]


def test_fit_job_result_schema_and_truth(tmp_path, cohort):
    job = read_manifest(cohort).jobs[0]
    out = tmp_path / "out"
    events = []
    r = fit_job(job, out, FAST, progress=events.append)
    folder = job_folder(out, job)
    assert folder == out / "subjects" / "S0" / "right"
    assert json.loads((folder / "result.json").read_text()) == r
    assert set(r) == RESULT_KEYS and set(r["metrics"]) == METRIC_KEYS
    assert (r["schema"], r["version"], r["subject"], r["side"], r["status"]) == ("lungdeform.cohort.result", 1,
                                                                                 "S0", "right", "ok")
    assert r["error"] is None and r["error_type"] is None
    assert r["inputs"] == [str(p) for p in job.inputs]
    assert len(r["constants"]) == 9 and np.all(np.isfinite(r["constants"]))
    # truth: the second scan was made 200 mL larger by the model; volumes were measured
    assert r["volumes_ml"][1] - r["volumes_ml"][0] == pytest.approx(INSPIRATION_ML, rel=0.02)
    # truth: a surface moved by the model itself is reproduced far better than by no motion
    assert r["metrics"]["surface_mean_mm"] < 0.6 * no_motion_mean_mm(job)
    assert r["metrics"]["landmark_mean_mm"] is None  # no landmarks: null, not NaN
    # the result repeats run_fit's own metrics, not numbers of its own
    m = json.loads((folder / "metrics.json").read_text())
    assert r["metrics"]["surface_rms_mm"] == pytest.approx(m["model"]["surface_rms_mm"])
    assert r["metrics"]["objective_rms_mm"] == pytest.approx(m["fit"]["optimizer"]["objective_rms_mm"])
    assert r["input_digest"] == input_digest(job, FAST) and r["seconds"] > 0
    assert {p.name for p in folder.iterdir()} == {"result.json", "model.npz", "metrics.json", "report.html"}
    assert _hidden(out) == []
    assert [e["stage"] for e in events] == list(J.STAGES)


def test_result_constants_are_those_of_the_saved_model(tmp_path):
    # with landmarks the headline (model.npz) is the landmark-informed fit: result.json must carry
    # its constants, not the surface-only fit's; --no-landmark-fit skips the cross-validation
    from lungdeform.io.landmarks import write_elastix_points
    from lungdeform.io.meshfile import write_mesh
    from lungdeform.io.modelfile import load_model
    from lungdeform.model.lung import BuildSettings, build_lung

    lung = ellipsoid_lung("right", subdivisions=2)
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(INSPIRATION_ML, INSPIRATION_ML))
    folder = tmp_path / "c"
    idx = np.arange(0, lung.n_vertices, 16)  # surface landmarks at their true positions
    write_mesh(folder / "ee.ply", lung.vertices, lung.faces)
    write_mesh(folder / "ei.ply", lung.vertices + model.displacement, lung.faces)
    write_elastix_points(folder / "ee.txt", lung.vertices[idx])
    write_elastix_points(folder / "ei.txt", (lung.vertices + model.displacement)[idx])
    (folder / "manifest.csv").write_text("subject,side,volume_ml,path,landmarks\n"
                                         "S0,right,,ee.ply,ee.txt\nS0,right,,ei.ply,ei.txt\n")
    job = read_manifest(folder / "manifest.csv").jobs[0]
    with_lm = FitOptions(max_evaluations=40, baselines=False, folds=2, align="none")
    r = fit_job(job, tmp_path / "o1", with_lm)
    m = json.loads((job_folder(tmp_path / "o1", job) / "metrics.json").read_text())
    saved = load_model(job_folder(tmp_path / "o1", job) / "model.npz").lungs["right"].constants
    assert r["status"] == "ok" and r["fit_kind"] == "optimizer" == m["headline_fit"] and m["interior_correction"]
    assert r["constants"] == pytest.approx(m["fit"]["optimizer"]["constants"])
    assert r["constants"] == pytest.approx(np.asarray(saved))
    # the landmarks went into the saved model's interior correction
    assert load_model(job_folder(tmp_path / "o1", job) / "model.npz").lungs["right"].landmarks.shape == (len(idx), 3)
    assert m["landmark_cv"]["folds"] == 2
    without = FitOptions(max_evaluations=40, baselines=False, landmark_fit=False, align="none")
    assert input_digest(job, without) != input_digest(job, with_lm)
    r2 = fit_job(job, tmp_path / "o2", without)
    m2 = json.loads((job_folder(tmp_path / "o2", job) / "metrics.json").read_text())
    assert r2["fit_kind"] == "optimizer" and "landmark_cv" not in m2 and "landmarks" not in m2["fit"]
    assert not m2["interior_correction"]
    assert load_model(job_folder(tmp_path / "o2", job) / "model.npz").lungs["right"].landmarks is None
    assert r2["constants"] == pytest.approx(m2["fit"]["optimizer"]["constants"])
    with pytest.raises(InputError, match="align"):
        FitOptions(align="sideways")


def test_given_volumes_are_used_in_order(tmp_path, cohort, quick_report):
    job = read_manifest(cohort).jobs[1]  # S1: rows listed inhale first; the manifest sorts by volume
    r = fit_job(job, tmp_path / "out", FAST)
    # the given volumes fix the volume changes; the end-exhale volume is the model surface's own
    assert r["status"] == "ok" and np.diff(r["volumes_ml"]) == pytest.approx(np.diff(job.volumes_ml))
    assert r["volumes_ml"][0] < r["volumes_ml"][1] and Path(r["inputs"][0]).name == "ee.ply"


def test_fit_job_failure_is_a_result(tmp_path, cohort):
    job = read_manifest(cohort).jobs[2]  # S2: garbage second scan
    out = tmp_path / "out"
    r = fit_job(job, out, FAST)
    assert r["status"] == "failed" and r["error_type"] == "ReadError"
    assert "ei.ply" in r["error"] and "\n" not in r["error"]
    assert r["constants"] is None and set(r["metrics"].values()) == {None}
    folder = job_folder(out, job)
    assert {p.name for p in folder.iterdir()} == {"result.json", "traceback.txt"}  # no partial outputs
    assert "ReadError" in (folder / "traceback.txt").read_text()


def test_input_digest_tracks_files_and_options(tmp_path, cohort, monkeypatch):
    job = read_manifest(cohort).jobs[0]
    d = input_digest(job, FAST)
    assert input_digest(job, FAST) == d
    assert input_digest(job, FitOptions(max_evaluations=61, baselines=False)) != d
    assert input_digest(job, FitOptions(max_evaluations=60, baselines=False, side_check=False)) != d
    with pytest.raises(InputError, match="side_check must be True or False"):
        FitOptions(side_check="no")
    monkeypatch.setattr(J, "__version__", "99.0.0")  # an upgrade re-fits
    assert input_digest(job, FAST) != d
    monkeypatch.undo()
    st = job.inputs[1].stat()
    os.utime(job.inputs[1], ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert input_digest(job, FAST) != d


def test_a_4dct_folder_row_is_one_job_fitted_on_its_phases(tmp_path, rng):
    # one manifest row naming a 4-D CT folder (tests/fourdct_phantom.py: 4 phases, lungs 6 % larger per
    # axis and phase) gives a left and a right job; each fits all 4 phases, volumes measured and rising
    from tests.fourdct_phantom import write_4dct

    write_4dct(tmp_path / "P01" / "ct4d", rng, 4, "description")
    (tmp_path / "cohort.csv").write_text("subject,side,volume_ml,path\nP01,both,,P01/ct4d\n")
    jobs = read_manifest(tmp_path / "cohort.csv").jobs
    assert [j.side for j in jobs] == ["left", "right"]
    result = fit_job(jobs[1], tmp_path / "out", FitOptions(max_evaluations=20, baselines=False, align="none",
                                                           direction_degree=0))
    assert result["status"] == "ok", result["error"]
    assert len(result["volumes_ml"]) == 4 and np.all(np.diff(result["volumes_ml"]) > 0)
