"""The geometry of a DICOM series' slices, checked before its voxels are read.

A series is read as one regular grid (:class:`lungdeform.io.grid.Image`): one orientation, slices
stacked along the normal of that orientation, evenly spaced. ITK reads any series onto such a grid
whatever its slices say: it spaces them by the distance from the first slice to the last divided by
their number, and ignores a gantry tilt. :func:`check_slices` refuses what such a grid would
misplace, with a :class:`~lungdeform.errors.ReadError` naming the folder, the file and the cause:

- an ImageOrientationPatient (0020,0037) that is not six finite numbers making two orthogonal unit
  vectors (:data:`ORTHO_TOL`), or that differs between slices;
- an ImagePositionPatient (0020,0032) that is not three finite numbers;
- a PixelSpacing (0028,0030) that is not two positive finite numbers, or Rows, Columns or
  PixelSpacing that differ between slices (ITK takes the first slice's);
- two slices at one position, uneven gaps between slices or a missing slice (gaps differing from
  their median by more than :data:`GAP_TOL` of it and :data:`GAP_TOL_MM`);
- a gantry tilt: slice positions that step away from the slice normal by more than
  :data:`TILT_TOL_DEG`, or a GantryDetectorTilt (0018,1120) other than 0.

Frames: positions are mm in the patient frame (LPS); the slice normal is ``row × column`` of
ImageOrientationPatient.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.errors import ReadError

#: ImagePositionPatient, ImageOrientationPatient, GantryDetectorTilt, PixelSpacing, Rows, Columns:
#: the tags :func:`check_slices` reads.
GEOMETRY_TAGS = ("0020|0032", "0020|0037", "0018|1120", "0028|0030", "0028|0010", "0028|0011")
#: Largest departure of an orientation's vectors from unit length and from orthogonality (DICOM
#: stores them as decimal strings of up to 16 characters: 1e-6 is usual, 1e-3 is generous).
ORTHO_TOL = 1e-3
#: Largest relative departure of a gap between slices from the median gap ...
GAP_TOL = 0.01
#: ... or in mm, whichever is larger (positions written with 2 decimals: 0.625 mm reads 0.62 or 0.63).
GAP_TOL_MM = 0.011
#: Largest angle (degrees) between the slices' stacking direction and their normal.
TILT_TOL_DEG = 0.5


@dataclass(frozen=True)
class SliceGeometry:
    """A series' slices in order along their normal.

    Attributes
    ----------
    files : tuple of str
        The files, ordered by position along the normal (ascending).
    positions : (n,) float
        Their positions along the normal, mm.
    spacing : float
        The gap between slices, mm (0 for one slice).
    """

    files: tuple[str, ...]
    positions: np.ndarray
    spacing: float


def _numbers(text: str, count: int, name: str, where: str, path: str) -> np.ndarray:
    """``count`` finite numbers of a backslash-separated DICOM value, or ReadError naming ``path``."""
    try:
        values = np.array([float(v) for v in text.split("\\")], dtype=np.float64)
    except ValueError:
        values = None
    if values is None or values.shape != (count,) or not np.isfinite(values).all():
        shown = text if len(text) <= 80 else text[:77] + "..."
        what = "missing" if not text.strip() else f"'{shown}', not {count} finite numbers"
        raise ReadError(f"{where}: {path}: {name} is {what}")
    return values


def orientation(text: str, where: str, path: str) -> np.ndarray:
    """ImageOrientationPatient as a (2, 3) array of the row and column unit vectors; ReadError naming
    ``path`` when it is not six finite numbers making two orthogonal unit vectors."""
    iop = _numbers(text, 6, "ImageOrientationPatient", where, path).reshape(2, 3)
    norms = np.linalg.norm(iop, axis=1)
    if np.abs(norms - 1).max() > ORTHO_TOL or abs(float(iop[0] @ iop[1])) > ORTHO_TOL:
        raise ReadError(f"{where}: {path}: ImageOrientationPatient '{text}' is not two orthogonal unit vectors "
                        f"(lengths {norms[0]:.4g} and {norms[1]:.4g}, dot product {float(iop[0] @ iop[1]):.4g})")
    return iop


def _gantry_tilt(tags: dict[str, str], where: str, path: str) -> None:
    """ReadError when GantryDetectorTilt is present and not 0 (degrees)."""
    text = tags.get("0018|1120", "").strip()
    if not text:
        return
    try:
        tilt = float(text)
    except ValueError:
        tilt = float("nan")
    if not tilt == 0:
        raise ReadError(f"{where}: {path}: GantryDetectorTilt is {text} degrees; a tilted-gantry series is not a "
                        "regular grid: resample it to axial slices first")


def check_orientations(slices: list[tuple[str, dict[str, str]]], where) -> np.ndarray:
    """The one orientation (:func:`orientation`, (2, 3)) of the slices ``[(file, tags)]``;
    ReadError naming the file whose ImageOrientationPatient is malformed or differs from the first's."""
    if not slices:
        raise ReadError(f"{where}: no slices")
    first = orientation(slices[0][1].get("0020|0037", ""), where, slices[0][0])
    for path, tags in slices[1:]:
        if np.abs(orientation(tags.get("0020|0037", ""), where, path) - first).max() > ORTHO_TOL:
            raise ReadError(f"{where}: {path}: ImageOrientationPatient differs from that of {slices[0][0]}; "
                            "the slices of one series must share one orientation")
    return first


def check_slices(slices: list[tuple[str, dict[str, str]]], where) -> SliceGeometry:
    """The geometry of one series' slices ``[(file, tags)]`` (``tags``: DICOM tag ``"gggg|eeee"`` →
    stripped string, at least :data:`GEOMETRY_TAGS`), after the checks of the module docstring;
    ``where`` (the folder or series) begins every message."""
    first = check_orientations(slices, where)
    for path, tags in slices:
        _gantry_tilt(tags, where, path)
    _check_pixels(slices, where)
    ipp = np.array([_numbers(tags.get("0020|0032", ""), 3, "ImagePositionPatient", where, path)
                    for path, tags in slices])
    normal = np.cross(first[0], first[1])
    order = np.argsort(ipp @ normal, kind="stable")
    files = tuple(slices[k][0] for k in order)
    ipp = ipp[order]
    z = ipp @ normal
    if len(z) < 2:
        return SliceGeometry(files, z, 0.0)
    check_gaps(files, z, where)
    _check_tilt(files, ipp, normal, where)
    return SliceGeometry(files, z, float(np.median(np.diff(z))))


def _check_pixels(slices: list[tuple[str, dict[str, str]]], where) -> None:
    """ReadError when a PixelSpacing is not two positive finite numbers, or PixelSpacing, Rows or
    Columns differ between slices."""
    first_path, first = slices[0]
    spacing0 = None
    for path, tags in slices:
        spacing = _numbers(tags.get("0028|0030", ""), 2, "PixelSpacing", where, path)
        if not (spacing > 0).all():
            raise ReadError(f"{where}: {path}: PixelSpacing '{tags['0028|0030']}' is not two positive numbers")
        spacing0 = spacing if spacing0 is None else spacing0
        if np.abs(spacing - spacing0).max() > 1e-4 * spacing0.max():
            raise ReadError(f"{where}: {path}: PixelSpacing '{tags['0028|0030']}' differs from that of {first_path} "
                            f"('{first['0028|0030']}'); the slices of one series must share one pixel size")
        for tag, name in (("0028|0010", "Rows"), ("0028|0011", "Columns")):
            if tags.get(tag, "") != first.get(tag, ""):
                raise ReadError(f"{where}: {path}: {name} {tags.get(tag, '')!r} differs from that of {first_path} "
                                f"({first.get(tag, '')!r}); the slices of one series must share one grid")


def check_gaps(files: tuple[str, ...], z: np.ndarray, where) -> None:
    """ReadError for two slices at one position, uneven gaps or a missing slice (``z``: the slices'
    sorted positions along their normal, mm; ``files`` in the same order; ``where`` begins the
    message). The one spacing check of every series reader (image, 4-D CT, RTSTRUCT's reference CT)."""
    gaps = np.diff(z)
    same = np.flatnonzero(gaps <= GAP_TOL_MM)
    if same.size:
        k = int(same[0])
        raise ReadError(f"{where}: two slices at one position ({z[k]:.3f} mm along the slice normal): "
                        f"{Path(files[k]).name} and {Path(files[k + 1]).name}")
    med = float(np.median(gaps))
    off = np.abs(gaps - med)
    k = int(np.argmax(off))
    tol = max(GAP_TOL * med, GAP_TOL_MM)
    if off[k] > tol:
        bad = gaps[off > tol] / med
        whole = np.abs(bad - np.round(bad)) * med <= tol
        # a few gaps of whole multiples of the others: slices missing; anything else: uneven spacing
        cause = (f"{int(np.round(bad).sum() - len(bad))} slice(s) missing"
                 if whole.all() and (bad > 1.5).all() and len(bad) <= len(gaps) / 4 else "uneven slice spacing")
        raise ReadError(f"{where}: {cause}: the gaps between slices run from {gaps.min():.4g} to {gaps.max():.4g} mm "
                        f"(median {med:.4g} mm); {gaps[k]:.4g} mm between {Path(files[k]).name} at {z[k]:.3f} mm and "
                        f"{Path(files[k + 1]).name} at {z[k + 1]:.3f} mm along the slice normal; lungdeform reads "
                        "evenly spaced slices only (resample the series first)")


def _check_tilt(files: tuple[str, ...], ipp: np.ndarray, normal: np.ndarray, where) -> None:
    """ReadError when the slice positions ``ipp`` (sorted) step away from the slice ``normal``."""
    steps = ipp - ipp[0]
    along = steps @ normal
    across = np.linalg.norm(steps - along[:, None] * normal, axis=1)
    angle = np.degrees(np.arctan2(across[1:], along[1:]))
    k = int(np.argmax(angle)) + 1
    if angle[k - 1] > TILT_TOL_DEG and across[k] > GAP_TOL_MM:
        raise ReadError(f"{where}: the slices are stacked {angle[k - 1]:.3g} degrees off their normal (gantry tilt): "
                        f"{Path(files[k]).name} lies {across[k]:.3g} mm sideways of {Path(files[0]).name}; "
                        "a tilted-gantry series is not a regular grid: resample it to axial slices first")


def check_spacing(spacing_z: float, geometry: SliceGeometry, where) -> None:
    """ReadError when the slice spacing a reader gave (``spacing_z``, mm) is not the series' gap
    (``geometry``; a single slice passes): the voxels would be misplaced along the normal."""
    if len(geometry.files) > 1 and abs(spacing_z - geometry.spacing) > max(GAP_TOL * geometry.spacing, GAP_TOL_MM):
        raise ReadError(f"{where}: read with a slice spacing of {spacing_z:.4g} mm, and its slices lie "
                        f"{geometry.spacing:.4g} mm apart")
