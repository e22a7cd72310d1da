"""CLI tests of ``lungdeform validate paper`` (the paper's Sec. IV-A validation)."""

from __future__ import annotations

import json

from lungdeform.cli.main import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_writes_metrics_and_figures(tmp_path, capsys):
    out = tmp_path / "paper" / "run"  # parents are created
    code = main(["validate", "paper", "--out", str(out), "--grid", "9", "--rings", "3"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    m = json.loads((out / "metrics.json").read_text())
    # the required keys, with values that say the paper's claims hold
    assert m["planar"]["rms_percent"] < 0.1  # paper: < 0.1 % RMS
    assert 0 < m["circular"]["stiff_to_soft_displacement_ratio"] < 1  # stiffer nodes move less
    assert m["circular"]["all_nodes_move_outward"] is True
    conv = m["convergence"]
    assert isinstance(conv["push_iterations"], int) and conv["push_iterations"] > 0
    assert isinstance(conv["msd_iterations"], int) and conv["msd_iterations"] > 0
    assert conv["tol"] == 1e-6 and "definition" in conv
    for name in m["figures"].values():
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000
    assert len(m["figures"]) == 3
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left behind
    assert "metrics.json" in captured.out and "RMS" in captured.out


def test_out_pointing_at_a_file_is_refused_in_one_line(tmp_path, capsys):
    target = tmp_path / "taken.txt"
    target.write_text("not a folder")
    code = main(["validate", "paper", "--out", str(target)])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(target) in lines[0] and "not a directory" in lines[0]
    assert target.read_text() == "not a folder"


def test_bad_grid_is_refused_in_one_line(tmp_path, capsys):
    code = main(["validate", "paper", "--out", str(tmp_path / "o"), "--grid", "2"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--grid" in err
    assert not (tmp_path / "o").exists()
