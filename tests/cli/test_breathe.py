"""CLI: ``lungdeform breathe`` (``validate breathing``: tests/cli/test_validate_breathing.py)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from lungdeform.cli.main import main
from tests.breathing.test_trace import breath, write_marker_csv


def _synthetic_trace(path, rng, seconds=64.0, period=4.0):
    t = np.arange(0.0, seconds, 0.1)
    s = 12.0 * breath(t, period) + rng.normal(0, 0.05, t.size)
    return write_marker_csv(path, t * 1000, s)


def test_breathe_preset_writes_outputs(tmp_path, capsys):
    out = tmp_path / "normal"
    assert main(["breathe", "--preset", "normal", "--out", str(out), "--cycles", "2", "--fs", "25"]) == 0
    for name in ("curve.csv", "metrics.json", "volume.png", "pv_loop.png", "residuals.png"):
        assert (out / name).stat().st_size > 0, name
    with open(out / "curve.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t_s", "volume_ml", "flow_ml_s", "pressure_cmH2O"]
    vol = np.array([float(r[1]) for r in rows[1:]])
    assert np.ptp(vol) == pytest.approx(500.0, rel=0.01)  # the preset's tidal volume
    m = json.loads((out / "metrics.json").read_text())
    assert m["preset"]["name"] == "normal" and m["integrator_vs_periodic_max_abs_ml"] < 0.1
    assert not list(out.glob(".*tmp"))  # atomic writes leave no temporaries
    assert "wrote" in capsys.readouterr().out


def test_breathe_fit_writes_outputs(tmp_path, rng, capsys):
    trace = _synthetic_trace(tmp_path / "synthetic.csv", rng)
    out = tmp_path / "fit"
    assert main(["breathe", "--fit", str(trace), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    # truth: a perfectly regular synthetic breath; every model must do well on held-out cycles
    assert m["model_rms_percent"] < 5.0
    assert m["cycles_held_out"] >= 3
    assert m["stream"]["latency_per_sample_us_median"] > 0
    for name in ("curve.csv", "volume.png", "pv_loop.png", "residuals.png"):
        assert (out / name).stat().st_size > 0
    assert "held-out RMS" in capsys.readouterr().out


def test_breathe_bad_file_exit_2(tmp_path, capsys):
    bad = tmp_path / "broken.csv"
    bad.write_text("Frame;Timestamp;x;y;z\n0;0;1;2;3\n1;100;oops;2;3\n")
    assert main(["breathe", "--fit", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.csv" in err[0] and "line 3" in err[0]
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_breathe_needs_one_source(tmp_path, capsys):
    assert main(["breathe", "--out", str(tmp_path)]) == 2
    assert "exactly one of --preset" in capsys.readouterr().err
    assert main(["breathe", "--preset", "zz", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown breathing preset 'zz'" in err[0]


@pytest.mark.parametrize("cycles, message", [("0", "--cycles must be >= 1"), ("1000000", "--cycles must be at most 100")])
def test_breathe_cycles_out_of_range(tmp_path, capsys, cycles, message):
    # a million breaths ran for hours (killed after 300 s) without a word: refused at once, nothing written
    assert main(["breathe", "--preset", "normal", "--cycles", cycles, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "o").exists()


def test_breathe_preset_numbers_do_not_depend_on_fs(tmp_path, capsys):
    # truth: the preset's own tidal volume (500 mL). Measured on the output samples, 2 Hz (8 samples
    # per 4 s breath) used to report about 410 mL; the summary now comes from a fine run
    m = {}
    for fs in ("2", "50"):
        assert main(["breathe", "--preset", "normal", "--out", str(tmp_path / fs), "--fs", fs]) == 0
        m[fs] = json.loads((tmp_path / fs / "metrics.json").read_text())
    assert m["2"]["tidal_volume_ml"] == pytest.approx(500.0, rel=1e-3)
    assert m["2"]["tidal_volume_ml"] == pytest.approx(m["50"]["tidal_volume_ml"], rel=1e-6)
    assert m["2"]["peak_flow_ml_s"] == pytest.approx(m["50"]["peak_flow_ml_s"], rel=1e-6)
    capsys.readouterr()
    # fewer than 8 samples per breath: refused in one line naming the option
    assert main(["breathe", "--preset", "normal", "--out", str(tmp_path / "low"), "--fs", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fs 1 Hz gives 4 samples per 4 s breath" in err[0]
    assert not (tmp_path / "low").exists()


def test_breathe_deep_preset_is_not_negative_air_trapping(tmp_path, capsys):
    # the deep preset exhales actively below the relaxation volume: that is not "air trapping -1452 mL"
    assert main(["breathe", "--preset", "deep", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["end_expiratory_above_relaxation_ml"] < -100.0 and m["air_trapping_ml"] == 0.0
    assert "active expiration to" in out and "air trapping -" not in out


def test_breathe_fit_progress_only_when_verbose(tmp_path, rng, capsys):
    # stderr is not a terminal under pytest: without --verbose only the notes (what the reader fixed)
    trace = _synthetic_trace(tmp_path / "synthetic.csv", rng)
    assert main(["breathe", "--fit", str(trace), "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "fits on" not in err and all(ln.startswith("note: ") for ln in err.strip().splitlines())
    assert main(["--verbose", "breathe", "--fit", str(trace), "--out", str(tmp_path / "b")]) == 0
    assert "fits on" in capsys.readouterr().err


def test_breathe_tidal_ml_and_its_old_name(tmp_path, rng, capsys):
    # --tidal-ml, as in build, export and track; the old --tidal-volume-ml still works (hidden from
    # the help, a note on stderr) and calibrates the same (truth: metrics.json records the volume used)
    trace = _synthetic_trace(tmp_path / "synthetic.csv", rng)
    for option, out in (("--tidal-ml", "new"), ("--tidal-volume-ml", "old")):
        assert main(["breathe", "--fit", str(trace), "--out", str(tmp_path / out), option, "600"]) == 0
        assert json.loads((tmp_path / out / "metrics.json").read_text())["tidal_volume_ml"] == 600.0
    err = capsys.readouterr().err
    assert err.count("note: --tidal-volume-ml is now --tidal-ml (the old name still works)") == 1
    assert main(["breathe", "--fit", str(trace), "--out", str(tmp_path / "both"), "--tidal-ml", "600",
                 "--tidal-volume-ml", "600"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: --tidal-volume-ml is the old name of --tidal-ml: give one of them"]
    # a preset has its own tidal volume: the option used to be ignored there without a word
    assert main(["breathe", "--preset", "normal", "--out", str(tmp_path / "p"), "--tidal-ml", "600"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: --tidal-ml applies to --fit (the calibration); a --preset has its own tidal volume"]
    assert not (tmp_path / "p").exists() and not (tmp_path / "both").exists()
    assert main(["breathe", "--help"]) == 0
    shown = capsys.readouterr().out
    assert "--tidal-ml" in shown and "--tidal-volume-ml" not in shown
