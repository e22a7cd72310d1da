"""The cohort runner: per-job results (schema, truth), failure isolation, atomic folders, resume.

Subjects are tiny ellipsoid lungs (162 vertices) whose second scan is the same lung moved by the
model with known constants (+200 mL): a fit must explain that motion much better than no motion.
Runs use an in-process Dask cluster (threads) to keep the tests fast; tests/cli/test_cohort.py
runs the default worker processes.
"""

import json
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from lungdeform import cohort as C
from lungdeform.cohort import FitOptions, fit_job, input_digest, job_folder, run_cohort
from lungdeform.errors import InputError
from lungdeform.manifest import read_manifest
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
    from lungdeform.io import write_mesh
    from lungdeform.model import build_lung

    rows = ["subject,side,volume_ml,path"]
    for i, side in enumerate(("right", "left", "right")):
        name = f"S{i}"
        lung = ellipsoid_lung(side, subdivisions=2)
        model = build_lung(lung, side, constants=TRUE, calibration_ml=INSPIRATION_ML, unit_ml=INSPIRATION_ML)
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
    from lungdeform.distance import symmetric_distance
    from lungdeform.io import load_surface

    a, b = (load_surface(p)[0] for p in job.inputs)
    return symmetric_distance(a, b).stats.mean


@pytest.fixture
def cohort(tmp_path):
    return make_cohort(tmp_path / "cohort")


@pytest.fixture
def population_stub(monkeypatch):
    """Stands in for lungdeform.population (helper B's module) and records its calls: these tests
    are about the runner; the statistics have their own tests."""
    calls = []

    def write_population(results, out, manifest_dir):
        calls.append((list(results), Path(out), Path(manifest_dir)))
        return {"files": {}, "n_ok": sum(r["status"] == "ok" for r in results)}

    module = types.ModuleType("lungdeform.population")
    module.write_population = write_population
    monkeypatch.setitem(sys.modules, "lungdeform.population", module)
    return calls


@pytest.fixture
def quick_report(monkeypatch):
    """run_fit's HTML report takes ~2 s of matplotlib per fit (the fit itself ~0.3 s here); the
    runner tests below are about orchestration, so they get a one-line report. The real report is
    written in test_fit_job_result_schema_and_truth and tested in tests/cli/test_fit.py."""
    from lungdeform.atomic import write_text

    monkeypatch.setattr("lungdeform.report.write_report",
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
    assert [e["stage"] for e in events] == list(C.STAGES)


def test_result_constants_are_those_of_the_saved_model(tmp_path):
    # with landmarks the headline (model.npz) is the landmark-informed fit: result.json must carry
    # its constants, not the surface-only fit's; --no-landmark-fit skips the cross-validation
    from lungdeform.io import write_mesh
    from lungdeform.landmarks import write_elastix_points
    from lungdeform.model import build_lung
    from lungdeform.modelfile import load_model

    lung = ellipsoid_lung("right", subdivisions=2)
    model = build_lung(lung, "right", constants=TRUE, calibration_ml=INSPIRATION_ML, unit_ml=INSPIRATION_ML)
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
    import lungdeform

    monkeypatch.setattr(lungdeform, "__version__", "99.0.0")  # an upgrade re-fits
    assert input_digest(job, FAST) != d
    monkeypatch.undo()
    st = job.inputs[1].stat()
    os.utime(job.inputs[1], ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert input_digest(job, FAST) != d


def test_cohort_isolates_failure_and_resumes(tmp_path, cohort, population_stub, quick_report):
    out = tmp_path / "out"
    events = []
    r1 = run_cohort(cohort, out, workers=1, processes=False, options=FAST, progress=events.append)
    status = {f"{r['subject']}/{r['side']}": r["status"] for r in r1.results}
    assert status == {"S0/right": "ok", "S1/left": "ok", "S2/right": "failed"}
    assert r1.skipped == frozenset() and r1.failed[0]["error_type"] == "ReadError"
    for r in r1.ok:
        assert len(r["constants"]) == 9
    summary = json.loads((out / "cohort.json").read_text())
    assert summary["jobs"] == {"total": 3, "ok": 2, "failed": 1, "skipped": 0, "ran": 3, "not_run": 0}
    assert summary["workers"] == 1 and summary["scheduler"].startswith("inproc://") and not summary["interrupted"]
    assert summary["population"] == {"files": {}, "n_ok": 2}
    # every job went through the stages in order before its result
    for key in status:
        seen = [e.get("stage", e["event"]) for e in events if e.get("job") == key]
        assert seen[-1] == "done" and seen[0] == "read"
        assert [C.STAGES.index(s) for s in seen[:-1]] == sorted(C.STAGES.index(s) for s in seen[:-1])
    # population statistics got every result (ok and failed) and the manifest's folder
    (results, pop_out, manifest_dir), = population_stub
    assert [r["status"] for r in results] == ["ok", "ok", "failed"] and manifest_dir == cohort.parent.resolve()
    stamps = {k: (out / "subjects" / k / "result.json").stat().st_mtime_ns for k in ("S0/right", "S1/left")}

    # second run: the finished jobs are skipped untouched, the failed one runs again
    r2 = run_cohort(cohort, out, workers=1, processes=False, options=FAST)
    assert r2.skipped == {"S0/right", "S1/left"}
    assert [r["status"] for r in r2.results] == ["ok", "ok", "failed"]
    for k, t in stamps.items():
        assert (out / "subjects" / k / "result.json").stat().st_mtime_ns == t
    assert json.loads((out / "cohort.json").read_text())["jobs"]["ran"] == 1

    # --skip-failed: nothing to run, so no cluster is even started
    r3 = run_cohort(cohort, out, workers=1, processes=False, options=FAST, skip_failed=True)
    assert r3.skipped == {"S0/right", "S1/left", "S2/right"} and r3.scheduler is None

    # the broken input is fixed: only that job runs, and its new folder replaces the failed one whole
    good = make_cohort(tmp_path / "fixed", broken=None)
    (cohort.parent / "S2" / "ei.ply").write_bytes((good.parent / "S2" / "ei.ply").read_bytes())
    r4 = run_cohort(cohort, out, workers=1, processes=False, options=FAST)
    assert r4.skipped == {"S0/right", "S1/left"} and len(r4.ok) == 3
    assert {p.name for p in (out / "subjects" / "S2" / "right").iterdir()} == {
        "result.json", "model.npz", "metrics.json", "report.html"}  # no traceback.txt left from the failure
    assert _hidden(out) == []


def test_exception_after_temp_folder_leaves_no_half_folder(tmp_path, cohort, monkeypatch, quick_report):
    # the rename into place fails for S1 after its temporary folder is complete: S1 is reported as
    # failed (in memory, since its folder cannot be written either), the others finish, and no
    # folder, half or whole, appears for S1
    publish = C._publish

    def flaky(tmp, final):
        if final.parent.name == "S1":
            raise OSError(28, "No space left on device (injected)")
        publish(tmp, final)

    monkeypatch.setattr(C, "_publish", flaky)
    out = tmp_path / "out"
    r = run_cohort(cohort, out, workers=1, processes=False, options=FAST, population=False)
    s1 = r.results[1]
    assert s1["status"] == "failed" and "injected" in s1["error"] and "could not be written" in s1["error"]
    assert [x["status"] for x in r.results] == ["ok", "failed", "failed"]
    assert not (out / "subjects" / "S1").exists() or not any((out / "subjects" / "S1").iterdir())
    assert _hidden(out) == []
    # once the disk is fine again, a re-run does S1 (and the still-broken S2) only
    monkeypatch.setattr(C, "_publish", publish)
    r2 = run_cohort(cohort, out, workers=1, processes=False, options=FAST, population=False)
    assert r2.skipped == {"S0/right"} and r2.results[1]["status"] == "ok"


def test_killed_job_leaves_only_a_stale_temp_folder_cleaned_next_run(tmp_path, cohort, monkeypatch, quick_report):
    job = read_manifest(cohort).jobs[0]
    out = tmp_path / "out"
    publish, discard = C._publish, C._discard
    # Ctrl-C just before the rename: the temporary folder is removed on the way out
    monkeypatch.setattr(C, "_publish", lambda tmp, final: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        fit_job(job, out, FAST)
    assert not job_folder(out, job).exists() and _hidden(out) == []
    # a hard kill at the same point (no clean-up runs): only a hidden temporary folder remains
    monkeypatch.setattr(C, "_discard", lambda path: None)
    with pytest.raises(KeyboardInterrupt):
        fit_job(job, out, FAST)
    assert not job_folder(out, job).exists()
    stale, = _hidden(out)
    assert stale.name.startswith(".right.partial-") and (stale / "result.json").is_file()
    monkeypatch.setattr(C, "_publish", publish)
    monkeypatch.setattr(C, "_discard", discard)
    # the next run removes it and does the job
    r = run_cohort(cohort, out, workers=1, processes=False, options=FAST, population=False)
    assert r.results[0]["status"] == "ok" and _hidden(out) == []


def test_refuses_bad_options_and_a_busy_output(tmp_path, cohort):
    with pytest.raises(InputError, match="--workers sets the size of the local cluster"):
        run_cohort(cohort, tmp_path / "o", scheduler="tcp://127.0.0.1:1", workers=2)
    with pytest.raises(InputError, match=r"--scheduler tcp://127\.0\.0\.1:1: cannot connect"):
        run_cohort(cohort, tmp_path / "o", scheduler="tcp://127.0.0.1:1", connect_timeout_s=0.5, population=False)
    busy = tmp_path / "busy"
    busy.mkdir()
    with C._exclusive(busy):
        with pytest.raises(InputError, match="in use by another cohort run"):
            run_cohort(cohort, busy, processes=False)
    with pytest.raises(InputError, match=r"max_evaluations \(--evaluations\) must be a whole number >= 1"):
        FitOptions(max_evaluations=0)
    # no silent coercion: fractions and strings are refused, numpy integers accepted
    for bad, match in (({"folds": 2.9}, "folds"), ({"direction_degree": "3"}, "direction_degree"),
                       ({"landmark_fit": "no"}, "landmark_fit"), ({"max_evaluations": True}, "max_evaluations")):
        with pytest.raises(InputError, match=match):
            FitOptions(**bad)
    numpy_ints = FitOptions(direction_degree=np.int64(2), folds=np.int64(3))
    assert type(numpy_ints.direction_degree) is int and numpy_ints.folds == 3
    job = read_manifest(cohort).jobs[0]
    assert input_digest(job, numpy_ints) == input_digest(job, FitOptions(direction_degree=2, folds=3))
