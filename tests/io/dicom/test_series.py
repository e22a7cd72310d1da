"""A 3-D image written as a DICOM CT series (lungdeform.io.dicom.series), read back by SimpleITK and pydicom."""

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from lungdeform.atomic import atomic_dir
from lungdeform.errors import InputError, ReadError
from lungdeform.io.dicom import series as DS
from lungdeform.io.dicom.rtstruct import read_ct_series
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from tests.io.dicom_support import write_ct_series as write_source_series

#: an oblique grid: index axes rotated 30° about z, so a swapped row/column or a wrong slice
#: normal moves the read-back origin or direction
_C, _S = np.cos(np.pi / 6), np.sin(np.pi / 6)
DIRECTION = np.array([[_C, -_S, 0.0], [_S, _C, 0.0], [0.0, 0.0, 1.0]])
SPACING, ORIGIN = np.array([0.8, 0.9, 2.5]), np.array([-40.0, 12.0, -150.0])


def _image(rng, shape=(6, 10, 12)):
    return rng.uniform(-1024, 1500, shape)


def test_written_series_reads_back_with_its_grid_and_hu(rng, tmp_path):
    # HU in the int16 range are stored with slope 1: the round trip is the rounding, ≤ 0.5 HU;
    # the grid is the one given (ImagePositionPatient/ImageOrientationPatient/PixelSpacing are LPS as it stands)
    a = _image(rng)
    head = DS.study_header()
    uids = DS.write_ct_series(tmp_path / "s", Image(a, SPACING, ORIGIN, DIRECTION), head, description="test")
    got = read_image(tmp_path / "s")
    assert np.abs(got.array - a).max() <= 0.5
    assert np.allclose(got.spacing, SPACING) and np.allclose(got.origin, ORIGIN, atol=1e-5)
    assert np.allclose(got.direction, DIRECTION, atol=1e-5)
    # the UIDs returned are the slices', in slice order (read_ct_series sorts along the normal)
    assert read_ct_series(tmp_path / "s").sop_uids == uids


def test_tags_of_a_phase(rng, tmp_path):
    # a phase keeps the source's study, patient and frame of reference, has a new series, and says
    # its temporal position both ways a 4-D CT reader sorts by (1-based index, "phase 30%")
    src = write_source_series(tmp_path / "src", shape=(4, 8, 8))
    head = DS.study_header(src)
    DS.write_ct_series(tmp_path / "p", Image(_image(rng, (4, 8, 8)), SPACING, ORIGIN, np.eye(3)), head,
                       description=DS.phase_description("CT", 3, 10), series_number=103, temporal=(3, 10))
    ds = pydicom.dcmread(tmp_path / "p" / "CT0002.dcm")
    s = pydicom.dcmread(next(src.iterdir()), stop_before_pixels=True)
    assert ds.SOPClassUID == DS.CT_SOP_CLASS and ds.Modality == "CT" and ds.InstanceNumber == 2
    assert ds.StudyInstanceUID == s.StudyInstanceUID and ds.FrameOfReferenceUID == s.FrameOfReferenceUID
    assert ds.SeriesInstanceUID != s.SeriesInstanceUID and ds.PatientID == "SYN001"
    assert ds.SeriesDescription == "CT phase 30%"
    # TemporalPositionIdentifier, not the multi-frame TemporalPositionIndex (not in the CT IOD, dciodvfy)
    assert "TemporalPositionIndex" not in ds and ds[0x0020, 0x0100].value == 4 and ds.NumberOfTemporalPositions == 10
    assert ds.pixel_array.dtype == np.int16 and ds.RescaleType == "HU"


def test_wide_range_is_rescaled_within_half_a_step(rng):
    # 0 … 100 000 does not fit int16: slope = range / 65535, so the error is at most slope / 2 (≈ 0.76)
    a = rng.uniform(0, 1e5, (3, 5, 7))
    a[0, 0, 0], a[-1, -1, -1] = 0.0, 1e5
    stored, slope, intercept = DS.rescale(a)
    assert slope == pytest.approx(1e5 / 65535, rel=0.01)
    assert np.abs(stored * slope + intercept - a).max() <= slope / 2 + 1e-9
    with pytest.raises(InputError, match="non-finite"):
        DS.rescale(np.full((1, 2, 2), np.nan))


def test_phase_names_and_description():
    # folder names are whole percentages of the cycle (10 phases: phase00 … phase90), the
    # description the exact percentage (8 phases: 12.5 %)
    assert [DS.phase_folder(i, 10) for i in (0, 3, 9)] == ["phase00", "phase30", "phase90"]
    assert DS.phase_description("4D CT", 1, 8) == "4D CT phase 12.5%"
    assert len(DS.phase_description("x" * 80, 1, 10)) == 64
    with pytest.raises(InputError, match="at most 100"):
        DS.phase_folder(0, 101)


def test_an_error_leaves_no_folder(rng, tmp_path):
    # written inside atomic_dir: the second phase fails (NaN), so neither phase nor any temporary folder remains
    head = DS.study_header()
    with pytest.raises(InputError):
        with atomic_dir(tmp_path / "4d") as tmp:
            DS.write_ct_series(tmp / "phase00", Image(_image(rng), SPACING, ORIGIN, np.eye(3)), head, description="a")
            DS.write_ct_series(tmp / "phase50", Image(np.full((2, 3, 3), np.nan), SPACING, ORIGIN, np.eye(3)), head,
                               description="b")
    assert list(tmp_path.iterdir()) == []


def test_refuses_a_folder_that_is_not_a_series(tmp_path):
    # --out on a folder replaces it whole: only an earlier lungdeform series or 4-D CT may be replaced
    (tmp_path / "phase00").mkdir()
    DS.check_series_output(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="notes.txt"):
        DS.check_series_output(tmp_path)
    assert DS.is_series_output(tmp_path / "4dct") and not DS.is_series_output(tmp_path / "ct.mha")


def test_sitk_series_reader_sorts_the_slices(rng, tmp_path):
    # GDCM sorts by position, not file name: the series has one id and every slice in it
    DS.write_ct_series(tmp_path / "s", Image(_image(rng), SPACING, ORIGIN, np.eye(3)), DS.study_header(), description="s")
    ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(tmp_path / "s"))
    assert len(ids) == 1 and len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "s"), ids[0])) == 6


def test_study_header_refuses_a_source_without_a_valid_frame_of_reference(tmp_path):
    # why: the phases keep the source's Frame of Reference; a source without one (or with a malformed
    # UID) would give phases that a planning system places nowhere, or that fail validation on write
    src = write_source_series(tmp_path / "src", shape=(2, 4, 4))
    for f in src.iterdir():
        ds = pydicom.dcmread(f)
        del ds.FrameOfReferenceUID
        ds.save_as(f)
    with pytest.raises(ReadError, match="lacks FrameOfReferenceUID, which every series derived from it keeps"):
        DS.study_header(src)
