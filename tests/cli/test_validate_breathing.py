"""CLI: ``lungdeform validate breathing``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lungdeform.cli.main import main
from tests.cli.test_breathe import _synthetic_trace

MODELS = {"model", "lujan", "fourier"}


def test_validate_breathing_schema(tmp_path, rng, capsys):
    data = tmp_path / "data"
    data.mkdir()
    _synthetic_trace(data / "a.csv", rng)
    _synthetic_trace(data / "b.csv", rng, period=3.5)
    (data / "short.csv").write_text("Frame;Timestamp;x;y;z\n0;0;1;2;3\n6;100;1;2;3\n")
    out = tmp_path / "out"
    # the target is met on regular synthetic breaths, so --strict exits 0 too
    assert main(["validate", "breathing", "--data", str(data), "--out", str(out), "--strict"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["traces"]) == {"a.csv", "b.csv"} and "short.csv" in m["errors"]
    for r in m["traces"].values():
        # the schema, and the variants that explain it
        assert {"model_rms_percent", "lujan_rms_percent", "fourier_insample_rms_percent"} <= set(r)
        for key in ("shared_shape", "shared_shape_no_drift", "anchored", "per_cycle_refit_insample",
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
def test_validate_breathing_real_traces(traces_validated):
    # real data: the 16 shared traces (RPM + external markers), held-out cycles (the run is shared
    # with tests/test_docs_figures.py, which checks docs/METHOD_NOTES.md's table against it)
    # --strict: the median target (< 5 %) is not met on the real traces, so exit code 3, with every
    # output written first
    code, m, _ = traces_validated("lungdeform validate breathing --data DATA --out OUT", "--strict")
    assert code == 3
    assert not m["median_model_rms_percent"] < m["target_median_model_rms_percent"]
    assert len(m["traces"]) == 16 and not m["errors"]
    # The target (median < 5 %) is NOT met (measured 8.9 % of the breath amplitude, 4.5 % of
    # the whole held-out range, with everything that feeds a fit taken from the training part; 9.1 %
    # and 4.8 % in 0.7, whose cycles were found on the whole trace): the held-out cycles vary more than
    # any shared shape can follow (see the report). What must hold under the same protocol and the
    # same per-cycle freedom, per trace (a paired comparison): the PV driver beats the Lujan shape on
    # most traces (14 of 16 measured), and never by chance alone.
    p = m["paired_model_vs_lujan"]
    assert p["traces_model_better"] >= 12 and p["median_difference_percent"] < 0
    # the variants order as their freedoms: anchored (0 fitted) > no drift (2) > drift (3) > refit (5)
    med = m["median_shared_shape"]["model"]
    assert m["median_anchored"]["model"] > m["median_shared_shape_no_drift"]["model"] > med
    assert m["in_sample"]["median_per_cycle_refit_insample"]["model"] < med
    # the white-noise floor is far below the error: noise does not limit it
    assert m["median_noise_floor_percent"] < 1.5
    # orientation: the three traces recorded upside down were turned (LT upper markers, RPM)
    turned = {k for k, r in m["traces"].items() if any("negated" in f for f in r["fixes"])}
    assert turned == {"201205101536-UAC-1-LT-142-6.csv", "201205101536-UCC-1-LT-142-6.csv",
                      "PT01_PT09-2_13112021.vxp"}
    for name, r in m["traces"].items():
        assert 0 < r["model_rms_percent"] < 50, name


def test_validate_breathing_finds_variants_recursively(tmp_path, rng, capsys):
    """Traces under sub-folders, upper-case extensions, a repeated file name, a VXP 1.7 without
    marks, a BOM/dot-decimal CSV, plus files that must each be skipped with one line."""
    from tests.breathing.test_trace import breath, write_vxp

    data = tmp_path / "data"
    (data / "rpm" / "s1").mkdir(parents=True)
    (data / "rpm" / "s2").mkdir(parents=True)
    (data / "markers").mkdir()
    t = np.arange(0, 64, 0.04)
    for k, sub in enumerate(("s1", "s2")):  # same name, two sessions
        f = write_vxp(data / "rpm" / sub / "PT.VXP", 5e4 + t * 1000, 0.4 * breath(t, 4.0 + 0.3 * k) +
                      rng.normal(0, 0.002, t.size), [""] * t.size)
        f.write_text(f.read_text().replace("Version=1.6", "Version=1.7\nNew_key=x"))
    m1 = _synthetic_trace(data / "markers" / "201205101541-ABC-1-Q-64-6.CSV", rng)
    m1.write_bytes(b"\xef\xbb\xbf" + m1.read_text().replace(",", ".").encode())
    (data / "markers" / "._201205101541-ABC-1-Q-64-6.CSV").write_bytes(b"\x00\x05\x16\x07Mac OS X")  # resource fork
    (data / "markers" / "empty.csv").write_text("")
    (data / "markers" / "header_only.csv").write_text('"Frame";"Timestamp";"x";"y";"z"\n')
    _synthetic_trace(data / "markers" / "one_breath.csv", rng, seconds=5.0)
    out = tmp_path / "out"
    assert main(["validate", "breathing", "--data", str(data), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    # truth: the three good traces are all scored, the repeated name kept apart by its folder
    assert set(m["traces"]) == {"rpm/s1/PT.VXP", "rpm/s2/PT.VXP", "201205101541-ABC-1-Q-64-6.CSV"}
    assert set(m["errors"]) == {"empty.csv", "header_only.csv", "one_breath.csv"}
    assert "file is empty" in m["errors"]["empty.csv"]
    # a 5 s trace split in time: its training half is too short to hold a breath, and says so
    assert "training part (0.0–2.4 s)" in m["errors"]["one_breath.csv"]
    assert "too short to hold one breathing cycle" in m["errors"]["one_breath.csv"]
    for r in m["traces"].values():
        assert r["model_rms_percent"] < 5.0  # regular synthetic breaths: every trace fits well
    err = capsys.readouterr().err
    skipped = [ln for ln in err.splitlines() if ln.startswith("skipped ")]
    assert len(skipped) == 3 and all(n in err for n in ("empty.csv", "header_only.csv", "one_breath.csv"))


def test_validate_breathing_nothing_usable_is_one_line(tmp_path, capsys):
    data = tmp_path / "data"
    data.mkdir()
    (data / "empty.VXP").write_text("")
    (data / "header.csv").write_text("Frame;Timestamp;x;y;z\r\n0;0;0;0;0\r\n")
    assert main(["validate", "breathing", "--data", str(data), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "no trace could be scored (2 failed" in err[0]
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_validate_breathing_all_scores_nan(tmp_path, rng, capsys, monkeypatch):
    # every score undefined (NaN: e.g. no regular held-out cycle to score): the medians are null in
    # metrics.json and "n/a" in the summary, never a TypeError from formatting None
    import lungdeform.breathing.holdout as holdout

    real = holdout.evaluate

    def nan_scores(*args, **kwargs):
        r = real(*args, **kwargs)
        for key in ("model_rms_percent", "lujan_rms_percent", "fourier_insample_rms_percent", "noise_floor_percent"):
            r[key] = float("nan")
        for key in ("shared_shape", "shared_shape_no_drift", "anchored", "per_cycle_refit_insample",
                    "percent_of_trace_range", "regular_cycles"):
            r[key].update({m: float("nan") for m in holdout.MODELS})
        return r

    monkeypatch.setattr(holdout, "evaluate", nan_scores)
    data = tmp_path / "data"
    data.mkdir()
    _synthetic_trace(data / "a.csv", rng)
    out = tmp_path / "out"
    assert main(["validate", "breathing", "--data", str(data), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["median_model_rms_percent"] is None and m["median_noise_floor_percent"] is None
    assert all(v is None for v in m["median_anchored"].values())
    text = capsys.readouterr().out
    assert "median held-out RMS: PV n/a %, Lujan n/a %, Fourier n/a %" in text
    assert "white-noise floor n/a %" in text


def test_validate_breathing_tidal_ml_and_its_old_name(tmp_path, capsys):
    # --tidal-ml as in breathe, build, export and track; --tidal-volume-ml is kept, hidden, and
    # the two together are refused before any work (nothing written)
    (tmp_path / "data").mkdir()
    assert main(["validate", "breathing", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "out"),
                 "--tidal-ml", "600", "--tidal-volume-ml", "600"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: --tidal-volume-ml is the old name of --tidal-ml: give one of them"]
    assert not (tmp_path / "out").exists()
    assert main(["validate", "breathing", "--help"]) == 0
    shown = capsys.readouterr().out
    assert "--tidal-ml" in shown and "--tidal-volume-ml" not in shown
