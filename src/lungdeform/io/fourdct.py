"""A 4-D CT in one DICOM folder: its respiratory phases found, told apart and ordered.

:func:`read_phases` reads a folder holding every phase of a 4-D CT, either as one DICOM series per
phase (the usual export) or as one series whose slices repeat each position once per phase; the
files may lie in the folder itself or in its subfolders. Phases are told apart and ordered by the
first of these that every phase has and no two phases share (docs/FITTING.md, "4-D CT input"):

1. a phase percentage in SeriesDescription (0008,103E): ``"CT 30%"``, ``"Gated 40.0%"``,
   ``"T=50%"``, ``"phase 20"``;
2. TemporalPositionIndex (0020,9128);
3. TemporalPositionIdentifier (0020,0100) (GE, Siemens and Philips 4-D CT exports);
4. TriggerTime (0018,1060) (ms after the respiratory trigger);
5. AcquisitionTime (0008,0032), the last resort.

One series holding repeated slice positions is split by the first of 2–5 present in all its slices.
A :class:`~lungdeform.errors.ReadError` names the folder when it holds fewer than two phases, when
no key tells the phases apart, or when a phase holds two slices at one position.

Frames: each phase is an :class:`~lungdeform.io.image.Image` (``array`` ``(z, y, x)``, spacing
x y z mm, origin mm LPS, direction columns in LPS), read by SimpleITK from its files in slice order.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from lungdeform.errors import ReadError

from .image import Image, _quiet_itk, check_dicom_file, is_dicom_file

#: The tags that may tell phases apart, in order of preference after the SeriesDescription percentage.
PHASE_TAGS = (("0020|9128", "TemporalPositionIndex"), ("0020|0100", "TemporalPositionIdentifier"),
              ("0018|1060", "TriggerTime"), ("0008|0032", "AcquisitionTime"))
_READ_TAGS = ("0020|000e", "0008|103e", "0020|0032", "0020|0037") + tuple(t for t, _ in PHASE_TAGS)
_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%|\bphase[\s_:=-]*(\d+(?:\.\d+)?)", re.I)
#: Files looked at at most (a 4-D CT of 10 phases × 200 slices is 2000): do not crawl a disk.
MAX_FILES = 20000


@dataclass(frozen=True, eq=False)
class Phase:
    """One respiratory phase of a 4-D CT.

    Attributes
    ----------
    label : str
        How it was told apart, e.g. ``"30%"`` or ``"TemporalPositionIndex 4"``.
    key : float
        Its place in the phase order (a percentage, an index or a time in s).
    files : tuple of str
        Its DICOM files, in slice order.
    image : Image
        The phase's CT (HU), ``source`` = ``"<folder> [<label>]"``.
    """

    label: str
    key: float
    files: tuple[str, ...]
    image: Image


def _slice_info(path: str) -> dict[str, str] | None:
    """The tags of :data:`_READ_TAGS` of one DICOM file (stripped strings), or None if it is not a DICOM image;
    :class:`ReadError` for a damaged one (:func:`~lungdeform.io.image.check_dicom_file`)."""
    check_dicom_file(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(path)
    reader.SetImageIO("GDCMImageIO")
    try:
        with _quiet_itk():
            reader.ReadImageInformation()
    except RuntimeError:
        return None
    return {t: reader.GetMetaData(t).strip() if reader.HasMetaDataKey(t) else "" for t in _READ_TAGS}


def _dicom_files(folder: Path) -> list[str]:
    """DICOM files in ``folder`` and its subfolders (sorted, at most :data:`MAX_FILES`)."""
    found = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            p = Path(root) / name
            if name.upper() != "DICOMDIR" and is_dicom_file(p):
                found.append(str(p))
        if len(found) > MAX_FILES:
            raise ReadError(f"{folder}: more than {MAX_FILES} DICOM files; give the folder of one 4-D CT")
    return found


def _number(tag: str, value: str) -> float | None:
    """A tag's value as a number (AcquisitionTime HHMMSS.frac as seconds), None if missing or not a number."""
    try:
        if tag == "0008|0032":
            if not re.fullmatch(r"\d{2,6}(\.\d+)?", value):
                return None
            digits, _, frac = value.partition(".")
            digits = digits.ljust(6, "0")
            return int(digits[:2]) * 3600 + int(digits[2:4]) * 60 + int(digits[4:6]) + float("0." + (frac or "0"))
        number = float(value)
    except ValueError:
        return None
    return number if np.isfinite(number) else None


def _percent(description: str) -> float | None:
    """The phase percentage a SeriesDescription names (``"CT 30%"``, ``"T=50%"``, ``"phase 20"``), or None."""
    m = _PERCENT.search(description)
    return None if m is None else float(m.group(1) or m.group(2))


def _position(info: dict[str, str]) -> float | None:
    """A slice's position (mm) along its normal (ImagePositionPatient · (row × column)), None if unreadable."""
    try:
        ipp = np.array([float(v) for v in info["0020|0032"].split("\\")])
        iop = np.array([float(v) for v in info["0020|0037"].split("\\")])
    except ValueError:
        return None
    if ipp.shape != (3,) or iop.shape != (6,) or not (np.isfinite(ipp).all() and np.isfinite(iop).all()):
        return None
    return float(ipp @ np.cross(iop[:3], iop[3:]))


def _group_key(folder: Path, files: list[tuple[str, dict]], kind: str) -> tuple[float, str] | None:
    """``(key, label)`` of one phase's files by ``kind`` (``"percent"`` or a tag), None when its files
    lack it or disagree on it."""
    if kind == "percent":
        values = {_percent(info["0008|103e"]) for _, info in files}
    else:
        values = {_number(kind, info[kind]) for _, info in files}
    if len(values) != 1 or None in values:
        return None
    value = values.pop()
    name = dict(PHASE_TAGS).get(kind)
    return value, f"{value:g}%" if kind == "percent" else f"{name} {files[0][1][kind]}"


def _split_series(folder: Path, files: list[tuple[str, dict]]) -> list[list[tuple[str, dict]]]:
    """One series split into phases by the first tag of :data:`PHASE_TAGS` present in all its slices
    (it is returned whole when no slice position repeats)."""
    positions = [_position(info) for _, info in files]
    if len(set(positions)) == len(positions):
        return [files]
    for tag, _name in PHASE_TAGS:
        values = [_number(tag, info[tag]) for _, info in files]
        if None not in values:
            groups: dict[float, list] = {}
            for f, v in zip(files, values):
                groups.setdefault(v, []).append(f)
            return list(groups.values())
    raise ReadError(f"{folder}: one DICOM series repeats slice positions but has no "
                    f"{', '.join(n for _, n in PHASE_TAGS)} in every slice; the phases cannot be told apart")


def _order(folder: Path, groups: list[list[tuple[str, dict]]]) -> list[tuple[float, str, list]]:
    """``[(key, label, files)]`` of the phases, ordered by the first key of the module docstring that
    every phase has and no two share; :class:`ReadError` naming the folder when none does."""
    for kind in ("percent",) + tuple(t for t, _ in PHASE_TAGS):
        keys = [_group_key(folder, g, kind) for g in groups]
        if None not in keys and len({k for k, _ in keys}) == len(keys):
            return sorted(((k, label, g) for (k, label), g in zip(keys, groups)), key=lambda x: x[0])
    raise ReadError(f"{folder}: {len(groups)} phases (DICOM series) that cannot be told apart: no phase percentage "
                    f"in SeriesDescription, nor {', '.join(n for _, n in PHASE_TAGS)} that differs between them")


def _read_phase(folder: Path, label: str, files: list[tuple[str, dict]]) -> tuple[tuple[str, ...], Image]:
    """One phase's files in slice order and its image; :class:`ReadError` for repeated or unreadable positions."""
    positions = [_position(info) for _, info in files]
    if None in positions:
        bad = files[positions.index(None)][0]
        raise ReadError(f"{folder}: phase {label}: {bad} has no readable ImagePositionPatient/ImageOrientationPatient")
    if len(set(positions)) != len(positions):
        raise ReadError(f"{folder}: phase {label} holds two slices at one position; the phases cannot be told apart")
    names = tuple(f for _, f in sorted(zip(positions, (f for f, _ in files))))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(list(names))
    try:
        with _quiet_itk():
            img = reader.Execute()
    except RuntimeError as exc:
        detail = next((ln.strip() for ln in str(exc).splitlines() if "rror" in ln), "")
        raise ReadError(f"{folder}: phase {label}: cannot read its series ({detail[:200]})") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise ReadError(f"{folder}: phase {label}: expected a 3-D scalar image")
    image = Image(sitk.GetArrayFromImage(img), np.array(img.GetSpacing()), np.array(img.GetOrigin()),
                  np.array(img.GetDirection()).reshape(3, 3), source=f"{folder} [{label}]")
    return names, image


def read_phases(folder) -> list[Phase]:
    """Every phase of the 4-D CT in ``folder`` (module docstring), in phase order.

    Raises :class:`ReadError` naming the folder when it is missing, holds no DICOM image, fewer than
    two phases, or phases that cannot be told apart.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ReadError(f"{folder}: not a folder (a 4-D CT is one DICOM folder holding all phases)")
    infos = [(f, _slice_info(f)) for f in _dicom_files(folder)]
    bad = next((f for f, info in infos if info is None), None)
    if bad is not None:
        raise ReadError(f"{folder}: {bad} is not a readable DICOM image")
    if not infos:
        raise ReadError(f"{folder}: no DICOM files in this folder or its subfolders")
    series: dict[str, list] = {}
    for f, info in infos:
        series.setdefault(info["0020|000e"], []).append((f, info))
    groups = [g for s in series.values() for g in _split_series(folder, s)]
    if len(groups) < 2:
        raise ReadError(f"{folder}: holds one phase only ({len(infos)} slices of one series); a 4-D CT needs two or more")
    phases = []
    for key, label, files in _order(folder, groups):
        names, image = _read_phase(folder, label, files)
        phases.append(Phase(label, float(key), names, image))
    return phases


def is_fourdct(path) -> bool:
    """True when ``path`` is a folder holding two or more DICOM series, or one series that repeats
    slice positions: what :func:`read_phases` reads (cheap: the series of the folder's files only)."""
    p = Path(path)
    if not p.is_dir():
        return False
    files = _dicom_files(p)
    series: dict[str, list] = {}
    for f in files:
        info = _slice_info(f)
        if info is not None:
            series.setdefault(info["0020|000e"], []).append(_position(info))
    return len(series) >= 2 or any(len(set(v)) < len(v) for v in series.values())
