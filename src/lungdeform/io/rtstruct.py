"""DICOM RT Structure Sets (RTSTRUCT): radiotherapy contours in and out, with pydicom alone.

:func:`read_rtstruct` reads a file into named :class:`Structure` s, each a list of planar contours
``(k, 3) float`` mm. DICOM patient coordinates are LPS (x to the patient's left, y posterior, z
head), the frame of every lungdeform array, so ContourData is taken as it stands (this holds for
any patient position: the CT's ImagePositionPatient/ImageOrientationPatient are in the same frame).
:func:`structure_points` gives a structure's points, :func:`structure_mesh` a closed surface through
its contours (:func:`lungdeform.geometry.contours.contours_to_mesh`).

:func:`write_rtstruct` writes surfaces (e.g. a structure moved by the model to several breathing
states) as a new RTSTRUCT referencing the CT series read by :func:`read_ct_series`: its Study
Instance UID, Frame of Reference UID, Series Instance UID and, per contour, the SOP Instance UID of
the slice it lies on. Each surface is cut with every slice plane
(:func:`lungdeform.geometry.contours.section_mesh`), so every contour is CLOSED_PLANAR on a slice
of the referenced series, as planning systems expect. See docs/RADIOTHERAPY.md.
"""

from __future__ import annotations

import datetime as _dt
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.sequence import Sequence
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.contours import contours_to_mesh, section_mesh

from .image import dicom_series_files

#: RT Structure Set Storage
RTSTRUCT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.481.3"
#: Detached Study Management (the SOP class DICOM names for a referenced study)
STUDY_SOP_CLASS = "1.2.840.10008.3.1.2.3.1"
#: ROI colours (RGB) given in turn
COLOURS = ((255, 0, 0), (0, 160, 255), (0, 200, 0), (255, 160, 0), (200, 0, 255), (255, 255, 0),
           (0, 255, 200), (255, 80, 160), (120, 120, 255), (160, 255, 80))
#: Study and patient attributes copied from the CT into the structure set
_COPIED = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID", "StudyDate",
           "StudyTime", "StudyID", "AccessionNumber", "ReferringPhysicianName", "StudyDescription")


@dataclass(frozen=True, eq=False)
class Structure:
    """One ROI of a structure set: ``contours`` a list of ``(k, 3) float`` mm LPS polygons."""

    name: str
    number: int
    contours: list = field(default_factory=list, repr=False)
    colour: tuple = (255, 0, 0)
    kind: str = ""


@dataclass(frozen=True, eq=False)
class CTSeries:
    """What an RTSTRUCT references of a CT series: ``header`` the first slice's dataset (without
    pixels); per slice in order ``sop_uids``, ``sop_class`` and ``origins : (s, 3) float`` mm LPS
    (ImagePositionPatient); ``normal : (3,)`` the slices' unit normal; ``source`` the folder."""

    header: Dataset
    sop_uids: list
    sop_class: str
    origins: np.ndarray
    normal: np.ndarray
    source: str


def read_rtstruct(path) -> dict[str, Structure]:
    """Structures of the RTSTRUCT file ``path`` by ROI name, in file order. Raises
    :class:`ReadError` naming the file when it is missing, not DICOM or not a structure set."""
    p = Path(path)
    if not p.is_file():
        raise ReadError(f"{p}: no such file")
    # pydicom parses lazily and warns about values it can still read (a VR mismatch, a malformed
    # UID): the structures are checked below, so its warnings are not the user's; a file it
    # cannot parse raises anything from ValueError to NotImplementedError (an unknown VR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ds = pydicom.dcmread(p)
            modality, sop_class = ds.get("Modality"), ds.get("SOPClassUID")
        except Exception as exc:  # any parse failure becomes one clear line
            raise ReadError(f"{p}: not a DICOM file ({type(exc).__name__}: {_first_line(exc)})") from exc
        if sop_class != RTSTRUCT_SOP_CLASS and modality != "RTSTRUCT":
            raise ReadError(f"{p}: not an RTSTRUCT (Modality {modality or 'missing'}, SOP class {sop_class or 'missing'})")
        try:
            return _structures(ds)
        except Exception as exc:  # a damaged sequence or value, found while reading it
            raise ReadError(f"{p}: malformed structure set ({type(exc).__name__}: {_first_line(exc)})") from exc


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else "no detail"


def _structures(ds: Dataset) -> dict[str, Structure]:
    """ROIs of a structure set dataset: names from StructureSetROISequence, contours from
    ROIContourSequence, the interpreted type from RTROIObservationsSequence."""
    names = {int(r.ROINumber): str(r.ROIName) for r in ds.get("StructureSetROISequence", [])}
    kinds = {int(o.ReferencedROINumber): str(o.get("RTROIInterpretedType", ""))
             for o in ds.get("RTROIObservationsSequence", [])}
    contours: dict[int, list] = {n: [] for n in names}
    colours: dict[int, tuple] = {}
    for roi in ds.get("ROIContourSequence", []):
        number = int(roi.ReferencedROINumber)
        if number not in names:
            continue
        if roi.get("ROIDisplayColor"):
            colours[number] = tuple(int(c) for c in roi.ROIDisplayColor)
        for c in roi.get("ContourSequence", []):
            pts = np.asarray(c.get("ContourData", []), dtype=np.float64).reshape(-1, 3)
            if len(pts) and np.all(np.isfinite(pts)):
                contours[number].append(np.ascontiguousarray(pts))
    return {name: Structure(name, n, contours[n], colours.get(n, (255, 0, 0)), kinds.get(n, ""))
            for n, name in names.items()}


def pick_structure(structures: dict[str, Structure], name: str, source: str) -> Structure:
    """The structure called ``name``; :class:`InputError` listing the names there are, or when it
    has no contour."""
    if name not in structures:
        listed = ", ".join(repr(n) for n in structures) or "none"
        raise InputError(f"{source}: no structure {name!r} (structures: {listed})")
    s = structures[name]
    if not s.contours:
        raise InputError(f"{source}: structure {name!r} has no contours")
    return s


def structure_points(structure: Structure) -> np.ndarray:
    """All contour points of ``structure``: ``(n, 3) float`` mm LPS."""
    if not structure.contours:
        raise InputError(f"structure {structure.name!r} has no contours")
    return np.ascontiguousarray(np.concatenate(structure.contours))


def structure_mesh(structure: Structure) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface through the structure's contours: ``(vertices (n, 3) float mm, faces)``."""
    return contours_to_mesh(structure.contours, name=f"structure {structure.name!r}")


def read_ct_series(path) -> CTSeries:
    """The slices of the DICOM CT series ``path`` names (a folder or one of its files, as
    :func:`lungdeform.io.image.dicom_series_files`), sorted along their normal."""
    files = dicom_series_files(path)
    heads = []
    for f in files:
        try:
            heads.append(pydicom.dcmread(f, stop_before_pixels=True))
        except (InvalidDicomError, OSError, EOFError, ValueError) as exc:
            raise ReadError(f"{f}: not a readable DICOM slice ({exc})") from exc
    try:
        iop = np.asarray(heads[0].ImageOrientationPatient, float).reshape(2, 3)
        origins = np.array([np.asarray(h.ImagePositionPatient, float) for h in heads])
        uids = [str(h.SOPInstanceUID) for h in heads]
        for key in ("FrameOfReferenceUID", "StudyInstanceUID", "SeriesInstanceUID", "SOPClassUID"):
            getattr(heads[0], key)
    except AttributeError as exc:
        raise ReadError(f"{path}: DICOM series lacks an attribute an RTSTRUCT needs ({exc})") from exc
    normal = np.cross(iop[0], iop[1])
    normal /= np.linalg.norm(normal)
    order = np.argsort(origins @ normal)
    return CTSeries(heads[order[0]], [uids[i] for i in order], str(heads[0].SOPClassUID), origins[order],
                    normal, str(path))


def write_rtstruct(path, ct: CTSeries, surfaces: list, *, label: str = "lungdeform") -> dict:
    """Write ``surfaces`` — ``(name, vertices (n, 3) float mm LPS, faces (m, 3) int)`` each, or
    ``(name, vertices, faces, kind)`` with an RT ROI interpreted type (GTV, ITV, ORGAN …) — as an
    RTSTRUCT referencing ``ct``, every contour a section of the surface by one slice plane.
    Atomic. Returns ``{name: number of contours}``; a surface outside every slice gets none."""
    ds = _base_dataset(ct, label)
    counts = {}
    for number, surf in enumerate(surfaces, start=1):
        name, v, f = surf[:3]
        kind = surf[3] if len(surf) > 3 else "ORGAN"
        if len(name) > 64:
            raise InputError(f"ROI name {name!r}: longer than DICOM's 64 characters")
        contours = _slice_contours(ct, v, f)
        counts[name] = len(contours)
        _add_roi(ds, number, name, kind, COLOURS[(number - 1) % len(COLOURS)], contours, ct)
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    return counts


def _slice_contours(ct: CTSeries, vertices, faces) -> list[tuple[int, np.ndarray]]:
    """``(slice index, (k, 3) float mm)`` for each polygon where a slice plane cuts the surface."""
    out = []
    h = np.asarray(vertices, float) @ ct.normal
    for k, origin in enumerate(ct.origins):
        level = origin @ ct.normal
        if h.min() <= level <= h.max():
            out += [(k, c) for c in section_mesh(vertices, faces, origin, ct.normal)]
    return out


def _base_dataset(ct: CTSeries, label: str) -> FileDataset:
    """The structure set's header: patient and study of the CT, a new series, the referenced
    frame of reference with every slice of the CT series."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = RTSTRUCT_SOP_CLASS
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset("", Dataset(), file_meta=meta, preamble=b"\0" * 128)
    now = _dt.datetime.now()
    for key in _COPIED:
        setattr(ds, key, ct.header.get(key, ""))
    ds.SOPClassUID, ds.SOPInstanceUID = RTSTRUCT_SOP_CLASS, meta.MediaStorageSOPInstanceUID
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber, ds.InstanceNumber = "RTSTRUCT", generate_uid(), 900, 1
    ds.Manufacturer, ds.SeriesDescription = "lungdeform", label[:64]
    ds.FrameOfReferenceUID = ct.header.FrameOfReferenceUID
    ds.StructureSetLabel = label[:16]
    ds.StructureSetDate, ds.StructureSetTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    series = Dataset()
    series.SeriesInstanceUID = ct.header.SeriesInstanceUID
    series.ContourImageSequence = Sequence([_image_ref(ct, k) for k in range(len(ct.sop_uids))])
    study = Dataset()
    study.ReferencedSOPClassUID, study.ReferencedSOPInstanceUID = STUDY_SOP_CLASS, ct.header.StudyInstanceUID
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID = ct.header.FrameOfReferenceUID
    frame.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = Sequence(), Sequence(), Sequence()
    return ds


def _image_ref(ct: CTSeries, k: int) -> Dataset:
    ref = Dataset()
    ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = ct.sop_class, ct.sop_uids[k]
    return ref


def _add_roi(ds: FileDataset, number: int, name: str, kind: str, colour, contours, ct: CTSeries) -> None:
    """One ROI: its name (StructureSetROISequence), colour and CLOSED_PLANAR contours, each
    referencing its slice (ROIContourSequence), and its interpreted type (RTROIObservationsSequence)."""
    roi = Dataset()
    roi.ROINumber, roi.ReferencedFrameOfReferenceUID = number, ct.header.FrameOfReferenceUID
    roi.ROIName, roi.ROIGenerationAlgorithm = name, "AUTOMATIC"
    ds.StructureSetROISequence.append(roi)
    rc = Dataset()
    rc.ROIDisplayColor, rc.ReferencedROINumber = list(colour), number
    rc.ContourSequence = Sequence()
    for i, (k, pts) in enumerate(contours, start=1):
        c = Dataset()
        c.ContourNumber, c.ContourImageSequence = i, Sequence([_image_ref(ct, k)])
        c.ContourGeometricType, c.NumberOfContourPoints = "CLOSED_PLANAR", len(pts)
        c.ContourData = [f"{x:.3f}" for x in np.asarray(pts, float).ravel()]  # 0.0005 mm, <= 16 chars
        rc.ContourSequence.append(c)
    ds.ROIContourSequence.append(rc)
    obs = Dataset()
    obs.ObservationNumber, obs.ReferencedROINumber = number, number
    obs.RTROIInterpretedType, obs.ROIInterpreter = kind, ""
    ds.RTROIObservationsSequence.append(obs)
