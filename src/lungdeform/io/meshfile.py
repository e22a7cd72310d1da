"""Surfaces in and out: mesh files, and the dispatcher from a file (mesh or mask image) to surfaces.

Readers return raw indexed triangles; :func:`load_surface` adds unit conversion and
:func:`lungdeform.geometry.mesh.check_surface`. Every failure is a :class:`~lungdeform.errors.ReadError`
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
             (:mod:`lungdeform.io.vtk`)
.vtp         VTK XML PolyData (own): ascii,     inline base64 binary (own)
             inline base64 (zlib/lzma or not),
             appended raw/base64
             (:mod:`lungdeform.io.vtk`)
.off         own                                own
.gltf .glb   trimesh: every triangle primitive  —
             of the default scene, node
             transforms applied; seams merged
===========  =================================  ===================================================
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import struct
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from lungdeform.atomic import write_bytes
from lungdeform.errors import InputError, LungdeformError, MeshError, ReadError
from lungdeform.geometry.mesh import Surface, SurfaceReport, as_faces, as_vertices, check_surface
from lungdeform.geometry.remesh import float32_coincident
from lungdeform.io import image as _image
from lungdeform.io import mask as _mask
from lungdeform.io import vtk as vtkio

from .vtk import FormatError

MESH_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".off", ".gltf", ".glb")
WRITE_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".off")
#: millimetres per unit
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


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
    except FormatError as exc:  # from every reader here (and vtkio's): the message lacks the path
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

    ``vertices : (n, 3) float`` (written as float32 in STL, float64 elsewhere; STL refuses, with
    :class:`MeshError`, vertices that share a float32 position, which its readers would weld),
    ``faces : (m, 3) int``. Formats: binary STL, OBJ, binary PLY, legacy binary VTK POLYDATA,
    VTK XML PolyData (inline base64) and OFF. Returns the path.
    """

    p = Path(path)
    suffix = p.suffix.lower()
    writer = _WRITERS.get(suffix)
    if writer is None:
        raise InputError(f"{p}: cannot write '{suffix}' (supported: {', '.join(WRITE_SUFFIXES)})")
    v = as_vertices(vertices)
    f = as_faces(faces, len(v))
    if suffix == ".stl" and (n := float32_coincident(v[np.unique(f)])):
        # STL keeps float32 triangle corners and readers weld equal ones: refuse, not a file that
        # reads back as another surface
        raise MeshError(f"{p}: {n} vertices share a float32 position with another, so STL (float32 corners, "
                        "welded on reading) would not read back as this surface; write OBJ, PLY or VTP, "
                        "or clean the mesh (lungdeform.geometry.remesh.clean_mesh)")
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
      per label group (see :func:`lungdeform.io.mask.label_groups`: None = all non-zero voxels,
      ``"left,right"``, ``"1,2"``, ``{"left": (1, 2)}``), by :func:`lungdeform.io.mask.extract_surface`.
      What the mask pipeline did (components dropped, cavities filled, smoothing, decimation) is
      listed in the report's ``repairs``. Image spacing is already in mm, so ``units`` must be "mm".

    Each surface passed :func:`check_surface` (messages start with the path). ``repair`` applies
    to mesh files; surfaces made from masks are closed, manifold and outward by construction.
    """

    p = Path(path)
    if _is_mesh_path(p):
        if labels is not None:
            raise InputError(f"{p}: labels select parts of a mask image; this is a mesh file")
        if progress:
            progress(f"reading {p}")
        return [load_surface(p, units=units, repair=repair)]
    if not _image.is_image_path(p):
        if not p.exists():
            raise ReadError(f"{p}: no such file or directory")
        raise ReadError(
            f"{p}: unknown format (meshes: {', '.join(MESH_SUFFIXES)}; images: "
            f"{', '.join(_image.IMAGE_SUFFIXES)} or a DICOM directory)"
        )
    if _unit_factor(units) != 1.0:
        raise InputError(f"{p}: units={units!r} applies to mesh files; image spacing is in mm already")
    groups = _mask.label_groups(labels)
    if progress:
        progress(f"reading {p}")
    image = _image.read_image(p)
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
        raise FormatError(f"truncated STL: {size} bytes, shorter than the 84-byte binary header")
    expected = 84 + 50 * n
    if size < expected:
        raise FormatError(
            f"truncated binary STL (or not an STL): header announces {n} triangles "
            f"({expected} bytes) but the file has {size} bytes"
        )
    if size > expected:
        raise FormatError(
            f"not a valid binary STL: header announces {n} triangles ({expected} bytes) "
            f"but the file has {size} bytes"
        )
    if n == 0:
        raise FormatError("no triangles in the file (binary STL with 0 facets)")
    rec = np.frombuffer(data, dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]),
                        count=n, offset=84)
    soup = rec["v"].reshape(-1, 3).astype(np.float64)
    return merge_duplicate_vertices(soup, np.arange(3 * n).reshape(-1, 3))


_FLOAT = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"


def _read_stl_ascii(data: bytes):
    text = data.decode("ascii", errors="replace")
    rows = re.findall(rf"vertex\s+({_FLOAT})\s+({_FLOAT})\s+({_FLOAT})", text, flags=re.I)
    if not rows:
        raise FormatError("not an STL file (starts with 'solid' but has no 'vertex' lines)")
    if len(rows) % 3:
        raise FormatError(f"truncated ASCII STL: {len(rows)} vertex lines, not a multiple of 3")
    if "endsolid" not in text[-200:].lower():
        raise FormatError("truncated ASCII STL: no 'endsolid' at the end")
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
                    raise FormatError(f"line {lineno}: a 'v' record needs 3 coordinates")
                try:
                    verts.append([float(x) for x in parts[1:4]])
                except ValueError:
                    raise FormatError(f"line {lineno}: bad vertex coordinates") from None
            elif line.startswith(b"f ") or line.startswith(b"f\t"):
                try:
                    idx = [int(tok.split(b"/", 1)[0]) for tok in line.split()[1:]]
                except ValueError:
                    raise FormatError(f"line {lineno}: bad face indices") from None
                n = len(verts)
                idx = [i - 1 if i > 0 else n + i for i in idx]
                if len(idx) < 3:
                    raise FormatError(f"line {lineno}: a face needs at least 3 vertices")
                polys.append(idx)
    if not verts and not polys:
        raise FormatError("not an OBJ mesh (no 'v' or 'f' records)")
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
        raise FormatError("not an OFF file (first keyword is not 'OFF')")
    head = lines[0].split()[1:]
    rest = lines[1:]
    if not head:
        if not rest:
            raise FormatError("truncated OFF: no vertex/face counts")
        head, rest = rest[0].split(), rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
    except (ValueError, IndexError):
        raise FormatError("not a valid OFF file (bad vertex/face counts)") from None
    if len(rest) < nv + nf:
        raise FormatError(
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
        raise FormatError("not a valid OFF file (non-numeric data)") from None
    return verts, _fan(polys)


def _write_off(v: np.ndarray, f: np.ndarray) -> bytes:
    lines = ["OFF", f"{len(v)} {len(f)} 0"]
    lines += [f"{x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += [f"3 {a} {b} {c}" for a, b, c in f.tolist()]
    return ("\n".join(lines) + "\n").encode()


# =========================================================================== PLY
def _read_ply(p: Path):
    with open(p, "rb") as fh:
        if fh.read(3) != b"ply":
            raise FormatError("not a PLY file (no 'ply' magic)")
    geom = trimesh.load(str(p), file_type="ply", process=False)
    faces = getattr(geom, "faces", None)
    if faces is None or len(faces) == 0:
        raise FormatError("no triangles in the file (a point cloud?)")
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
    suffix = p.suffix.lower()
    if suffix == ".glb":
        with open(p, "rb") as fh:
            head = fh.read(12)
        if head[:4] != b"glTF":
            raise FormatError("not a GLB file (no 'glTF' magic)")
        if len(head) < 12 or struct.unpack("<I", head[8:12])[0] > p.stat().st_size:
            raise FormatError("truncated GLB: shorter than the length in its header")
    else:
        try:
            json.loads(p.read_bytes())
        except (ValueError, UnicodeDecodeError):
            raise FormatError("not a glTF file (not valid JSON)") from None
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
        raise FormatError("no triangle primitives in the default scene")
    return merge_duplicate_vertices(np.vstack(chunks_v), np.vstack(chunks_f))


_READERS = {
    ".stl": _read_stl, ".obj": _read_obj, ".off": _read_off, ".ply": _read_ply,
    ".vtk": vtkio.read_vtk, ".vtp": vtkio.read_vtp, ".gltf": _read_gltf, ".glb": _read_gltf,
}
_WRITERS = {
    ".stl": _write_stl, ".obj": _write_obj, ".off": _write_off, ".ply": _write_ply,
    ".vtk": vtkio.vtk_bytes, ".vtp": vtkio.vtp_bytes,
}
