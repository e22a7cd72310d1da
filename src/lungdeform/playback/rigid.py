"""A structure that moves rigidly inside a breathing field (a tumour that does not inflate with the lung).

Behind ``lungdeform dvf|warp --rigid-structure NAME --rtstruct FILE`` and ``--rigid-mask MASK``
(docs/RADIOTHERAPY.md, "A rigid tumour"). The model's interior field stretches everything inside a
lung by the lung's volume change (a GTV's mean Jacobian ≈ 1.10 on the POPI CT at +500 mL); a solid
tumour is far stiffer than the parenchyma around it and keeps its volume. Here the field ``f`` inside
the structure's region ``S`` is replaced by the best rigid motion of ``S`` under ``f`` (least
squares, Kabsch: the rotation ``R`` and the centroid's motion ``t``), blended back to ``f`` over a
border of ``border_mm`` outside ``S`` by the smoothstep :func:`lungdeform.playback.displacement_field.fade` of the
distance to ``S``:

    f'(x) = f(x) + β(x) · (R (x − c) + c + t − x − f(x)),   β = 1 in S, 0 from border_mm outside.

Inside ``S`` the map is rigid (Jacobian 1: the volume is kept); the border absorbs the difference.
Arrays: fields ``(z, y, x, 3) float32`` mm LPS, masks ``(z, y, x) bool`` on the same
:class:`~lungdeform.playback.displacement_field.Grid`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from types import SimpleNamespace

import numpy as np
from scipy import ndimage

from lungdeform.errors import FoldError, InputError
from lungdeform.geometry.distance import point_to_surface
from lungdeform.geometry.mesh import winding_numbers

from .displacement_field import Grid, Lattice, fade, inside_lattice, jacobian_determinant, jacobian_range

#: Default width (mm) of the border over which the rigid motion is blended back into the field.
BORDER_MM = 10.0


@dataclass(frozen=True)
class RigidMotion:
    """The best rigid motion of a region: ``rotation`` (3, 3), ``centroid`` (3,) mm LPS of the region,
    ``translation`` (3,) mm (the centroid's motion); ``residual_mm`` the RMS of the field about it."""

    rotation: np.ndarray
    centroid: np.ndarray
    translation: np.ndarray
    residual_mm: float

    def displacement(self, points) -> np.ndarray:
        """``(n, 3) float`` mm: ``R (x − c) + c + t − x`` at ``points : (n, 3)`` mm LPS."""
        p = np.asarray(points, float)
        return (p - self.centroid) @ self.rotation.T + self.centroid + self.translation - p


def best_rigid(points, displacement) -> RigidMotion:
    """The rigid motion closest (least squares) to ``points : (n, 3)`` mm moving by ``displacement :
    (n, 3)`` mm (Kabsch, a proper rotation)."""
    p = np.asarray(points, float)
    q = p + np.asarray(displacement, float)
    if len(p) < 4:
        raise InputError(f"a rigid structure needs at least 4 voxels on the grid, got {len(p)}")
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    u, _s, vt = np.linalg.svd((p - cp).T @ (q - cq))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    motion = RigidMotion(rot, cp, cq - cp, 0.0)
    res = float(np.sqrt(np.mean(np.sum((motion.displacement(p) - (q - p)) ** 2, axis=1))))
    return RigidMotion(rot, cp, cq - cp, res)


def surface_mask(vertices, faces, grid: Grid) -> np.ndarray:
    """``(z, y, x) bool``: the voxels of ``grid`` whose centres lie inside a closed surface (mm LPS)."""
    size = np.array(grid.shape[::-1], int)
    lat = Lattice(np.zeros(3, int), np.ones(3, int), size, ((0, 0, 0), tuple(int(s) for s in size)))

    surface = SimpleNamespace(vertices=np.asarray(vertices, float), faces=np.asarray(faces, np.int64))
    return inside_lattice(surface, grid, lat)


def rigidify(field: np.ndarray, grid: Grid, mask, border_mm: float = BORDER_MM) -> RigidMotion:
    """Make ``field`` rigid, in place, over the region ``mask : (z, y, x) bool`` (module docstring),
    blended back over ``border_mm`` outside it. Returns the rigid motion used."""
    m = np.asarray(mask, bool)
    if m.shape != tuple(field.shape[:3]):
        raise InputError(f"rigid structure: mask of shape {m.shape} on a field of shape {field.shape[:3]}")
    if not (np.isfinite(border_mm) and border_mm > 0):
        raise InputError(f"--rigid-border-mm must be a finite number > 0 mm, got {border_mm}")
    k, j, i = np.nonzero(m)
    motion = best_rigid(grid.world(np.stack([i, j, k], axis=1)), field[k, j, i])
    pad = np.ceil(border_mm / grid.spacing).astype(int) + 1  # (i, j, k) voxels
    lo = np.maximum(np.array([i.min(), j.min(), k.min()]) - pad, 0)
    hi = np.minimum(np.array([i.max(), j.max(), k.max()]) + pad + 1, grid.shape[::-1])
    box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    # rigid one voxel beyond the region, so that the region's own voxels (whose central differences
    # reach their neighbours) see a rigid map: Jacobian 1 on every voxel of it
    core = ndimage.binary_dilation(m[box], structure=np.ones((3, 3, 3), bool))
    dist = ndimage.distance_transform_edt(~core, sampling=grid.spacing[::-1])
    beta = fade(dist, border_mm).reshape(dist.shape)
    kk, jj, ii = np.nonzero(beta > 0)
    world = grid.world(np.stack([ii + lo[0], jj + lo[1], kk + lo[2]], axis=1))
    sub = field[box]
    f = sub[kk, jj, ii].astype(float)
    sub[kk, jj, ii] = (f + beta[kk, jj, ii, None] * (motion.displacement(world) - f)).astype(field.dtype)
    return motion


def region_volume_ml(mask, field: np.ndarray, grid: Grid) -> float:
    """Volume (mL) of a region ``mask : (z, y, x)`` of the reference after resampling through the
    inverse field ``field`` (ITK convention, :func:`lungdeform.io.image.resample_image`): the sum of the
    mask's trilinear interpolation at ``y + field(y)`` over every voxel ``y``, times the voxel volume
    (partial voxels counted; a rigid motion keeps it to interpolation error)."""
    m = np.asarray(mask, np.float32)
    k, j, i = np.nonzero(_moved_bounds(m > 0, field, grid.spacing))
    y = grid.world(np.stack([i, j, k], axis=1)) + field[k, j, i]
    idx = grid.index(y)[:, ::-1].T
    vals = ndimage.map_coordinates(m, idx, order=1, mode="constant", cval=0.0)
    return float(vals.sum() * np.prod(grid.spacing) / 1000.0)


def _moved_bounds(m, field, spacing) -> np.ndarray:
    """Voxels within the mask's box grown by the field's largest displacement (where the moved region can be)."""
    reach = float(np.abs(field).max()) if field.size else 0.0
    out = np.zeros(m.shape, bool)
    k, j, i = np.nonzero(m)
    if not len(k):
        return out
    gi, gj, gk = (int(np.ceil(reach / s)) + 2 for s in spacing)
    out[max(k.min() - gk, 0):k.max() + gk + 1, max(j.min() - gj, 0):j.max() + gj + 1,
        max(i.min() - gi, 0):i.max() + gi + 1] = True
    return out


@dataclass(frozen=True)
class RigidReport:
    """What :func:`rigid_field` did: the region's volume ``volume_ml`` in the reference, at the state
    with the plain field (``elastic_ml``) and with the rigid one (``rigid_ml``), the motion used."""

    volume_ml: float
    elastic_ml: float
    rigid_ml: float
    motion: RigidMotion


def rigid_field(result, grid: Grid, mask, border_mm: float = BORDER_MM) -> RigidReport:
    """Make ``result.field`` (a :class:`~lungdeform.playback.displacement_field.FieldResult`) rigid, in place, over a
    region ``mask : (z, y, x) bool`` of the reference, blended over ``border_mm``: a forward field over
    the region itself, an inverse (resampling) field over where the region lies at the state (the
    region resampled through the field). The Jacobian is checked again (:class:`FoldError` on folding)."""
    m = np.asarray(mask, bool)
    if not m.any():
        raise InputError("the rigid structure covers no voxel of the grid: is it in the image's frame?")
    voxel_ml = float(np.prod(grid.spacing)) / 1000.0
    field = result.field
    volume = region_volume_ml if result.inverse else _forward_volume
    elastic = volume(m, field, grid)
    if result.inverse:  # where the region lies at the state: the voxels whose source is in it
        k, j, i = np.nonzero(_moved_bounds(m, field, grid.spacing))
        src = grid.index(grid.world(np.stack([i, j, k], axis=1)) + field[k, j, i])[:, ::-1].T
        inside = ndimage.map_coordinates(m.astype(np.float32), src, order=1, mode="constant", cval=0.0) >= 0.5
        region = np.zeros(m.shape, bool)
        region[k[inside], j[inside], i[inside]] = True
    else:
        region = m
    motion = rigidify(field, grid, region, border_mm)
    lo, _hi, folded = jacobian_range(field, grid)
    if folded:
        raise FoldError(f"the field folds at {folded} voxel(s) after the rigid structure was blended in (Jacobian "
                        f"down to {lo:.3g}); give a wider --rigid-border-mm")
    return RigidReport(float(m.sum() * voxel_ml), elastic, volume(m, field, grid), motion)


def _forward_volume(mask, field: np.ndarray, grid: Grid) -> float:
    """Volume (mL) of ``mask`` moved by the forward field: ``Σ det(I + ∇u) · dV`` over its voxels."""
    k, j, i = np.nonzero(mask)
    lo = np.maximum(np.array([k.min(), j.min(), i.min()]) - 1, 0)
    hi = np.array([k.max(), j.max(), i.max()]) + 2
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    jac = jacobian_determinant(field[box], grid.spacing, grid.direction)
    return float(jac[mask[box]].sum() * np.prod(grid.spacing) / 1000.0)


#: About this many samples of a rigid structure's inside fit its rigid motion under a point field.
RIGID_SAMPLES = 10_000
#: A rigid structure's points are rigid this far (mm) outside its surface, as :func:`rigidify` makes one
#: voxel beyond the region rigid: the surface through a structure's contours lies within a quarter of
#: its 0.5 mm pixels of them (:mod:`lungdeform.geometry.contours`), so the contour points stay rigid.
RIGID_REACH_MM = 0.5


@dataclass(frozen=True, eq=False)
class RigidRegion:
    """A structure (closed surface ``vertices (n, 3)`` mm LPS of the model's scan, ``faces``) that moves
    rigidly with points (``lungdeform track --rigid-structure``), as :func:`rigidify` keeps it rigid
    in a field (``dvf|warp --rigid-structure``): at each state its inside moves by its best rigid
    motion under the model's forward point field (:func:`best_rigid` of :attr:`samples`, the voxel
    centres inside it on a regular grid of about :data:`RIGID_SAMPLES`), blended back to the field
    over ``border_mm`` outside it by the smoothstep of the distance to its surface. ``placement``:
    the lung of each sample (:func:`lungdeform.playback.trajectory.place_points`), once placed."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    border_mm: float = BORDER_MM
    placement: object = None

    @cached_property
    def samples(self) -> np.ndarray:
        """``(k, 3) float`` mm LPS: points of a regular grid inside the surface."""
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        step = max(float(np.prod(hi - lo) / RIGID_SAMPLES) ** (1.0 / 3.0), 0.1)
        shape = tuple(int(n) for n in (np.ceil((hi - lo) / step).astype(int) + 1)[::-1])
        grid = Grid(shape, np.full(3, step), lo, np.eye(3))
        k, j, i = np.nonzero(surface_mask(self.vertices, self.faces, grid))
        if len(k) < 4:
            raise InputError(f"rigid structure {self.name!r}: too small to fit a rigid motion ({len(k)} samples inside)")
        return grid.world(np.stack([i, j, k], axis=1))

    def motions(self, moved_samples: np.ndarray) -> list[RigidMotion]:
        """Per state the best rigid motion of :attr:`samples` moved to ``moved_samples : (f, k, 3)`` mm."""
        return [best_rigid(self.samples, m - self.samples) for m in np.asarray(moved_samples, float)]

    def weights(self, points) -> np.ndarray:
        """``(n,) float`` β: 1 inside the structure and up to :data:`RIGID_REACH_MM` outside it, fading
        to 0 at ``border_mm`` beyond that."""
        p = np.asarray(points, float)
        inside = winding_numbers(p, self.vertices, self.faces) > 0.5
        d = np.where(inside, 0.0, np.maximum(point_to_surface(p, self.vertices, self.faces) - RIGID_REACH_MM, 0.0))
        return fade(d, self.border_mm)

    def applied(self, points, elastic: np.ndarray, motions: list[RigidMotion]) -> np.ndarray:
        """``(f, n, 3)`` mm: ``points (n, 3)`` moved to ``elastic (f, n, 3)`` by the field, made rigid
        by ``motions`` (one per state, :meth:`motions`) where :meth:`weights` says."""
        p = np.asarray(points, float)
        beta = self.weights(p)[None, :, None]
        rigid = np.stack([p + m.displacement(p) for m in motions])
        return elastic + beta * (rigid - elastic)
