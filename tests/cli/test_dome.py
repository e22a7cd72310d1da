"""``build``/``demo`` ``--dome-mm`` and ``--breathing`` (cli/common.py): recorded when given, refused with one
line and exit 2 (nothing written) when not a dome excursion, or when the volume cannot produce it."""

import json

import pytest

from lungdeform.cli.main import main
from lungdeform.data import default_lungs
from lungdeform.geometry.dome import dome_weights
from lungdeform.io.meshfile import write_mesh
from lungdeform.io.modelfile import load_model
from lungdeform.model.dome import ACCEPT_MM, BREATHING


@pytest.fixture
def left_lung(tmp_path):
    lung = default_lungs()["left"]
    return write_mesh(tmp_path / "left.ply", lung.vertices, lung.faces)


def test_build_records_the_dome_it_was_told(tmp_path, left_lung, capsys):
    # one number: the lone left lung's dome descends 6 mm over its share of the breath (232 mL of 500 mL); the
    # model file says what was asked, where it came from and what the built lung does (measured on it)
    out = tmp_path / "m.npz"
    assert main(["build", str(left_lung), "--side", "left", "--out", str(out), "--dome-mm", "6"]) == 0
    rec = load_model(out).provenance["dome"]
    assert rec["asked_mm"] == {"left": 6.0} and rec["source"] == "--dome-mm 6"
    assert rec["measured_mm"]["left"] == pytest.approx(6.0, abs=ACCEPT_MM + 1e-3)
    assert "left: dome excursion 6.0 mm relative to the apex over +232 mL" in capsys.readouterr().out
    # per side, and the shorthand: mm per litre inspired × --tidal-ml
    assert main(["build", str(left_lung), "--side", "left", "--out", str(out), "--dome-mm", "left=4.5"]) == 0
    assert load_model(out).provenance["dome"]["asked_mm"] == {"left": 4.5}
    assert main(["build", str(left_lung), "--side", "left", "--out", str(out), "--breathing", "belly",
                 "--tidal-ml", "400"]) == 0
    m = load_model(out)  # the lone left lung takes 46.4 % of 400 mL; E = κ·ΔV/F
    lung = m.lungs["left"]
    footprint = dome_weights(lung.surface.vertices, lung.surface.faces).footprint_mm2
    assert lung.calibration_ml == pytest.approx(0.464 * 400.0)
    assert m.provenance["dome"]["asked_mm"]["left"] == pytest.approx(BREATHING["belly"] * lung.calibration_ml * 1000
                                                                     / footprint, abs=1e-3)


@pytest.mark.parametrize("args, message", [
    (["--dome-mm", "nan"], "--dome-mm must be a number of mm in [0, 150]"),
    (["--dome-mm", "inf"], "--dome-mm must be a number of mm in [0, 150]"),
    (["--dome-mm", "-3"], "--dome-mm must be ≥ 0 mm (a dome that rises on inspiration"),
    (["--dome-mm", "ten"], "--dome-mm must be a number of mm, got 'ten'"),
    (["--dome-mm", "left=3,left=4"], "--dome-mm must be MM or 'left=MM,right=MM'"),
    (["--dome-mm", "right=5"], "no dome excursion given for the left lung"),
    (["--dome-mm", "5", "--breathing", "chest"], "give --dome-mm or --breathing, not both"),
    (["--breathing", "deep"], "--breathing must be one of chest, mixed, belly"),
    (["--dome-mm", "40"], "left lung: a dome excursion of 40 mm cannot come with +232 mL: the floor"),
])
def test_build_refuses_what_is_not_a_dome_excursion(tmp_path, left_lung, capsys, args, message):
    out = tmp_path / "m.npz"
    assert main(["build", str(left_lung), "--side", "left", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_demo_with_chest_breathing(tmp_path, capsys):
    # the embedded lungs breathing with the chest: each floor sweeps 30 % of its lung's share, said and recorded
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--breathing", "chest", "--duration", "0.5"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dome"]["share"] == BREATHING["chest"] and set(summary["dome"]["asked_mm"]) == {"left", "right"}
    text = capsys.readouterr().out
    for side, mm in summary["dome"]["asked_mm"].items():
        assert 2.0 < mm < 5.0 and f"{side}: dome excursion {summary['dome']['measured_mm'][side]:.1f} mm" in text
    assert main(["demo", "--out", str(tmp_path / "d2"), "--dome-mm", "-1"]) == 2
    assert not (tmp_path / "d2").exists()
