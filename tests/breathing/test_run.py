"""A preset run or a trace fit with its outputs (``lungdeform breathe``; the CLI in tests/cli/test_breathe.py)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing.presets import get_preset
from lungdeform.breathing.pv import BreathingCurve
from lungdeform.breathing.run import check_sample_rate, curve_csv, run_fit, run_preset, simulate_preset
from lungdeform.errors import InputError
from tests.breathing.test_trace import breath, write_marker_csv

OUTPUTS = ("curve.csv", "metrics.json", "volume.png", "pv_loop.png", "residuals.png")


def test_curve_csv_header_and_six_significant_digits():
    # truth: the header curve.csv readers expect, then each sample with 6 significant digits
    curve = BreathingCurve(np.array([0.0, 0.02]), np.array([2400.123456, 2401.5]), np.array([12.3456789, -1e-7]),
                           np.array([0.0, 3.25]))
    assert curve_csv(curve) == "t_s,volume_ml,flow_ml_s,pressure_cmH2O\n0,2400.12,12.3457,0\n0.02,2401.5,-1e-07,3.25\n"


def test_check_sample_rate_names_the_parameter():
    # truth: the normal preset breathes every 4 s, so 2 Hz is exactly 8 samples per breath (accepted)
    # and 1 Hz is 4 (refused, the message naming the rate as the caller calls it); NaN is no rate
    assert check_sample_rate("normal", 2.0).name == "normal"
    with pytest.raises(InputError, match=r"fs_hz 1 Hz gives 4 samples per 4 s breath of preset normal"):
        check_sample_rate("normal", 1.0)
    with pytest.raises(InputError, match=r"^--fs 1 Hz .*\(--fs ≥ 2\)"):
        check_sample_rate("normal", 1.0, name="--fs")
    with pytest.raises(InputError, match="fs_hz nan Hz"):
        check_sample_rate("normal", float("nan"))


def test_simulate_preset_matches_the_periodic_solution():
    # truth: the preset's tidal volume is 500 mL (its definition), measured on a fine run even at 2 Hz;
    # the Radau integrator agrees with the exact periodic (Fourier) solution to well under 0.1 mL
    curve, resid, metrics = simulate_preset(get_preset("normal"), cycles=2, fs_hz=2.0)
    assert resid.shape == curve.t_s.shape and curve.t_s.size == 17  # 0 to 8 s in 0.5 s steps, both ends
    assert metrics["tidal_volume_ml"] == pytest.approx(500.0, rel=1e-3)
    assert metrics["integrator_vs_periodic_max_abs_ml"] == pytest.approx(np.abs(resid).max())
    assert np.abs(resid).max() < 0.1


def test_run_preset_writes_outputs_and_refuses_before_writing(tmp_path):
    m = run_preset("normal", tmp_path / "n", cycles=1, fs_hz=25.0)
    assert m["mode"] == "preset" and all((tmp_path / "n" / name).stat().st_size > 0 for name in OUTPUTS)
    # a refused run leaves no output folder behind
    for cycles, fs in ((0, 25.0), (1, 1.0)):
        with pytest.raises(InputError):
            run_preset("normal", tmp_path / "bad", cycles=cycles, fs_hz=fs)
    assert not (tmp_path / "bad").exists()


def test_run_fit_curve_follows_a_regular_trace(tmp_path, rng):
    # truth: a perfectly regular synthetic breath (12 mm peak-to-peak, 0.05 mm noise) calibrated to
    # 500 mL: the PV fit to all its cycles follows it to a few % of the tidal volume
    t = np.arange(0.0, 64.0, 0.1)
    trace = write_marker_csv(tmp_path / "regular.csv", t * 1000, 12.0 * breath(t) + rng.normal(0, 0.05, t.size))
    m = run_fit(trace, tmp_path / "fit", tidal_volume_ml=500.0, train_fraction=0.5)
    assert m["mode"] == "fit" and m["full_fit"]["rms_percent"] < 5.0 and m["model_rms_percent"] < 5.0
    rows = np.loadtxt(tmp_path / "fit" / "curve.csv", delimiter=",", skiprows=1)
    assert np.ptp(rows[:, 1]) == pytest.approx(500.0, rel=0.1)  # the calibrated tidal volume
    assert all((tmp_path / "fit" / name).stat().st_size > 0 for name in OUTPUTS)
