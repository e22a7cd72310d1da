"""``lungdeform synth-cohort``: files, truth and bad input through the real command line."""

import csv
import json

import numpy as np
import pytest

from lungdeform.cli.main import main


def test_synth_cohort_writes_manifest_and_truth(tmp_path, capsys):
    out = tmp_path / "cohort"
    rc = main(["synth-cohort", "--out", str(out), "--subjects", "1", "--noise-mm", "0.4", "--seed", "9",
               "--volumes", "150,250", "--landmarks", "10"])
    assert rc == 0
    text = capsys.readouterr().out
    assert str(out / "manifest.csv") in text and str(out / "truth.json") in text
    # the files are in one frame: the hint names the alignment that keeps them there
    assert "--align none" in text
    with open(out / "manifest.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["subject"], r["side"]) for r in rows] == [("synth000", "left")] * 3 + [("synth000", "right")] * 3
    truth = json.loads((out / "truth.json").read_text())
    assert truth["noise_mm"] == 0.4 and truth["delta_ml"] == [150.0, 250.0] and truth["seed"] == 9
    for lung in truth["lungs"]:
        vols = [float(r["volume_ml"]) for r in rows if r["side"] == lung["side"]]
        # the manifest's volumes are V_EE, V_EE + 150, V_EE + 250 (exact law: also the enclosed volumes)
        assert vols == pytest.approx([lung["volume_ee_ml"], lung["volume_ee_ml"] + 150, lung["volume_ee_ml"] + 250])
        assert lung["enclosed_volumes_ml"] == pytest.approx(vols[1:], rel=1e-9)
        assert lung["licence"] in ("CC BY 4.0", "Apache-2.0")
        # noise SD per surface within 5 standard errors (σ/√(2n), n ≈ 3000) of the request
        assert np.array(lung["noise_sd_measured_mm"]) == pytest.approx(0.4, abs=5 * 0.4 / np.sqrt(6000))
    for r in rows:
        assert (out / r["path"]).is_file() and (out / r["landmarks"]).is_file()
    # same seed, same cohort
    again = tmp_path / "again"
    assert main(["synth-cohort", "--out", str(again), "--subjects", "1", "--noise-mm", "0.4", "--seed", "9",
                 "--volumes", "150,250", "--landmarks", "10"]) == 0
    assert json.loads((again / "truth.json").read_text())["lungs"][0]["constants"] == truth["lungs"][0]["constants"]


@pytest.mark.parametrize("args, expected", [
    (["--volumes", "300,abc"], "--volumes"),
    (["--volumes", "300,200"], "increasing"),
    (["--noise-mm", "-1"], "noise"),
    (["--subjects", "0"], "subjects"),
    (["--law", "cubic"], "law"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, args, expected):
    rc = main(["synth-cohort", "--out", str(tmp_path / "o"), "--subjects", "1"] + args)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and err.startswith("error:") and expected in err
    assert not (tmp_path / "o").exists()  # refused before anything is written


def test_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["synth-cohort", "--out", str(f)]) == 2
    assert str(f) in capsys.readouterr().err


def test_hint_is_a_command_that_survives_spaces(tmp_path, capsys):
    # a folder with a space: the printed hint used to split into two arguments when pasted
    import shlex

    out = tmp_path / "my cohort ü"
    assert main(["synth-cohort", "--out", str(out), "--subjects", "1", "--volumes", "200"]) == 0
    hint = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fit with: "))
    argv = shlex.split(hint[len("fit with: "):].split(" (")[0])
    assert argv[:3] == ["lungdeform", "cohort", str(out / "manifest.csv")]
