"""The cohort runner: failure isolation, atomic folders, resume, locking (one job's own tests:
tests/cohort/test_job.py, which also builds the test cohort).

Runs use an in-process Dask cluster (threads) to keep the tests fast; tests/cli/test_cohort.py
runs the default worker processes.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from lungdeform.cohort import job as J
from lungdeform.cohort import runner as C
from lungdeform.cohort.job import FitOptions, fit_job, input_digest, job_folder
from lungdeform.cohort.manifest import read_manifest
from lungdeform.cohort.runner import Cluster, run_cohort
from lungdeform.errors import InputError
from tests.cohort.test_job import FAST, _hidden, cohort, make_cohort, quick_report  # noqa: F401 (fixtures)


@pytest.fixture
def population_stub(monkeypatch):
    """Stands in for lungdeform.cohort.population (helper B's module) and records its calls: these tests
    are about the runner; the statistics have their own tests."""
    calls = []

    def write_population(results, out, manifest_dir):
        calls.append((list(results), Path(out), Path(manifest_dir)))
        return {"files": {}, "n_ok": sum(r["status"] == "ok" for r in results)}

    monkeypatch.setattr(C, "write_population", write_population)
    return calls


#: one worker thread in this process: the jobs run here, fast to start
LOCAL = Cluster(workers=1, processes=False)


def test_cohort_isolates_failure_and_resumes(tmp_path, cohort, population_stub, quick_report):
    out = tmp_path / "out"
    events = []
    r1 = run_cohort(cohort, out, cluster=LOCAL, options=FAST, progress=events.append)
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
        assert [J.STAGES.index(s) for s in seen[:-1]] == sorted(J.STAGES.index(s) for s in seen[:-1])
    # population statistics got every result (ok and failed) and the manifest's folder
    (results, pop_out, manifest_dir), = population_stub
    assert [r["status"] for r in results] == ["ok", "ok", "failed"] and manifest_dir == cohort.parent.resolve()
    stamps = {k: (out / "subjects" / k / "result.json").stat().st_mtime_ns for k in ("S0/right", "S1/left")}

    # second run: the finished jobs are skipped untouched, the failed one runs again
    r2 = run_cohort(cohort, out, cluster=LOCAL, options=FAST)
    assert r2.skipped == {"S0/right", "S1/left"}
    assert [r["status"] for r in r2.results] == ["ok", "ok", "failed"]
    for k, t in stamps.items():
        assert (out / "subjects" / k / "result.json").stat().st_mtime_ns == t
    assert json.loads((out / "cohort.json").read_text())["jobs"]["ran"] == 1

    # --skip-failed: nothing to run, so no cluster is even started
    r3 = run_cohort(cohort, out, cluster=LOCAL, options=FAST, skip_failed=True)
    assert r3.skipped == {"S0/right", "S1/left", "S2/right"} and r3.scheduler is None

    # the broken input is fixed: only that job runs, and its new folder replaces the failed one whole
    good = make_cohort(tmp_path / "fixed", broken=None)
    (cohort.parent / "S2" / "ei.ply").write_bytes((good.parent / "S2" / "ei.ply").read_bytes())
    r4 = run_cohort(cohort, out, cluster=LOCAL, options=FAST)
    assert r4.skipped == {"S0/right", "S1/left"} and len(r4.ok) == 3
    assert {p.name for p in (out / "subjects" / "S2" / "right").iterdir()} == {
        "result.json", "model.npz", "metrics.json", "report.html"}  # no traceback.txt left from the failure
    assert _hidden(out) == []


def test_exception_after_temp_folder_leaves_no_half_folder(tmp_path, cohort, monkeypatch, quick_report):
    # the rename into place fails for S1 after its temporary folder is complete: S1 is reported as
    # failed (in memory, since its folder cannot be written either), the others finish, and no
    # folder, half or whole, appears for S1
    publish = J._publish

    def flaky(tmp, final):
        if final.parent.name == "S1":
            raise OSError(28, "No space left on device (injected)")
        publish(tmp, final)

    monkeypatch.setattr(J, "_publish", flaky)
    out = tmp_path / "out"
    r = run_cohort(cohort, out, cluster=LOCAL, options=FAST, population=False)
    s1 = r.results[1]
    assert s1["status"] == "failed" and "injected" in s1["error"] and "could not be written" in s1["error"]
    assert [x["status"] for x in r.results] == ["ok", "failed", "failed"]
    assert not (out / "subjects" / "S1").exists() or not any((out / "subjects" / "S1").iterdir())
    assert _hidden(out) == []
    # once the disk is fine again, a re-run does S1 (and the still-broken S2) only
    monkeypatch.setattr(J, "_publish", publish)
    r2 = run_cohort(cohort, out, cluster=LOCAL, options=FAST, population=False)
    assert r2.skipped == {"S0/right"} and r2.results[1]["status"] == "ok"


def test_killed_job_leaves_only_a_stale_temp_folder_cleaned_next_run(tmp_path, cohort, monkeypatch, quick_report):
    job = read_manifest(cohort).jobs[0]
    out = tmp_path / "out"
    publish, discard = J._publish, J._discard
    # Ctrl-C just before the rename: the temporary folder is removed on the way out
    monkeypatch.setattr(J, "_publish", lambda tmp, final: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        fit_job(job, out, FAST)
    assert not job_folder(out, job).exists() and _hidden(out) == []
    # a hard kill at the same point (no clean-up runs): only a hidden temporary folder remains
    monkeypatch.setattr(J, "_discard", lambda path: None)
    with pytest.raises(KeyboardInterrupt):
        fit_job(job, out, FAST)
    assert not job_folder(out, job).exists()
    stale, = _hidden(out)
    assert stale.name.startswith(".right.partial-") and (stale / "result.json").is_file()
    monkeypatch.setattr(J, "_publish", publish)
    monkeypatch.setattr(J, "_discard", discard)
    # the next run removes it and does the job
    r = run_cohort(cohort, out, cluster=LOCAL, options=FAST, population=False)
    assert r.results[0]["status"] == "ok" and _hidden(out) == []


def test_refuses_bad_options_and_a_busy_output(tmp_path, cohort):
    with pytest.raises(InputError, match="^workers sets the size of the local cluster"):
        run_cohort(cohort, tmp_path / "o", cluster=Cluster(scheduler="tcp://127.0.0.1:1", workers=2))
    with pytest.raises(InputError, match=r"^scheduler tcp://127\.0\.0\.1:1: cannot connect"):
        run_cohort(cohort, tmp_path / "o", cluster=Cluster(scheduler="tcp://127.0.0.1:1", connect_timeout_s=0.5),
                   population=False)
    busy = tmp_path / "busy"
    busy.mkdir()
    with C._exclusive(busy):
        with pytest.raises(InputError, match="in use by another cohort run"):
            run_cohort(cohort, busy, cluster=Cluster(processes=False))
    with pytest.raises(InputError, match="max_evaluations must be a whole number >= 1"):
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
