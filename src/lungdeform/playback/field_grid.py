"""A displacement field carried to a coarser grid (the grid of a DICOM REG) and what that costs.

A REG holds its vectors on a regular grid of its own (PS3.3 C.20.3); a planning system interpolates
them trilinearly. On a 512 × 512 × 141 planning grid the full field is 443 MB per state, while the
model's field is smooth at a few millimetres: it is itself interpolated from a lattice about 4 mm
apart (:data:`lungdeform.playback.displacement_field.NODE_SPACING_MM`), except within 8 mm of a
fitted landmark, at the lung surface (where the motion slides) and over a rigid structure's border.
:func:`coarse_grid` spans the same box as the field's grid (its first and last nodes on the grid's
first and last voxel centres along each axis, same origin and direction) at the largest node step
at most ``spacing_mm`` (an axis already that coarse is kept); :func:`coarsened` samples the field at
its nodes (trilinear, exact at nodes that fall on voxels), and :func:`interpolation_error` measures
what a reader of the coarse field gets back on the full grid (trilinear, as planning systems and ITK
interpolate) against the full field.

Arrays: fields ``(z, y, x, 3) float32`` mm LPS on a :class:`~lungdeform.playback.displacement_field.Grid`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lungdeform.errors import InputError

from .displacement_field import Grid

#: Default node spacing (mm) of a REG's grid: within the 2.5–4 mm at which the model's field is smooth.
REG_SPACING_MM = 3.0
#: Displacements below this (mm) count as still tissue in :func:`interpolation_error`'s percentiles.
MOVING_MM = 0.01


def coarse_grid(grid: Grid, spacing_mm: float) -> Grid:
    """The grid over the same box as ``grid`` with node steps at most ``spacing_mm`` mm (module
    docstring); ``grid`` itself when no axis is finer than that."""
    if not (np.isfinite(spacing_mm) and spacing_mm > 0):
        raise InputError(f"the REG's grid spacing must be > 0 mm, got {spacing_mm!r}")
    n = np.array(grid.shape[::-1], int)  # (x, y, z) voxels
    extent = (n - 1) * grid.spacing
    m = np.where(grid.spacing < spacing_mm, np.ceil(extent / spacing_mm - 1e-9).astype(int) + 1, n)
    m = np.minimum(np.maximum(m, 2), n)
    if np.array_equal(m, n):
        return grid
    step = np.where(m > 1, extent / np.maximum(m - 1, 1), grid.spacing)
    return Grid(tuple(int(x) for x in m[::-1]), step, np.asarray(grid.origin, float).copy(), grid.direction.copy())


def _resized(array: np.ndarray, shape: tuple) -> np.ndarray:
    """``array (z, y, x)`` linearly interpolated to ``shape``, corners on corners (``grid_mode=False``)."""
    # the factor sets the output shape (round(a · b / a) = b); the map is corners on corners,
    # output index o at input o · (a − 1) / (b − 1)
    zoom = [b / a for a, b in zip(array.shape, shape)]
    out = ndimage.zoom(array, zoom, output=np.float32, order=1, mode="nearest", grid_mode=False)
    if out.shape != tuple(shape):  # zoom rounds the output shape; never off by more than one here
        raise InputError(f"field resampling gave shape {out.shape}, expected {tuple(shape)}")
    return out


def coarsened(field: np.ndarray, grid: Grid, coarse: Grid) -> np.ndarray:
    """``field`` on ``grid`` sampled at the nodes of ``coarse`` (:func:`coarse_grid` of it): ``(z, y, x, 3)
    float32``; ``field`` itself when the grids are one."""
    if coarse is grid:
        return field
    return np.stack([_resized(field[..., c], coarse.shape) for c in range(3)], axis=-1)


@dataclass(frozen=True)
class GridError:
    """What a trilinear reader of the coarse field gets back against the full one, mm (vector
    length): ``max_mm`` over every voxel, ``p99_mm`` and ``mean_mm`` over the voxels that move
    (``|u| >`` :data:`MOVING_MM`), ``moving`` how many those are."""

    max_mm: float
    p99_mm: float
    mean_mm: float
    moving: int


def interpolation_error(field: np.ndarray, coarse_field: np.ndarray) -> GridError:
    """The coarse field interpolated back onto the full grid of ``field`` against ``field`` (module docstring)."""
    diff = np.zeros(field.shape[:3], np.float32)
    size = np.zeros(field.shape[:3], np.float32)
    for c in range(3):
        full = field[..., c]
        back = _resized(coarse_field[..., c], full.shape)
        back -= full
        diff += back * back
        size += full * full
    np.sqrt(diff, out=diff)
    moving = size > MOVING_MM ** 2
    if not moving.any():
        return GridError(float(diff.max(initial=0.0)), 0.0, 0.0, 0)
    moved = diff[moving]
    return GridError(float(diff.max()), float(np.percentile(moved, 99)), float(moved.mean()), int(moving.sum()))
