"""Tests of lungdeform.playback.schedule: the breathing schedule (plain cycle, curve CSV, PV-model presets)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.playback import schedule as S


def test_plain_cycle_is_one_cosine_breath():
    tr = S.plain_cycle(500, 4.0)
    assert tr.t_s[0] == 0 and tr.t_s[-1] == pytest.approx(4.0)
    assert tr.volume_ml[0] == pytest.approx(0) and tr.volume_ml[-1] == pytest.approx(0, abs=1e-9)
    assert tr.sample(2.0) == pytest.approx(500.0)
    assert tr.sample(1.0) == pytest.approx(250.0)


def test_curve_csv_relative_and_absolute(tmp_path):
    t = np.linspace(0, 8, 81)
    v = 250 * (1 - np.cos(np.pi * t / 2))
    rel = tmp_path / "rel.csv"
    rel.write_text("t_s,volume_ml,flow_ml_s,pressure_cmH2O\n" + "".join(f"{a},{b},0,0\n" for a, b in zip(t, v)))
    tr = S.read_volume_csv(rel)
    assert tr.shifted_ml == 0 and np.allclose(tr.volume_ml, v)
    absolute = tmp_path / "abs.csv"  # volumes of 2.4–2.9 L: far above 0, so the minimum is removed
    absolute.write_text("t_s,volume_ml\n" + "".join(f"{a + 3},{b + 2400}\n" for a, b in zip(t, v)))
    tr = S.read_volume_csv(absolute)
    assert tr.shifted_ml == pytest.approx(2400) and np.allclose(tr.volume_ml, v)
    assert tr.t_s[0] == 0  # time starts at 0


@pytest.mark.parametrize("encoding, sep, decimal", [
    ("utf-8-sig", ",", "."),   # "CSV UTF-8" from a spreadsheet: a byte-order mark before "t_s"
    ("utf-8", ";", ","),       # re-saved in a decimal-comma locale
    ("utf-8-sig", ";", ","),
    ("utf-8", "\t", "."),
])
def test_curve_csv_spreadsheet_variants(tmp_path, encoding, sep, decimal):
    # truth: the same curve as the plain file; before, a BOM or ';' gave "needs a 't_s' column"
    t = np.linspace(0, 8, 81)
    v = 250 * (1 - np.cos(np.pi * t / 2))
    rows = [sep.join(["t_s", "volume_ml", "flow_ml_s"])]
    rows += [sep.join(f"{x:.6g}".replace(".", decimal) for x in (a, b, 0.5)) for a, b in zip(t, v)]
    path = tmp_path / "curve.csv"
    path.write_text("\r\n".join(rows) + "\r\n", encoding=encoding)
    tr = S.read_volume_csv(path)
    assert np.allclose(tr.t_s, t) and np.allclose(tr.volume_ml, v, atol=1e-3)


def test_volume_trace_from_breathing_curve(tmp_path):
    # truth: an analytic absolute-volume curve (2.4 L + a 500 mL cosine, clock starting at 3 s)
    from lungdeform.breathing.pv import BreathingCurve

    t = np.linspace(3.0, 7.0, 201)
    v = 2400.0 + 250.0 * (1 - np.cos(np.pi * (t - 3.0) / 2))
    curve = BreathingCurve(t, v, np.gradient(v, t), np.zeros_like(t), meta={"source": "test breath"})
    tr = S.VolumeTrace.from_breathing(curve)
    assert tr.t_s[0] == 0 and tr.t_s[-1] == pytest.approx(4.0)
    assert tr.shifted_ml == pytest.approx(2400.0) and tr.source == "test breath"
    np.testing.assert_allclose(tr.volume_ml, v - 2400.0, atol=1e-12)
    assert tr.sample(2.0) == pytest.approx(500.0)
    assert S.VolumeTrace.from_breathing(curve, source="x").source == "x"


def test_from_breathing_agrees_with_the_curve_csv_reader(tmp_path):
    # the two ways a simulated preset reaches the exporter give one trace: in memory through the
    # adapter, and through curve.csv (t_s, volume_ml, … as 'lungdeform breathe' writes it)
    from lungdeform.breathing.presets import get_preset
    from lungdeform.breathing.pv import simulate

    curve = simulate(get_preset("copd").params, n_cycles=2, fs_hz=25.0)
    path = tmp_path / "curve.csv"
    path.write_text("t_s,volume_ml,flow_ml_s,pressure_cmH2O\n" + "".join(
        f"{a!r},{b!r},{c!r},{d!r}\n" for a, b, c, d in
        zip(*(x.tolist() for x in (curve.t_s, curve.volume_ml, curve.flow_ml_s, curve.pressure_cmH2O)))))
    via_csv, direct = S.read_volume_csv(path), S.VolumeTrace.from_breathing(curve)
    np.testing.assert_allclose(direct.t_s, via_csv.t_s, atol=1e-12)
    np.testing.assert_allclose(direct.volume_ml, via_csv.volume_ml, atol=1e-9)
    assert direct.shifted_ml == pytest.approx(via_csv.shifted_ml) == pytest.approx(curve.v_ee_ml)
    assert direct.volume_ml.min() == 0 and direct.volume_ml.max() == pytest.approx(500.0, rel=2e-3)  # 25 Hz samples


def test_preset_trace_is_the_pv_simulation_on_an_exact_grid():
    # truth: lungdeform.breathing.pv.simulate run here on the grid the docstring promises:
    # n = ceil(D·rate) intervals ending exactly at D (dyspnoea, T = 1.875 s: 2 breaths at >= 50 Hz
    # is 3.75 s · 50 = 187.5 → 188 intervals, 50.13 Hz)
    from lungdeform.breathing.presets import get_preset
    from lungdeform.breathing.pv import simulate

    p = get_preset("dyspnoea")
    params, curve, tr = S.preset_trace("dyspnoea", 2, rate_hz=50.0)
    assert params is p.params and len(tr.t_s) == 189 and tr.t_s[-1] == pytest.approx(3.75, abs=1e-12)
    ref = simulate(p.params, n_cycles=2, fs_hz=188 / 3.75)
    np.testing.assert_allclose(tr.t_s, ref.t_s, atol=1e-12)
    np.testing.assert_allclose(tr.volume_ml, ref.volume_ml - ref.volume_ml.min(), atol=1e-12)
    assert tr.shifted_ml == pytest.approx(ref.volume_ml.min()) and "lungdeform.presets:dyspnoea" in tr.source
    np.testing.assert_allclose(curve.volume_ml, ref.volume_ml, atol=1e-12)
    # any duration: 3 s is cut from two whole cycles, 150 intervals, volume above the cut's minimum
    _, _, cut = S.preset_trace(p, duration_s=3.0, rate_hz=50.0)
    ref = simulate(p.params, n_cycles=2, fs_hz=50.0)
    keep = ref.t_s <= 3.0 + 1e-9
    assert len(cut.t_s) == 151 == keep.sum()
    np.testing.assert_allclose(cut.volume_ml, ref.volume_ml[keep] - ref.volume_ml[keep].min(), atol=1e-12)


@pytest.mark.parametrize("kwargs, message", [
    ({"preset": "panting"}, "unknown breathing preset 'panting'; choose one of: normal, deep"),
    ({"preset": "normal", "cycles": 0}, "cycles must be a whole number >= 1"),
    ({"preset": "normal", "cycles": 1.5}, "cycles must be a whole number >= 1"),
    ({"preset": "normal", "duration_s": -1.0}, "duration must be > 0 s"),
    ({"preset": "normal", "tidal_ml": float("nan")}, "tidal volume must be > 0 mL"),
    ({"preset": "normal", "rate_hz": 0.0}, "rate_hz must be > 0"),
])
def test_preset_trace_bad_input(kwargs, message):
    with pytest.raises(InputError, match=message):
        S.preset_trace(**kwargs)


@pytest.mark.parametrize("text, message", [
    ("time,volume\n0,1\n1,2\n", "needs a 't_s' column"),
    ("t_s,volume_ml\n0,1\n", "at least 2 rows"),
    ("t_s,volume_ml\n0,1\n0,2\n", "strictly increasing"),
    ("t_s,volume_ml\n0,1\n1,nan\n", "finite"),
    ("t_s,volume_ml\n0,1\n1,abc\n", "line 3"),
])
def test_bad_curve_names_file_and_problem(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ReadError, match=message) as info:
        S.read_volume_csv(path)
    assert str(path) in str(info.value)


def test_curve_below_what_the_lungs_can_reach_names_its_line(tmp_path):
    # Each lung plays V_EE + share·ΔV; a ΔV (both lungs) of -0.6·(V_EE total) takes each lung to 40 %
    # of its end-exhale volume, below MIN_VOLUME_FRACTION (50 %): refused at the first such row, line 4
    # of the file (line 1 is the header, line 3 is blank). -0.4·V_EE (60 %) is reachable.
    from tests.browser.support import two_lungs

    model = two_lungs(2)
    vee = sum(lung.volume_ee_ml for lung in model.lungs.values())
    path = tmp_path / "deep.csv"
    path.write_text(f"t_s,volume_ml\n0,0\n\n1,{-0.6 * vee:.1f}\n2,{-0.7 * vee:.1f}\n3,0\n")
    trace = S.read_volume_csv(path)
    assert trace.lines.tolist() == [2, 4, 5, 6]
    with pytest.raises(InputError, match=rf"^{path} line 4: volume_ml .* below 50% of its end-exhale .*2 such rows"):
        S.check_reachable(trace, model)
    path.write_text(f"t_s,volume_ml\n0,0\n1,{-0.4 * vee:.1f}\n2,0\n")
    S.check_reachable(S.read_volume_csv(path), model)
    # a trace not read from a file names its sample and time instead
    with pytest.raises(InputError, match=r"sample 2 \(t 1 s\)"):
        S.check_reachable(S.VolumeTrace(np.array([0.0, 1.0]), np.array([0.0, -0.6 * vee]), "made"), model)


def test_curve_above_what_the_lungs_can_hold_names_its_line(tmp_path):
    # Each lung plays V_EE + share·ΔV; ΔV = 2.2·(V_EE total) takes each lung to 3.2 times its end-exhale
    # volume, above MAX_GROWTH (3: total lung capacity is about twice the end-exhale volume): refused at
    # the first such row, line 3. 1.8·V_EE (2.8 times) is reachable, at the bound's either side
    from tests.browser.support import two_lungs

    model = two_lungs(2)
    vee = sum(lung.volume_ee_ml for lung in model.lungs.values())
    path = tmp_path / "big.csv"
    path.write_text(f"t_s,volume_ml\n0,0\n1,{2.2 * vee:.1f}\n2,0\n")
    with pytest.raises(InputError, match=rf"^{path} line 3: volume_ml .* above 3 times its end-exhale .*1 such rows"):
        S.check_reachable(S.read_volume_csv(path), model)
    path.write_text(f"t_s,volume_ml\n0,0\n1,{1.8 * vee:.1f}\n2,0\n")
    S.check_reachable(S.read_volume_csv(path), model)


def test_curve_that_is_a_folder(tmp_path):
    # the path exists: named as a folder, not as missing
    with pytest.raises(ReadError) as info:
        S.read_volume_csv(tmp_path)
    assert str(info.value) == f"{tmp_path}: is a folder, not a curve file (give the curve.csv that breathe wrote)"
