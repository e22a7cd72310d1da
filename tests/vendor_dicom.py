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
    refs = [_image_ref(u) for u in ct["sop_uids"]]
    series = Dataset()
    series.SeriesInstanceUID, series.ContourImageSequence = SERIES_UID, Sequence(refs)
    study = Dataset()
    study.ReferencedSOPClassUID, study.ReferencedSOPInstanceUID = "1.2.840.10008.3.1.2.3.1", STUDY_UID
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID, frame.RTReferencedStudySequence = FRAME_UID, Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
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
            c.ContourGeometricType = "POINT" if len(pts) == 1 else "CLOSED_PLANAR"
            c.NumberOfContourPoints, c.ContourNumber = len(pts), i
            c.ContourData = [f"{x:.2f}" for x in np.asarray(pts, float).ravel()]
            rc.ContourSequence.append(c)
    ds.ROIContourSequence.append(rc)
    obs = Dataset()
    obs.ObservationNumber, obs.ReferencedROINumber, obs.RTROIInterpretedType = number, number, kind
    obs.ROIInterpreter = ""
    ds.RTROIObservationsSequence.append(obs)
