"""The VTK file formats: legacy ``.vtk`` and VTK XML PolyData ``.vtp``, read and written by our own code.

This is the format layer under :func:`lungdeform.io.meshfile.read_mesh` / :func:`lungdeform.io.meshfile.write_mesh`
(which dispatch here by suffix, add the path to every message and turn failures into
:class:`~lungdeform.errors.ReadError`); use those for checked input. The functions here raise
:class:`FormatError` (message without the path) for a malformed file.

- Legacy (``# vtk DataFile``): DATASET POLYDATA, ASCII or big-endian BINARY, the classic cell
  layout ``[k, i1..ik, …]`` and the VTK ≥ 5.1 OFFSETS/CONNECTIVITY layout, METADATA blocks skipped;
  POLYGONS are fanned, TRIANGLE_STRIPS unrolled (alternating winding), VERTICES/LINES ignored.
  DATASET UNSTRUCTURED_GRID is read through meshio (triangle, quad and polygon cells).
  Written: POLYDATA, BINARY, double points, triangles.
- XML PolyData (``<VTKFile type="PolyData">``): DataArray ``ascii``, inline ``binary`` (base64) and
  ``appended`` (raw or base64); UInt32 or UInt64 size headers; either byte order; uncompressed,
  zlib or lzma block compression; several Pieces; Polys and Strips. Written (:func:`vtp_bytes`, the
  one writer): one Piece, little endian, UInt64 headers, Int64 connectivity and offsets; inline
  base64 with Float64 points (a mesh file) or appended raw with Float32 points, point data and the
  frame's ``TimeValue`` (the frames of a ParaView series, :mod:`lungdeform.playback.export`).

Arrays: ``vertices : (n, 3) float64`` in the file's units and frame, ``faces : (m, 3) int64``.
"""

from __future__ import annotations

import base64
import contextlib
import io as _io
import lzma
import re
import struct
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import meshio
import numpy as np


class FormatError(Exception):
    """A malformed mesh file (raised by the VTK readers here and the other readers in
    :mod:`lungdeform.io.meshfile`); the message does not name the path (:func:`lungdeform.io.meshfile.read_mesh` adds it)."""


# =========================================================================== cell layouts
def _fan_offsets(connectivity: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Fan triangulation of polygons stored as flat connectivity and *end* offsets (VTK layout)."""
    connectivity = np.asarray(connectivity, dtype=np.int64)
    ends = np.asarray(offsets, dtype=np.int64)
    # bounds first: with offsets near +-2**63 the differences below wrap around, and np.repeat on
    # the wrapped counts corrupts memory (a segmentation fault)
    if len(ends) and (ends.min() < 0 or ends.max() > len(connectivity)):
        raise FormatError("polygon offsets are inconsistent with the connectivity array")
    starts = np.concatenate([[0], ends[:-1]])
    sizes = ends - starts
    if (sizes < 0).any():
        raise FormatError("polygon offsets are inconsistent with the connectivity array")
    n_tri = np.maximum(sizes - 2, 0)
    poly = np.repeat(np.arange(len(sizes)), n_tri)
    k = np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    s = starts[poly]
    return np.stack(
        [connectivity[s], connectivity[s + k + 1], connectivity[s + k + 2]], axis=1
    ) if len(poly) else np.zeros((0, 3), np.int64)


def _strips(connectivity: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Triangles of triangle strips (alternating winding), flat connectivity + end offsets."""
    tris = []
    start = 0
    for end in np.asarray(offsets, dtype=np.int64):
        s = connectivity[start:end]
        for k in range(len(s) - 2):
            tris.append((s[k], s[k + 1], s[k + 2]) if k % 2 == 0 else (s[k + 1], s[k], s[k + 2]))
        start = end
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


# =========================================================================== legacy VTK
_VTK_LEGACY_TYPES = {
    "bit": None, "unsigned_char": "u1", "char": "i1", "unsigned_short": "u2", "short": "i2",
    "unsigned_int": "u4", "int": "i4", "unsigned_long": "u8", "long": "i8", "float": "f4",
    "double": "f8", "vtktypeint64": "i8", "vtktypeuint64": "u8", "vtkidtype": "i8",
}


_VTK_SECTIONS = {"POINTS", "VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS", "POINT_DATA",
                 "CELL_DATA", "FIELD", "METADATA"}


class _Cursor:
    """Reads keyword lines and ASCII or big-endian binary blocks of a legacy VTK file."""

    def __init__(self, data: bytes, binary: bool):
        self.data, self.pos, self.binary = data, 0, binary

    def line(self) -> str | None:
        """The next non-blank line, stripped (None at the end); advances past it."""
        text, self.pos = self._next(self.pos)
        return text

    def peek(self) -> str | None:
        """The next non-blank line without advancing."""
        return self._next(self.pos)[0]

    def _next(self, pos: int) -> tuple[str | None, int]:
        while pos < len(self.data):
            end = self.data.find(b"\n", pos)
            end = len(self.data) if end < 0 else end
            text = self.data[pos:end].decode("ascii", errors="replace").strip()
            pos = end + 1
            if text:
                return text, pos
        return None, pos

    def numbers(self, count: int, vtk_type: str) -> np.ndarray:
        code = _VTK_LEGACY_TYPES.get(vtk_type.lower())
        if code is None:
            raise FormatError(f"unsupported data type '{vtk_type}'")
        if self.binary:
            dt = np.dtype(">" + code)
            nbytes = count * dt.itemsize
            if self.pos + nbytes > len(self.data):
                raise FormatError("truncated: binary block shorter than announced")
            arr = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
            self.pos += nbytes
            return arr.astype(dt.newbyteorder("="))
        tokens: list[bytes] = []
        while len(tokens) < count:
            if self.pos >= len(self.data):
                raise FormatError(f"truncated: expected {count} values, found {len(tokens)}")
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            tokens += self.data[self.pos:end].split()
            self.pos = end + 1
        return np.array(tokens[:count], dtype=np.float64 if code[0] == "f" else np.int64)


def read_vtk(path) -> tuple[np.ndarray, np.ndarray]:
    """Legacy VTK file ``path`` → ``(vertices (n, 3) float64, faces (m, 3) int64)``; see the module docstring."""
    p = Path(path)
    data = p.read_bytes()
    head = data[:1024].split(b"\n", 4)
    if not head[0].startswith(b"# vtk DataFile"):
        raise FormatError("not a legacy VTK file (no '# vtk DataFile' header)")
    if len(head) < 4:
        raise FormatError("truncated VTK header")
    mode = head[2].strip().upper()
    dataset = head[3].split()
    if mode not in (b"ASCII", b"BINARY"):
        raise FormatError("not a valid VTK file (third line must be ASCII or BINARY)")
    if len(dataset) < 2 or dataset[0].upper() != b"DATASET":
        raise FormatError("not a valid VTK file (fourth line must be DATASET ...)")
    kind = dataset[1].upper().decode()
    if kind == "UNSTRUCTURED_GRID":
        return _read_unstructured(p)
    if kind != "POLYDATA":
        raise FormatError(f"DATASET {kind} holds no surface (need POLYDATA or UNSTRUCTURED_GRID)")
    cur = _Cursor(data, mode == b"BINARY")
    cur.pos = sum(len(h) + 1 for h in head[:4])
    points = None
    faces = []
    while (line := cur.line()) is not None:
        tok = line.split()
        key = tok[0].upper()
        if key == "POINTS":
            n = int(tok[1])
            points = cur.numbers(3 * n, tok[2]).reshape(-1, 3)
        elif key == "METADATA":  # ASCII information block: skip to the next section keyword
            while (nxt := cur.peek()) is not None and nxt.split()[0].upper() not in _VTK_SECTIONS:
                cur.line()
        elif key in ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"):
            n1, n2 = int(tok[1]), int(tok[2])
            nxt = cur.peek()
            if nxt is not None and nxt.split()[0].upper() == "OFFSETS":  # VTK >= 5.1 layout
                cur.line()
                offsets = cur.numbers(n1, nxt.split()[1]).astype(np.int64)
                conn_head = cur.line() or ""
                if not conn_head.upper().startswith("CONNECTIVITY"):
                    raise FormatError(f"{key}: OFFSETS without CONNECTIVITY")
                conn = cur.numbers(n2, conn_head.split()[1]).astype(np.int64)
                ends = offsets[1:]
            else:
                flat = cur.numbers(n2, "int").astype(np.int64)
                conn, ends = _split_classic_cells(flat, n1)
            if key == "POLYGONS":
                faces.append(_fan_offsets(conn, ends))
            elif key == "TRIANGLE_STRIPS":
                faces.append(_strips(conn, ends))
        elif key in ("POINT_DATA", "CELL_DATA", "FIELD"):
            break
    if points is None:
        raise FormatError("no POINTS section")
    if not faces:
        raise FormatError("no triangles in the file (no POLYGONS or TRIANGLE_STRIPS)")
    return points, np.vstack(faces)


def _split_classic_cells(flat: np.ndarray, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """``[k, i1..ik, k, ...]`` -> (connectivity, end offsets)."""
    if len(flat) and (flat[0] == 3).all() and len(flat) == 4 * n_cells and (flat[::4] == 3).all():
        cells = flat.reshape(-1, 4)[:, 1:]
        return cells.ravel(), np.arange(1, n_cells + 1) * 3
    conn, ends, pos = [], [], 0
    for _ in range(n_cells):
        if pos >= len(flat):
            raise FormatError("truncated cell list")
        k = int(flat[pos])
        conn.append(flat[pos + 1 : pos + 1 + k])
        ends.append((ends[-1] if ends else 0) + k)
        pos += k + 1
    return np.concatenate(conn) if conn else np.zeros(0, np.int64), np.array(ends, dtype=np.int64)


def _read_unstructured(p: Path):
    sink = _io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        m = meshio.vtk.read(str(p))  # the format reader itself: meshio.read() calls sys.exit
    faces = []
    for block in m.cells:
        if block.type in ("triangle", "quad", "polygon"):
            data = np.asarray(block.data, dtype=np.int64)
            faces.append(_fan_offsets(data.ravel(), np.arange(1, len(data) + 1) * data.shape[1])
                         if data.shape[1] > 3 else data)
    if not faces:
        raise FormatError("no triangles in the unstructured grid (no triangle/quad/polygon cells)")
    return np.asarray(m.points, dtype=np.float64), np.vstack(faces)


def vtk_bytes(v: np.ndarray, f: np.ndarray) -> bytes:
    """Legacy VTK POLYDATA, BINARY: ``v : (n, 3) float`` (written as big-endian double), ``f : (m, 3) int``."""
    head = (
        "# vtk DataFile Version 3.0\nsurface written by lungdeform\nBINARY\nDATASET POLYDATA\n"
        f"POINTS {len(v)} double\n"
    ).encode()
    cells = np.hstack([np.full((len(f), 1), 3), f]).astype(">i4")
    return (head + v.astype(">f8").tobytes() + f"\nPOLYGONS {len(f)} {4 * len(f)}\n".encode()
            + cells.tobytes() + b"\n")


# =========================================================================== VTK XML PolyData
_VTK_XML_TYPES = {
    "Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
    "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8",
}


def read_vtp(path) -> tuple[np.ndarray, np.ndarray]:
    """VTK XML PolyData file ``path`` → ``(vertices (n, 3) float64, faces (m, 3) int64)``; see the module docstring."""

    p = Path(path)
    data = p.read_bytes()
    appended = b""
    encoding = "raw"
    start = data.find(b"<AppendedData")
    if start >= 0:
        tag_end = data.find(b">", start)
        m = re.search(rb'encoding\s*=\s*"(\w+)"', data[start:tag_end])
        encoding = m.group(1).decode() if m else "raw"
        underscore = data.find(b"_", tag_end)
        stop = data.rfind(b"</AppendedData>")
        if underscore < 0 or stop < underscore:
            raise FormatError("truncated: <AppendedData> is not closed")
        appended = data[underscore + 1 : stop]
        xml_text = data[:start] + b"</VTKFile>"
    else:
        xml_text = data
    try:
        root = ET.fromstring(xml_text)
    except ET.ParseError as exc:
        raise FormatError(f"truncated or not a VTK XML file (XML error: {exc})") from None
    if root.tag != "VTKFile" or root.get("type") != "PolyData":
        raise FormatError(f"not a VTK XML PolyData file (root <{root.tag} type={root.get('type')!r}>)")
    ctx = {
        "order": "<" if root.get("byte_order", "LittleEndian") == "LittleEndian" else ">",
        "header": _VTK_XML_TYPES[root.get("header_type", "UInt32")],
        "compressor": root.get("compressor"),
        "appended": appended,
        "encoding": encoding,
        "offsets": sorted({int(e.get("offset")) for e in root.iter("DataArray") if e.get("format") == "appended"}),
    }
    pieces = root.findall("./PolyData/Piece")
    if not pieces:
        raise FormatError("no <PolyData><Piece> element")
    all_v, all_f, base = [], [], 0
    for piece in pieces:
        pts_el = piece.find("./Points/DataArray")
        if pts_el is None:
            raise FormatError("a <Piece> has no <Points>")
        n_pts = int(piece.get("NumberOfPoints", "0"))
        pts = _vtp_array(pts_el, ctx).astype(np.float64)
        if pts.size != 3 * n_pts:
            raise FormatError(f"Points has {pts.size} values, expected 3 x {n_pts}")
        pts = pts.reshape(-1, 3)
        for section, fn in (("Polys", _fan_offsets), ("Strips", _strips)):
            el = piece.find(section)
            if el is None or int(piece.get(f"NumberOf{section}", "1")) == 0:
                continue
            arrays = {a.get("Name"): a for a in el.findall("DataArray")}
            if "connectivity" not in arrays or "offsets" not in arrays:
                raise FormatError(f"<{section}> needs 'connectivity' and 'offsets' arrays")
            conn = _vtp_array(arrays["connectivity"], ctx).astype(np.int64)
            offs = _vtp_array(arrays["offsets"], ctx).astype(np.int64)
            all_f.append(fn(conn, offs) + base)
        all_v.append(pts)
        base += len(pts)
    if not all_f:
        raise FormatError("no triangles in the file (no <Polys> or <Strips>)")
    return np.vstack(all_v), np.vstack(all_f)


def _vtp_array(el, ctx) -> np.ndarray:
    vtype = el.get("type")
    if vtype not in _VTK_XML_TYPES:
        raise FormatError(f"DataArray '{el.get('Name')}' has unsupported type {vtype!r}")
    dtype = np.dtype(ctx["order"] + _VTK_XML_TYPES[vtype])
    fmt = el.get("format", "ascii")
    if fmt == "ascii":
        text = (el.text or "").split()
        return np.array(text, dtype=np.float64 if dtype.kind == "f" else np.int64)
    if fmt == "binary":
        return _decode_binary((el.text or "").strip().encode(), dtype, ctx, base64_encoded=True)
    if fmt == "appended":
        off = int(el.get("offset"))
        blob = ctx["appended"]
        if ctx["encoding"] == "base64":
            later = [o for o in ctx["offsets"] if o > off]
            chunk = blob[off : later[0] if later else len(blob)].strip()
            return _decode_binary(chunk, dtype, ctx, base64_encoded=True)
        return _decode_binary(blob[off:], dtype, ctx, base64_encoded=False)
    raise FormatError(f"DataArray format {fmt!r} is not ascii, binary or appended")


def _b64(chars: bytes) -> bytes:
    try:
        return base64.b64decode(chars, validate=False)
    except (ValueError, base64.binascii.Error):
        raise FormatError("corrupt base64 data") from None


def _decode_binary(blob: bytes, dtype: np.dtype, ctx, *, base64_encoded: bool) -> np.ndarray:
    """One binary DataArray: a size header (UInt32/UInt64) then data, optionally compressed.

    Uncompressed: ``[nbytes][data]``. Compressed: ``[nblocks, blocksize, lastsize, c1..cn]``
    then the compressed blocks. In base64 the header may be encoded on its own (always so when
    compressed) or together with the data; both are accepted.
    """
    htype = np.dtype(ctx["order"] + ctx["header"])
    hsize = htype.itemsize

    def chars(nbytes):  # base64 characters for nbytes bytes
        return 4 * ((nbytes + 2) // 3)

    if ctx["compressor"] is None:
        if base64_encoded:
            first = blob[: chars(hsize)]
            if first.endswith(b"="):  # header encoded separately
                nbytes = int(np.frombuffer(_b64(first)[:hsize], htype)[0])
                raw = _b64(blob[chars(hsize):])
            else:
                joined = _b64(blob)
                nbytes = int(np.frombuffer(joined[:hsize], htype)[0])
                raw = joined[hsize:]
        else:
            if len(blob) < hsize:
                raise FormatError("truncated appended data")
            nbytes = int(np.frombuffer(blob[:hsize], htype)[0])
            raw = blob[hsize : hsize + nbytes]
        if len(raw) < nbytes:
            raise FormatError(f"truncated binary DataArray ({len(raw)} of {nbytes} bytes)")
        return np.frombuffer(raw[:nbytes], dtype=dtype).astype(dtype.newbyteorder("="))
    # compressed
    comp = ctx["compressor"]
    if comp == "vtkZLibDataCompressor":
        decompress = zlib.decompress
    elif comp == "vtkLZMADataCompressor":
        decompress = lzma.decompress
    else:
        raise FormatError(f"unsupported compressor {comp} (zlib and lzma are supported)")
    if base64_encoded:
        nblocks = int(np.frombuffer(_b64(blob[: chars(hsize)])[:hsize], htype)[0])
        hchars = chars(hsize * (3 + nblocks))
        header = np.frombuffer(_b64(blob[:hchars])[: hsize * (3 + nblocks)], htype)
        body = _b64(blob[hchars:])
    else:
        nblocks = int(np.frombuffer(blob[:hsize], htype)[0])
        header = np.frombuffer(blob[: hsize * (3 + nblocks)], htype)
        body = blob[hsize * (3 + nblocks):]
    sizes = header[3:].astype(np.int64)
    if sizes.sum() > len(body):
        raise FormatError("truncated compressed DataArray")
    out, pos = [], 0
    for s in sizes:
        try:
            out.append(decompress(body[pos : pos + s]))
        except Exception:
            raise FormatError("corrupt compressed DataArray") from None
        pos += s
    return np.frombuffer(b"".join(out), dtype=dtype).astype(dtype.newbyteorder("="))


#: VTK XML type name of each numpy type code (kind and size), the inverse of ``_VTK_XML_TYPES``.
_VTK_XML_NAMES = {code: name for name, code in _VTK_XML_TYPES.items()}


class _ArrayWriter:
    """DataArray elements of one VTK XML file, little endian, UInt64 size headers: inline base64
    (``format="binary"``) or raw blocks for the file's ``<AppendedData>`` (``format="appended"``)."""

    def __init__(self, appended: bool):
        self.appended, self.blocks, self.offset = appended, [], 0

    def element(self, name: str, a: np.ndarray) -> str:
        """The ``<DataArray>`` of ``a`` ((n,) one component or (n, c) c components), in its own type."""
        a = np.ascontiguousarray(a)
        raw = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        block = struct.pack("<Q", len(raw)) + raw
        head = (f'<DataArray type="{_VTK_XML_NAMES[a.dtype.kind + str(a.dtype.itemsize)]}" Name="{name}" '
                f'NumberOfComponents="{1 if a.ndim == 1 else a.shape[1]}" ')
        if not self.appended:
            return head + f'format="binary">{base64.b64encode(block).decode()}</DataArray>'
        self.blocks.append(block)
        self.offset += len(block)
        return head + f'format="appended" offset="{self.offset - len(block)}"/>'


def vtp_bytes(vertices: np.ndarray, faces: np.ndarray, point_data: dict[str, np.ndarray] | None = None, *,
              time_s: float | None = None, appended: bool = False, points_dtype=np.float64) -> bytes:
    """VTK XML PolyData of one triangle Piece, little endian, UInt64 size headers.

    vertices : (n, 3) float, written as ``points_dtype`` (Float64 by default; Float32 halves the
    bytes of a time-series frame); faces : (m, 3) int, written as Int64 connectivity and offsets;
    point_data : name -> (n,) or (n, c) array, written in its own type (``<PointData>``);
    time_s : float, s, written as the Float64 field ``TimeValue`` (``<FieldData>``) that ParaView
    reads as the frame's time. ``appended``: the arrays go raw into one ``<AppendedData>`` block (the
    frames of :func:`lungdeform.playback.export.export_pvd`) instead of inline base64, one element per
    line (what :func:`lungdeform.io.meshfile.write_mesh` writes for ``.vtp``).
    """
    w = _ArrayWriter(appended)
    sep = "" if appended else "\n"
    field = ("" if time_s is None
             else f"<FieldData>{w.element('TimeValue', np.array([time_s], np.float64))}</FieldData>")
    pts = w.element("Points", np.asarray(vertices).astype(points_dtype))
    pd = "".join(w.element(k, v) for k, v in (point_data or {}).items())
    conn = w.element("connectivity", np.asarray(faces).astype(np.int64).reshape(-1))
    offs = w.element("offsets", np.arange(3, 3 * len(faces) + 1, 3, dtype=np.int64))
    body = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
        f'<PolyData>{field}<Piece NumberOfPoints="{len(vertices)}" NumberOfVerts="0" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{len(faces)}">{sep}'
        + (f"<PointData>{pd}</PointData>{sep}" if pd else "")
        + f"<Points>{pts}</Points>{sep}<Polys>{conn}{offs}</Polys>{sep}</Piece></PolyData>\n"
    ).encode()
    if not appended:
        return body + b"</VTKFile>\n"
    return body + b'<AppendedData encoding="raw">\n_' + b"".join(w.blocks) + b"\n</AppendedData>\n</VTKFile>\n"
