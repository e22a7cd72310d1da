"""The one validation walk of DICOM attributes: what a reader requires, what a writer may write.

Reading: :func:`require` checks that a dataset holds the attributes a reader needs, each readable,
and that those holding UIDs are DICOM UIDs (:data:`UID`); a :class:`~lungdeform.errors.ReadError`
names the file and the attributes. Every reader of this package calls it
(:mod:`~lungdeform.io.dicom.rtstruct`, :mod:`~lungdeform.io.dicom.series`,
:mod:`~lungdeform.io.dicom.registration`, and :mod:`~lungdeform.io.dicom.fourdct` on the
attributes the folder survey read of each file, as text).

Writing: :func:`decimal` formats a number as a Decimal String of at most 16 bytes (PS3.5 6.2, DS;
Eclipse refuses longer ones); :func:`fit_text` makes every text value lungdeform derives (a
structure set label, a series description, a ROI name ``GTV_β肿瘤@phase03``) fit its VR: characters
the VR cannot hold replaced, cut on a character boundary to the VR's length in bytes of UTF-8 (what
dciodvfy counts; never inside a combining sequence), kept unique. :func:`check_dataset` walks a
dataset, its sequences included, before it is saved: every value within its VR's limits
(:data:`MAX_BYTES`: DS 16, IS 12, UI 64 bytes, ...), every UI a UID. A value outside them is a bug
of the writer, refused with :class:`~lungdeform.errors.InputError` naming the attribute, never written.
"""

from __future__ import annotations

import math
import re
import unicodedata
import warnings
from collections.abc import Mapping

from pydicom.dataset import Dataset
from pydicom.multival import MultiValue

from lungdeform.errors import InputError, ReadError

#: A DICOM UID (PS3.5 9.1): dot-separated numbers without leading zeros, at most 64 characters.
UID = re.compile(r"(?=.{1,64}$)(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*")
#: Largest value length in bytes per VR, one value of a multi-valued attribute (PS3.5 Table 6.2-1;
#: PN: 64 per component group).
MAX_BYTES = {"AE": 16, "AS": 4, "CS": 16, "DA": 8, "DS": 16, "IS": 12, "LO": 64, "LT": 10240, "PN": 64,
             "SH": 16, "ST": 1024, "TM": 14, "UI": 64, "DT": 26}
#: Attributes holding UIDs that :func:`require` checks when asked for them.
_UID_KEYS = ("SOPInstanceUID", "SOPClassUID", "FrameOfReferenceUID", "StudyInstanceUID", "SeriesInstanceUID")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else "no detail"


def require(ds: Dataset | Mapping[str, str], keys, where, purpose: str, optional=()) -> None:
    """:class:`ReadError` naming ``where`` (the file) when ``ds`` (a dataset, or ``{keyword: text}``
    another reader gave) lacks any of ``keys`` (absent or empty), when one of ``keys`` or
    ``optional`` cannot be read (pydicom converts on first access),
    or when one of the UID attributes among them (:data:`_UID_KEYS`) is not a DICOM UID (an
    ``optional`` one only when present); ``purpose`` ends the message ("which an RTSTRUCT needs")."""
    try:  # a value pydicom cannot convert raises on first access
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            missing = [k for k in keys if not ds.get(k)]
            given = [k for k in optional if ds.get(k)]
            uids = {k: str(ds.get(k, "")) for k in (*keys, *given) if k in _UID_KEYS and k not in missing}
    except Exception as exc:  # any conversion failure becomes one clear line
        raise ReadError(f"{where}: unreadable DICOM attribute ({type(exc).__name__}: {_first_line(exc)})") from exc
    if missing:
        raise ReadError(f"{where}: DICOM file lacks {', '.join(missing)}, {purpose}")
    for key, uid in uids.items():
        if not UID.fullmatch(uid):
            raise ReadError(f"{where}: {key} {uid[:70]!r} is not a DICOM UID (digits and dots, at most 64 characters)")


def decimal(value: float, digits: int = 12, places: int | None = None) -> str:
    """``value`` as a DICOM Decimal String of at most 16 bytes: with ``places`` decimals when that
    fits (``f"{value:.6f}"``, how lungdeform has always written positions), else with as many
    significant digits as fit, up to ``digits`` (``-123.456789012`` for -123.45678901234,
    ``1.2345678901e-05``); a value that is not finite is refused with :class:`InputError`."""
    x = float(value)
    if not math.isfinite(x):
        raise InputError(f"a DICOM decimal string must be finite, got {value!r}")
    if places is not None and len(text := f"{x:.{places}f}") <= 16:
        return text
    for n in range(digits, 0, -1):
        text = f"{x:.{n}g}"
        if len(text) <= 16:
            return text
    raise InputError(f"{value!r} cannot be written as a DICOM decimal string of 16 bytes")


#: Text value representations, whose characters SpecificCharacterSet (0008,0005) governs (PS3.5 6.1.2.3)
TEXT_VRS = ("SH", "LO", "ST", "LT", "UT", "UC", "PN")


def declare_charset(ds: Dataset) -> None:
    """Set ``ds.SpecificCharacterSet`` to ``ISO_IR 192`` (UTF-8) when a text value of ``ds`` or its
    sequences is not ASCII (a patient name copied from a Latin-1 source, ``Müller``; a ROI name in
    Chinese), so that pydicom writes it as UTF-8 and says so; without it the file would hold bytes
    outside the default repertoire, which dciodvfy and planning systems refuse or garble (PS3.5
    6.1.2.3). ``ISO_IR 100`` (Latin-1) instead when every text is Latin-1 and a value copied from a
    Latin-1 source fits its VR's bytes in Latin-1 only (a 64-character description with umlauts):
    a valid source is not refused for its re-encoding."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        texts = [(e.VR, e.value) for e in ds.iterall() if e.VR in TEXT_VRS and e.value is not None]
    values = [(vr, str(v)) for vr, t in texts for v in (t if isinstance(t, (list, tuple, MultiValue)) else [t])]
    if all(v.isascii() for _, v in values):
        return
    overflow = any(len(part.encode("utf-8")) > MAX_BYTES.get(vr, 1 << 30)
                   for vr, v in values for part in (v.split("=") if vr == "PN" else [v]))
    latin1 = all(_encodes(v, "latin-1") for _, v in values)
    ds.SpecificCharacterSet = "ISO_IR 100" if overflow and latin1 else "ISO_IR 192"


def _encodes(text: str, codec: str) -> bool:
    try:
        text.encode(codec)
    except UnicodeEncodeError:
        return False
    return True


def _codec(ds: Dataset, default: str = "utf-8") -> str:
    """The codec of ``ds``'s declared SpecificCharacterSet as lungdeform writes it: Latin-1 for
    ``ISO_IR 100``, else UTF-8 (ASCII text is the same in both)."""
    charset = ds.get("SpecificCharacterSet")
    if charset is None:
        return default
    return "latin-1" if str(charset).strip() == "ISO_IR 100" else "utf-8"


#: Characters a short text value (SH, LO, PN, CS) cannot hold: the backslash (it separates values)
#: and every control character (PS3.5 6.2; ESC only begins an ISO 2022 escape, never in UTF-8)
_NOT_IN_TEXT = re.compile(r"[\\\x00-\x1f\x7f-\x9f]")
#: Characters that join what follows to what precedes them: a cut never falls before one
_JOINERS = {"\u200c", "\u200d", "\u034f"}


def text_boundary(text: str, i: int) -> bool:
    """Whether ``text`` may be cut before index ``i`` without splitting a user-perceived character: not
    before a combining mark (``e`` + U+0301), a variation selector or a joiner, nor after a joiner."""
    if i <= 0 or i >= len(text):
        return True
    ch, before = text[i], text[i - 1]
    return not (unicodedata.combining(ch) or unicodedata.category(ch) in ("Mn", "Me", "Mc")
                or "\ufe00" <= ch <= "\ufe0f" or "\U000e0100" <= ch <= "\U000e01ef"
                or ch in _JOINERS or before in _JOINERS)


def cut_text(text: str, limit: int) -> str:
    """The longest start of ``text`` whose UTF-8 encoding is at most ``limit`` bytes and that ends on
    a character boundary (:func:`text_boundary`), trailing spaces removed (DICOM's padding)."""
    if len(text.encode("utf-8")) <= limit:
        return text.rstrip(" ")
    size, i = 0, 0
    while i < len(text) and size + len(text[i].encode("utf-8")) <= limit:
        size += len(text[i].encode("utf-8"))
        i += 1
    while i > 0 and not text_boundary(text, i):
        i -= 1
    return text[:i].rstrip(" ")


def fit_text(text: str, vr: str, *, keep: str = "", taken=()) -> str:
    """``text`` followed by ``keep`` as one value of VR ``vr`` (SH, LO, ST …, :data:`MAX_BYTES`):
    characters the VR cannot hold (:data:`_NOT_IN_TEXT`) become ``_``; ``text`` is cut
    (:func:`cut_text`) so that the whole fits the VR's length in bytes of UTF-8 with ``keep`` (a phase
    tag ``@phase03``) whole at its end; when the result is one of ``taken`` (values already given, e.g.
    the other ROI names of a structure set) a ``~2``, ``~3`` … goes before ``keep`` until it is not.
    ASCII text within the limit comes back as it is."""
    limit = MAX_BYTES[vr]
    clean = (lambda t: _NOT_IN_TEXT.sub("_", str(t))) if vr in ("SH", "LO", "PN", "CS", "AE") else str
    text, keep = clean(text), clean(keep)
    if len(keep.encode("utf-8")) > limit // 2:  # a tag longer than half the value: cut it too
        keep = cut_text(keep, limit // 2)
    value = cut_text(text, limit - len(keep.encode("utf-8"))) + keep
    n = 1
    while value in taken:
        n += 1
        mark = f"~{n}{keep}"
        value = cut_text(text, limit - len(mark.encode("utf-8"))) + mark
    return value


def type2_defaults(ds: Dataset, keys) -> None:
    """Add each of ``keys`` that ``ds`` lacks with an empty value: a Type 2 attribute must be present,
    empty when unknown (PS3.5 7.4.3); a value is never invented."""
    for key in keys:
        if key not in ds:
            setattr(ds, key, "")


def check_dataset(ds: Dataset, where: str = "dataset") -> None:
    """Walk ``ds`` and its sequences: every value of a VR in :data:`MAX_BYTES` at most that many
    bytes, every UI value a UID (:data:`UID`); :class:`InputError` naming ``where`` and the attribute."""
    with warnings.catch_warnings():  # pydicom's own warnings on such values: refused here instead
        warnings.simplefilter("ignore")
        _walk(ds, where, _codec(ds))


def _walk(ds: Dataset, where: str, codec: str) -> None:
    """:func:`check_dataset` of ``ds``, its text measured in bytes of ``codec`` (the declared character set's)."""
    for elem in ds:
        if elem.VR == "SQ":
            for i, item in enumerate(elem.value):
                _walk(item, f"{where}: {elem.keyword}[{i}]", codec)
            continue
        limit = MAX_BYTES.get(elem.VR)
        if limit is None or elem.value is None:
            continue
        values = elem.value if isinstance(elem.value, (list, tuple, MultiValue)) else [elem.value]
        for v in values:
            text = v.original_string if getattr(v, "original_string", None) is not None else v
            text = text.decode("latin-1") if isinstance(text, bytes) else str(text)
            parts = text.split("=") if elem.VR == "PN" else [text]
            if any(len(part.encode(codec, errors="replace")) > limit for part in parts):
                raise InputError(f"{where}: {elem.keyword or elem.tag} value {text[:40]!r} is longer than "
                                 f"{limit} bytes, the limit of VR {elem.VR}")
            if elem.VR == "UI" and text and not UID.fullmatch(text):
                raise InputError(f"{where}: {elem.keyword or elem.tag} {text[:70]!r} is not a DICOM UID")
