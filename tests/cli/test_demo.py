"""``lungdeform demo``: the main job on the embedded lungs writes everything it promises."""

import json

import numpy as np
import pytest

from lungdeform.cli.main import main
from lungdeform.modelfile import load_model


def test_demo_writes_model_series_summary_and_snapshot(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in ("model.npz", "series.pvd", "summary.json", "snapshot.png"):
        assert (out / name).is_file() and str(out / name) in printed
    model = load_model(out / "model.npz")
    assert sorted(model.names) == ["left", "right"]
    summary = json.loads((out / "summary.json").read_text())
    t = np.array(summary["t_s"])
    assert t[-1] == pytest.approx(5.0) and len(t) == 334  # 5 s at 66.66 frames/s
    total = np.array(summary["total_volume_ml"])
    ee = sum(l["volume_ee_ml"] for l in summary["lungs"].values())
    # one 500 mL breath: starts and ends at end-exhale, peaks 500 mL above it (within 1 %)
    assert total[0] == pytest.approx(ee, rel=1e-9) and total[-1] == pytest.approx(ee, rel=1e-9)
    assert total.max() - ee == pytest.approx(500.0, rel=0.01)
    for lung in summary["lungs"].values():
        assert len(lung["volume_ml"]) == len(t) and lung["max_volume_error_percent"] < 1.0
    assert (out / "snapshot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the time series names one .vtp per lung and frame, all present
    import re

    files = re.findall(r'file="([^"]+)"', (out / "series.pvd").read_text())
    assert len(files) >= 2 * 50 and all((out / f).is_file() for f in files)


def test_demo_refuses_a_file_as_output(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("x")
    assert main(["demo", "--out", str(f)]) == 2
    assert "taken" in capsys.readouterr().err
