"""``lungdeform validate single-scan`` and ``learn-default``: bad input exits 2 with one line and no output."""

from lungdeform.cli.main import main


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
