"""The field as a DICOM Deformable Spatial Registration (lungdeform.io.dicom.registration, ``dvf --out-reg``):
read back raw by pydicom against the .mha field, checked by dciodvfy, refused across patients or frames."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.io.dicom import series as DS
from lungdeform.io.dicom.registration import REG_SOP_CLASS
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.io.modelfile import save_model
from lungdeform.model.lung import Model
from tests.browser.support import two_lungs
from tests.io.dicom_support import dciodvfy

SPACING, ORIGIN = np.array([4.8, 4.8, 8.0]), np.array([-180.0, -108.0, -166.0])


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A two-lung model and a DICOM CT series (the fixed one) of its lungs' boxes on a coarse grid."""
    d = tmp_path_factory.mktemp("reg")
    m = two_lungs(2)
    save_model(d / "model.npz", m)
    a = np.eye(4)
    a[:3, 3] = [1.0, 2.0, -30.0]  # a fitted scan's alignment: its states lie in that scan's frame
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    save_model(d / "fitted.npz", Model(m.lungs, {"volumes_ml": [ee, ee + 300.0],
                                                  "alignment": [{"applied": {"matrix": a.tolist()}}]}))
    a = np.full((42, 45, 75), 40, np.int16)
    a[12:30, 10:35, 8:30] = a[12:30, 10:35, 45:67] = -800
    head = DS.study_header(None)
    head.PatientID, head.PatientName = "REG001", "Reg^Test"
    DS.write_ct_series(d / "ct", Image(a, SPACING, ORIGIN, np.eye(3)), head, description="fixed")
    return d, sum(lung.volume_ee_ml for lung in m.lungs.values())


def _raw_field(path):
    """The vectors as an independent reader takes them: the first grid item of the LAST registration
    item, float32 little endian, x fastest (PS3.3 C.20.3.1.3), so (z, y, x, 3) in C order."""
    ds = pydicom.dcmread(path)
    grid = ds.DeformableRegistrationSequence[-1].DeformableRegistrationGridSequence[0]
    nx, ny, nz = (int(n) for n in grid.GridDimensions)
    return ds, grid, np.frombuffer(grid.VectorGridData, dtype="<f4").reshape(nz, ny, nx, 3)


def test_reg_round_trip_equals_the_mha_field_and_validates(case, tmp_path, capsys):
    # why: the REG must carry exactly the field of --out (within 0.01 mm), on the same grid, in the
    # fixed series' frame, with identity matrices (the vectors hold the whole fixed → moving map)
    d, ee = case
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ct"), "--volume-ml", str(ee + 300),
                 "--out", str(tmp_path / "u.mha"), "--out-reg", str(tmp_path / "reg.dcm")]) == 0
    assert f"wrote {tmp_path / 'reg.dcm'}" in capsys.readouterr().out
    mha = sitk.ReadImage(str(tmp_path / "u.mha"))
    ds, grid, raw = _raw_field(tmp_path / "reg.dcm")
    want = sitk.GetArrayFromImage(mha)
    assert raw.shape == want.shape and np.abs(raw - want).max() <= 0.01 and np.abs(want).max() > 1.0
    assert np.allclose([float(x) for x in grid.ImagePositionPatient], mha.GetOrigin())
    assert np.allclose([float(x) for x in grid.GridResolution], mha.GetSpacing())
    assert np.allclose([float(x) for x in grid.ImageOrientationPatient], [1, 0, 0, 0, 1, 0])
    fixed = pydicom.dcmread(d / "ct" / "CT0001.dcm", stop_before_pixels=True)
    assert ds.SOPClassUID == REG_SOP_CLASS and ds.Modality == "REG" and ds.PatientID == "REG001"
    assert ds.FrameOfReferenceUID == fixed.FrameOfReferenceUID and ds.StudyInstanceUID == fixed.StudyInstanceUID
    first, last = ds.DeformableRegistrationSequence
    # a predicted state without a series: its frame is the reference's; the fixed images map by identity
    assert first.SourceFrameOfReferenceUID == last.SourceFrameOfReferenceUID == fixed.FrameOfReferenceUID
    assert len(first.ReferencedImageSequence) == 42 and "ReferencedImageSequence" not in last
    for item in (first, last):
        for seq in (item.PreDeformationMatrixRegistrationSequence, item.PostDeformationMatrixRegistrationSequence):
            assert np.allclose([float(x) for x in seq[0].FrameOfReferenceTransformationMatrix], np.eye(4).ravel())
    errors, _ = dciodvfy(tmp_path / "reg.dcm")
    assert errors == []


def test_reg_with_a_moving_series_references_it_and_validates(case, tmp_path):
    # the moving state as a DICOM series (warp keeps the study and frame): the last item names its
    # images, the first the fixed ones; the vectors equal the .mha field; dciodvfy: 0 errors
    d, ee = case
    assert main(["warp", str(d / "ct"), str(d / "model.npz"), "--volume-ml", str(ee + 300),
                 "--out", str(tmp_path / "mov")]) == 0
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ct"), "--volume-ml", str(ee + 300),
                 "--out", str(tmp_path / "u.mha"), "--out-reg", str(tmp_path / "reg.dcm"),
                 "--moving", str(tmp_path / "mov")]) == 0
    ds, _, raw = _raw_field(tmp_path / "reg.dcm")
    assert np.abs(raw - sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u.mha")))).max() <= 0.01
    moving = {pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID for p in (tmp_path / "mov").iterdir()}
    fixed = {pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID for p in (d / "ct").iterdir()}
    first, last = ds.DeformableRegistrationSequence
    assert {r.ReferencedSOPInstanceUID for r in last.ReferencedImageSequence} == moving
    assert {r.ReferencedSOPInstanceUID for r in first.ReferencedImageSequence} == fixed
    assert len(ds.ReferencedSeriesSequence) == 2
    errors, _ = dciodvfy(tmp_path / "reg.dcm")
    assert errors == []


@pytest.mark.parametrize("why", ["frame", "patient", "inverse", "nifti", "aligned", "same"])
def test_reg_refused_across_frames_or_patients_writes_nothing(case, tmp_path, capsys, why):
    # radiotherapy: a REG between two Frames of Reference (or patients) that lungdeform cannot
    # relate would be a wrong answer; --inverse is not the DICOM direction; a NIfTI reference has no
    # series to reference; a state in a fitted scan's frame without that scan's series has no frame
    # to name. Each: exit 2, one line naming the cause, neither output written
    d, ee = case
    model, state = d / "model.npz", ["--volume-ml", str(ee + 300)]
    ct = read_image(d / "ct")
    args = ["--reference", str(d / "ct")]
    if why in ("frame", "patient"):
        head = DS.study_header(d / "ct")
        if why == "frame":
            head.FrameOfReferenceUID = pydicom.uid.generate_uid()
        else:
            head.PatientID = "OTHER"
        DS.write_ct_series(tmp_path / "other", Image(ct.array, ct.spacing, ct.origin, ct.direction), head, description="x")
        args += ["--moving", str(tmp_path / "other")]
    if why == "inverse":
        args += ["--inverse"]
    if why == "nifti":
        sitk.WriteImage(_nifti(ct), str(tmp_path / "ref.nii.gz"))
        args = ["--reference", str(tmp_path / "ref.nii.gz")]
    if why == "same":  # two items, identity and the grid, for the same images: contradictory
        args += ["--moving", str(d / "ct")]
    if why == "aligned":
        model, state = d / "fitted.npz", ["--scan", "1"]
    code = main(["dvf", str(model), *args, *state, "--out", str(tmp_path / "u.mha"),
                 "--out-reg", str(tmp_path / "reg.dcm")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    expect = {"frame": "FrameOfReferenceUID", "patient": "PatientID", "inverse": "--inverse",
              "nifti": "DICOM CT series", "aligned": "give that scan's series as --moving",
              "same": "the fixed series itself"}
    assert expect[why] in err[0]
    assert not (tmp_path / "u.mha").exists() and not (tmp_path / "reg.dcm").exists()


def _nifti(image):
    img = sitk.GetImageFromArray(image.array)
    img.SetSpacing(tuple(image.spacing))
    img.SetOrigin(tuple(image.origin))
    return img


def _plastimatch():
    """plastimatch's command (PyPI wheel, Linux x86-64; requirements.lock), or skip naming it."""
    exe = shutil.which("plastimatch") or str(Path(sys.executable).with_name("plastimatch"))
    if not Path(exe).exists():
        pytest.skip("plastimatch missing: pip install plastimatch (requirements.lock, Linux x86-64 only)")
    return exe


def test_plastimatch_writes_the_same_vectors_from_the_mha(case, tmp_path):
    # an independent writer: plastimatch 1.10 turns the .mha field into its own REG (xf-convert
    # --output-dicom); its grid and VectorGridData must equal ours bit for bit (the same layout and
    # direction, fixed → moving). plastimatch 1.10 cannot read a deformable REG back (xf-convert
    # --input REG.dcm: "Error reading from xf_in file"), so this is the check it allows.
    exe = _plastimatch()
    d, ee = case
    assert main(["dvf", str(d / "model.npz"), "--reference", str(d / "ct"), "--volume-ml", str(ee + 300),
                 "--out", str(tmp_path / "u.mha"), "--out-reg", str(tmp_path / "reg.dcm")]) == 0
    out = subprocess.run([exe, "xf-convert", "--input", str(tmp_path / "u.mha"), "--output-dicom", str(tmp_path / "pm"),
                          "--fixed-rcs", str(d / "ct"), "--moving-rcs", str(d / "ct")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    (theirs,) = (tmp_path / "pm").glob("*.dcm")
    _, ours_grid, ours = _raw_field(tmp_path / "reg.dcm")
    _, their_grid, their = _raw_field(theirs)
    assert np.array_equal(ours, their) and np.abs(ours).max() > 1.0
    for key in ("GridDimensions", "GridResolution", "ImagePositionPatient", "ImageOrientationPatient"):
        assert np.allclose([float(x) for x in ours_grid.get(key)], [float(x) for x in their_grid.get(key)]), key
