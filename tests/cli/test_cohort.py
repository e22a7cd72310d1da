"""``lungdeform cohort``: exit codes, output lines, resume, bad manifests, Ctrl-C; and a smoke run of
``lungdeform bench cohort`` (its JSON schema; no timing assertions)."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from lungdeform.cli.main import main
from tests.cohort.test_job import make_cohort, quick_report  # noqa: F401 (fixtures)
from tests.cohort.test_runner import population_stub  # noqa: F401 (fixtures)

FAST = ["--evaluations", "60", "--no-baselines"]


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def test_cohort_reports_failures_and_resumes(tmp_path, capsys, population_stub, quick_report):  # noqa: F811
    manifest = make_cohort(tmp_path / "c")
    out = tmp_path / "out"
    args = ["cohort", str(manifest), "--out", str(out), "--threads", "--workers", "1", *FAST]
    assert main(args) == 0  # some jobs succeeded: exit 0, the failure listed
    captured = capsys.readouterr()
    assert captured.err == ""  # not a terminal: results on stdout, stderr only for errors
    lines = captured.out.splitlines()
    assert any(line.startswith("ok      S0/right") for line in lines)
    assert any(line.startswith("FAILED  S2/right") and "ReadError" in line for line in lines)
    assert "cohort: 3 jobs: 2 ok, 1 failed, 0 skipped" in captured.out
    assert "volume_ml is empty for 2 jobs (S0 right, S2 right)" in captured.out
    assert (out / "subjects" / "S1" / "left" / "model.npz").is_file()
    # resume: the finished jobs are skipped, the failed one is tried again
    assert main(args) == 0
    again = capsys.readouterr().out
    assert "skipping 2 of 3 jobs already done" in again and "fitting 1 job" in again
    assert "ok      S0/right" not in again and "FAILED  S2/right" in again


def test_every_job_failed_exits_1(tmp_path, capsys, population_stub):  # noqa: F811
    make_cohort(tmp_path / "c")
    m = tmp_path / "c" / "broken.csv"
    m.write_text("subject,side,volume_ml,path\nS2,right,,S2/ee.ply\nS2,right,,S2/ei.ply\n")
    assert main(["cohort", str(m), "--out", str(tmp_path / "o"), "--threads", *FAST]) == 1
    line = _one_error_line(capsys)
    assert line.startswith("error: all 1 jobs failed (first: S2/right: ReadError") and "ei.ply" in line
    assert population_stub == []  # nothing to summarise


def test_bad_manifest_exits_2_before_any_work(tmp_path, capsys):
    make_cohort(tmp_path / "c")
    m = tmp_path / "c" / "bad.csv"
    m.write_text("subject,side,volume_ml,path\nS0,right,,S0/ee.ply\nS0,right,,S0/gone.ply\n"
                 "S1,left,x,S1/ee.ply\nS1,left,2,S1/ei.ply\nS0,right,,S0/ee.ply\n")
    out = tmp_path / "o"
    assert main(["cohort", str(m), "--out", str(out), "--threads"]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(f"error: {m}: 3 problems in the cohort manifest: ")
    for fragment in ("row 3: path S0/gone.ply: no such file", "row 4: volume_ml 'x' is not a number",
                     "rows 2, 6: subject S0 side right: ee.ply listed twice"):
        assert fragment in line
    assert not out.exists()  # nothing was started or created


def test_wrong_columns_and_option_conflicts_exit_2(tmp_path, capsys):
    m = tmp_path / "m.csv"
    m.write_text("id,side,file\nA,left,a.ply\n")
    assert main(["cohort", str(m), "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert str(m) in line and "row 1" in line and "missing column(s) subject, volume_ml, path" in line
    manifest = make_cohort(tmp_path / "c")
    assert main(["cohort", str(manifest), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:1",
                 "--workers", "2"]) == 2
    assert "--workers sets the size of the local cluster" in _one_error_line(capsys)


@pytest.mark.slow
def test_default_local_cluster_of_processes(tmp_path, capsys):
    # the default path end to end: worker processes, the real report and population statistics
    make_cohort(tmp_path / "c")
    m = tmp_path / "c" / "one.csv"
    m.write_text("subject,side,volume_ml,path\nS0,right,,S0/ee.ply\nS0,right,,S0/ei.ply\n")
    out = tmp_path / "o"
    assert main(["cohort", str(m), "--out", str(out), "--workers", "1", *FAST]) == 0
    assert "cohort: 1 job: 1 ok, 0 failed" in capsys.readouterr().out
    summary = json.loads((out / "cohort.json").read_text())
    assert summary["processes"] is True and summary["scheduler"].startswith("tcp://127.0.0.1:")
    assert (out / "subjects" / "S0" / "right" / "report.html").stat().st_size > 10_000
    files = summary["population"]["files"]
    assert files and all(os.path.isfile(p) for p in files.values())


@pytest.mark.slow
def test_ctrl_c_keeps_what_finished_and_resumes(tmp_path, capsys, population_stub, quick_report):  # noqa: F811
    # a real Ctrl-C: SIGINT to the whole process group, as a terminal sends it, once one job is done
    manifest = make_cohort(tmp_path / "c", broken=None)
    out = tmp_path / "out"
    args = ["cohort", str(manifest), "--out", str(out), "--workers", "1", "--evaluations", "300", "--no-baselines"]
    proc = subprocess.Popen([sys.executable, "-m", "lungdeform", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not list((out / "subjects").glob("*/*/result.json")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    err = stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("interrupted: ") and "Run the same command again to resume" in err[0]
    summary = json.loads((out / "cohort.json").read_text())
    assert summary["interrupted"] and summary["jobs"]["not_run"] >= 1
    # whatever is visible under subjects/ is whole; an interrupted job left at most a hidden temp folder
    done = {p.parent.relative_to(out / "subjects").as_posix() for p in (out / "subjects").glob("*/*/result.json")}
    assert {p.relative_to(out / "subjects").as_posix() for p in (out / "subjects").glob("*/[!.]*")} == done
    # resume (in-process here, for speed): the finished jobs are skipped, the rest done, temp folders gone
    assert main([*args[:4], "--threads", *args[6:]]) == 0
    again = capsys.readouterr().out
    assert f"skipping {len(done)} of 3 jobs already done" in again and "cohort: 3 jobs: 3 ok" in again
    assert list((out / "subjects").glob("*/.*")) == []


@pytest.mark.slow
def test_bench_cohort_json(tmp_path):
    path = tmp_path / "bench.json"
    assert main(["bench", "cohort", "--subjects", "1", "--workers", "1", "--vertices", "300",
                 "--evaluations", "5", "--json", str(path)]) == 0
    doc = json.loads(path.read_text())
    rows = doc["results"]
    assert doc["benchmark"] == "cohort" and [(r["method"], r["workers"]) for r in rows] == [("serial", 1), ("dask", 1)]
    for r in rows:
        assert r["subjects"] == 1 and r["ok"] == 1 and r["seconds"] > 0, r["errors"]
        assert r["subjects_per_min"] == pytest.approx(60.0 / r["seconds"])
    assert rows[0]["ratio_to_serial"] == 1.0


@pytest.mark.realdata
@pytest.mark.slow
def test_cohort_on_the_real_itk_pair(tmp_path, capsys, data_dir, quick_report):  # noqa: F811
    # The only real two-volume lung in the data: the ITK right lung as masks, volumes left empty so
    # the runner measures them, with its 51 landmark pairs. Truth: the data README's volumes (3.36 L
    # and 3.97 L) and the landmarks' own motion (the no-motion error after alignment is ~11.3 mm, so a
    # fit that moves landmarks the right way must land below it).
    pair = data_dir / "itk-right-lung-two-volumes"
    manifest = tmp_path / "manifest.csv"
    manifest.write_text(
        "subject,side,volume_ml,path,landmarks\n"
        f"itk,right,,{pair / 'CT_3D_lung_fixed_mask.mha'},{pair / 'CT_3D_lung_fixed_point_set_corrected.txt'}\n"
        f"itk,right,,{pair / 'CT_3D_lung_moving_mask.mha'},{pair / 'CT_3D_lung_moving_point_set_corrected.txt'}\n")
    out = tmp_path / "out"
    assert main(["cohort", str(manifest), "--out", str(out), "--threads", "--workers", "1",
                 "--evaluations", "80", "--no-baselines"]) == 0
    result = json.loads((out / "subjects" / "itk" / "right" / "result.json").read_text())
    assert result["status"] == "ok", result["error"]
    assert result["volumes_ml"] == pytest.approx([3360.0, 3970.0], rel=0.02)
    assert len(result["constants"]) == 9 and all(map(lambda c: c == c, result["constants"]))
    # a short optimiser budget (80 evaluations) gives ~8 mm; no motion gives ~11.3 mm
    assert 0.0 < result["metrics"]["landmark_mean_mm"] < 10.0
    population = json.loads((out / "population.json").read_text())
    assert population["n_ok"] == 1 and population["n_failed"] == 0


def test_cohort_options_reach_every_job(tmp_path, monkeypatch):
    # the command's fit options become the jobs' FitOptions (part of their digest): defaults, then
    # --stiffness and --no-side-check (truth: the options object run_cohort receives)
    import lungdeform.cli.cohort as C  # the command calls the run_cohort it imported

    seen = []

    def capture(m, folder, *, options, **kw):
        seen.append(options)
        raise KeyboardInterrupt  # stop before any work: exit 130

    monkeypatch.setattr(C, "run_cohort", capture)
    manifest = make_cohort(tmp_path / "c")
    assert main(["cohort", str(manifest), "--out", str(tmp_path / "o")]) == 130
    assert main(["cohort", str(manifest), "--out", str(tmp_path / "o"), "--stiffness", "--no-side-check"]) == 130
    assert (seen[0].stiffness, seen[0].side_check) == (False, True)
    assert (seen[1].stiffness, seen[1].side_check) == (True, False)


@pytest.mark.slow
@pytest.mark.realdata
def test_cohort_on_one_dirlab_copd_case(data_dir, tmp_path, capsys):
    # One real COPDgene subject (case 1, both lungs in one mask per phase, each phase re-centred) through
    # the documented two commands: `validate copd --manifest-only`, then `cohort` with the experiment's
    # fit (--align joint --stiffness) at a small budget. Truth: the data README's volumes (both lungs:
    # expiration 2.0–4.0 L, inspiration 3.9–6.5 L, rounded: 5 % slack; case 1 measures 4.02 L at
    # expiration from the surfaces) from the measured volumes of the two jobs; every lung
    # fitted; one value per side for each of c1…c9 and Table I's value beside it; a time per lung.
    from lungdeform.cohort.population import CONSTANTS, table_i

    folder = data_dir / "dirlab-copd-lung-masks"
    if not folder.is_dir():
        pytest.skip(f"real data missing: {folder}")
    out = tmp_path / "out"
    assert main(["validate", "copd", "--data", str(folder), "--out", str(out), "--cases", "1", "--manifest-only"]) == 0
    capsys.readouterr()
    assert main(["cohort", str(out / "manifest.csv"), "--out", str(out / "cohort"), "--align", "joint", "--stiffness",
                 "--evaluations", "10", "--folds", "2", "--no-baselines", "--workers", "1", "--threads"]) == 0
    text = capsys.readouterr().out
    assert "cohort: 2 jobs: 2 ok, 0 failed" in text and "time per lung: median" in text
    results = {s: json.loads((out / "cohort" / "subjects" / "copd1" / s / "result.json").read_text())
               for s in ("left", "right")}
    assert all(r["status"] == "ok" for r in results.values()), [r["error"] for r in results.values()]
    exp_ml, insp_ml = (sum(r["volumes_ml"][k] for r in results.values()) for k in (0, -1))
    assert 0.95 * 2000 <= exp_ml <= 1.05 * 4000 and 0.95 * 3900 <= insp_ml <= 1.05 * 6500
    assert insp_ml > 1.2 * exp_ml
    pop = json.loads((out / "cohort" / "population.json").read_text())
    assert pop["n_ok"] == 2 and all(pop["overall"][c]["n"] == 2 for c in CONSTANTS)
    for side in ("left", "right"):
        rows = pop["table_i"][side]
        assert list(rows) == list(CONSTANTS)
        assert [rows[c]["paper"] for c in CONSTANTS] == pytest.approx(list(table_i(side)))
        assert all(rows[c]["n"] == 1 and rows[c]["in_range"] is not None for c in CONSTANTS)
    times = pop["time_per_lung"]
    assert times["n"] == 2 and all(p["seconds"] > 0 for p in times["per_lung"])
    assert times["median_s"] == pytest.approx(sum(r["seconds"] for r in results.values()) / 2)
    for name in ("constants_by_side", "constants_vs_volume", "fit_errors"):
        assert (out / "cohort" / "plots" / f"{name}.png").stat().st_size > 1000
