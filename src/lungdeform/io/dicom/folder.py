"""A DICOM folder as exports come: its image series told from everything else the export holds.

A CT exported from a planning system or a PACS holds more than its slices: an RTSTRUCT, an RTPLAN,
an RTDOSE, a REG, key objects (KO), structured reports (SR), presentation states (PR), a DICOMDIR,
a localizer (scout), other reconstructions, and files that are no DICOM at all (a README,
``Thumbs.db``, ``.DS_Store``). :func:`survey` reads the header of every DICOM file (pydicom, up to
the last attribute it needs, no pixels; each file through
:func:`~lungdeform.io.dicom.guard.check_dicom_file` first, so a damaged file is refused, never
skipped), keeps of each image file the attributes a series reader asks for (:attr:`ImageSeries.tags`:
the 4-D CT reader's need no second reading) and sorts what it finds:

- **image series**, grouped by SeriesInstanceUID: every object with an image (Rows) that is no RT
  Dose or RT Image grid;
- **everything else**, ignored and named (:func:`ignored_line`): objects without an image, by their
  Modality (RTSTRUCT, RTPLAN, REG, KO, SR …) or SOP class, RT Dose and RT Image grids, files that
  are no DICOM (neither a ``.dcm``/``.ima``/``.dicom`` name nor the ``DICM`` preamble).

:func:`candidates` are the series a CT reader may take: the CT image series (Modality CT or a CT
SOP class) that are no localizer (ImageType LOCALIZER) and hold two or more slices (one slice: only
when there is nothing else); only when a folder holds no CT series at all, its other image series
(what a tool that sets no Modality writes). :func:`pick` takes the one candidate, or the one a
:class:`SeriesChoice` names (``--series UID``, ``--series-description TEXT``); more than one
candidate without a choice is refused, naming each (UID, description, images): lungdeform does not
guess which reconstruction or which phase is meant.

Where the files are: a folder's own files; a DICOMDIR at its top (PS3.10 8.6, the media directory of
a CD or an export) is followed, its referenced files being the ones looked at (a file it names that
is missing is named among the ignored; a DICOMDIR that cannot be read is said, and the folder's files
read instead); a folder holding no DICOM file itself is looked into, each subfolder's series a
series of its own (named with its subfolder), at most :data:`MAX_FILES` files.

Library code: nothing is printed; the CLI says :func:`ignored_line`.
"""

from __future__ import annotations

import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import pydicom
from pydicom.charset import convert_encodings, default_encoding
from pydicom.datadict import dictionary_VR, tag_for_keyword
from pydicom.dataelem import RawDataElement, convert_raw_data_element
from pydicom.filereader import data_element_generator
from pydicom.multival import MultiValue
from pydicom.tag import Tag
from pydicom.uid import UID

from lungdeform.errors import ReadError

from .guard import check_dicom_file, is_dicom_file

#: Files looked at at most (a 4-D CT of 10 phases × 200 slices is 2000): do not crawl a disk.
MAX_FILES = 20000
#: Folders walked at most looking for DICOM files below a folder that holds none itself.
MAX_FOLDERS = 2000
#: CT Image Storage, Enhanced CT Image Storage, Legacy Converted Enhanced CT Image Storage
CT_SOP_CLASSES = ("1.2.840.10008.5.1.4.1.1.2", "1.2.840.10008.5.1.4.1.1.2.1", "1.2.840.10008.5.1.4.1.1.2.2")
#: Image objects that are no patient image a reader may take: RT Dose and RT Image grids
GRID_MODALITIES = ("RTDOSE", "RTIMAGE")
#: The header attributes :func:`survey` reads of each file (SpecificCharacterSet: how its text is encoded)
_KEY = {k: Tag(tag_for_keyword(k)) for k in ("SpecificCharacterSet", "SOPClassUID", "SOPInstanceUID", "Modality",
                                             "SeriesInstanceUID", "SeriesDescription", "ImageType", "Rows",
                                             "NumberOfFrames")}
_TAGS = tuple(_KEY.values())
_CHARSET, _MEDIA_SOP_CLASS, _TRANSFER_SYNTAX = _KEY["SpecificCharacterSet"], Tag(0x0002, 0x0002), Tag(0x0002, 0x0010)
#: Ignored objects named in full in :func:`ignored_line`; beyond, a count
_NAMED = 12
#: Value representations :func:`_text` takes as written (ASCII by the standard), text ones (ASCII when
#: it holds no escape: the same in every character set; else decoded by pydicom) and binary numbers
#: it unpacks itself (struct formats, as pydicom does); any other is left to pydicom
_AS_WRITTEN = frozenset(("AE", "AS", "CS", "DA", "DS", "DT", "IS", "TM", "UI", "UR"))
_TEXT_VRS = frozenset(("SH", "LO", "ST", "LT", "UT", "UC", "PN"))
_NUMBERS = {"US": "H", "SS": "h", "UL": "I", "SL": "i", "FL": "f", "FD": "d"}


@dataclass(frozen=True)
class SeriesChoice:
    """Which image series of a folder to read when it holds more than one candidate: ``uid`` its
    SeriesInstanceUID (``--series``), or ``description`` its SeriesDescription (``--series-description``:
    equal ignoring case and surrounding spaces, else the one description that contains it).
    ``several_only``: it applies only to a folder where several candidates remain (one choice for
    several folders, e.g. the inputs of a fit), else to every folder it is given for."""

    uid: str | None = None
    description: str | None = None
    several_only: bool = False

    @property
    def given(self) -> bool:
        return self.uid is not None or self.description is not None

    def __str__(self) -> str:
        return f"--series {self.uid}" if self.uid is not None else f"--series-description {self.description!r}"


@dataclass(frozen=True, eq=False)
class ImageSeries:
    """One image series of a folder: ``uid``, ``description`` (SeriesDescription, '' when none),
    ``modality``, ``files`` (its files, in name order), ``localizer`` (ImageType LOCALIZER),
    ``ct`` (Modality CT or a CT SOP class), ``folder`` the subfolder it lies in (relative) when a
    parent folder's subfolders were looked into ('' otherwise), ``tags`` one dict per file (in the
    order of ``files``) of the tags :func:`survey` was asked for (``"gggg|eeee"`` → text as
    :func:`_text` gives it), read with the rest of the header; empty dicts when none were asked for."""

    uid: str
    description: str
    modality: str
    files: tuple[str, ...]
    localizer: bool
    ct: bool
    folder: str = ""
    tags: tuple[dict[str, str], ...] = ()

    @property
    def label(self) -> str:
        """``[folder: ]UID 'description' (n CT images)`` for messages."""
        where = f"{self.folder}: " if self.folder else ""
        return f"{where}{self.uid} {self.description!r} ({len(self.files)} {self.modality or 'DICOM'} image(s))"


@dataclass(frozen=True, eq=False)
class FolderSurvey:
    """What :func:`survey` found under ``path``: ``series`` every image series (largest first),
    ``ignored`` ``(name, what)`` of every object that is no image series (``what``: ``RTSTRUCT``,
    ``no DICOM`` …; ``name`` relative to ``path``), ``dicomdir`` a line when a DICOMDIR was followed
    or could not be."""

    path: Path
    series: tuple[ImageSeries, ...]
    ignored: tuple[tuple[str, str], ...]
    dicomdir: str = ""


def survey(path, tags=()) -> FolderSurvey:
    """The image series and the other objects of the DICOM folder ``path`` (module docstring).
    ``tags`` (``"gggg|eeee"``): tags to keep of each image file (:attr:`ImageSeries.tags`), read in the
    same pass over its header, so that a series reader need not read the headers again.
    :class:`ReadError` naming the file for a damaged DICOM file, the folder when it is none."""
    root = Path(path)
    if not root.is_dir():
        raise ReadError(f"{root}: not a folder")
    files, ignored, note, below = _files(root)
    wanted = tuple((t, Tag(int(t[:4], 16), int(t[5:], 16))) for t in tags)
    found: dict[tuple[str, str], list] = {}
    for f in files:
        kind = _object(f, wanted)
        if isinstance(kind, str):
            ignored.append((_name(f, root), kind))
        else:  # below a parent folder: a series per subfolder (two copies of one series are two)
            found.setdefault((_name(Path(f).parent, root) if below else "", kind[0]), []).append((f, kind))
    series = [_series(uid, members, where) for (where, uid), members in found.items()]
    return FolderSurvey(root, tuple(sorted(series, key=lambda s: -len(s.files))), tuple(ignored), note)


def _files(root: Path) -> tuple[list[str], list[tuple[str, str]], str, bool]:
    """``(files to look at, [(name, "no DICOM")], DICOMDIR line, whether they are below root's subfolders)``."""
    with os.scandir(root) as it:
        entries = sorted((e for e in it if e.is_file()), key=lambda e: e.name)
    dicomdir = next((e for e in entries if e.name.upper() == "DICOMDIR"), None)
    own = [e.path for e in entries if e.name.upper() != "DICOMDIR"]
    dicom = [f for f in own if is_dicom_file(f)]
    ignored = [(_name(f, root), "no DICOM") for f in own if not is_dicom_file(f)]
    note = ""
    if dicomdir is not None:
        try:
            referenced, missing = _dicomdir_files(Path(dicomdir.path))
        except ReadError as exc:
            note = f"its DICOMDIR could not be followed ({exc}); the folder's files read instead"
        else:
            note = f"followed its DICOMDIR ({len(referenced)} file(s))"
            return referenced, ignored + [(m, "named in the DICOMDIR, missing") for m in missing], note, False
    if dicom or dicomdir is not None:
        return dicom, ignored, note, False
    for sub, dirs, names in _walk(root):
        for name in sorted(names):
            f = os.path.join(sub, name)
            (dicom.append(f) if is_dicom_file(f) else ignored.append((_name(f, root), "no DICOM")))
        if len(dicom) > MAX_FILES:
            raise ReadError(f"{root}: more than {MAX_FILES} DICOM files below it; give the folder of one CT or 4-D CT")
    return dicom, ignored, note, True


def _walk(root: Path):
    """``os.walk`` below ``root`` (its own files excluded), sorted, at most :data:`MAX_FOLDERS` folders."""
    for n, (sub, dirs, names) in enumerate(os.walk(root)):
        dirs.sort()
        if n > MAX_FOLDERS:
            raise ReadError(f"{root}: more than {MAX_FOLDERS} folders below it; give the folder of one CT or 4-D CT")
        if n:
            yield sub, dirs, names


def _dicomdir_files(path: Path) -> tuple[list[str], list[str]]:
    """``(existing files, missing names)`` the DICOMDIR ``path`` references (ReferencedFileID, its
    components relative to the DICOMDIR's folder; matched ignoring case, as CDs name them)."""
    check_dicom_file(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, force=True)
            records = list(ds.get("DirectoryRecordSequence", []))
    except Exception as exc:  # any parse failure: said by the caller, the folder read instead
        raise ReadError(f"{type(exc).__name__}: {str(exc).strip()[:120]}") from exc
    if not records:
        raise ReadError("no directory records")
    found, missing = [], []
    for record in records:
        ref = record.get("ReferencedFileID")
        if not ref:
            continue
        parts = [str(p) for p in (ref if isinstance(ref, (list, tuple, pydicom.multival.MultiValue)) else [ref])]
        inside = all(p not in ("", ".", "..") and "/" not in p and "\\" not in p for p in parts)  # never above it
        f = _case_insensitive(path.parent, parts) if inside else None
        (found.append(str(f)) if f is not None else missing.append("/".join(parts)))
    return sorted(dict.fromkeys(found)), missing


def _case_insensitive(folder: Path, parts: list[str]) -> Path | None:
    """``folder/parts…`` as it exists, each component matched ignoring case; None when missing."""
    here = folder
    for part in parts:
        exact = here / part
        if exact.exists():
            here = exact
            continue
        try:
            here = next(p for p in here.iterdir() if p.name.upper() == part.upper())
        except (StopIteration, OSError):
            return None
    return here if here.is_file() else None


def _name(f, root: Path) -> str:
    try:
        return str(Path(f).relative_to(root))
    except ValueError:
        return str(f)


def _object(f: str, wanted=()):
    """What the DICOM file ``f`` holds: ``(series UID, modality, description, localizer, SOP class,
    {tag: text} of ``wanted`` ((``"gggg|eeee"``, Tag) pairs, :func:`_text`))`` for an image of a
    patient, or a word saying what it is (``RTSTRUCT``, ``RTDOSE grid`` …)."""
    check_dicom_file(f)
    asked = frozenset(_TAGS + tuple(tag for _, tag in wanted))
    try:
        with warnings.catch_warnings():  # values pydicom still reads (a VR mismatch): not the user's concern
            warnings.simplefilter("ignore")
            meta, data = _header(f, asked)
            encoding = convert_encodings(_value(data, _CHARSET, default_encoding) or default_encoding)
            kept = {name: _text(data, tag, encoding) for name, tag in wanted}
            sop = _text(data, _KEY["SOPClassUID"], encoding) or _text(meta, _MEDIA_SOP_CLASS, encoding)
            modality = _text(data, _KEY["Modality"], encoding).upper()
            image = _text(data, _KEY["Rows"], encoding) != ""
            uid = _text(data, _KEY["SeriesInstanceUID"], encoding)
            description = _text(data, _KEY["SeriesDescription"], encoding)
            types = [t.strip().upper() for t in _text(data, _KEY["ImageType"], encoding).split("\\")]
    except Exception as exc:  # any parse failure becomes one clear line
        raise ReadError(f"{f}: not a readable DICOM file ({type(exc).__name__}: {str(exc).strip()[:160]})") from exc
    if sop == "1.2.840.10008.1.3.10":
        return "DICOMDIR"
    if modality in GRID_MODALITIES:
        return f"{modality} grid"
    if not image:
        return modality or _sop_name(sop)
    return (uid, modality, description, "LOCALIZER" in types, sop, kept)


def _header(f: str, tags: frozenset) -> tuple[dict, dict]:
    """``(file meta, data set)`` of the DICOM file ``f``: ``{tag: element}`` of its file meta
    information and of the data set elements ``tags`` (Tag), values unconverted
    (:class:`~pydicom.dataelem.RawDataElement`) where pydicom leaves them so. The common file (the
    ``DICM`` preamble, a standard transfer syntax, little endian, not deflated) is read by pydicom's
    element reader up to the last of ``tags`` (what follows, the pixels included, is not read); any
    other by ``dcmread``."""
    last = max(tags)
    with open(f, "rb") as fh:
        if fh.read(132)[128:132] == b"DICM":
            meta = {e.tag: e for e in data_element_generator(fh, False, True, stop_when=_after_meta)}
            syntax = UID(_text(meta, _TRANSFER_SYNTAX, default_encoding))
            if syntax.is_transfer_syntax and syntax.is_little_endian and not syntax.is_deflated:
                data = data_element_generator(fh, syntax.is_implicit_VR, True, specific_tags=tags,
                                              stop_when=lambda tag, _vr, _length: tag > last)
                return meta, {e.tag: e for e in data}
    try:
        ds = pydicom.dcmread(f, stop_before_pixels=True, specific_tags=list(tags))
    except pydicom.errors.InvalidDicomError:  # no preamble (GDCM reads such files): its header checked above
        ds = pydicom.dcmread(f, stop_before_pixels=True, specific_tags=list(tags), force=True)
    meta = getattr(ds, "file_meta", None)
    return ({} if meta is None else {e.tag: e for e in meta}), {tag: ds.get_item(tag) for tag in tags if tag in ds}


def _after_meta(tag, _vr, _length) -> bool:
    """Whether ``tag`` is past the file meta information (group 0002)."""
    return tag.group != 2


def _value(elements: dict, tag, encoding):
    """The value of ``tag`` in ``elements`` (:func:`_header`) as pydicom converts it (text decoded with
    ``encoding``, the data set's character set), None when absent or empty."""
    elem = elements.get(tag)
    if elem is None:
        return None
    if isinstance(elem, RawDataElement):
        elem = convert_raw_data_element(elem, encoding=encoding)
    return elem.value if elem.value not in ("", b"") else None


def _text(elements: dict, tag, encoding) -> str:
    """The value of ``tag`` in ``elements`` (:func:`_header`) as text, as GDCM gives it: what the file
    holds, stripped of its padding (spaces, NUL), several values ``\\``-separated; binary numbers (US,
    UL ...) written out, text (LO, PN ...) decoded with ``encoding`` (the data set's character set);
    ``""`` when absent or empty. Decimal strings, times and UIDs stay as written, so that a malformed
    one is refused by whoever needs it (:mod:`~lungdeform.io.dicom.slices`), naming it, not here."""
    elem = elements.get(tag)
    if elem is None or elem.value is None:
        return ""
    if isinstance(elem, RawDataElement):
        vr = elem.VR if elem.VR not in (None, "UN") else dictionary_VR(tag)  # implicit VR: the dictionary's
        raw = elem.value
        size = struct.calcsize(_NUMBERS.get(vr, "x"))
        if vr in _NUMBERS and len(raw) % size == 0:  # what pydicom would unpack
            form = ("<" if elem.is_little_endian else ">") + _NUMBERS[vr] * (len(raw) // size)
            return "\\".join(str(v) for v in struct.unpack(form, raw))
        if vr in _AS_WRITTEN or (vr in _TEXT_VRS and raw.isascii() and b"\x1b" not in raw):
            return raw.decode("utf-8", "replace").strip(" \0\t\r\n")
    value = _value(elements, tag, encoding)
    values = value if isinstance(value, (list, tuple, MultiValue)) else [value]
    return "\\".join("" if v is None else str(v) for v in values).strip(" \0\t\r\n")


def _sop_name(sop: str) -> str:
    """A SOP class by its name (``Key Object Selection Document Storage``), or its UID."""
    name = UID(sop).name if sop else ""
    return name if name and name != sop else (f"SOP class {sop}" if sop else "DICOM without SOP class")


def _series(uid: str, members: list, folder: str = "") -> ImageSeries:
    """One image series of ``(file, object)`` members (:func:`_object`), in the subfolder ``folder``."""
    first = members[0][1]
    modalities = {m[1] for _, m in members}
    ct = any(m[1] == "CT" or m[4] in CT_SOP_CLASSES for _, m in members)
    members = sorted(members, key=lambda m: m[0])
    return ImageSeries(uid, first[2], "CT" if ct else "/".join(sorted(modalities - {""})) or "",
                       tuple(f for f, _ in members), all(m[3] for _, m in members), ct, folder,
                       tuple(m[5] for _, m in members))


def candidates(found: FolderSurvey) -> list[ImageSeries]:
    """The series a CT reader may take (module docstring), largest first."""
    ct = [s for s in found.series if s.ct and not s.localizer]
    volumes = [s for s in ct if len(s.files) >= 2]
    if volumes or ct:
        return volumes or ct
    return [s for s in found.series if not s.localizer]


def pick(found: FolderSurvey, choice: SeriesChoice | None = None) -> ImageSeries:
    """The image series of ``found`` to read: the one ``choice`` names (among every image series;
    a UID exactly, a description as :class:`SeriesChoice` says), else the one candidate
    (:func:`candidates`). :class:`ReadError` naming the folder when there is none, when the choice
    matches none or several, or when several candidates remain without a choice (each named)."""
    pool = candidates(found)
    if choice is not None and choice.given and not (choice.several_only and len(pool) < 2):
        return _chosen(found, choice)
    if len(pool) == 1:
        return pool[0]
    if not pool:
        what = "; ".join(f"{n} ({w})" for n, w in found.ignored[:6]) or "nothing"
        raise ReadError(f"{found.path}: no DICOM image series (found: {what})")
    listed = "; ".join(s.label for s in pool)
    raise ReadError(f"{found.path}: holds {len(pool)} CT series ({listed}): which one is meant cannot be told; "
                    "choose one with --series UID or --series-description TEXT")


def _chosen(found: FolderSurvey, choice: SeriesChoice) -> ImageSeries:
    """The image series ``choice`` names among every series of ``found`` (localizers included: asked for by name)."""
    every = list(found.series)
    if choice.uid is not None:
        hits = [s for s in every if s.uid == choice.uid.strip()]
    else:
        want = choice.description.strip().casefold()
        hits = [s for s in every if s.description.casefold() == want] or \
               [s for s in every if want and want in s.description.casefold()]
    if len(hits) == 1:
        return hits[0]
    listed = "; ".join(s.label for s in (hits or every)) or "none"
    if hits:
        raise ReadError(f"{found.path}: {choice} matches {len(hits)} series ({listed}); give --series UID")
    raise ReadError(f"{found.path}: no image series matches {choice} (its image series: {listed})")


def ignored_line(found: FolderSurvey, chosen=()) -> str | None:
    """One line naming what a reader of ``chosen`` (the image series read) ignored under
    ``found.path``: each other object by name and kind, each other image series by its label; None
    when nothing was ignored. ``"<folder>: ignored N object(s) that are not the CT: RS_plan.dcm
    (RTSTRUCT), README.txt (no DICOM), series 1.2.3 'Topogram' (1 CT image(s), a localizer) …"``"""
    taken = {id(s) for s in chosen}
    items = [f"{name} ({what})" for name, what in found.ignored]
    for s in found.series:
        if id(s) not in taken:
            why = "a localizer" if s.localizer else ("not CT" if not s.ct else "another series")
            items.append(f"series {s.label[:-1]}, {why})")
    if not items and not found.dicomdir:
        return None
    shown = ", ".join(items[:_NAMED]) + (f" and {len(items) - _NAMED} more" if len(items) > _NAMED else "")
    head = f"{found.path}: " + (f"{found.dicomdir}; " if found.dicomdir else "")
    return head + (f"ignored {len(items)} object(s) that are not the images read: {shown}" if items else "nothing else in it")
