"""The model mesh and the targets in its frame (steps 2 and 3 of :func:`lungdeform.evaluate.pipeline.run_fit`).

The first input is end-exhale: its surface, decimated to a few thousand vertices (:func:`model_mesh`),
is the model mesh. Every other surface is brought into its frame (``align``,
:data:`lungdeform.fit.config.ALIGN_MODES`): ``"apex"`` rigidly aligns it on the apex cap and a
posterior band (:func:`lungdeform.fit.align.align_apex`; scans with a table shift), ``"none"`` takes
it as it is (inputs already in one frame, e.g. a synthetic cohort), ``"joint"`` starts from the apex
alignment and later moves each target by the translation fitted jointly with the model constants
(:func:`shift_targets`), which removes a table shift without assuming that the apex and the
posterior band do not move. Surfaces whose bounding boxes barely overlap once aligned are refused.
Model vertices near any crop face (image border, motion never fitted) are not measured.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError, LungdeformError
from lungdeform.fit.align import CropPlane, RigidTransform, align_apex, align_landmarks, near_planes
from lungdeform.fit.objective import Target
from lungdeform.geometry.mesh import Surface, check_surface
from lungdeform.geometry.remesh import decimate
from lungdeform.progress import Progress, silent

from .inputs import ReadInputs

#: Model-mesh sizes tried in turn (mesh decimation can fail on a given budget; the next is tried).
MODEL_MESH_BUDGETS = (3000, 3200, 2800, 3500, 4000, 2500, 5000)
#: Landmark sets whose rigid motion differs more than this from the apex alignment (at the lung
#: centroid) are reported (measured on the ITK pair: 9 mm in order, 74 mm with the files swapped).
LANDMARK_ALIGNMENT_GAP_MM = 30.0
#: Aligned bounding boxes overlapping less than this fraction of the end-exhale lung's are refused.
MIN_OVERLAP = 0.5


@dataclass(frozen=True, eq=False)
class Placement:
    """The model mesh and the targets in its (end-exhale) frame; lists per target (inputs 2…).

    Attributes
    ----------
    rest : Surface
        The model mesh (end-exhale), mm.
    volumes_ml : list of float
        Every input's volume (mL); given volumes are anchored on the model mesh's own.
    targets : list of Target
        Each larger-volume surface in the end-exhale frame, its crop-face vertices not measured.
    transforms : list of RigidTransform
        Moving → end-exhale, as applied to each target.
    alignments : list of dict
        What each alignment did (``metrics["alignment"]``).
    landmarks : list of (m, 3) float or None
        Each target's landmarks moved by its transform, mm.
    planes : list of CropPlane
        Every crop face in the end-exhale frame.
    keep : (n,) bool
        Model vertices away from every crop face (measured, and driving the interior field).
    warnings : list of str
        Landmark sets whose rigid motion disagrees with the alignment.
    """

    rest: Surface
    volumes_ml: list[float]
    targets: list[Target]
    transforms: list[RigidTransform]
    alignments: list[dict]
    landmarks: list[np.ndarray] | None
    planes: list[CropPlane]
    keep: np.ndarray
    warnings: list[str]


def model_mesh(surface, image=None):
    """The end-exhale model mesh: the mask's surface decimated to about 3000 vertices."""

    if surface.n_vertices <= MODEL_MESH_BUDGETS[0] * 1.2:
        return surface
    last = None
    for budget in MODEL_MESH_BUDGETS:
        try:
            v, f, _ = decimate(surface.vertices, surface.faces, budget)
            v, f, _ = check_surface(v, f, source=surface.name)
            return Surface(v, f, surface.name)
        except LungdeformError as exc:
            last = exc
    raise last


def place_targets(read: ReadInputs, paths, landmark_paths, align: str,
                  progress: Progress | None = None) -> Placement:
    """The model mesh of the first input and every other input ``paths[i]`` (landmark file
    ``landmark_paths[i]``) brought into its frame by ``align`` (module docstring)."""

    say = progress or silent
    say("model mesh (decimation)")
    rest = model_mesh(read.surfaces[0])
    vols = read.volumes_ml
    if read.given_ml is not None:
        # the model's end-exhale volume is its mesh's; the given volumes fix the changes from it
        # (spirometry and segmentation disagree on absolute volume, not on its changes)
        vols = [rest.volume_ml + v - read.given_ml[0] for v in read.given_ml]
    targets, transforms, alignments, warnings = [], [], [], []
    aligned_lms = [] if read.landmarks is not None else None
    planes = list(read.planes[0])  # every crop face, in the end-exhale frame
    for i in range(1, len(read.surfaces)):
        target, moved, xf, info = _align_one(read, i, align, vols[i], Path(paths[i]))
        planes += moved
        targets.append(target)
        transforms.append(xf)
        if read.landmarks is not None:
            warnings += _compare_landmarks(read, i, xf, info, align, landmark_paths[i])
            aligned_lms.append(xf.apply(read.landmarks[i]))
        alignments.append(info)
        say(f"aligned {paths[i]} ({align}): translation {np.round(xf.translation, 2).tolist()} mm")
    keep = ~near_planes(rest.vertices, planes)  # model vertices near any crop face are not measured
    return Placement(rest, vols, targets, transforms, alignments, aligned_lms, planes, keep, warnings)


def _align_one(read: ReadInputs, i: int, align: str, volume_ml: float, path: Path):
    """Input ``i`` placed in the end-exhale frame: ``(Target, its crop planes moved,
    RigidTransform applied, alignment record)``; refused if it barely overlaps the end-exhale lung."""

    fixed, fixed_planes = read.surfaces[0], read.planes[0]
    moving, planes_m = read.surfaces[i], read.planes[i]
    if align == "none":
        al, xf = None, RigidTransform.identity()
    else:
        al = align_apex(fixed, moving, exclude_moving=near_planes(moving.vertices, planes_m),
                        exclude_fixed=near_planes(fixed.vertices, fixed_planes))
        xf = al.transform
    target, moved = place(moving, planes_m, xf, fixed_planes, volume_ml, path.name)
    lo = np.maximum(fixed.bounds[0], target.surface.bounds[0])
    hi = np.minimum(fixed.bounds[1], target.surface.bounds[1])
    overlap = np.prod(np.clip(hi - lo, 0, None)) / np.prod(np.ptp(fixed.vertices, axis=0))
    if overlap < MIN_OVERLAP:
        raise InputError(f"{path}: after alignment its bounding box overlaps only {overlap:.0%} of the "
                         f"end-exhale lung's; the volumes do not overlap (different subject or wrong side?)")
    info = {"target": path.name, "method": align, "applied": xf.as_dict(),
            "crop_planes": len(fixed_planes) + len(moved)}
    if al is not None:
        info["apex"] = al.as_dict()
    return target, moved, xf, info


def _compare_landmarks(read: ReadInputs, i: int, xf: RigidTransform, info: dict, align: str,
                       landmark_path) -> list[str]:
    """Record in ``info`` the landmarks' own rigid motion of input ``i`` against the applied ``xf``;
    a warning when they differ by more than :data:`LANDMARK_ALIGNMENT_GAP_MM` at the lung centroid."""

    lal = align_landmarks(read.landmarks[0], read.landmarks[i])
    info["landmarks_rigid_for_comparison"] = lal.as_dict()
    # the two rigid parts compared where it matters (a rotation about the far-away world
    # origin makes the translations themselves incomparable): at the moving lung's centroid
    c = read.surfaces[i].vertices.mean(axis=0)[None]
    info["landmarks_minus_apex_at_lung_centroid_mm"] = (lal.transform.apply(c) - xf.apply(c))[0].tolist()
    gap = float(np.linalg.norm(info["landmarks_minus_apex_at_lung_centroid_mm"]))
    if align != "none" and gap > LANDMARK_ALIGNMENT_GAP_MM:
        return [f"{landmark_path}: the landmarks' rigid motion differs from the apex alignment by "
                f"{gap:.0f} mm at the lung centroid (expected a few mm): are the landmark files in "
                f"the inputs' order and frame?"]
    return []


def shift_targets(placed: Placement, read: ReadInputs, translations,
                  progress: Progress | None = None) -> Placement:
    """``placed`` with every target (its landmarks and crop faces) moved by its jointly fitted
    translation ``translations : (k, 3) float`` mm (``align="joint"``)."""

    say = progress or silent
    planes = list(read.planes[0])
    targets, transforms, alignments = list(placed.targets), list(placed.transforms), list(placed.alignments)
    landmarks = None if placed.landmarks is None else list(placed.landmarks)
    for ti, (tg, t) in enumerate(zip(placed.targets, translations)):
        shift = RigidTransform(np.eye(3), np.asarray(t, float))
        total = transforms[ti] = shift.compose(transforms[ti])
        targets[ti], moved = place(read.surfaces[ti + 1], read.planes[ti + 1], total, read.planes[0],
                                   tg.volume_ml, tg.name)
        planes += moved
        if landmarks is not None:
            landmarks[ti] = shift.apply(landmarks[ti])
        alignments[ti] = {**alignments[ti], "applied": total.as_dict(), "joint_translation_mm": [float(x) for x in t]}
        say(f"joint alignment of {tg.name}: translation {np.round(t, 2).tolist()} mm on top of the apex alignment")
    return replace(placed, targets=targets, transforms=transforms, alignments=alignments, landmarks=landmarks,
                   planes=planes, keep=~near_planes(placed.rest.vertices, planes))


def place(surface, planes, transform, fixed_planes, volume_ml: float, name: str):
    """Target ``surface`` placed in the end-exhale frame by the rigid ``transform`` (moving →
    end-exhale): ``(Target, its crop planes moved by transform)``; the target's vertices near any
    of those planes or of the end-exhale ``fixed_planes`` are not measured."""

    placed = transform.apply_surface(surface)
    moved = [p.transformed(transform) for p in planes]
    return Target(placed, volume_ml, ~near_planes(placed.vertices, fixed_planes + moved), name), moved
