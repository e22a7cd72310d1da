"""A small synthetic CT series written as DICOM with SimpleITK, for the RTSTRUCT tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

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
