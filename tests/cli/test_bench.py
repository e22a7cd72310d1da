"""``lungdeform bench``: the JSON schema the issue asks for (a smoke run, no timing assertions)."""

import json

from lungdeform.cli.main import main


def test_bench_solve_and_playback_json(tmp_path):
    for kind, methods in (("solve", {"sparse", "push"}), ("playback", {"playback", "memcpy"})):
        out = tmp_path / f"{kind}.json"
        args = ["bench", kind, "--vertices", "2000", "--json", str(out)]
        if kind == "playback":
            args += ["--frames", "5"]
        assert main(args) == 0
        doc = json.loads(out.read_text())
        rows = doc["results"]
        assert {r["method"] for r in rows} == methods
        for r in rows:
            assert r["vertices"] > 1000 and r["seconds"] > 0
        if kind == "solve":
            push = next(r for r in rows if r["method"] == "push")
            assert push["max_relative_difference_to_sparse"] < 1e-6


def test_bench_refuses_tiny_sizes(tmp_path, capsys):
    assert main(["bench", "solve", "--vertices", "5"]) == 2
    assert "--vertices" in capsys.readouterr().err


def test_bench_cohort_refuses_bad_counts(capsys):
    # argument checks come before any cohort is built; the message names the flag
    assert main(["bench", "cohort", "--subjects", "0"]) == 2
    assert "--subjects must be at least 1, got 0" in capsys.readouterr().err
    assert main(["bench", "cohort", "--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err


def test_bench_predict_reports_the_ratio_to_the_linear_baseline(tmp_path, capsys):
    # one short stream: each predictor's line, and the JSON records with the same-run yardstick
    import json

    path = tmp_path / "p.json"
    assert main(["bench", "predict", "--seconds", "45", "--rate-hz", "10", "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert "the linear baseline" in out and "model:" in out
    doc = json.loads(path.read_text())
    assert doc["benchmark"] == "predict" and [r["method"] for r in doc["results"]] == ["model", "model_intervals", "gate", "linear", "none"]


def test_bench_dvf_small_grid(tmp_path, capsys):
    # a small grid: the command times both and reports their ratio and the field's Jacobian
    out = tmp_path / "b.json"
    assert main(["bench", "dvf", "--shape", "40,64,64", "--repeats", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())["results"][0]
    assert r["shape_zyx"] == [40, 64, 64] and r["ratio"] > 0 and r["jacobian_min"] > 0
    # the CPU seconds beside the wall ones: the ratio is theirs
    assert r["cpu_ratio"] == r["field_cpu_seconds"] / r["resample_cpu_seconds"] and r["field_cpu_seconds"] > 0
    printed = capsys.readouterr().out
    assert "ratio" in printed and "CPU seconds" in printed
    # the threads of each, so that the comparison's fairness can be read off the output
    assert f"({r['field_threads']} threads;" in printed and f"({r['threads']} threads)" in printed
