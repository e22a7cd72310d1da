"""One lung at two volumes, as ``validate single-scan`` and ``learn-default`` see it (:class:`LungPair`).

:func:`read_pair` reads one lung of a two-volume subject (:mod:`lungdeform.validate.subjects`): both
scans (a mask holding both lungs is split, :mod:`lungdeform.segment.split`), the model mesh of the
smaller-volume scan (:func:`lungdeform.evaluate.placement.model_mesh`), the larger-volume surface as the
target, the volume change, and the lung's landmarks when the subject has them.

**A cut lung.** Where a lung's mask touches its image's border (a crop face,
:func:`lungdeform.fit.align.crop_planes`), part of the lung lies outside the field of view and its
surface there is a flat cut, not pleura. Such a lung is kept, and its cut is left out of every surface
distance, on both sides: the model mesh's vertices within 5 mm of its own crop faces, and of the other
scan's crop faces, are not measured, and neither are the target's vertices beyond either scan's crop
faces (:func:`exclude_cuts`). The two scans of a subject need not share a frame (the Learn2Reg scans
were cropped around their own lungs, the ITK scans carry a table shift), so the other scan's crop
faces are first placed by the translation that best fits the isotropic prediction to the target
(:func:`lungdeform.validate.translation.best_translation`); the excluded region is then the same for
every row scored. :attr:`LungPair.cut` names the crop faces (docs/DEFAULTS.md says why a cut lung is
kept: the choice and its effect were measured).

:func:`cached_pair` keeps what :func:`read_pair` read in a folder, under a digest of the subject's files
and the side, so that a rerun (or another command) reads it back instead of splitting and meshing the
masks again.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes
from lungdeform.errors import InputError
from lungdeform.evaluate.inputs import read_inputs
from lungdeform.evaluate.placement import place_targets
from lungdeform.fit.align import CropPlane, RigidTransform, near_planes
from lungdeform.fit.config import FitInputs
from lungdeform.fit.objective import Target
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.dome import dome_excursion
from lungdeform.geometry.frame import clear_side
from lungdeform.geometry.mesh import Surface
from lungdeform.geometry.moments import solid_moments
from lungdeform.io.image import read_image
from lungdeform.io.mask import extract_surface, side_mask
from lungdeform.progress import Progress
from lungdeform.segment.split import SIDES, SplitCache, find_lungs

from .subjects import Subject
from .translation import best_translation

#: Bumped whenever :func:`read_pair` reads a lung differently (a cached pair of another version is read again).
PAIR_VERSION = 1


@dataclass(frozen=True, eq=False)
class LungPair:
    """One lung at two volumes.

    Attributes
    ----------
    subject : str
    side : str
    rest : Surface
        Model mesh of the smaller-volume scan, mm LPS.
    keep : (n,) bool
        Its vertices measured (away from either scan's crop faces).
    target : Target
        The larger-volume surface in its own scan's frame, its vertices beyond a crop face not measured.
    volume_ml : float
        The larger volume, anchored on the model mesh (``rest.volume_ml`` + the measured change), mL.
    landmarks_rest, landmarks_target : (m, 3) float or None
        Landmarks of the lung in each scan, mm LPS (each in its scan's frame); None without landmarks.
    cut : tuple of str
        The crop faces the lung's masks touch, e.g. ``"exp j-low"`` (empty: the lung is whole in both scans).
    """

    subject: str
    side: str
    rest: Surface
    keep: np.ndarray
    target: Target
    volume_ml: float
    landmarks_rest: np.ndarray | None = None
    landmarks_target: np.ndarray | None = None
    cut: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        """``"<subject>/<side>"``."""
        return f"{self.subject}/{self.side}"

    @property
    def has_landmarks(self) -> bool:
        return self.landmarks_rest is not None and len(self.landmarks_rest) > 0

    @cached_property
    def target_distance(self) -> SurfaceDistance:
        """Exact distances to the larger-volume surface, built once for every row of the lung."""
        return SurfaceDistance(self.target.surface.vertices, self.target.surface.faces)

    @cached_property
    def dome_mm(self) -> float | None:
        """The dome excursion measured from the two scans (:func:`measured_excursion`), once for every row
        of the lung that is given it."""
        return measured_excursion(self.rest, self.keep, self.target)


def measured_excursion(rest: Surface, keep, target) -> float | None:
    """``E`` mm from the smaller-volume ``rest`` (``keep (n,) bool``: its vertices off the crop faces) to the
    larger-volume ``target`` (a :class:`lungdeform.fit.objective.Target`); None when the scans cut off the apex
    or the dome."""
    try:
        return dome_excursion(rest, target.surface, keep_smaller=keep, keep_larger=target.keep)
    except InputError:
        return None


def isotropic_vertices(rest: Surface, volume_ml: float, points=None) -> tuple[np.ndarray, np.ndarray | None]:
    """``(vertices (n, 3), points (m, 3) or None)`` mm: ``rest`` (and ``points``) scaled about the solid's
    centroid so that its volume is ``volume_ml``."""
    _, mu, _ = solid_moments(rest.vertices, rest.faces)
    s = (volume_ml / rest.volume_ml) ** (1.0 / 3.0)
    return mu + (rest.vertices - mu) * s, None if points is None else mu + (np.asarray(points, float) - mu) * s


def lung_sides(subject: Subject, splits: SplitCache | None = None) -> tuple[str, ...]:
    """The lungs of ``subject`` to take: its ``sides``, else both lungs of a mask (or lobe map) holding
    both, else the one lung its smaller-volume mask holds, its side from its shape
    (:func:`lungdeform.geometry.frame.clear_side`; :class:`InputError` naming the file when unclear)."""
    if subject.sides:
        return tuple(subject.sides)
    image = read_image(subject.scans[0])
    if side_mask(image, "left") is not image or find_lungs(image, cache=splits) is not None:
        return SIDES
    surface = extract_surface(image, name=Path(subject.scans[0]).name).surface
    side, score = clear_side(surface.vertices, surface.faces)
    if side is None:
        raise InputError(f"{subject.scans[0]}: one lung whose side its shape does not tell (score {score:+.3f}); "
                         "give both lungs in the mask")
    return (side,)


def read_pair(subject: Subject, side: str, progress: Progress | None = None,
              splits: SplitCache | None = None) -> LungPair:
    """The ``side`` lung of ``subject`` (module docstring); ``splits``: where a mask holding both lungs
    is split (one cache for both lungs of a subject)."""
    lms = list(subject.landmarks) if subject.landmarks else None
    inputs = FitInputs(list(subject.scans), side, landmarks=lms, splits=splits)
    read = read_inputs(inputs, True, progress)
    placed = place_targets(read, read.paths, lms or [None, None], "none", progress)
    volume = placed.rest.volume_ml + read.volumes_ml[1] - read.volumes_ml[0]
    landmarks = (None, None) if read.landmarks is None else (read.landmarks[0], read.landmarks[1])
    cut = tuple(f"{phase} {p.label}" for phase, planes in zip(("exp", "insp"), read.planes) for p in planes)
    pair = LungPair(subject.name, side, placed.rest, placed.keep, placed.targets[0], float(volume), *landmarks, cut)
    return exclude_cuts(pair, read.planes[0], read.planes[1]) if cut else pair


def exclude_cuts(pair: LungPair, rest_planes: list[CropPlane], target_planes: list[CropPlane]) -> LungPair:
    """``pair`` with its cut left out of the surface distance (module docstring): ``rest_planes`` are the
    smaller-volume scan's crop faces (its frame), ``target_planes`` the larger-volume scan's (its frame)."""
    grown, _ = isotropic_vertices(pair.rest, pair.volume_ml)
    tv = pair.target.surface.vertices
    first = Target(pair.target.surface, pair.target.volume_ml, ~near_planes(tv, target_planes))  # own cut only
    start = best_translation(grown, pair.rest.faces, ~near_planes(pair.rest.vertices, rest_planes), first)
    shift = RigidTransform(np.eye(3), start)
    keep = ~near_planes(pair.rest.vertices, rest_planes) & ~near_planes(grown + start, target_planes)
    target_keep = ~near_planes(tv, target_planes) & ~near_planes(tv, [p.transformed(shift) for p in rest_planes])
    target = Target(pair.target.surface, pair.target.volume_ml, target_keep, pair.target.name)
    return LungPair(pair.subject, pair.side, pair.rest, keep, target, pair.volume_ml, pair.landmarks_rest,
                    pair.landmarks_target, pair.cut)


def files_digest(subject: Subject, side: str) -> str:
    """SHA-256 (16 hex digits) of the subject's files (scans and landmarks), the side and :data:`PAIR_VERSION`."""
    h = hashlib.sha256(f"{side}/{PAIR_VERSION}".encode())
    for p in [*subject.scans, *(subject.landmarks or ())]:
        h.update(Path(p).read_bytes())
    return h.hexdigest()[:16]


def _pair_arrays(pair: LungPair) -> dict:
    none = np.zeros((0, 3))
    return {"subject": np.array(pair.subject), "side": np.array(pair.side), "rest_vertices": pair.rest.vertices,
            "rest_faces": pair.rest.faces, "rest_name": np.array(pair.rest.name), "keep": pair.keep,
            "target_vertices": pair.target.surface.vertices, "target_faces": pair.target.surface.faces,
            "target_name": np.array(pair.target.name), "target_surface_name": np.array(pair.target.surface.name),
            "target_volume_ml": np.array(pair.target.volume_ml),
            "target_keep": np.ones(pair.target.surface.n_vertices, bool) if pair.target.keep is None else pair.target.keep,
            "volume_ml": np.array(pair.volume_ml), "has_landmarks": np.array(pair.landmarks_rest is not None),
            "landmarks_rest": none if pair.landmarks_rest is None else pair.landmarks_rest,
            "landmarks_target": none if pair.landmarks_target is None else pair.landmarks_target,
            "cut": np.array(list(pair.cut), dtype=str)}


def _pair_from(z) -> LungPair:
    lms = (z["landmarks_rest"], z["landmarks_target"]) if bool(z["has_landmarks"]) else (None, None)
    rest = Surface(z["rest_vertices"], z["rest_faces"], str(z["rest_name"]))
    target = Target(Surface(z["target_vertices"], z["target_faces"], str(z["target_surface_name"])),
                    float(z["target_volume_ml"]), z["target_keep"], str(z["target_name"]))
    return LungPair(str(z["subject"]), str(z["side"]), rest, z["keep"], target, float(z["volume_ml"]), *lms,
                    tuple(str(c) for c in z["cut"]))


def cached_pair(subject: Subject, side: str, folder: Path | None, progress: Progress | None = None,
                splits: SplitCache | None = None) -> LungPair:
    """:func:`read_pair`, kept in ``folder/pairs/<subject>_<side>_<digest>.npz`` (:func:`files_digest`)
    and read back from there when present (None: no cache)."""
    if folder is None:
        return read_pair(subject, side, progress, splits)
    path = Path(folder) / "pairs" / f"{subject.name}_{side}_{files_digest(subject, side)}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                return _pair_from(z)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is read again
    pair = read_pair(subject, side, progress, splits)
    buf = io.BytesIO()
    np.savez(buf, **_pair_arrays(pair))
    write_bytes(path, buf.getvalue())
    return pair
