"""A small synthetic CT series written as DICOM with SimpleITK, and minimal RTSTRUCTs of given contours,
for the RTSTRUCT tests and the bad-input corpus."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from pydicom import config
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian

CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"


def write_ct_series(folder: Path, shape=(20, 32, 32), spacing=(2.0, 2.0, 2.0), origin=(-31.0, -31.0, -19.0),
                    uid_root: str = "1.2.826.0.1.3680043.8.498.77") -> Path:
    """Axial slices ``shape`` = (z, y, x) of ``spacing`` (x, y, z) mm from ``origin`` (mm LPS), one
    file per slice, with the UIDs and geometry an RTSTRUCT references."""
    folder.mkdir(parents=True, exist_ok=True)
    arr = np.zeros(shape, np.int16)
    study, series, frame = f"{uid_root}.1", f"{uid_root}.2", f"{uid_root}.3"
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(shape[0]):
        img = sitk.GetImageFromArray(arr[k:k + 1])
        img.SetSpacing(spacing)
        z = origin[2] + k * spacing[2]
        img.SetOrigin((origin[0], origin[1], z))
        tags = {"0008|0060": "CT", "0008|0016": CT_SOP_CLASS, "0008|0018": f"{uid_root}.4.{k + 1}",
                "0020|000d": study, "0020|000e": series, "0020|0052": frame, "0020|0013": str(k + 1),
                "0010|0010": "Synthetic^Phantom", "0010|0020": "SYN001",
                "0020|0032": f"{origin[0]}\\{origin[1]}\\{z}", "0020|0037": "1\\0\\0\\0\\1\\0",
                "0028|0030": f"{spacing[1]}\\{spacing[0]}", "0018|0050": str(spacing[2])}
        for key, value in tags.items():
            img.SetMetaData(key, value)
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(img)
    return folder


#: The UIDs :func:`write_ct_series` gives by default (uid_root ``…77``): study, series, frame of reference
STUDY_UID, SERIES_UID, FRAME_UID = (f"1.2.826.0.1.3680043.8.498.77.{k}" for k in (1, 2, 3))


def rtstruct_bytes(rois, *, frame_uid: str = FRAME_UID, study_uid: str = STUDY_UID) -> bytes:
    """A minimal RTSTRUCT, byte for byte the same on every call: ``rois`` a list of ``(number,
    name, contours)`` or ``(number, name, contours, geometric type)``, each contour ``(k, 3)``
    mm or a list of strings (written as they stand, e.g. ``"nan"``). Values DICOM would refuse
    (NaN, a 65-character name) are written too: the files are bad inputs on purpose."""
    sop = "1.2.826.0.1.3680043.8.498.77.9.1"
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = "1.2.840.10008.5.1.4.1.1.481.3", sop
    meta.TransferSyntaxUID, meta.ImplementationClassUID = ExplicitVRLittleEndian, "1.2.826.0.1.3680043.8.498.1"
    ds = FileDataset("", Dataset(), file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = meta.MediaStorageSOPClassUID, sop, "RTSTRUCT"
    ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, "1.2.826.0.1.3680043.8.498.77.9.2"
    frame = Dataset()
    frame.FrameOfReferenceUID = frame_uid
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
    ds.StructureSetROISequence, ds.ROIContourSequence = Sequence(), Sequence()
    mode = config.settings.writing_validation_mode
    config.settings.writing_validation_mode = config.IGNORE
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pydicom's on a NaN DS: written on purpose
            for roi_spec in rois:
                _add_contours(ds, frame_uid, *roi_spec)
            buf = io.BytesIO()
            ds.save_as(buf, enforce_file_format=True)
    finally:
        config.settings.writing_validation_mode = mode
    return buf.getvalue()


def _add_contours(ds: Dataset, frame_uid: str, number: int, name: str, contours, kind: str = "CLOSED_PLANAR") -> None:
    roi = Dataset()
    roi.ROINumber, roi.ROIName, roi.ReferencedFrameOfReferenceUID = number, name, frame_uid
    ds.StructureSetROISequence.append(roi)
    rc = Dataset()
    rc.ReferencedROINumber, rc.ContourSequence = number, Sequence()
    for c in contours:
        item = Dataset()
        item.ContourGeometricType = kind
        item.ContourData = [v if isinstance(v, str) else f"{v:.3f}" for v in np.ravel(np.asarray(c, object))]
        item.NumberOfContourPoints = len(item.ContourData) // 3
        rc.ContourSequence.append(item)
    ds.ROIContourSequence.append(rc)


def circle(z: float, radius: float = 8.0, centre=(0.0, 0.0), n: int = 24) -> np.ndarray:
    """A closed polygon ``(n, 3)`` mm: a circle on the axial plane at ``z``."""
    t = 2 * np.pi * np.arange(n) / n
    return np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t), np.full(n, float(z))])


def patch_element(path: Path, group: int, element: int, value: bytes) -> None:
    """Replace the value of element (group, element) in the implicit-VR file ``path`` (as
    :func:`write_ct_series` writes) by ``value`` as it stands (padded to an even length): a value
    pydicom would refuse to write, such as a non-numeric ImagePositionPatient."""
    data = path.read_bytes()
    tag = group.to_bytes(2, "little") + element.to_bytes(2, "little")
    at = data.index(tag, 132)
    length = int.from_bytes(data[at + 4:at + 8], "little")
    value = value + b" " * (len(value) % 2)
    path.write_bytes(data[:at + 4] + len(value).to_bytes(4, "little") + value + data[at + 8 + length:])


DCIODVFY = "/usr/bin/dciodvfy"


def dciodvfy(path) -> tuple[list[str], list[str]]:
    """``(errors, warnings)``: the lines dciodvfy (Debian's dicom3tools, an independent IOD checker)
    prints for the DICOM file ``path``. Skips the calling test, naming what is missing, without it."""
    import shutil
    import subprocess

    import pytest

    exe = DCIODVFY if Path(DCIODVFY).exists() else shutil.which("dciodvfy")
    if exe is None:
        pytest.skip(f"{DCIODVFY} missing: apt-get install dicom3tools (make test does, as root)")
    out = subprocess.run([exe, str(path)], capture_output=True, text=True, errors="replace", timeout=120)
    lines = (out.stdout + out.stderr).splitlines()
    return [ln for ln in lines if ln.startswith("Error")], [ln for ln in lines if ln.startswith("Warning")]
