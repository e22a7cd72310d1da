"""A 4-D CT folder written from a text table, for the fourdct_folder fuzz harness.

The fuzzed input is the table, not DICOM bytes: its first line names DICOM tags (``gggg,eeee``)
after a ``file`` column, and every further line is one slice file (a path under the folder) with
the values of those tags. Mutating the text changes the tags the phase sorter reads (positions,
orientation, UIDs, phase tags) in one slice, or in all of them through the header line; a line
deleted or repeated is a slice missing or repeated. :func:`write_folder` writes the table as one
explicit-VR little-endian DICOM file per line (6 × 5 int16 voxels each, the pixel module fixed),
so that every table, however mutated, becomes a folder that
:func:`lungdeform.io.dicom.fourdct.read_phases` must read or refuse with the package's own errors.
"""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

#: Value representations of the tags a table may name; any other tag is written as UN.
VRS = {(0x0008, 0x0016): "UI", (0x0008, 0x0018): "UI", (0x0008, 0x0032): "TM", (0x0008, 0x0060): "CS",
       (0x0008, 0x103E): "LO", (0x0010, 0x0020): "LO", (0x0018, 0x0050): "DS", (0x0018, 0x1060): "DS",
       (0x0018, 0x1120): "DS", (0x0020, 0x000D): "UI", (0x0020, 0x000E): "UI", (0x0020, 0x0013): "IS",
       (0x0020, 0x0032): "DS", (0x0020, 0x0037): "DS", (0x0020, 0x0052): "UI", (0x0020, 0x0100): "IS",
       (0x0020, 0x9128): "UL", (0x0028, 0x0030): "DS"}
_LONG = {"OB", "OW", "UN", "UT", "SQ"}
MAX_ROWS, MAX_VALUE = 48, 64
ROWS, COLUMNS = 5, 6
_STUDY = "1.2.826.0.1.3680043.2.1125.11"


def _element(group: int, elem: int, vr: str, value: bytes) -> bytes:
    """One explicit-VR little-endian element (value padded to an even length)."""
    if len(value) % 2:
        value += b"\0" if vr in ("UI", "OB", "UN") else b" "
    if vr in _LONG:
        return struct.pack("<HH2sHI", group, elem, vr.encode(), 0, len(value)) + value
    return struct.pack("<HH2sH", group, elem, vr.encode(), len(value)) + value


def _value(vr: str, text: bytes) -> bytes:
    """A table value as the element's bytes: UL packed when it is a whole number in range, else as is."""
    if vr == "UL":
        try:
            n = int(text)
            if 0 <= n < 2 ** 32:
                return struct.pack("<I", n)
        except ValueError:
            pass
    return text


def slice_bytes(tags: dict[tuple[int, int], bytes], index: int) -> bytes:
    """The bytes of one slice file: preamble, file meta information, ``tags`` and the pixel module."""
    sop = f"{_STUDY}.9.{index + 1}".encode()
    base = {(0x0008, 0x0016): b"1.2.840.10008.5.1.4.1.1.2", (0x0008, 0x0018): sop, (0x0008, 0x0060): b"CT",
            (0x0028, 0x0030): b"0.8\\0.8"}
    data = {**base, **{t: v for t, v in tags.items() if t[0] >= 0x0008 and t[0] not in (0x0028, 0x7FE0)},
            (0x0028, 0x0030): tags.get((0x0028, 0x0030), base[(0x0028, 0x0030)])}
    pixel = {(0x0028, 0x0002): struct.pack("<H", 1), (0x0028, 0x0004): b"MONOCHROME2",
             (0x0028, 0x0010): struct.pack("<H", ROWS), (0x0028, 0x0011): struct.pack("<H", COLUMNS),
             (0x0028, 0x0100): struct.pack("<H", 16), (0x0028, 0x0101): struct.pack("<H", 16),
             (0x0028, 0x0102): struct.pack("<H", 15), (0x0028, 0x0103): struct.pack("<H", 1)}
    pixel_vrs = {0x0004: "CS", 0x0030: "DS"}
    body = b""
    for (g, e), v in sorted({**data, **pixel}.items()):
        vr = pixel_vrs.get(e, "US") if g == 0x0028 else VRS.get((g, e), "UN")
        body += _element(g, e, vr, _value(vr, v))
    voxels = struct.pack(f"<{ROWS * COLUMNS}h", *[(-1000 + 10 * k + 7 * index) for k in range(ROWS * COLUMNS)])
    body += _element(0x7FE0, 0x0010, "OW", voxels)
    meta = (_element(0x0002, 0x0001, "OB", b"\0\1") + _element(0x0002, 0x0002, "UI", base[(0x0008, 0x0016)])
            + _element(0x0002, 0x0003, "UI", sop) + _element(0x0002, 0x0010, "UI", b"1.2.840.10008.1.2.1"))
    meta = _element(0x0002, 0x0000, "UL", struct.pack("<I", len(meta))) + meta
    return b"\0" * 128 + b"DICM" + meta + body


def _name(raw: bytes, row: int) -> str:
    """A safe relative file name from a table cell: at most two parts of ``[A-Za-z0-9_.-]``, no ``..``."""
    text = raw.decode("ascii", errors="replace").strip()
    parts = [p for p in text.split("/") if p]
    if not parts or len(parts) > 2 or any(not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", p) or p in (".", "..")
                                          for p in parts):
        return f"x{row:03d}.dcm"
    return "/".join(parts)


def write_folder(table: bytes, folder: Path) -> int:
    """Write the slices of ``table`` (module docstring) into ``folder`` (emptied first); the number
    of files written (a file whose path clashes with another's is left out)."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    lines = table.split(b"\n")
    header = lines[0].split(b"|")[1:]
    tags = []
    for cell in header:
        m = re.fullmatch(rb"\s*([0-9A-Fa-f]{4}),([0-9A-Fa-f]{4})\s*", cell)
        tags.append(None if m is None else (int(m.group(1), 16), int(m.group(2), 16)))
    written = 0
    for row, line in enumerate(lines[1:MAX_ROWS + 1]):
        if not line.strip():
            continue
        cells = line.split(b"|")
        values = {t: v.strip()[:MAX_VALUE] for t, v in zip(tags, cells[1:]) if t is not None}
        path = folder / _name(cells[0], row)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(slice_bytes(values, row))
            written += 1
        except OSError:  # a path that clashes with a folder or file written before
            continue
    return written


#: The tags of the seed tables.
SEED_TAGS = ("0010,0020", "0020,000D", "0020,0052", "0020,000E", "0008,103E", "0020,9128", "0008,0032",
             "0020,0032", "0020,0037", "0018,1120", "0020,0013")


def seed_tables() -> list[bytes]:
    """Two valid 4-D CTs of 3 phases × 3 slices: a series per phase in subfolders (told apart by
    SeriesDescription percentages), and one series repeating its positions per phase (told apart by
    TemporalPositionIndex)."""
    tables = []
    for split in (False, True):
        rows = ["file|" + "|".join(SEED_TAGS)]
        for phase in range(3):
            for n in range(3):
                series = f"{_STUDY}.1" if split else f"{_STUDY}.1.{phase + 1}"
                name = f"s{phase}_{n}.dcm" if split else f"p{phase}/s{n}.dcm"
                rows.append("|".join([name, "PAT11", _STUDY, f"{_STUDY}.4", series,
                                      "4D CT" if split else f"CT {10 * phase}%", str(phase + 1),
                                      f"10{phase}5{n}0.5", f"-2.0\\-1.6\\{2.5 * n - 2.5}", "1\\0\\0\\0\\1\\0", "0",
                                      str(3 * phase + n + 1)]))
        tables.append(("\n".join(rows) + "\n").encode())
    return tables
