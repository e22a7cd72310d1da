"""``lungdeform warp`` on a small synthetic model and image."""


import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.geometry.mesh import icosphere
from lungdeform.io.dicom import series as DS
from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.modelfile import load_model
from tests.cli.test_dvf import files  # noqa: F401  (the shared module fixture)
from tests.conftest import require_path
from tests.io.dicom_support import dciodvfy
from tests.popi_workflow import downsampled_series, extract_popi, popi_model


def test_warp_keeps_labels_and_metadata(files, tmp_path):
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    out = tmp_path / "w.nii.gz"
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 300), "--label",
                 "--out", str(out)]) == 0
    ref, got = read_image(d / "ref.nii.gz"), read_image(out)
    assert got.array.dtype == ref.array.dtype and set(np.unique(got.array)) == {0, 1, 2}
    assert np.allclose(got.origin, ref.origin) and np.allclose(got.spacing, ref.spacing)
    # inhaling: the labelled lungs grow (the boxes stand in for the lungs, so they grow too)
    assert (got.array > 0).sum() > (ref.array > 0).sum()


def test_warp_phases_over_a_curve(files, tmp_path):
    d, _ = files
    curve = tmp_path / "c.csv"
    t = np.linspace(0, 8, 161)
    curve.write_text("t_s,volume_ml\n" + "".join(f"{a:.3f},{250 * (1 - np.cos(np.pi * a / 2)):.3f}\n" for a in t))
    out = tmp_path / "ct.mha"
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--curve", str(curve), "--phases", "2",
                 "--out", str(out)]) == 0
    names = sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".mha")
    assert names == ["ct_phase00.mha", "ct_phase01.mha"]


def test_warp_preset_phases_are_the_phases_of_track_preset(files, tmp_path, capsys):
    # why: warp takes --preset as track does (no curve written by hand); given the same preset the
    # two commands play the same states, phase for phase (track's delta_ml, warp's printed states)
    d, _ = files
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--preset", "deep", "--phases", "3",
                 "--label", "--out", str(tmp_path / "w.mha")]) == 0
    text = capsys.readouterr().out
    states = [ln.rsplit("(", 1)[1].split(" above")[0] for ln in text.splitlines() if ln.startswith("phase ")]
    assert len(states) == 3 and "preset" in text and "deep" in text
    (tmp_path / "p.csv").write_text("x_mm,y_mm,z_mm\n90,0,-40\n")
    assert main(["track", str(d / "model.npz"), "--points", str(tmp_path / "p.csv"), "--preset", "deep", "--phases", "3",
                 "--out", str(tmp_path / "t")]) == 0
    rows = (tmp_path / "t" / "trajectories.csv").read_text().splitlines()[1:]
    assert [f"{float(r.split(',')[1]):+.0f} mL" for r in rows] == states


def _curve(path):
    t = np.linspace(0, 8, 161)
    path.write_text("t_s,volume_ml\n" + "".join(f"{a:.3f},{250 * (1 - np.cos(np.pi * a / 2)):.3f}\n" for a in t))
    return path


def test_warp_phases_to_dicom_series(files, tmp_path):
    # a source given as a DICOM series: each phase a series of its own in OUT/phaseNN (NN the
    # percentage) that SimpleITK reads on the source's grid, the source's study and frame of
    # reference kept, a new series each, the phase in the description and the temporal tags
    d, _ = files
    ref = read_image(d / "ref.nii.gz")
    head = DS.study_header()
    DS.write_ct_series(tmp_path / "src", Image(ref.array, ref.spacing, ref.origin, ref.direction), head,
                       description="4D")
    out = tmp_path / "4dct"
    args = ["--curve", str(_curve(tmp_path / "c.csv")), "--phases", "2"]
    assert main(["warp", str(tmp_path / "src"), str(d / "model.npz"), *args, "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["phase00", "phase50"]
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), *args, "--out", str(tmp_path / "ct.mha")]) == 0
    series = set()
    for i, name in enumerate(["phase00", "phase50"]):
        got, mha = read_image(out / name), read_image(tmp_path / f"ct_phase{i:02d}.mha")
        assert np.allclose(got.origin, ref.origin) and np.allclose(got.spacing, ref.spacing)
        # the same resampling as the .mha output; HU stored as whole numbers (≤ 0.5 apart)
        assert np.abs(got.array - mha.array.astype(float)).max() <= 0.5
        ds = pydicom.dcmread(out / name / "CT0001.dcm")
        assert ds.StudyInstanceUID == head.StudyInstanceUID and ds.FrameOfReferenceUID == head.FrameOfReferenceUID
        assert ds.SeriesDescription == f"4D phase {50 * i}%" and ds.TemporalPositionIdentifier == i + 1
        assert ds.NumberOfTemporalPositions == 2
        series.add(ds.SeriesInstanceUID)
    assert len(series) == 2


def test_warp_one_state_to_a_dicom_folder_of_a_nifti_source(files, tmp_path, capsys):
    # a NIfTI source has no study: a new Study and Frame of Reference UID; the one series fills OUT
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    out = tmp_path / "ct"
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 300),
                 "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    ds = pydicom.dcmread(out / "CT0001.dcm")
    assert ds.SeriesDescription == "ref lungdeform warp" and "TemporalPositionIndex" not in ds
    assert read_image(out).array.shape == read_image(d / "ref.nii.gz").array.shape


def test_warp_dicom_refusals_write_nothing(files, tmp_path, capsys):
    # a label map is not a CT series; a folder holding something else would be replaced: both
    # exit 2 with one line before any work, and leave the folder as it was
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    base = ["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 300)]
    assert main([*base, "--label", "--out", str(tmp_path / "lab")]) == 2
    assert "not written as a DICOM CT series" in capsys.readouterr().err
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "plan.txt").write_text("keep")
    assert main([*base, "--out", str(tmp_path / "mine")]) == 2
    assert "plan.txt" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["plan.txt"]


@pytest.mark.realdata
def test_popi_ten_phase_dicom_4dct_and_its_rtstruct(data_dir, tmp_path, capsys):
    # the POPI phase-00 CT → lung masks → a model; the CT (downsampled 4 × 4 × 2 and a 12 mm field
    # lattice, to keep this near 35 s; a DICOM series keeping POPI's UIDs) warped to 10 phases as DICOM: SimpleITK's
    # series reader opens each phase; a 12 mm "GTV" sphere in the right lung (-857 HU at
    # (-90, 80, -50) mm LPS, docs/RADIOTHERAPY.md) tracked to the 10 phases is written as one
    # RTSTRUCT on phase00 that pydicom reads, every referenced SOP Instance UID a slice of phase00
    popi = extract_popi(data_dir, tmp_path)
    model = popi_model(popi, tmp_path, 1000)
    head = downsampled_series(popi, tmp_path / "ct", (2, 4, 4))
    curve = _curve(tmp_path / "c.csv")
    assert main(["warp", str(tmp_path / "ct"), str(model), "--curve", str(curve), "--phases", "10",
                 "--node-mm", "12", "--out", str(tmp_path / "4dct")]) == 0
    for i in range(10):
        folder = str(tmp_path / "4dct" / DS.phase_folder(i, 10))
        reader = sitk.ImageSeriesReader()
        reader.SetFileNames(reader.GetGDCMSeriesFileNames(folder))
        assert reader.Execute().GetSize() == (128, 128, 71)
        assert pydicom.dcmread(f"{folder}/CT0001.dcm").StudyInstanceUID == head.StudyInstanceUID
    sphere = icosphere(3, 12.0, center=(-90.0, 80.0, -50.0))
    write_rtstruct(tmp_path / "gtv.dcm", read_ct_series(tmp_path / "ct"), [("GTV", sphere.vertices, sphere.faces, "GTV")])
    assert main(["track", str(model), "--rtstruct", str(tmp_path / "gtv.dcm"), "--structure", "GTV",
                 "--curve", str(curve), "--phases", "10", "--out", str(tmp_path / "track"),
                 "--out-rtstruct", str(tmp_path / "gtv_phases.dcm"),
                 "--reference-ct", str(tmp_path / "4dct" / "phase00")]) == 0
    ds = pydicom.dcmread(tmp_path / "gtv_phases.dcm")
    # one ROI per phase, then the ITV (their union) that track adds (docs/RADIOTHERAPY.md)
    assert [r.ROIName for r in ds.StructureSetROISequence] == [f"GTV@phase{i:02d}" for i in range(10)] + ["ITV_GTV"]
    refs = {c.ContourImageSequence[0].ReferencedSOPInstanceUID for r in ds.ROIContourSequence
            for c in r.ContourSequence}
    slices = {pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID
              for p in (tmp_path / "4dct" / "phase00").iterdir()}
    assert refs and refs <= slices and ds.FrameOfReferenceUID == head.FrameOfReferenceUID
    # every DICOM kind written from the real CT passes dciodvfy with 0 errors (docs/RADIOTHERAPY.md,
    # "DICOM conformance"): the RTSTRUCT, a CT phase, and the REG of the 50 % phase's field, whose raw
    # vectors equal the .mha field (the last registration item names phase50's images)
    ee = sum(lung.volume_ee_ml for lung in load_model(model).lungs.values())
    assert main(["dvf", str(model), "--reference", str(tmp_path / "ct"), "--volume-ml", str(ee + 499.79),
                 "--node-mm", "12", "--out", str(tmp_path / "u50.mha"), "--out-reg", str(tmp_path / "reg.dcm"),
                 "--moving", str(tmp_path / "4dct" / "phase50")]) == 0
    for f in (tmp_path / "gtv_phases.dcm", tmp_path / "4dct" / "phase50" / "CT0036.dcm", tmp_path / "reg.dcm"):
        assert dciodvfy(f)[0] == [], f
    grid = pydicom.dcmread(tmp_path / "reg.dcm").DeformableRegistrationSequence[-1].DeformableRegistrationGridSequence[0]
    raw = np.frombuffer(grid.VectorGridData, "<f4").reshape(71, 128, 128, 3)
    assert np.abs(raw - sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u50.mha")))).max() <= 0.01


def _exact_lung_mass_change(tmp_path, ct, lungs, model, state, grid=None) -> tuple[float, float, float]:
    """The change of the lungs' mass (fraction) at ``state`` (warp's state options), ``lungs`` in ``ct``
    against ``lungs`` warped with --label in the --density image: (--density --no-lung-mask, --density
    (the model's rest lungs as the mask), --density --lung-mask)."""
    extra = [] if grid is None else ["--grid", str(grid)]
    args = ["warp", str(ct), str(model), *state, *extra, "--density"]
    assert main([*args, "--no-lung-mask", "--out", str(tmp_path / "old.mha")]) == 0
    assert main([*args, "--out", str(tmp_path / "model.mha")]) == 0
    assert main([*args, "--lung-mask", str(lungs), "--out", str(tmp_path / "new.mha")]) == 0
    assert main(["warp", str(lungs), str(model), *state, *extra, "--label", "--out", str(tmp_path / "moved.mha")]) == 0
    moved = read_image(tmp_path / "moved.mha")
    voxel = [float(np.prod(g.spacing)) / 1000 for g in (read_image(lungs), moved)]
    m0 = float(((read_image(ct).array.astype(float) + 1000) * (read_image(lungs).array > 0)).sum()) * voxel[0]
    return tuple(float(((read_image(tmp_path / n).array.astype(float) + 1000) * (moved.array > 0)).sum()) * voxel[1]
                 / m0 - 1 for n in ("old.mha", "model.mha", "new.mha"))


@pytest.mark.realdata
def test_popi_density_keeps_the_mass_of_the_exact_lungs(data_dir, tmp_path):
    # why: issue 27's aim, mass over the exact lung mask (the segmented lungs in the CT against them
    # warped with --label) within 1 % at +500 mL: the real CT's lung surface (≈ −800 HU against the
    # chest wall's ≈ 0) is where a linear resampling mixes wall into lung (today +1.80 % on the full
    # grid, docs/RADIOTHERAPY.md "Measured: mass"); here on the grid `segment --downsample 4` segments
    # (the CT block-averaged 4 × 4 in-plane, int16 as a CT), where the masks are exact: +5.1 % with
    # --no-lung-mask, −0.3 % with --lung-mask, +0.2 % by default (the model's rest lungs as the mask)
    popi = extract_popi(data_dir, tmp_path)
    model = popi_model(popi, tmp_path, 1000)
    from lungdeform.io.image import write_image
    from lungdeform.segment.ct import downsample
    ct = downsample(read_image(popi), (1, 4, 4))
    left, right = (read_image(tmp_path / "seg" / f"{s}_lung.nii.gz") for s in ("left", "right"))
    assert left.array.shape == ct.array.shape and np.allclose(left.origin, ct.origin, atol=1e-3)
    write_image(tmp_path / "ct.mha", np.rint(ct.array).astype(np.int16), ct.spacing, ct.origin, ct.direction)
    write_image(tmp_path / "lungs.mha", ((left.array > 0) | (right.array > 0)).astype(np.uint8), ct.spacing,
                ct.origin, ct.direction)
    ee = sum(lung.volume_ee_ml for lung in load_model(model).lungs.values())
    old, default, new = _exact_lung_mass_change(tmp_path, tmp_path / "ct.mha", tmp_path / "lungs.mha", model,
                                                ["--volume-ml", str(ee + 500)])
    # the default, the model's rest lungs rasterised on the CT's grid as the mask, also within 1 %;
    # --lung-mask within 1.5 %: since the interior prior is tapered to the surface (0.10) the field moves
    # the lungs by the model's whole volume change (+500.9 mL here, it moved 55 % of it before), its
    # Jacobian steeper under the surface (0.69–1.46), and on these 3.9 × 3.9 × 2 mm voxels the
    # nearest-neighbour label the mass is measured over rounds it (+448.9 mL): −1.10 %, was −0.3 %
    assert abs(new) < 0.015 and 0.01 < old and abs(default) < 0.01, (old, default, new)


@pytest.mark.realdata
def test_itk_pair_density_keeps_the_mass_of_the_exact_lung(data_dir, tmp_path):
    # why: the same on the ITK pair's right lung at its second volume (3968 mL, +605 mL, +18 %), as a
    # CT: −780 HU in the fixed mask, water around it, the grid padded by 12 voxels of water so that no
    # lung leaves it (the mask touches its cropped medial face); --no-lung-mask +4.5 %, --lung-mask +0.1 %,
    # the default (the model's rest lung as the mask) +0.6 %: the model is built with 3000 vertices, as
    # the default mask is only as close to the lung as the rest surface (with 1000 vertices, Dice 0.994
    # with the mask: +1.5 %; docs/RADIOTHERAPY.md "Density and projections")
    fixed = read_image(require_path(data_dir, "itk-right-lung-two-volumes", "CT_3D_lung_fixed_mask.mha"))
    from lungdeform.io.image import write_image
    mask = np.pad((fixed.array > 0).astype(np.uint8), 12)
    origin = fixed.origin - np.reshape(fixed.direction, (3, 3)) @ (12 * fixed.spacing)
    write_image(tmp_path / "lung.mha", mask, fixed.spacing, origin, fixed.direction)
    write_image(tmp_path / "ct.mha", np.where(mask > 0, -780, 0).astype(np.int16), fixed.spacing, origin, fixed.direction)
    assert main(["build", str(tmp_path / "lung.mha"), "--side", "right", "--target-vertices", "3000",
                 "--out", str(tmp_path / "model.npz")]) == 0
    old, default, new = _exact_lung_mass_change(tmp_path, tmp_path / "ct.mha", tmp_path / "lung.mha",
                                                tmp_path / "model.npz", ["--volume-ml", "3968"])
    assert abs(new) < 0.01 < old and abs(default) < 0.01, (old, default, new)


def test_warp_failure_in_a_later_phase_leaves_no_folder(files, tmp_path, monkeypatch, capsys):
    # phases are written into a hidden folder renamed at the end: a failure while writing phase 2
    # of 2 (a full disk, here an OSError) leaves neither OUT nor the hidden folder
    d, _ = files
    calls = []

    def failing(folder, *args, **kwargs):
        calls.append(folder)
        if len(calls) == 2:
            raise OSError(28, "No space left on device", str(folder))
        return write(folder, *args, **kwargs)

    write = DS.write_ct_series
    monkeypatch.setattr(DS, "write_ct_series", failing)
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--curve", str(_curve(tmp_path / "c.csv")),
                 "--phases", "2", "--out", str(tmp_path / "4dct")]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert len(calls) == 2 and sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]


def test_warp_phases_has_an_upper_bound(files, tmp_path, capsys):
    # why: --phases had no upper bound (10⁶ phases: hours of work and 10⁶ files); above
    # MAX_PHASES it is refused before the model is read
    d, _ = files
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--curve", str(_curve(tmp_path / "c.csv")),
                 "--phases", "1000000", "--out", str(tmp_path / "ct.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--phases must be 1 to 100" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]


def test_warp_refuses_outputs_that_would_destroy_an_input_or_misplace_a_file(files, tmp_path, capsys):
    # why: --out equal to the source image overwrote it; --out X.mha naming an existing folder
    # wrote a DICOM series into that folder; --out under a regular file failed with a bare
    # "File exists"; each is refused before any work, naming the path
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    source = tmp_path / "src.nii.gz"
    source.write_bytes((d / "ref.nii.gz").read_bytes())
    (tmp_path / "X.mha").mkdir()
    (tmp_path / "plain").write_text("a file")
    before = sorted(p.name for p in tmp_path.rglob("*"))
    cases = [(source, "would overwrite the input"), (tmp_path / "X.mha", "an existing folder where a file is meant"),
             (tmp_path / "plain" / "w.mha", f"{tmp_path / 'plain'} is a file, not a folder")]
    for out, needle in cases:
        assert main(["warp", str(source), str(d / "model.npz"), "--volume-ml", str(ee + 200), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and str(out) in err[0], err
    # a phase file that is the source: OUT_phase00.nii.gz is refused too
    phase0 = tmp_path / "ct_phase00.nii.gz"
    phase0.write_bytes(source.read_bytes())
    assert main(["warp", str(phase0), str(d / "model.npz"), "--curve", str(_curve(tmp_path / "c.csv")),
                 "--phases", "2", "--out", str(tmp_path / "ct.nii.gz")]) == 2
    assert "would overwrite the input" in capsys.readouterr().err
    assert source.read_bytes() == (d / "ref.nii.gz").read_bytes() == phase0.read_bytes()
    assert sorted(p.name for p in tmp_path.rglob("*")) == sorted([*before, "ct_phase00.nii.gz", "c.csv"])


def test_dvf_refuses_an_output_that_is_an_input(files, tmp_path, capsys):
    # why: --out equal to an input overwrote it (any command); refused before any work
    d, _ = files
    ref = tmp_path / "ref.nii.gz"
    ref.write_bytes((d / "ref.nii.gz").read_bytes())
    assert main(["dvf", str(d / "model.npz"), "--reference", str(ref), "--volume-ml", "4500", "--out", str(ref)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "would overwrite the input" in err[0], err
    assert ref.read_bytes() == (d / "ref.nii.gz").read_bytes() and [p.name for p in tmp_path.iterdir()] == ["ref.nii.gz"]


def _hu_image(d, tmp_path):
    """A CT-like float image on the fixture's grid: −800 HU in the lung boxes, water elsewhere, air
    in a 4-voxel rim (so nothing dense leaves the grid)."""
    ref = read_image(d / "ref.nii.gz")
    hu = np.where(ref.array > 0, -800.0, 0.0).astype(np.float32)
    hu[:4], hu[-4:], hu[:, :4], hu[:, -4:], hu[:, :, :4], hu[:, :, -4:] = (-1000.0,) * 6
    from lungdeform.io.image import write_image
    write_image(tmp_path / "hu.mha", hu, ref.spacing, ref.origin, ref.direction)
    return tmp_path / "hu.mha", ref


def test_warp_density_conserves_the_mass_that_a_plain_warp_adds(files, tmp_path, capsys):
    # why: mass = Σ (HU + 1000)/1000 · dV (g); an inhaled state resampled plainly keeps the lungs'
    # −800 HU over a larger volume and squeezes the water around them (mass not conserved),
    # --density scales by det ∇φ and keeps the image's mass within 1 % (the field is zero at the
    # grid's edge, so nothing leaves it)
    from lungdeform.playback.density import mass_g
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    hu, ref = _hu_image(d, tmp_path)
    args = ["warp", str(hu), str(d / "model.npz"), "--volume-ml", str(ee + 400)]
    assert main([*args, "--out", str(tmp_path / "plain.mha")]) == 0
    assert main([*args, "--density", "--out", str(tmp_path / "dens.mha")]) == 0
    text = capsys.readouterr().out
    # without --lung-mask the model's rest lungs are the tissue partition, and the output says so
    assert "mass conserved" in text and "lung mask for --density: the model's lungs at rest, rasterised" in text, text
    vox = float(np.prod(ref.spacing)) / 1000
    m0 = mass_g(read_image(hu).array, vox)
    plain, dens = (read_image(tmp_path / n).array for n in ("plain.mha", "dens.mha"))
    assert abs(mass_g(dens, vox) / m0 - 1) < 0.01
    lungs = read_image(d / "ref.nii.gz").array > 0
    assert abs(mass_g(plain, vox) / m0 - 1) > 0.01 > abs(mass_g(dens, vox) / m0 - 1)
    assert dens[lungs].mean() < plain[lungs].mean()  # the lungs get darker


def test_warp_density_with_the_lung_mask_conserves_the_mass_of_the_exact_lungs(files, tmp_path, capsys):
    # why: the lungs' mass, reference mask in the reference image against the same mask warped with
    # --label (nearest neighbour) in the --density image, is conserved (within 1 %) only when lung
    # voxels are resampled from lung tissue: a plain linear resampling mixes the water beside the
    # lung boxes' sharp faces into the lung voxels near them (here +9.5 %, against −0.8 %: the
    # nearest-neighbour mask's voxel count on 4.8–8 mm voxels, box faces parallel to the grid); the
    # image's mass stays conserved as well (each voxel takes the tissue the warped mask gives it)
    from lungdeform.playback.density import mass_g
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    hu, ref = _hu_image(d, tmp_path)
    args = ["warp", str(hu), str(d / "model.npz"), "--volume-ml", str(ee + 400), "--density"]
    assert main([*args, "--no-lung-mask", "--out", str(tmp_path / "old.mha")]) == 0
    assert main([*args, "--lung-mask", str(d / "ref.nii.gz"), "--out", str(tmp_path / "new.mha")]) == 0
    text = capsys.readouterr().out
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 400), "--label",
                 "--out", str(tmp_path / "lungs.mha")]) == 0
    vox = float(np.prod(ref.spacing)) / 1000
    lungs, moved = ref.array > 0, read_image(tmp_path / "lungs.mha").array > 0
    m0 = mass_g(read_image(hu).array, vox, lungs)
    old, new = (mass_g(read_image(tmp_path / n).array, vox, moved) / m0 - 1 for n in ("old.mha", "new.mha"))
    assert abs(new) < 0.01 < old, (old, new)
    whole = mass_g(read_image(tmp_path / "new.mha").array, vox) / mass_g(read_image(hu).array, vox) - 1
    assert abs(whole) < 0.01
    assert f"({100 * new:+.2f} %)" in text and "lungs (--lung-mask" in text, text
    # the lung boxes are not the model's ellipsoids: --no-lung-mask stands in for "no mask" here; said,
    # not left silent, in that run only
    assert text.count("note: --no-lung-mask: voxels at the lung's edge mix in chest-wall density") == 1


def test_warp_lung_mask_on_another_grid_is_refused(files, tmp_path, capsys):
    # why: the mask says which of IMAGE's voxels are lung; one on another grid is refused, not resampled
    d, _ = files
    hu, ref = _hu_image(d, tmp_path)
    from lungdeform.io.image import write_image
    write_image(tmp_path / "half.mha", ref.array[::2], ref.spacing * [1, 1, 2], ref.origin, ref.direction)
    assert main(["warp", str(hu), str(d / "model.npz"), "--volume-ml", "4000", "--density", "--lung-mask",
                 str(tmp_path / "half.mha"), "--out", str(tmp_path / "w.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not IMAGE's" in err[0], err
    assert not (tmp_path / "w.mha").exists()


@pytest.fixture(scope="module")
def ellipsoid_ct(tmp_path_factory):
    """A −800 HU ellipsoidal right lung (semi-axes 45, 60, 90 mm: 1018 mL) in water on 4 mm voxels,
    its exact mask (voxel centres inside the ellipsoid) and a model built on that mask (the workflow's
    `build`): (folder, model)."""
    from lungdeform.io.image import write_image
    d = tmp_path_factory.mktemp("ellipsoid")
    semi, centre, spacing = np.array([45.0, 60.0, 90.0]), np.array([-80.0, 10.0, -120.0]), 4.0
    lo = centre - semi - 24.0
    shape = tuple(int(n) for n in (np.ceil((2 * semi + 48.0) / spacing) + 1)[::-1])
    k, j, i = np.indices(shape)
    inside = ((((np.stack([i, j, k], axis=-1) * spacing + lo) - centre) / semi) ** 2).sum(axis=-1) <= 1.0
    write_image(d / "lung.mha", inside.astype(np.uint8), [spacing] * 3, lo, np.eye(3))
    write_image(d / "ct.mha", np.where(inside, -800, 0).astype(np.int16), [spacing] * 3, lo, np.eye(3))
    assert main(["build", str(d / "lung.mha"), "--side", "right", "--target-vertices", "1000",
                 "--out", str(d / "model.npz")]) == 0
    return d, load_model(d / "model.npz")


def test_warp_density_by_default_keeps_the_mass_of_the_exact_lung_by_the_models_own_lungs(ellipsoid_ct, tmp_path,
                                                                                          capsys):
    # why: --density without --lung-mask now partitions the CT's voxels by the model's own lungs at rest,
    # rasterised on the CT's grid (the model was built on this CT's lung, as `segment` → `build` → `warp`
    # does). The exact lung, the analytic mask in the CT against it warped by nearest neighbour
    # (`warp --label`), keeps its mass within 1 % (+0.54 %, as with the exact mask as --lung-mask: the
    # rasterised rest surface holds the same voxel centres here), where --no-lung-mask, the whole image resampled linearly,
    # mixes water into the lung's edge voxels: +14 % on these 4 mm voxels (> 3 % required)
    d, m = ellipsoid_ct
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    state = ["--volume-ml", str(ee + 300)]
    args = ["warp", str(d / "ct.mha"), str(d / "model.npz"), *state, "--density"]
    assert main([*args, "--out", str(tmp_path / "default.mha")]) == 0
    text = capsys.readouterr().out
    assert main([*args, "--no-lung-mask", "--out", str(tmp_path / "old.mha")]) == 0
    assert main(["warp", str(d / "lung.mha"), str(d / "model.npz"), *state, "--label",
                 "--out", str(tmp_path / "moved.mha")]) == 0
    ct, lung, moved = (read_image(p) for p in (d / "ct.mha", d / "lung.mha", tmp_path / "moved.mha"))
    m0 = float(((ct.array + 1000.0) * (lung.array > 0)).sum())
    default, old = (float(((read_image(tmp_path / n).array + 1000.0) * (moved.array > 0)).sum()) / m0 - 1
                    for n in ("default.mha", "old.mha"))
    assert abs(default) < 0.01 and old > 0.03, (default, old)
    assert "lung mask for --density: the model's lungs at rest, rasterised on IMAGE's grid" in text, text
    assert "lungs (the model's lungs at rest, rasterised, at this state by nearest neighbour)" in text, text


@pytest.mark.parametrize("constants", ["population", "paper"])
def test_the_field_moves_the_lung_by_the_models_volume(ellipsoid_ct, tmp_path, constants):
    # why: the lungs of a warped CT, DVF or tracked structure must breathe the volume the model says. The
    # dense field warp and dvf write (the forward x → x + u(x) on the CT's grid) changes the lung's volume
    # by its Jacobian, ∫ (det(I + ∇u) − 1) over the lung's rest mask; truth: the model lung's own volume
    # change, the signed volume of its surface mesh at that state (this lone right lung plays its 53.6 %
    # share of the both-lung state). They agree within 1.5 % inhaling and exhaling, with the shipped
    # population default (interior: surface extension plus the tapered prior) and with Table I (the
    # sliding interior). Measured: within 0.5 % for both; before the population prior was tapered to
    # zero at the surface, ~55 % on the POPI lungs (docs/DEFAULTS.md). End to end for the default,
    # `warp --label` (nearest neighbour through the inverse field) moves the mask's voxel count by the
    # same volume within 3 % (measured −0.1 % and +0.8 %; before: 76 % at −300 mL). Table I's motion,
    # mostly posterior, is not checked by voxel count: on these 4 mm voxels nearest neighbour quantises it
    # (−10 % to +16 % of the change, with the field's Jacobian within 0.5 %)
    from lungdeform.geometry.mesh import signed_volume
    from lungdeform.playback.displacement_field import Grid, displacement_field, jacobian_determinant, state_scales

    d, m = ellipsoid_ct
    path = d / "model.npz"
    if constants != "population":
        path = tmp_path / "model.npz"
        assert main(["build", str(d / "lung.mha"), "--side", "right", "--target-vertices", "1000",
                     "--constants", constants, "--out", str(path)]) == 0
        m = load_model(path)
    lung = m.lungs["right"]
    ee = lung.volume_ee_ml
    rest = read_image(d / "lung.mha")
    grid, inside = Grid.of(rest), rest.array > 0
    voxel_ml = float(np.prod(rest.spacing)) / 1000.0
    for dv in (-300.0, -100.0, 500.0):
        s = state_scales(m, dv)["right"]
        model = signed_volume(lung.positions_at(s), lung.surface.faces) / 1000.0 - ee
        assert abs(model) > 0.5 * 0.536 * abs(dv), (dv, model)
        jac = jacobian_determinant(displacement_field(m, grid, dv).field, grid.spacing, grid.direction)
        field = float((jac[inside] - 1.0).sum()) * voxel_ml
        assert abs(field - model) < 0.015 * abs(model), (dv, model, field)
        if constants == "population" and dv != -100.0:
            out = tmp_path / f"moved{dv:+.0f}.mha"
            assert main(["warp", str(d / "lung.mha"), str(path), "--volume-ml", str(ee + dv), "--label",
                         "--out", str(out)]) == 0
            change = float((read_image(out).array > 0).sum() - inside.sum()) * voxel_ml
            assert abs(change - model) < 0.03 * abs(model), (dv, model, change)


def test_warp_density_refuses_an_image_that_does_not_hold_the_models_lungs(files, tmp_path, capsys):
    # why: the default mask is the model's rest lungs on IMAGE's grid; an IMAGE whose box cuts them (a
    # cropped scan, another scan) would give a mask cut at its edge and a wrong mass without a word:
    # refused with one line, nothing written; --no-lung-mask still warps it
    d, m = files
    hu, ref = _hu_image(d, tmp_path)
    from lungdeform.io.image import write_image
    write_image(tmp_path / "half.mha", read_image(hu).array[:, :, :37], ref.spacing, ref.origin, ref.direction)
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    args = ["warp", str(tmp_path / "half.mha"), str(d / "model.npz"), "--volume-ml", str(ee + 200), "--density"]
    assert main([*args, "--out", str(tmp_path / "w.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lung at rest spans" in err[0] and "beyond IMAGE" in err[0], err
    assert not (tmp_path / "w.mha").exists()
    assert main([*args, "--no-lung-mask", "--out", str(tmp_path / "w.mha")]) == 0


def test_warp_projections_and_a_rigid_mask(files, tmp_path, capsys):
    # why: MIP/AIP/MinIP files are the voxel-wise max/mean/min of the phase files written beside
    # them; a rigid mask keeps its volume (< 2 %) where the elastic field inflates it
    d, m = files
    hu, ref = _hu_image(d, tmp_path)
    mask = np.zeros(ref.array.shape, np.uint8)
    mask[18:24, 18:26, 14:22] = 1  # inside the left box
    from lungdeform.io.image import write_image
    write_image(tmp_path / "gtv.mha", mask, ref.spacing, ref.origin, ref.direction)
    out = tmp_path / "ct.mha"
    assert main(["warp", str(hu), str(d / "model.npz"), "--curve", str(_curve(tmp_path / "c.csv")), "--phases", "3",
                 "--projections", "mip,aip,minip", "--rigid-mask", str(tmp_path / "gtv.mha"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    stack = np.stack([read_image(tmp_path / f"ct_phase0{i}.mha").array for i in range(3)])
    assert np.array_equal(read_image(tmp_path / "ct_mip.mha").array, stack.max(axis=0))
    assert np.array_equal(read_image(tmp_path / "ct_minip.mha").array, stack.min(axis=0))
    assert np.allclose(read_image(tmp_path / "ct_aip.mha").array, stack.mean(axis=0), atol=1e-3)
    import re
    changes = [float(x) for x in re.findall(r"at this state [\d.]+ mL \(([-+\d.]+) %", text)]
    elastic = [float(x) for x in re.findall(r"the elastic field gave [\d.]+ mL, ([-+\d.]+) %", text)]
    assert len(changes) == 3 and max(abs(c) for c in changes) < 2 and max(elastic) > 2, text


@pytest.mark.parametrize("extra, needle", [
    (["--density", "--label"], "--density scales CT numbers"),
    (["--lung-mask", "nowhere.mha"], "--lung-mask goes with --density"),
    (["--no-lung-mask"], "--no-lung-mask goes with --density"),
    (["--density", "--no-lung-mask", "--lung-mask", "nowhere.mha"], "--lung-mask with --no-lung-mask"),
    (["--projections", "mip"], "--projections needs --phases N"),
    (["--rigid-structure", "GTV"], "--rigid-structure and --rtstruct go together"),
    (["--rigid-mask", "nowhere.mha", "--rigid-border-mm", "0"], "--rigid-border-mm must be"),
])
def test_warp_new_options_bad_input_is_one_line(files, tmp_path, capsys, extra, needle):
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 100), *extra,
                 "--out", str(tmp_path / "w.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not list(tmp_path.iterdir())


def test_warp_density_on_a_label_pixel_type_is_refused(files, tmp_path, capsys):
    # why: a uint8 image cannot hold mass-conserving CT numbers (−1000 …); refused, not clipped, nothing written
    d, m = files
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    assert main(["warp", str(d / "ref.nii.gz"), str(d / "model.npz"), "--volume-ml", str(ee + 100), "--density",
                 "--out", str(tmp_path / "w.mha")]) == 2
    assert "pixel type uint8" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_warp_rigid_structure_from_an_rtstruct(tmp_path, capsys):
    # why: the RTSTRUCT path of --rigid-structure (the ROI's closed surface filled on the grid): the
    # 10 mm GTV inflates with the elastic field at +500 mL and keeps its volume within 2 % when rigid
    import re

    import trimesh

    from lungdeform.io.modelfile import save_model
    from tests.browser.support import two_lungs
    from tests.cli.test_track import GTV_CENTRE
    from tests.io.dicom_support import write_ct_series
    m = two_lungs(2)
    model = save_model(tmp_path / "m.npz", m)
    folder = write_ct_series(tmp_path / "ct", origin=tuple(GTV_CENTRE + [-31.0, -31.0, -19.0]))
    s = trimesh.creation.icosphere(4, radius=10.0)
    write_rtstruct(tmp_path / "gtv.dcm", read_ct_series(folder), [("GTV", s.vertices + GTV_CENTRE, s.faces, "GTV")])
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    assert main(["warp", str(folder), str(model), "--volume-ml", str(ee + 500), "--rigid-structure", "GTV",
                 "--rtstruct", str(tmp_path / "gtv.dcm"), "--out", str(tmp_path / "w.mha")]) == 0
    text = capsys.readouterr().out
    rigid = float(re.search(r"at this state [\d.]+ mL \(([-+\d.]+) %", text).group(1))
    elastic = float(re.search(r"the elastic field gave [\d.]+ mL, ([-+\d.]+) %", text).group(1))
    assert abs(rigid) < 2 and elastic > 2, text
    assert main(["warp", str(folder), str(model), "--volume-ml", str(ee + 500), "--rigid-structure", "CTV",
                 "--rtstruct", str(tmp_path / "gtv.dcm"), "--out", str(tmp_path / "x.mha")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no structure 'CTV'" in err[0] and not (tmp_path / "x.mha").exists()
