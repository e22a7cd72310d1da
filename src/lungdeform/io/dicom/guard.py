"""A guard on DICOM bytes: damaged element headers refused before GDCM parses the file.

:func:`is_dicom_file` tells a DICOM file by its name or its preamble; :func:`check_dicom_file`
walks a file's element headers (PS3.5 7.1, 7.5) and refuses, with a
:class:`~lungdeform.errors.ReadError` naming the file and element, what would make GDCM take
seconds and gigabytes or corrupt its heap (tests/fuzz/fuzz_image_dicom.py feeds it damaged files). Every DICOM
reader of lungdeform calls it on each file before any other library opens it.
"""

from __future__ import annotations

import struct
from pathlib import Path

from lungdeform.errors import ReadError

#: DICOM value representations whose explicit-VR element header holds a 4-byte length (PS3.5 7.1.2)
_LONG_VRS = frozenset((b"OB", b"OW", b"OF", b"OD", b"OL", b"OV", b"SQ", b"UC", b"UR", b"UT", b"UN", b"SV", b"UV"))
#: every value representation of PS3.5 Table 6.2-1
_VRS = _LONG_VRS | frozenset(v.encode() for v in (
    "AE AS AT CS DA DS DT FL FD IS LO LT PN SH SL SS ST TM UI UL US").split())
_IMPLICIT_LE, _BIG_ENDIAN, _DEFLATED = b"1.2.840.10008.1.2", b"1.2.840.10008.1.2.2", b"1.2.840.10008.1.2.1.99"


def is_dicom_file(path) -> bool:
    """True for a file named ``*.dcm``/``*.ima`` or holding the DICOM preamble (``DICM`` at byte 128)."""
    p = Path(path)
    if not p.is_file():
        return False
    if p.name.lower().endswith((".dcm", ".ima", ".dicom")):
        return True
    try:
        with open(p, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return len(head) == 132 and head[128:132] == b"DICM"



def _element_header(h: bytes, explicit: bool) -> tuple[int, int, bytes, int, int]:
    """``(group, element, VR, value length, header bytes)`` of the little-endian element header ``h``
    (12 bytes, fewer at the end of a file); VR ``b""`` when implicit or an item/delimiter tag."""
    group, elem = struct.unpack("<HH", h[:4])
    if group == 0xFFFE or not (explicit or group == 2):  # items and delimiters; implicit VR
        return group, elem, b"", struct.unpack("<I", h[4:8])[0], 8
    vr = h[4:6]
    if vr in _LONG_VRS:
        return group, elem, vr, (struct.unpack("<I", h[8:12])[0] if len(h) == 12 else 0xFFFFFFFE), 12
    return group, elem, vr, struct.unpack("<H", h[6:8])[0], 8


def check_dicom_file(path) -> None:
    """Refuse, before GDCM parses it, a DICOM file whose element headers are damaged: an explicit value
    representation that is none of the standard's (PS3.5 Table 6.2-1), or a value length larger than
    what is left of the file. GDCM tries to make sense of such a file and allocates what a length read
    from the wrong bytes says (seconds and gigabytes for a file of a few hundred bytes).

    Walks the element headers only (sequences and items flatly, PS3.5 7.5), up to the pixel data:
    after the ``DICM`` preamble, from byte 132, the file meta information (group 0002) first (PS3.10
    7.1); without it, from byte 0, as explicit VR when a standard VR sits at bytes 4–5, else as implicit
    VR little endian (the default transfer syntax), starting with group 0002 or a data set group (0008
    or above). Big-endian or deflated data sets and sequences of unknown content (UN, undefined length)
    are left to GDCM. tests/fuzz/fuzz_image_dicom.py feeds it damaged files."""
    p = Path(path)
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(132)
        if len(head) < 8:
            return
        if head[128:132] == b"DICM":
            pos, explicit = 132, True
        else:  # no preamble: an explicit-VR element first, else implicit VR (GDCM reads both)
            pos, explicit = 0, head[4:6] in _VRS
        syntax, guessed = None, not explicit and pos == 0  # implicit without preamble: maybe no DICOM at all
        pixel, nested = {}, False  # the image pixel module's numbers (0028,xxxx); inside a sequence yet?
        while pos + 8 <= size:
            fh.seek(pos)
            h = fh.read(12)
            group, elem, vr, length, hdr = _element_header(h, explicit)
            where = (f"{p} is not a readable DICOM image slice: no preamble, and read as implicit VR its element "
                     f"({group:04X},{elem:04X}) at byte {pos}" if guessed else
                     f"{p}: damaged DICOM file: element ({group:04X},{elem:04X}) at byte {pos}")
            if pos == 132 and group != 0x0002:  # PS3.10 7.1: the file meta information follows "DICM"
                raise ReadError(f"{where}: the file meta information (group 0002) must follow the preamble")
            if pos == 0 and group != 0x0002 and group < 0x0008:  # groups 0000-0007 are no file's first
                raise ReadError(f"{p} is not a readable DICOM image slice: no preamble, and its first element "
                                f"({group:04X},{elem:04X}) is neither file meta information (group 0002) nor a "
                                "data set element (group 0008 or above)")
            if vr and vr not in _VRS:
                raise ReadError(f"{where} has no valid value representation ({vr!r})")
            if length == 0xFFFFFFFF:  # undefined length: a sequence or encapsulated pixels, walked into
                if vr == b"UN" or (group, elem) == (0x7FE0, 0x0010):
                    return
                pos += hdr
                continue
            if pos + hdr + length > size:
                raise ReadError(f"{where} claims {length} bytes, {size - pos - hdr} are left")
            if (group, elem) == (0x0002, 0x0010):
                fh.seek(pos + hdr)
                syntax = fh.read(length).rstrip(b"\0 ")
            if group != 2 and syntax in (_BIG_ENDIAN, _DEFLATED):
                return
            if group == 0x0028 and elem in _PIXEL_TAGS and length == 2 and (group, elem) not in pixel:
                fh.seek(pos + hdr)
                pixel[(group, elem)] = struct.unpack("<H", fh.read(2))[0]
                _check_pixel_module(pixel, where)
            if (group, elem) == (0x7FE0, 0x0010):
                if not nested:
                    _check_pixel_length(pixel, length, where)
                return
            nested = nested or vr == b"SQ" or group == 0xFFFE
            if syntax is not None:
                explicit = syntax != _IMPLICIT_LE
            pos += hdr if vr == b"SQ" or group == 0xFFFE else hdr + length  # into sequences and items


#: (0028,0002) SamplesPerPixel, (0028,0010) Rows, (0028,0011) Columns, (0028,0100) BitsAllocated,
#: (0028,0101) BitsStored: the numbers that size the pixel data (PS3.3 C.7.6.3).
_PIXEL_TAGS = (0x0002, 0x0010, 0x0011, 0x0100, 0x0101)


def _check_pixel_module(pixel: dict, where: str) -> None:
    """ReadError (``where`` names the file and element) for BitsAllocated other than 1 or a multiple
    of 8 up to 64 (PS3.5 8.1.1), or BitsStored outside 1…BitsAllocated: GDCM sizes its buffers from
    them, and other values over the pixel data can overrun the heap and kill the process."""
    ba, bs = pixel.get((0x0028, 0x0100)), pixel.get((0x0028, 0x0101))
    if ba is not None and not (ba == 1 or (ba % 8 == 0 and 8 <= ba <= 64)):
        raise ReadError(f"{where}: BitsAllocated is {ba}, not 1 or a multiple of 8 up to 64")
    if ba is not None and bs is not None and not 1 <= bs <= ba:
        raise ReadError(f"{where}: BitsStored is {bs}, not 1…{ba} (BitsAllocated)")


def _check_pixel_length(pixel: dict, length: int, where: str) -> None:
    """ReadError when native pixel data of ``length`` bytes is shorter than one frame of Rows ×
    Columns × SamplesPerPixel × BitsAllocated (when all of them were read)."""
    rows, cols, ba = (pixel.get((0x0028, e)) for e in (0x0010, 0x0011, 0x0100))
    if rows is None or cols is None or ba is None:
        return
    need = (rows * cols * pixel.get((0x0028, 0x0002), 1) * ba + 7) // 8
    if length < need:
        raise ReadError(f"{where} holds {length} bytes of pixel data, and one frame of {rows} × {cols} "
                        f"at {ba} bits needs {need}")


