"""DIR-Lab 4-D CT files: finding the cases' landmark files and reading the voxel-spacing table.

:func:`discover` (and the shortcut :func:`find_cases`) walks a folder, recognises DIR-Lab landmark
file names (``caseN_dirLab300_T00_xyz.txt``, ``CaseN_300_T50_xyz.txt``, ``caseN_4D-75_T10.txt``, …)
and returns one :class:`CaseFiles` per usable case inside a :class:`Discovery`, with notes on what was
ignored or assumed. :func:`read_voxel_spacing` reads ``voxel_spacing.csv`` in its many dialects;
:data:`PUBLISHED_GEOMETRY` is the published spacing/size per case, used to cross-check the table
(:func:`geometry_notes`) and, with a note, for a case the table does not list.

Reading the landmark coordinates themselves (index → mm) is :mod:`lungdeform.io.landmarks`; the
motion models and their evaluation are :mod:`lungdeform.validate.dirlab`, which re-exports the public
names here.
"""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError, ReadError
from lungdeform.io.landmarks import as_spacing, read_dirlab_indices

PHASES = ("T00", "T10", "T20", "T30", "T40", "T50")
#: Published image geometry per case: ((dim_x, dim_y, dim_z) voxels, (sx, sy, sz) mm). Used to
#: *cross-check* voxel_spacing.csv (a mismatch is reported, never silently replaced), and, with a
#: note, for a case the spacing table does not list (see :func:`discover`).
PUBLISHED_GEOMETRY = {
    1: ((256, 256, 94), (0.97, 0.97, 2.5)),
    2: ((256, 256, 112), (1.16, 1.16, 2.5)),
    3: ((256, 256, 104), (1.15, 1.15, 2.5)),
    4: ((256, 256, 99), (1.13, 1.13, 2.5)),
    5: ((256, 256, 106), (1.10, 1.10, 2.5)),
    6: ((512, 512, 128), (0.97, 0.97, 2.5)),
    7: ((512, 512, 136), (0.97, 0.97, 2.5)),
    8: ((512, 512, 128), (0.97, 0.97, 2.5)),
    9: ((512, 512, 128), (0.97, 0.97, 2.5)),
    10: ((512, 512, 120), (0.97, 0.97, 2.5)),
}

# Landmark file names, matched case-insensitively: caseN_dirLab300_T00_xyz.txt, CaseN_300_T00_xyz.txt,
# caseN_4D-75_T10.txt, CASE10-DIRLAB300-T50-XYZ.TXT, and without the case number (dirLab300_T00_xyz.txt)
# when a folder above is named caseN / CaseNPack / CaseNDeploy. '300' in the middle part marks the
# extreme-phase pairs, '75' the tracked points.
_SEP = r"[\s_.\-]*"
_FILE_RE = re.compile(
    rf"^(?:case{_SEP}(?P<case>\d+)(?!\d){_SEP})?(?P<mid>.*?){_SEP}t(?P<phase>\d0)(?:{_SEP}xyz)?"
    r"(?:\.(?:txt|dat|csv|pts))?$",
    re.IGNORECASE,
)
_CASE_DIR_RE = re.compile(rf"^(?:dir{_SEP}lab{_SEP})?(?:4dct{_SEP})?case{_SEP}0*(?P<case>\d+)(?:{_SEP}(?:pack|deploy))?$", re.I)
_ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".7z", ".rar", ".gz")
# voxel_spacing.csv columns (names lower-cased, runs of spaces/hyphens/dots/brackets mapped to '_')
_CASE_COL = re.compile(r"case(?:_?(?:id|no|nr|number|name))?")
_CASE_COL_OTHER = re.compile(r"id|name|patient|subject|dataset|scan")
_SPACING_COL = {
    a: re.compile(
        rf"(?:voxel_?|pixel_?)?(?:spacing|res|resolution)_?{a}(?:_mm)?|{a}_?(?:spacing|res|resolution)(?:_mm)?"
        rf"|voxel_?(?:size_?)?{a}(?:_mm)?|{a}_?voxel(?:_?size)?(?:_mm)?|[ds]{a}(?:_mm)?|{a}_mm"
    )
    for a in "xyz"
}
_DIM_COL = {
    a: re.compile(rf"(?:dim|dims|size|n|image_size|image_dim|matrix)_?{a}|{a}_?(?:dim|dims|size|voxels)|n{a}")
    for a in "xyz"
}
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
#: Where a case's spacing came from when the table has no row for it (see :func:`discover`).
PUBLISHED_SOURCE = "the published DIR-Lab table (lungdeform.validate.dirlab.PUBLISHED_GEOMETRY)"


# --------------------------------------------------------------------------- voxel-spacing table
def _norm_col(name: str) -> str:
    return re.sub(r"[\s\-.()\[\]]+", "_", (name or "").strip().lower()).strip("_")


def _sniff_rows(path: Path) -> list[tuple[int, list[str]]]:
    """``[(line number, fields)]`` of a small delimited table: comma, semicolon, tab or spaces."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ReadError(f"{path}: not a text file ({exc.reason})") from exc
    lines = [(i, ln) for i, ln in enumerate(text.splitlines(), start=1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        return []
    head = lines[0][1]
    delim = next((d for d in (",", ";", "\t") if d in head), None)
    if delim is None:
        return [(i, ln.split()) for i, ln in lines]
    rows = csv.reader([ln for _, ln in lines], delimiter=delim, skipinitialspace=True)
    return [(i, [f.strip() for f in r]) for (i, _), r in zip(lines, rows)]


def _case_number(text: str) -> int:
    """``6``, ``"06"``, ``"6.0"``, ``"case6"``, ``"Case 6"``, ``"Case8Deploy"``, ``"4DCT6"`` → int."""
    t = str(text).strip().lower()
    m = re.fullmatch(rf"(?:dir{_SEP}lab{_SEP})?(?:4dct|case)?{_SEP}(\d+)(?:\.0*)?{_SEP}(?:pack|deploy)?", t)
    if not m:
        raise ValueError(f"case {text!r} is not a case number")
    return int(m.group(1))


def _triple(cell: str, what: str) -> list[float]:
    """Three numbers out of one cell: ``"0.97 x 0.97 x 2.5"``, ``"(512, 512, 128)"``, ``"0.97×0.97×2.5"``."""
    vals = _NUMBER.findall(cell or "")
    if len(vals) != 3:
        raise ValueError(f"{what} {cell!r} is not 3 numbers")
    return [float(v) for v in vals]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _headerless_columns(path: Path, row: list[str]) -> dict[str, int] | None:
    """Column map of a table without a header (first row is data), or None if it has one.

    4 columns: ``case sx sy sz``; 7 columns: ``case`` then the image size and the spacing in
    either order (the triple of whole numbers ≥ 16 is the size).
    """
    try:
        _case_number(row[0])
    except (ValueError, IndexError):
        return None
    if not all(_is_number(f) for f in row[1:]) or len(row) < 2:
        return None
    if len(row) == 4:
        return {"case": 0, "spacing_x": 1, "spacing_y": 2, "spacing_z": 3}
    if len(row) == 7:
        return {"case": 0, "size_and_spacing": 1}  # which triple is which: decided row by row
    raise ReadError(
        f"{path}: no header and {len(row)} columns; expected a header 'case,spacing_x_mm,spacing_y_mm,spacing_z_mm' "
        "(or 4 unlabelled columns case sx sy sz, or 7: case, size x y z, spacing x y z)"
    )


def _size_and_spacing_columns(row: list[str]) -> dict[str, int]:
    """Columns of a 7-field row without header: case, then size and spacing in either order."""
    def is_size(cells: list[str]) -> bool:
        try:
            return all(float(v).is_integer() and float(v) >= 16 for v in cells)
        except ValueError:
            return False

    first, second = ("dim", "spacing") if is_size(row[1:4]) and not is_size(row[4:7]) else ("spacing", "dim")
    return {"case": 0, **{f"{first}_{ax}": 1 + k for k, ax in enumerate("xyz")},
            **{f"{second}_{ax}": 4 + k for k, ax in enumerate("xyz")}}


def _header_columns(path: Path, raw: list[str]) -> dict[str, int]:
    """Column map from a header row (per-axis columns, or one combined 'spacing'/'dims' column)."""
    header = [_norm_col(c) for c in raw]
    cols: dict[str, int] = {}

    def first(pred) -> int | None:
        return next((i for i, h in enumerate(header) if i not in cols.values() and pred(h)), None)

    for key, pred in [("case", _CASE_COL.fullmatch), ("case", _CASE_COL_OTHER.fullmatch),
                      *[(f"spacing_{a}", _SPACING_COL[a].fullmatch) for a in "xyz"],
                      *[(f"dim_{a}", _DIM_COL[a].fullmatch) for a in "xyz"]]:
        i = None if key in cols else first(pred)
        if i is not None:
            cols[key] = i
    if not all(f"spacing_{a}" in cols for a in "xyz"):
        i = first(lambda h: "spacing" in h or "resolution" in h or h.startswith("voxel"))
        if i is not None:
            cols = {k: v for k, v in cols.items() if not k.startswith("spacing")}
            cols["spacing"] = i
    if not all(f"dim_{a}" in cols for a in "xyz"):
        cols = {k: v for k, v in cols.items() if not k.startswith("dim_")}
        i = first(lambda h: "dim" in h or h in ("size", "image_size", "matrix", "matrix_size", "shape", "image_shape"))
        if i is not None:
            cols["dims"] = i
    missing = [c for c in ("case", "spacing_x_mm", "spacing_y_mm", "spacing_z_mm")
               if c.removesuffix("_mm") not in cols and not (c.startswith("spacing") and "spacing" in cols)]
    if missing:
        raise ReadError(f"{path}: missing column(s) {', '.join(missing)} (have {raw})")
    return cols


def read_voxel_spacing(path) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
    """Read DIR-Lab's ``voxel_spacing.csv``: ``{case: (spacing (3,) mm, dims (3,) int or None)}``.

    Needs columns ``case``, ``spacing_x_mm``, ``spacing_y_mm``, ``spacing_z_mm`` in any order, with
    any extra columns; ``dim_x``, ``dim_y``, ``dim_z`` are optional (blank cells give ``None``).
    Column names are matched case-insensitively with aliases (``spacing_x``, ``x spacing (mm)``,
    ``dx``, ``voxel_x``; ``size_x``, ``nx``), or as one combined column (``spacing`` /
    ``voxel size (mm)`` holding ``0.97 x 0.97 x 2.5``; ``dims`` / ``image size`` holding
    ``512 x 512 x 128``); a table without a header is read as ``case sx sy sz`` (4 columns) or
    ``case`` + size + spacing (7 columns). The separator may be comma, semicolon, tab or spaces;
    cells may carry spaces; ``#`` lines are comments; case cells may read ``6``, ``case6`` or
    ``Case8Deploy``. Non-positive spacings and a case listed twice with different values are
    refused (:class:`ReadError` naming file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise ReadError(f"{path}: no such file")
    rows = _sniff_rows(path)
    if not rows:
        raise ReadError(f"{path}: empty file (expected a header 'case,spacing_x_mm,spacing_y_mm,spacing_z_mm')")
    cols = _headerless_columns(path, rows[0][1])
    if cols is None:
        cols = _header_columns(path, rows[0][1])
        rows = rows[1:]
    out: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
    auto = "size_and_spacing" in cols
    for lineno, row in rows:
        if not any(row):
            continue
        if auto:
            cols = _size_and_spacing_columns(row)
        cell = lambda key: row[cols[key]] if cols[key] < len(row) else ""  # noqa: E731
        try:
            case = _case_number(cell("case"))
            sp = _triple(cell("spacing"), "spacing") if "spacing" in cols else [float(cell(f"spacing_{a}")) for a in "xyz"]
            if "dims" in cols:
                dcells = [cell("dims")] if cell("dims") else []
                dvals = _triple(dcells[0], "image size") if dcells else None
            else:
                dcells = [cell(f"dim_{a}") for a in "xyz"] if "dim_x" in cols else []
                dvals = [float(c) for c in dcells] if dcells and all(dcells) else None
            dims = None if dvals is None else np.array([int(round(v)) for v in dvals])
        except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: an image size of inf
            raise ReadError(f"{path}, line {lineno}: not a number ({exc})") from exc
        try:
            spacing = as_spacing(sp)
        except InputError as exc:
            raise ReadError(f"{path}, line {lineno}: inconsistent spacing {sp}: each must be > 0 mm") from exc
        if dims is not None and np.any(dims < 1):
            raise ReadError(f"{path}, line {lineno}: image size {dims.tolist()} must be positive")
        if case in out and not np.allclose(out[case][0], spacing):
            raise ReadError(
                f"{path}, line {lineno}: inconsistent spacing for case {case}: "
                f"{spacing.tolist()} here, {out[case][0].tolist()} earlier"
            )
        out[case] = (spacing, dims)
    if not out:
        raise ReadError(f"{path}: no cases listed")
    return out


def geometry_notes(case: int, spacing, dims=None) -> list[str]:
    """Differences between a case's ``spacing`` (3,) mm / ``dims`` (3,) and :data:`PUBLISHED_GEOMETRY`."""
    if case not in PUBLISHED_GEOMETRY:
        return []
    pub_dims, pub_sp = PUBLISHED_GEOMETRY[case]
    notes = []
    if not np.allclose(np.asarray(spacing, dtype=float), pub_sp, atol=0.005):
        notes.append(f"case {case}: spacing {np.round(spacing, 3).tolist()} mm differs from the published {list(pub_sp)} mm")
    if dims is not None and tuple(int(v) for v in dims) != pub_dims:
        notes.append(f"case {case}: image size {[int(v) for v in dims]} differs from the published {list(pub_dims)}")
    return notes


# --------------------------------------------------------------------------- discovery
@dataclass(frozen=True)
class CaseFiles:
    """Where one DIR-Lab case's files are.

    ``extreme``: phase ('T00', 'T50') → 300-pair file; ``sampled``: phase ('T00'…'T50') → 75-point
    file; ``spacing : (3,) float`` mm; ``dims``: (3,) voxels or None; ``spacing_source``: the
    table the spacing came from, or :data:`PUBLISHED_SOURCE`.
    """

    case: int
    spacing: np.ndarray
    dims: np.ndarray | None
    extreme: dict[str, Path] = field(default_factory=dict)
    sampled: dict[str, Path] = field(default_factory=dict)
    #: what discovery noticed and did about this case (ignored files, a missing set), one line each
    notes: tuple[str, ...] = ()
    spacing_source: str = ""


@dataclass(frozen=True)
class Discovery:
    """What :func:`discover` found under a folder.

    ``cases``: case → :class:`CaseFiles` (the usable ones); ``skipped``: case → why it was left
    out (one line naming a file); ``spacing_files``: the spacing tables read; ``notes``: remarks
    not tied to one case (which table was used, none found, …).
    """

    root: Path
    cases: dict[int, CaseFiles]
    skipped: dict[int, str]
    spacing_files: tuple[Path, ...]
    notes: tuple[str, ...] = ()


def _walk_files(root: Path) -> list[Path]:
    """Every file under ``root``, sorted; follows linked folders once; skips hidden and ``__MACOSX``."""
    out: list[Path] = []
    seen: set[str] = set()
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        real = os.path.realpath(dirpath)
        if real in seen:  # a link loop, or the same folder linked twice
            dirnames[:] = []
            continue
        seen.add(real)
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and d.lower() != "__macosx")
        out += [Path(dirpath) / f for f in sorted(filenames) if not f.startswith(".")]
    return [p for p in out if p.is_file()]


def _classify(name: str) -> tuple[int | None, str, str] | None:
    """``(case or None, 'extreme' | 'sampled', 'Tnn')`` for a landmark file name, else None."""
    m = _FILE_RE.match(name)
    if not m:
        return None
    mid = m.group("mid").lower()
    if m.group("case") is None and "case" in mid:  # e.g. 'my_case1_300_T00.txt': not a DIR-Lab name
        return None
    if "300" in mid:
        kind = "extreme"
    elif "75" in mid:
        kind = "sampled"
    else:
        return None
    case = m.group("case")
    return (None if case is None else int(case)), kind, "T" + m.group("phase")


def _folder_case(path: Path) -> int | None:
    """Case number of the nearest folder above ``path`` named caseN / CaseNPack / CaseNDeploy."""
    for parent in path.parents:
        m = _CASE_DIR_RE.match(parent.name)
        if m:
            return int(m.group("case"))
    return None


def _is_spacing_table(path: Path) -> bool:
    stem = re.sub(r"[^a-z]", "", path.stem.lower())
    return path.suffix.lower() in (".csv", ".tsv", ".txt") and ("spacing" in stem or "voxelsize" in stem)


def _same_file_content(a: Path, b: Path) -> bool:
    x, y = read_dirlab_indices(a), read_dirlab_indices(b)
    return x.shape == y.shape and bool(np.array_equal(x, y))


def discover(root, published_fallback: bool = True) -> Discovery:
    """Find DIR-Lab cases under ``root`` by file name, case-insensitively.

    ``root`` may be a folder holding case folders (``Case1Pack``, ``Case8Deploy``, ``case10``, …),
    their parent, or one case folder itself. Recognised, at any depth: ``caseN_dirLab300_T00_xyz.txt``,
    ``CaseN_300_T50_xyz.txt`` (300 pairs) and ``caseN_4D-75_T10.txt`` (75 tracked points), with
    ``_``/``-``/space separators; a name without the case number takes it from the nearest folder
    named like ``CaseNPack``. Hidden files and ``__MACOSX`` are skipped; linked folders are followed.

    Spacing: every table named like ``voxel_spacing.csv`` (any case, ``.csv``/``.tsv``/``.txt``,
    e.g. ``VoxelSpacing.txt``) under ``root``, or beside ``root`` or up to two folders above it when
    none is inside; several tables are merged (a case given two different spacings is refused).
    A case the tables do not list (or every case, with no table at all) takes the spacing and size of
    :data:`PUBLISHED_GEOMETRY` when ``published_fallback`` and the case is one of DIR-Lab's 1–10,
    with a note naming the table; otherwise it is skipped with the reason
    (``published_fallback=False``: :class:`ReadError` instead).

    A case needs both extreme phases (T00, T50) and/or all six sampled phases (T00–T50); a partial
    set raises :class:`ReadError` naming a file of the case and what is missing. A case with only
    one of the two sets is kept with a note (the other set's measurements are skipped); files of
    phases not used here (T60–T90) are ignored with a note. Two files for the same phase are
    accepted if they hold the same numbers (noted), refused otherwise.
    """
    root = Path(root)
    if not root.is_dir():
        raise ReadError(f"{root}: not a directory")
    files = _walk_files(root)
    spacing, tables, notes = _read_spacing_tables(_find_spacing_tables(root, files))
    table_names = " and ".join(map(str, tables)) if tables else None
    if table_names:
        notes.append(f"voxel spacing from {table_names}")
    found, ignored, case_notes, unnumbered = _landmark_files(root, files)
    if unnumbered:
        notes.append(f"ignored {len(unnumbered)} landmark file(s) with no case number in their name or folder, "
                     f"e.g. {unnumbered[0]}")
    if not found:
        archives = [p for p in files if p.name.lower().endswith(_ARCHIVE_SUFFIXES)]
        hint = f"; extract the archive(s) first, e.g. {archives[0]}" if archives else ""
        raise ReadError(f"{root}: no DIR-Lab landmark files (caseN_…300_T00_xyz.txt, caseN_4D-75_T00.txt){hint}")
    where = f"no row in {table_names}" if table_names else \
        f"no voxel_spacing.csv found in {root} or the folders above it"
    cases: dict[int, CaseFiles] = {}
    skipped: dict[int, str] = {}
    for case, kinds in sorted(found.items()):
        got = _case_files(case, kinds, spacing.get(case), where, published_fallback, case_notes.get(case, []),
                          ignored.get(case, []))
        if isinstance(got, str):
            skipped[case] = got
        else:
            cases[case] = got
    for case, paths in sorted(ignored.items()):
        if case not in found:
            skipped[case] = (f"case {case}: skipped: only files of phases outside T00–T50, which this tool does "
                             f"not use, e.g. {paths[0]}")
    if not cases:
        raise ReadError(f"{root}: no usable DIR-Lab case: " + "; ".join(skipped.values()))
    return Discovery(root, cases, skipped, tuple(tables), tuple(notes))


def _find_spacing_tables(root: Path, files: list[Path]) -> list[Path]:
    """The spacing tables among ``files`` (under ``root``); when there are none, those beside
    ``root`` or up to two folders above it (the nearest folder holding one)."""
    tables = [p for p in files if _is_spacing_table(p) and _classify(p.name) is None]
    if tables:
        return tables
    ups = list(Path(os.path.abspath(root)).parents)[:3] + list(root.resolve().parents)[:3]
    for up in dict.fromkeys(ups):
        try:
            tables = sorted(p for p in up.iterdir() if p.is_file() and _is_spacing_table(p))
        except OSError:
            continue
        if tables:
            break
    return tables


def _read_spacing_tables(tables: list[Path]):
    """``(spacing, tables read, notes)``: ``spacing`` is case → ``(spacing (3,) mm, dims (3,) or None,
    the table)`` merged over ``tables`` (dims from a table that has them); a case given two different
    spacings raises :class:`ReadError`, and so does a broken ``voxel_spacing`` table, while another
    file that only looks like one is ignored with a note."""
    spacing: dict[int, tuple[np.ndarray, np.ndarray | None, Path]] = {}
    notes: list[str] = []
    read_tables = []
    for t in tables:
        try:
            table = read_voxel_spacing(t)
        except ReadError as exc:
            if re.sub(r"[^a-z]", "", t.stem.lower()) == "voxelspacing":
                raise  # the table itself is broken: say so
            notes.append(f"ignored {t}: not a spacing table ({exc})")  # e.g. spacing_notes.txt
            continue
        read_tables.append(t)
        for case, (sp, dims) in table.items():
            if case in spacing and not np.allclose(spacing[case][0], sp):
                raise ReadError(f"case {case}: spacing {sp.tolist()} mm in {t} but {spacing[case][0].tolist()} mm "
                                f"in {spacing[case][2]}")
            if case not in spacing or (spacing[case][1] is None and dims is not None):
                spacing[case] = (sp, dims, t)
    return spacing, read_tables, notes


def _landmark_files(root: Path, files: list[Path]):
    """``(found, ignored, case_notes, unnumbered)`` among ``files`` under ``root``: ``found`` is
    case → ``{"extreme": {phase: path}, "sampled": {phase: path}}``; ``ignored`` case → files of
    phases not used here; ``case_notes`` case → remarks (a name that disagrees with its folder, a
    repeated file); ``unnumbered`` the landmark files with no case number. Two different files for
    one phase raise :class:`ReadError`."""
    found: dict[int, dict[str, dict[str, Path]]] = {}
    ignored: dict[int, list[Path]] = {}
    case_notes: dict[int, list[str]] = {}
    unnumbered: list[Path] = []
    for p in files:
        hit = _classify(p.name)
        if hit is None:
            continue
        case, kind, phase = hit
        folder = _folder_case(p.relative_to(root) if case is not None else p)
        if case is None:
            if folder is None:
                unnumbered.append(p)
                continue
            case = folder
        elif folder is not None and folder != case:
            case_notes.setdefault(case, []).append(f"case {case}: {p} lies in a folder named for case {folder}; "
                                                   f"its file name (case {case}) was used")
        if phase not in (("T00", "T50") if kind == "extreme" else PHASES):
            ignored.setdefault(case, []).append(p)  # e.g. T60–T90 files: not used by the models here
            continue
        slot = found.setdefault(case, {"extreme": {}, "sampled": {}})[kind]
        if phase in slot:
            if not _same_file_content(slot[phase], p):
                raise ReadError(f"case {case}: two different files for {kind} phase {phase}: {slot[phase]} and {p}")
            case_notes.setdefault(case, []).append(f"case {case}: {p} repeats {slot[phase]} (same numbers): ignored")
            continue
        slot[phase] = p
    return found, ignored, case_notes, unnumbered


def _case_files(case: int, kinds: dict[str, dict[str, Path]], table_row, where: str, published_fallback: bool,
                found_notes: list[str], ignored: list[Path]) -> CaseFiles | str:
    """One found case (``kinds`` from :func:`_landmark_files`) as :class:`CaseFiles`, or the reason
    it is skipped (no spacing and not one of DIR-Lab's 1–10). ``table_row``: its ``(spacing, dims,
    table)`` or None (``where`` says why); ``found_notes``, ``ignored``: what discovery noticed."""
    ext, smp = kinds["extreme"], kinds["sampled"]
    first = next(iter({**ext, **smp}.values()))
    lead: list[str] = []
    if table_row is not None:
        sp, dims, table = table_row
        src, geo = str(table), geometry_notes(case, sp, dims)
    else:
        if not published_fallback:
            raise ReadError(f"case {case}: {where} for its landmark files (e.g. {first})")
        if case not in PUBLISHED_GEOMETRY:
            return (f"case {case}: skipped: {where} for its landmark files (e.g. {first}), and it is not "
                    "one of DIR-Lab's cases 1–10 with a published spacing")
        pub_dims, pub_sp = PUBLISHED_GEOMETRY[case]
        sp, dims, src, geo = np.array(pub_sp, dtype=float), np.array(pub_dims), PUBLISHED_SOURCE, []
        lead = [f"case {case}: {where}: used the published DIR-Lab spacing {list(pub_sp)} mm and size {list(pub_dims)}"]
    _check_phase_sets(case, ext, smp)
    cnotes = lead + list(found_notes)
    for p in ignored:
        outside = "T00/T50" if _classify(p.name)[1] == "extreme" else "T00–T50"
        cnotes.append(f"case {case}: ignored {p} (phase outside {outside})")
    if not smp:
        cnotes.append(f"case {case}: no 75-point files (caseN_4D-75_T00…T50) beside {first}: motion models "
                      "skipped, 300-pair displacement only")
    if not ext:
        cnotes.append(f"case {case}: no 300-pair files (caseN_…300_T00/T50_xyz) beside {first}: 300-pair "
                      "displacement skipped")
    return CaseFiles(case, sp, dims, dict(ext), dict(smp), tuple(cnotes + geo), src)


def _check_phase_sets(case: int, ext: dict[str, Path], smp: dict[str, Path]) -> None:
    """Refuse a partial set: 300-pair files need T00 and T50, 75-point files all of :data:`PHASES`."""
    if ext and set(ext) != {"T00", "T50"}:
        have = next(iter(ext.values()))
        missing = sorted({"T00", "T50"} - set(ext))
        raise ReadError(
            f"case {case}: 300-pair file for {', '.join(missing)} missing beside {have} "
            f"(need T00 and T50; found {', '.join(sorted(ext))})"
        )
    if smp and set(smp) != set(PHASES):
        missing = sorted(set(PHASES) - set(smp))
        have = next(iter(smp.values()))
        raise ReadError(
            f"case {case}: 75-point files missing phase(s) {', '.join(missing)} beside {have} "
            f"(need {', '.join(PHASES)})"
        )


def find_cases(root, published_fallback: bool = True) -> dict[int, CaseFiles]:
    """The usable cases under ``root``: ``discover(root, published_fallback).cases`` (see :func:`discover`)."""
    return discover(root, published_fallback).cases
