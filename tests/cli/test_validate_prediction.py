"""``lungdeform validate prediction``: the command parses, calls the library, prints the medians and
picks exit codes."""

import json

import numpy as np

from lungdeform.cli.main import main
from tests.breathing.test_trace import breath, write_marker_csv


def _data(tmp_path, rng):
    data = tmp_path / "data"
    data.mkdir()
    t = np.arange(0, 80, 0.1)
    write_marker_csv(data / "201201010000-LAC-1-N-80-6.csv", t * 1000, 8 * breath(t) + rng.normal(0, 0.1, t.size))
    return data


def test_validate_prediction_prints_medians_and_writes_metrics(tmp_path, rng, capsys):
    out = tmp_path / "out"
    assert main(["validate", "prediction", "--data", str(_data(tmp_path, rng)), "--out", str(out),
                 "--horizons", "200,400"]) == 0
    text = capsys.readouterr().out
    assert "model/linear" in text and "400 ms" in text and "target quiet model/none" in text
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["horizons_ms"] == [200, 400] and doc["n_traces"] == 1


def test_bad_horizons_and_a_missing_folder_exit_2_with_one_line(tmp_path, rng, capsys):
    data = _data(tmp_path, rng)
    assert main(["validate", "prediction", "--data", str(data), "--out", str(tmp_path / "o"),
                 "--horizons", "400,abc"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--horizons" in err[0]
    assert main(["validate", "prediction", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing written on bad input
