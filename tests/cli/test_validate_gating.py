"""``lungdeform validate gating``: the command parses, calls the library, prints the medians and picks
exit codes."""

import json

from lungdeform.cli.main import main
from tests.breathing.test_trace import write_marker_folder


def test_validate_gating_prints_every_strategy_and_writes_metrics(tmp_path, rng, capsys):
    out = tmp_path / "out"
    assert main(["validate", "gating", "--data", str(write_marker_folder(tmp_path / "data", rng)), "--out", str(out),
                 "--latency-ms", "200", "--window", "end-exhale:25", "--confident"]) == 0
    text = capsys.readouterr().out
    for k in ("none", "linear", "model", "model_intervals", "oracle", "beam-on error"):
        assert k in text
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["latency_ms"] == 200 and doc["window"] == "end-exhale:25" and doc["confident"] is True
    assert doc["summary"]["oracle"]["beam_on_error"] == 0.0  # the oracle is never on outside the window


def test_bad_options_exit_2_with_one_line_and_write_nothing(tmp_path, rng, capsys):
    data = write_marker_folder(tmp_path / "data", rng)
    for opts, word in ((["--window", "middle:30"], "--window"), (["--latency-ms", "0"], "--latency-ms"),
                       (["--coverage", "1.5"], "coverage"), (["--min-probability", "0"], "--min-probability")):
        assert main(["validate", "gating", "--data", str(data), "--out", str(tmp_path / "o"), *opts]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and word in err[0]
    assert main(["validate", "gating", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
