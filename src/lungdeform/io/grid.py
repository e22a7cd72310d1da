"""The image grid every reader and writer shares: :class:`Image`, voxel index → world, the voxel cap.

Frames and units: arrays follow SimpleITK: ``array`` is indexed ``[k, j, i]`` = ``[z, y, x]``;
spacing (mm), origin (mm, LPS world) and voxel indices ``ijk`` are ordered ``(x, y, z)``; the
columns of ``direction`` are the index axes in LPS. :func:`index_to_world` maps ``ijk : (n, 3)
float`` to world points ``(n, 3) float`` mm LPS. :func:`check_grid` refuses a grid over the cap
(:func:`voxel_limit`) from a header, before any voxel is allocated; :func:`quiet_itk` silences
ITK's own warnings while a reader asks it something (the reader raises instead).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from lungdeform.errors import InputError, ReadError

#: Default largest grid read or written, in voxels: 2^29 ≈ 5.4e8 (a CT of 512 × 512 × 2000 slices
#: fits; 1000^3 does not). Raised by :data:`MAX_VOXELS_ENV` or a ``max_voxels`` argument.
MAX_VOXELS = 2 ** 29
#: The environment variable that raises (or lowers) :data:`MAX_VOXELS` (``lungdeform --max-voxels`` sets it).
MAX_VOXELS_ENV = "LUNGDEFORM_MAX_VOXELS"


@dataclass(frozen=True, eq=False)
class Image:
    """A 3-D scalar image in the ITK/LPS convention.

    Attributes
    ----------
    array : (z, y, x) array
        Voxel values, indexed ``[k, j, i]`` as SimpleITK gives them.
    spacing : (3,) float
        Voxel size in mm along ``(i, j, k)`` = ``(x, y, z)`` index axes.
    origin : (3,) float
        World position (mm, LPS) of the centre of voxel ``(0, 0, 0)``.
    direction : (3, 3) float
        Columns are the unit directions of the index axes ``i, j, k`` in LPS world.
    source : str
        The file or folder it came from (used in messages).
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    source: str = "image"

    def __post_init__(self):
        a = np.asarray(self.array)
        if a.ndim != 3:
            raise InputError(f"{self.source}: image array must be 3-D (z, y, x), got shape {a.shape}")
        sp = np.asarray(self.spacing, dtype=np.float64).reshape(3)
        org = np.asarray(self.origin, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3, 3)
        for name, value in (("spacing", sp), ("origin", org), ("direction", d)):
            if not np.isfinite(value).all():
                raise InputError(f"{self.source}: {name} must be finite, got {value.tolist()}")
        if not (sp > 0).all():
            raise InputError(f"{self.source}: spacing must be positive, got {sp}")
        if abs(abs(np.linalg.det(d)) - 1.0) > 1e-3:
            raise InputError(f"{self.source}: direction must be orthonormal, det = {np.linalg.det(d):.4g}")
        for name, value in (("array", a), ("spacing", sp), ("origin", org), ("direction", d)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def index_to_world(self, ijk) -> np.ndarray:
        """``(n, 3)`` voxel indices (i=x, j=y, k=z) -> ``(n, 3) float`` mm LPS."""
        return index_to_world(ijk, self.spacing, self.origin, self.direction)

    @property
    def voxel_ml(self) -> float:
        """The volume of one voxel, mL (the direction is orthonormal: spacing alone)."""
        return float(np.prod(self.spacing)) / 1000.0


def index_to_world(ijk, spacing, origin, direction) -> np.ndarray:
    """World points ``(n, 3) float`` mm LPS of voxel indices ``ijk : (n, 3) float`` (i, j, k).

    ``world = origin + direction @ (spacing * ijk)`` (ITK's TransformContinuousIndexToPhysicalPoint).
    """
    ijk = np.asarray(ijk, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(direction, dtype=np.float64).reshape(3, 3)
    return np.ascontiguousarray((ijk * np.asarray(spacing, float)) @ d.T + np.asarray(origin, float))



def voxel_limit(max_voxels=None) -> int:
    """The grid-size cap in voxels: ``max_voxels`` when given, else the environment variable
    :data:`MAX_VOXELS_ENV`, else :data:`MAX_VOXELS`; :class:`InputError` naming the one given when it
    is not a positive whole number (``"2e9"`` is one)."""
    source, value = "max_voxels", max_voxels
    if value is None:
        text = os.environ.get(MAX_VOXELS_ENV, "").strip()
        if not text:
            return MAX_VOXELS
        source, value = MAX_VOXELS_ENV, text
    try:
        n = float(value)
    except (TypeError, ValueError):
        n = float("nan")
    if not (np.isfinite(n) and n >= 1 and n == int(n)):
        raise InputError(f"{source} must be a positive whole number of voxels, got {value!r}")
    return int(n)


def check_grid(size, where, max_voxels=None, error: type[Exception] = ReadError) -> None:
    """Refuse a grid of ``size`` voxels per axis over the cap (:func:`voxel_limit`), with ``error``
    (:class:`ReadError` for a read, :class:`InputError` for a write) naming ``where``: checked from
    a header, before any voxel is read or allocated."""
    limit = voxel_limit(max_voxels)
    size = [int(s) for s in size]
    count = int(np.prod(size, dtype=object))
    if count > limit:
        raise error(f"{where}: the image grid {' x '.join(map(str, size))} is {count:,} voxels, over the limit of "
                    f"{limit:,} (raise it with 'lungdeform --max-voxels N' or ${MAX_VOXELS_ENV})")




@contextmanager
def quiet_itk():
    """Silence ITK's own warnings on stderr (e.g. GDCM's "No Series were found"): the CLI's
    contract is one error line; what went wrong is said by the :class:`ReadError` raised instead."""

    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(before)


