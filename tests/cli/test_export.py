"""CLI tests of ``lungdeform export`` (glb and pvd) and the argument checks of ``view`` and ``bench viewer``."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from lungdeform.cli.main import main
from lungdeform.modelfile import save_model
from tests.browser.support import two_lungs


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


def test_export_pvd(model_file, tmp_path, capsys):
    out = tmp_path / "series.pvd"
    assert main(["export", str(model_file), "--format", "pvd", "--out", str(out), "--fps", "2",
                 "--period", "2"]) == 0
    assert f"wrote {out} and 10 frames" in capsys.readouterr().out  # 2 lungs × (2 s × 2 fps + 1)
    frames = sorted((tmp_path / "series_frames").iterdir())
    assert len(frames) == 10 and out.read_text().count("<DataSet") == 10


@pytest.mark.parametrize("args, message", [
    (["--format", "obj"], "--format must be glb or pvd"),
    (["--format", "pvd", "--markers", "m.csv"], "--markers applies to --format glb only"),
])
def test_export_bad_options(model_file, tmp_path, capsys, args, message):
    assert main(["export", str(model_file), "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


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
