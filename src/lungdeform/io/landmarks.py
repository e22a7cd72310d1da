"""Landmark point sets: DIR-Lab voxel-index files and elastix point-set files.

Frames and units
----------------
- DIR-Lab files hold one landmark per line, ``x y z`` as **1-based voxel indices** (integers, or
  floats in some 75-point files), CRLF line endings, tabs or spaces. They are converted once, here,
  to millimetres in the image's *index-aligned* frame: ``mm = (index - 1) * spacing`` per axis
  (x, y, z). DIR-Lab ships no origin or direction, so this frame is not LPS world; distances and
  displacements are what it is meant for.
- elastix point-set files are ``point`` (world mm, LPS) or ``index`` (0-based voxel index), a
  count, then one ``x y z`` row per point. ``index`` files need the image geometry to reach mm.

Every reader returns ``points : (n, 3) float64`` C-contiguous, and raises
:class:`~lungdeform.errors.ReadError` naming the file and the 1-based line for a bad row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lungdeform.atomic import write_text
from lungdeform.errors import InputError, ReadError


# --------------------------------------------------------------------------- validation helpers
def as_spacing(spacing, name: str = "spacing") -> np.ndarray:
    """Return ``spacing : (3,) float`` (mm, x y z), or raise :class:`InputError` if not 3 positive finite numbers."""
    try:
        arr = np.asarray(spacing, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be 3 numbers (x, y, z in mm), got {spacing!r}") from exc
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise InputError(f"{name} must be 3 positive finite numbers (x, y, z in mm), got {spacing!r}")
    return arr


def _split_row(line: str) -> list[str]:
    return line.replace(",", " ").replace(";", " ").split()


def _read_text(path: Path) -> list[str]:
    path = Path(path)
    if not path.is_file():
        raise ReadError(f"{path}: no such file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ReadError(f"{path}: not a text file ({exc.reason})") from exc
    # splitlines handles CRLF, CR and LF alike
    return text.splitlines()


def _parse_xyz(path: Path, lineno: int, line: str) -> tuple[float, float, float]:
    fields = _split_row(line)
    if len(fields) != 3:
        raise ReadError(f"{path}, line {lineno}: expected 3 numbers 'x y z', got {len(fields)} field(s): {line.strip()!r}")
    try:
        values = tuple(float(f) for f in fields)
    except ValueError as exc:
        raise ReadError(f"{path}, line {lineno}: not a number in {line.strip()!r}") from exc
    if not all(np.isfinite(values)):
        raise ReadError(f"{path}, line {lineno}: non-finite value in {line.strip()!r}")
    return values  # type: ignore[return-value]


# --------------------------------------------------------------------------- DIR-Lab
def read_dirlab_indices(path) -> np.ndarray:
    """Read a DIR-Lab landmark file as raw 1-based voxel indices.

    Returns
    -------
    indices : (n, 3) float
        1-based voxel indices (x, y, z) exactly as written in the file.

    Blank lines are skipped; any other row that is not three finite numbers raises
    :class:`ReadError` naming the file and line. Indices below 0.5 are refused (the file is 1-based;
    a 0 usually means a 0-based file was passed).
    """
    path = Path(path)
    rows: list[tuple[float, float, float]] = []
    for lineno, line in enumerate(_read_text(path), start=1):
        if not line.strip():
            continue
        xyz = _parse_xyz(path, lineno, line)
        if min(xyz) < 0.5:
            raise ReadError(f"{path}, line {lineno}: voxel index {min(xyz):g} < 1, but DIR-Lab indices are 1-based")
        rows.append(xyz)
    if not rows:
        raise ReadError(f"{path}: no landmarks in the file")
    return np.ascontiguousarray(rows, dtype=np.float64)


def dirlab_index_to_mm(indices, spacing) -> np.ndarray:
    """``points : (n, 3) float`` mm in the index-aligned frame: ``(indices - 1) * spacing``.

    ``indices : (n, 3)`` 1-based voxel indices (x, y, z); ``spacing : (3,)`` mm (x, y, z).
    """
    idx = np.asarray(indices, dtype=np.float64)
    if idx.ndim != 2 or idx.shape[1] != 3:
        raise InputError(f"indices must have shape (n, 3), got {idx.shape}")
    return np.ascontiguousarray((idx - 1.0) * as_spacing(spacing))


def read_dirlab_points(path, spacing, shape=None) -> np.ndarray:
    """Read a DIR-Lab landmark file and return ``points : (n, 3) float`` in mm (index-aligned frame).

    Parameters
    ----------
    path : DIR-Lab text file (1-based ``x y z`` voxel indices).
    spacing : (3,) float, mm per voxel along x, y, z (from DIR-Lab's voxel_spacing.csv).
    shape : optional (3,) int, image size (dim_x, dim_y, dim_z) in voxels. When given, a landmark
        outside the image (index outside ``[0.5, dim + 0.5]``) raises :class:`ReadError`.
    """
    path = Path(path)
    spacing = as_spacing(spacing)
    idx = read_dirlab_indices(path)
    if shape is not None:
        dims = np.asarray(shape, dtype=np.float64).reshape(-1)
        if dims.shape != (3,) or np.any(dims < 1):
            raise InputError(f"shape must be 3 positive voxel counts (x, y, z), got {shape!r}")
        outside = np.any(idx > dims + 0.5, axis=1)
        if outside.any():
            k = int(np.argmax(outside))
            raise ReadError(
                f"{path}: landmark {k + 1} at voxel index {idx[k].tolist()} lies outside the image "
                f"of {dims.astype(int).tolist()} voxels ({int(outside.sum())} landmark(s) outside)"
            )
    return dirlab_index_to_mm(idx, spacing)


# --------------------------------------------------------------------------- elastix
def read_elastix_points(path, spacing=None, origin=None, direction=None) -> np.ndarray:
    """Read an elastix/transformix point-set file; return ``points : (n, 3) float`` in world mm (LPS).

    Format: first non-blank line ``point`` (world coordinates, mm) or ``index`` (0-based voxel
    index), then the number of points, then one ``x y z`` row per point. For ``index`` files pass
    the image geometry (``spacing`` (3,) mm, ``origin`` (3,) mm, ``direction`` (3, 3)); world =
    origin + direction @ (index * spacing). The count must match the number of rows.
    """
    path = Path(path)
    lines = [(i, line) for i, line in enumerate(_read_text(path), start=1) if line.strip()]
    if len(lines) < 2:
        raise ReadError(f"{path}: an elastix point set needs a 'point'/'index' line and a count")
    kind = lines[0][1].strip().lower()
    if kind not in ("point", "index"):
        raise ReadError(f"{path}, line {lines[0][0]}: expected 'point' or 'index', got {lines[0][1].strip()!r}")
    count_line, count_text = lines[1]
    try:
        count = int(count_text.strip())
    except ValueError as exc:
        raise ReadError(f"{path}, line {count_line}: expected the number of points, got {count_text.strip()!r}") from exc
    rows = [_parse_xyz(path, i, line) for i, line in lines[2:]]
    if count != len(rows) or count == 0:
        raise ReadError(f"{path}: header says {count} points, the file holds {len(rows)}")
    pts = np.ascontiguousarray(rows, dtype=np.float64)
    if kind == "point":
        return pts
    if spacing is None or origin is None:
        raise InputError(f"{path} holds voxel indices ('index'): pass spacing and origin to convert them to mm")
    sp = as_spacing(spacing)
    org = np.asarray(origin, dtype=np.float64).reshape(3)
    rot = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64).reshape(3, 3)
    return np.ascontiguousarray(org + (pts * sp) @ rot.T)


def write_elastix_points(path, points) -> Path:
    """Write ``points : (n, 3) float`` (world mm) as an elastix ``point`` file, atomically."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(f"points must have shape (n, 3) with n > 0, got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("points must be finite")
    path = Path(path)
    body = "point\n%d\n" % len(pts) + "".join("%.6f %.6f %.6f\n" % tuple(p) for p in pts)

    write_text(path, body)
    return path
