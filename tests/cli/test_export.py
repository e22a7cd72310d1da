"""CLI tests of ``lungdeform export`` (glb and pvd) and the argument checks of ``view`` and ``bench viewer``."""

from __future__ import annotations

import json
import math
import re
import struct

import numpy as np
import pytest

from lungdeform.breathing.presets import PRESET_NAMES, get_preset
from lungdeform.breathing.pv import simulate
from lungdeform.cli.main import main
from lungdeform.constants import STEPS_PER_S
from lungdeform.geometry.mesh import signed_volume
from lungdeform.io.meshfile import read_mesh
from lungdeform.io.modelfile import load_model, save_model
from lungdeform.playback.schedule import lung_shares
from tests.browser.support import two_lungs
from tests.playback.test_export import _accessor, _glb_json


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return save_model(tmp_path_factory.mktemp("model") / "m.npz", two_lungs(2))


def _glb_doc(path):
    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + jlen])


def test_export_glb_plain_cycle(model_file, tmp_path, capsys):
    out = tmp_path / "lungs.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and "plain cycle" in printed
    doc = _glb_doc(out)
    curve = doc["extras"]["lungdeform"]["curve"]
    assert max(curve["volume_ml"]) == pytest.approx(500) and curve["t_s"][-1] == pytest.approx(4.0)
    assert [m["name"] for m in doc["meshes"]] == ["left", "right"]


@pytest.mark.parametrize("kind", ["glb", "pvd"])
def test_export_into_an_existing_folder(model_file, tmp_path, capsys, kind):
    # --out an existing folder: the file goes inside it (it used to be written beside it, as DIR.glb)
    folder = tmp_path / "exports"
    folder.mkdir()
    assert main(["export", str(model_file), "--format", kind, "--out", str(folder)]) == 0
    assert (folder / f"m.{kind}").is_file() and not (tmp_path / f"exports.{kind}").exists()
    assert f"wrote {folder / f'm.{kind}'}" in capsys.readouterr().out


def test_export_glb_with_curve_and_markers(model_file, tmp_path, capsys):
    # an absolute-volume curve (2.5 L baseline) is shifted to its minimum, and the CLI says so
    t = np.linspace(0, 10, 101)
    v = 2500 + 300 * (1 - np.cos(2 * np.pi * t / 5))
    curve = tmp_path / "curve.csv"
    curve.write_text("t_s,volume_ml,flow_ml_s,pressure_cmH2O\n" + "".join(f"{a:.3f},{b:.4f},0,0\n" for a, b in zip(t, v)))
    markers = tmp_path / "markers.csv"
    markers.write_text("x_mm,y_mm,z_mm,label\n90,0,0,tumour\n-90,0,50,nodule\n")
    out = tmp_path / "lungs"  # suffix added
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), "--curve", str(curve),
                 "--markers", str(markers)]) == 0
    printed = capsys.readouterr().out
    assert "subtracted its minimum 2500.0 mL" in printed
    doc = _glb_doc(tmp_path / "lungs.glb")
    ex = doc["extras"]["lungdeform"]
    assert max(ex["curve"]["volume_ml"]) == pytest.approx(600, rel=1e-6)
    assert [m["label"] for m in ex["markers"]] == ["tumour", "nodule"]
    assert [m["lung"] for m in ex["markers"]] == ["left", "right"]
    assert "markers: 2 (tumour in left; nodule in right), moving with each lung's interior field" in printed
    # truth: the model file's own interior field (LungModel.points_at) at the scale of target 0's
    # weight λ = 1 (calibration_ml), through the extras' formula position_mm + λ·tidal_mm
    model = load_model(model_file)
    for m in ex["markers"]:
        lung = model.lungs[m["lung"]]
        want = lung.points_at([m["position_mm"]], scale=lung.calibration_ml / lung.unit_ml)[0]
        np.testing.assert_allclose(np.add(m["position_mm"], m["tidal_mm"]), want, atol=1e-6)


def test_export_markers_far_outside_every_lung(model_file, tmp_path, capsys):
    # a marker in the wrong frame or unit (here 300 mm anterior of both lungs): refused, one line
    # naming the markers file and the marker, and no output written
    markers = tmp_path / "markers.csv"
    markers.write_text("x_mm,y_mm,z_mm,label\n90,0,0,tumour\n0,-300,0,typo\n")
    out = tmp_path / "x.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), "--markers", str(markers)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(markers) in err[0] and "outside every lung" in err[0] and ": 2 (" in err[0]
    assert not out.exists()


def test_export_glb_preset(model_file, tmp_path, capsys):
    # copd (3.2 s breaths, air trapping: end-exhale is not at t = 0) for 2 breaths, rescaled to 600 mL
    out = tmp_path / "copd.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), "--preset", "copd",
                 "--cycles", "2", "--tidal-ml", "600"]) == 0
    printed = capsys.readouterr().out
    assert "preset copd: 2 × 3.2 s" in printed and f"wrote {out}" in printed
    doc, blob = _glb_json(out.read_bytes())
    ex = doc["extras"]["lungdeform"]["curve"]
    t, dv = np.array(ex["t_s"]), np.array(ex["volume_ml"])
    # frame grid: 2 periods at >= the paper's 66.67 frames/s, the last key exactly at the end
    preset = get_preset("copd")
    duration = 2 * preset.params.period_s
    n = len(t) - 1
    assert n == math.ceil(duration * STEPS_PER_S - 1e-9) and t[0] == 0 and t[-1] == pytest.approx(duration, abs=1e-9)
    # truth: the PV model simulated here, independently, on the same grid, with the preset's own
    # parameters. The equation is linear and a_1 = 0, so 600 mL is 600/500 times its curve above
    # end-exhale (the same shape, not a cosine, not the preset's 500 mL)
    ref = simulate(preset.params, n_cycles=2, fs_hz=n / duration)
    np.testing.assert_allclose(t, ref.t_s, atol=1e-9)
    ref_dv = (ref.volume_ml - ref.volume_ml.min()) * 600.0 / preset.tidal_volume_ml
    np.testing.assert_allclose(dv, ref_dv, atol=1e-4)  # two integrations (rtol 1e-7): ~1e-5 mL apart
    assert dv.max() == pytest.approx(600, rel=2e-3) and dv[0] > 1.0  # air trapping: V(0) above V_EE
    # the animation plays that volume: its key times are the curve's, and at the key frames each
    # lung's weights give a mesh (measured by the divergence theorem) of exactly V_EE + share·ΔV(t)
    times = _accessor(doc, blob, doc["animations"][0]["samplers"][0]["input"])
    np.testing.assert_allclose(times, ref.t_s, rtol=1e-6, atol=1e-6)
    model = load_model(model_file)
    shares = lung_shares(model)
    keys = sorted({0, n // 3, int(np.argmax(ref_dv)), int(np.argmin(ref_dv)), n})
    for mesh in doc["meshes"]:
        lung = model.lungs[mesh["name"]]
        t0 = _accessor(doc, blob, mesh["primitives"][0]["targets"][0]["POSITION"]).astype(float)
        ch = next(c for c in doc["animations"][0]["channels"]
                  if doc["nodes"][c["target"]["node"]]["name"] == mesh["name"])
        w = _accessor(doc, blob, doc["animations"][0]["samplers"][ch["sampler"]]["output"]).reshape(-1, 5)
        assert len(w) == n + 1 and np.all(w[:, 1:] == 0)
        for k in keys:
            v = signed_volume(lung.surface.vertices + float(w[k, 0]) * t0, lung.surface.faces) / 1000
            assert v == pytest.approx(lung.volume_ee_ml + shares[mesh["name"]] * ref_dv[k], rel=1e-6)


def test_export_pvd_preset(model_file, tmp_path, capsys):
    # one breath of 'normal' (4 s) at 2 frames/s: 2 lungs × (4 × 2 + 1) frames
    out = tmp_path / "series.pvd"
    assert main(["export", str(model_file), "--format", "pvd", "--out", str(out), "--fps", "2",
                 "--preset", "normal"]) == 0
    assert f"wrote {out} and 18 frames" in capsys.readouterr().out
    # truth: the preset simulated here on the exporter's grid (n = ceil(4 s · 66.67) intervals); the
    # frames at k/fps sample it linearly, and each frame's mesh (float32 .vtp) holds V_EE + share·ΔV(t)
    preset = get_preset("normal")
    n = math.ceil(preset.params.period_s * STEPS_PER_S - 1e-9)
    ref = simulate(preset.params, n_cycles=1, fs_hz=n / preset.params.period_s)
    model = load_model(model_file)
    shares = lung_shares(model)
    entries = re.findall(r'timestep="([^"]+)" part="\d" name="(\w+)" file="([^"]+)"', out.read_text())
    assert len(entries) == 18
    for ts, name, file in entries:
        v, f = read_mesh(tmp_path / file)
        dv = np.interp(float(ts), ref.t_s, ref.volume_ml - ref.volume_ml.min())
        lung = model.lungs[name]
        assert signed_volume(v, f) / 1000 == pytest.approx(lung.volume_ee_ml + shares[name] * dv, rel=1e-5)


def test_export_pvd(model_file, tmp_path, capsys):
    out = tmp_path / "series.pvd"
    assert main(["export", str(model_file), "--format", "pvd", "--out", str(out), "--fps", "2",
                 "--period", "2"]) == 0
    assert f"wrote {out} and 10 frames" in capsys.readouterr().out  # 2 lungs × (2 s × 2 fps + 1)
    frames = sorted((tmp_path / "series_frames").iterdir())
    assert len(frames) == 10 and out.read_text().count("<DataSet") == 10


@pytest.mark.parametrize("args, message", [
    (["--format", "obj"], "--format must be one of glb, usd, usdc, usda, usdz, pvd"),
    (["--format", "pvd", "--markers", "m.csv"], "--markers applies to --format glb only"),
    (["--format", "usdz", "--markers", "m.csv"], "--markers applies to --format glb only"),
    (["--format", "glb", "--baked"], "--baked applies to the USD formats (usd, usdc, usda, usdz) only"),
    (["--format", "glb", "--fps", "30"], "--fps does not apply to --format glb"),
    (["--format", "glb", "--curve", "c.csv", "--preset", "normal"], "--curve and --preset are mutually exclusive"),
    (["--format", "glb", "--curve", "c.csv", "--tidal-ml", "600"], "do not apply to --curve"),
    (["--format", "glb", "--preset", "normal", "--period", "3"], "a --preset has its own period"),
    (["--format", "glb", "--cycles", "2"], "--cycles applies to --preset only"),
    (["--format", "glb", "--preset", "normal", "--cycles", "0"], "--cycles must be >= 1"),
    # a million breaths simulated for hours without a word (track refused it already): one cap for both
    (["--format", "pvd", "--preset", "normal", "--cycles", "1000000"], "--cycles must be at most 100"),
    (["--format", "glb", "--preset", "normal", "--tidal-ml", "-5"], "--tidal-ml must be a tidal volume in mL"),
    # a typo far above any vital capacity used to give lungs of hundreds of litres
    (["--format", "glb", "--tidal-ml", "500000"], "--tidal-ml must be a tidal volume in mL in (0, 10000]"),
])
def test_export_bad_options(model_file, tmp_path, capsys, args, message):
    assert main(["export", str(model_file), "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_export_unknown_preset_lists_the_names(model_file, tmp_path, capsys):
    out = tmp_path / "x.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), "--preset", "panting"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'panting'" in err[0] and all(name in err[0] for name in PRESET_NAMES)
    assert not out.exists()


def test_export_bad_model_and_curve(model_file, tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["export", str(bad), "--format", "glb", "--out", str(tmp_path / "x.glb")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0]
    curve = tmp_path / "c.csv"
    curve.write_text("t_s,volume_ml\n0,0\n0,5\n")
    assert main(["export", str(model_file), "--format", "glb", "--out", str(tmp_path / "x.glb"),
                 "--curve", str(curve)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(curve) in err[0] and "strictly increasing" in err[0]
    assert not (tmp_path / "x.glb").exists()


@pytest.mark.parametrize("kind", ["glb", "pvd", "usdz"])
def test_export_refuses_a_curve_the_lungs_cannot_reach(model_file, tmp_path, capsys, kind):
    # ΔV -2900 mL on these lungs (V_EE about 2 × 1.3 L) would empty them: the CSV line is named, exit 2,
    # nothing written (it used to export a lung of negative volume)
    curve = tmp_path / "neg.csv"
    curve.write_text("t_s,volume_ml\n0,0\n1,-2900\n2,0\n")
    out = tmp_path / f"x.{kind}"
    assert main(["export", str(model_file), "--format", kind, "--out", str(out), "--curve", str(curve)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {curve} line 3: volume_ml -2900 mL")
    assert not out.exists() and list(tmp_path.iterdir()) == [curve]


def test_view_refuses_curve_for_glb(model_file, tmp_path, capsys):
    out = tmp_path / "m.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["view", str(out), "--curve", str(tmp_path / "c.csv"), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "apply to a model file" in err[0]


def test_view_missing_file(tmp_path, capsys):
    assert main(["view", str(tmp_path / "none.npz"), "--port", "0"]) == 2
    assert "no such file" in capsys.readouterr().err


def test_bench_viewer_bad_vertices(capsys):
    assert main(["bench", "viewer", "--vertices", "10", "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--vertices must be at least 1000" in err[0]


@pytest.mark.parametrize("kind, name, message", [
    # a suffix that contradicts --format used to be kept and .glb appended (e3.pvd.glb, exit 0)
    ("glb", "e3.pvd", "--out {out}: --format glb writes a .glb file, not .pvd; name it e3.glb or give --format pvd"),
    ("pvd", "e3.glb", "--out {out}: --format pvd writes a .pvd file, not .glb; name it e3.pvd or give --format glb"),
    ("glb", "e3.v2", "--out {out}: --format glb writes a .glb file, but the name ends in .v2; name it e3.v2.glb"),
    ("usdz", "e3.usdc", "--out {out}: --format usdz writes a .usdz file, not .usdc; name it e3.usdz or give --format usdc"),
])
def test_export_refuses_an_out_suffix_that_contradicts_the_format(model_file, tmp_path, capsys, kind, name, message):
    out = tmp_path / name
    assert main(["export", str(model_file), "--format", kind, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: " + message.format(out=out)]
    assert list(tmp_path.iterdir()) == []  # refused before any work: nothing written, nothing renamed


def test_export_appends_the_suffix_to_a_bare_name(model_file, tmp_path, capsys):
    # a name without a suffix gets the format's (docs/VIEWER.md), and the line says the file written
    assert main(["export", str(model_file), "--format", "glb", "--out", str(tmp_path / "lungs")]) == 0
    assert f"wrote {tmp_path / 'lungs.glb'}" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir()] == ["lungs.glb"]


@pytest.mark.parametrize("make, message", [
    (lambda p: p.mkdir(), "{p}: is a folder, not a model file (give the .npz that build, fit or demo wrote)"),
    (lambda p: p.write_text("hello\n"), "{p}: not a lungdeform model file (not a NumPy .npz archive: not a zip file)"),
    (lambda p: np.savez(p, a=np.zeros(2)),
     "{p}: not a lungdeform model file (a NumPy .npz archive without the 'schema' member; it holds 'a')"),
])
def test_export_names_what_the_model_argument_is(tmp_path, capsys, make, message):
    # a new user's wrong MODEL: one line, exit 2, saying what the file is rather than a wrong guess
    bad = tmp_path / "bad.npz"
    make(bad)
    assert main(["export", str(bad), "--format", "glb", "--out", str(tmp_path / "x.glb")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == ["error: " + message.format(p=bad)]


# --------------------------------------------------------------------------- USD
@pytest.mark.parametrize("kind", ["usd", "usdc", "usda", "usdz"])
def test_export_usd_formats(model_file, tmp_path, capsys, kind):
    # each --format writes its suffix; what the file holds is tested in tests/playback/test_usd.py
    pxr = pytest.importorskip("pxr", reason="usd-core is not installed (pip install 'lungdeform[usd]')")
    out = tmp_path / "lungs"
    assert main(["export", str(model_file), "--format", kind, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    path = tmp_path / f"lungs.{kind}"
    assert f"wrote {path}" in printed and "time codes 0…120 at 30 per second" in printed
    stage = pxr.Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetTypeName() == "SkelRoot" and stage.GetTimeCodesPerSecond() == 30
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_export_usd_preset_uneven_curve_and_baked(model_file, tmp_path, capsys, monkeypatch):
    pxr = pytest.importorskip("pxr", reason="usd-core is not installed (pip install 'lungdeform[usd]')")
    from lungdeform.playback import usd as U

    # a preset plays on its own frames (n = ceil(D·66.67) intervals): fps = n / D
    out = tmp_path / "copd.usdc"
    assert main(["export", str(model_file), "--format", "usdc", "--out", str(out), "--preset", "copd"]) == 0
    period = get_preset("copd").params.period_s
    n = math.ceil(period * STEPS_PER_S - 1e-9)
    stage = pxr.Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == n and stage.GetTimeCodesPerSecond() == pytest.approx(n / period)
    capsys.readouterr()
    # an uneven curve is resampled at 30 per second, and the CLI says so
    curve = tmp_path / "c.csv"
    curve.write_text("t_s,volume_ml\n0,0\n0.4,120\n1.5,400\n3,0\n")
    assert main(["export", str(model_file), "--format", "usda", "--out", str(tmp_path / "c.usda"),
                 "--curve", str(curve)]) == 0
    assert "curve resampled (its samples are not evenly spaced): 91 frames at 30 per second" in capsys.readouterr().out
    # --baked past the size threshold warns on stderr, and still writes the file
    monkeypatch.setattr(U, "BAKED_WARN_BYTES", 1000)
    out = tmp_path / "b.usdz"
    assert main(["export", str(model_file), "--format", "usdz", "--out", str(out), "--baked", "--fps", "10"]) == 0
    captured = capsys.readouterr()
    assert "curve resampled (--fps 10): 41 frames at 10 per second" in captured.out
    assert captured.err.startswith("warning: the baked file will be about ") and out.is_file()
    assert "points at every time code (baked)" in captured.out


def test_export_usd_without_usd_core(model_file, tmp_path, capsys, monkeypatch):
    # the optional extra is named in one line, exit 2, before any work
    import sys

    monkeypatch.setitem(sys.modules, "pxr", None)
    out = tmp_path / "x.usdz"
    assert main(["export", str(model_file), "--format", "usdz", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: USD export needs usd-core, the optional extra 'usd': pip install 'lungdeform[usd]'"]
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--vertices", "10"], "--vertices must be at least 1000"),
    (["--repeats", "0"], "--repeats must be >= 1"),
])
def test_bench_export_bad_options(capsys, args, message):
    assert main(["bench", "export", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


@pytest.mark.parametrize("args", [["--tidal-ml", "9000"], ["--preset", "normal", "--tidal-ml", "9000"]])
def test_export_refuses_a_tidal_volume_beyond_what_the_lungs_hold(model_file, tmp_path, capsys, args):
    # why: a 9 L breath on these lungs (V_EE about 2 × 1.3 L, shared by calibration) takes each lung past
    # 3 × its end-exhale volume (total lung capacity is about twice it): it used to export a lung blown
    # up several times over without a word. Exit 2, one line naming the bound, nothing written;
    # 2 L (each lung +0.8 of its volume) exports
    out = tmp_path / "x.glb"
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "above 3 times its end-exhale" in err[0] and "9000 mL" in err[0], err
    assert not out.exists() and list(tmp_path.iterdir()) == []
    assert main(["export", str(model_file), "--format", "glb", "--out", str(out), *args[:-1], "2000"]) == 0
    assert out.exists()
