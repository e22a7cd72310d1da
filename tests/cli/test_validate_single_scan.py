"""``lungdeform validate single-scan`` and ``learn-default``: bad input exits 2 with one line and no output."""

import pytest

from lungdeform.cli.main import main
from lungdeform.geometry.regions import REGIONS
from tests.validate.test_copd import phantom_case
from tests.validate.test_lung_pair import _cut_folder


def test_folder_without_subjects(tmp_path, capsys):
    # no two-volume subject: exit 2, one line naming the folder, no output folder created
    out = tmp_path / "out"
    assert main(["validate", "single-scan", "--data", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0] and "no two-volume subject" in err[0]
    assert not out.exists()


def test_unknown_default_names_the_option(tmp_path, capsys):
    # a bad --default is refused before anything is read or written
    data = tmp_path / "pair"
    data.mkdir()
    for name in ("CT_3D_lung_fixed_mask.mha", "CT_3D_lung_moving_mask.mha",
                 "CT_3D_lung_fixed_point_set_corrected.txt", "CT_3D_lung_moving_point_set_corrected.txt"):
        (data / name).write_text("x")
    out = tmp_path / "out"
    assert main(["validate", "single-scan", "--data", str(data), "--out", str(out), "--default", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--default must be one of population, paper" in err[0]
    assert not out.exists()


def test_learn_default_refuses_a_folder_as_out(tmp_path, capsys):
    assert main(["learn-default", "--data", str(tmp_path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a folder" in err[0]


def test_build_with_paper_constants_records_it(tmp_path, capsys):
    # build --constants paper: Table I, and the model file says so
    from lungdeform.data import default_lungs
    from lungdeform.io.meshfile import write_mesh
    from lungdeform.io.modelfile import load_model

    lung = default_lungs()["left"]
    path = write_mesh(tmp_path / "left.ply", lung.vertices, lung.faces)
    out = tmp_path / "m.npz"
    assert main(["build", str(path), "--side", "left", "--out", str(out), "--constants", "paper"]) == 0
    assert load_model(out).provenance["default"]["name"] == "paper"
    assert main(["build", str(path), "--side", "left", "--out", str(out), "--constants", "x"]) == 2
    assert "--constants must be one of" in capsys.readouterr().err


@pytest.mark.slow
def test_two_folders_one_without_landmarks_print_every_lung_and_the_regions(tmp_path, capsys):
    # truth: two folders (a COPDgene-named phantom with landmarks, .mha masks without and cut by the field
    # of view): every lung on its own line, the cut ones marked, '-' for a landmark error that does not
    # exist, the medians over 4 lungs (landmarks over 2) and one line per surface region; a subject lacking
    # its second landmark file is said, and scored on the surface
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    phantom_case(a, n=2)
    _cut_folder(b)
    (b / "cut_exp_landmarks.txt").write_text("point\n0\n")
    out = tmp_path / "out"
    assert main(["validate", "single-scan", "--data", str(a), "--data", str(b), "--out", str(out),
                 "--default", "population", "--cache", str(tmp_path / "cache")]) == 0
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == [
        f"warning: {b}: cut: lacks cut_insp_landmarks.txt (its landmarks are not used)"]
    lines = captured.out.splitlines()
    cut = [ln for ln in lines if ln.startswith("cut/left*")]
    assert len(cut) == 1 and cut[0].split()[2:4] == ["/", "-"]  # surface / no landmark error
    assert any(ln.startswith("median (4)") for ln in lines)
    assert "landmark medians over the 2 lungs with landmarks; * cut by the field of view (2:" in captured.out
    assert [ln.split()[0] for ln in lines if ln.split() and ln.split()[0] in REGIONS] == list(REGIONS)
    assert len(list((tmp_path / "cache" / "pairs").iterdir())) == 4 and not (out / "pairs").exists()
