"""Masks that hold both lungs in one label → a left and a right lung mask.

A binary mask (one non-zero value) may hold both lungs (e.g. the DIR-Lab COPDgene masks,
docs/FITTING.md "Masks with both lungs in one label"). :func:`find_lungs` splits it:

1. **components** (6-connected): when the two largest are each at least ``min_part`` of the mask,
   they are the lungs (they do not touch);
2. **narrowest neck**: otherwise the lungs touch and form one component; it is eroded in-plane
   until two large pieces appear and they are grown back geodesically over the mask
   (:func:`lungdeform.segment.lungs.erode_apart`, the same cut as for a CT's touching lungs in
   :func:`lungdeform.segment.lungs.segment_lungs`), so the cut falls at the narrowest neck;
3. **two lungs, side by side**: each part must be at least ``min_part`` of the mask, their
   centroids at least 0.4 of the wider part's width apart along x and their heights overlapping by
   half, or the mask is not two lungs (None; :func:`split_lungs` raises :class:`MaskError`);
4. **specks**: mask voxels in neither part (small components) go to the nearest lung, each speck
   whole (noted with their volume);
5. **sides** from position: the part whose centroid has the larger LPS world x is the **left** lung.

:func:`assign_landmarks` gives each landmark (mm LPS) the lung of its voxel; landmarks in neither
are given to the nearest lung and counted. :func:`one_lung` is the hook the commands use (fit,
cohort): a lobe map gives its side's lobes (:func:`lungdeform.io.mask.side_mask`), a binary mask
holding both lungs the side's lung of the split, anything else is returned as it is.
:func:`load_lungs` does the same for ``lungdeform build``, and :func:`mask_segmentation` gives
``lungdeform segment`` the left and right masks of such a mask (:func:`read_ct_or_mask`,
:func:`segment_ct_or_mask`).

Arrays are ``(z, y, x)`` on the mask's grid (SimpleITK order); geometry follows
:class:`lungdeform.io.grid.Image`; volumes are mL.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from lungdeform.errors import InputError, MaskError
from lungdeform.io import mask as M
from lungdeform.io import meshfile as lio
from lungdeform.io.grid import Image
from lungdeform.io.image import IMAGE_SUFFIXES, is_image_path, read_image
from lungdeform.progress import Progress

from .ct import check_ct, read_ct, to_axial
from .ct import downsample as downsample_ct
from .lungs import LungSegmentation, _padded_box, erode_apart, largest_components, segment_lungs

#: Each lung must hold at least this fraction of a both-lung mask.
MIN_PART = 0.15
#: In-plane erosions tried before a touching mask is declared not two lungs (the DIR-Lab masks need 2–5).
MAX_EROSIONS = 12
SIDES = ("left", "right")


@dataclass(frozen=True, eq=False)
class LungSplit:
    """A both-lung mask split into its lungs (:func:`find_lungs`).

    Attributes
    ----------
    labels : (z, y, x) uint8
        0 background, 1 left lung, 2 right lung, on the grid of ``image``.
    image : Image
        The both-lung mask.
    touching : bool
        The lungs formed one component (cut at the narrowest neck).
    erosions : int
        In-plane erosions that separated them (0 when they did not touch).
    n_specks, specks_ml : int, float
        Small pieces in neither lung, given to the nearest lung, and their volume (mL).
    notes : tuple of str
        What was done, one line each, naming the file.
    """

    labels: np.ndarray
    image: Image
    touching: bool
    erosions: int
    n_specks: int
    specks_ml: float
    notes: tuple[str, ...]

    @property
    def volumes_ml(self) -> dict[str, float]:
        """``{"left": mL, "right": mL}``."""
        counts = np.bincount(self.labels.ravel(), minlength=3)
        return {sd: float(counts[k]) * self.image.voxel_ml for k, sd in ((1, "left"), (2, "right"))}

    def mask(self, side: str) -> Image:
        """The ``side`` lung as a uint8 0/1 :class:`Image` on the mask's grid."""
        if side not in SIDES:
            raise InputError(f"side must be 'left' or 'right', got {side!r}")
        im = self.image
        return Image((self.labels == SIDES.index(side) + 1).astype(np.uint8), im.spacing, im.origin,
                     im.direction, f"{im.source} ({side} lung of the split)")


def is_binary_mask(image: Image) -> bool:
    """True for a mask with one non-zero value (0/1, 0/255 …): one label, whatever it holds."""
    a = np.asarray(image.array)
    if a.size == 0 or np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        return False
    values = np.unique(a)
    return values.size == 2 and values[0] == 0


def split_lungs(image: Image, *, max_erosions: int = MAX_EROSIONS,
                min_part: float = MIN_PART) -> tuple[Image, Image, tuple[str, ...]]:
    """``(left mask, right mask, notes)`` of a binary mask holding both lungs (module docstring).

    Raises :class:`MaskError` naming the file when the mask is not binary or no two-lung split is
    found (one lung, one blob, or lungs fused beyond ``max_erosions`` in-plane erosions).
    """
    split = require_split(image, max_erosions=max_erosions, min_part=min_part)
    return split.mask("left"), split.mask("right"), split.notes


def require_split(image: Image, *, max_erosions: int = MAX_EROSIONS, min_part: float = MIN_PART,
                  cache: SplitCache | None = None) -> LungSplit:
    """:func:`find_lungs` (through ``cache`` when given), or :class:`MaskError` naming the file when
    there is no two-lung split."""
    if not is_binary_mask(image):
        raise MaskError(f"{image.source}: not a binary mask (one non-zero label): cannot split it into two lungs")
    split = find_lungs(image, max_erosions=max_erosions, min_part=min_part, cache=cache)
    if split is None:
        raise MaskError(f"{image.source}: no two-lung split found (neither two components nor {max_erosions} "
                        f"in-plane erosions give two side-by-side parts of ≥ {min_part:.0%} each): one lung, "
                        "or lungs fused beyond a neck")
    return split


class SplitCache:
    """The splits a caller has asked :func:`find_lungs` for, kept by mask: the same mask (same voxels,
    geometry and source) read again, e.g. once per lung and once for the mask-only baselines of one
    DIR-Lab COPDgene case, gets the split already found. The caller makes one, passes it as
    ``cache=`` (``FitInputs(splits=)``) and drops it when done (one case, one subject)."""

    def __init__(self):
        self._splits: dict[tuple, LungSplit | None] = {}

    def split(self, image: Image, max_erosions: int, min_part: float) -> LungSplit | None:
        """:func:`find_lungs` of ``image``, computed on the first call for its mask."""
        key = _split_key(image, max_erosions, min_part)
        if key not in self._splits:
            self._splits[key] = _find_lungs(image, max_erosions, min_part)
        return self._splits[key]

    def split_files(self, paths) -> None:
        """Read each mask file of ``paths`` and split it now (:func:`find_lungs`; a mask that is not
        both lungs in one label is kept as None), so that later reads of the same files find their
        splits here (e.g. before a subject's two lungs are fitted in worker processes)."""
        for path in paths:
            find_lungs(read_image(path), cache=self)

    def __len__(self) -> int:
        return len(self._splits)


def _split_key(image: Image, max_erosions: int, min_part: float) -> tuple:
    a = np.ascontiguousarray(image.array)
    digest = hashlib.blake2b(a.view(np.uint8).ravel(), digest_size=16).hexdigest()
    geometry = np.concatenate([np.ravel(image.spacing), np.ravel(image.origin), np.ravel(image.direction)])
    return digest, a.shape, a.dtype.str, geometry.tobytes(), str(image.source), int(max_erosions), float(min_part)


def find_lungs(image: Image, *, max_erosions: int = MAX_EROSIONS, min_part: float = MIN_PART,
               cache: SplitCache | None = None) -> LungSplit | None:
    """The :class:`LungSplit` of a binary mask holding both lungs, or None when it is not that (not
    binary, or no two large side-by-side parts: steps 1–3 of the module docstring). With a
    ``cache``, a mask already split through it gives the same split again."""
    if cache is None:
        return _find_lungs(image, max_erosions, min_part)
    return cache.split(image, max_erosions, min_part)


def _find_lungs(image: Image, max_erosions: int, min_part: float) -> LungSplit | None:
    if not is_binary_mask(image):
        return None
    m = np.asarray(image.array) != 0
    total = int(m.sum())
    lab, ids = largest_components(m, 1)
    sizes = np.bincount(lab.ravel())[ids[:2]]
    if ids.size >= 2 and sizes[1] >= min_part * total:
        parts, erosions = np.where(lab == ids[0], 1, np.where(lab == ids[1], 2, 0)).astype(np.int32), 0
    else:
        apart = erode_apart(lab == ids[0], max_erosions, min_part)
        if apart is None:
            return None
        parts, erosions = apart
    del lab
    if min(np.count_nonzero(parts == 1), np.count_nonzero(parts == 2)) < min_part * total:
        return None
    cx = _side_by_side(parts, image)
    if cx is None:
        return None
    n_specks, speck_voxels = _specks_to_nearest(parts, m, image.spacing)
    labels = np.zeros(m.shape, np.uint8)
    left_id = 1 if cx[0] > cx[1] else 2
    labels[parts == left_id] = 1
    labels[parts == 3 - left_id] = 2
    specks_ml = speck_voxels * image.voxel_ml
    split = LungSplit(labels, image, erosions > 0, erosions, n_specks, specks_ml, ())
    return LungSplit(labels, image, erosions > 0, erosions, n_specks, specks_ml, _split_notes(split))


def _side_by_side(parts: np.ndarray, image: Image, step: int = 7) -> list[float] | None:
    """World x (mm) of the centroids of parts 1 and 2, or None when they do not lie side by side
    (centroids ≥ 0.4 of the wider part's x width apart, heights (world z) overlapping by half the
    shorter). Extents from every ``step``-th voxel (speed)."""
    ext = []
    for k in (1, 2):
        w = image.index_to_world(np.argwhere(parts == k)[::step, ::-1])
        ext.append((w[:, 0].mean(), np.ptp(w[:, 0]), w[:, 2].min(), w[:, 2].max()))
    (c1, w1, lo1, hi1), (c2, w2, lo2, hi2) = ext
    overlap = min(hi1, hi2) - max(lo1, lo2)
    if abs(c1 - c2) < 0.4 * max(w1, w2) or overlap < 0.5 * min(hi1 - lo1, hi2 - lo2):
        return None
    return [float(c1), float(c2)]


def _specks_to_nearest(parts: np.ndarray, mask: np.ndarray, spacing) -> tuple[int, int]:
    """Give every piece of ``mask`` in neither part (0 in ``parts``) whole to the part nearest to it
    (in mm), in place. Returns ``(pieces, voxels)`` given."""
    rest = mask & (parts == 0)
    if not rest.any():
        return 0, 0
    box = _padded_box(mask)  # every part and speck lies in the mask's box: the transform there only (speed)
    sub, rest = parts[box], rest[box]
    specks, n = ndi.label(rest)
    dist, idx = ndi.distance_transform_edt(sub == 0, sampling=np.asarray(spacing, float)[::-1],
                                           return_indices=True)
    nearest = sub[tuple(idx)]
    del idx
    at = ndi.minimum_position(dist, specks, np.arange(1, n + 1))
    to = np.array([0] + [nearest[p] for p in at])
    sub[rest] = to[specks[rest]]
    return n, int(rest.sum())


def _split_notes(split: LungSplit) -> tuple[str, ...]:
    v = split.volumes_ml
    how = (f"the lungs touch (one component): cut at the narrowest neck after {split.erosions} in-plane "
           "erosions, grown back over the mask" if split.touching else "two separate components")
    notes = [f"{split.image.source}: a mask holding both lungs in one label, split into left {v['left']:.0f} mL "
             f"and right {v['right']:.0f} mL ({how}; left = larger LPS x)"]
    if split.n_specks:
        notes.append(f"{split.image.source}: {split.n_specks} small pieces ({split.specks_ml:.2f} mL) given to the "
                     "nearest lung")
    return tuple(notes)


# =========================================================================== landmarks
@dataclass(frozen=True, eq=False)
class LandmarkSides:
    """Each landmark's lung (:func:`assign_landmarks`).

    Attributes
    ----------
    side : (m,) str
        ``"left"`` or ``"right"`` per landmark.
    outside : (m,) bool
        In neither lung's voxels (given to the nearest lung).
    notes : tuple of str
    """

    side: np.ndarray
    outside: np.ndarray
    notes: tuple[str, ...]

    def counts(self) -> dict[str, int]:
        """Landmarks per lung (including those given to it) and outside both."""
        return {"left": int(np.sum(self.side == "left")), "right": int(np.sum(self.side == "right")),
                "outside": int(self.outside.sum())}


def assign_landmarks(points, split: LungSplit, name: str = "landmarks") -> LandmarkSides:
    """The lung of each landmark ``points : (m, 3) float`` mm LPS: the label of its voxel in
    ``split``; landmarks in neither lung (or off the grid) go to the lung whose nearest voxel centre
    is closest (mm), counted in the notes under ``name``."""
    pts = np.asarray(points, float).reshape(-1, 3)
    im = split.image
    ijk = np.rint((pts - im.origin) @ np.asarray(im.direction) / im.spacing).astype(np.int64)
    shape = np.array(split.labels.shape[::-1])
    on_grid = np.all((ijk >= 0) & (ijk < shape), axis=1)
    lab = np.zeros(len(pts), np.uint8)
    i, j, k = ijk[on_grid].T
    lab[on_grid] = split.labels[k, j, i]
    outside = lab == 0
    if outside.any():
        fg = split.labels > 0
        rim = np.argwhere(fg & ~ndi.binary_erosion(fg))  # the nearest lung voxel lies on the rim
        _, near = cKDTree(im.index_to_world(rim[:, ::-1])).query(pts[outside])
        lab[outside] = split.labels[tuple(rim[near].T)]
    side = np.where(lab == 1, "left", "right")
    notes = []
    if outside.any():
        notes.append(f"{name}: {int(outside.sum())} of {len(pts)} landmarks lie in neither lung of the split "
                     f"(given to the nearest: {int(np.sum(outside & (lab == 1)))} left, "
                     f"{int(np.sum(outside & (lab == 2)))} right)")
    return LandmarkSides(side, outside, tuple(notes))


def landmarks_of_side(points: list[np.ndarray], splits: list[LungSplit | None], side: str,
                      names: list[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(rows kept (k,) int, notes)``: the landmark rows (corresponding across the inputs'
    ``points``, each ``(m, 3)`` mm) that lie in the ``side`` lung of every input whose mask held both
    lungs (``splits``; None for the others). The other rows are dropped, with a note saying how many."""
    keep = np.ones(len(points[0]), bool)
    notes: list[str] = []
    disagree = np.zeros(len(points[0]), bool)
    first = None
    for pts, split, name in zip(points, splits, names):
        if split is None:
            continue
        a = assign_landmarks(pts, split, name)
        notes += a.notes
        here = a.side == side
        if first is not None:
            disagree |= here != first
        first = here if first is None else first
        keep &= here
    if first is None:
        return np.arange(len(points[0])), ()
    n_drop = int((~keep).sum())
    if not keep.any():
        raise InputError(f"{names[0]}: none of the {len(keep)} landmarks lie in the {side} lung of the split mask")
    if n_drop:
        extra = f", {int(disagree.sum())} of them in different lungs in different inputs" if disagree.any() else ""
        notes.append(f"{names[0]}: kept the {int(keep.sum())} landmarks in the {side} lung; dropped {n_drop} of "
                     f"{len(keep)} in the other lung{extra}")
    return np.flatnonzero(keep), tuple(notes)


# =========================================================================== commands
def one_lung(image: Image, side: str,
             cache: SplitCache | None = None) -> tuple[Image, tuple[str, ...], LungSplit | None]:
    """``(the side lung's mask, notes, split or None)`` of a mask given for one lung: a lobe map gives
    its side's lobes (:func:`lungdeform.io.mask.side_mask`), a binary mask holding both lungs the
    side's lung of its split (:func:`find_lungs`, through ``cache`` when given), anything else comes
    back as it is."""
    lobes = M.side_mask(image, side)
    if lobes is not image:
        return lobes, (), None
    split = find_lungs(image, cache=cache)
    if split is None:
        return image, (), None
    return split.mask(side), split.notes + (f"{image.source}: took the {side} lung of the split",), split


def load_lungs(path, side: str | None = None, *, labels=None, units: str = "mm", repair: bool = False,
               target_vertices: int | None = None, progress: Progress | None = None):
    """``(list of (Surface, SurfaceReport), notes)``: :func:`lungdeform.io.meshfile.load`, except that a
    binary mask holding both lungs (and no ``labels``) gives its two lungs, named ``<stem>-left`` and
    ``<stem>-right``, or only the ``side`` one."""
    p = Path(path)
    kw = dict(labels=labels, units=units, repair=repair, target_vertices=target_vertices, progress=progress)
    if labels is not None or units != "mm" or p.suffix.lower() in lio.MESH_SUFFIXES or not is_image_path(p):
        return lio.load(p, **kw), ()
    if progress:
        progress(f"reading {p}")
    image = read_image(p)
    split = find_lungs(image)
    if split is None:  # one lung, or not a binary mask: as before
        return lio.load(p, **kw), ()
    stem = p.name[:-7] if p.name.lower().endswith(".nii.gz") else (p.name if p.is_dir() else p.stem)
    out = []
    for sd in (side,) if side else SIDES:
        res = M.extract_surface(split.mask(sd), None, target_vertices=target_vertices, name=f"{stem}-{sd}")
        out.append((res.surface, res.report))
    took = f"{p}: took the {side} lung of the split" if side else f"{p}: built both lungs of the split"
    return out, split.notes + (took,)


def mask_segmentation(image: Image) -> LungSegmentation:
    """:class:`~lungdeform.segment.lungs.LungSegmentation` of a binary mask holding both lungs (no
    airways removed; ``details`` say how it was split). :class:`MaskError` when it is not that."""
    split = require_split(image)
    lm, rm = split.labels == 1, split.labels == 2
    v = split.volumes_ml
    vol = {**v, "airway": 0.0, "removed": 0.0, "candidate": float(np.count_nonzero(image.array)) * image.voxel_ml}
    desc = f"Input is a lung mask, not a CT: no airway removal. {' '.join(split.notes)}"
    details = {"input": "binary mask holding both lungs", "split": {
        "touching": split.touching, "erosions": split.erosions, "specks": split.n_specks,
        "specks_ml": split.specks_ml}, "notes": list(split.notes)}
    return LungSegmentation(lm, rm, np.zeros_like(lm), image, vol, desc, details)


def read_ct_or_mask(path, series=None) -> Image:
    """A CT (:func:`lungdeform.segment.ct.read_ct`; ``series``: which CT series of a DICOM folder
    holding several, :class:`~lungdeform.io.dicom.folder.SeriesChoice`) or, for an image file holding
    a binary mask, that mask (``lungdeform segment`` then splits it: :func:`segment_ct_or_mask`)."""
    p = Path(path)
    if p.is_file() and p.name.lower().endswith(IMAGE_SUFFIXES):
        image = read_image(p)
        if is_binary_mask(image):
            return image
        check_ct(image)
        return image
    return read_ct(p, series=series)


def segment_ct_or_mask(image: Image, downsample: int = 1,
                       progress: Progress | None = None) -> tuple[Image, LungSegmentation]:
    """``(the image segmented, its LungSegmentation)``: a binary mask holding both lungs is split
    (:func:`mask_segmentation`, at full resolution); a CT is block-mean downsampled in-plane by
    ``downsample`` (along world x and y whatever the file's axis order) and segmented
    (:func:`lungdeform.segment.lungs.segment_lungs`)."""
    if is_binary_mask(image):
        if progress:
            progress("a binary mask: splitting it into left and right lungs")
        return image, mask_segmentation(image)
    if downsample > 1:
        image = downsample_ct(to_axial(image), (1, downsample, downsample))
    return image, segment_lungs(image, progress=progress)
