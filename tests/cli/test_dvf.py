"""``lungdeform dvf`` on a small synthetic model and image (the fixture is shared with test_warp)."""

import numpy as np
import pydicom
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


def _state_lines(text: str) -> list[str]:
    """The phase lines a command printed: ``phase i of N (P %) at t = … s (+X mL above end-exhale)``."""
    return [ln.split(":", 1)[0].split(" field at ")[-1] for ln in text.splitlines()
            if ln.lstrip().startswith(("phase ", "forward field at phase", "inverse field at phase"))]


def test_dvf_phases_are_warps_phases_one_field_and_one_coarse_reg_each(files, tmp_path, capsys):
    # why: one breath through every command (no volumes added by hand): `dvf --phases N` gives the
    # states of `warp --phases N` and `track --phases N` phase for phase (the same printed states,
    # track's delta_ml), and its inverse fields reproduce warp's phase images (SimpleITK's linear
    # resampling of the source through each field against warp's output: ≤ 1 HU after rounding).
    # An end-inhale model: phase 0 is the scan (a zero field). Each phase's REG holds the forward
    # field sampled on a grid of at most 3 mm in-plane (the field's 2.4 mm; its 8 mm slices kept): exactly the
    # coarsened .mha), references that phase's series of the 4-D CT, and passes dciodvfy
    from lungdeform.io.image import write_image
    from lungdeform.model.lung import Model
    from lungdeform.model.scan_state import ScanState
    from lungdeform.playback.displacement_field import Grid
    from lungdeform.playback.field_grid import coarse_grid, coarsened
    from tests.io.dicom_support import dciodvfy
    d, m = files
    model = tmp_path / "ei.npz"
    save_model(model, Model(m.lungs, m.provenance, ScanState("end-inhale", 500.0)))
    ref = read_image(d / "ref.nii.gz")
    hu = (np.repeat(np.repeat(ref.array, 2, axis=1), 2, axis=2).astype(np.int16) * 400 - 1000).astype(np.int16)
    spacing = np.asarray(ref.spacing) * [0.5, 0.5, 1.0]
    write_image(tmp_path / "ct.mha", hu, spacing, ref.origin, ref.direction)
    from lungdeform.io.dicom import series as DS
    from lungdeform.io.grid import Image
    DS.write_ct_series(tmp_path / "src", Image(hu, spacing, ref.origin, ref.direction), DS.study_header(), description="CT")
    phases = ["--phases", "4"]
    assert main(["warp", str(tmp_path / "ct.mha"), str(model), *phases, "--out", str(tmp_path / "w.mha")]) == 0
    assert main(["warp", str(tmp_path / "src"), str(model), *phases, "--out", str(tmp_path / "4dct")]) == 0
    warped = _state_lines(capsys.readouterr().out)
    assert main(["dvf", str(model), "--reference", str(tmp_path / "src"), *phases, "--out", str(tmp_path / "u.mha"),
                 "--out-reg", str(tmp_path / "reg.dcm"), "--moving", str(tmp_path / "4dct")]) == 0
    text = capsys.readouterr().out
    assert _state_lines(text) == warped[:4] and len(warped) == 8
    assert "the scan (end-inhale, 500 mL above end-exhale) is at 0 % of the cycle" in text
    assert text.count("trilinear interpolation of it differs from the full field by at most") == 4
    assert main(["dvf", str(model), "--reference", str(tmp_path / "ct.mha"), *phases, "--inverse",
                 "--out", str(tmp_path / "w_inv.mha")]) == 0
    capsys.readouterr()
    src = sitk.ReadImage(str(tmp_path / "ct.mha"), sitk.sitkFloat32)
    grid = Grid.of(read_image(tmp_path / "ct.mha"))
    for k in range(4):
        u = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / f"u_phase{k:02d}.mha")))
        if k == 0:  # end-inhale: the scan itself
            assert np.abs(u).max() == 0.0
        field = sitk.ReadImage(str(tmp_path / f"w_inv_phase{k:02d}.mha"), sitk.sitkVectorFloat64)
        out = sitk.Resample(src, src, sitk.DisplacementFieldTransform(field), sitk.sitkLinear, -1000.0)
        mine = read_image(tmp_path / f"w_phase{k:02d}.mha").array.astype(float)
        assert np.abs(np.round(sitk.GetArrayFromImage(out)) - mine).max() <= 1.0
        reg = pydicom.dcmread(tmp_path / f"reg_phase{k:02d}.dcm")
        item = reg.DeformableRegistrationSequence[-1]
        g = item.DeformableRegistrationGridSequence[0]
        nx, ny, nz = g.GridDimensions
        assert [float(x) for x in g.GridResolution][2] == 8.0 and max(g.GridResolution[:2]) <= 3.0 and (nx, ny) == (121, 73)
        raw = np.frombuffer(g.VectorGridData, "<f4").reshape(nz, ny, nx, 3)
        assert np.array_equal(raw, coarsened(u, grid, coarse_grid(grid, 3.0)))
        folder = tmp_path / "4dct" / DS.phase_folder(k, 4)
        uids = {pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID for p in folder.iterdir()}
        assert {r.ReferencedSOPInstanceUID for r in item.ReferencedImageSequence} == uids
    assert dciodvfy(tmp_path / "reg_phase02.dcm")[0] == []
    # one phase: the same field as in the set; track's frames are the same states
    assert main(["dvf", str(model), "--reference", str(tmp_path / "src"), *phases, "--phase", "2",
                 "--out", str(tmp_path / "u2.mha")]) == 0
    assert np.array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u2.mha"))),
                          sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u_phase02.mha"))))
    (tmp_path / "p.csv").write_text("x_mm,y_mm,z_mm\n90,0,-40\n")
    assert main(["track", str(model), "--points", str(tmp_path / "p.csv"), *phases, "--out", str(tmp_path / "t")]) == 0
    rows = (tmp_path / "t" / "trajectories.csv").read_text().splitlines()[1:]
    assert [f"{float(r.split(',')[1]):+.0f} mL" for r in rows] == [ln.rsplit("(", 1)[1].split(" above")[0] for ln in warped[:4]]


@pytest.mark.parametrize("args, needle", [
    (["--curve", "c.csv"], "--curve goes with --phases N"),
    (["--phases", "4", "--phase", "4"], "--phase must be 0 to 3"),
    (["--phases", "4", "--volume-ml", "4000"], "--phases with --volume-ml or --scan"),
    (["--phases", "4", "--tidal-ml", "600", "--curve", "c.csv"], "--tidal-ml applies to --preset or the plain cycle"),
    (["--phases", "4", "--preset", "normal", "--curve", "c.csv"], "--curve and --preset are mutually exclusive"),
    (["--phases", "4", "--phase-zero", "peak"], "--phase-zero must be one of end-inhale, end-exhale, start"),
    ([], "give --volume-ml, --scan or --phases N (states over a breath: --curve CSV ('lungdeform breathe"),
])
def test_dvf_breath_options_that_do_not_go_together_are_one_line(files, tmp_path, capsys, args, needle):
    d, _ = files
    (tmp_path / "c.csv").write_text("t_s,volume_ml\n0,0\n2,500\n4,0\n")
    args = [str(tmp_path / a) if a == "c.csv" else a for a in args]
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ref.nii.gz"), *args,
                 "--out", str(tmp_path / "u.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]
