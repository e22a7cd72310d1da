"""``lungdeform validate copd``: the per-lung table on a two-lung phantom; bad input exits 2."""

import json

import pytest

from lungdeform.cli.main import main
from tests.validate.test_copd import phantom_case


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    return err[0]


def test_bad_cases_and_missing_case_exit_2(tmp_path, capsys):
    # truth: --cases must be numbers; a case asked for must have its four files; nothing is written
    (tmp_path / "data").mkdir()
    out = tmp_path / "out"
    assert main(["validate", "copd", "--data", str(tmp_path / "data"), "--out", str(out), "--cases", "x"]) == 2
    assert "cases must be case numbers" in _one_error_line(capsys)
    assert main(["validate", "copd", "--data", str(tmp_path / "data"), "--out", str(out), "--cases", "2"]) == 2
    assert "case 2 is missing copd2_exp_mask.nii.gz" in _one_error_line(capsys)
    assert not (out / "metrics.json").exists()


@pytest.mark.slow
def test_validate_copd_prints_table_and_resumes(tmp_path, capsys):
    # truth: both lungs of the phantom case fitted (a tiny budget), one table line per lung and the
    # medians; a second run fits nothing (the settings digest matches)
    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=3)
    args = ["validate", "copd", "--data", str(data), "--out", str(tmp_path / "out"), "--evaluations", "2"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "copd3 left" in text and "copd3 right" in text and "median (2)" in text
    assert "fitted 2 lung(s) this run" in text
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert set(m["cases"]["copd3"]) == {"left", "right"} and m["summary"]["n_lungs"] == 2
    assert main(args) == 0
    assert "fitted 0 lung(s) this run (all resumed)" in capsys.readouterr().out


def test_manifest_only_writes_the_cohort_manifest_and_fits_nothing(tmp_path, capsys):
    # truth: OUT/manifest.csv lists the two phases of each case asked for (header + 2 rows), the printed
    # command is the cohort run with the experiment's fit (joint translation, stiffness); no fit runs, so
    # no metrics.json; a data folder without the case exits 2 and leaves no output folder
    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=2)
    out = tmp_path / "out"
    assert main(["validate", "copd", "--data", str(data), "--out", str(out), "--manifest-only", "--cases", "2"]) == 0
    text = capsys.readouterr().out
    rows = (out / "manifest.csv").read_text(encoding="utf-8").splitlines()
    assert rows[0] == "subject,side,volume_ml,path,landmarks" and len(rows) == 3
    assert rows[1].startswith("copd2,both,,") and "copd2_exp_mask.nii.gz" in rows[1] and "copd2_insp" in rows[2]
    assert f"fit with: lungdeform cohort {out / 'manifest.csv'} --out {out / 'cohort'} --align joint --stiffness" in text
    assert not (out / "metrics.json").exists()
    assert main(["validate", "copd", "--data", str(data), "--out", str(tmp_path / "o2"), "--manifest-only",
                 "--cases", "5"]) == 2
    assert "case 5 is missing" in _one_error_line(capsys) and not (tmp_path / "o2").exists()


def test_inputs_checked_before_out_and_a_skipped_case_is_said(tmp_path, capsys):
    # why: validate copd created --out before it looked at --data (an empty folder left behind),
    # and --manifest-only dropped a case missing one of its four files without a word
    (tmp_path / "data").mkdir()
    out = tmp_path / "out"
    assert main(["validate", "copd", "--data", str(tmp_path / "data"), "--out", str(out)]) == 2
    assert "no DIR-Lab COPDgene case" in _one_error_line(capsys) and not out.exists()
    data = phantom_case(tmp_path / "data", n=2)
    phantom_case(tmp_path / "data", n=4)
    (data / "copd4_insp_landmarks.txt").unlink()
    assert main(["validate", "copd", "--data", str(data), "--out", str(tmp_path / "fit"), "--cases", "2,4"]) == 2
    assert "case 4 is missing copd4_insp_landmarks.txt" in _one_error_line(capsys)
    # the manifest takes any two-volume subject, landmarks optional: copd4 is kept, without landmarks, and said
    assert main(["validate", "copd", "--data", str(data), "--out", str(out), "--manifest-only"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"warning: {data}: copd4: lacks copd4_insp_landmarks.txt (its landmarks are not used)"], err
    rows = [r.split(",") for r in (out / "manifest.csv").read_text().splitlines()[1:]]
    assert [r[0] for r in rows] == ["copd2", "copd2", "copd4", "copd4"]
    assert rows[0][4].endswith("copd2_exp_landmarks.txt") and rows[2][4] == rows[3][4] == ""
    assert main(["validate", "copd", "--data", str(data), "--out", str(data), "--manifest-only"]) == 2
    assert "would overwrite the input" in _one_error_line(capsys)


@pytest.mark.parametrize("damage, message", [
    ("landmarks", "landmark"),  # the inspiration file holds one row fewer
    ("nan", "non-finite"),  # a NaN landmark
])
def test_a_refused_case_leaves_no_folder(tmp_path, capsys, damage, message):
    # issue 36: a refused run left an empty case folder OUT/copdN in --out (and --out itself). Truth:
    # after the refusal (exit 2, one line) --out does not exist, as before the run
    from lungdeform.io.landmarks import read_elastix_points, write_elastix_points

    (tmp_path / "data").mkdir()
    data = phantom_case(tmp_path / "data", n=3)
    insp = data / "copd3_insp_landmarks.txt"
    pts = read_elastix_points(insp)
    if damage == "landmarks":
        write_elastix_points(insp, pts[:-1])
    else:
        lines = insp.read_text().splitlines()
        lines[3] = "nan " + " ".join(lines[3].split()[1:])  # the second point's x
        insp.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["validate", "copd", "--data", str(data), "--out", str(out), "--evaluations", "2"]) == 2
    assert message in _one_error_line(capsys).lower()
    assert not out.exists()
