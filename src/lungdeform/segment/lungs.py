"""Thoracic CT → left and right lung masks, with no learned weights.

Pipeline of :func:`segment_lungs` (each step names what it is for):

1. **threshold**: ``air = HU < air_hu`` (default −400 HU; lung parenchyma is ≈ −850 HU, soft
   tissue > −100 HU).
2. **outside air**: air components (6-connected, 3-D) that touch the in-plane border of the volume
   (front, back, left, right faces) are outside the body and dropped. The top and bottom faces are
   not used: lung apices and bases often touch them.
3. **lung candidate**: the 3-D components of the remaining air larger than ``min_lung_ml``
   (default 100 mL; bowel gas and stray bubbles are smaller). Lungs and airways usually form one
   component here.
4. **trachea seed**: from the top slice down, 2-D components of ``candidate ∧ HU < lumen_hu``
   (default −900 HU) of tracheal size (``30–1200 mm²``) whose centre lies within ``25 mm`` of the
   body's left–right centre; the topmost such component, closest to the centre, is the seed.
5. **airway tree**: region growing from the seed inside the candidate with a rising threshold
   (−1000 HU up to ``airway_max_hu``, default −900 HU, steps of 20 HU) and *explosion control*:
   growing stops before the first step whose volume more than doubles once the tree holds
   ≥ 5 mL, or exceeds ``airway_max_ml`` (leakage into parenchyma). The tree (trachea, main and
   the visible lobar bronchi) is removed with a one-voxel 6-connected dilation (its wall).
6. **left/right split**: the two largest remaining components ≥ 10 % of the total. If the lungs
   still touch (one component), the component is eroded in-plane until it separates (at most
   ``max_erosions`` voxels); the pieces are grown back geodesically inside the original mask.
   If erosion does not separate them, each axial slice is cut along the column with the fewest
   lung voxels within ``25 mm`` of the midline (minimal-cost cut). Side: the piece whose
   centroid lies at larger LPS world x is the **left** lung (LPS: +x = patient left).
7. **hole filling**: vessels, nodules and carved bronchi inside each lung are filled, per axial
   slice (2-D) and in 3-D.

Frames: masks are ``(z, y, x) bool`` arrays on the CT grid (SimpleITK order); geometry follows
:class:`lungdeform.io.grid.Image` (spacing x y z mm, origin mm LPS, direction columns in LPS).
Volumes are mL (= voxel count × voxel volume / 1000). Reading the CT and reordering its grid are
in :mod:`lungdeform.segment.ct`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from scipy import ndimage as ndi

from lungdeform.errors import InputError, MaskError
from lungdeform.io.grid import Image
from lungdeform.plot.figure import save_png
from lungdeform.plot.segmentation import label_overlay
from lungdeform.progress import Progress, silent

from .ct import axial_axes, check_ct, to_axial

_SIX = ndi.generate_binary_structure(3, 1)
#: 4-connected in-plane structure with no link across slices: per-slice (2-D) operations on a 3-D array.
_INPLANE = np.zeros((3, 3, 3), bool)
_INPLANE[1] = ndi.generate_binary_structure(2, 1)


# =========================================================================== result
@dataclass(frozen=True, eq=False)
class LungSegmentation:
    """Left and right lung masks of one CT and what was done to get them.

    Attributes
    ----------
    left, right : (z, y, x) bool
        Lung masks on the CT grid (``left`` = patient left, larger LPS x).
    airway : (z, y, x) bool
        The airway tree that was grown and removed (before the wall dilation).
    image : Image
        The CT (HU) whose geometry the masks share.
    volumes_ml : dict
        ``left``, ``right``, ``airway`` (grown tree), ``removed`` (tree + wall), ``candidate``
        (all inside-body air of the lung component(s), i.e. lungs + airways by plain threshold), mL.
    airway_removal : str
        One paragraph saying how the trachea and bronchi were found and removed.
    details : dict
        Seeds, thresholds, component sizes, split method, timings (s).
    """

    left: np.ndarray
    right: np.ndarray
    airway: np.ndarray
    image: Image
    volumes_ml: dict
    airway_removal: str
    details: dict = field(default_factory=dict)

    def labels(self) -> np.ndarray:
        """``(z, y, x) uint8`` label map: 0 background, 1 left lung, 2 right lung."""
        out = np.zeros(self.left.shape, np.uint8)
        out[self.left] = 1
        out[self.right] = 2
        return out

    def mask_image(self, side: str) -> Image:
        """The ``"left"`` or ``"right"`` mask as a uint8 :class:`Image` with the CT's geometry."""
        if side not in ("left", "right"):
            raise InputError(f"side must be 'left' or 'right', got {side!r}")
        m = (self.left if side == "left" else self.right).astype(np.uint8)
        im = self.image
        return Image(m, im.spacing, im.origin, im.direction, source=f"{im.source} ({side} lung)")


# =========================================================================== steps
def inside_body_air(ct: np.ndarray, air_hu: float) -> np.ndarray:
    """``(z, y, x) bool``: voxels below ``air_hu`` not connected (6-conn., 3-D) to the in-plane border."""
    air = ct < air_hu
    lab, _ = ndi.label(air, structure=_SIX)
    border = np.unique(np.concatenate([lab[:, 0, :].ravel(), lab[:, -1, :].ravel(),
                                       lab[:, :, 0].ravel(), lab[:, :, -1].ravel()]))
    keep = np.ones(lab.max() + 1, bool)
    keep[border] = False
    keep[0] = False
    return keep[lab]


def largest_components(mask: np.ndarray, min_voxels: int, structure=_SIX) -> tuple[np.ndarray, np.ndarray]:
    """Label ``mask``; return ``(labels (z, y, x) int, ids)`` of components ≥ ``min_voxels``, largest first."""
    lab, n = ndi.label(mask, structure=structure)
    if n == 0:
        return lab, np.zeros(0, int)
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    ids = np.nonzero(sizes >= max(min_voxels, 1))[0]
    return lab, ids[np.argsort(sizes[ids])[::-1]]


def find_trachea_seed(ct, candidate, spacing, body_center_x, lumen_hu=-900.0,
                      area_mm2=(30.0, 1200.0), max_offset_mm=25.0, search_fraction=0.35):
    """Find the trachea in the top slices. Returns ``(z, seed mask (y, x) bool, info)`` or None.

    Scans from the top slice of ``candidate`` down through ``search_fraction`` of its height; in each
    slice takes the 2-D components of ``candidate ∧ ct < lumen_hu`` with area in ``area_mm2`` and
    centre within ``max_offset_mm`` of ``body_center_x`` (voxel x, per slice); returns the first
    slice's component closest to the centre. Arrays are (z, y, x) in head-up order: the highest
    z index is the most cranial slice.
    """
    px = float(spacing[0] * spacing[1])
    zs = np.nonzero(candidate.any(axis=(1, 2)))[0]
    if zs.size == 0:
        return None
    order = zs[::-1]
    n_scan = max(1, int(np.ceil(search_fraction * len(zs))))
    for z in order[:n_scan]:
        lab, n = ndi.label(candidate[z] & (ct[z] < lumen_hu))
        if n == 0:
            continue
        sizes = np.bincount(lab.ravel())[1:] * px
        best = None
        for i in np.nonzero((sizes >= area_mm2[0]) & (sizes <= area_mm2[1]))[0] + 1:
            yy, xx = np.nonzero(lab == i)
            off = abs(xx.mean() - body_center_x[z]) * spacing[0]
            if off <= max_offset_mm and (best is None or off < best[1]):
                best = (i, off, float(sizes[i - 1]), float(xx.mean()), float(yy.mean()))
        if best is not None:
            info = {"slice": int(z), "area_mm2": best[2], "offset_mm": best[1],
                    "centre_voxel_xy": [best[3], best[4]]}
            return int(z), lab == best[0], info
    return None


@dataclass(frozen=True)
class AirwayGrowth:
    """The rising threshold of :func:`grow_airways`: from ``start_hu`` to ``max_hu`` in steps of
    ``step_hu`` (HU); a step is refused (leak) when the tree exceeds ``max_ml`` mL, or, once it holds
    ``min_tree_ml`` mL, grows by more than ``explosion_ratio`` times in one step."""

    start_hu: float = -1000.0
    max_hu: float = -900.0
    step_hu: float = 20.0
    min_tree_ml: float = 5.0
    explosion_ratio: float = 2.0
    max_ml: float = 400.0


def grow_airways(ct, candidate, seed, voxel_ml, growth: AirwayGrowth = AirwayGrowth()):
    """Region-grow the airway tree from ``seed`` with a rising threshold and explosion control
    (``growth``).

    Returns ``(tree (z, y, x) bool, info)``; ``info['history']`` lists ``[threshold HU, volume mL]``
    per step, ``info['threshold_hu']`` the accepted one and ``info['stopped']`` why growing stopped.
    """
    start_hu, max_hu, step_hu = growth.start_hu, growth.max_hu, growth.step_hu
    min_tree_ml, explosion_ratio, max_ml = growth.min_tree_ml, growth.explosion_ratio, growth.max_ml
    # work in the candidate's bounding box (speed)
    nz = [np.nonzero(candidate.any(axis=ax))[0] for ax in ((1, 2), (0, 2), (0, 1))]
    box = tuple(slice(v.min(), v.max() + 1) for v in nz)
    c, s, a = candidate[box], seed[box], ct[box]
    best, best_t, prev_ml, history, stopped = None, None, 0.0, [], "reached the maximum threshold"
    t = start_hu
    while t <= max_hu + 1e-9:
        lab, _ = ndi.label(c & (a < t), structure=_SIX)
        ids = np.unique(lab[s])
        ids = ids[ids > 0]
        grown = np.isin(lab, ids) if ids.size else np.zeros_like(c)
        ml = float(grown.sum()) * voxel_ml
        history.append([float(t), ml])
        if ml > max_ml:
            stopped = f"volume {ml:.0f} mL at {t:g} HU exceeds {max_ml:g} mL (leak)"
            break
        if prev_ml >= min_tree_ml and ml > explosion_ratio * prev_ml:
            stopped = f"volume jumped {prev_ml:.1f} → {ml:.1f} mL at {t:g} HU (leak)"
            break
        best, best_t, prev_ml = grown, t, ml
        t += step_hu
    tree = np.zeros_like(candidate)
    if best is not None:
        tree[box] = best
    return tree, {"threshold_hu": best_t, "history": history, "stopped": stopped}


def _two_seeds_grown(separated, m, shape, box, min_fraction):
    """Labels 1/2 grown back over ``m`` from the two largest pieces of ``separated``, or None when
    there are not two pieces or the smaller is below ``min_fraction`` of both."""
    lab, ids = largest_components(separated, 1)
    if ids.size < 2:
        return None
    sizes = np.bincount(lab.ravel())[ids[:2]]
    if sizes[1] < min_fraction * sizes.sum():
        return None
    seeds = np.zeros(lab.shape, np.int32)
    seeds[lab == ids[0]] = 1
    seeds[lab == ids[1]] = 2
    out = np.zeros(shape, np.int32)
    out[box] = _grow_back(m, seeds)
    return out


def _grow_back(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Geodesic growth of the labelled ``seeds`` (int, 0 = none) inside ``mask``, one 6-connected step
    at a time for every label in turn (lowest first), until no voxel changes. Returns the labels on
    ``mask``. One breadth-first pass (:func:`_grow_kernel`): each step a label claims the free mask
    voxels beside those it claimed in the step before, exactly what dilating the whole label by one
    voxel each step claimed (until 0.8: ``scipy.ndimage.binary_dilation`` of every label every step)."""
    out = np.ascontiguousarray(np.where(mask, seeds, 0), np.int32)
    labels = int(out.max()) if out.size else 0
    if labels > 0:
        _grow_kernel(np.ascontiguousarray(mask, np.bool_), out, labels)
    return out


@numba.njit(cache=True)
def _grow_kernel(mask, out, labels):
    """In place on ``out : (z, y, x) int32`` (labels 1…``labels``, 0 free): the growth of :func:`_grow_back`."""
    nz, ny, nx = mask.shape
    flat_mask, flat = mask.ravel(), out.ravel()
    buf = np.empty(flat.size, np.int64)  # every voxel enters a front at most once
    start, end = np.zeros(labels + 1, np.int64), np.zeros(labels + 1, np.int64)
    pos = 0
    for k in range(1, labels + 1):
        start[k] = pos
        for i in range(flat.size):
            if flat[i] == k:
                buf[pos] = i
                pos += 1
        end[k] = pos
    grew = True
    while grew:
        grew = False
        for k in range(1, labels + 1):
            first = pos
            for m in range(start[k], end[k]):
                i = buf[m]
                z, rem = divmod(i, ny * nx)
                y, x = divmod(rem, nx)
                for dz, dy, dx in ((-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)):
                    zz, yy, xx = z + dz, y + dy, x + dx
                    if 0 <= zz < nz and 0 <= yy < ny and 0 <= xx < nx:
                        j = (zz * ny + yy) * nx + xx
                        if flat_mask[j] and flat[j] == 0:
                            flat[j] = k
                            buf[pos] = j
                            pos += 1
            start[k], end[k] = first, pos
            grew = grew or pos > first
    return out


def _padded_box(mask: np.ndarray) -> tuple[slice, slice, slice]:
    """The bounding box of ``mask`` (z, y, x) with one voxel to spare on each side (within the array)."""
    nz = [np.nonzero(mask.any(axis=ax))[0] for ax in ((1, 2), (0, 2), (0, 1))]
    return tuple(slice(max(v.min() - 1, 0), v.max() + 2) for v in nz)


def erode_apart(mask: np.ndarray, max_erosions: int = 10, min_fraction: float = 0.1):
    """Cut one component at its narrowest neck: ``(labels (z, y, x) int32 with parts 1 and 2, erosions)``
    or None.

    ``mask`` is eroded in-plane (4-connected, per axial slice) one voxel at a time until its two
    largest pieces are each at least ``min_fraction`` of the two together; they are then grown back
    geodesically over ``mask`` (:func:`_grow_back`), so the cut falls where the pieces met: at the
    narrowest neck. None when ``max_erosions`` steps do not give two such pieces. Voxels of ``mask``
    not connected to either piece stay 0.
    """
    box = _padded_box(mask)
    m = mask[box]
    eroded = m
    for k in range(1, max_erosions + 1):
        eroded = ndi.binary_erosion(eroded, structure=_INPLANE)
        if not eroded.any():
            return None
        out = _two_seeds_grown(eroded, m, mask.shape, box, min_fraction)
        if out is not None:
            return out, k
    return None


def split_touching(mask: np.ndarray, spacing, midline_x: float, max_erosions: int = 10,
                   min_fraction: float = 0.1, cut_window_mm: float = 25.0):
    """Split one component holding both lungs into two labels (1, 2). Returns ``(labels, info)``.

    First in-plane erosion until two pieces of ≥ ``min_fraction`` of the eroded volume appear,
    grown back geodesically (:func:`_grow_back`); if ``max_erosions`` steps do not separate them,
    a per-slice cut along the column (x) with the fewest lung voxels within ``cut_window_mm`` of
    ``midline_x`` (voxel x). Raises :class:`MaskError` if neither separates the lungs.
    """
    apart = erode_apart(mask, max_erosions, min_fraction)
    if apart is not None:
        return apart[0], {"method": "in-plane erosion", "erosions": apart[1]}
    box = _padded_box(mask)
    m = mask[box]
    # minimal-cost cut per slice near the midline
    x0 = box[2].start
    half = int(round(cut_window_mm / spacing[0]))
    cut = m.copy()
    lo = max(int(midline_x) - half - x0, 0)
    hi = min(int(midline_x) + half - x0 + 1, m.shape[2])
    if hi <= lo:
        raise MaskError("the lungs touch and the midline lies outside the lung mask: cannot split them")
    for z in range(m.shape[0]):
        cols = m[z, :, lo:hi].sum(axis=0)
        if not cols.any():
            continue
        dist = np.abs(np.arange(lo, hi) + x0 - midline_x)
        j = lo + int(np.lexsort((dist, cols))[0])
        cut[z, :, j] = False
    out = _two_seeds_grown(cut, m, mask.shape, box, min_fraction)
    if out is not None:
        return out, {"method": "minimal-cost cut per slice near the midline", "erosions": max_erosions}
    raise MaskError(
        f"the lungs form one component that neither {max_erosions} in-plane erosions nor a midline cut "
        "separate; check the CT (one lung only, or lungs fused by disease)"
    )


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill holes per axial slice (2-D) and then in 3-D (vessels, nodules, carved bronchi)."""
    nz = [np.nonzero(mask.any(axis=ax))[0] for ax in ((1, 2), (0, 2), (0, 1))]
    if any(v.size == 0 for v in nz):
        return mask.copy()
    box = tuple(slice(v.min(), v.max() + 1) for v in nz)
    m = ndi.binary_fill_holes(mask[box], structure=_INPLANE)
    m = ndi.binary_fill_holes(m, structure=_SIX)
    out = np.zeros_like(mask)
    out[box] = m
    return out


# =========================================================================== pipeline
def segment_lungs(
    image: Image,
    *,
    air_hu: float = -400.0,
    lumen_hu: float = -900.0,
    airway_max_hu: float = -900.0,
    airway_max_ml: float = 400.0,
    min_lung_ml: float = 100.0,
    max_erosions: int = 10,
    progress: Progress | None = None,
) -> LungSegmentation:
    """Segment left and right lungs of a CT in HU (module docstring: the steps and their defaults).

    Raises :class:`MaskError` when no lung-sized air is found inside the body, or the lungs cannot
    be split, and :class:`InputError` for an image that is not CT in HU.
    """
    say = progress or silent
    options = {"air_hu": air_hu, "lumen_hu": lumen_hu, "airway_max_hu": airway_max_hu, "airway_max_ml": airway_max_ml,
               "min_lung_ml": min_lung_ml, "max_erosions": max_erosions, "progress": progress}
    check_ct(image)
    perm = axial_axes(image)
    if perm != (0, 1, 2):  # stored in another axis order (e.g. sagittal or coronal stacks)
        return _segment_transposed(image, perm, options)
    ct = np.asarray(image.array)
    sp = np.asarray(image.spacing, float)
    vml = image.voxel_ml
    timings, t0 = {}, time.perf_counter()
    # axial slices with the head at the top index: flip a feet-up stack into head-up order for the scan
    head_up = image.direction[2, 2] > 0
    if not head_up:
        ct = ct[::-1]

    say("threshold and outside air")
    inside = inside_body_air(ct, air_hu)
    timings["outside_air_s"] = time.perf_counter() - t0
    candidate, cand_ml, comp_ml = _lung_candidate(inside, vml, air_hu, min_lung_ml, image.source)
    timings["candidate_s"] = time.perf_counter() - t0

    say("trachea and bronchi")
    body_cx = _body_centre_x(ct, air_hu)
    tree, removed, grow, seed_info = _remove_airways(ct, candidate, sp, body_cx, vml, lumen_hu, airway_max_hu,
                                                     airway_max_ml)
    lungs = candidate & ~removed
    timings["airways_s"] = time.perf_counter() - t0

    say("left/right split")
    labels, split, n_dropped, dropped_ml = _split_left_right(lungs, body_cx, sp, vml, max_erosions, image.source)
    timings["split_s"] = time.perf_counter() - t0

    say("hole filling")
    left, right, cx = _filled_sides(labels, image, sp, head_up)
    if not head_up:
        left, right, tree, removed = left[::-1], right[::-1], tree[::-1], removed[::-1]
    timings["fill_s"] = time.perf_counter() - t0

    vol = _volumes_ml(left, right, tree, removed, cand_ml, vml, image.source)
    if seed_info is not None and not head_up:  # the seed's slice number on the image's own grid
        seed_info = {**seed_info, "slice": ct.shape[0] - 1 - seed_info["slice"]}
    desc = _airway_removal_text(seed_info, grow, tree, vol, split, lumen_hu)
    details = {
        "air_hu": air_hu,
        "candidate_components_ml": comp_ml,
        "trachea_seed": seed_info,
        "airway_growing": grow,
        "split": split,
        "small_pieces_dropped": n_dropped,
        "small_pieces_dropped_ml": dropped_ml,
        "centroid_world_x_mm": sorted(cx, reverse=True),
        "timings_s": timings,
    }
    return LungSegmentation(left, right, tree, image, vol, desc, details)


def _segment_transposed(image: Image, perm: tuple[int, int, int], options: dict) -> LungSegmentation:
    """:func:`segment_lungs` of an image stored in another axis order: segment it in axial
    (z, y, x) order, an exact transpose (``perm``, from :func:`~lungdeform.segment.ct.axial_axes`), and
    give the masks back on the image's own grid."""
    inv = tuple(int(a) for a in np.argsort(perm))
    seg = segment_lungs(to_axial(image, perm), **options)
    back = {k: np.ascontiguousarray(np.transpose(getattr(seg, k), inv)) for k in ("left", "right", "airway")}
    details = {**seg.details, "array_axes_to_axial_zyx": list(perm)}
    desc = seg.airway_removal + (f" (Slice numbers refer to the image transposed to axial order: array axes "
                                 f"{list(perm)} of the file are z, y, x.)")
    return LungSegmentation(back["left"], back["right"], back["airway"], image, seg.volumes_ml, desc, details)


def _lung_candidate(inside, voxel_ml, air_hu, min_lung_ml, source):
    """Step 3: ``(candidate (z, y, x) bool, its volume mL, the largest components' volumes mL)``:
    the two largest components of ``inside`` (:func:`inside_body_air`) of at least ``min_lung_ml``."""
    lab, ids = largest_components(inside, int(np.ceil(min_lung_ml / voxel_ml)))
    if ids.size == 0:
        raise MaskError(
            f"{source}: no air region ≥ {min_lung_ml:g} mL below {air_hu:g} HU inside the body: "
            "no lungs found (empty mask)"
        )
    candidate = np.isin(lab, ids[:2])
    cand_ml = float(candidate.sum()) * voxel_ml
    comp_ml = [float(v) * voxel_ml for v in np.bincount(lab.ravel())[ids[:6]]]
    return candidate, cand_ml, comp_ml


def _body_centre_x(ct, air_hu) -> np.ndarray:
    """``(z,) float``: per slice, the mean voxel x of the body (``ct > air_hu``); mid-width for an
    empty slice."""
    body = ct > air_hu
    return np.array([np.nonzero(row)[0].mean() if row.any() else ct.shape[2] / 2 for row in body.any(axis=1)])


def _remove_airways(ct, candidate, spacing, body_cx, voxel_ml, lumen_hu, airway_max_hu, airway_max_ml):
    """Steps 4–5: ``(tree, removed, growing info, seed info or None)``; ``tree`` the grown airways,
    ``removed`` the tree with its one-voxel wall, both ``(z, y, x) bool`` (empty with no seed)."""
    seed = find_trachea_seed(ct, candidate, spacing, body_cx, lumen_hu)
    if seed is None:
        tree = np.zeros_like(candidate)
        grow = {"threshold_hu": None, "history": [], "stopped": "no trachea seed found"}
        return tree, tree, grow, None
    z, seed2d, seed_info = seed
    seed_mask = np.zeros_like(candidate)
    seed_mask[z] = seed2d
    growth = AirwayGrowth(max_hu=airway_max_hu, max_ml=airway_max_ml)
    tree, grow = grow_airways(ct, candidate, seed_mask, voxel_ml, growth)
    removed = ndi.binary_dilation(tree, structure=_SIX) & candidate
    return tree, removed, grow, seed_info


def _split_left_right(lungs, body_cx, spacing, voxel_ml, max_erosions, source):
    """Step 6: ``(labels (z, y, x) int32 with lungs 1 and 2, split info, pieces dropped, mL dropped)``:
    the two largest components of ``lungs`` ≥ 10 % of it, or one split by :func:`split_touching`."""
    lab, ids = largest_components(lungs, 1)
    total = float(lungs.sum())
    big = [i for i in ids[:2] if np.count_nonzero(lab == i) >= 0.1 * total]
    if len(big) == 2:
        labels = np.where(lab == big[0], 1, np.where(lab == big[1], 2, 0)).astype(np.int32)
        split = {"method": "two components after airway removal", "erosions": 0}
    elif len(big) == 1:
        midline = float(np.median(body_cx[lungs.any(axis=(1, 2))]))
        labels, split = split_touching(lab == big[0], spacing, midline, max_erosions)
    else:
        raise MaskError(f"{source}: nothing left of the lungs after airway removal (empty mask)")
    n_dropped = int(ids.size - 2)
    dropped_ml = float(total - np.count_nonzero(labels)) * voxel_ml
    return labels, split, n_dropped, dropped_ml


def _filled_sides(labels, image: Image, spacing, head_up: bool):
    """Step 7 and the sides: ``(left, right, centroid world x mm of labels 1 and 2)``; the hole-filled
    masks of labels 1 and 2 (head-up order, as ``labels``), the one at larger LPS x is the left lung."""
    parts = [fill_holes(labels == k) for k in (1, 2)]
    # side from the world x of each centroid (LPS: +x = patient left)
    cx = []
    for p in parts:
        ijk = np.array(ndi.center_of_mass(p))[::-1].copy()
        if not head_up:
            ijk[2] = labels.shape[0] - 1 - ijk[2]
        cx.append(float((image.direction @ (ijk * spacing) + image.origin)[0]))
    left, right = (parts[0], parts[1]) if cx[0] > cx[1] else (parts[1], parts[0])
    overlap = left & right
    if overlap.any():  # hole filling of one lung cannot reach into the other, but be explicit
        right &= ~overlap
    return left, right, cx


def _volumes_ml(left, right, tree, removed, candidate_ml, voxel_ml, source) -> dict:
    """:attr:`LungSegmentation.volumes_ml` of the final masks; :class:`MaskError` if a lung is empty."""
    vol = {
        "left": float(left.sum()) * voxel_ml,
        "right": float(right.sum()) * voxel_ml,
        "airway": float(tree.sum()) * voxel_ml,
        "removed": float(removed.sum()) * voxel_ml,
        "candidate": candidate_ml,
    }
    if vol["left"] == 0 or vol["right"] == 0:
        raise MaskError(f"{source}: an empty lung mask after segmentation (left {vol['left']:.0f} mL, "
                        f"right {vol['right']:.0f} mL)")
    return vol


def _airway_removal_text(seed_info, grow, tree, vol, split, lumen_hu) -> str:
    """The paragraph of :attr:`LungSegmentation.airway_removal`; ``seed_info['slice']`` on the
    image's own grid, ``tree`` in its orientation."""
    if seed_info is None:
        return (f"No trachea found in the top slices (no {lumen_hu:g} HU component of tracheal size within "
                "25 mm of the body centre); no airway was removed.")
    zz = np.nonzero(tree.any(axis=(1, 2)))[0]
    return (
        f"Trachea seed: a {seed_info['area_mm2']:.0f} mm² air component below {lumen_hu:g} HU in slice "
        f"{seed_info['slice']}, {seed_info['offset_mm']:.1f} mm from the body's left-right centre. Airways "
        f"region-grown from it with a threshold rising from -1000 HU in 20 HU steps up to "
        f"{grow['threshold_hu']:g} HU ({grow['stopped']}): {vol['airway']:.1f} mL spanning slices "
        f"{zz.min()}-{zz.max()} (trachea, main and visible lobar bronchi). Removed with a one-voxel wall "
        f"dilation: {vol['removed']:.1f} mL in all. Lungs split by: {split['method']}."
    )


# =========================================================================== overlay
def overlay_png(seg: LungSegmentation, path, n_axial: int = 3) -> Path:
    """Write a PNG of the masks over CT slices: ``n_axial`` axial slices through the lungs and one
    coronal slice; left lung blue, right lung red, removed airways yellow. Radiological display
    (patient right on the image's left, anterior up, head up). Written atomically."""

    perm = axial_axes(seg.image)  # draw in axial (z, y, x) order whatever the file's axis order
    axial = to_axial(seg.image, perm)
    ct = np.asarray(axial.array)
    d = axial.direction
    sp = np.asarray(axial.spacing, float)
    lab = seg.labels().astype(np.int16)
    lab[seg.airway & (lab == 0)] = 3
    lab = np.transpose(lab, perm)
    lung = np.transpose(seg.left | seg.right, perm)
    zs = np.nonzero(lab.any(axis=(1, 2)) & (lab != 3).any(axis=(1, 2)))[0]
    if zs.size == 0:
        raise MaskError(f"{seg.image.source}: empty lung masks, nothing to draw")
    picks = [int(zs[int(round(q * (len(zs) - 1)))]) for q in np.linspace(0.2, 0.8, n_axial)]
    ycen = int(round(np.nonzero(lung.any(axis=(0, 2)))[0].mean()))

    def orient_axial(a):
        a = a[:, ::-1] if d[0, 0] < 0 else a  # patient right on the image's left
        return a[::-1] if d[1, 1] < 0 else a  # anterior up

    def orient_coronal(a):
        a = a[:, ::-1] if d[0, 0] < 0 else a
        return a[::-1] if d[2, 2] > 0 else a  # head up

    views = [(orient_axial(ct[z]), orient_axial(lab[z]), sp[1] / sp[0], f"axial slice {z}") for z in picks]
    views.append((orient_coronal(ct[:, ycen]), orient_coronal(lab[:, ycen]), sp[2] / sp[0], f"coronal row {ycen}"))
    v = seg.volumes_ml
    title = (f"{Path(seg.image.source).name}: left (blue) {v['left']:.0f} mL, right (red) {v['right']:.0f} mL, "
             f"airways removed (yellow) {v['airway']:.0f} mL")
    return save_png(label_overlay(views, title), path)
