"""Mask and label images to closed lung surfaces.

Pipeline of :func:`extract_surface` (each step says what it fixes):

1. select the voxels of the requested labels (None = any non-zero);
2. crop to their bounding box (speed only);
3. keep the largest 6-connected component (stray islands would become extra surface pieces); a
   dropped component larger than :data:`MAX_DROPPED_FRACTION` of the kept one is refused
   (:class:`MaskError`: two lungs in one label, say), smaller specks are reported in a note with
   their total volume;
4. fill internal cavities (vessels or airways left out of a lung mask would become inner
   surfaces; the model needs the outer lung surface only);
5. pad by one background voxel, so that the surface is closed where the mask touches the volume
   border (the ITK example masks touch the cropped medial face); the faces it touches are named
   in a warning (the lung may be cropped there);
6. marching cubes (scikit-image, Lewiner, level 0.5) in voxel index space, then index → world mm
   LPS through spacing, direction and origin (:func:`lungdeform.io.grid.index_to_world`); faces are
   flipped if needed so that the signed volume is positive (outward), which also covers
   ``det(direction) < 0``;
7. volume-preserving Taubin smoothing (:func:`lungdeform.geometry.remesh.taubin_smooth`) against the voxel
   staircase;
8. optional decimation to a vertex budget (fast-simplification), then cleanup
   (:func:`lungdeform.geometry.remesh.clean_mesh`): degenerate and duplicate faces removed, duplicate
   vertices merged, non-manifold fins and pinches removed, so that
   :func:`lungdeform.geometry.mesh.check_surface` passes.

Images are :class:`lungdeform.io.grid.Image` (read by :func:`lungdeform.io.image.read_image`); their
arrays follow SimpleITK: ``array`` is indexed ``[k, j, i]`` = ``[z, y, x]``; spacing, origin and
voxel indices ``ijk`` are ordered ``(x, y, z)``. Surfaces are in mm, LPS world.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
from scipy import ndimage
from skimage.measure import marching_cubes

from lungdeform.errors import InputError, MaskError, MeshError, UnitsError
from lungdeform.geometry.mesh import Surface, SurfaceReport, check_surface, signed_volume
from lungdeform.geometry.remesh import clean_mesh, decimate, largest_surface_piece, taubin_smooth

from .grid import Image, index_to_world

#: Lobe label maps (coronacases convention): 1 left upper, 2 left lower, 3 right upper,
#: 4 right middle, 5 right lower lobe.
LOBE_LABELS: dict[str, tuple[int, ...]] = {"left": (1, 2), "right": (3, 4, 5)}

#: A dropped mask component larger than this fraction of the kept (largest) one is refused rather
#: than dropped: it is lung, not a speck (two lungs in one label, or a lung split by the mask).
MAX_DROPPED_FRACTION = 0.2


# =========================================================================== labels
def side_mask(image: Image, side: str) -> Image:
    """The ``side`` lung of a lobe label map as a 0/1 image; other images are returned unchanged.

    A lobe map (non-zero labels within 1–5, more than one of them: the coronacases convention of
    :data:`LOBE_LABELS`) gives the voxels of ``LOBE_LABELS[side]``. The convention is checked in
    the world frame (LPS: the left lung lies at larger x): when the chosen lobes' centroid is not on
    ``side`` of the other lobes' centroid, :class:`MaskError` is raised naming the file, rather than
    returning the wrong lung. A binary mask or a single label is returned as it is.
    """
    if side not in LOBE_LABELS:
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    a = np.asarray(image.array)
    values = np.unique(a[a != 0]) if a.size else np.zeros(0)
    if values.size < 2 or not np.all(np.isin(values, np.arange(1, 6))):
        return image
    want = np.isin(a, LOBE_LABELS[side])
    other = (a != 0) & ~want
    if not want.any():
        raise MaskError(f"{image.source}: lobe labels {sorted(int(v) for v in values)}: none of the {side} lobes "
                        f"{list(LOBE_LABELS[side])}")
    if other.any():
        cw = image.index_to_world(np.array([ndimage.center_of_mass(want)[::-1]]))[0]
        co = image.index_to_world(np.array([ndimage.center_of_mass(other)[::-1]]))[0]
        if (cw[0] - co[0]) * (1 if side == "left" else -1) <= 0:
            raise MaskError(f"{image.source}: labels {list(LOBE_LABELS[side])} ({side} lobes in the coronacases "
                            f"convention) lie on the other side (LPS x {cw[0]:.0f} mm vs {co[0]:.0f} mm): "
                            "not a left/right lobe map in that convention")
    return Image(want.astype(np.uint8), image.spacing, image.origin, image.direction,
                 f"{image.source} ({side} lobes {','.join(map(str, LOBE_LABELS[side]))})")


def label_groups(spec) -> dict[str, tuple[int, ...] | None]:
    """Normalise a label selection to ``{group name: labels}``.

    - ``None`` -> ``{"": None}``: one surface of all non-zero voxels;
    - an int or a sequence of ints -> one group, e.g. ``{"labels 1,2": (1, 2)}``;
    - a mapping ``{"left": (1, 2), ...}`` -> as given;
    - a string (CLI form): groups separated by ``;``; a group is ``name=1,2``, a list of
      :data:`LOBE_LABELS` names (``"left,right"`` gives two groups; ``"lungs"`` = both), or a
      comma-separated list of ints (one group).
    """
    if spec is None:
        return {"": None}
    if isinstance(spec, Mapping):
        return {str(k): _as_labels(v, f"labels[{k!r}]") for k, v in spec.items()}
    if isinstance(spec, (int, np.integer)):
        return {f"label {int(spec)}": (int(spec),)}
    if isinstance(spec, str):
        groups: dict[str, tuple[int, ...] | None] = {}
        for part in (s.strip() for s in spec.split(";")):
            if not part:
                continue
            if "=" in part:
                name, values = part.split("=", 1)
                groups[name.strip()] = _parse_ints(values, spec)
                continue
            tokens = [t.strip().lower() for t in part.split(",") if t.strip()]
            if tokens == ["lungs"]:
                groups.update(LOBE_LABELS)
            elif all(t in LOBE_LABELS for t in tokens):
                groups.update({t: LOBE_LABELS[t] for t in tokens})
            else:
                values = _parse_ints(part, spec)
                groups["labels " + ",".join(map(str, values))] = values
        if not groups:
            raise InputError(f"labels: empty selection {spec!r}")
        return groups
    values = _as_labels(spec, "labels")
    return {"labels " + ",".join(map(str, values)): values}


def _parse_ints(text: str, spec: str) -> tuple[int, ...]:
    try:
        values = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise InputError(
            f"labels: cannot read {spec!r}; use names ({', '.join(LOBE_LABELS)}, lungs), "
            "integers '1,2', or 'name=1,2;other=3'"
        ) from None
    if not values:
        raise InputError(f"labels: empty group in {spec!r}")
    return values


def _as_labels(value, name: str) -> tuple[int, ...]:
    arr = np.atleast_1d(np.asarray(value))
    if arr.size == 0 or arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{name} must be a non-empty sequence of integer labels, got {value!r}")
    return tuple(int(x) for x in arr)


# =========================================================================== pipeline
@dataclass(frozen=True)
class MaskSurface:
    """Result of :func:`extract_surface`.

    ``surface`` passed :func:`check_surface`; ``report`` is that check's report with ``notes``
    (what the pipeline changed) as its repairs and ``warnings`` (suspicious but usable input: the
    mask touches the image border) as its warnings; ``timings`` are
    seconds per stage (mask, marching_cubes, smooth, decimate, check).
    """

    surface: Surface
    report: SurfaceReport
    notes: tuple[str, ...]
    components_dropped: int
    voxels_filled: int
    timings: dict[str, float] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()


def mask_to_surface(
    image: Image,
    labels=None,
    *,
    smooth_iterations: int = 10,
    target_vertices: int | None = None,
    name: str | None = None,
) -> Surface:
    """Closed, outward, manifold surface (mm LPS) of ``labels`` in ``image``.

    One-shot form of :func:`extract_surface` (see the module docstring for the steps).
    Raises :class:`MaskError` naming the file and labels when there is no foreground.
    """
    return extract_surface(
        image, labels, smooth_iterations=smooth_iterations,
        target_vertices=target_vertices, name=name,
    ).surface


def extract_surface(
    image: Image,
    labels=None,
    *,
    smooth_iterations: int = 10,
    target_vertices: int | None = None,
    name: str | None = None,
) -> MaskSurface:
    """Surface of the selected labels, with a record of what the pipeline changed.

    ``labels``: None (any non-zero voxel) or a sequence of ints. ``target_vertices``: decimate
    to about this many vertices (None: keep the marching-cubes resolution).
    """

    what = "any non-zero label" if labels is None else f"labels {list(_as_labels(labels, 'labels'))}"
    source = image.source
    name = name or Path(source).name
    if smooth_iterations < 0:
        raise InputError(f"smooth_iterations must be >= 0, got {smooth_iterations}")
    if target_vertices is not None and target_vertices < 100:
        raise InputError(f"target_vertices must be at least 100, got {target_vertices}")
    t = {}
    t0 = time.perf_counter()
    fg = _foreground(image.array, labels, source, what)
    notes: list[str] = []
    warnings = border_warnings(fg)
    fg, lo, dropped, n_filled = _prepared_mask(fg, notes, _Context(source, what, _voxel_ml(image)))
    t["mask"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    v, f = _marching_cubes_world(fg, lo, image, what, notes)
    del fg
    t["marching_cubes"] = time.perf_counter() - t0
    n_mc = len(v)

    t0 = time.perf_counter()
    if smooth_iterations:
        v = taubin_smooth(v, f, smooth_iterations)
        notes.append(f"Taubin-smoothed ({smooth_iterations} iterations)")
    t["smooth"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if target_vertices is not None and target_vertices < len(v):
        try:
            v, f, cleaned = decimate(v, f, target_vertices)
        except MeshError as exc:
            raise MeshError(f"{name or image.source}: {exc}") from exc
        notes.append(f"decimated {n_mc} -> {len(v)} vertices")
        notes.extend(cleaned)
    t["decimate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    v, f, report = _checked_surface(v, f, source, what, notes)
    t["check"] = time.perf_counter() - t0
    report = dataclasses.replace(report, repairs=tuple(notes), warnings=tuple(warnings))
    return MaskSurface(Surface(v, f, name), report, tuple(notes), dropped, n_filled, t, tuple(warnings))


@dataclass(frozen=True)
class _Context:
    """What :func:`_prepared_mask` needs to word its errors and notes."""

    source: str
    what: str
    voxel_ml: float


def _voxel_ml(image: Image) -> float:
    """Volume of one voxel of ``image`` (mL; spacing in mm, a rotation direction keeps volume)."""
    return float(np.prod(np.asarray(image.spacing, dtype=float))) / 1000.0


def border_warnings(fg: np.ndarray) -> list[str]:
    """A one-item list naming the image border faces that ``fg : (z, y, x) bool`` touches (voxel
    index axes i, j, k = x, y, z; low = index 0), or ``[]``: a lung cut by the border is cropped
    there, and its model would have a flat face that does not move like lung."""
    faces = []
    for name, np_axis in (("i", 2), ("j", 1), ("k", 0)):
        n = fg.shape[np_axis]
        for side, idx in (("low", 0), ("high", n - 1)):
            if np.take(fg, idx, axis=np_axis).any():
                faces.append(f"{name}-{side}")
    if not faces:
        return []
    whole = " (the whole image is foreground: is this a lung mask?)" if fg.all() else ""
    return [f"the mask touches the image border on faces {', '.join(faces)}; the lung may be cropped{whole}"]


def _foreground(a: np.ndarray, labels, source: str, what: str) -> np.ndarray:
    """Step 1: ``(z, y, x) bool`` voxels of ``labels`` in the array ``a`` (None: any non-zero, after
    refusing a CT in HU). :class:`MaskError` naming ``source`` when there are none."""
    if labels is None:
        if np.issubdtype(a.dtype, np.floating) or (a.size and a.min() < 0):
            lo, hi = a.min(), a.max()
            if lo < -100:  # a CT in HU, not a mask
                raise MaskError(
                    f"{source}: values {lo:g}..{hi:g} look like a CT, not a mask or label image; "
                    "segment the lungs first"
                )
            _refuse_fractions(a, source)
        fg = a != 0
    else:
        fg = np.isin(a, _as_labels(labels, "labels"))
    if not fg.any():
        raise MaskError(f"{source}: no foreground voxels for {what}")
    return fg


def _refuse_fractions(a: np.ndarray, source: str) -> None:
    """:class:`MaskError` naming ``source`` when the float array ``a`` holds values that are not whole
    numbers: a probability map, or a mask resampled with linear interpolation, whose every voxel above
    0 would otherwise count as lung (the lung grown by the blur, without a word). Which threshold is
    meant is the user's to say."""
    frac = a[a != np.rint(a)]
    if frac.size:
        raise MaskError(f"{source}: {frac.size} voxel(s) hold fractions ({float(frac.min()):g}..{float(frac.max()):g}), "
                        "not labels: a probability map or a mask resampled with linear interpolation? threshold it "
                        "first (e.g. at 0.5); lungdeform does not guess where the lung ends")


def _prepared_mask(fg: np.ndarray, notes: list[str], ctx: _Context) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Steps 2–5 on ``fg : (z, y, x) bool``: ``(padded mask, lo (3,) int, components dropped, voxels
    filled)``; ``lo`` is the (z, y, x) index of the crop's first voxel (before the one-voxel pad).
    What was changed (dropped specks with their volume, filled cavities) is appended to ``notes``."""
    idx = np.nonzero(fg.any(axis=(1, 2)))[0], np.nonzero(fg.any(axis=(0, 2)))[0], np.nonzero(fg.any(axis=(0, 1)))[0]
    lo = np.array([x[0] for x in idx])
    hi = np.array([x[-1] for x in idx]) + 1
    fg = fg[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    # largest 6-connected component
    lab, n = ndimage.label(fg)
    dropped = 0
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        keep = int(np.argmax(sizes)) + 1
        _check_dropped(np.delete(sizes, keep - 1), int(sizes[keep - 1]), ctx)
        fg = lab == keep
        dropped = n - 1
        n_vox = int(sizes.sum() - sizes[keep - 1])
        notes.append(f"kept the largest of {n} mask components ({sizes[keep - 1] * ctx.voxel_ml:.0f} mL); dropped "
                     f"{dropped} ({n_vox} voxels, {n_vox * ctx.voxel_ml:.3g} mL in all)")
    del lab
    filled = ndimage.binary_fill_holes(fg)
    n_filled = int(filled.sum() - fg.sum())
    if n_filled:
        notes.append(f"filled {n_filled} voxels of internal cavities")
    return np.pad(filled, 1), lo, dropped, n_filled


def _check_dropped(others: np.ndarray, kept: int, ctx: _Context) -> None:
    """:class:`MaskError` when a component other than the kept one (``others``, voxel counts) is
    larger than :data:`MAX_DROPPED_FRACTION` of the ``kept`` one: dropping it would lose lung."""
    big = np.sort(others[others > MAX_DROPPED_FRACTION * kept])[::-1]
    if big.size == 0:
        return
    ml = ", ".join(f"{x * ctx.voxel_ml:.0f}" for x in big[:3]) + (", …" if big.size > 3 else "")
    raise MaskError(
        f"{ctx.source}: {ctx.what} has {big.size + 1} large separate components (kept {kept * ctx.voxel_ml:.0f} mL; "
        f"would drop {ml} mL, over {MAX_DROPPED_FRACTION:.0%} of it): two lungs in one label? "
        "select one lung per surface (--labels) or split the mask"
    )


def _marching_cubes_world(fg: np.ndarray, lo: np.ndarray, image: Image, what: str,
                          notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Step 6: ``(vertices (n, 3) float mm LPS, faces (m, 3) int)`` of the padded crop ``fg`` whose
    first unpadded voxel is (z, y, x) index ``lo`` of ``image``; the largest piece, faces outward."""
    try:
        verts_zyx, faces, _, _ = marching_cubes(fg.astype(np.float32), level=0.5, allow_degenerate=False)
    except (ValueError, RuntimeError) as exc:
        raise MaskError(f"{image.source}: marching cubes failed for {what} ({exc})") from exc
    # padded cropped index (z, y, x) -> full-volume index (i, j, k) = (x, y, z)
    ijk = verts_zyx[:, ::-1].astype(np.float64) - 1.0 + lo[::-1]
    v = index_to_world(ijk, image.spacing, image.origin, image.direction)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    v, f, extra = largest_surface_piece(v, f)
    if extra:
        notes.append(f"dropped {extra} small surface pieces")
    if signed_volume(v, f) < 0:  # index->world flips handedness when det(direction) < 0, etc.
        f = np.ascontiguousarray(f[:, ::-1])
    return v, f


def _checked_surface(v: np.ndarray, f: np.ndarray, source: str, what: str, notes: list[str]):
    """:func:`check_surface` of the final surface, cleaned (:func:`clean_mesh`, noted) only when the
    check fails; a wrong size becomes :class:`MaskError` (the mask's spacing, not the units)."""
    try:
        try:
            return check_surface(v, f, source=f"{source} ({what})")
        except UnitsError:
            raise
        except MeshError:
            # an undecimated surface has not been cleaned: marching cubes on a real mask can leave
            # fins and sheets touching along an edge (voxels that share only an edge). Clean it only
            # when needed, so that surfaces that pass as they are stay bit-identical.
            v, f, cleaned = clean_mesh(v, f)
            notes.extend(cleaned)
            return check_surface(v, f, source=f"{source} ({what})")
    except UnitsError as exc:  # image spacing is in mm: a wrong size is the mask's, not the units'
        size = float(np.linalg.norm(np.ptp(v, axis=0)))
        raise MaskError(
            f"{source}: the surface of {what} is {size:.4g} mm across, not the size of a lung "
            "(check the voxel spacing in the image header)"
        ) from exc
    except MeshError as exc:  # a defect of this pipeline, not of the input: say so
        raise MeshError(f"{exc} [after mask_to_surface; try other smoothing/decimation settings]") from exc
