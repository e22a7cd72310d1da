"""A DICOM CT series: found in a folder, its slices checked and read; an image written as one.

Reading: :func:`dicom_series_files` picks the series a path names (a folder as exports come, its
RTSTRUCT, RTPLAN, RTDOSE, DICOMDIR, localizer and non-DICOM files told apart and named:
:mod:`~lungdeform.io.dicom.folder`; a parent folder of one series; or one file), every file
checked by :func:`~lungdeform.io.dicom.guard.check_dicom_file` first; :func:`dicom_series_geometry` checks its slices
(:func:`~lungdeform.io.dicom.slices.check_slices`) and :func:`read_series` reads it with SimpleITK
(:func:`lungdeform.io.image.read_image` is the entry point for every format).

Writing: with pydicom, CT Image Storage, one file per slice.

Behind ``lungdeform warp … --out FOLDER`` (docs/RADIOTHERAPY.md, "From a 4-D CT to tumour motion
and DVFs"): each breathing phase of a synthetic 4-D CT becomes its own series in ``FOLDER/phaseNN``
(NN the phase's percentage of the cycle: ``phase00`` … ``phase90`` for 10 phases).

Conventions, so that 4-D CT readers sort the phases: every phase keeps the Study Instance UID and
Frame of Reference UID of the source CT (new ones, shared by all phases, when the source is not
DICOM), has a new Series Instance UID, a SeriesDescription ending ``phase 30%``, and the temporal
position as TemporalPositionIdentifier (0020,0100), 1-based, with NumberOfTemporalPositions
(0020,0105), as GE, Siemens and Philips 4-D CT exports have them.

Conformance (dciodvfy, docs/RADIOTHERAPY.md "DICOM conformance"): every Type 2 attribute of the CT
Image IOD is present, empty when the source does not give it (:data:`TYPE2_KEYS`); BodyPartExamined
is the source's or ``CHEST`` (unpaired: Laterality, Type 2C, is written only when the source has it); ImageType is
``DERIVED, SECONDARY, AXIAL``; decimal strings are at most 16 bytes
(:func:`~lungdeform.io.dicom.attributes.decimal`) and every slice passes
:func:`~lungdeform.io.dicom.attributes.check_dataset` before it is saved. The two temporal
attributes are not in the CT Image IOD (they come from the MR Image module): dciodvfy warns that
such a file is a Standard Extended SOP Class, which the standard allows (PS3.4 B.1.3). The
TemporalPositionIndex (0020,9128) that 0.7 wrote as well is a multi-frame functional group
attribute and is no longer written.

Frames and units: the arrays of :class:`lungdeform.io.grid.Image`: ``array`` ``(z, y, x)`` in HU,
``spacing`` (x, y, z) mm, ``origin`` mm LPS of voxel (0, 0, 0), ``direction`` (3, 3) whose
columns are the index axes in LPS; DICOM patient coordinates are LPS too, so
ImagePositionPatient of slice ``k`` is ``origin + k * spacing_z * direction[:, 2]`` as it stands.
Voxels are stored as int16 with RescaleSlope/RescaleIntercept (:func:`rescale`).
"""


from __future__ import annotations

import datetime as _dt
import re
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

from lungdeform.errors import InputError, ReadError
from lungdeform.io.grid import Image, check_grid, quiet_itk

from .attributes import check_dataset, decimal, declare_charset, fit_text, require, type2_defaults
from .folder import SeriesChoice, ignored_line, pick, survey
from .guard import is_dicom_file
from .slices import GEOMETRY_TAGS, SliceGeometry, check_slices, check_spacing

#: CT Image Storage
CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"
#: Patient, study and frame-of-reference attributes a derived series keeps from its source
STUDY_KEYS = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "PatientPosition", "StudyInstanceUID",
              "StudyDate", "StudyTime", "StudyID", "AccessionNumber", "ReferringPhysicianName", "StudyDescription",
              "FrameOfReferenceUID", "PositionReferenceIndicator", "KVP", "BodyPartExamined", "Laterality")
#: Type 2 attributes of the CT Image IOD (Patient, General Study, General Series, Frame of Reference,
#: General Image, CT Image modules) written empty when the source does not give them
TYPE2_KEYS = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime", "StudyID",
              "AccessionNumber", "ReferringPhysicianName", "PatientPosition", "PositionReferenceIndicator",
              "KVP", "AcquisitionNumber")
#: Most phases written as DICOM folders: the folder names are whole percentages of the cycle
MAX_PHASES = 100


def dicom_series_files(path, series: SeriesChoice | None = None, ignored: list | None = None) -> list[str]:
    """The files of the DICOM image series that ``path`` names.

    ``path`` may be a folder (its image series told from every other object of an export:
    :func:`~lungdeform.io.dicom.folder.survey`; a DICOMDIR followed; a folder holding no DICOM file
    itself looked into), or one file of the series (its series is read from its folder). The series
    is the folder's one candidate, or the one ``series`` names
    (:func:`~lungdeform.io.dicom.folder.pick`); ``ignored``, when given, gets the line that names
    what else the folder held (:func:`~lungdeform.io.dicom.folder.ignored_line`). Raises
    :class:`ReadError` naming the path when there is no series, or more than one to choose from.
    """
    p = Path(path)
    if p.is_file():
        found = survey(p.parent)
        target = p.resolve()
        for s in found.series:
            if any(Path(f).resolve() == target for f in s.files):
                return list(s.files)
        what = dict(found.ignored).get(p.name)
        raise ReadError(f"{p}: not a readable DICOM image slice" + (f" (it is {what})" if what else
                                                                    f" (no DICOM series in {p.parent} contains it)"))
    found = survey(p)
    chosen = pick(found, series)
    line = ignored_line(found, [chosen])
    if ignored is not None and line:
        ignored.append(line)
    return list(chosen.files)


def dicom_series_geometry(files, where, max_voxels=None) -> SliceGeometry:
    """The geometry of one DICOM series (``files``, any order), its files in order along the slice
    normal, after the grid cap (:func:`check_grid`, from the headers) and, for two or more files,
    the checks of :func:`lungdeform.io.dicom.slices.check_slices`; :class:`ReadError` naming ``where``
    and the file."""
    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    slices, size, depth = [], (0, 0), 0
    for f in files:
        reader.SetFileName(str(f))
        try:
            with quiet_itk():
                reader.ReadImageInformation()
        except RuntimeError as exc:
            raise ReadError(f"{where}: {f} is not a readable DICOM image slice") from exc
        slices.append((str(f), {t: reader.GetMetaData(t).strip() if reader.HasMetaDataKey(t) else ""
                                for t in GEOMETRY_TAGS}))
        got = reader.GetSize()
        size = (max(size[0], got[0]), max(size[1], got[1]))
        depth += int(np.prod(got[2:], dtype=np.int64))
        check_grid((*size, depth), where, max_voxels)
    if len(slices) < 2:
        return SliceGeometry(tuple(s for s, _ in slices), np.zeros(len(slices)), 0.0)
    return check_slices(slices, where)




def read_series(path, max_voxels=None, series: SeriesChoice | None = None, ignored: list | None = None) -> sitk.Image:
    """The DICOM series ``path`` names (:func:`dicom_series_files`: ``series`` chooses one, ``ignored``
    gets what else the folder held) read by SimpleITK, after every header is checked
    (:func:`dicom_series_geometry`) and ITK's slice spacing is compared with the slices' own
    (:func:`~lungdeform.io.dicom.slices.check_spacing`)."""
    geometry = dicom_series_geometry(dicom_series_files(path, series, ignored), path, max_voxels)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(list(geometry.files))
    with quiet_itk():
        img = reader.Execute()
    check_spacing(img.GetSpacing()[2], geometry, path)
    return img


def series_identity(files) -> dict[str, str]:
    """What tells one DICOM series from another, read from the first of its ``files`` (pydicom,
    header only): ``{"patient_id", "study_uid", "series_uid", "frame_of_reference"}`` (``""`` where
    the file has none). A model records it per fitted scan, so that an output later said to be on
    scan K's series can be checked against it (:func:`lungdeform.io.dicom.rtstruct.check_ct_is_scan`).
    :class:`ReadError` naming the file when it cannot be read, lacks a SeriesInstanceUID or holds a
    UID that is not one (:func:`~lungdeform.io.dicom.attributes.require`)."""
    first = str(next(iter(files)))
    try:
        ds = pydicom.dcmread(first, stop_before_pixels=True)
    except (InvalidDicomError, OSError, EOFError, ValueError) as exc:
        raise ReadError(f"{first}: not a readable DICOM slice ({exc})") from exc
    require(ds, ("SeriesInstanceUID",), first, "which a fitted scan's record needs",
            optional=("StudyInstanceUID", "FrameOfReferenceUID"))
    return {"patient_id": str(ds.get("PatientID", "") or "").strip(),
            "study_uid": str(ds.get("StudyInstanceUID", "") or "").strip(),
            "series_uid": str(ds.SeriesInstanceUID).strip(),
            "frame_of_reference": str(ds.get("FrameOfReferenceUID", "") or "").strip()}


def study_header(source=None, series: SeriesChoice | None = None) -> Dataset:
    """The patient, study and frame-of-reference attributes (:data:`STUDY_KEYS`) and the
    SeriesDescription of the DICOM series ``source`` names (a folder or one of its files), or
    new Study and Frame of Reference UIDs when ``source`` is None or not DICOM. Call it once for
    all the phases of a 4-D CT, so that they share one study and one frame of reference. A DICOM
    source without a valid StudyInstanceUID or FrameOfReferenceUID is refused with
    :class:`ReadError` (:func:`~lungdeform.io.dicom.attributes.require`): its phases keep them.
    ``series`` chooses among several series of the folder (:func:`dicom_series_files`)."""
    head = Dataset()
    p = None if source is None else Path(source)
    if p is not None and (p.is_dir() or is_dicom_file(p)):
        first = dicom_series_files(p, series)[0]
        try:
            src = pydicom.dcmread(first, stop_before_pixels=True)
        except (InvalidDicomError, OSError, EOFError, ValueError) as exc:
            raise ReadError(f"{first}: not a readable DICOM slice ({exc})") from exc
        require(src, ("StudyInstanceUID", "FrameOfReferenceUID"), first, "which every series derived from it keeps")
        for key in STUDY_KEYS + ("SeriesDescription",):
            if key in src:
                setattr(head, key, src.get(key))
    if not head.get("StudyInstanceUID"):  # a new study, begun now
        now = _dt.datetime.now()
        head.StudyInstanceUID = generate_uid()
        head.StudyDate, head.StudyTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    head.FrameOfReferenceUID = head.get("FrameOfReferenceUID") or generate_uid()
    if not head.get("SeriesDescription"):
        head.SeriesDescription = "" if p is None else fit_text(re.sub(r"(\.nii)?\.[^.]+$", "", p.name), "LO")
    return head


def is_series_output(path) -> bool:
    """Whether ``--out path`` names a DICOM series folder: an existing folder, or a name without
    a suffix (``4dct``, ``out/ct``); a name with a suffix is an image file (``ct.mha``)."""
    p = Path(path)
    return p.is_dir() or (p.suffix == "" and not p.exists())


def check_series_output(path) -> None:
    """Refuse, before any work, a series folder that exists and holds anything but an earlier
    series or 4-D CT written here (``phaseNN`` folders, ``CTnnnn.dcm`` files): it is replaced whole."""
    p = Path(path)
    if p.is_dir():
        other = [c.name for c in p.iterdir() if not re.fullmatch(r"phase\d\d|CT\d{4}\.dcm", c.name)]
        if other:
            raise InputError(f"--out {p}: folder exists and holds {other[0]!r}, not a DICOM series written by "
                             "lungdeform: it would be replaced; give a new folder")


def phase_folder(index: int, count: int) -> str:
    """``phaseNN``, NN the whole percentage of phase ``index`` (0-based) of ``count``: ``phase30``."""
    if not 1 <= count <= MAX_PHASES:
        raise InputError(f"--phases: at most {MAX_PHASES} phases as DICOM series folders, got {count}")
    return f"phase{round(100 * index / count):02d}"


def phase_description(base: str, index: int, count: int) -> str:
    """``"<base> phase 30%"`` (the percentage a 4-D CT reader sorts by): ``base`` cut on a character
    boundary so that the whole fits a SeriesDescription (LO, 64 bytes of UTF-8), the tag whole."""
    tag = f"phase {100 * index / count:.4g}%"
    return fit_text(str(base), "LO", keep=f" {tag}").strip()


def state_description(base: str) -> str:
    """``"<base> lungdeform warp"``, ``base`` cut so that the whole fits a SeriesDescription (LO)."""
    return fit_text(str(base), "LO", keep=" lungdeform warp").strip()


def rescale(array) -> tuple[np.ndarray, float, float]:
    """``(stored int16, slope, intercept)`` with ``array ≈ stored * slope + intercept``.

    Values within the int16 range are rounded to whole units (slope 1, intercept 0: HU as CT
    scanners store them, error ≤ 0.5); a wider range is spread over the 65 536 int16 steps (error ≤
    slope / 2). Non-finite values are refused."""
    a = np.asarray(array, dtype=np.float64)
    if not np.isfinite(a).all():
        raise InputError("image to write as DICOM holds non-finite values")
    lo, hi = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)
    if lo >= -32768 and hi <= 32767:
        return np.rint(a).astype(np.int16), 1.0, 0.0
    slope = (hi - lo) / 65535.0
    intercept = lo + 32768.0 * slope
    stored = np.clip(np.rint((a - intercept) / slope), -32768, 32767).astype(np.int16)
    return stored, slope, intercept


def write_ct_series(folder, image: Image, header: Dataset, *, description: str, series_number: int = 1,
                    temporal: tuple[int, int] | None = None) -> list[str]:
    """Write ``image`` (its ``array : (z, y, x)`` HU on the grid ``spacing`` (x, y, z) mm, ``origin``
    mm LPS, ``direction`` (3, 3)) as a new CT series in ``folder`` (created; it must not hold files
    yet), one file ``CT0001.dcm`` … per slice. ``header`` (:func:`study_header`) gives the patient, study and
    frame of reference; ``temporal`` = ``(index, count)`` (0-based index) sets the temporal tags.
    Not atomic by itself: write into :func:`lungdeform.atomic.atomic_dir`. Returns the SOP Instance
    UIDs in slice order. A grid over the cap (:func:`~lungdeform.io.grid.check_grid`) is refused first."""
    array, spacing, origin, direction = image.array, image.spacing, image.origin, image.direction
    a = np.asarray(array)
    if a.ndim != 3 or 0 in a.shape:
        raise InputError(f"{folder}: a DICOM series needs a non-empty 3-D (z, y, x) array, got shape {a.shape}")
    check_grid(a.shape[::-1], folder, error=InputError)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if any(folder.iterdir()):
        raise InputError(f"{folder}: not empty; a DICOM series is written into a new folder")
    stored, slope, intercept = rescale(a)
    series = _series_dataset(a.shape, spacing, direction, header, description, series_number, temporal)
    series.RescaleSlope, series.RescaleIntercept = decimal(slope, 10), decimal(intercept, 10)
    d = np.asarray(direction, float).reshape(3, 3)
    uids = []
    for k in range(a.shape[0]):
        position = np.asarray(origin, float) + k * float(spacing[2]) * d[:, 2]
        series.SliceLocation = decimal(position @ d[:, 2], places=6)  # along the slice normal
        uids.append(_write_slice(folder / f"CT{k + 1:04d}.dcm", series, stored[k], k, position))
    return uids


def _series_dataset(shape, spacing, direction, header: Dataset, description: str, series_number: int,
                    temporal) -> Dataset:
    """The attributes every slice of the series shares: study (``header``), series, geometry, pixels."""
    ds = Dataset()
    for key in STUDY_KEYS:
        if key in header:
            setattr(ds, key, header.get(key))
    type2_defaults(ds, TYPE2_KEYS)
    if not ds.get("BodyPartExamined"):  # lungs: an unpaired body part, so Laterality (2C) stays absent
        ds.BodyPartExamined = "CHEST"
    if not ds.get("Laterality"):  # 2C: present only with a value (a paired body part)
        ds.pop("Laterality", None)
    now = _dt.datetime.now()
    ds.SOPClassUID, ds.Modality, ds.SeriesInstanceUID = CT_SOP_CLASS, "CT", generate_uid()
    ds.SeriesNumber, ds.SeriesDescription = int(series_number), fit_text(description, "LO")
    ds.SeriesDate, ds.SeriesTime, ds.ContentDate = now.strftime("%Y%m%d"), now.strftime("%H%M%S"), now.strftime("%Y%m%d")
    ds.ImageType, ds.Manufacturer = ["DERIVED", "SECONDARY", "AXIAL"], "lungdeform"
    ds.DerivationDescription = "resampled through a lungdeform breathing-model displacement field"
    d = np.asarray(direction, float).reshape(3, 3)
    ds.ImageOrientationPatient = [decimal(x, places=6) for x in np.concatenate([d[:, 0], d[:, 1]])]
    ds.PixelSpacing = [decimal(spacing[1], 6), decimal(spacing[0], 6)]  # row (y), column (x)
    ds.SliceThickness = ds.SpacingBetweenSlices = decimal(spacing[2], 6)
    ds.Rows, ds.Columns = int(shape[1]), int(shape[2])
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    ds.RescaleType = "HU"
    if temporal is not None:
        index, count = temporal
        ds.TemporalPositionIdentifier = int(index) + 1
        ds.NumberOfTemporalPositions = int(count)
    return ds


def _write_slice(path: Path, series: Dataset, pixels: np.ndarray, k: int, position) -> str:
    """One slice file: the series attributes, its position and its int16 pixels."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = CT_SOP_CLASS, generate_uid()
    meta.TransferSyntaxUID, meta.ImplementationClassUID = ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", Dataset(), file_meta=meta, preamble=b"\0" * 128)
    ds.update(series)
    ds.SOPInstanceUID, ds.InstanceNumber = meta.MediaStorageSOPInstanceUID, k + 1
    ds.ImagePositionPatient = [decimal(x, places=6) for x in position]
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<i2").tobytes()
    declare_charset(ds)  # a Latin-1 patient name of the source, written as UTF-8 and declared
    check_dataset(ds, str(path))
    ds.save_as(path, enforce_file_format=True)
    return str(ds.SOPInstanceUID)
