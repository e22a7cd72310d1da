"""The cohort manifest: a CSV file listing every scan of every subject, read and checked in full
before any work starts.

Format (UTF-8, comma-separated, header row required; column order free)::

    subject,side,volume_ml,path[,landmarks]
    P01,right,2310,P01/ee_right.ply,P01/ee.pts
    P01,right,2905,P01/ei_right.ply,P01/ei.pts
    P02,both,,P02/ct_exhale.nii.gz
    P02,both,,P02/ct_inhale.nii.gz

- one row per scan; ``subject`` names the output folder (letters, digits, ``.``, ``_``, ``-``);
- ``side`` is ``left``, ``right`` or ``both`` (a CT, or a mask holding both lungs in one label: it
  gives a left and a right job; such a mask is split, :mod:`lungdeform.segment.split`, also on
  ``left``/``right`` rows). A subject uses ``both`` on all its rows or ``left``/``right`` on all its rows;
- ``volume_ml`` is the lung volume in mL, or empty to measure it from the data. Within one job
  volumes are all given or all empty;
- ``path`` (a surface, a mask or a CT; a DICOM series folder) and ``landmarks`` (an elastix point
  file, optional) are relative to the manifest's folder (absolute paths are kept).

Rows are numbered as a spreadsheet shows them: the header is row 1.

A job may also be one row naming a folder that holds a 4-D CT (every phase, :mod:`lungdeform.io.dicom.fourdct`;
``volume_ml`` and ``landmarks`` empty): its phases are the scans, measured and ordered by the fit.

One job is one (subject, side) with two or more scans, end-exhale first: ordered by volume, or,
when the volumes are empty, in row order (said in :attr:`Manifest.notes`; the fit then refuses the
job if the measured volumes do not increase).

Every problem found (missing files, wrong columns, duplicated rows or volumes, bad values,
subjects with fewer than two scans, ...) is collected, and :func:`read_manifest` raises one
:class:`~lungdeform.errors.InputError` naming the manifest and each row at fault.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from lungdeform.errors import InputError
from lungdeform.io.image import IMAGE_SUFFIXES
from lungdeform.io.meshfile import MESH_SUFFIXES

REQUIRED_COLUMNS = ("subject", "side", "volume_ml", "path")
OPTIONAL_COLUMNS = ("landmarks",)
MANIFEST_SIDES = ("left", "right", "both")
SUBJECT_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


@dataclass(frozen=True)
class Scan:
    """One manifest row as used by one job.

    row : int
        Spreadsheet row number in the manifest (header = 1).
    path, landmarks : Path
        Absolute paths (``landmarks`` None when not given).
    volume_ml : float or None
        Lung volume (mL); None = measured from the data.
    """

    row: int
    path: Path
    volume_ml: float | None
    landmarks: Path | None


@dataclass(frozen=True)
class Job:
    """One lung of one subject: two or more scans, end-exhale first."""

    subject: str
    side: str  # "left" | "right"
    scans: tuple[Scan, ...]
    ordered_by: str  # "volume" | "row"

    @property
    def key(self) -> str:
        return f"{self.subject}/{self.side}"

    @property
    def inputs(self) -> list[Path]:
        return [s.path for s in self.scans]

    @property
    def volumes_ml(self) -> list[float] | None:
        """The manifest's volumes (mL), or None when they are to be measured."""
        if self.ordered_by == "row":
            return None
        return [float(s.volume_ml) for s in self.scans]

    @property
    def landmarks(self) -> list[Path] | None:
        if self.scans[0].landmarks is None:
            return None
        return [s.landmarks for s in self.scans]

    @property
    def rows(self) -> list[int]:
        return [s.row for s in self.scans]


@dataclass(frozen=True)
class Problem:
    """One thing wrong with the manifest: the rows at fault (empty: the whole file) and what."""

    rows: tuple[int, ...]
    message: str

    def __str__(self) -> str:
        if not self.rows:
            return self.message
        label = "row" if len(self.rows) == 1 else "rows"
        return f"{label} {', '.join(str(r) for r in self.rows)}: {self.message}"


@dataclass(frozen=True)
class Manifest:
    """A checked manifest: its path, its jobs (manifest order) and notes for the user."""

    path: Path
    jobs: tuple[Job, ...]
    notes: tuple[str, ...]

    @property
    def folder(self) -> Path:
        return self.path.parent


@dataclass(frozen=True)
class _Row:
    row: int
    subject: str
    side: str
    volume_ml: float | None
    path: Path
    landmarks: Path | None


def read_manifest(path) -> Manifest:
    """Read and check the manifest at ``path``; raise one :class:`InputError` listing every problem."""
    manifest, problems = check_manifest(path)
    if problems:
        n = len(problems)
        raise InputError(f"{Path(path)}: {n} problem{'s' if n > 1 else ''} in the cohort manifest: "
                         + "; ".join(str(p) for p in problems))
    return manifest


def check_manifest(path) -> tuple[Manifest | None, list[Problem]]:
    """``(manifest, problems)``; the manifest is None when there are problems. Nothing is read but
    the manifest itself and the existence of the files it names."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None, [Problem((), "no such file")]
    except IsADirectoryError:
        return None, [Problem((), "is a folder, not a CSV file")]
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        return None, [Problem((), f"not UTF-8 text (byte {exc.start})")]
    rows, tainted, problems = _parse(text, path.resolve().parent)
    jobs, notes, group_problems = _group(rows, tainted)
    problems += group_problems
    if not problems:
        return Manifest(path.resolve(), tuple(jobs), tuple(notes)), []
    return None, sorted(problems, key=lambda p: (p.rows[:1] or (0,), p.message))


def _parse(text: str, folder: Path) -> tuple[list[_Row], set[str], list[Problem]]:
    """Rows usable for grouping, the subjects with unusable rows, and the problems found."""

    problems: list[Problem] = []
    reader = csv.reader(io.StringIO(text))
    header, columns = None, {}
    rows: list[_Row] = []
    tainted: set[str] = set()
    try:
        records = [(reader.line_num, rec) for rec in reader]
    except csv.Error as exc:
        return [], set(), [Problem((reader.line_num,), f"not valid CSV ({exc})")]
    for line, rec in records:
        if not any(cell.strip() for cell in rec):
            continue  # blank line
        if header is None:
            header = [c.strip().lower() for c in rec]
            bad = _header_problem(header, line)
            if bad is not None:
                return [], set(), [bad]
            columns = {c: header.index(c) for c in header}
            continue
        if len(rec) != len(header):
            problems.append(Problem((line,), f"{len(rec)} fields, the header has {len(header)}"))
            tainted.add(rec[columns["subject"]].strip() if len(rec) > columns["subject"] else "")
            continue
        cell = {c: rec[i].strip() for c, i in columns.items()}
        row, row_problems = _parse_row(line, cell, folder)
        problems += row_problems
        if row is not None:
            rows.append(row)
        else:
            tainted.add(cell["subject"])
    if header is None:
        problems.append(Problem((), "empty: no header row (expected " + ",".join(REQUIRED_COLUMNS) + "[,landmarks])"))
    elif not rows and not problems:
        problems.append(Problem((), "no scans listed (only a header)"))
    return rows, tainted, problems


def _header_problem(header: list[str], line: int) -> Problem | None:
    """What is wrong with the (lower-cased) ``header`` at ``line``: missing, unknown or repeated
    columns; None when it is usable."""
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    dup = sorted({c for c in header if header.count(c) > 1})
    if not (missing or unknown or dup):
        return None
    what = []
    if missing:
        what.append(f"missing column(s) {', '.join(missing)}")
    if unknown:
        what.append(f"unknown column(s) {', '.join(repr(c) for c in unknown)}")
    if dup:
        what.append(f"repeated column(s) {', '.join(dup)}")
    expected = ",".join(REQUIRED_COLUMNS) + "[,landmarks]"
    return Problem((line,), f"header {','.join(header)!r}: {'; '.join(what)} (expected {expected})")


def _parse_row(line: int, cell: dict[str, str], folder: Path) -> tuple[_Row | None, list[Problem]]:
    """One data row (``cell``: column → stripped text) at ``line``: ``(row, problems)``; ``row`` is
    None when a value is bad (its subject is then not judged further). A missing file is a
    problem but keeps the row: it does not stop the grouping checks."""
    problems: list[Problem] = []
    subject, side = cell["subject"], cell["side"].lower()
    ok = True
    if not SUBJECT_PATTERN.match(subject):
        problems.append(Problem((line,), f"subject {subject!r} is not a usable folder name "
                                         "(letters, digits, '.', '_', '-'; starting with a letter or digit)"))
        ok = False
    if side not in MANIFEST_SIDES:
        problems.append(Problem((line,), f"side {cell['side']!r} is not left, right or both"))
        ok = False
    volume, volume_problem = _parse_volume(cell["volume_ml"])
    if volume_problem:
        problems.append(Problem((line,), volume_problem))
        ok = False
    scan = None
    if not cell["path"]:
        problems.append(Problem((line,), "path is empty"))
        ok = False
    else:
        try:  # a NUL byte, an over-long name or an unknown ~user makes the file system calls raise
            scan = _resolve(folder, cell["path"])
            path_problem = _scan_problem(scan, cell["path"], side)
        except (ValueError, OSError, RuntimeError) as exc:  # RuntimeError: "~nosuchuser"
            scan, path_problem, ok = None, f"path {cell['path']!r}: not a usable file name ({exc})", False
        if path_problem:
            problems.append(Problem((line,), path_problem))
    landmarks = None
    if cell.get("landmarks"):
        try:
            landmarks = _resolve(folder, cell["landmarks"])
            landmarks_problem = None if landmarks.is_file() else \
                f"landmarks {cell['landmarks']}: no such file ({landmarks})"
        except (ValueError, OSError, RuntimeError) as exc:  # RuntimeError: "~nosuchuser"
            landmarks_problem, ok = f"landmarks {cell['landmarks']!r}: not a usable file name ({exc})", False
        if landmarks_problem:
            problems.append(Problem((line,), landmarks_problem))
    return (_Row(line, subject, side, volume, scan, landmarks) if ok else None), problems


def _parse_volume(text: str) -> tuple[float | None, str | None]:
    """``(volume mL or None when empty, problem or None)`` of a ``volume_ml`` cell."""
    if not text:
        return None, None
    try:
        volume = float(text)
    except ValueError:
        return None, f"volume_ml {text!r} is not a number (mL, or empty)"
    if not (math.isfinite(volume) and volume > 0):
        return volume, f"volume_ml {text!r} must be a positive number of mL"
    return volume, None


def _scan_problem(scan: Path, text: str, side: str) -> str | None:
    """What is wrong with the scan ``scan`` (resolved from the ``path`` cell ``text``) for ``side``:
    missing, not a surface, image or DICOM folder, or a one-lung surface for side 'both'."""
    name = scan.name.lower()
    if not scan.exists():
        return f"path {text}: no such file ({scan})"
    if not (scan.is_dir() or name.endswith(MESH_SUFFIXES + IMAGE_SUFFIXES)):
        return (f"path {text}: not a surface ({', '.join(MESH_SUFFIXES)}), "
                f"an image ({', '.join(IMAGE_SUFFIXES)}) or a DICOM folder")
    if side == "both" and name.endswith(MESH_SUFFIXES):
        return f"path {text}: a surface holds one lung; side 'both' needs a CT (both lungs are segmented from it)"
    return None


def _resolve(folder: Path, text: str) -> Path:
    p = Path(text).expanduser()
    return (p if p.is_absolute() else folder / p).resolve()


def _group(rows: list[_Row], tainted: set[str]) -> tuple[list[Job], list[str], list[Problem]]:
    """Jobs from the rows; checks per subject and per job. Subjects in ``tainted`` (rows with bad
    values, already reported) are not judged on scan counts, volumes or landmarks."""
    problems: list[Problem] = []
    seen: dict[tuple, int] = {}
    for r in rows:
        key = (r.subject, r.side, r.path)
        if key in seen:
            problems.append(Problem((seen[key], r.row), f"subject {r.subject} side {r.side}: {r.path.name} "
                                                        "listed twice"))
        else:
            seen[key] = r.row
    spellings = defaultdict(set)
    for r in rows:
        spellings[r.subject.lower()].add(r.subject)
    for names in spellings.values():
        if len(names) > 1:
            tainted = tainted | names  # judged again once spelt one way
            clash = sorted(names)
            problems.append(Problem(tuple(sorted(r.row for r in rows if r.subject in names)),
                                    f"subjects {', '.join(clash)} differ only in letter case (one folder on "
                                    "case-insensitive disks); use one spelling"))
    by_subject: dict[str, list[_Row]] = defaultdict(list)
    for r in rows:
        by_subject[r.subject].append(r)
    jobs_rows: dict[tuple[str, str], list[_Row]] = {}
    for subject, rs in by_subject.items():
        sides = {r.side for r in rs}
        if "both" in sides and len(sides) > 1:
            both = [r.row for r in rs if r.side == "both"]
            other = [r.row for r in rs if r.side != "both"]
            problems.append(Problem(tuple(sorted(both + other)),
                                    f"subject {subject} mixes side 'both' (rows {_rows(both)}) with left/right "
                                    f"(rows {_rows(other)}); use 'both' on every row of a subject or left/right "
                                    "on every row"))
            continue
        for r in rs:
            for side in (("left", "right") if r.side == "both" else (r.side,)):
                jobs_rows.setdefault((subject, side), []).append(r)
    jobs, notes = [], []
    for (subject, side), rs in jobs_rows.items():
        if subject in tainted:
            continue
        rows_ = tuple(r.row for r in rs)
        label = f"subject {subject} {side}"
        few = _count_problem(label, rs)
        if few:
            problems.append(Problem(rows_, few))
            continue
        given = [r for r in rs if r.volume_ml is not None]
        if given and len(given) != len(rs):
            problems.append(Problem(rows_, f"{label}: volume_ml given on rows {_rows([r.row for r in given])} but "
                                           f"empty on rows {_rows([r.row for r in rs if r.volume_ml is None])}; "
                                           "give all or none"))
            continue
        with_lm = [r.row for r in rs if r.landmarks is not None]
        if with_lm and len(with_lm) != len(rs):
            problems.append(Problem(rows_, f"{label}: landmarks given on rows {_rows(with_lm)} but not on rows "
                                           f"{_rows([r.row for r in rs if r.landmarks is None])}; give all or none"))
            continue
        if given:
            vols = [r.volume_ml for r in rs]
            dup = sorted({v for v in vols if vols.count(v) > 1})
            if dup:
                problems.append(Problem(tuple(r.row for r in rs if r.volume_ml in dup),
                                        f"{label}: volume {', '.join(f'{v:g}' for v in dup)} mL listed twice; "
                                        "volumes must differ (end-exhale first, then larger)"))
                continue
            rs = sorted(rs, key=lambda r: r.volume_ml)
            ordered = "volume"
        else:
            ordered = "row"
        jobs.append(Job(subject, side, tuple(Scan(r.row, r.path, r.volume_ml, r.landmarks) for r in rs), ordered))
    by_row = [f"{j.subject} {j.side}" for j in jobs if j.ordered_by == "row"]
    if by_row:
        names = ", ".join(by_row[:5]) + (f" and {len(by_row) - 5} more" if len(by_row) > 5 else "")
        notes.append(f"volume_ml is empty for {len(by_row)} job{'s' if len(by_row) > 1 else ''} ({names}): their "
                     "scans are taken in row order, end-exhale first, and a fit refuses a job whose measured "
                     "volumes do not increase")
    return jobs, notes, problems


def _count_problem(label: str, rs: list[_Row]) -> str | None:
    """What is wrong with a job of one row: a file (a fit needs two or more volumes), or a folder (a 4-D
    CT) with a volume or landmarks (measured per phase); None for two or more rows."""
    if len(rs) > 1:
        return None
    if not rs[0].path.is_dir():
        return f"{label}: {len(rs)} scan; a fit needs two or more volumes, or one folder holding a 4-D CT"
    if rs[0].volume_ml is not None or rs[0].landmarks is not None:
        return (f"{label}: one scan, a folder (a 4-D CT): its volumes are measured per phase; leave volume_ml "
                "and landmarks empty")
    return None


def _rows(rows) -> str:
    return ", ".join(str(r) for r in sorted(rows))
