"""A vendor-like DICOM export that no lungdeform code wrote, for the radiotherapy workflow tests.

:func:`write_vendor_ct` writes a CT volume with plain pydicom the way scanner and PACS exports look:
random file names without a suffix, slices in random file order, InstanceNumber not following the
slice position, Rescale slope/intercept 0.5/−1100 over unsigned pixels, private tags (a Siemens-style
private block), Latin-1 patient name (SpecificCharacterSet ISO_IR 100), GantryDetectorTilt 0, every
third file in implicit VR little endian, and in the same folder a coronal localizer (scout) image and
a second, thicker reconstruction of the same study. :func:`write_planning_rtstruct` writes, again
with pydicom alone, an RTSTRUCT in the style of a treatment planning system: a spherical GTV as one
CLOSED_PLANAR contour per slice (listed in random order, each referencing its slice), an external
POINT marker ROI, the ReferencedFrameOfReference → study → series → image chain over every slice.
All of it is legal DICOM (PS3.3 A.3, A.19; PS3.5 7.8 private data elements).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"
RTSTRUCT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.481.3"
#: A vendor-like UID root (not pydicom's, not lungdeform's)
ROOT = "1.3.12.2.1107.5.1.4.424242"
PATIENT = {"PatientName": "Müller^Jürgen", "PatientID": "VND-0042", "PatientBirthDate": "19580304", "PatientSex": "M"}
STUDY_UID, FRAME_UID = f"{ROOT}.1.1", f"{ROOT}.1.2"
SERIES_UID, THICK_UID, SCOUT_UID = f"{ROOT}.2.1", f"{ROOT}.2.2", f"{ROOT}.2.3"
SLOPE, INTERCEPT = 0.5, -1100.0


def _meta(sop_class: str, sop_uid: str, implicit: bool) -> FileMetaDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = sop_class, sop_uid
    meta.TransferSyntaxUID = ImplicitVRLittleEndian if implicit else ExplicitVRLittleEndian
    meta.ImplementationClassUID, meta.ImplementationVersionName = f"{ROOT}.9", "VENDOR_VA42"
    return meta


def _common(ds: Dataset) -> None:
    """Patient, study, equipment and frame of reference, as a scanner writes them."""
    ds.SpecificCharacterSet = "ISO_IR 100"
    for key, value in PATIENT.items():
        setattr(ds, key, value)
    ds.StudyInstanceUID, ds.FrameOfReferenceUID = STUDY_UID, FRAME_UID
    ds.StudyDate, ds.StudyTime, ds.StudyID, ds.AccessionNumber = "20260301", "101500.123000", "4711", "ACC0815"
    ds.ReferringPhysicianName, ds.StudyDescription = "", "Thorax^01_Planning (Adult)"
    ds.PositionReferenceIndicator, ds.Manufacturer, ds.ManufacturerModelName = "", "SIEMENS", "SOMATOM Confidence"
    ds.InstitutionName, ds.StationName, ds.SoftwareVersions = "Klinikum Beispiel", "CTAWP00001", "syngo CT VB20A"
    ds.Modality, ds.PatientPosition, ds.BodyPartExamined = "CT", "HFS", "CHEST"
    # a private block (PS3.5 7.8): creator at (0019,0010), its elements at (0019,10xx)
    ds.add_new(0x00190010, "LO", "ACMEMED CT RECON 2")
    ds.add_new(0x00191090, "LO", "0.5 mm detector; Br40d")
    ds.add_new(0x00191092, "DS", "120.0")
    ds.add_new(0x00290010, "LO", "ACMEMED CT RAW 1")
    ds.add_new(0x00291010, "OB", b"SV10\x04\x03\x02\x01" * 8)


def _slice(image_hu: np.ndarray, position, k: int, instance: int, series: tuple, geometry: dict) -> FileDataset:
    """One CT Image Storage slice of ``image_hu`` (y, x) HU at ``position`` mm LPS."""
    uid = f"{ROOT}.3.{series[2]}.{k + 1}"
    ds = FileDataset("", Dataset(), file_meta=_meta(CT_SOP_CLASS, uid, geometry["implicit"]), preamble=b"\0" * 128)
    _common(ds)
    ds.SOPClassUID, ds.SOPInstanceUID = CT_SOP_CLASS, uid
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.SeriesDescription = series[0], series[1], series[3]
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "CT_SOM5 SPI"]
    ds.InstanceNumber, ds.AcquisitionNumber = instance, 2
    ds.ContentDate, ds.ContentTime, ds.AcquisitionTime = "20260301", f"1016{k % 60:02d}.5", "101601.250000"
    ds.KVP, ds.ConvolutionKernel, ds.GantryDetectorTilt = "120", ["Br40d", "3"], "0"
    ds.SliceThickness, ds.PixelSpacing = f"{geometry['spacing'][2]:g}", [f"{geometry['spacing'][1]:g}", f"{geometry['spacing'][0]:g}"]
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    ds.ImagePositionPatient = [f"{x:.4f}" for x in position]
    ds.SliceLocation = f"{position[2]:.4f}"
    ds.Rows, ds.Columns = image_hu.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.RescaleSlope, ds.RescaleIntercept, ds.RescaleType = f"{SLOPE:g}", f"{INTERCEPT:g}", "HU"
    ds.WindowCenter, ds.WindowWidth = ["-600", "40"], ["1200", "400"]
    stored = np.rint((np.asarray(image_hu, float) - INTERCEPT) / SLOPE)
    assert stored.min() >= 0 and stored.max() < 4096, "HU outside 12 unsigned bits at slope 0.5"
    ds.PixelData = stored.astype("<u2").tobytes()
    return ds


def write_vendor_ct(folder, image, rng) -> dict:
    """Write ``image`` (:class:`lungdeform.io.grid.Image`, HU, axial, identity direction) as a
    vendor-like export into ``folder`` (module docstring), with a localizer and a second series.
    Returns ``{"files": main series' paths in slice order, "sop_uids": their SOP Instance UIDs}``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    a = np.asarray(image.array, float)
    nz = a.shape[0]
    origin, spacing = np.asarray(image.origin, float), np.asarray(image.spacing, float)
    names = [f"{rng.integers(16 ** 12):012X}" for _ in range(nz + nz // 2 + 1)]
    instances = rng.permutation(nz) + 1  # InstanceNumber unrelated to the position
    order = rng.permutation(nz)  # written in random order
    files, uids = [None] * nz, [None] * nz
    for n, k in enumerate(order):
        geometry = {"spacing": spacing, "implicit": n % 3 == 0}
        ds = _slice(a[k], origin + [0, 0, k * spacing[2]], int(k), int(instances[k]),
                    (SERIES_UID, 2, 3, "Thorax 3.0 Br40 Planning"), geometry)
        files[k], uids[k] = folder / names[n], str(ds.SOPInstanceUID)
        ds.save_as(files[k], implicit_vr=geometry["implicit"], little_endian=True, enforce_file_format=True)
    for n, k in enumerate(range(0, nz - 1, 2)):  # the same study reconstructed at twice the slice gap
        thick = {"spacing": spacing * [1, 1, 2], "implicit": False}
        ds = _slice(a[k], origin + [0, 0, k * spacing[2]], k, n + 1, (THICK_UID, 3, 4, "Thorax 6.0 Br40"), thick)
        ds.save_as(folder / names[nz + n], enforce_file_format=True)
    _write_scout(folder / names[-1], a, origin, spacing)
    return {"files": [str(f) for f in files], "sop_uids": uids}


def _write_scout(path: Path, a: np.ndarray, origin, spacing) -> None:
    """A coronal localizer (topogram) of the volume: one image, ImageType …\\LOCALIZER."""
    uid = f"{ROOT}.3.1.1"
    ds = FileDataset("", Dataset(), file_meta=_meta(CT_SOP_CLASS, uid, False), preamble=b"\0" * 128)
    _common(ds)
    ds.SOPClassUID, ds.SOPInstanceUID = CT_SOP_CLASS, uid
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.SeriesDescription = SCOUT_UID, 1, "Topogram 0.6 T20f"
    ds.ImageType, ds.InstanceNumber, ds.AcquisitionNumber = ["ORIGINAL", "PRIMARY", "LOCALIZER", "CT_SOM5 TOP"], 1, 1
    ds.KVP, ds.GantryDetectorTilt, ds.SliceThickness = "120", "0", "0.6"
    proj = np.clip(a.mean(axis=1)[::-1], -1000, 1000)  # (z top first, x)
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "0", "-1"]
    top = origin + [0, 0, (a.shape[0] - 1) * spacing[2]]
    ds.ImagePositionPatient = [f"{x:.4f}" for x in top]
    ds.PixelSpacing = [f"{spacing[2]:g}", f"{spacing[0]:g}"]
    ds.Rows, ds.Columns = proj.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.RescaleSlope, ds.RescaleIntercept = f"{SLOPE:g}", f"{INTERCEPT:g}"
    ds.PixelData = np.rint((proj - INTERCEPT) / SLOPE).astype("<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)


def write_planning_rtstruct(path, ct: dict, image, centre, radius: float, rng) -> Path:
    """An RTSTRUCT in the style of a planning system on the series :func:`write_vendor_ct` wrote
    (``ct`` its return value, ``image`` its volume): ROI 1 "External" (an empty body ROI: no
    contours), ROI 2 "GTV" a sphere of ``radius`` mm about ``centre`` (mm LPS), a 48-point circle on
    every slice it crosses, contours in random order; ROI 3 "Marker" a POINT."""
    origin, spacing = np.asarray(image.origin, float), np.asarray(image.spacing, float)
    uid = f"{ROOT}.5.1"
    ds = FileDataset("", Dataset(), file_meta=_meta(RTSTRUCT_SOP_CLASS, uid, False), preamble=b"\0" * 128)
    _common(ds)
    for key in ("PatientPosition", "BodyPartExamined"):
        del ds[key]
    ds.Modality, ds.SOPClassUID, ds.SOPInstanceUID = "RTSTRUCT", RTSTRUCT_SOP_CLASS, uid
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.SeriesDescription = f"{ROOT}.2.9", 9, "RTSTRUCT planning"
    ds.InstanceNumber, ds.OperatorsName = 1, "Planner^Paula"
    ds.StructureSetLabel, ds.StructureSetName = "Plan1", "Thorax Plan 1"
    now = _dt.datetime(2026, 3, 2, 9, 30)
    ds.StructureSetDate, ds.StructureSetTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.ReferencedFrameOfReferenceSequence = _frame_chain(ct["sop_uids"])
    z = origin[2] + np.arange(len(ct["sop_uids"])) * spacing[2]
    gtv = [(k, _circle(centre, radius, z[k])) for k in np.flatnonzero(np.abs(z - centre[2]) < radius)]
    gtv = [gtv[i] for i in rng.permutation(len(gtv))]
    marker = [(int(np.argmin(np.abs(z - centre[2]))), np.asarray(centre, float)[None])]
    rois = [(1, "External", "EXTERNAL", []), (2, "GTV", "GTV", gtv), (3, "Marker", "MARKER", marker)]
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = Sequence(), Sequence(), Sequence()
    for number, name, kind, contours in rois:
        _roi(ds, number, name, kind, contours, ct["sop_uids"])
    ds.save_as(path, enforce_file_format=True)
    return Path(path)


def _frame_chain(sop_uids) -> Sequence:
    """ReferencedFrameOfReferenceSequence → study → series → every image of the main series."""
    series = Dataset()
    series.SeriesInstanceUID, series.ContourImageSequence = SERIES_UID, Sequence([_image_ref(u) for u in sop_uids])
    study = Dataset()
    study.ReferencedSOPClassUID, study.ReferencedSOPInstanceUID = "1.2.840.10008.3.1.2.3.1", STUDY_UID
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID, frame.RTReferencedStudySequence = FRAME_UID, Sequence([study])
    return Sequence([frame])


def _image_ref(uid: str) -> Dataset:
    ref = Dataset()
    ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID = CT_SOP_CLASS, uid
    return ref


def _circle(centre, radius: float, z: float) -> np.ndarray:
    r = np.sqrt(radius ** 2 - (z - centre[2]) ** 2)
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    return np.stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t), np.full_like(t, z)], 1)


def _roi(ds: Dataset, number: int, name: str, kind: str, contours, sop_uids) -> None:
    roi = Dataset()
    roi.ROINumber, roi.ReferencedFrameOfReferenceUID, roi.ROIName = number, FRAME_UID, name
    roi.ROIGenerationAlgorithm = "MANUAL"
    ds.StructureSetROISequence.append(roi)
    rc = Dataset()
    rc.ROIDisplayColor, rc.ReferencedROINumber = [255, 0, 0], number
    if contours:
        rc.ContourSequence = Sequence()
        for i, (k, pts) in enumerate(contours, start=1):
            c = Dataset()
            c.ContourImageSequence = Sequence([_image_ref(sop_uids[k])])
            c.ContourGeometricType = "POINT" if kind == "MARKER" else "CLOSED_PLANAR"  # a tool's 1-point tip too
            c.NumberOfContourPoints, c.ContourNumber = len(pts), i
            c.ContourData = [f"{x:.2f}" for x in np.asarray(pts, float).ravel()]
            rc.ContourSequence.append(c)
    ds.ROIContourSequence.append(rc)
    obs = Dataset()
    obs.ObservationNumber, obs.ReferencedROINumber, obs.RTROIInterpretedType = number, number, kind
    obs.ROIInterpreter = ""
    ds.RTROIObservationsSequence.append(obs)


# --- the rest of an export (issue 36): what a planning system writes beside the CT --------------------

RTPLAN_SOP_CLASS, RTDOSE_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.481.5", "1.2.840.10008.5.1.4.1.1.481.2"
REG_SOP_CLASS, KO_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.66.1", "1.2.840.10008.5.1.4.1.1.88.59"
#: The objects :func:`write_export_extras` writes: file name → what lungdeform says it ignored
EXTRAS = {"RS_plan.dcm": "RTSTRUCT", "RP_plan.dcm": "RTPLAN", "RD_plan.dcm": "RTDOSE grid", "RE_rigid.dcm": "REG",
          "KO_selection.dcm": "KO", "README.txt": "no DICOM", "Thumbs.db": "no DICOM"}


def _object(sop_class: str, uid: str, modality: str, series: int) -> FileDataset:
    ds = FileDataset("", Dataset(), file_meta=_meta(sop_class, uid, False), preamble=b"\0" * 128)
    _common(ds)
    for key in ("PatientPosition", "BodyPartExamined"):
        del ds[key]
    ds.Modality, ds.SOPClassUID, ds.SOPInstanceUID = modality, sop_class, uid
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.InstanceNumber = f"{ROOT}.2.{series}", series, 1
    ds.ContentDate, ds.ContentTime = "20260302", "093000"
    ds.ContentLabel, ds.ContentDescription, ds.ContentCreatorName = modality, "", ""
    return ds


def write_rtplan(path) -> Path:
    """A minimal RT Plan (no pixels): a label, one fraction group, one beam."""
    ds = _object(RTPLAN_SOP_CLASS, f"{ROOT}.6.1", "RTPLAN", 10)
    ds.RTPlanLabel, ds.RTPlanName, ds.RTPlanDate, ds.RTPlanTime = "Lung1", "Lung SBRT", "20260302", "093000"
    ds.RTPlanGeometry, ds.ApprovalStatus = "PATIENT", "UNAPPROVED"
    beam = Dataset()
    beam.BeamNumber, beam.BeamName, beam.BeamType, beam.RadiationType = 1, "AP", "STATIC", "PHOTON"
    ds.BeamSequence = Sequence([beam])
    ds.save_as(path, enforce_file_format=True)
    return Path(path)


def write_rtdose(path, image) -> Path:
    """An RT Dose grid (an image: multi-frame, Modality RTDOSE) over ``image``'s box at 4 mm."""
    ds = _object(RTDOSE_SOP_CLASS, f"{ROOT}.7.1", "RTDOSE", 11)
    ds.DoseUnits, ds.DoseType, ds.DoseSummationType = "GY", "PHYSICAL", "PLAN"
    nz, ny, nx = (max(2, n // 2) for n in image.array.shape)
    ds.Rows, ds.Columns, ds.NumberOfFrames = ny, nx, nz
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 32, 32, 31, 0
    ds.ImagePositionPatient = [f"{x:.2f}" for x in image.origin]
    ds.ImageOrientationPatient = ["1", "0", "0", "0", "1", "0"]
    step = 2 * np.asarray(image.spacing, float)
    ds.PixelSpacing = [f"{step[1]:g}", f"{step[0]:g}"]
    ds.GridFrameOffsetVector = [f"{k * step[2]:g}" for k in range(nz)]
    ds.FrameIncrementPointer, ds.DoseGridScaling = 0x3004000C, "1e-4"
    ds.PixelData = (np.arange(nz * ny * nx, dtype="<u4") % 50000).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return Path(path)


def write_rigid_registration(path) -> Path:
    """A Spatial Registration (REG, no pixels): the CT's frame onto itself."""
    ds = _object(REG_SOP_CLASS, f"{ROOT}.8.1", "REG", 12)
    item = Dataset()
    item.FrameOfReferenceUID = FRAME_UID
    matrix = Dataset()
    matrix.FrameOfReferenceTransformationMatrixType = "RIGID"
    matrix.FrameOfReferenceTransformationMatrix = [str(x) for x in np.eye(4).ravel().astype(int)]
    reg = Dataset()
    reg.MatrixRegistrationSequence = Sequence([Dataset()])
    reg.MatrixRegistrationSequence[0].MatrixSequence = Sequence([matrix])
    item.MatrixRegistrationSequence = reg.MatrixRegistrationSequence
    ds.RegistrationSequence = Sequence([item])
    ds.save_as(path, enforce_file_format=True)
    return Path(path)


def write_key_object(path) -> Path:
    """A Key Object Selection document (KO, no pixels), as PACS exports add them."""
    ds = _object(KO_SOP_CLASS, f"{ROOT}.9.1", "KO", 13)
    code = Dataset()
    code.CodeValue, code.CodingSchemeDesignator, code.CodeMeaning = "113000", "DCM", "Of Interest"
    ds.ConceptNameCodeSequence, ds.ValueType = Sequence([code]), "CONTAINER"
    ds.save_as(path, enforce_file_format=True)
    return Path(path)


def write_export_extras(folder, image, rois_ct: dict, rng, gtv=((-45.0, -8.0, 10.0), 10.0)) -> dict:
    """Beside the CT of :func:`write_vendor_ct` in ``folder``: the structure set of
    :func:`write_structure_set` (``rois_ct``: its ``ct`` argument; ``gtv``: its GTV's centre mm LPS
    and radius mm), an RT Plan, an RT Dose grid, a rigid REG, a KO, a README and a ``Thumbs.db``
    (:data:`EXTRAS`). Returns ``{name: path}``."""
    folder = Path(folder)
    out = {"RS_plan.dcm": write_structure_set(folder / "RS_plan.dcm", rois_ct, image, rng, *gtv),
           "RP_plan.dcm": write_rtplan(folder / "RP_plan.dcm"), "RD_plan.dcm": write_rtdose(folder / "RD_plan.dcm", image),
           "RE_rigid.dcm": write_rigid_registration(folder / "RE_rigid.dcm"),
           "KO_selection.dcm": write_key_object(folder / "KO_selection.dcm")}
    (folder / "README.txt").write_text("Export of plan Lung1 (Thorax). Do not edit.\n")
    (folder / "Thumbs.db").write_bytes(b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1" + bytes(rng.integers(0, 256, 504, dtype=np.uint8)))
    out.update({"README.txt": folder / "README.txt", "Thumbs.db": folder / "Thumbs.db"})
    return out


def write_dicomdir_export(files, dest) -> Path:
    """The DICOM ``files`` as a media export (PS3.10): pydicom's File-set writes them under ``dest``
    (``PT000000/ST000000/SE000000/IM000000`` …) with a DICOMDIR at the top; a README beside it."""
    from pydicom.fileset import FileSet

    fs = FileSet()
    try:
        for f in files:
            fs.add(str(f))
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        fs.write(str(dest))
    finally:  # the File-set's staging folder, removed now (left to the garbage collector it warns)
        fs._stage["t"].cleanup()
    (dest / "README.TXT").write_text("Patient CD. Open DICOMDIR with a DICOM viewer.\n")
    return dest / "DICOMDIR"


#: The ROIs of :func:`write_structure_set` tracked and checked by the tests: (name, kind)
GTV_NAME = "GTV_β肿瘤"


def write_structure_set(path, ct: dict, image, rng, centre=(-45.0, -8.0, 10.0), radius: float = 10.0) -> Path:
    """A structure set of 30 ROIs as planning systems and mask-to-contour tools leave them, on the series
    :func:`write_vendor_ct` wrote (``ct`` its return value): ROI names in several scripts
    (SpecificCharacterSet ISO_IR 192); "External" and four more without contours; three POINT ROIs;
    :data:`GTV_NAME` a sphere of ``radius`` mm about ``centre`` (mm LPS) with a mask-to-contour tool's
    leftovers: a 2-point tip on the slice above it, a 1-point tip and a repeated-point contour on
    slices it covers, and a zero-area (collinear) contour; 21 organ-like balls elsewhere, 4 mm to 8 mm."""
    origin, spacing = np.asarray(image.origin, float), np.asarray(image.spacing, float)
    uid = f"{ROOT}.5.2"
    ds = _object(RTSTRUCT_SOP_CLASS, uid, "RTSTRUCT", 14)
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.OperatorsName, ds.StructureSetLabel, ds.StructureSetName = "Planner^Paula", "Plan1", "Thorax Plan 1"
    ds.StructureSetDate, ds.StructureSetTime = "20260302", "093000"
    ds.ReferencedFrameOfReferenceSequence = _frame_chain(ct["sop_uids"])
    z = origin[2] + np.arange(len(ct["sop_uids"])) * spacing[2]
    centre = np.asarray(centre, float)
    on = np.flatnonzero(np.abs(z - centre[2]) < radius)
    gtv = [(k, _circle(centre, radius, z[k])) for k in on]
    mid, top = int(on[len(on) // 2]), int(on[-1]) + 1
    gtv += [(top, np.array([[centre[0], centre[1], z[top]], [centre[0] + 0.7, centre[1], z[top]]])),  # 2-point tip
            (mid, np.array([[centre[0] + radius - 0.5, centre[1], z[mid]]])),  # 1-point tip
            (int(on[1]), np.array([[centre[0], centre[1] + 2, z[on[1]]], [centre[0] + 1, centre[1] + 2, z[on[1]]],
                                   [centre[0], centre[1] + 2, z[on[1]]]])),  # a repeated point: no area
            (int(on[2]), np.array([[centre[0] + t, centre[1] - 3, z[on[2]]] for t in (0.0, 0.5, 1.0)]))]  # collinear
    gtv = [gtv[i] for i in rng.permutation(len(gtv))]
    rois = [(1, "External", "EXTERNAL", []), (2, GTV_NAME, "GTV", gtv),
            (3, "Marker", "MARKER", [(int(on[0]), centre[None])])]
    names = ["Lunge_links", "Lunge_rechts", "肺_右", "肺_左", "Καρδιά", "Οισοφάγος", "القلب", "الحبل_الشوكي",
             "e\u0301sophage", "Trache\u0301e", "PTV", "CTV", "Rib_1", "Rib_2", "Rib_3", "Bronchus", "Aorta",
             "Vena_cava", "Liver_dome", "Stomach", "Scapula_L", "Empty_1", "Empty_2", "Empty_3", "Empty_4",
             "Point_A", "Point_B"]
    far = origin + (np.array(image.array.shape[::-1]) - 1) * spacing
    margin = np.minimum(12.0, (far - origin) / 4)
    box_lo, box_hi = origin + margin, far - margin
    for n, name in enumerate(names, start=4):
        if name.startswith("Empty"):
            rois.append((n, name, "ORGAN", []))
            continue
        c = rng.uniform(box_lo, box_hi)
        k = int(np.argmin(np.abs(z - c[2])))
        if name.startswith("Point"):
            rois.append((n, name, "MARKER", [(k, np.array([[c[0], c[1], z[k]]]))]))
            continue
        r = rng.uniform(4.0, 8.0)
        rois.append((n, name, "ORGAN", [(j, _circle(c, r, z[j])) for j in np.flatnonzero(np.abs(z - c[2]) < r)]))
    ds.StructureSetROISequence, ds.ROIContourSequence, ds.RTROIObservationsSequence = Sequence(), Sequence(), Sequence()
    for number, name, kind, contours in rois:
        _roi(ds, number, name, kind, contours, ct["sop_uids"])
    ds.save_as(path, enforce_file_format=True)
    return Path(path)
