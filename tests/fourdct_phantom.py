"""A small synthetic 4-D CT written as DICOM (tests of lungdeform.io.dicom.fourdct, fit and cohort)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

SHAPE = (24, 48, 48)  # z, y, x voxels
SPACING = (4.0, 4.0, 6.0)  # mm, x y z
STUDY = "1.2.826.0.1.3680043.2.1125.7"


def phase_ct(scale: float, rng, shift_z: float = 0.0) -> np.ndarray:
    """A (z, y, x) int16 CT in HU: a body (40 HU, elliptic cylinder) in air (-1000 HU) holding two
    "lungs" (-850 HU), ellipsoids of semi-axes (28, 34, 44) mm * ``scale`` centred at x = +-40 mm,
    z = ``shift_z`` mm."""
    nz, ny, nx = SHAPE
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    p = np.stack([(i - (nx - 1) / 2) * SPACING[0], (j - (ny - 1) / 2) * SPACING[1],
                  (k - (nz - 1) / 2) * SPACING[2]], -1)
    ct = np.full(SHAPE, -1000.0)
    ct[(p[..., 0] / 90) ** 2 + (p[..., 1] / 80) ** 2 <= 1] = 40.0
    for sgn in (1.0, -1.0):
        ct[((((p - [sgn * 40.0, 0.0, shift_z]) / (np.array([28.0, 34.0, 44.0]) * scale)) ** 2).sum(-1)) <= 1] = -850.0
    return (ct + rng.normal(0, 5, ct.shape)).astype(np.int16)


def write_slices(folder, ct, tags: dict, series_uid: str, first_instance: int = 1, name: str = "s") -> None:
    """Write ``ct`` (z, y, x) as one DICOM file per slice into ``folder`` with the extra ``tags``."""
    folder.mkdir(parents=True, exist_ok=True)
    w = sitk.ImageFileWriter()
    w.KeepOriginalImageUIDOn()
    nz, ny, nx = ct.shape
    for n, sl in enumerate(ct):
        im = sitk.GetImageFromArray(sl[None])
        im.SetSpacing([SPACING[0], SPACING[1], 1.0])
        z = (n - (nz - 1) / 2) * SPACING[2]
        base = {"0008|0060": "CT", "0020|000e": series_uid, "0020|000d": STUDY,
                "0008|0018": f"{series_uid}.{first_instance + n}", "0020|0013": str(first_instance + n),
                "0020|0032": f"{-(nx - 1) / 2 * SPACING[0]}\\{-(ny - 1) / 2 * SPACING[1]}\\{z}",
                "0020|0037": "1\\0\\0\\0\\1\\0", "0028|0030": f"{SPACING[1]}\\{SPACING[0]}",
                "0018|0050": str(SPACING[2]), "0028|1052": "0", "0028|1053": "1"}
        for tag, value in {**base, **tags}.items():
            im.SetMetaData(tag, value)
        w.SetFileName(str(folder / f"{name}{first_instance + n:04d}.dcm"))
        w.Execute(im)


def write_4dct(folder, rng, n_phases: int = 4, mode: str = "description", order=None) -> list[float]:
    """A 4-D CT in ``folder``: phase ``p`` (0 … n-1) inflates the lungs by ``1 + 0.06 p`` per axis.

    ``mode``: ``"description"``: a series per phase with SeriesDescription ``"CT <10 p>%"``, each in a
    subfolder; ``"index"``: one series, slices repeated per phase with TemporalPositionIndex ``p + 1``
    only; ``"same"``: a series per phase with nothing telling them apart. ``order``: the order in
    which the phases are written (default ``reversed``: the files' order must not matter).
    Returns the scales, by phase."""
    scales = [1.0 + 0.06 * p for p in range(n_phases)]
    for p in (order if order is not None else reversed(range(n_phases))):
        ct = phase_ct(scales[p], rng)
        if mode == "description":
            write_slices(folder / f"phase{p}", ct, {"0008|103e": f"Gated {10 * p}%"}, f"{STUDY}.{p + 1}")
        elif mode == "index":
            write_slices(folder, ct, {"0020|9128": str(p + 1), "0008|103e": "4D CT"}, f"{STUDY}.1",
                         first_instance=1 + p * SHAPE[0])
        else:
            write_slices(folder, ct, {"0008|103e": "4D CT"}, f"{STUDY}.{p + 1}", name=f"p{p}_")
    return scales


def write_cycle(folder, rng, scales, shifts_z=None, frame_uid: str | None = None) -> None:
    """A full-cycle 4-D CT in ``folder``: phase ``p`` (SeriesDescription ``"CT <100 p / n>%"``, a
    subfolder each) has lungs scaled by ``scales[p]`` per axis and moved by ``shifts_z[p]`` mm
    along z; ``frame_uid``: the FrameOfReferenceUID of every slice (none when None)."""
    n = len(scales)
    for p in range(n):
        ct = phase_ct(scales[p], rng, 0.0 if shifts_z is None else shifts_z[p])
        tags = {"0008|103e": f"CT {100 * p // n}%", **({"0020|0052": frame_uid} if frame_uid else {})}
        write_slices(folder / f"phase{p}", ct, tags, f"{STUDY}.{p + 1}")
