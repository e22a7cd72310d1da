"""A displacement field written as a DICOM Deformable Spatial Registration (REG) object.

Behind ``lungdeform dvf … --out-reg REG.dcm`` (docs/RADIOTHERAPY.md, "A DICOM registration object"):
the field of ``--out FIELD.mha`` as SOP class 1.2.840.10008.5.1.4.1.1.66.3 (PS3.3 A.39.2), the form
in which planning systems and SlicerRT exchange a deformation.

Convention (PS3.3 C.20.3.1.1): the Registered RCS is the REG's own Frame of Reference, that of the
fixed series (the reference CT). A point ``x`` of the Registered RCS maps to the Source RCS point
``M_post · (M_pre · x + D(x))``, where ``D`` is the vector at ``x`` of the grid (ImagePositionPatient,
ImageOrientationPatient, GridDimensions, GridResolution, all in the Registered RCS). lungdeform writes
``M_pre = M_post = identity`` (any rigid alignment of a fitted scan is inside the vectors) and ``D``
the forward field of ``lungdeform dvf``: ``D(x) = u(x)``, the displacement in mm (LPS) that carries
the tissue at ``x`` in the reference to where it is at the moving state (fixed → moving). This is the
resampling direction of the standard: the moving image sampled at ``x + u(x)`` is the moving image
brought onto the fixed one. VectorGridData holds float32 ``(dx, dy, dz)`` triples, x fastest, then y,
then z: a ``(z, y, x, 3)`` float32 array as it lies in C order.

Items of the DeformableRegistrationSequence, always two: first the fixed series (its own Frame of
Reference, its images, identity, no grid), last the moving one with the grid. The moving item
names the moving series' Frame of Reference and images; for a predicted state without a series
(``dvf --volume-ml`` without ``--moving``) it names the reference's Frame of Reference (the model
moves tissue within the reference's patient frame, and ``lungdeform warp`` keeps that frame for the
images of a state) and no images: in that frame the fixed series' images map by identity (first
item) and any other image, the state's, through the grid (PS3.3 C.20.3: an item with Referenced
Image Sequence applies to those images only).

Refused (:class:`~lungdeform.errors.InputError`) before anything is written: a moving series of
another patient (PatientID) or another Frame of Reference than the fixed one (lungdeform knows no
registration between two frames: a wrong answer is worse than none), a grid that is not
right-handed (DICOM's third grid axis is row × column), a field whose shape is not the grid's.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

from lungdeform import __version__
from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError

from .attributes import check_dataset, decimal, declare_charset, fit_text, type2_defaults
from .rtstruct import CTSeries

#: Deformable Spatial Registration Storage
REG_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.66.3"
#: Patient and study attributes the REG copies from the fixed series
_COPIED = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID", "StudyDate",
           "StudyTime", "StudyID", "AccessionNumber", "ReferringPhysicianName", "StudyDescription")
#: Type 2 attributes of the IOD written empty when the fixed series does not give them
_TYPE2 = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime", "StudyID",
          "AccessionNumber", "ReferringPhysicianName", "PositionReferenceIndicator", "ContentCreatorName",
          "ContentDescription", "SeriesNumber")


def check_pair(fixed: CTSeries, moving: CTSeries | None) -> None:
    """Refuse a moving series that is ``fixed`` itself, or of another patient or Frame of Reference
    (messages name both)."""
    if moving is None:
        return
    if str(moving.header.SeriesInstanceUID) == str(fixed.header.SeriesInstanceUID):
        raise InputError(f"--moving {moving.source}: the fixed series itself ({fixed.source}); "
                         "give the moving state's series")
    for key in ("PatientID", "FrameOfReferenceUID"):
        a, b = str(fixed.header.get(key, "")), str(moving.header.get(key, ""))
        if a != b:
            raise InputError(f"--moving {moving.source}: {key} {b!r} differs from the fixed series' ({fixed.source}: "
                             f"{a!r}); a REG is written only between series of one patient and one Frame of Reference")


def _grid_item(field: np.ndarray, grid) -> Dataset:
    """The DeformableRegistrationGridSequence item: grid geometry and the float32 vectors."""
    d = np.asarray(grid.direction, float).reshape(3, 3)
    if not np.allclose(np.cross(d[:, 0], d[:, 1]), d[:, 2], atol=1e-6):
        raise InputError("--out-reg: the field's grid is not right-handed (DICOM takes its third axis as row × column)")
    f = np.ascontiguousarray(field, dtype="<f4")
    if f.ndim != 4 or f.shape[3] != 3:
        raise InputError(f"--out-reg: a field must be (z, y, x, 3), got shape {f.shape}")
    item = Dataset()
    item.ImagePositionPatient = [decimal(x) for x in np.asarray(grid.origin, float)]
    item.ImageOrientationPatient = [decimal(x) for x in np.concatenate([d[:, 0], d[:, 1]])]
    item.GridDimensions = [int(f.shape[2]), int(f.shape[1]), int(f.shape[0])]
    item.GridResolution = [float(x) for x in np.asarray(grid.spacing, float)]
    item.VectorGridData = f.tobytes()
    return item


def _matrix(kind: str = "RIGID") -> Sequence:
    m = Dataset()
    m.FrameOfReferenceTransformationMatrixType = kind
    m.FrameOfReferenceTransformationMatrix = [decimal(x) for x in np.eye(4).ravel()]
    return Sequence([m])


def _images(ct: CTSeries) -> Sequence:
    refs = []
    for uid in ct.sop_uids:
        r = Dataset()
        r.ReferencedSOPClassUID, r.ReferencedSOPInstanceUID = ct.sop_class, uid
        refs.append(r)
    return Sequence(refs)


def _registration_item(ct: CTSeries | None, frame_uid: str, grid_item: Dataset | None) -> Dataset:
    item = Dataset()
    item.SourceFrameOfReferenceUID = frame_uid
    if ct is not None:
        item.ReferencedImageSequence = _images(ct)
    item.RegistrationTypeCodeSequence = Sequence()
    item.PreDeformationMatrixRegistrationSequence = _matrix()
    item.PostDeformationMatrixRegistrationSequence = _matrix()
    if grid_item is not None:
        item.DeformableRegistrationGridSequence = Sequence([grid_item])
    return item


def _references(ds: Dataset, fixed: CTSeries, moving: CTSeries | None) -> None:
    """Common Instance Reference module: every referenced series, by study."""
    same, other = [], {}
    for ct in [fixed] + ([moving] if moving is not None else []):
        s = Dataset()
        s.SeriesInstanceUID = ct.header.SeriesInstanceUID
        s.ReferencedInstanceSequence = _images(ct)
        study = str(ct.header.StudyInstanceUID)
        (same.append(s) if study == str(ds.StudyInstanceUID) else other.setdefault(study, []).append(s))
    ds.ReferencedSeriesSequence = Sequence(same)
    if other:
        studies = []
        for study, series in other.items():
            st = Dataset()
            st.StudyInstanceUID, st.ReferencedSeriesSequence = study, Sequence(series)
            studies.append(st)
        ds.StudiesContainingOtherReferencedInstancesSequence = Sequence(studies)


def build_registration(field, grid, fixed: CTSeries, moving: CTSeries | None = None, *,
                       description: str = "lungdeform breathing model") -> FileDataset:
    """The REG dataset of ``field : (z, y, x, 3)`` mm LPS (forward, fixed → moving) on ``grid``
    (anything with ``spacing`` (x, y, z) mm, ``origin`` mm LPS and ``direction`` (3, 3)), referencing
    the ``fixed`` series (:func:`~lungdeform.io.dicom.rtstruct.read_ct_series`) and, when given, the
    ``moving`` one (module docstring), every value checked against its VR."""
    check_pair(fixed, moving)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = REG_SOP_CLASS, generate_uid()
    meta.TransferSyntaxUID, meta.ImplementationClassUID = ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", Dataset(), file_meta=meta, preamble=b"\0" * 128)
    for key in _COPIED:
        if key in fixed.header:
            setattr(ds, key, fixed.header.get(key))
    now = _dt.datetime.now()
    ds.SOPClassUID, ds.SOPInstanceUID = REG_SOP_CLASS, meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber, ds.InstanceNumber = "REG", generate_uid(), 901, 1
    ds.SeriesDescription, ds.ContentLabel = fit_text(description, "LO"), "LUNGDEFORM_DVF"
    ds.ContentDate, ds.ContentTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.FrameOfReferenceUID = fixed.header.FrameOfReferenceUID
    ds.PositionReferenceIndicator = fixed.header.get("PositionReferenceIndicator", "")
    ds.Manufacturer = ds.ManufacturerModelName = "lungdeform"
    ds.DeviceSerialNumber, ds.SoftwareVersions = "none", __version__
    type2_defaults(ds, _TYPE2)
    grid_item = _grid_item(field, grid)
    # lungs: an unpaired body part, so Laterality (General Series, 2C) stays absent
    ds.BodyPartExamined = fixed.header.get("BodyPartExamined") or "CHEST"
    items = [_registration_item(fixed, str(ds.FrameOfReferenceUID), None)]
    source = ds.FrameOfReferenceUID if moving is None else moving.header.FrameOfReferenceUID
    items.append(_registration_item(moving, str(source), grid_item))
    ds.DeformableRegistrationSequence = Sequence(items)
    _references(ds, fixed, moving)
    declare_charset(ds)  # a patient name that is not ASCII: UTF-8, declared
    check_dataset(ds, "REG")
    return ds


def write_registration(path, field, grid, fixed: CTSeries, moving: CTSeries | None = None, *,
                       description: str = "lungdeform breathing model") -> Path:
    """Write the REG of :func:`build_registration` to ``path``, atomically."""
    ds = build_registration(field, grid, fixed, moving, description=description)
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    return Path(path)
