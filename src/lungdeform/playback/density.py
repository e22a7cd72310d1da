"""CT values of a warped image: mass conservation and projections over the phases of a 4-D CT.

Behind ``lungdeform warp --density`` and ``warp --phases N --projections mip,aip,minip``
(docs/RADIOTHERAPY.md, "Density and projections").

**Mass.** A CT number is a linear function of density: ``ρ = (HU + 1000) / 1000`` g/mL (water 0 HU
is 1 g/mL, air −1000 HU is 0). Resampling an image through the inverse field ``w`` (the output point
``y`` takes the reference at ``φ(y) = y + w(y)``) carries the density along unchanged, so an inhaled
lung keeps its end-exhale HU while its volume grows: its mass grows with it. Conserving mass
(continuity equation) divides the density by the local volume change of the forward map, i.e.
multiplies it by ``det ∇φ(y) = det(I + ∇w(y))``:

    HU_out(y) = (HU_ref(φ(y)) + 1000) · det(I + ∇w(y)) − 1000.

Then ``Σ (HU + 1000) · dV`` over a region equals the same sum over its preimage (change of variables),
up to interpolation and the discrete Jacobian. Arrays: images ``(z, y, x)``, fields ``(z, y, x, 3)
float32`` mm LPS, as in :mod:`lungdeform.playback.displacement_field`.

**Which density is pulled back** (:func:`resample_by_tissue`, ``warp --density --lung-mask``). The
formula above is exact for the continuous density ``ρ``; a CT gives it at voxel centres, and
``HU_ref(φ(y))`` between them is a reconstruction. Trilinear interpolation of the whole image smears
the lung surface (≈ −780 HU against ≈ 0 HU of the chest wall) over one voxel, so a state's lung
voxel whose source falls within half a voxel of the surface takes chest-wall density (on average a
quarter of the contrast over that half-voxel layer): the lungs gain 2–5 % of their mass and the wall
loses it (docs/RADIOTHERAPY.md, "Measured: mass"). With the lung mask ``m`` the reconstruction is
piecewise, the surface being the mask's voxel faces: lung ``ρ_L = interp(ρ·m) / interp(m)`` (only lung
voxels enter, normalised convolution), the rest ``ρ_R = interp(ρ·(1 − m)) / interp(1 − m)``, and the
state's voxel ``y`` takes ``ρ_L`` when the mask resampled by nearest neighbour (what ``warp --label``
writes) puts it in the lung, ``ρ_R`` otherwise. The nearest-neighbour mask is the pull-back of the union
of the lung voxels' cubes, so ``Σ_lung det ∇φ · dV`` is the reference lung volume (no bias, unlike a
threshold of the linearly resampled mask, which cuts corners), and both sides conserve their mass.
Voxels whose interpolation stencil holds no lung voxel are the ordinary linear resampling.

**Which mask** (:func:`model_lung_mask`, ``warp --density`` without ``--lung-mask``). The segmented
lungs on the image's grid are the exact partition; without them the model's own lungs at rest stand
in: the image's voxels whose centres lie inside the model's rest surfaces. The model is played on the
image as its rest scan, so the rest surfaces lie in the image's LPS world whatever state (and fitted
alignment of scan K, which moves only the output grid) is asked for. The rest surface is a smoothed
mesh through the segmentation's voxel faces, so its voxels differ from the segmentation's along the
surface (docs/RADIOTHERAPY.md, "Density and projections", for what that costs).
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.io.grid import Image
from lungdeform.io.image import resample_channels, resample_image

from .displacement_field import Grid
from .rigid import surface_mask

#: CT number of air (HU): zero density.
AIR_HU = -1000.0
#: The projections ``--projections`` names: maximum, average and minimum intensity over the phases.
PROJECTIONS = ("mip", "aip", "minip")


def conserve_mass(hu, jacobian) -> np.ndarray:
    """``(z, y, x) float32`` HU of a resampled image ``hu : (z, y, x)`` scaled so that mass is
    conserved: ``(hu + 1000) · jacobian − 1000``, with ``jacobian : (z, y, x)`` the determinant
    ``det(I + ∇w)`` of the resampling field ``w`` on the same grid
    (:func:`lungdeform.playback.displacement_field.jacobian_determinant`)."""
    hu = np.asarray(hu)
    j = np.asarray(jacobian)
    if hu.shape != j.shape:
        raise InputError(f"mass conservation: the image has shape {hu.shape}, the Jacobian {j.shape}")
    return ((hu.astype(np.float32) - np.float32(AIR_HU)) * j.astype(np.float32) + np.float32(AIR_HU)).astype(np.float32)


def resample_by_tissue(image: Image, lung, field, grid: Image | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (HU) resampled through the inverse ``field : (z, y, x, 3)`` mm LPS on ``grid``'s
    grid (its own without one) with the lung surface kept sharp (module docstring): returns
    ``(hu, lung_at_state)``, the ``(z, y, x) float32`` HU before the Jacobian scaling
    (:func:`conserve_mass`) and the ``(z, y, x) bool`` lung at the state (the mask resampled by nearest
    neighbour). ``lung : (z, y, x) bool`` is the lung mask on ``image``'s own grid. Arithmetic in
    float32: an integer image resampled as it is would be truncated toward zero (+0.5 HU in the lungs,
    +0.2 % of their mass)."""
    m = np.asarray(lung)
    if m.shape != image.array.shape:
        raise InputError(f"lung mask: shape {m.shape}, the image {image.source} {image.array.shape}; "
                         "give the mask on the image's own grid")
    m = m.astype(bool)
    rho = image.array.astype(np.float32) - np.float32(AIR_HU)
    # one linear pass over (ρ·m, m, ρ, 1): the lung's share, its fraction in each stencil, the whole
    # image, and 1 where the source point lies in the image (0 outside, where the ordinary resampling
    # fills with the image's minimum, air in a CT)
    ones = np.ones_like(rho)
    lung_rho, f, all_rho, seen = np.moveaxis(resample_channels(
        image, np.stack([np.where(m, rho, np.float32(0)), m.astype(np.float32), rho, ones], axis=-1), field,
        grid=grid), -1, 0)
    all_rho = all_rho + (1 - seen) * np.float32(float(np.min(image.array)) - AIR_HU)
    at_state = resample_image(Image(m.astype(np.uint8), image.spacing, image.origin, image.direction, image.source),
                              field, label=True, default=0, grid=grid).array > 0
    rest = 1.0 - f
    with np.errstate(divide="ignore", invalid="ignore"):
        in_lung = lung_rho / f
        in_rest = np.where(rest > 1e-6, (all_rho - lung_rho) / rest, all_rho)
    out = np.where(at_state & (f > 1e-6), in_lung, in_rest) + np.float32(AIR_HU)
    return out.astype(np.float32), at_state


def model_lung_mask(model, image: Image) -> np.ndarray:
    """``(z, y, x) bool``: the voxels of ``image``'s grid whose centres lie inside any of ``model``'s
    lungs at rest (its rest surfaces, mm LPS, in the image's world: the model's rest scan; module
    docstring). :class:`InputError` when a lung's rest surface reaches beyond the image's box (its
    voxels' outer faces) by more than half a voxel: the image is not the model's rest scan, or crops
    its lungs, and a mask cut at the edge would be wrong without a word. (A lung that the segmentation
    cut at the grid's edge, as POPI's at its bottom slice, meshes through those voxels' outer faces,
    its smoothing a little beyond: 0.1 mm on POPI.)"""
    grid = Grid.of(image)
    size = np.array(grid.shape[::-1], int)  # (i, j, k)
    mask = np.zeros(grid.shape, bool)
    for side, lung in model.lungs.items():
        v = np.asarray(lung.surface.vertices, float)
        ijk = grid.index(v)
        lo, hi = ijk.min(axis=0), ijk.max(axis=0)
        if np.any(lo < -1.0) or np.any(hi > size):
            raise InputError(f"--density: the model's {side} lung at rest spans {np.round(v.min(axis=0), 1).tolist()} to "
                             f"{np.round(v.max(axis=0), 1).tolist()} mm LPS, beyond IMAGE {image.source}'s box "
                             f"({size.tolist()} voxels of {np.round(grid.spacing, 3).tolist()} mm at "
                             f"{np.round(grid.origin, 1).tolist()}): IMAGE is not the model's rest scan or crops its "
                             "lungs; give --lung-mask (the lungs segmented on IMAGE) or --no-lung-mask")
        # only the lung's box of voxels is filled: a sub-grid whose voxel (0, 0, 0) is the box's first
        i0, i1 = np.maximum(np.floor(lo).astype(int), 0), np.minimum(np.ceil(hi).astype(int) + 1, size)
        sub = Grid(tuple(int(n) for n in (i1 - i0)[::-1]), grid.spacing, grid.world(i0), grid.direction)
        mask[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]] |= surface_mask(v, lung.surface.faces, sub)
    if not mask.any():
        raise InputError(f"--density: no voxel centre of IMAGE {image.source} lies inside the model's lungs at rest "
                         "(voxels larger than the lungs?); give --lung-mask or --no-lung-mask")
    return mask


def mass_g(hu, voxel_ml: float, mask=None) -> float:
    """Mass (g) of an image in HU, ``Σ (HU + 1000) / 1000 · voxel_ml`` over the voxels of ``mask``
    (``(z, y, x) bool``, or float weights: the fraction of each voxel in the region, e.g. a mask
    resampled linearly; the whole image without one): the figure ``warp --density`` conserves."""
    a = (np.asarray(hu, np.float64) - AIR_HU) / 1000.0
    if mask is not None:
        w = np.asarray(mask)
        a = a[w] if w.dtype == bool else a * w
    return float(a.sum() * float(voxel_ml))


def as_pixel_type(values, dtype) -> np.ndarray:
    """``values`` in the image's pixel ``dtype``: rounded to the nearest integer for an integer type;
    :class:`InputError` when a value falls outside that type's range (no silent clipping)."""
    dtype = np.dtype(dtype)
    if not np.issubdtype(dtype, np.integer):
        return np.asarray(values, dtype)
    r = np.rint(values)
    info = np.iinfo(dtype)
    lo, hi = float(r.min(initial=0)), float(r.max(initial=0))
    if lo < info.min or hi > info.max:
        raise InputError(f"--density: the mass-conserving CT numbers span {lo:.0f} to {hi:.0f} HU, outside the "
                         f"image's pixel type {dtype} ({info.min} to {info.max}); write a float image (.mha of float32)")
    return r.astype(dtype)


def parse_projections(text: str | None) -> list[str]:
    """The projection names of ``--projections`` (comma-separated ``mip``, ``aip``, ``minip``), in the
    given order, each once; :class:`InputError` for an unknown or repeated name, or none."""
    if text is None:
        return []
    names = [t.strip().lower() for t in text.split(",")]
    unknown = [n for n in names if n not in PROJECTIONS]
    if unknown or not names or len(set(names)) != len(names):
        raise InputError(f"--projections must be a comma-separated subset of {','.join(PROJECTIONS)}, each once; "
                         f"got {text!r}")
    return names


class Projector:
    """Running maximum, sum and minimum of the phases' images ``(z, y, x)``, one phase at a time (no
    stack of every phase in memory); :meth:`result` the ``(z, y, x) float32`` projection by name."""

    def __init__(self):
        self.high = self.low = self.total = None
        self.count = 0

    def add(self, image) -> None:
        a = np.asarray(image, np.float32)
        if self.count == 0:
            self.high, self.low, self.total = a.copy(), a.copy(), a.astype(np.float64)
        else:
            if a.shape != self.high.shape:
                raise InputError(f"projections: phase {self.count} has shape {a.shape}, phase 0 {self.high.shape}")
            np.maximum(self.high, a, out=self.high)
            np.minimum(self.low, a, out=self.low)
            self.total += a
        self.count += 1

    def result(self, name: str) -> np.ndarray:
        if self.count == 0:
            raise InputError("projections: no phase was added")
        if name == "mip":
            return self.high
        if name == "minip":
            return self.low
        if name == "aip":
            return (self.total / self.count).astype(np.float32)
        raise InputError(f"unknown projection {name!r}; expected one of {', '.join(PROJECTIONS)}")
