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
    for k in ("none", "linear", "linear_plain", "model", "model_intervals", "linear_intervals", "oracle",
              "beam-on error", "hindsight ranking, not a gate"):
        assert k in text
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["latency_ms"] == 200 and doc["window"] == "end-exhale:25" and doc["confident"] is True
    assert doc["summary"]["oracle"]["beam_on_error"] == 0.0  # the oracle is never on outside the window


def test_bad_options_exit_2_with_one_line_and_write_nothing(tmp_path, rng, capsys):
    data = write_marker_folder(tmp_path / "data", rng)
    for opts, word in ((["--window", "middle:30"], "--window"), (["--latency-ms", "0"], "--latency-ms"),
                       (["--coverage", "1.5"], "coverage"), (["--min-probability", "0"], "--min-probability"),
                       (["--target-error", "1"], "--target-error")):
        assert main(["validate", "gating", "--data", str(data), "--out", str(tmp_path / "o"), *opts]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and word in err[0]
    assert main(["validate", "gating", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_target_error_is_the_default_rule_and_min_probability_fixes_the_threshold(tmp_path, rng, capsys):
    # the adaptive threshold (tolerated beam-on error 0.05) is the default; --min-probability P turns it
    # into the fixed gate "window probability >= P", and metrics.json says which rule ran
    data = write_marker_folder(tmp_path / "data", rng)
    assert main(["validate", "gating", "--data", str(data), "--out", str(tmp_path / "a"), "--target-error", "0.1"]) == 0
    assert main(["validate", "gating", "--data", str(data), "--out", str(tmp_path / "b"), "--min-probability", "0.6"]) == 0
    capsys.readouterr()
    a, b = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in "ab")
    assert a["target_error"] == 0.1 and "adapted online to a beam-on error of 0.1" in a["protocol"]
    assert b["target_error"] is None and b["min_probability"] == 0.6 and ">= 0.6" in b["protocol"]
