"""``lungdeform validate dirlab``: table on stdout, metrics.json, one-line errors."""

from __future__ import annotations

import json

import pytest

from lungdeform.cli import main as cli_main
from tests.conftest import require_path
from tests.test_dirlab import make_case_folder


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
    text = capsys.readouterr().out
    assert "one_scalar" in text and "metrics.json" in text and "direction constant" in text
    assert [p.name for p in out.iterdir()] == ["metrics.json"]  # written atomically, no temp file


@pytest.mark.parametrize(
    "prepare, message",
    [
        (lambda d: (d / "voxel_spacing.csv").unlink(), "no voxel_spacing.csv"),
        (lambda d: (d / "Case1Pack/Sampled4D/case1_4D-75_T10.txt").write_text("1 2\n"),
         r"case1_4D-75_T10\.txt, line 1: expected 3 numbers"),
        (lambda d: (d / "voxel_spacing.csv").write_text("case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,1,-1,1\n2,1,1,1\n"),
         "inconsistent spacing"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, rng, run, capsys, prepare, message):
    import re

    make_case_folder(tmp_path / "data", rng)
    prepare(tmp_path / "data")
    out = tmp_path / "out"
    assert run(["validate", "dirlab", "--data", str(tmp_path / "data"), "--out", str(out)]) == 2
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
