"""Reading and checking a fit's inputs (step 1 of :func:`lungdeform.evaluate.pipeline.run_fit`).

:func:`read_inputs` reads every input (mesh file, mask image, or CT in HU, segmented with
:func:`lungdeform.segment.lungs.segment_lungs`) into a full-resolution surface; for images it notes
the border faces the mask touches (crop faces, :func:`lungdeform.fit.align.crop_planes`) and checks
that all images share one voxel spacing. It then checks that the inputs are one lung of the given
side with volumes increasing from the end-exhale one (later inputs may share a volume), and reads the landmarks (refused outside their image,
reported when they lie outside their own lung mask). A mask holding both lungs in one label gives the
side's lung of its split (:mod:`lungdeform.segment.split`); with landmarks, only the rows in that
lung are kept (noted, with how many were dropped).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError, ReadError
from lungdeform.fit.align import CropPlane, crop_planes
from lungdeform.fit.config import FitInputs
from lungdeform.fit.cycle import hysteresis, volume_order
from lungdeform.geometry.distance import point_to_surface
from lungdeform.geometry.frame import check_side
from lungdeform.geometry.mesh import Surface, winding_numbers
from lungdeform.io import mask as M
from lungdeform.io import meshfile as lio
from lungdeform.io.dicom.fourdct import frame_of_reference, read_phases
from lungdeform.io.dicom.series import dicom_series_files, series_identity
from lungdeform.io.grid import Image
from lungdeform.io.image import is_dicom_series_path, is_image_path, read_image
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.progress import Progress, silent
from lungdeform.segment.ct import archive_in, is_archive, read_ct
from lungdeform.segment.lungs import segment_lungs
from lungdeform.segment.split import SplitCache, landmarks_of_side, one_lung

#: Landmarks more than this outside their own image's lung mask count as outside (mm).
LANDMARK_OUTSIDE_MM = 3.0


@dataclass(frozen=True, eq=False)
class ReadInputs:
    """Every input of one lung, read and checked (:func:`read_inputs`); lists in input order.

    Attributes
    ----------
    surfaces : list of Surface
        Full-resolution surfaces, mm, each in its own scan's frame.
    planes : list of list of CropPlane
        Each input's crop faces (image border faces its mask touches; none for a mesh).
    images : list of Image or None
        Each input's lung mask (None for a mesh file).
    volumes_ml : list of float
        Measured volumes, or the given ones (mL).
    given_ml : list of float or None
        The given volumes (mL), None when measured.
    landmarks : list of (m, 3) float or None
        Each input's landmarks, mm, in its own scan's frame.
    warnings : list of str
        Suspicious but usable input (landmarks outside their own lung mask).
    notes : list of str
        What was done to the inputs (masks holding both lungs split, landmarks of the other lung dropped;
        a 4-D CT's phase order and volumes).
    paths : list of str
        What each input is, in fit order (its path; a 4-D CT's phases as ``"<folder> [<label>]"``).
    cycle : dict or None
        For a 4-D CT (:mod:`lungdeform.fit.cycle`): ``phases`` (label, volume mL, in phase order),
        ``frame_of_reference`` (the UID all phases share, or None) and ``hysteresis`` (one dict per
        exhale-branch phase, :class:`~lungdeform.fit.cycle.HysteresisPair`); None otherwise.
    scans : list of dict
        Each input's identity (:func:`scan_identity`), in fit order: its ``source``, its image
        ``grid`` (None for a mesh) and, for a DICOM series, its patient, study, series and Frame of
        Reference. The model records them, so that ``track --scan K --out-rtstruct`` can check that
        its ``--reference-ct`` is scan K's (:func:`lungdeform.io.dicom.rtstruct.check_ct_is_scan`).
    """

    surfaces: list[Surface]
    planes: list[list[CropPlane]]
    images: list[Image | None]
    volumes_ml: list[float]
    given_ml: list[float] | None
    landmarks: list[np.ndarray] | None
    warnings: list[str]
    notes: list[str] = field(default_factory=list)
    paths: list[str] = field(default_factory=list)
    cycle: dict | None = None
    scans: list[dict] = field(default_factory=list)


def read_inputs(inputs: FitInputs, side_check: bool = True,
                progress: Progress | None = None) -> ReadInputs:
    """Read and check every input of ``inputs`` (module docstring); ``side_check``: refuse an input
    whose shape says the other side (:func:`lungdeform.geometry.frame.check_side`)."""

    say = progress or silent
    cycle = None
    if len(inputs.paths) == 1:  # one 4-D CT folder: its phases, in the order of their volumes
        paths, read, notes4d, cycle = read_fourdct(Path(inputs.paths[0]), inputs.side, say)
        series = cycle.pop("series")
    else:
        paths, read, notes4d = list(inputs.paths), [], []
        series = [_dicom_files_of(Path(p), inputs.series) for p in inputs.paths]
        first_image = None  # every image is checked against the first one's spacing as soon as it is read
        for p in inputs.paths:
            say(f"reading {p}")
            read.append(read_input(Path(p), inputs.side, progress=say, spacing_like=first_image,
                                   splits=inputs.splits, series=inputs.series))
            if first_image is None and read[-1][2] is not None:
                first_image = (p, read[-1][2])
    surfaces, images = [r[0] for r in read], [r[3] for r in read]
    check_sides(paths, surfaces, inputs.side if side_check else None)
    given = None if inputs.volumes_ml is None else list(inputs.volumes_ml)
    volumes = [s.volume_ml for s in surfaces] if given is None else list(given)
    check_increasing(paths, volumes)
    landmarks, warnings = None, []
    splits = [r[4] for r in read]
    notes = notes4d + [n for sp in splits if sp is not None for n in sp.notes + (f"{sp.image.source}: took the {inputs.side} "
                                                                         "lung of the split",)]
    if inputs.landmarks:
        landmarks = read_landmark_files(inputs.landmarks, images)
        if any(sp is not None for sp in splits):  # landmarks of both lungs: this side's rows only
            rows, dropped = landmarks_of_side(landmarks, splits, inputs.side, [str(p) for p in inputs.landmarks])
            landmarks, notes = [pts[rows] for pts in landmarks], notes + list(dropped)
        for p, pts, image, surface in zip(inputs.landmarks, landmarks, images, surfaces):
            check_landmarks(pts, image, p)
            warnings += landmark_mask_warnings(pts, image, surface, p)
    scans = [scan_identity(str(p), image, files) for p, image, files in zip(paths, images, series)]
    return ReadInputs(surfaces, [r[1] for r in read], images, volumes, given, landmarks, warnings, notes,
                      [str(p) for p in paths], cycle, scans)


def _dicom_files_of(path: Path, series=None):
    """The files of the DICOM series an input path names (a folder or one of its files; ``series``
    chooses among several), or None when it is no DICOM series (an image file, a mesh, an archive)."""
    if is_dicom_series_path(path):
        try:
            return dicom_series_files(path, series)
        except ReadError:
            return None  # e.g. a dataset folder holding one archive: read as such, no series identity
    return None


def scan_identity(source: str, image: Image | None, files) -> dict:
    """One input's identity: ``source``, ``grid`` (``size`` x y z voxels, ``spacing`` mm, ``origin``
    mm LPS, ``direction`` row-major (3, 3); None for a mesh) and, when ``files`` are the DICOM series
    it was read from, ``patient_id``, ``study_uid``, ``series_uid`` and ``frame_of_reference``
    (:func:`lungdeform.io.dicom.series.series_identity`)."""
    grid = None if image is None else {
        "size": [int(n) for n in np.asarray(image.array).shape[::-1]], "spacing": np.asarray(image.spacing, float).tolist(),
        "origin": np.asarray(image.origin, float).tolist(), "direction": np.asarray(image.direction, float).ravel().tolist()}
    return {"source": source, "grid": grid, **(series_identity(files) if files else {})}


def read_fourdct(folder: Path, side: str, progress) -> tuple[list[str], list[tuple], list[str], dict]:
    """The phases of the 4-D CT in ``folder`` (:func:`lungdeform.io.dicom.fourdct.read_phases`) as inputs:
    ``(names, read_input results, notes, cycle)``, each phase's ``side`` lung segmented, the phases
    ordered by their lung's volume (end-exhale, the smallest, first: the model is a function of
    volume; equal volumes kept, in phase order, :func:`lungdeform.fit.cycle.volume_order`). A phase
    of exactly the end-exhale volume is no target (the model cannot move at zero volume change):
    left out, noted, still measured in the hysteresis. The notes give the phase order and each
    phase's volume (mL); ``cycle``: :attr:`ReadInputs.cycle`, with ``"series"`` (each phase's files, in
    fit order) that :func:`read_inputs` takes out for :attr:`ReadInputs.scans`."""

    progress(f"reading the 4-D CT {folder}")
    ignored: list[str] = []
    phases = read_phases(folder, ignored=ignored)
    read, first = [], None
    for ph in phases:
        progress(f"segmenting phase {ph.label}")
        read.append(image_input(ph.image, ph.image.source, side, progress=progress, spacing_like=first))
        first = first or (ph.image.source, read[-1][2])
    volumes = [r[0].volume_ml for r in read]
    order = volume_order([ph.key for ph in phases], volumes)
    tied = [i for i in order[1:] if volumes[i] <= volumes[order[0]]]
    order = [i for i in order if i not in tied]
    by_phase = ", ".join(f"{ph.label} {v:.1f} mL" for ph, v in zip(phases, volumes))
    notes = ignored + [f"{folder}: 4-D CT of {len(phases)} phases; {side} lung by phase: {by_phase}",
             (f"{folder}: phases fitted in the order of their volume (end-exhale first; a phase of equal volume on "
              f"the other branch is a second target at that volume): {', '.join(phases[i].label for i in order)}")]
    notes += [f"{folder}: phase {phases[i].label} has the end-exhale volume ({volumes[i]:.1f} mL): not a target"
              for i in tied]
    progress("hysteresis: exhale-branch phases against inhale-branch phases of similar volume")
    pairs = hysteresis([ph.label for ph in phases], [r[0] for r in read], volumes)
    cycle = {"phases": [{"label": ph.label, "volume_ml": v} for ph, v in zip(phases, volumes)],
             "frame_of_reference": frame_of_reference([ph.files for ph in phases]),
             "hysteresis": [p.as_dict() for p in pairs], "series": [phases[i].files for i in order]}
    return [phases[i].image.source for i in order], [read[i] for i in order], notes, cycle


def read_input(path: Path, side: str, *, progress: Progress | None = None, spacing_like=None,
               splits: SplitCache | None = None, series=None):
    """``(dense Surface, crop planes, spacing or None, image or None, split or None)`` for one input
    path; ``split`` (:class:`~lungdeform.segment.split.LungSplit`) when the input was a mask holding
    both lungs in one label, ``image`` then its ``side`` lung.

    ``spacing_like``: ``(path, spacing (3,) mm)`` of an image read before; an image of another
    spacing is refused as soon as it is read, before the (slow) segmentation and surface. ``splits``:
    where a mask holding both lungs is split (:class:`~lungdeform.segment.split.SplitCache`); ``series``:
    which CT series of a DICOM folder holding several (:class:`~lungdeform.io.dicom.folder.SeriesChoice`)."""

    path = Path(path)
    if not path.exists():
        raise ReadError(f"{path}: no such file or directory")

    path = archive_in(path)  # a dataset folder holding one archive: that archive
    if is_archive(path):  # a zipped or tarred DICOM series (or image): a CT
        image = read_ct(path, series=series)
    elif not is_image_path(path):
        surface, _ = lio.load_surface(path, name=path.name)
        return surface, [], None, None, None
    else:
        image = read_image(path, series=series)
    return image_input(image, path, side, progress=progress, spacing_like=spacing_like, splits=splits)


def image_input(image: Image, path: Path, side: str, *, progress: Progress | None = None, spacing_like=None,
                splits: SplitCache | None = None):
    """What :func:`read_input` returns for an ``image`` read from ``path`` (a CT is segmented, a mask
    split, both checked against ``spacing_like``)."""

    if spacing_like is not None and not np.allclose(image.spacing, spacing_like[1], rtol=1e-3):
        raise InputError(f"{path}: voxel spacing {np.asarray(image.spacing, float).tolist()} mm differs from "
                         f"{spacing_like[0]} ({np.asarray(spacing_like[1], float).tolist()} mm); inconsistent spacing")
    a = np.asarray(image.array)
    split = None
    if a.size and a.min() < -100:  # a CT in HU: segment the lungs first
        seg = segment_lungs(image, progress=progress)
        image = Image(getattr(seg, side).astype(np.uint8), image.spacing, image.origin, image.direction,
                      f"{image.source} ({side} lung)")
    else:  # a lobe map or a binary mask holding both lungs: this side's lung (one lung passes unchanged)
        image, _notes, split = one_lung(image, side, splits)
    surface = M.extract_surface(image, name=Path(path).name).surface
    return surface, crop_planes(image), np.asarray(image.spacing, float), image, split


def check_sides(paths, surfaces, side: str | None) -> None:
    """Refuse inputs that are not one lung: every centroid on the same side of the end-exhale lung
    (within 0.75 of the widest lung's width along x, mm); with ``side``, each surface must be that
    side's lung (its medial face, :func:`lungdeform.geometry.frame.check_side`)."""

    widths = [np.ptp(s.vertices[:, 0]) for s in surfaces]
    cx = [s.vertices[:, 0].mean() for s in surfaces]
    for p, c in zip(paths[1:], cx[1:]):
        if abs(c - cx[0]) > 0.75 * max(widths):
            raise InputError(f"{p}: this lung lies {c - cx[0]:+.0f} mm from the end-exhale lung along x; "
                             "the sides do not match (left and right lungs mixed)")
    for p, s in zip(paths, surfaces) if side is not None else ():
        check_side(s.vertices, s.faces, side, str(p))


def check_increasing(paths, volumes_ml) -> None:
    """Refuse volumes (mL, one per input path) not larger than the first (end-exhale) one, or that
    decrease; later inputs may share a volume (two phases of a cycle, inhale and exhale)."""

    for i in range(1, len(volumes_ml)):
        if not volumes_ml[i] > volumes_ml[0]:
            raise InputError(f"{paths[i]}: volume {volumes_ml[i]:.1f} mL is not larger than that of "
                             f"{paths[0]} ({volumes_ml[0]:.1f} mL); volumes must increase (end-exhale first)")
        if volumes_ml[i] < volumes_ml[i - 1]:
            raise InputError(f"{paths[i]}: volume {volumes_ml[i]:.1f} mL is smaller than that of "
                             f"{paths[i - 1]} ({volumes_ml[i - 1]:.1f} mL); volumes must increase (end-exhale "
                             "first; equal volumes allowed)")


def read_landmark_files(paths, images) -> list[np.ndarray]:
    """Each elastix point file in ``paths`` as ``(m, 3) float`` mm ('index' files are voxel indices
    of the image of the same input, ``images``); every file must hold as many points as the first."""

    lms = [read_elastix_points(p, *(() if im is None else (im.spacing, im.origin, im.direction)))
           for p, im in zip(paths, images)]
    for p, pts in zip(paths[1:], lms[1:]):
        if pts.shape != lms[0].shape:
            raise InputError(f"{p}: {len(pts)} landmarks, the end-exhale file has {len(lms[0])}")
    return lms


def landmark_mask_warnings(points, image, surface, path, limit: float = 0.05) -> list[str]:
    """A warning when more than ``limit`` of the landmarks ``points : (m, 3)`` mm lie more than
    :data:`LANDMARK_OUTSIDE_MM` outside the lung mask of their own ``image`` (files swapped, or in
    another frame; on the ITK pair every landmark is inside its own mask, 8–12 % are not inside
    the other's). Points off the mask are measured to the mask's ``surface`` (mm)."""

    if image is None or len(points) == 0:
        return []
    mask = np.asarray(image.array) > 0
    pts = np.asarray(points, float)
    ijk = np.rint((pts - image.origin) @ np.asarray(image.direction) / image.spacing).astype(np.int64)
    shape = np.array(mask.shape[::-1])
    inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
    i, j, k = ijk[inside].T
    on = np.zeros(len(pts), bool)
    on[np.flatnonzero(inside)] = mask[k, j, i]
    far = np.zeros(len(pts), bool)
    off = np.flatnonzero(~on)
    if len(off):  # off the mask's voxels: outside only if also outside its closed surface (holes count as in)
        q = pts[off]
        far[off] = ((winding_numbers(q, surface.vertices, surface.faces) < 0.5)
                    & (point_to_surface(q, surface.vertices, surface.faces) > LANDMARK_OUTSIDE_MM))
    if far.mean() <= limit:
        return []
    return [f"{path}: {int(far.sum())} of {len(far)} landmarks lie more than {LANDMARK_OUTSIDE_MM:g} mm outside "
            f"the lung mask of {image.source} (first: row {int(np.flatnonzero(far)[0]) + 1}); are the landmark files "
            f"in the inputs' order and frame?"]


def check_landmarks(points, image, path, margin_mm: float = 0.0) -> None:
    """Refuse landmarks outside the image's world bounding box (mm)."""

    if image is None:
        return
    n = np.array(image.array.shape[::-1])
    corners = np.array([[i, j, k] for i in (-0.5, n[0] - 0.5) for j in (-0.5, n[1] - 0.5) for k in (-0.5, n[2] - 0.5)])
    w = image.index_to_world(corners)
    lo, hi = w.min(axis=0) - margin_mm, w.max(axis=0) + margin_mm
    bad = np.nonzero(np.any((points < lo) | (points > hi), axis=1))[0]
    if len(bad):
        raise InputError(f"{path}: {len(bad)} landmarks lie outside the image {image.source} "
                         f"(first: row {bad[0] + 1}, {np.round(points[bad[0]], 2).tolist()} mm)")
