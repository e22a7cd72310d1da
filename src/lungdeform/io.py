"""Surfaces in and out: mesh files, and the dispatcher from a file (mesh or mask image) to surfaces.

Readers return raw indexed triangles; :func:`load_surface` adds unit conversion and
:func:`lungdeform.mesh.check_surface`. Every failure is a :class:`~lungdeform.errors.ReadError`
whose message starts with the path and says what is wrong; library exceptions are wrapped.

Formats (by suffix, case-insensitive):

===========  =================================  ===================================================
suffix       read                               write
===========  =================================  ===================================================
.stl         binary and ASCII (own); triangle   binary (own)
             soup is merged into indexed faces
.obj         own (``v``/``f`` records; polygons  own
             fanned; negative indices)
.ply         trimesh (ASCII/binary)             binary little-endian (own)
.vtk         legacy POLYDATA (own, ASCII and    legacy POLYDATA, binary (own)
             binary, classic and 5.x layouts);
             UNSTRUCTURED_GRID via meshio
.vtp         VTK XML PolyData (own): ascii,     inline base64 binary (own)
             inline base64 (zlib/lzma or not),
             appended raw/base64
.off         own                                own
.gltf .glb   trimesh: every triangle primitive  —
             of the default scene, node
             transforms applied; seams merged
===========  =================================  ===================================================
"""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import re
import struct
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

from .atomic import write_bytes
from .errors import InputError, LungdeformError, ReadError
from .mesh import Surface, SurfaceReport, check_surface

MESH_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".off", ".gltf", ".glb")
WRITE_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".off")
#: millimetres per unit
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


class _FormatError(Exception):
    """Raised inside a reader; :func:`read_mesh` prefixes the path and turns it into ReadError."""


# =========================================================================== public API
def read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh file.

    Returns ``vertices : (n, 3) float64`` in the file's units and frame, and
    ``faces : (m, 3) int64``; polygons are triangulated as fans. Nothing is checked beyond
    well-formedness (use :func:`load_surface` for that). Raises :class:`ReadError` starting with
    the path: missing, empty or truncated file, unknown format, not a mesh, no triangles.
    """
    p = Path(path)
    if not p.exists():
        raise ReadError(f"{p}: no such file")
    if p.is_dir():
        raise ReadError(f"{p}: is a directory, not a mesh file")
    suffix = p.suffix.lower()
    reader = _READERS.get(suffix)
    if reader is None:
        raise ReadError(
            f"{p}: unknown mesh format '{suffix or p.name}' (supported: {', '.join(MESH_SUFFIXES)})"
        )
    if p.stat().st_size == 0:
        raise ReadError(f"{p}: file is empty")
    try:
        vertices, faces = reader(p)
    except _FormatError as exc:
        raise ReadError(f"{p}: {exc}") from None
    except LungdeformError as exc:
        raise ReadError(f"{p}: {exc}") from exc
    except MemoryError as exc:
        raise ReadError(f"{p}: not a valid {suffix[1:].upper()} file (sizes in it are absurd)") from exc
    except Exception as exc:  # any library failure becomes one clear line
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ReadError(f"{p}: not a valid {suffix[1:].upper()} mesh ({detail})") from exc
    vertices = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64).reshape(-1, 3))
    faces = np.ascontiguousarray(np.asarray(faces).reshape(-1, 3).astype(np.int64))
    if len(faces) == 0:
        raise ReadError(f"{p}: no triangles in the file (points or lines only?)")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ReadError(f"{p}: faces index vertices outside 0..{len(vertices) - 1}")
    return vertices, faces


def load_surface(
    path, *, units: str = "mm", repair: bool = False, name: str | None = None
) -> tuple[Surface, SurfaceReport]:
    """Read a mesh file, convert it to millimetres and check it with :func:`check_surface`.

    ``units`` is the unit of the file's coordinates (``"mm"``, ``"cm"`` or ``"m"``); a
    conversion is reported as a repair line (``"scaled from m to mm"``). The frame is taken as
    LPS world as stored (meshes carry no frame information). A surface not in millimetres is
    refused by :class:`~lungdeform.errors.UnitsError`; open, non-manifold or NaN surfaces by
    :class:`~lungdeform.errors.MeshError`, both naming the file. ``repair`` is passed on to
    :func:`check_surface` (drops extra components, flips inward orientation, ...).
    """
    factor = _unit_factor(units)
    vertices, faces = read_mesh(path)
    notes: list[str] = []
    if factor != 1.0:
        vertices = vertices * factor
        notes.append(f"scaled from {units} to mm")
    v, f, report = check_surface(vertices, faces, source=str(path), repair=repair)
    report = dataclasses.replace(report, repairs=tuple(notes) + report.repairs)
    return Surface(v, f, name or Path(path).name), report


def write_mesh(path, vertices, faces) -> Path:
    """Write a triangle mesh by suffix, atomically (temp file in the same folder, then rename).

    ``vertices : (n, 3) float`` (written as float32 in STL, float64 elsewhere),
    ``faces : (m, 3) int``. Formats: binary STL, OBJ, binary PLY, legacy binary VTK POLYDATA,
    VTK XML PolyData (inline base64) and OFF. Returns the path.
    """
    from .mesh import as_faces, as_vertices

    p = Path(path)
    suffix = p.suffix.lower()
    writer = _WRITERS.get(suffix)
    if writer is None:
        raise InputError(f"{p}: cannot write '{suffix}' (supported: {', '.join(WRITE_SUFFIXES)})")
    v = as_vertices(vertices)
    f = as_faces(faces, len(v))
    data = writer(v, f)
    write_bytes(p, data)
    return p


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def load(
    path,
    *,
    labels=None,
    units: str = "mm",
    repair: bool = False,
    smooth_iterations: int = 10,
    target_vertices: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[tuple[Surface, SurfaceReport]]:
    """Surfaces from one input of ``lungdeform build``: a mesh file or a mask/label image.

    - A mesh file (:data:`MESH_SUFFIXES`) gives one surface (:func:`load_surface`); ``labels``
      must be None; ``target_vertices`` is not applied to mesh files (they are used as given).
    - A mask or label image (NIfTI, MHA/MHD, NRRD, or a DICOM series directory) gives one surface
      per label group (see :func:`lungdeform.mask.label_groups`: None = all non-zero voxels,
      ``"left,right"``, ``"1,2"``, ``{"left": (1, 2)}``), by :func:`lungdeform.mask.extract_surface`.
      What the mask pipeline did (components dropped, cavities filled, smoothing, decimation) is
      listed in the report's ``repairs``. Image spacing is already in mm, so ``units`` must be "mm".

    Each surface passed :func:`check_surface` (messages start with the path). ``repair`` applies
    to mesh files; surfaces made from masks are closed, manifold and outward by construction.
    """
    from . import mask as _mask

    p = Path(path)
    if _is_mesh_path(p):
        if labels is not None:
            raise InputError(f"{p}: labels select parts of a mask image; this is a mesh file")
        if progress:
            progress(f"reading {p}")
        return [load_surface(p, units=units, repair=repair)]
    if not _mask.is_image_path(p):
        if not p.exists():
            raise ReadError(f"{p}: no such file or directory")
        raise ReadError(
            f"{p}: unknown format (meshes: {', '.join(MESH_SUFFIXES)}; images: "
            f"{', '.join(_mask.IMAGE_SUFFIXES)} or a DICOM directory)"
        )
    if _unit_factor(units) != 1.0:
        raise InputError(f"{p}: units={units!r} applies to mesh files; image spacing is in mm already")
    groups = _mask.label_groups(labels)
    if progress:
        progress(f"reading {p}")
    image = _mask.read_image(p)
    out = []
    for group, values in groups.items():
        if progress:
            progress(f"{p}: surface of {group or 'all labels'}")
        name = f"{_stem(p)}-{group}" if group else _stem(p)
        result = _mask.extract_surface(
            image, values, smooth_iterations=smooth_iterations,
            target_vertices=target_vertices, name=name,
        )
        out.append((result.surface, result.report))
    return out


# =========================================================================== helpers
def _unit_factor(units: str) -> float:
    try:
        return UNITS_MM[units]
    except (KeyError, TypeError):
        raise InputError(f"units must be one of {', '.join(UNITS_MM)}, got {units!r}") from None


def _is_mesh_path(p: Path) -> bool:
    return p.suffix.lower() in MESH_SUFFIXES and not p.is_dir()


def _stem(p: Path) -> str:
    if p.name.lower().endswith(".nii.gz"):
        return p.name[:-7]
    return p.name if p.is_dir() else p.stem


def _fan(polygons: list[list[int]] | tuple) -> np.ndarray:
    """Fan-triangulate polygons given as index lists: ``(a, b, c, d)`` -> ``(a,b,c), (a,c,d)``."""
    tris = [(poly[0], poly[k], poly[k + 1]) for poly in polygons for k in range(1, len(poly) - 1)]
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


def _fan_offsets(connectivity: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Fan triangulation of polygons stored as flat connectivity and *end* offsets (VTK layout)."""
    connectivity = np.asarray(connectivity, dtype=np.int64)
    ends = np.asarray(offsets, dtype=np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    sizes = ends - starts
    if (sizes < 0).any() or (len(ends) and ends[-1] > len(connectivity)):
        raise _FormatError("polygon offsets are inconsistent with the connectivity array")
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


def merge_duplicate_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with bit-identical coordinates (``-0.0 == 0.0``); re-index faces.

    Used for triangle soup (STL) and glTF seams, where duplication is an artefact of storage.
    Returns ``(vertices (k, 3) float, faces (m, 3) int64)``, vertices in sorted order.
    """
    v = np.asarray(vertices, dtype=np.float64) + 0.0
    uniq, inverse = np.unique(v, axis=0, return_inverse=True)
    return np.ascontiguousarray(uniq), inverse.reshape(-1)[np.asarray(faces)].astype(np.int64)


# =========================================================================== STL
def _read_stl(p: Path):
    data = p.read_bytes()
    size = len(data)
    n = struct.unpack_from("<I", data, 80)[0] if size >= 84 else None
    binary_ok = n is not None and size == 84 + 50 * n
    if not binary_ok and data[:5].lower() == b"solid":
        return _read_stl_ascii(data)
    if n is None:
        raise _FormatError(f"truncated STL: {size} bytes, shorter than the 84-byte binary header")
    expected = 84 + 50 * n
    if size < expected:
        raise _FormatError(
            f"truncated binary STL (or not an STL): header announces {n} triangles "
            f"({expected} bytes) but the file has {size} bytes"
        )
    if size > expected:
        raise _FormatError(
            f"not a valid binary STL: header announces {n} triangles ({expected} bytes) "
            f"but the file has {size} bytes"
        )
    if n == 0:
        raise _FormatError("no triangles in the file (binary STL with 0 facets)")
    rec = np.frombuffer(data, dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]),
                        count=n, offset=84)
    soup = rec["v"].reshape(-1, 3).astype(np.float64)
    return merge_duplicate_vertices(soup, np.arange(3 * n).reshape(-1, 3))


_FLOAT = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"


def _read_stl_ascii(data: bytes):
    text = data.decode("ascii", errors="replace")
    rows = re.findall(rf"vertex\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})", text, flags=re.I)
    if not rows:
        raise _FormatError("not an STL file (starts with 'solid' but has no 'vertex' lines)")
    if len(rows) % 3:
        raise _FormatError(f"truncated ASCII STL: {len(rows)} vertex lines, not a multiple of 3")
    if "endsolid" not in text[-200:].lower():
        raise _FormatError("truncated ASCII STL: no 'endsolid' at the end")
    soup = np.array(rows, dtype=np.float64)
    return merge_duplicate_vertices(soup, np.arange(len(soup)).reshape(-1, 3))


def _write_stl(v: np.ndarray, f: np.ndarray) -> bytes:
    rec = np.zeros(len(f), dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]))
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    rec["n"] = nrm / np.where(length > 0, length, 1.0)
    rec["v"] = tri
    header = b"binary STL written by lungdeform".ljust(80, b" ")
    return header + struct.pack("<I", len(f)) + rec.tobytes()


# =========================================================================== OBJ
def _read_obj(p: Path):
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    with open(p, "rb") as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.split(b"#", 1)[0].strip()
            if line.startswith(b"v ") or line.startswith(b"v\t"):
                parts = line.split()
                if len(parts) < 4:
                    raise _FormatError(f"line {lineno}: a 'v' record needs 3 coordinates")
                try:
                    verts.append([float(x) for x in parts[1:4]])
                except ValueError:
                    raise _FormatError(f"line {lineno}: bad vertex coordinates") from None
            elif line.startswith(b"f ") or line.startswith(b"f\t"):
                try:
                    idx = [int(tok.split(b"/", 1)[0]) for tok in line.split()[1:]]
                except ValueError:
                    raise _FormatError(f"line {lineno}: bad face indices") from None
                n = len(verts)
                idx = [i - 1 if i > 0 else n + i for i in idx]
                if len(idx) < 3:
                    raise _FormatError(f"line {lineno}: a face needs at least 3 vertices")
                polys.append(idx)
    if not verts and not polys:
        raise _FormatError("not an OBJ mesh (no 'v' or 'f' records)")
    return np.array(verts, dtype=np.float64).reshape(-1, 3), _fan(polys)


def _write_obj(v: np.ndarray, f: np.ndarray) -> bytes:
    lines = ["# written by lungdeform"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f.tolist()]
    return ("\n".join(lines) + "\n").encode()


# =========================================================================== OFF
def _read_off(p: Path):
    text = p.read_bytes().decode("ascii", errors="replace")
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].split()[0].upper().endswith("OFF"):
        raise _FormatError("not an OFF file (first keyword is not 'OFF')")
    head = lines[0].split()[1:]
    rest = lines[1:]
    if not head:
        if not rest:
            raise _FormatError("truncated OFF: no vertex/face counts")
        head, rest = rest[0].split(), rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
    except (ValueError, IndexError):
        raise _FormatError("not a valid OFF file (bad vertex/face counts)") from None
    if len(rest) < nv + nf:
        raise _FormatError(
            f"truncated OFF: header announces {nv} vertices and {nf} faces, "
            f"file has {len(rest)} data lines"
        )
    try:
        verts = np.array([ln.split()[:3] for ln in rest[:nv]], dtype=np.float64).reshape(-1, 3)
        polys = []
        for ln in rest[nv : nv + nf]:
            tok = ln.split()
            k = int(tok[0])
            polys.append([int(t) for t in tok[1 : 1 + k]])
    except ValueError:
        raise _FormatError("not a valid OFF file (non-numeric data)") from None
    return verts, _fan(polys)


def _write_off(v: np.ndarray, f: np.ndarray) -> bytes:
    lines = ["OFF", f"{len(v)} {len(f)} 0"]
    lines += [f"{x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
    return ("\n".join(lines) + "\n").encode()


# =========================================================================== PLY
def _read_ply(p: Path):
    import trimesh

    with open(p, "rb") as fh:
        if fh.read(3) != b"ply":
            raise _FormatError("not a PLY file (no 'ply' magic)")
    geom = trimesh.load(str(p), file_type="ply", process=False)
    faces = getattr(geom, "faces", None)
    if faces is None or len(faces) == 0:
        raise _FormatError("no triangles in the file (a point cloud?)")
    return np.asarray(geom.vertices), np.asarray(faces)


def _write_ply(v: np.ndarray, f: np.ndarray) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by lungdeform\n"
        f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    rec = np.zeros(len(f), dtype=np.dtype([("k", "u1"), ("i", "<i4", 3)]))
    rec["k"] = 3
    rec["i"] = f
    return header + v.astype("<f8").tobytes() + rec.tobytes()


# =========================================================================== glTF / GLB
def _read_gltf(p: Path):
    import trimesh

    suffix = p.suffix.lower()
    if suffix == ".glb":
        with open(p, "rb") as fh:
            head = fh.read(12)
        if head[:4] != b"glTF":
            raise _FormatError("not a GLB file (no 'glTF' magic)")
        if len(head) < 12 or struct.unpack("<I", head[8:12])[0] > p.stat().st_size:
            raise _FormatError("truncated GLB: shorter than the length in its header")
    else:
        try:
            json.loads(p.read_bytes())
        except (ValueError, UnicodeDecodeError):
            raise _FormatError("not a glTF file (not valid JSON)") from None
    scene = trimesh.load_scene(str(p), file_type=suffix[1:], process=False)
    chunks_v, chunks_f, offset = [], [], 0
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue  # points and lines are not surfaces
        vv = np.asarray(geom.vertices, dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
        ff = np.asarray(geom.faces, dtype=np.int64)
        if np.linalg.det(transform[:3, :3]) < 0:
            ff = ff[:, ::-1]  # a mirroring node transform flips the winding
        chunks_v.append(vv)
        chunks_f.append(ff + offset)
        offset += len(vv)
    if not chunks_f:
        raise _FormatError("no triangle primitives in the default scene")
    return merge_duplicate_vertices(np.vstack(chunks_v), np.vstack(chunks_f))


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
            raise _FormatError(f"unsupported data type '{vtk_type}'")
        if self.binary:
            dt = np.dtype(">" + code)
            nbytes = count * dt.itemsize
            if self.pos + nbytes > len(self.data):
                raise _FormatError("truncated: binary block shorter than announced")
            arr = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
            self.pos += nbytes
            return arr.astype(dt.newbyteorder("="))
        tokens: list[bytes] = []
        while len(tokens) < count:
            if self.pos >= len(self.data):
                raise _FormatError(f"truncated: expected {count} values, found {len(tokens)}")
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            tokens += self.data[self.pos:end].split()
            self.pos = end + 1
        return np.array(tokens[:count], dtype=np.float64 if code[0] == "f" else np.int64)


def _read_vtk(p: Path):
    data = p.read_bytes()
    head = data[:1024].split(b"\n", 4)
    if not head[0].startswith(b"# vtk DataFile"):
        raise _FormatError("not a legacy VTK file (no '# vtk DataFile' header)")
    if len(head) < 4:
        raise _FormatError("truncated VTK header")
    mode = head[2].strip().upper()
    dataset = head[3].split()
    if mode not in (b"ASCII", b"BINARY"):
        raise _FormatError("not a valid VTK file (third line must be ASCII or BINARY)")
    if len(dataset) < 2 or dataset[0].upper() != b"DATASET":
        raise _FormatError("not a valid VTK file (fourth line must be DATASET ...)")
    kind = dataset[1].upper().decode()
    if kind == "UNSTRUCTURED_GRID":
        return _read_vtk_unstructured(p)
    if kind != "POLYDATA":
        raise _FormatError(f"DATASET {kind} holds no surface (need POLYDATA or UNSTRUCTURED_GRID)")
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
                    raise _FormatError(f"{key}: OFFSETS without CONNECTIVITY")
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
        raise _FormatError("no POINTS section")
    if not faces:
        raise _FormatError("no triangles in the file (no POLYGONS or TRIANGLE_STRIPS)")
    return points, np.vstack(faces)


def _split_classic_cells(flat: np.ndarray, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """``[k, i1..ik, k, ...]`` -> (connectivity, end offsets)."""
    if len(flat) and (flat[0] == 3).all() and len(flat) == 4 * n_cells and (flat[::4] == 3).all():
        cells = flat.reshape(-1, 4)[:, 1:]
        return cells.ravel(), np.arange(1, n_cells + 1) * 3
    conn, ends, pos = [], [], 0
    for _ in range(n_cells):
        if pos >= len(flat):
            raise _FormatError("truncated cell list")
        k = int(flat[pos])
        conn.append(flat[pos + 1 : pos + 1 + k])
        ends.append((ends[-1] if ends else 0) + k)
        pos += k + 1
    return np.concatenate(conn) if conn else np.zeros(0, np.int64), np.array(ends, dtype=np.int64)


def _read_vtk_unstructured(p: Path):
    import contextlib
    import io as _io

    import meshio

    sink = _io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        m = meshio.vtk.read(str(p))  # the format reader itself: meshio.read() calls sys.exit
    faces = []
    for block in m.cells:
        if block.type in ("triangle", "quad", "polygon"):
            data = np.asarray(block.data, dtype=np.int64)
            faces.append(_fan(data.tolist()) if data.shape[1] > 3 else data)
    if not faces:
        raise _FormatError("no triangles in the unstructured grid (no triangle/quad/polygon cells)")
    return np.asarray(m.points, dtype=np.float64), np.vstack(faces)


def _write_vtk(v: np.ndarray, f: np.ndarray) -> bytes:
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


def _read_vtp(p: Path):
    import xml.etree.ElementTree as ET

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
            raise _FormatError("truncated: <AppendedData> is not closed")
        appended = data[underscore + 1 : stop]
        if encoding == "raw" and appended.endswith(b"\n"):
            pass  # trailing whitespace after raw data is harmless: arrays carry their own sizes
        xml_text = data[:start] + b"</VTKFile>"
    else:
        xml_text = data
    try:
        root = ET.fromstring(xml_text)
    except ET.ParseError as exc:
        raise _FormatError(f"truncated or not a VTK XML file (XML error: {exc})") from None
    if root.tag != "VTKFile" or root.get("type") != "PolyData":
        raise _FormatError(f"not a VTK XML PolyData file (root <{root.tag} type={root.get('type')!r}>)")
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
        raise _FormatError("no <PolyData><Piece> element")
    all_v, all_f, base = [], [], 0
    for piece in pieces:
        pts_el = piece.find("./Points/DataArray")
        if pts_el is None:
            raise _FormatError("a <Piece> has no <Points>")
        n_pts = int(piece.get("NumberOfPoints", "0"))
        pts = _vtp_array(pts_el, ctx).astype(np.float64)
        if pts.size != 3 * n_pts:
            raise _FormatError(f"Points has {pts.size} values, expected 3 x {n_pts}")
        pts = pts.reshape(-1, 3)
        for section, fn in (("Polys", _fan_offsets), ("Strips", _strips)):
            el = piece.find(section)
            if el is None or int(piece.get(f"NumberOf{section}", "1")) == 0:
                continue
            arrays = {a.get("Name"): a for a in el.findall("DataArray")}
            if "connectivity" not in arrays or "offsets" not in arrays:
                raise _FormatError(f"<{section}> needs 'connectivity' and 'offsets' arrays")
            conn = _vtp_array(arrays["connectivity"], ctx).astype(np.int64)
            offs = _vtp_array(arrays["offsets"], ctx).astype(np.int64)
            all_f.append(fn(conn, offs) + base)
        all_v.append(pts)
        base += len(pts)
    if not all_f:
        raise _FormatError("no triangles in the file (no <Polys> or <Strips>)")
    return np.vstack(all_v), np.vstack(all_f)


def _vtp_array(el, ctx) -> np.ndarray:
    vtype = el.get("type")
    if vtype not in _VTK_XML_TYPES:
        raise _FormatError(f"DataArray '{el.get('Name')}' has unsupported type {vtype!r}")
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
    raise _FormatError(f"DataArray format {fmt!r} is not ascii, binary or appended")


def _b64(chars: bytes) -> bytes:
    try:
        return base64.b64decode(chars, validate=False)
    except (ValueError, base64.binascii.Error):
        raise _FormatError("corrupt base64 data") from None


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
                raise _FormatError("truncated appended data")
            nbytes = int(np.frombuffer(blob[:hsize], htype)[0])
            raw = blob[hsize : hsize + nbytes]
        if len(raw) < nbytes:
            raise _FormatError(f"truncated binary DataArray ({len(raw)} of {nbytes} bytes)")
        return np.frombuffer(raw[:nbytes], dtype=dtype).astype(dtype.newbyteorder("="))
    # compressed
    comp = ctx["compressor"]
    if comp == "vtkZLibDataCompressor":
        decompress = zlib.decompress
    elif comp == "vtkLZMADataCompressor":
        import lzma

        decompress = lzma.decompress
    else:
        raise _FormatError(f"unsupported compressor {comp} (zlib and lzma are supported)")
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
        raise _FormatError("truncated compressed DataArray")
    out, pos = [], 0
    for s in sizes:
        try:
            out.append(decompress(body[pos : pos + s]))
        except Exception:
            raise _FormatError("corrupt compressed DataArray") from None
        pos += s
    return np.frombuffer(b"".join(out), dtype=dtype).astype(dtype.newbyteorder("="))


def _write_vtp(v: np.ndarray, f: np.ndarray) -> bytes:
    def arr(name, a, vtype, ncomp=1):
        raw = np.ascontiguousarray(a).tobytes()
        enc = base64.b64encode(struct.pack("<Q", len(raw)) + raw).decode()
        return (f'<DataArray type="{vtype}" Name="{name}" NumberOfComponents="{ncomp}" '
                f'format="binary">{enc}</DataArray>')

    return (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
        f'<PolyData><Piece NumberOfPoints="{len(v)}" NumberOfVerts="0" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{len(f)}">\n'
        f"<Points>{arr('Points', v.astype('<f8'), 'Float64', 3)}</Points>\n"
        f"<Polys>{arr('connectivity', f.astype('<i8'), 'Int64')}"
        f"{arr('offsets', (3 * np.arange(1, len(f) + 1)).astype('<i8'), 'Int64')}</Polys>\n"
        "</Piece></PolyData>\n</VTKFile>\n"
    ).encode()


_READERS = {
    ".stl": _read_stl, ".obj": _read_obj, ".off": _read_off, ".ply": _read_ply,
    ".vtk": _read_vtk, ".vtp": _read_vtp, ".gltf": _read_gltf, ".glb": _read_gltf,
}
_WRITERS = {
    ".stl": _write_stl, ".obj": _write_obj, ".off": _write_off, ".ply": _write_ply,
    ".vtk": _write_vtk, ".vtp": _write_vtp,
}
