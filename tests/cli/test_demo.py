"""``lungdeform demo``: the main job on the embedded lungs writes everything it promises."""

import json
import re

import numpy as np
import pytest

from lungdeform.breathing.presets import get_preset
from lungdeform.breathing.pv import simulate
from lungdeform.cli.main import main
from lungdeform.constants import STEPS_PER_S
from lungdeform.geometry.mesh import signed_volume
from lungdeform.io.modelfile import load_model
from lungdeform.model.displacement import scale_for_volume
from lungdeform.playback import demo as demo_module


def test_demo_plays_the_normal_preset_and_writes_everything(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in ("model.npz", "series.pvd", "summary.json", "snapshot.png"):
        assert (out / name).is_file() and str(out / name) in printed
    assert "preset 'normal'" in printed
    model = load_model(out / "model.npz")
    assert sorted(model.names) == ["left", "right"]
    summary = json.loads((out / "summary.json").read_text())
    preset = get_preset("normal")
    assert summary["breathing"]["preset"] == "normal"
    assert summary["breathing"]["sources"] == list(preset.sources)

    # frame times: one breath of the preset (4 s at 15/min) at the paper's 66.66 frames/s, the last
    # frame exactly at the end of the breath: n = ⌈4 s · 66.67⌉ = 267 intervals (round gives the same here)
    t = np.array(summary["t_s"])
    n = round(preset.params.period_s * STEPS_PER_S)
    assert len(t) == n + 1 and t[0] == 0 and t[-1] == pytest.approx(preset.params.period_s, abs=1e-9)
    assert np.allclose(np.diff(t), preset.params.period_s / n, atol=1e-6)

    # truth: the PV model simulated here, independently, on the same frame times. The demo must play
    # exactly this curve (volume above its minimum, end-exhale), not a cosine of the same size.
    ref = simulate(preset.params, n_cycles=1, fs_hz=n / preset.params.period_s)
    assert np.allclose(ref.t_s, t, atol=1e-6)
    dv = ref.volume_ml - ref.volume_ml.min()
    target = np.array(summary["target_volume_above_ee_ml"])
    assert np.allclose(target, dv, atol=1e-5)
    assert target.max() == pytest.approx(preset.tidal_volume_ml, rel=1e-3)  # 500 mL breath
    cosine = 0.5 * dv.max() * (1 - np.cos(2 * np.pi * t / t[-1]))
    assert np.max(np.abs(target - cosine)) > 20.0  # the PV shape is not the old plain cycle

    # each lung's volume per frame, measured on its own deformed mesh, is V_EE + share·ΔV(t): the
    # shares follow the end-exhale volumes and the demo inverts the exact volume cubic per frame
    ee = {k: l["volume_ee_ml"] for k, l in summary["lungs"].items()}
    total_ee = sum(ee.values())
    for name, lung in summary["lungs"].items():
        share = ee[name] / total_ee
        vols = np.array(lung["volume_ml"])
        assert len(vols) == len(t)
        assert np.allclose(vols, ee[name] + share * dv, rtol=1e-8, atol=1e-5)
        err = np.array(lung["volume_error_ml"])
        assert len(err) == len(t) and np.max(np.abs(err)) < 1e-6
        assert lung["max_volume_error_percent"] < 1e-8
        # the paper's linear reading s = ΔV/unit_ml would be off by well under 1 % (never exact)
        assert 0 < lung["linear_reading_max_error_percent"] < 1.0
    total = np.array(summary["total_volume_ml"])
    assert total[0] == pytest.approx(total_ee, rel=1e-9)
    assert np.allclose(total - total_ee, dv, atol=1e-4)

    # the saved model reproduces a frame: the peak frame's mesh volume from model.npz alone
    peak = int(np.argmax(dv))
    for name, lung in model.lungs.items():
        share = ee[name] / total_ee
        x = lung.positions_at(scale_for_volume(lung.volume_poly, share * dv[peak]))
        assert signed_volume(x, lung.surface.faces) / 1000 == pytest.approx(ee[name] + share * dv[peak], rel=1e-9)

    assert (out / "snapshot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the time series names one .vtp per lung and frame (10 frames/s over 4 s: 41 each), all present
    files = re.findall(r'file="([^"]+)"', (out / "series.pvd").read_text())
    assert len(files) == 2 * 41 and all((out / f).is_file() for f in files)


def test_demo_other_preset_duration_and_tidal(tmp_path, capsys):
    # dyspnoea (1.875 s breaths) played for 3 s at 400 mL: 1.6 breaths, the preset's shape rescaled
    out = tmp_path / "d"
    assert main(["demo", "--out", str(out), "--preset", "dyspnoea", "--duration", "3", "--tidal-ml", "400"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    t = np.array(summary["t_s"])
    assert t[-1] == pytest.approx(3.0) and len(t) == round(3 * STEPS_PER_S) + 1
    target = np.array(summary["target_volume_above_ee_ml"])
    # the simulation is linear in the control parameters: 400/280 times the preset's own curve
    p = get_preset("dyspnoea")
    ref = simulate(p.params, n_cycles=2, fs_hz=(len(t) - 1) / 3.0)
    ref_v = ref.volume_ml[ref.t_s <= 3.0 + 1e-9]
    assert np.allclose(target, (ref_v - ref_v.min()) * 400 / 280, atol=1e-4)
    assert target.max() == pytest.approx(400, rel=2e-3)
    assert summary["tidal_ml"] == 400
    for lung in summary["lungs"].values():
        assert lung["max_volume_error_percent"] < 1e-8


def test_demo_refuses_a_file_as_output(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("x")
    assert main(["demo", "--out", str(f)]) == 2
    assert "taken" in capsys.readouterr().err


def test_demo_refuses_an_unknown_preset(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "x"), "--preset", "panting"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "panting" in err[0] and "normal" in err[0]
    assert not (tmp_path / "x" / "summary.json").exists()


@pytest.mark.parametrize("args, message", [
    # 1e5 s used to run for minutes and would have written millions of mesh files
    (["--duration", "1e5"], "--duration must be at most 300 s, got 100000"),
    (["--duration", "nan"], "--duration must be a finite number in (0, 300] s, got nan"),
    # 1e6 mL used to give 458 L lungs without a word
    (["--tidal-ml", "1e6"], "--tidal-ml must be a tidal volume in mL in (0, 10000]"),
    (["--orientation", "sideways"], "--orientation must be one of supine, prone, upright"),
    (["--orientation", "0,0,0"], "--orientation must be a non-zero finite vector"),
])
def test_demo_refuses_absurd_settings_before_writing(tmp_path, capsys, args, message):
    out = tmp_path / "x"
    assert main(["demo", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists()


def _boom(*_a, **_k):
    raise RuntimeError("killed midway")


def test_demo_killed_midway_leaves_no_folder(tmp_path, capsys, monkeypatch):
    # the snapshot is the last step: model.npz, summary.json and the series are written by then.
    # A run stopped there used to leave D with part of the set and nothing marking it incomplete;
    # now the set is built in a hidden sibling folder that is removed, and D never appears
    monkeypatch.setattr(demo_module, "_snapshot", _boom)
    out = tmp_path / "D"
    with pytest.raises(RuntimeError, match="killed midway"):
        main(["demo", "--out", str(out)])
    assert list(tmp_path.iterdir()) == []  # no D, no temporary folder


def test_demo_replaces_a_previous_demo_only_at_the_end(tmp_path, capsys, monkeypatch):
    out = tmp_path / "D"
    assert main(["demo", "--out", str(out), "--duration", "1"]) == 0
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # a second run (another preset) that fails at its last step leaves the first set as it was
    monkeypatch.setattr(demo_module, "_snapshot", _boom)
    with pytest.raises(RuntimeError):
        main(["demo", "--out", str(out), "--preset", "dyspnoea", "--duration", "1"])
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before and [p.name for p in tmp_path.iterdir()] == ["D"]
    # and one that finishes replaces it as a whole
    monkeypatch.undo()
    assert main(["demo", "--out", str(out), "--preset", "dyspnoea", "--duration", "1"]) == 0
    assert json.loads((out / "summary.json").read_text())["breathing"]["preset"] == "dyspnoea"
    assert [p.name for p in tmp_path.iterdir()] == ["D"]


def test_demo_refuses_a_folder_with_other_files(tmp_path, capsys):
    # the demo replaces its folder as a whole: a folder holding the user's own files is not its to replace
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["demo", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and "notes.txt" in err[0]
    assert [p.name for p in out.iterdir()] == ["notes.txt"] and [p.name for p in tmp_path.iterdir()] == ["mine"]
