"""``--rigid-structure NAME --rtstruct FILE`` / ``--rigid-mask MASK`` of ``dvf`` and ``warp``: a tumour
that moves rigidly (:mod:`lungdeform.playback.rigid`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError
from lungdeform.io.image import read_image, resample_image
from lungdeform.playback import rigid as RG
from lungdeform.playback.structures import read_structure


@dataclass(frozen=True)
class RigidOptions:
    """The rigid-structure options: a ROI ``name`` of ``rtstruct``, or a ``mask`` image; ``border_mm``."""

    name: str | None
    rtstruct: Path | None
    mask: Path | None
    border_mm: float

    @staticmethod
    def of(name, rtstruct, mask, border_mm) -> RigidOptions | None:
        """Checked before any work: --rigid-structure with --rtstruct, or --rigid-mask; None without."""
        if (name is None) != (rtstruct is None):
            raise InputError("--rigid-structure and --rtstruct go together")
        if name is not None and mask is not None:
            raise InputError("--rigid-structure and --rigid-mask are mutually exclusive: give one rigid region")
        if not (np.isfinite(border_mm) and 0 < border_mm <= 100):
            raise InputError(f"--rigid-border-mm must be a finite number in (0, 100] mm, got {border_mm}")
        if name is None and mask is None:
            return None
        return RigidOptions(name, rtstruct, mask, float(border_mm))

    @property
    def label(self) -> str:
        return self.name if self.name is not None else str(self.mask)


def rigid_region(options: RigidOptions | None, grid) -> np.ndarray | None:
    """``(z, y, x) bool`` on ``grid``: the structure's voxels (inside its closed surface through the
    contours) or the mask's non-zero voxels (a mask on another grid of the same LPS world taken by
    nearest neighbour); None without options."""
    if options is None:
        return None
    if options.name is not None:
        s = read_structure(options.rtstruct, options.name)
        region = RG.surface_mask(s.vertices, s.faces, grid)
        where = f"{options.rtstruct} {options.name}"
    else:
        img = read_image(options.mask)
        same = (img.array.shape == tuple(grid.shape) and np.allclose(img.spacing, grid.spacing, atol=1e-4)
                and np.allclose(img.origin, grid.origin, atol=1e-3)
                and np.allclose(np.asarray(img.direction).reshape(3, 3), grid.direction, atol=1e-6))
        if not same:  # another grid of the same world: its voxels, nearest neighbour, on this grid
            img = resample_image(img, np.zeros(tuple(grid.shape) + (3,)), label=True, grid=grid)
        region = img.array != 0
        where = f"--rigid-mask {options.mask}"
    if region.sum() < 4:
        raise InputError(f"{where}: covers {int(region.sum())} voxel(s) of the grid; a rigid structure needs at "
                         "least 4 (is it in the image's frame, mm LPS?)")
    return region


def apply_rigid(result, grid, region, options: RigidOptions | None) -> list[str]:
    """Make the field rigid over ``region`` (in place) and say so in lines for the terminal."""
    if options is None:
        return []
    r = RG.rigid_field(result, grid, region, options.border_mm)
    angle = np.degrees(np.arccos(np.clip((np.trace(r.motion.rotation) - 1) / 2, -1, 1)))
    t = ", ".join(f"{x:.2f}" for x in r.motion.translation)
    return [(f"rigid {options.label}: {r.volume_ml:.2f} mL; at this state {r.rigid_ml:.2f} mL "
             f"({100 * (r.rigid_ml / r.volume_ml - 1):+.2f} %; the elastic field gave {r.elastic_ml:.2f} mL, "
             f"{100 * (r.elastic_ml / r.volume_ml - 1):+.2f} %); centroid moved ({t}) mm, rotated {angle:.2f}°, "
             f"blended over {options.border_mm:g} mm"),
            "Jacobian determinant after the rigid structure: checked (no folding)"]
