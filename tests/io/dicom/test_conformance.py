"""Every kind of DICOM file lungdeform writes passes dciodvfy (Debian's dicom3tools, an independent
IOD checker) with 0 errors, and only the warnings docs/RADIOTHERAPY.md ("DICOM conformance") explains."""

import re

import numpy as np
import pydicom
import pytest
from trimesh.creation import icosphere

from lungdeform.io.dicom import series as DS
from lungdeform.io.dicom.registration import write_registration
from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from tests.io.dicom_support import dciodvfy, write_ct_series

#: The warnings explained in docs/RADIOTHERAPY.md: attributes a DICOMDIR would want that the source
#: leaves empty (Type 2: empty when unknown), and the two temporal attributes 4-D CT readers sort by
#: that the CT Image IOD lacks (a Standard Extended SOP Class).
EXPLAINED = (r"needed to build DICOMDIR - (Patient ID|Study ID|Study Date|Study Time)",
             r"not present in standard DICOM IOD - \(0x0020,0x010[05]\) IS (Temporal Position Identifier|Number of "
             r"Temporal Positions)",
             r"attributes not present in standard DICOM IOD - this is a Standard Extended SOP Class")


def _check(path):
    errors, warnings = dciodvfy(path)
    assert errors == [], errors
    unexplained = [w for w in warnings if not any(re.search(p, w) for p in EXPLAINED)]
    assert unexplained == [], unexplained


@pytest.mark.parametrize("source", ["dicom", "nifti"])
def test_ct_phase_validates(tmp_path, source):
    # a phase of a synthetic 4-D CT from a DICOM source (its study kept) and from an image without a
    # study (new UIDs, every Type 2 attribute empty); odd spacings and origins so that a decimal
    # string written with too many digits (> 16 bytes) would show; HU over the int16 range (rescaled)
    src = write_ct_series(tmp_path / "src", shape=(4, 8, 8))
    head = DS.study_header(src if source == "dicom" else None)
    rng = np.random.default_rng(7)
    DS.write_ct_series(tmp_path / "p", Image(rng.uniform(-1024, 40000, (4, 8, 8)), [0.9765625, 0.9765625, 2.5],
                                             [-249.51171875, -123.456789012345, -1234.56789012345], np.eye(3)), head,
                       description="CT phase 30%", temporal=(3, 10))
    for f in sorted((tmp_path / "p").iterdir()):
        _check(f)


def test_rtstruct_and_reg_validate(tmp_path):
    src = write_ct_series(tmp_path / "src")
    ct = read_ct_series(src)
    sphere = icosphere(3, 8.0)
    write_rtstruct(tmp_path / "rs.dcm", ct, [("GTV", sphere.vertices, sphere.faces, "GTV"),
                                             ("Lung", sphere.vertices * 1.5, sphere.faces)])
    _check(tmp_path / "rs.dcm")
    image = read_image(src)
    field = np.random.default_rng(3).normal(0, 2, image.array.shape + (3,)).astype(np.float32)
    write_registration(tmp_path / "reg.dcm", field, image, ct)
    _check(tmp_path / "reg.dcm")


def test_reg_with_a_moving_series_of_another_study_validates(tmp_path):
    # the moving series in another study of the same patient and frame: referenced through
    # StudiesContainingOtherReferencedInstancesSequence (Common Instance Reference module)
    src = write_ct_series(tmp_path / "src", shape=(3, 8, 8))
    image = read_image(src)
    head = DS.study_header(src)
    head.StudyInstanceUID = pydicom.uid.generate_uid()
    DS.write_ct_series(tmp_path / "mov", Image(image.array, image.spacing, image.origin, image.direction), head,
                       description="moving")
    field = np.random.default_rng(5).normal(0, 2, image.array.shape + (3,)).astype(np.float32)
    write_registration(tmp_path / "reg.dcm", field, image, read_ct_series(src), read_ct_series(tmp_path / "mov"))
    other = pydicom.dcmread(tmp_path / "reg.dcm").StudiesContainingOtherReferencedInstancesSequence
    assert [s.StudyInstanceUID for s in other] == [head.StudyInstanceUID]
    _check(tmp_path / "reg.dcm")
