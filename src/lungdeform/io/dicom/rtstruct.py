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

import dataclasses
import datetime as _dt
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.multival import MultiValue
from pydicom.sequence import Sequence
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.contours import contours_to_mesh, enclosing, section_mesh

from .attributes import check_dataset, declare_charset, fit_text, require
from .folder import SeriesChoice
from .series import dicom_series_files
from .slices import check_gaps

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
    """One ROI of a structure set: ``contours`` a list of ``(k, 3) float`` mm LPS polygons, every
    contour of the ROI's ContourSequence in file order (none dropped: :func:`structure_mesh` checks
    them); ``frame_uid`` the Frame of Reference UID it is drawn in, ``study_uid`` the structure
    set's study, ``image_uids`` the SOP Instance UIDs of the slices its contours reference,
    ``types`` each contour's ContourGeometricType ('' when absent), ``patient_id`` the structure set's
    PatientID ('' when absent), ``numbers`` each contour's number in the file (1-based; empty: 1, 2 …
    in order) once contours that enclose no area were left out (:func:`enclosing_contours`)."""

    name: str
    number: int
    contours: list = field(default_factory=list, repr=False)
    colour: tuple = (255, 0, 0)
    kind: str = ""
    frame_uid: str = ""
    study_uid: str = ""
    image_uids: frozenset = frozenset()
    types: tuple = ()
    patient_id: str = ""
    numbers: tuple = ()


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

    @property
    def levels(self) -> np.ndarray:
        """``(s,) float`` mm: each slice's position along ``normal``, increasing."""
        return self.origins @ self.normal


def read_rtstruct(path) -> dict[str, Structure]:
    """Structures of the RTSTRUCT file ``path`` by ROI name, in file order (a name given to two
    ROIs: the first; :func:`read_rois` keeps both). Raises :class:`ReadError` naming the file when
    it is missing, not DICOM or not a structure set."""
    out: dict[str, Structure] = {}
    for s in read_rois(path):
        out.setdefault(s.name, s)
    return out


def read_rois(path) -> list[Structure]:
    """Every ROI of the RTSTRUCT file ``path`` in file order, duplicate names included (see
    :func:`read_rtstruct`)."""
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
        if "StructureSetROISequence" not in ds:
            raise ReadError(f"{p}: no StructureSetROISequence: not a complete structure set (truncated?)")
        try:
            return _structures(ds, p)
        except ReadError:
            raise
        except Exception as exc:  # a damaged sequence or value, found while reading it
            raise ReadError(f"{p}: malformed structure set ({type(exc).__name__}: {_first_line(exc)})") from exc


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else "no detail"


def _rois(ds: Dataset, p: Path) -> dict[int, tuple[str, str]]:
    """``{ROI number: (name, frame of reference UID)}`` of StructureSetROISequence; a number given
    to two ROIs is refused (which one the contours belong to cannot be told)."""
    frames = [str(f.get("FrameOfReferenceUID", "")) for f in ds.get("ReferencedFrameOfReferenceSequence", [])]
    default = frames[0] if len(set(frames)) == 1 else str(ds.get("FrameOfReferenceUID", ""))
    rois: dict[int, tuple[str, str]] = {}
    for r in ds.get("StructureSetROISequence", []):
        number, name = int(r.ROINumber), str(r.ROIName)
        if number in rois:
            raise ReadError(f"{p}: ROI number {number} is given to two ROIs ({rois[number][0]!r} and {name!r})")
        rois[number] = (name, str(r.get("ReferencedFrameOfReferenceUID", "") or default))
    return rois


def _structures(ds: Dataset, p: Path) -> list[Structure]:
    """ROIs of a structure set dataset: names and frames from StructureSetROISequence, contours
    from ROIContourSequence, the interpreted type from RTROIObservationsSequence."""
    rois = _rois(ds, p)
    kinds = {int(o.ReferencedROINumber): str(o.get("RTROIInterpretedType", ""))
             for o in ds.get("RTROIObservationsSequence", [])}
    contours: dict[int, list] = {n: [] for n in rois}
    types: dict[int, list] = {n: [] for n in rois}
    images: dict[int, set] = {n: set() for n in rois}
    colours: dict[int, tuple] = {}
    for roi in ds.get("ROIContourSequence", []):
        number = int(roi.ReferencedROINumber)
        if number not in rois:
            continue
        if roi.get("ROIDisplayColor"):
            colours[number] = tuple(int(c) for c in roi.ROIDisplayColor)
        for c in roi.get("ContourSequence", []):
            contours[number].append(np.ascontiguousarray(np.asarray(c.get("ContourData", []), np.float64).reshape(-1, 3)))
            types[number].append(str(c.get("ContourGeometricType", "")))
            images[number].update(str(i.get("ReferencedSOPInstanceUID", "")) for i in c.get("ContourImageSequence", []))
    study, patient = str(ds.get("StudyInstanceUID", "")), str(ds.get("PatientID", "")).strip()
    return [Structure(name, n, contours[n], colours.get(n, (255, 0, 0)), kinds.get(n, ""), frame, study,
                      frozenset(images[n] - {""}), tuple(types[n]), patient)
            for n, (name, frame) in rois.items()]


def pick_structure(structures, name: str, source: str) -> Structure:
    """The structure called ``name`` of ``structures`` (a list of :func:`read_rois`, or the dict of
    :func:`read_rtstruct`); :class:`InputError` listing the names there are, when two ROIs carry
    that name (naming their numbers), or when it has no contour."""
    rois = list(structures.values()) if isinstance(structures, dict) else list(structures)
    found = [s for s in rois if s.name == name]
    if not found:
        listed = ", ".join(dict.fromkeys(repr(s.name) for s in rois)) or "none"
        raise InputError(f"{source}: no structure {name!r} (structures: {listed})")
    if len(found) > 1:
        numbers = " and ".join(str(s.number) for s in found)
        raise InputError(f"{source}: {len(found)} ROIs are named {name!r} (ROI numbers {numbers}): ambiguous; "
                         "rename one in the planning system")
    s = found[0]
    if not s.contours:
        raise InputError(f"{source}: structure {name!r} has no contours")
    return s


def structure_points(structure: Structure) -> np.ndarray:
    """All contour points of ``structure``: ``(n, 3) float`` mm LPS."""
    if not structure.contours:
        raise InputError(f"structure {structure.name!r} has no contours")
    return np.ascontiguousarray(np.concatenate(structure.contours))


def enclosing_contours(structure: Structure, source: str | None = None) -> tuple[Structure, list[str]]:
    """``(the structure with only its contours that enclose an area, one line per contour left out)``:
    a contour of fewer than 3 distinct points (a mask-to-contour tool's tip of 1 or 2 points, a
    repeated point) or of points on a line is skipped, as planning systems and 3D Slicer skip it
    (:func:`lungdeform.geometry.contours.enclosing`; the lines name ``source``, the structure, the
    contour's number in the file and its slice). Refused (:class:`InputError`): a NaN or a coordinate
    beyond reach in any contour, and a structure none of whose contours encloses an area."""
    name = f"structure {structure.name!r}"
    keep, lines = enclosing(structure.contours, name, source)
    if not keep:
        pre = f"{source}: " if source else ""
        raise InputError(f"{pre}{name}: none of its {len(structure.contours)} contour(s) encloses an area (points, "
                         "tips or lines only): no region to move")
    numbers = structure.numbers or tuple(range(1, len(structure.contours) + 1))
    types = structure.types or ("",) * len(structure.contours)
    kept = dataclasses.replace(structure, contours=[structure.contours[i] for i in keep],
                               types=tuple(types[i] for i in keep), numbers=tuple(numbers[i] for i in keep))
    return kept, lines


def structure_mesh(structure: Structure, source: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface through the structure's contours: ``(vertices (n, 3) float mm, faces)``.
    Every contour must be CLOSED_PLANAR (or untyped), and pass the checks of
    :func:`lungdeform.geometry.contours.contours_to_mesh` (contours that enclose no area are left out
    first by :func:`enclosing_contours`); errors name ``source`` (the file), the structure and the
    contour (1-based, in file order)."""
    name, pre = f"structure {structure.name!r}", f"{source}: " if source else ""
    numbers = structure.numbers or tuple(range(1, len(structure.contours) + 1))
    for k, kind in zip(numbers, structure.types):
        if kind not in ("", "CLOSED_PLANAR"):
            raise InputError(f"{pre}contour {k} of {name} is {kind}, not CLOSED_PLANAR: it encloses no region")
    return contours_to_mesh(structure.contours, name=name, source=source, numbers=numbers)


def read_ct_series(path, series: SeriesChoice | None = None) -> CTSeries:
    """The slices of the DICOM CT series ``path`` names (a folder or one of its files, as
    :func:`lungdeform.io.dicom.series.dicom_series_files`; ``series`` chooses among several), sorted
    along their normal.

    Refused with :class:`ReadError` naming the file: a slice pydicom cannot read, an
    ImageOrientationPatient that is not two unit, orthogonal vectors (or differs between slices), an
    ImagePositionPatient that is not three finite numbers, a missing UID or one Frame of Reference
    differing between slices; naming the folder: two slices at one position, slices missing or
    unevenly spaced (:func:`lungdeform.io.dicom.slices.check_gaps`, the check every series reader
    makes: contours on a missing slice would be lost)."""
    files = dicom_series_files(path, series)
    with warnings.catch_warnings():  # pydicom's warnings on values it still reads: checked below
        warnings.simplefilter("ignore")
        slices = [_ct_slice(f) for f in files]
    first = slices[0]
    for f, sl in zip(files[1:], slices[1:]):
        if np.abs(sl["iop"] - first["iop"]).max() > 1e-3:
            raise ReadError(f"{f}: ImageOrientationPatient differs from {files[0]}'s: not one series of parallel slices")
        if sl["frame"] != first["frame"]:
            raise ReadError(f"{f}: Frame of Reference {sl['frame']} differs from {files[0]}'s ({first['frame']})")
    iop = first["iop"]
    normal = np.cross(iop[0], iop[1])
    normal /= np.linalg.norm(normal)
    origins = np.array([sl["ipp"] for sl in slices])
    order = np.argsort(origins @ normal, kind="stable")
    uids = [slices[i]["uid"] for i in order]
    if len(set(uids)) < len(uids):
        raise ReadError(f"{path}: two slices share one SOP Instance UID")
    check_gaps(tuple(str(files[i]) for i in order), origins[order] @ normal, path)
    head = slices[order[0]]["header"]
    return CTSeries(head, uids, str(head.SOPClassUID), origins[order], normal, str(path))


def _ct_slice(f) -> dict:
    """One slice's header and the geometry and UIDs an RTSTRUCT needs, checked."""
    try:
        h = pydicom.dcmread(f, stop_before_pixels=True)
    except Exception as exc:  # any parse failure becomes one clear line
        raise ReadError(f"{f}: not a readable DICOM slice ({type(exc).__name__}: {_first_line(exc)})") from exc
    # the UIDs are copied into the RTSTRUCT, where an invalid UID cannot go
    require(h, ("ImageOrientationPatient", "ImagePositionPatient", "SOPInstanceUID", "SOPClassUID",
                "FrameOfReferenceUID", "StudyInstanceUID", "SeriesInstanceUID"), f, "which an RTSTRUCT needs")
    iop = _numbers(h, "ImageOrientationPatient", 6, f).reshape(2, 3)
    if np.abs(np.linalg.norm(iop, axis=1) - 1).max() > 1e-2 or abs(float(iop[0] @ iop[1])) > 1e-2:
        raise ReadError(f"{f}: ImageOrientationPatient {iop.ravel().tolist()} is not two orthogonal unit vectors")
    iop = iop / np.linalg.norm(iop, axis=1, keepdims=True)
    return {"header": h, "iop": iop, "ipp": _numbers(h, "ImagePositionPatient", 3, f),
            "uid": str(h.SOPInstanceUID), "frame": str(h.FrameOfReferenceUID)}


def _numbers(h: Dataset, key: str, count: int, f) -> np.ndarray:
    """The attribute ``key`` as ``count`` finite floats, or :class:`ReadError` naming the file ``f``."""
    try:
        raw = h[key].value
        values = np.asarray([float(v) for v in (raw if isinstance(raw, (list, tuple, MultiValue)) else [raw])])
    except (TypeError, ValueError, OverflowError) as exc:
        raise ReadError(f"{f}: {key} is not numeric ({_first_line(exc)})") from exc
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise ReadError(f"{f}: {key} must be {count} finite numbers, got {values.tolist()[:8]}")
    return values


def check_structure_on_ct(structure: Structure, ct: CTSeries, source: str, option: str = "--reference-ct") -> list[str]:
    """Refuse (:class:`InputError` naming ``source``, the structure and the cause) a structure that
    cannot be written on ``ct``: another patient (PatientID, when both give one), another Frame of
    Reference than the CT's (its coordinates mean nothing there), slices it is drawn on that the CT
    lacks (when it references slices of this series), or contours beyond the CT's first or last
    slice. Returns warnings: the same Frame of Reference in another study. ``option`` names the CT
    in messages (``--reference-ct``, ``--reference``)."""
    name = f"{source}: structure {structure.name!r}"
    frame, study = str(ct.header.FrameOfReferenceUID), str(ct.header.StudyInstanceUID)
    patient = str(ct.header.get("PatientID", "")).strip()
    if structure.patient_id and patient and structure.patient_id != patient:
        raise InputError(f"{name} belongs to patient {structure.patient_id!r}, {option} {ct.source} to "
                         f"patient {patient!r}: not the same patient")
    if not structure.frame_uid:
        raise InputError(f"{name} has no Frame of Reference UID: cannot check it is drawn on {option} {ct.source}")
    if structure.frame_uid != frame:
        also = f"; study {structure.study_uid} against {study}" if structure.study_uid and structure.study_uid != study else ""
        raise InputError(f"{name} is in Frame of Reference {structure.frame_uid}, {option} {ct.source} in "
                         f"{frame}{also}: not the CT it was drawn on")
    ours = structure.image_uids & set(ct.sop_uids)
    lost = structure.image_uids - set(ct.sop_uids)
    if ours and lost:
        raise InputError(f"{name} is drawn on {len(lost)} slice(s) that {option} {ct.source} lacks "
                         f"(e.g. SOP Instance UID {min(lost)}): missing slices")
    check_within_slices(ct, name, np.concatenate([c for c in structure.contours if len(c)]), option)
    if structure.study_uid and structure.study_uid != study:
        return [f"{name} is in study {structure.study_uid}, {option} {ct.source} in study {study} "
                "(the same Frame of Reference): check that this is the planning CT it was drawn on"]
    return []


def check_ct_is_scan(ct: CTSeries, scans, k: int) -> None:
    """Refuse (:class:`InputError` naming ``--reference-ct`` and the mismatch) a CT that is not
    scan ``k`` of a fit: ``scans`` the model's provenance ``scans`` (one identity per fitted scan,
    :func:`lungdeform.evaluate.inputs.scan_identity`). Its patient (when both give one) and Frame of
    Reference (when scan ``k`` was a DICOM series) must be scan ``k``'s, and its slices must span scan
    ``k``'s image box (each face within the larger of the two voxel sizes and 0.5 mm; a mask
    segmented with ``--downsample`` spans the same box). Contours in scan ``k``'s frame written on
    another CT would be a wrong answer: positions meaningful in one frame, labelled with another."""
    where = f"--reference-ct {ct.source}"
    if not scans or not 0 <= k < len(scans) or not isinstance(scans[k], dict):
        raise InputError(f"{where}: the model records no identity of scan {k} (fitted before lungdeform recorded "
                         f"its scans): cannot check that this CT is scan {k}'s; fit again, or give --volume-ml")
    scan = scans[k]
    what = f"scan {k} ({scan.get('source', '?')})"
    if not scan.get("frame_of_reference") and not scan.get("grid"):
        raise InputError(f"{where}: {what} was neither a DICOM series nor an image (a mesh?): nothing to check "
                         f"that this CT is scan {k}'s against; give --volume-ml")
    patient = str(ct.header.get("PatientID", "") or "").strip()
    if scan.get("patient_id") and patient and scan["patient_id"] != patient:
        raise InputError(f"{where}: patient {patient!r}, {what} patient {scan['patient_id']!r}: not scan {k}'s series")
    frame = str(ct.header.FrameOfReferenceUID)
    if scan.get("frame_of_reference") and scan["frame_of_reference"] != frame:
        raise InputError(f"{where}: Frame of Reference {frame}, {what} {scan['frame_of_reference']}: not scan {k}'s "
                         "series (its contours would be written in another frame)")
    if scan.get("grid"):
        _check_box(ct, scan["grid"], where, (what, k))


def check_structure_on_scan(structure: Structure, scans, source: str) -> None:
    """Refuse (:class:`InputError` naming ``source`` and the structure) a structure that is not drawn
    on scan 0 of a fit (``scans``, as :func:`check_ct_is_scan`): another patient, or another Frame
    of Reference than scan 0's; a scan 0 that was no DICOM series has no frame to check it against,
    refused too. For ``track --scan K`` where the fit aligned scan K: the structure is drawn in the
    model's frame (scan 0's), its moved contours are written in scan K's, on scan K's CT."""
    name = f"{source}: structure {structure.name!r}"
    scan = scans[0] if scans and isinstance(scans[0], dict) else {}
    if scan.get("patient_id") and structure.patient_id and scan["patient_id"] != structure.patient_id:
        raise InputError(f"{name} belongs to patient {structure.patient_id!r}, scan 0 of the fit "
                         f"({scan.get('source', '?')}) to patient {scan['patient_id']!r}: not the same patient")
    if not scan.get("frame_of_reference"):
        raise InputError(f"{name}: scan 0 of the fit ({scan.get('source', '?')}) was no DICOM series, so nothing shows "
                         "the structure is drawn on it; give --no-rigid, or fit DICOM series")
    if structure.frame_uid != scan["frame_of_reference"]:
        raise InputError(f"{name} is in Frame of Reference {structure.frame_uid or '(none)'}, scan 0 of the fit "
                         f"({scan.get('source', '?')}) in {scan['frame_of_reference']}: not drawn on the model's scan")


def _ct_box(ct: CTSeries) -> tuple[np.ndarray, float]:
    """``((2, 3) lowest and highest voxel-centre corner mm LPS, largest voxel size mm)`` of ``ct``."""
    h = ct.header
    require(h, ("PixelSpacing", "Rows", "Columns"), ct.source, "which the check against the fitted scan needs")
    iop = np.asarray([float(v) for v in h.ImageOrientationPatient], float).reshape(2, 3)
    dy, dx = _numbers(h, "PixelSpacing", 2, ct.source)  # row spacing, column spacing
    rows, cols = int(h.Rows), int(h.Columns)
    corners = [o + i * (cols - 1) * dx * iop[0] + j * (rows - 1) * dy * iop[1]
               for o in (ct.origins[0], ct.origins[-1]) for i in (0, 1) for j in (0, 1)]
    step = float(np.median(np.diff(ct.levels))) if len(ct.levels) > 1 else 0.0
    return np.array([np.min(corners, 0), np.max(corners, 0)]), max(dx, dy, step)


def _span(box: np.ndarray) -> str:
    """``"(x0..x1, y0..y1, z0..z1) mm"`` of a (2, 3) box."""
    return "(" + ", ".join(f"{lo:.1f}..{hi:.1f}" for lo, hi in zip(box[0], box[1])) + ") mm"


def _check_box(ct: CTSeries, grid: dict, where: str, scan: tuple[str, int]) -> None:
    """InputError when ``ct``'s voxel-centre box differs from that of the recorded ``grid`` of
    ``scan`` = ``(its description, its index k)``."""
    what, k = scan
    size, spacing = np.asarray(grid["size"], float), np.asarray(grid["spacing"], float)
    origin, direction = np.asarray(grid["origin"], float), np.asarray(grid["direction"], float).reshape(3, 3)
    idx = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float) * (size - 1)
    corners = origin + (idx * spacing) @ direction.T
    box = np.array([corners.min(0), corners.max(0)])
    ours, voxel = _ct_box(ct)
    tol = max(voxel, float(spacing.max())) + 0.5
    off = np.abs(ours - box)
    if off.max() > tol:
        raise InputError(f"{where}: its slices span {_span(ours)} LPS, {what} spans {_span(box)}: not scan "
                         f"{k}'s series (another grid, {off.max():.1f} mm off)")


def check_within_slices(ct: CTSeries, name: str, points, option: str = "--reference-ct") -> None:
    """Refuse (:class:`InputError` naming ``name``) ``points : (n, 3)`` mm reaching a slice spacing
    or more beyond the first or last slice of ``ct``: a slice there would cut it, and the CT has
    none, so its contours there would be lost (a surface through contours on the end slice closes
    less than a spacing beyond it)."""
    h = np.asarray(points, float) @ ct.normal
    levels = ct.levels
    step = float(np.median(np.diff(levels))) if len(levels) > 1 else 0.0
    if not (h.min() > levels[0] - step - 1e-6 and h.max() < levels[-1] + step + 1e-6):
        raise InputError(f"{name} reaches {h.min():.1f} to {h.max():.1f} mm along the slice normal, beyond the "
                         f"slices of {option} {ct.source} ({levels[0]:.1f} to {levels[-1]:.1f} mm, "
                         f"{step:.2f} mm apart): its contours there would be lost")


def roi_name(name: str, taken=()) -> str:
    """The ROI Name (LO: 64 bytes of UTF-8, no backslash or control character) written for the
    structure ``name``: ``name`` itself when it fits, else cut on a character boundary with its state
    tag (what follows the last ``@``: ``@phase03``) kept whole, and unique among ``taken``
    (:func:`~lungdeform.io.dicom.attributes.fit_text`); a cut name's whole is kept in ROIDescription."""
    base, at, tag = name.rpartition("@")
    return fit_text(base, "LO", keep=at + tag, taken=taken) if at else fit_text(name, "LO", taken=taken)


def build_rtstruct(ct: CTSeries, surfaces: list, *, label: str = "lungdeform",
                   source: str | None = None) -> tuple[FileDataset, dict]:
    """The RTSTRUCT dataset of ``surfaces`` (see :func:`write_rtstruct`) and ``{name: number of
    contours}`` (the names as written, :func:`roi_name`), every extent checked
    (:func:`check_within_slices`) before anything is written; errors name ``source`` if given."""
    for surf in surfaces:
        check_within_slices(ct, f"{source}: ROI {surf[0]!r}" if source else f"ROI {surf[0]!r}", surf[1])
    ds = _base_dataset(ct, label)
    counts: dict[str, int] = {}
    for number, surf in enumerate(surfaces, start=1):
        name, v, f = surf[:3]
        kind = surf[3] if len(surf) > 3 else "ORGAN"
        contours = _slice_contours(ct, v, f)
        written = roi_name(name, counts)
        counts[written] = len(contours)
        _add_roi(ds, number, (written, name), kind, COLOURS[(number - 1) % len(COLOURS)], contours, ct)
    declare_charset(ds)  # UTF-8 when a name that is not ASCII: it round-trips
    return ds, counts


def write_rtstruct(path, ct: CTSeries, surfaces: list, *, label: str = "lungdeform") -> dict:
    """Write ``surfaces`` — ``(name, vertices (n, 3) float mm LPS, faces (m, 3) int)`` each, or
    ``(name, vertices, faces, kind)`` with an RT ROI interpreted type (GTV, ORGAN …; empty when none applies) — as an
    RTSTRUCT referencing ``ct``, every contour a section of the surface by one slice plane.
    Atomic. Returns ``{name as written: number of contours}`` (a name longer than a ROI Name holds is
    cut, :func:`roi_name`). A surface reaching beyond the slices is refused before anything is
    written (:func:`build_rtstruct`)."""
    ds, counts = build_rtstruct(ct, surfaces, label=label)
    save_rtstruct(path, ds)
    return counts


def save_rtstruct(path, ds: FileDataset) -> None:
    """Save the dataset of :func:`build_rtstruct` to ``path`` atomically, every value within its VR's
    limits first (:func:`~lungdeform.io.dicom.attributes.check_dataset`)."""
    check_dataset(ds, str(path))
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)


def _slice_contours(ct: CTSeries, vertices, faces) -> list[tuple[int, np.ndarray]]:
    """``(slice index, (k, 3) float mm)`` for each polygon where a slice plane cuts the surface, those
    that enclose no area left out (a plane through a pole of the surface cuts it in one point, which
    :func:`lungdeform.geometry.contours.enclosing` tells, as every reader would skip it)."""
    out = []
    h = np.asarray(vertices, float) @ ct.normal
    for k, origin in enumerate(ct.origins):
        level = origin @ ct.normal
        if h.min() <= level <= h.max():
            polygons = section_mesh(vertices, faces, origin, ct.normal)
            out += [(k, polygons[i]) for i in enclosing(polygons)[0]]
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
    ds.Manufacturer, ds.SeriesDescription = "lungdeform", fit_text(label, "LO")
    ds.FrameOfReferenceUID = ct.header.FrameOfReferenceUID
    ds.PositionReferenceIndicator = ct.header.get("PositionReferenceIndicator", "")
    ds.OperatorsName = ""  # Type 2 (RT Series module): not known here
    ds.StructureSetLabel = fit_text(label, "SH")  # SH: 16 bytes, cut on a character boundary
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


def _add_roi(ds: FileDataset, number: int, names: tuple[str, str], kind: str, colour, contours, ct: CTSeries) -> None:
    """One ROI: its name (StructureSetROISequence; ``names`` = (as written, whole): the whole in
    ROIDescription, ST, when the name had to be cut), colour and CLOSED_PLANAR contours, each
    referencing its slice (ROIContourSequence), and its interpreted type (RTROIObservationsSequence)."""
    roi = Dataset()
    roi.ROINumber, roi.ReferencedFrameOfReferenceUID = number, ct.header.FrameOfReferenceUID
    roi.ROIName, roi.ROIGenerationAlgorithm = names[0], "AUTOMATIC"
    if names[0] != names[1]:
        roi.ROIDescription = fit_text(names[1], "ST")
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
