"""``lungdeform validate prediction``: the command parses, calls the library, prints the medians and
picks exit codes."""

import json

from lungdeform.cli.main import main
from tests.breathing.test_trace import write_marker_folder


def test_validate_prediction_prints_medians_and_writes_metrics(tmp_path, rng, capsys):
    out, data = tmp_path / "out", write_marker_folder(tmp_path / "data", rng)
    assert main(["validate", "prediction", "--data", str(data), "--out", str(out), "--horizons", "200,400"]) == 0
    text = capsys.readouterr().out
    assert "model/linear" in text and "400 ms" in text and "target quiet model/none" in text
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["horizons_ms"] == [200, 400] and doc["n_traces"] == 1


def test_bad_horizons_and_a_missing_folder_exit_2_with_one_line(tmp_path, rng, capsys):
    data = write_marker_folder(tmp_path / "data", rng)
    assert main(["validate", "prediction", "--data", str(data), "--out", str(tmp_path / "o"),
                 "--horizons", "400,abc"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--horizons" in err[0]
    assert main(["validate", "prediction", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing written on bad input
