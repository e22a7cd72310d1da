"""A 4-D CT in one DICOM folder: its respiratory phases found, told apart and ordered.

:func:`read_phases` reads a folder holding every phase of a 4-D CT, either as one DICOM series per
phase (the usual export) or as one series whose slices repeat each position once per phase; the
files may lie in the folder itself or in its subfolders. Phases are told apart and ordered by the
first of these that every phase has and no two phases share (docs/FITTING.md, "4-D CT input"):

What exports hold besides the phases (an RTSTRUCT, RTPLAN, RTDOSE, DICOMDIR, localizers, files that are
no DICOM) is left out (:mod:`~lungdeform.io.dicom.folder`), and so is a series that carries no phase
key while the phases do (an average or MIP reconstruction), each named in a line the caller says.

1. a phase percentage in SeriesDescription (0008,103E): ``"CT 30%"``, ``"Gated 40.0%"``,
   ``"T=50%"``, ``"phase 20"``;
2. TemporalPositionIndex (0020,9128);
3. TemporalPositionIdentifier (0020,0100) (GE, Siemens and Philips 4-D CT exports);
4. TriggerTime (0018,1060) (ms after the respiratory trigger);
5. AcquisitionTime (0008,0032), the last resort.

One series holding repeated slice positions is split by the first of 2–5 present in all its slices.
A :class:`~lungdeform.errors.ReadError` names the folder when it holds fewer than two phases, when
no key tells the phases apart, when its slices name more than one patient, study or frame of
reference (:data:`SAME_TAGS`), or when a phase's slices are no regular grid (two at one position,
uneven gaps, a missing slice, a gantry tilt, a bad orientation or position:
:func:`lungdeform.io.dicom.slices.check_slices`) or exceed the grid cap
(:func:`lungdeform.io.grid.voxel_limit`); every phase is checked before any is read.

Frames: each phase is an :class:`~lungdeform.io.grid.Image` (``array`` ``(z, y, x)``, spacing
x y z mm, origin mm LPS, direction columns in LPS), read by SimpleITK from its files in slice order.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
import SimpleITK as sitk

from lungdeform.errors import ReadError
from lungdeform.io.grid import Image, check_grid, quiet_itk

from .attributes import require
from .folder import candidates, ignored_line, survey
from .slices import GEOMETRY_TAGS, SliceGeometry, check_orientations, check_slices, check_spacing

#: The tags that may tell phases apart, in order of preference after the SeriesDescription percentage.
PHASE_TAGS = (("0020|9128", "TemporalPositionIndex"), ("0020|0100", "TemporalPositionIdentifier"),
              ("0018|1060", "TriggerTime"), ("0008|0032", "AcquisitionTime"))
#: The tags that must agree across the whole folder: one patient, one study, one frame of reference.
SAME_TAGS = (("0010|0020", "PatientID"), ("0020|000d", "StudyInstanceUID"), ("0020|0052", "FrameOfReferenceUID"))
#: The UIDs every slice's header is checked for (:func:`~lungdeform.io.dicom.attributes.require`): the
#: series that groups slices into phases required, the study and frame of reference valid when given.
UID_TAGS = (("0020|000e", "SeriesInstanceUID"), ("0020|000d", "StudyInstanceUID"), ("0020|0052", "FrameOfReferenceUID"))
_READ_TAGS = (("0020|000e", "0008|103e", "0008|0018", "0028|0008") + GEOMETRY_TAGS + tuple(t for t, _ in PHASE_TAGS)
              + tuple(t for t, _ in SAME_TAGS))
_PERCENT = re.compile(r"(\d+(?:\.\d+)?)\s*%|\bphase[\s_:=-]*(\d+(?:\.\d+)?)", re.I)


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


def _slice_tags(folder: Path, ignored: list | None) -> list[tuple[str, dict[str, str]]]:
    """``[(file, tags)]`` of the CT image series in ``folder``: each file's tags of :data:`_READ_TAGS`
    (stripped text, ``""`` when absent) and ``"size"`` (x y frames: for the grid cap), read by the survey
    in its one pass over each header (:func:`~lungdeform.io.dicom.folder.survey`; every file's
    element headers checked first, :func:`~lungdeform.io.dicom.guard.check_dicom_file`). The folder's
    RTSTRUCT, RTPLAN, RTDOSE, DICOMDIR, localizers and non-DICOM files are left out
    (:func:`~lungdeform.io.dicom.folder.candidates`), a line naming them added to ``ignored``.
    :class:`ReadError` naming the file when its Rows, Columns or NumberOfFrames are no whole numbers."""
    found = survey(folder, _READ_TAGS)
    pool = candidates(found)
    line = ignored_line(found, pool)
    if ignored is not None and line:
        ignored.append(line)
    infos = []
    for series in pool:
        for f, tags in zip(series.files, series.tags):
            try:
                size = [int(tags[t] or default) for t, default in (("0028|0011", ""), ("0028|0010", ""),
                                                                   ("0028|0008", "1"))]
            except ValueError:
                raise ReadError(f"{folder}: {f} is not a readable DICOM image (Rows {tags['0028|0010']!r}, "
                                f"Columns {tags['0028|0011']!r}, NumberOfFrames {tags['0028|0008']!r}: "
                                "not whole numbers)") from None
            infos.append((f, {**tags, "size": " ".join(str(n) for n in size)}))
    return infos


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
    (it is returned whole when no slice position repeats); its slices must share one orientation
    (:func:`~lungdeform.io.dicom.slices.check_orientations`), or positions along their normals mean nothing."""
    check_orientations(files, f"{folder}: series {files[0][1]['0020|000e'] or '(no SeriesInstanceUID)'}")
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


def _order(folder: Path, groups: list[list[tuple[str, dict]]], aside: list) -> list[tuple[float, str, list]]:
    """``[(key, label, files)]`` of the phases, ordered by the first key of the module docstring that
    every phase has and no two share; failing that, by the key that two or more phases have (no two
    the same) while the other series lack it entirely (an average or MIP series beside the phases):
    those are set aside, a line naming them added to ``aside``. :class:`ReadError` naming the folder
    when no key tells two or more phases apart."""
    kinds = ("percent",) + tuple(t for t, _ in PHASE_TAGS)
    best = None
    for kind in kinds:
        keys = [_group_key(folder, g, kind) for g in groups]
        have = [i for i, k in enumerate(keys) if k is not None]
        if len({keys[i][0] for i in have}) != len(have) or len(have) < 2:
            continue
        if len(have) == len(groups):
            return sorted(((k, label, g) for (k, label), g in zip(keys, groups)), key=lambda x: x[0])
        if all(_lacks(groups[i], kind) for i in range(len(groups)) if keys[i] is None) and (
                best is None or len(have) > len(best[1])):
            best = (keys, have)
    if best is None:
        raise ReadError(f"{folder}: {len(groups)} phases (DICOM series) that cannot be told apart: no phase percentage "
                        f"in SeriesDescription, nor {', '.join(n for _, n in PHASE_TAGS)} that differs between them")
    keys, have = best
    left = [g for i, g in enumerate(groups) if i not in have]
    named = ", ".join(f"{g[0][1]['0020|000e']} {g[0][1]['0008|103e']!r} ({len(g)} slices)" for g in left)
    aside.append(f"{folder}: set aside {len(left)} series that carry no phase ({named}): not a phase of the 4-D CT "
                 "(an average or MIP reconstruction?)")
    return sorted(((keys[i][0], keys[i][1], groups[i]) for i in have), key=lambda x: x[0])


def _lacks(files: list[tuple[str, dict]], kind: str) -> bool:
    """Whether no file of one series gives a value of ``kind`` (a percentage, or the tag)."""
    if kind == "percent":
        return all(_percent(info["0008|103e"]) is None for _, info in files)
    return all(_number(kind, info[kind]) is None for _, info in files)


def _phase_geometry(folder: Path, label: str, files: list[tuple[str, dict]], max_voxels=None) -> SliceGeometry:
    """One phase's slice geometry (its files in slice order); :class:`ReadError` for a grid over the
    cap (:func:`~lungdeform.io.grid.check_grid`) or slices that are no regular grid
    (:func:`~lungdeform.io.dicom.slices.check_slices`: orientation, positions, gaps, gantry tilt)."""
    where = f"{folder}: phase {label}"
    sizes = [[int(n) for n in info["size"].split()] for _, info in files]
    check_grid((max(s[0] for s in sizes), max(s[1] for s in sizes), sum(int(np.prod(s[2:])) for s in sizes)),
               where, max_voxels)
    return check_slices(files, where)


def _read_phase(folder: Path, label: str, geometry: SliceGeometry) -> Image:
    """One phase's image from its checked files (:func:`_phase_geometry`)."""
    where = f"{folder}: phase {label}"
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(list(geometry.files))
    try:
        with quiet_itk():
            img = reader.Execute()
    except RuntimeError as exc:
        detail = next((ln.strip() for ln in str(exc).splitlines() if "rror" in ln), "")
        raise ReadError(f"{where}: cannot read its series ({detail[:200]})") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise ReadError(f"{where}: expected a 3-D scalar image")
    check_spacing(img.GetSpacing()[2], geometry, where)
    return Image(sitk.GetArrayFromImage(img), np.array(img.GetSpacing()), np.array(img.GetOrigin()),
                 np.array(img.GetDirection()).reshape(3, 3), source=f"{folder} [{label}]")


def _check_one_study(folder: Path, infos: list[tuple[str, dict]]) -> None:
    """ReadError naming the folder, the tag and two files when the slices of ``folder`` do not share
    one patient, one study and one frame of reference (:data:`SAME_TAGS`; a tag absent from every
    slice passes, absent from some only does not)."""
    for tag, name in SAME_TAGS:
        first: dict[str, str] = {}
        for f, info in infos:
            first.setdefault(info[tag], f)
            if len(first) > 1:
                (a, fa), (b, fb) = first.items()
                raise ReadError(f"{folder}: holds more than one {name}: {a or '(none)'!r} in {fa} and "
                                f"{b or '(none)'!r} in {fb}; a 4-D CT folder holds one patient, one study and one "
                                "frame of reference")


def read_phases(folder, *, max_voxels=None, ignored: list | None = None) -> list[Phase]:
    """Every phase of the 4-D CT in ``folder`` (module docstring), in phase order.

    The folder may hold what exports hold besides the phases (an RTSTRUCT, an RTPLAN, an RTDOSE, a
    DICOMDIR, localizers, files that are no DICOM; an average or MIP series without a phase): they are
    left out, and ``ignored``, when given, gets the lines naming them. Raises :class:`ReadError`
    naming the folder when it is missing, holds no DICOM image, slices of more than one patient,
    study or frame of reference, fewer than two phases, phases that cannot be told apart, a phase that
    repeats another (one SOP instance in two phases, or identical pixel data: a phase exported twice),
    a phase whose slices are no regular grid (:func:`~lungdeform.io.dicom.slices.check_slices`) or a
    phase over the grid cap (``max_voxels``, :func:`~lungdeform.io.grid.voxel_limit`).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ReadError(f"{folder}: not a folder (a 4-D CT is one DICOM folder holding all phases)")
    lines: list[str] = []
    infos = _slice_tags(folder, lines)  # every header read once, by the survey; GDCM reads the pixels only
    for f, info in infos:
        require({name: info[tag] for tag, name in UID_TAGS}, ("SeriesInstanceUID",), f,
                "which tells the phases of a 4-D CT apart", optional=("StudyInstanceUID", "FrameOfReferenceUID"))
    if not infos:
        raise ReadError(f"{folder}: no DICOM CT images in this folder or its subfolders"
                        + (f" ({lines[0].split(': ', 1)[-1]})" if lines else ""))
    _check_one_study(folder, infos)
    series: dict[str, list] = {}
    for f, info in infos:
        series.setdefault(info["0020|000e"], []).append((f, info))
    groups = [g for s in series.values() for g in _split_series(folder, s)]
    if len(groups) < 2:
        raise ReadError(f"{folder}: holds one phase only ({len(infos)} slices of one series); a 4-D CT needs two or more")
    order = _order(folder, groups, lines)
    _check_shared_instances(folder, order)
    ordered = [(key, label, _phase_geometry(folder, label, files, max_voxels))
               for key, label, files in order]  # every phase checked before any is read
    phases = [Phase(label, float(key), geometry.files, _read_phase(folder, label, geometry))
              for key, label, geometry in ordered]
    _check_repeated_pixels(folder, phases)
    if ignored is not None:
        ignored += lines
    return phases


def _check_shared_instances(folder: Path, order: list[tuple[float, str, list]]) -> None:
    """ReadError naming both phases and the files when one SOP Instance UID is in two phases: one
    image instance exported into two phases (a phase exported twice)."""
    seen: dict[str, tuple[str, str]] = {}
    for _key, label, files in order:
        for f, info in files:
            uid = info.get("0008|0018", "")
            if uid and uid in seen and seen[uid][0] != label:
                raise ReadError(f"{folder}: phase {label} repeats phase {seen[uid][0]}: {f} and {seen[uid][1]} are one "
                                f"SOP instance ({uid}); a phase exported twice? A 4-D CT's phases are different images")
            seen.setdefault(uid, (label, f)) if uid else None


def _check_repeated_pixels(folder: Path, phases: list[Phase]) -> None:
    """ReadError naming both phases when two phases hold identical pixel data (the same voxels on the
    same grid, in HU): a phase exported twice, which a fit would take for a breathing state. Phases
    that only look alike (any voxel differs) pass."""
    seen: dict[bytes, Phase] = {}
    for ph in phases:
        a = np.ascontiguousarray(ph.image.array)
        key = hashlib.sha256(repr((a.shape, a.dtype.str, ph.image.origin.tolist(), ph.image.spacing.tolist())).encode()
                             + a.tobytes()).digest()
        if key in seen and np.array_equal(seen[key].image.array, a):
            other = seen[key]
            raise ReadError(f"{folder}: phase {ph.label} repeats phase {other.label}: identical pixel data "
                            f"({len(ph.files)} slices from {ph.files[0]}, {len(other.files)} from {other.files[0]}); a phase "
                            "exported twice? A 4-D CT's phases are different breathing states")
        seen.setdefault(key, ph)


def is_fourdct(path) -> bool:
    """True when ``path`` is a folder holding two or more CT image series (RTSTRUCT, RTDOSE, localizers
    and the like do not count, :func:`~lungdeform.io.dicom.folder.candidates`), or one series that
    repeats slice positions: what :func:`read_phases` reads (cheap: the headers only)."""
    p = Path(path)
    if not p.is_dir():
        return False
    pool = candidates(survey(p, ("0020|0032", "0020|0037")))
    if len(pool) >= 2:
        return True
    positions = [_position(info) for info in (pool[0].tags if pool else ())]
    return len(set(positions)) < len(positions)


def frame_of_reference(files_per_phase) -> str | None:
    """The FrameOfReferenceUID every phase shares (read from each phase's first DICOM file,
    ``files_per_phase``: a sequence of file lists), or None when a phase has none or two differ."""
    uids = set()
    for files in files_per_phase:
        try:
            ds = pydicom.dcmread(files[0], stop_before_pixels=True, specific_tags=["FrameOfReferenceUID"])
        except (OSError, pydicom.errors.InvalidDicomError) as exc:
            raise ReadError(f"{files[0]}: cannot read its FrameOfReferenceUID ({exc})") from exc
        require(ds, (), files[0], "which a 4-D CT's phases share", optional=("FrameOfReferenceUID",))
        uids.add(str(ds.get("FrameOfReferenceUID", "") or "").strip())
    return uids.pop() if len(uids) == 1 and "" not in uids else None
