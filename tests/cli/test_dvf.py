"""``lungdeform dvf`` on a small synthetic model and image (the fixture is shared with test_warp)."""

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.io.image import read_image, write_image
from lungdeform.io.modelfile import save_model
from tests.browser.support import two_lungs


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A two-lung model file and a label image of its lungs' boxes on a coarse grid."""
    d = tmp_path_factory.mktemp("dvf")
    m = two_lungs(2)
    save_model(d / "model.npz", m)
    a = np.zeros((42, 45, 75), np.uint8)
    a[12:30, 10:35, 8:30] = 1
    a[12:30, 10:35, 45:67] = 2
    write_image(d / "ref.nii.gz", a, [4.8, 4.8, 8.0], [-180.0, -108.0, -166.0], np.eye(3))
    return d, m


def test_dvf_writes_a_vector_field_on_the_reference_grid(files, tmp_path, capsys):
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    out = tmp_path / "u.mha"
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), "--volume-ml", str(ee + 300),
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Jacobian determinant: min" in text and "forward field" in text
    img = sitk.ReadImage(str(out))
    ref = read_image(d / "ref.nii.gz")
    # a 3-component float32 vector image on the reference's grid (what ITK/Slicer read as a DVF)
    assert img.GetNumberOfComponentsPerPixel() == 3 and img.GetPixelIDTypeAsString() == "vector of 32-bit float"
    assert np.allclose(img.GetOrigin(), ref.origin) and np.allclose(img.GetSpacing(), ref.spacing)
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), "--volume-ml", str(ee + 300),
                 "--inverse", "--out", str(tmp_path / "w.nrrd")]) == 0
    assert "residual" in capsys.readouterr().out


def test_dvf_bad_input_is_one_line(files, tmp_path, capsys):
    d, _ = files
    # a format it cannot write, before any work; and --scan on a model no fit wrote
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), "--volume-ml", "3000",
                 "--out", str(tmp_path / "u.png")]) == 2
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), "--scan", "1",
                 "--out", str(tmp_path / "u.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "unknown output image format" in err[0] and "volumes_ml" in err[1]
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args, needle", [
    (["--volume-ml", "1e9"], "--volume-ml must be a finite number in (0, 20000] mL"),
    (["--volume-ml", "15000"], "no lung reaches that"),
    (["--volume-ml", "1000"], "no lung reaches that"),
    (["--volume-ml", "5000", "--node-mm", "1e9"], "--node-mm must be a finite number in (0, 20] mm"),
    (["--volume-ml", "5000", "--node-mm", "inf"], "--node-mm must be a finite number in (0, 20] mm"),
])
def test_dvf_unreachable_volume_or_absurd_node_spacing_is_refused(files, tmp_path, capsys, args, needle):
    # why: --volume-ml 1e9 tried to allocate 926 TiB (a traceback); 15000 mL (3.5 × this model's
    # end-exhale) took minutes and gigabytes for a state no lung reaches; --node-mm 1e9 wrote a zero
    # field and --node-mm inf said "does not overlap"; each is refused before the image is read
    d, _ = files
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), *args,
                 "--out", str(tmp_path / "u.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not list(tmp_path.iterdir())


def test_a_field_beyond_the_lattice_cap_is_refused_before_it_is_allocated(files, monkeypatch):
    # why: the fade margin grows with the motion, and with it the lattice; a state whose lattice
    # would pass MAX_LATTICE_NODES is an InputError naming the margin, not a MemoryError
    from lungdeform.errors import InputError
    from lungdeform.playback import displacement_field as D

    d, m = files
    monkeypatch.setattr(D, "MAX_LATTICE_NODES", 1000)
    grid = D.Grid.of(read_image(d / "ref.nii.gz"))
    with pytest.raises(InputError, match="lattice nodes .* fade margin"):
        D.displacement_field(m, grid, 300.0)


def test_track_scan_is_in_the_frame_and_state_of_dvf_scan(files, tmp_path, capsys):
    # why: `dvf --scan K` maps x → A⁻¹(x + u(x)) (the fit's alignment A of scan K undone); `track
    # --scan K` must give the same point: the forward field sampled at the points by SimpleITK's
    # DisplacementFieldTransform equals track's displacement (within the lattice's error, 0.1 mm);
    # --no-rigid leaves A out of both (a 7 mm shift here), and the two still agree
    from lungdeform.model.lung import Model
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    a = np.eye(4)
    a[:3, 3] = [2.0, -3.0, 6.0]  # scan 1 → model frame
    fitted = tmp_path / "fitted.npz"
    save_model(fitted, Model(m.lungs, {"volumes_ml": [ee, ee + 300.0], "alignment": [{"applied": {"matrix": a.tolist()}}]}))
    pts = np.array([[90.0, 0.0, -40.0], [-90.0, 10.0, 20.0]])
    (tmp_path / "p.csv").write_text("x_mm,y_mm,z_mm\n" + "".join(f"{x},{y},{z}\n" for x, y, z in pts))
    moved = {}
    for extra in ([], ["--no-rigid"]):
        key = "no-rigid" if extra else "scan"
        assert main(["dvf", str(fitted), "--reference", str(d / "ref.nii.gz"), "--scan", "1", *extra,
                     "--out", str(tmp_path / f"{key}.mha")]) == 0
        assert main(["track", str(fitted), "--points", str(tmp_path / "p.csv"), "--scan", "1", *extra,
                     "--out", str(tmp_path / key)]) == 0
        field = sitk.ReadImage(str(tmp_path / f"{key}.mha"), sitk.sitkVectorFloat64)
        tx = sitk.DisplacementFieldTransform(field)
        via_dvf = np.array([tx.TransformPoint(tuple(p)) for p in pts])
        rows = (tmp_path / key / "trajectories.csv").read_text().splitlines()[1:]
        via_track = np.array([[float(x) for x in r.split(",")[5:8]] for r in rows])
        assert np.abs(via_dvf - via_track).max() < 0.1, (via_dvf, via_track)
        moved[key] = via_track
    assert np.allclose(moved["scan"] - moved["no-rigid"], -a[:3, 3], atol=1e-6)
    capsys.readouterr()
    assert main(["track", str(fitted), "--points", str(tmp_path / "p.csv"), "--no-rigid",
                 "--out", str(tmp_path / "x")]) == 2
    assert main(["track", str(fitted), "--points", str(tmp_path / "p.csv"), "--scan", "1", "--volume-ml", "3000",
                 "--out", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--no-rigid applies to --scan" in err[0] and "--scan names one state" in err[1]
