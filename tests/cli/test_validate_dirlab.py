"""``lungdeform validate dirlab``: table on stdout, metrics.json, one-line errors."""

from __future__ import annotations

import json

import pytest

from lungdeform.cli import main as cli_main
from tests.conftest import require_path
from tests.validate.test_dirlab import make_case_folder


@pytest.fixture
def run():
    """``main(argv)``: the real CLI, every command module loaded (a missing one must fail)."""
    return cli_main.main


def test_validate_dirlab_writes_metrics(tmp_path, rng, run, capsys):
    make_case_folder(tmp_path / "data", rng, motion="lag")
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(tmp_path / "data"), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert sorted(m["cases"]) == ["1", "2"]
    for c in m["cases"].values():
        for key in ("mean_displacement_300_mm", "one_scalar_mean_mm", "no_motion_mean_mm", "best_model",
                    "best_model_heldout_mean_mm"):
            assert key in c
        # the data were generated with per-landmark lag: one scalar beats no motion, lag beats one scalar
        assert c["one_scalar_mean_mm"] < c["no_motion_mean_mm"]
        assert c["heldout_mean_mm"]["lag_landmark"] < c["heldout_mean_mm"]["one_scalar"]
        assert c["best_model_heldout_mean_mm"] == min(c["heldout_mean_mm"].values())
        # the default model is chosen on the other case (two cases: its best), the best is a diagnostic
        assert c["default_model"] in c["heldout_mean_mm"] and c["best_model_diagnostic"] == c["best_model"]
    text = capsys.readouterr().out
    assert "default (other cases)" in text and "best (diagnostic)" in text
    assert "one_scalar" in text and "metrics.json" in text and "direction constant" in text
    assert [p.name for p in out.iterdir()] == ["metrics.json"]  # written atomically, no temp file


@pytest.mark.parametrize(
    "prepare, message, extra",
    [
        (lambda d: (d / "voxel_spacing.csv").unlink(), "case 1: no voxel_spacing.csv found", ["--no-published-spacing"]),
        (lambda d: (d / "Case1Pack/Sampled4D/case1_4D-75_T10.txt").write_text("1 2\n"),
         r"case1_4D-75_T10\.txt, line 1: expected 3 numbers", []),
        (lambda d: (d / "voxel_spacing.csv").write_text("case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,1,-1,1\n2,1,1,1\n"),
         "inconsistent spacing", []),
        (lambda d: (d / "case2/extremePhases/case2_dirLab300_T50_xyz.txt").write_bytes(b"\x00\xff\xfe 1 2 3\r\n"),
         r"case2_dirLab300_T50_xyz\.txt: not a text file", []),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, rng, run, capsys, prepare, message, extra):
    import re

    make_case_folder(tmp_path / "data", rng)
    prepare(tmp_path / "data")
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(tmp_path / "data"), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and re.search(message, err)
    assert not (out / "metrics.json").exists()


def test_missing_folder(tmp_path, run, capsys):
    assert run(["validate", "dirlab", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "nope: not a directory" in capsys.readouterr().err


@pytest.mark.realdata
def test_real_dirlab(data_dir, tmp_path, run):
    root = require_path(data_dir, "dirlab-4dct-landmarks")
    assert run(["validate", "dirlab", "--data", str(root), "--out", str(tmp_path)]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    published = {"1": 3.89, "2": 4.34, "3": 6.94, "4": 9.83, "5": 7.48}  # Castillo et al. 2009
    assert sorted(m["cases"]) == sorted(published)
    for case, c in m["cases"].items():
        assert c["mean_displacement_300_mm"] == pytest.approx(published[case], abs=0.01)
        assert c["one_scalar_mean_mm"] < c["no_motion_mean_mm"]


@pytest.mark.realdata
def test_real_cases_in_archive_layouts_run_with_notes(data_dir, tmp_path, run, capsys):
    """Real cases 1–5 copied (in tmp_path only) into the names/layouts of the archive's cases 6–10."""
    from tests.validate.test_dirlab import make_real_variant_layout

    root = tmp_path / "data"
    make_real_variant_layout(require_path(data_dir, "dirlab-4dct-landmarks"), root)
    # case 1 again, relabelled as case 6 (published spacing 0.97 mm, as case 1): its mean must be
    # reported against case 6's published 10.89 mm, as a note, not an error
    for p in sorted((root / "Case1Pack").rglob("*.txt")):
        dst = root / "Case6Pack" / p.parent.name / p.name.replace("case1_", "case6_")
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(p.read_bytes())
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(root), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert sorted(m["cases"], key=int) == ["1", "2", "3", "4", "5", "6"]
    for case, pub in {"1": 3.89, "2": 4.34, "3": 6.94, "4": 9.83}.items():
        assert m["cases"][case]["mean_displacement_300_mm"] == pytest.approx(pub, abs=0.01)
    assert m["cases"]["4"]["best_model"] is None  # 300 pairs only: models skipped, case kept
    assert m["cases"]["5"]["mean_displacement_300_mm"] is None and m["cases"]["5"]["best_model"]
    assert m["cases"]["6"]["published_300_mm"] == 10.89
    notes = "\n".join(m["notes"])
    assert "case 4: no 75-point files" in notes and "case 5: no 300-pair files" in notes
    assert "case5_4D-75_T60.txt" in notes
    assert "case 6: 300-pair mean 3.89 mm differs from the published 10.89 mm" in notes
    assert "note: case 4: no 75-point files" in text and "motion models skipped" in text


@pytest.mark.realdata
@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda r: (r / "Case2Deploy/ExtremePhases/CASE2_DIRLAB300_T50_XYZ.TXT").unlink(),
         r"case 2: 300-pair file for T50 missing beside .*CASE2_DIRLAB300_T00_XYZ\.TXT"),
        (lambda r: (r / "Case1Pack/Sampled4D/case1_4D-75_T30.txt").unlink(),
         r"case 1: 75-point files missing phase\(s\) T30 beside .*case1_4D-75_T"),
        (lambda r: (r / "voxel_spacing.csv").write_text(
            "case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,0.97,0.97,2.5\n2,1.16,1.16,2.5\n"),
         r"case 3: no row in .*voxel_spacing\.csv for its landmark files \(e\.g\. .*case3_.*\.txt\)"),
        (lambda r: (r / "Case3Pack/Sampled4D/case3_4D-75_T20.txt").write_text("12 13 14\nx 1 2\n"),
         r"case3_4D-75_T20\.txt, line 2: not a number"),
    ],
)
def test_real_variant_layout_errors_are_one_line(data_dir, tmp_path, run, capsys, mutate, pattern):
    import re

    from tests.validate.test_dirlab import make_real_variant_layout

    root = tmp_path / "data"
    make_real_variant_layout(require_path(data_dir, "dirlab-4dct-landmarks"), root)
    mutate(root)
    # strict spacing: a case the table does not list is an error, not a fall-back on the published table
    argv = ["validate", "dirlab", "--data", str(root), "--out", str(tmp_path / "out"), "--no-published-spacing"]
    assert run(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and re.search(pattern, err), err
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_archive_layout_cases_1_to_10(tmp_path, rng, run, capsys):
    """Synthetic files for cases 1–10 in the archives' layouts; voxel_spacing.csv lists 1–5 only."""
    from tests.validate.test_dirlab import ARCHIVE_LAYOUT, make_archive_1_10

    data = tmp_path / "data"
    truth = make_archive_1_10(data, rng)
    ext = data / "Case7Pack/extremePhases"
    for ph in ("00", "50"):  # case 11 is no DIR-Lab case: no published spacing, so it is skipped
        (ext / f"case7_dirLab300_T{ph}_xyz.txt").rename(data / f"case11_dirLab300_T{ph}_xyz.txt")
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(data), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    m = json.loads((out / "metrics.json").read_text())
    assert sorted(m["cases"], key=int) == [str(c) for c in (1, 2, 3, 4, 5, 6, 8, 9, 10)]
    for case, c in m["cases"].items():
        # truth: the generated pairs' mean in mm, whatever the folder/file spelling and text style
        assert c["mean_displacement_300_mm"] == pytest.approx(truth[int(case)])
        assert (c["best_model"] is None) == (ARCHIVE_LAYOUT[int(case)][1] is None)
        assert c["spacing_source"].endswith("voxel_spacing.csv") == (int(case) <= 5)
    assert m["cases"]["10"]["published_300_mm"] == 7.30 and m["cases"]["10"]["spacing_mm"] == [0.97, 0.97, 2.5]
    assert m["skipped"]["11"].startswith("case 11: skipped: no row in")
    notes = "\n".join(m["notes"])
    assert "case 8: no row in" in notes and "used the published DIR-Lab spacing [0.97, 0.97, 2.5] mm" in notes
    assert "case 9: no 75-point files" in notes
    assert "  11   (skipped: no row in" in captured.out and "motion models skipped" in captured.out
    assert captured.err == ""
    # strict spacing: the first case without a row is a one-line error naming the table
    argv = ["validate", "dirlab", "--data", str(data), "--out", str(tmp_path / "strict"), "--no-published-spacing"]
    assert run(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "case 6: no row in" in err and "voxel_spacing.csv" in err
    assert not (tmp_path / "strict" / "metrics.json").exists()


def test_data_folder_is_one_case_folder(tmp_path, rng, run, capsys):
    from tests.validate.test_dirlab import make_archive_1_10

    truth = make_archive_1_10(tmp_path / "data", rng, spacing_rows=range(1, 11))
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(tmp_path / "data" / "Case8Deploy"), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["cases"]) == ["8"] and m["cases"]["8"]["mean_displacement_300_mm"] == pytest.approx(truth[8])
    assert "voxel spacing from" in capsys.readouterr().out
