"""Two-volume subjects on disk: which files make one subject (``learn-default``, ``validate single-scan``,
the cohort manifest of ``validate copd --manifest-only``).

A folder of two-volume subjects is one of:

- **any folder of mask pairs**: ``NAME_exp_mask.EXT`` and ``NAME_insp_mask.EXT`` (EXT one of
  :data:`lungdeform.io.image.IMAGE_SUFFIXES`: NIfTI, MetaImage, NRRD), the smaller-volume
  (expiration) and the larger-volume (inspiration) scan of subject NAME; a mask may hold both lungs
  in one label (split, :mod:`lungdeform.segment.split`) or one lung. Landmarks are optional:
  ``NAME_exp_landmarks.txt`` and ``NAME_insp_landmarks.txt`` (elastix point files, row i ↔ row i),
  both or neither. The DIR-Lab COPDgene masks (``copdN_…``) are such a folder;
- **the ITK right lung pair** (:func:`lungdeform.validate.itk_pair.find_pair`): one subject, ``itk``.

A NAME with one of its two masks, or one of its two landmark files, is incomplete: :func:`find_subjects`
leaves it out and :func:`incomplete_subjects` names what it lacks (the caller says so, one line each).
"""

from __future__ import annotations

import csv
import hashlib
import io
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from lungdeform.atomic import write_text
from lungdeform.errors import ReadError
from lungdeform.io.image import IMAGE_SUFFIXES

from . import itk_pair

PHASES = ("exp", "insp")
_MASK = re.compile(r"(?P<name>.+)_(?P<phase>exp|insp)_mask(?P<ext>" +
                   "|".join(re.escape(s) for s in sorted(IMAGE_SUFFIXES, key=len, reverse=True)) + r")",
                   re.IGNORECASE)


@dataclass(frozen=True)
class Subject:
    """One subject's files.

    Attributes
    ----------
    name : str
    sides : tuple of str or None
        The lungs to take (``("right",)`` for the ITK pair); None: every lung the masks hold (both of a
        both-lung mask, or the one lung of a one-lung mask, its side from its shape).
    scans : (Path, Path)
        The smaller-volume (expiration) and the larger-volume (inspiration) scan.
    landmarks : (Path, Path) or None
        One elastix point file per scan (rows corresponding), or None: scored on the surface only.
    """

    name: str
    sides: tuple[str, ...] | None
    scans: tuple[Path, Path]
    landmarks: tuple[Path, Path] | None = None

    @cached_property
    def digest(self) -> str:
        """SHA-256 (16 hex digits) of the smaller-volume scan's bytes: who the subject is."""
        return hashlib.sha256(Path(self.scans[0]).read_bytes()).hexdigest()[:16]


def _mask_files(data: Path) -> dict[str, dict[str, Path]]:
    """``{NAME: {"exp": path, "insp": path}}`` of the mask files in ``data`` (either phase may be missing)."""
    out: dict[str, dict[str, Path]] = {}
    for p in sorted(data.iterdir()):
        m = _MASK.fullmatch(p.name)
        if m and p.is_file():
            phases = out.setdefault(m.group("name"), {})
            if m.group("phase").lower() in phases:
                raise ReadError(f"{data}: two {m.group('phase')} masks of {m.group('name')!r} "
                                f"({phases[m.group('phase').lower()].name}, {p.name})")
            phases[m.group("phase").lower()] = p
    return out


def _landmark_files(data: Path, name: str) -> list[Path | None]:
    return [(data / f"{name}_{ph}_landmarks.txt") if (data / f"{name}_{ph}_landmarks.txt").is_file() else None
            for ph in PHASES]


def incomplete_subjects(data: Path) -> dict[str, list[str]]:
    """``{NAME: [what it lacks]}`` for every NAME in ``data`` with one mask of the two, or one landmark
    file of the two (:func:`find_subjects` leaves the first out and scores the second without landmarks)."""
    data = Path(data)
    if not data.is_dir():
        return {}
    out = {}
    for name, phases in _mask_files(data).items():
        lacks = [f"its {ph} mask ({name}_{ph}_mask.*)" for ph in PHASES if ph not in phases]
        lms = _landmark_files(data, name)
        if sum(p is not None for p in lms) == 1:
            lacks += [f"{name}_{ph}_landmarks.txt (its landmarks are not used)" for ph, p in zip(PHASES, lms) if p is None]
        if lacks:
            out[name] = lacks
    return out


def find_subjects(data: Path) -> list[Subject]:
    """The two-volume subjects in ``data`` (module docstring), by name; :class:`ReadError` naming the
    folder when it holds none."""
    data = Path(data)
    if not data.is_dir():
        raise ReadError(f"{data}: not a folder")
    try:
        files = itk_pair.find_pair(data)
        return [Subject("itk", ("right",), (files[0], files[1]), (files[2], files[3]))]
    except ReadError:
        pass
    out = []
    for name, phases in _mask_files(data).items():
        if set(phases) != set(PHASES):
            continue
        lms = _landmark_files(data, name)
        landmarks = (lms[0], lms[1]) if all(p is not None for p in lms) else None
        out.append(Subject(name, None, (phases["exp"], phases["insp"]), landmarks))
    if not out:
        raise ReadError(f"{data}: no two-volume subject (NAME_exp_mask and NAME_insp_mask images, e.g. .nii.gz, "
                        ".mha, .nrrd, with optional NAME_exp_landmarks.txt and NAME_insp_landmarks.txt; or the ITK "
                        "right lung pair)")
    return out


def cohort_manifest(subjects: list[Subject]) -> str:
    """The text of a cohort manifest (:mod:`lungdeform.cohort.manifest`) of ``subjects``: per subject two
    rows, the smaller-volume scan then the larger, side ``both`` (each mask split into its lungs) or the
    subject's one side, ``volume_ml`` empty (measured; row order = end-exhale first), the scan's landmarks
    (empty without them); absolute paths, so the manifest may be written anywhere."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")  # quotes a path holding a comma, as the manifest reader expects
    w.writerow(["subject", "side", "volume_ml", "path", "landmarks"])
    for s in subjects:
        for side in s.sides or ("both",):
            for k, scan in enumerate(s.scans):
                lm = "" if s.landmarks is None else str(Path(s.landmarks[k]).resolve())
                w.writerow([s.name, side, "", str(Path(scan).resolve()), lm])
    return buf.getvalue()


def write_cohort_manifest(subjects: list[Subject], path: Path) -> Path:
    """Write (atomically) :func:`cohort_manifest` of ``subjects`` to ``path``; return it."""
    return write_text(Path(path), cohort_manifest(subjects))
