"""Every command in docs/RADIOTHERAPY.md is a command the CLI takes, and the worked examples run.

Why: the worked example compared ``dvf --scan 1`` with ``track --volume-ml 3968`` (different frames
and volumes, 40.8 mm apart); a document whose commands are not run drifts. The commands are read
from the document itself (its indented code blocks), so a new or changed command is checked too.
"""

from __future__ import annotations

import shlex
import shutil
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import typer

from lungdeform.cli.main import main, make_app
from tests.conftest import require_path

DOC = Path(__file__).resolve().parents[1] / "docs" / "RADIOTHERAPY.md"


def doc_commands() -> list[str]:
    """The ``lungdeform …`` commands of the document's indented code blocks, continuation lines
    (``\\``) joined, trailing ``# comments`` dropped, in order, each once."""
    out, current = [], None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        text = line.strip()
        if current is None and not (line.startswith("    ") and text.startswith("lungdeform ")):
            continue
        text = text.split("  #")[0].strip()
        current = (current or "") + " " + text.rstrip("\\").strip()
        if not text.endswith("\\"):
            if current.strip() not in out:
                out.append(current.strip())
            current = None
    return out


def _command(tokens: list[str]):
    """The click command a token list names (``validate itk-pair`` walks the group), and the rest."""
    cmd = typer.main.get_command(make_app())
    rest = tokens[1:]
    while hasattr(cmd, "commands"):  # a group
        cmd, rest = cmd.commands[rest[0]], rest[1:]
    return cmd, rest


def test_the_document_has_its_commands_and_each_is_one_the_cli_takes():
    # why: every option a documented command uses must exist on that command (a renamed or removed
    # option is a document that no longer runs); the worked example uses track --scan, not a volume
    commands = doc_commands()
    assert len(commands) >= 8
    for command in commands:
        cmd, rest = _command(shlex.split(command))
        known = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
        unknown = [t.split("=")[0] for t in rest if t.startswith("--") and t.split("=")[0] not in known]
        assert not unknown, f"{command}: {unknown} not options of {cmd.name}"
    example = [c for c in commands if c.startswith("lungdeform track itk/model.npz --points")]
    assert example and "--scan 1" in example[0] and "--volume-ml" not in example[0]


def _substitute(command: str, values: dict) -> list[str]:
    for key, value in values.items():
        command = command.replace(key, str(value))
    return shlex.split(command)[1:]


def test_worked_example_1_runs_and_track_agrees_with_dvf(data_dir, tmp_path, monkeypatch):
    # the ITK pair's commands as written (the fit quicker: 60 evaluations, 3 folds, no baselines,
    # instead of `validate itk-pair`'s defaults); then the frames check the document states: the 51
    # landmarks through dvf.mha (SimpleITK) land where `track --scan 1` puts them, within 0.01 mm
    from lungdeform.evaluate.pipeline import run_fit
    from lungdeform.fit.config import FitConfig, FitInputs
    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    monkeypatch.chdir(tmp_path)
    files = [folder / f"CT_3D_lung_{n}" for n in ("fixed_mask.mha", "moving_mask.mha",
                                                   "fixed_point_set_corrected.txt", "moving_point_set_corrected.txt")]
    run_fit(FitInputs(files[:2], "right", landmarks=files[2:]), tmp_path / "itk",
            FitConfig(baselines=False, max_evaluations=60, folds=3))
    values = {"$LUNGDEFORM_DATA": data_dir, "$D": folder, ".../": f"{folder}/"}
    ran = 0
    for command in doc_commands():
        if "itk/model.npz" not in command and "h11-itk" not in command:
            continue
        command = command.replace("/tmp/h11-itk/", "itk/")
        if " validate itk-pair" in command:
            continue  # the fit above
        args = _substitute(command, values)
        out = Path(args[args.index("--out") + 1])
        if out.is_file():
            out.unlink()  # the "Measured" section writes the same names
        assert main(args) == 0, command
        ran += 1
    assert ran >= 4
    field = sitk.DisplacementFieldTransform(sitk.ReadImage("dvf.mha", sitk.sitkVectorFloat64))
    rows = Path("landmarks/trajectories.csv").read_text().splitlines()[1:]
    via_track = np.array([[float(x) for x in r.split(",")[5:8]] for r in rows])
    fixed = np.loadtxt(files[2], skiprows=2)
    via_dvf = np.array([field.TransformPoint(tuple(p)) for p in fixed])
    assert len(via_track) == 51 and np.abs(via_dvf - via_track).max() < 0.01


def test_worked_example_2_runs_on_a_smaller_popi(data_dir, tmp_path, monkeypatch):
    # the POPI commands as written, on the CT downsampled 4 × 4 × 2 (a DICOM series keeping POPI's
    # UIDs: the full grid takes 7.5 min), with a 12 mm GTV sphere and a 500 mL cosine curve as the
    # document describes them
    from lungdeform.geometry.mesh import icosphere
    from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
    from tests.cli.test_warp import _curve
    from tests.popi_workflow import downsampled_series, extract_popi

    monkeypatch.chdir(tmp_path)
    downsampled_series(extract_popi(data_dir, tmp_path / "full"), tmp_path / "popi00", (2, 4, 4))
    shutil.rmtree(tmp_path / "full")
    _curve(Path("curve.csv"))
    sphere = icosphere(3, 12.0, center=(-90.0, 80.0, -50.0))
    write_rtstruct("gtv.dcm", read_ct_series(tmp_path / "popi00"), [("GTV", sphere.vertices, sphere.faces, "GTV")])
    ran = 0
    commands = doc_commands()  # the worked example, then the generic structure commands on its model and CT
    for command in [c for c in commands if "popi" in c or "4dct" in c] + [c for c in commands if "MODEL" in c]:
        if "MODEL" in command:
            from lungdeform.io.modelfile import load_model
            ee = sum(lung.volume_ee_ml for lung in load_model("popi.npz").lungs.values())
            values = {"MODEL": "popi.npz", "plan_rs.dcm": "gtv.dcm", "CT_FOLDER": "popi00", "track_out": "track_generic",
                      "3361": f"{ee:.0f}", "3968": f"{ee + 500:.0f}"}  # the ITK pair's volumes → this model's
        else:
            values = {}
        assert main(_substitute(command, values)) == 0, command
        ran += 1
    assert ran >= 6 and Path("track/structure_motion.csv").is_file()
