"""CLI: ``lungdeform validate breathing``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lungdeform.cli.main import main
from tests.cli.test_breathe import _synthetic_trace
from tests.conftest import require_path

MODELS = {"model", "lujan", "fourier"}


def test_validate_breathing_schema(tmp_path, rng, capsys):
    data = tmp_path / "data"
    data.mkdir()
    _synthetic_trace(data / "a.csv", rng)
    _synthetic_trace(data / "b.csv", rng, period=3.5)
    (data / "short.csv").write_text("Frame;Timestamp;x;y;z\n0;0;1;2;3\n6;100;1;2;3\n")
    out = tmp_path / "out"
    assert main(["validate", "breathing", "--data", str(data), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["traces"]) == {"a.csv", "b.csv"} and "short.csv" in m["errors"]
    for r in m["traces"].values():
        # the schema, and the variants that explain it
        assert {"model_rms_percent", "lujan_rms_percent", "fourier_rms_percent"} <= set(r)
        for key in ("shared_shape", "shared_shape_no_drift", "anchored", "per_cycle_refit",
                    "percent_of_trace_range", "regular_cycles"):
            assert MODELS <= set(r[key]), key
        # truth: a regular synthetic breath with 0.05 mm noise on 12 mm: every model does well,
        # and the noise floor is what was injected (0.05/12 ≈ 0.4 %)
        assert r["model_rms_percent"] < 5.0 and 0.2 < r["noise_floor_percent"] < 0.8
    assert m["median_model_rms_percent"] == pytest.approx(
        np.median([r["model_rms_percent"] for r in m["traces"].values()]))
    assert m["paired_model_vs_lujan"]["traces"] == 2
    assert "median held-out RMS" in capsys.readouterr().out


def test_validate_breathing_bad_folders(tmp_path, capsys):
    assert main(["validate", "breathing", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no .vxp or .csv trace found" in err[0]
    missing = tmp_path / "nowhere"
    assert main(["validate", "breathing", "--data", str(missing), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0] and "not a folder" in err[0]
    assert not (tmp_path / "o" / "metrics.json").exists()


@pytest.mark.realdata
@pytest.mark.slow
def test_validate_breathing_real_traces(data_dir, tmp_path):
    # real data: the 16 shared traces (RPM + external markers), held-out cycles
    traces = require_path(data_dir, "breathing-traces")
    out = tmp_path / "val"
    assert main(["validate", "breathing", "--data", str(traces), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["traces"]) == 16 and not m["errors"]
    # The target (median < 5 %) is NOT met (measured ≈ 9 % of the breath amplitude; ≈ 4.8 % of
    # the whole held-out range): the held-out cycles vary more than any shared shape can follow (see the
    # report). What must hold under the same protocol and the same per-cycle freedom, per trace (a
    # paired comparison): the PV driver beats the Lujan shape on most traces, and never by chance alone.
    p = m["paired_model_vs_lujan"]
    assert p["traces_model_better"] >= 12 and p["median_difference_percent"] < 0
    # the variants order as their freedoms: anchored (0 fitted) > no drift (2) > drift (3) > refit (5)
    med = m["median_shared_shape"]["model"]
    assert m["median_anchored"]["model"] > m["median_shared_shape_no_drift"]["model"] > med
    assert m["median_per_cycle_refit"]["model"] < med
    # the white-noise floor is far below the error: noise does not limit it
    assert m["median_noise_floor_percent"] < 1.5
    # orientation: the three traces recorded upside down were turned (LT upper markers, RPM)
    turned = {k for k, r in m["traces"].items() if any("negated" in f for f in r["fixes"])}
    assert turned == {"201205101536-UAC-1-LT-142-6.csv", "201205101536-UCC-1-LT-142-6.csv",
                      "PT01_PT09-2_13112021.vxp"}
    for name, r in m["traces"].items():
        assert 0 < r["model_rms_percent"] < 50, name
