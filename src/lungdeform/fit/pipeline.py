"""The fit pipeline: a lung model fitted to surfaces, masks or CTs at two or more volumes.

Library code behind ``lungdeform fit``, ``lungdeform validate itk-pair`` and the cohort runner
(:mod:`lungdeform.cohort.runner`); it imports nothing from the CLI. :func:`run_fit`:

1. read every input (mesh file, mask image, or CT in HU, segmented with
   :func:`lungdeform.fit.segment.segment_lungs`) into a full-resolution surface; for images, note the
   border faces the mask touches (crop faces) and check that all images share one voxel spacing;
2. check the inputs: one side, volumes strictly increasing, landmarks inside their images;
3. the first input is end-exhale; its surface is decimated to the model mesh (a few thousand
   vertices); every other surface is brought into its frame (``align``, :data:`ALIGN_MODES`):
   ``"apex"`` rigidly aligns it on the apex cap and a posterior band
   (:func:`lungdeform.fit.align.align_apex`; scans with a table shift), ``"none"`` takes it as it is
   (inputs already in one frame, e.g. a synthetic cohort), ``"joint"`` starts from the apex
   alignment and fits a translation per target jointly with the model constants (step 4), which
   removes a table shift without assuming that the apex and the posterior band do not move; the
   surfaces are refused if they do not overlap;
4. fit (:func:`lungdeform.fit.fitting.fit_lung`), optimiser and optionally the grid mode, and the
   baselines (:mod:`lungdeform.fit.baselines`), all measured with the same metrics, crop faces left out;
   with landmarks, the headline ``model`` is the surface fit with the interior landmark correction
   (:mod:`lungdeform.interior.field`), with the landmark-informed references (and, with
   ``landmark_comparisons``, the landmark-informed fit of c1…c9,
   :func:`lungdeform.fit.crossval.cross_validate_landmarks`) beside it, all scored on held-out
   landmarks (k-fold); with ``"joint"`` the translations of the surface-only fit move the targets (and their
   landmarks) before everything after it;
5. write ``model.npz`` (docs/MODEL_FORMAT.md), ``metrics.json`` and ``report.html``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lungdeform.atomic import jsonable, write_json
from lungdeform.errors import InputError, LungdeformError, ReadError
from lungdeform.fit import baselines as B
from lungdeform.fit.align import RigidTransform, align_apex, align_landmarks, crop_planes, near_planes
from lungdeform.fit.crossval import cross_validate_landmarks
from lungdeform.fit.ct import archive_in, is_archive, read_ct
from lungdeform.fit.direction_correction import DEFAULT_DEGREE, MAX_DEGREE
from lungdeform.fit.fitting import DIRECTION_HI, DIRECTION_LO, MODES, fit_lung, to_lung_model
from lungdeform.fit.objective import Target
from lungdeform.fit.report import write_report
from lungdeform.fit.segment import segment_lungs
from lungdeform.geometry.distance import SurfaceDistance, point_to_surface
from lungdeform.geometry.frame import SIDES, check_side
from lungdeform.geometry.mesh import Surface, check_surface, winding_numbers
from lungdeform.geometry.remesh import decimate
from lungdeform.interior.field import (
    correction_per_unit,
    correction_solvers,
    held_out_sliding,
    landmark_folds,
    select_correction_smoothing,
)
from lungdeform.io import mask as M
from lungdeform.io import meshfile as lio
from lungdeform.io.image import Image, is_image_path, read_image
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.io.modelfile import provenance, save_model
from lungdeform.model.lung import Model

#: Ways of bringing the larger-volume inputs into the end-exhale frame (see the module docstring).
ALIGN_MODES = ("apex", "joint", "none")

#: Model-mesh sizes tried in turn (mesh decimation can fail on a given budget; the next is tried).
MODEL_MESH_BUDGETS = (3000, 3200, 2800, 3500, 4000, 2500, 5000)


def read_input(path: Path, side: str, *, progress=None, spacing_like=None):
    """``(dense Surface, crop planes, spacing or None, image or None)`` for one input path.

    ``spacing_like``: ``(path, spacing (3,) mm)`` of an image read before; an image of another
    spacing is refused as soon as it is read, before the (slow) segmentation and surface."""

    path = Path(path)
    if not path.exists():

        raise ReadError(f"{path}: no such file or directory")

    path = archive_in(path)  # a dataset folder holding one archive: that archive
    if is_archive(path):  # a zipped or tarred DICOM series (or image): a CT
        image = read_ct(path)
    elif not is_image_path(path):
        surface, _ = lio.load_surface(path, name=path.name)
        return surface, [], None, None
    else:
        image = read_image(path)
    if spacing_like is not None and not np.allclose(image.spacing, spacing_like[1], rtol=1e-3):

        raise InputError(f"{path}: voxel spacing {np.asarray(image.spacing, float).tolist()} mm differs from "
                         f"{spacing_like[0]} ({np.asarray(spacing_like[1], float).tolist()} mm); inconsistent spacing")
    a = np.asarray(image.array)
    if a.size and a.min() < -100:  # a CT in HU: segment the lungs first

        seg = segment_lungs(image, progress=progress)
        image = Image(getattr(seg, side).astype(np.uint8), image.spacing, image.origin, image.direction,
                      f"{image.source} ({side} lung)")
    else:  # a lobe label map holds both lungs: keep this side's lobes (binary masks pass unchanged)
        image = M.side_mask(image, side)
    surface = M.extract_surface(image, name=path.name).surface
    return surface, crop_planes(image), np.asarray(image.spacing, float), image


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


#: Landmark sets whose rigid motion differs more than this from the apex alignment (at the lung
#: centroid) are reported (measured on the ITK pair: 9 mm in order, 74 mm with the files swapped).
LANDMARK_ALIGNMENT_GAP_MM = 30.0
#: Landmarks more than this outside their own image's lung mask count as outside (mm).
LANDMARK_OUTSIDE_MM = 3.0


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


def run_fit(inputs, *, side: str, out: Path, volumes=None, landmarks=None, grid: bool = False,
            stiffness: bool = False, baselines: bool = True, max_evaluations: int = 300,
            command: str = "fit", progress=None, landmark_fit: bool = True, folds: int = 5,
            landmark_weight: float = 1.0, align: str = "apex", mode: str = "optimizer",
            direction_degree: int = DEFAULT_DEGREE, landmark_comparisons: bool = False,
            side_check: bool = True) -> dict:
    """Run the whole pipeline; write model.npz, metrics.json and report.html in ``out``; return
    the metrics dictionary.

    Without landmarks (or with ``landmark_fit=False``) the headline ``model`` is the surface-only
    fit. With landmarks and ``landmark_fit`` it is the same surface fit whose interior field carries
    the landmark correction (:mod:`lungdeform.interior.field`; stored in ``model.npz``), with landmark
    errors measured on landmarks held out from the correction (``folds``-fold); the surface-driven
    field alone is reported as ``model_surface_only``, the landmark-informed fit of c1…c9 as
    ``model_landmark_fit`` (with ``landmark_comparisons``), and the landmark-informed references ``affine_landmarks`` and ``landmarks_tps`` are scored on the same
    folds. ``metrics["protocols"]`` says, per method, what
    it saw and how its landmark error was measured.

    ``landmark_comparisons`` (with landmarks): also run the landmark-informed fits of c1…c9
    (:func:`lungdeform.fit.crossval.cross_validate_landmarks`, ``folds`` + 1 fits, and as many again with
    ``stiffness``) as comparison rows ``model_landmark_fit`` / ``model_landmarks_stiffness``; slow,
    so off by default (``validate itk-pair`` turns it on).

    ``direction_degree``: the smooth correction of the directions fitted after the constants
    (:mod:`lungdeform.fit.direction_correction`; 0: the paper's directions only); with it, the paper's
    field is reported as ``model_paper_directions``; with a stiffness field, the paper's model
    (uniform stiffness, paper directions) as ``model_uniform_stiffness``.

    ``side_check``: refuse inputs whose shape clearly says the other side
    (:func:`lungdeform.geometry.frame.check_side`).

    ``align``: one of :data:`ALIGN_MODES` (module docstring, step 3); ``metrics["alignment"][i]
    ["applied"]`` is the rigid transform (moving → end-exhale) the fitted target went through.
    ``mode``: the search mode of the fits (:data:`lungdeform.fit.fitting.MODES`, ``"grid"`` excepted)."""

    say = progress or (lambda _m: None)
    t_start = time.perf_counter()
    if side not in SIDES:
        raise InputError(f"--side must be 'left' or 'right', got {side!r}")
    if align not in ALIGN_MODES:
        raise InputError(f"--align must be one of {', '.join(ALIGN_MODES)}, got {align!r}")
    if not (isinstance(direction_degree, (int, np.integer)) and 0 <= direction_degree <= MAX_DEGREE):
        raise InputError(f"--direction-degree must be a whole number 0…{MAX_DEGREE}, got {direction_degree!r}")
    if mode not in MODES or mode == "grid":
        raise InputError(f"mode must be one of {', '.join(m for m in MODES if m != 'grid')}, got {mode!r}")
    if align == "joint" and mode not in ("optimizer", "least_squares"):
        raise InputError(f"--align joint needs the least-squares optimiser, not mode {mode!r}")
    if len(inputs) < 2:
        raise InputError(f"fit needs inputs at two or more volumes (end-exhale first), got {len(inputs)}")
    read, first_image = [], None  # every image is checked against the first one's spacing as soon as it is read
    for p in inputs:
        say(f"reading {p}")
        read.append(read_input(Path(p), side, progress=say, spacing_like=first_image))
        if first_image is None and read[-1][2] is not None:
            first_image = (p, read[-1][2])
    surfaces = [r[0] for r in read]
    # sides: every input must be the same lung (centroids on the same side of each other's medial face)
    widths = [np.ptp(s.vertices[:, 0]) for s in surfaces]
    cx = [s.vertices[:, 0].mean() for s in surfaces]
    for p, c in zip(inputs[1:], cx[1:]):
        if abs(c - cx[0]) > 0.75 * max(widths):
            raise InputError(f"{p}: this lung lies {c - cx[0]:+.0f} mm from the end-exhale lung along x; "
                             "the sides do not match (left and right lungs mixed)")
    for p, s in zip(inputs, surfaces) if side_check else ():  # each is the lung --side says (its medial face)
        check_side(s.vertices, s.faces, side, str(p))
    warnings: list[str] = []  # suspicious but usable input: in metrics["warnings"], printed by the CLI
    given = None
    if volumes is None:
        vols = [s.volume_ml for s in surfaces]
    else:
        given = [float(v) for v in volumes]
        if len(given) != len(surfaces):
            raise InputError(f"--volumes has {len(given)} values for {len(surfaces)} inputs")
        if not all(np.isfinite(v) and v > 0 for v in given):
            raise InputError(f"--volumes must be positive mL, got {', '.join(f'{v:g}' for v in given)}")
        vols = list(given)  # anchored on the model mesh below, once it exists
    for i in range(1, len(vols)):
        if not vols[i] > vols[i - 1]:
            shown = given or vols
            raise InputError(f"{inputs[i]}: volume {shown[i]:.1f} mL is not larger than that of "
                             f"{inputs[i - 1]} ({shown[i - 1]:.1f} mL); volumes must increase (end-exhale first)")
    lms = None
    if landmarks:
        if len(landmarks) != len(inputs):
            raise InputError(f"--landmarks needs one file per input ({len(inputs)}), got {len(landmarks)}")
        # 'index' point files are voxel indices of their own image
        lms = [read_elastix_points(p, *(() if r[3] is None else (r[3].spacing, r[3].origin, r[3].direction)))
               for p, r in zip(landmarks, read)]
        for p, pts in zip(landmarks[1:], lms[1:]):
            if pts.shape != lms[0].shape:
                raise InputError(f"{p}: {len(pts)} landmarks, the end-exhale file has {len(lms[0])}")
        for p, pts, r in zip(landmarks, lms, read):
            check_landmarks(pts, r[3], p)
            warnings += landmark_mask_warnings(pts, r[3], r[0], p)
    # the landmark folds, split (and --folds checked) once, before any fitting
    lm_folds = landmark_folds(len(lms[0]), folds, parameter="--folds") if lms is not None and landmark_fit else None

    fixed_dense, fixed_planes = surfaces[0], read[0][1]
    say("model mesh (decimation)")
    rest = model_mesh(fixed_dense)
    if given is not None:
        # the model's end-exhale volume is its mesh's; the given volumes fix the changes from it
        # (spirometry and segmentation disagree on absolute volume, not on its changes)
        vols = [rest.volume_ml + v - given[0] for v in given]
    targets, alignments, aligned_lms, transforms = [], [], [], []
    crop_all = list(fixed_planes)  # every crop face, in the end-exhale frame
    for i in range(1, len(surfaces)):
        moving, planes_m = surfaces[i], read[i][1]
        if align == "none":
            xf = RigidTransform.identity()
        else:
            al = align_apex(fixed_dense, moving, exclude_moving=near_planes(moving.vertices, planes_m),
                            exclude_fixed=near_planes(fixed_dense.vertices, fixed_planes))
            xf = al.transform
        target, planes = _place(moving, planes_m, xf, fixed_planes, vols[i], Path(inputs[i]).name)
        lo = np.maximum(fixed_dense.bounds[0], target.surface.bounds[0])
        hi = np.minimum(fixed_dense.bounds[1], target.surface.bounds[1])
        overlap = np.prod(np.clip(hi - lo, 0, None)) / np.prod(np.ptp(fixed_dense.vertices, axis=0))
        if overlap < 0.5:
            raise InputError(f"{inputs[i]}: after alignment its bounding box overlaps only {overlap:.0%} of the "
                             f"end-exhale lung's; the volumes do not overlap (different subject or wrong side?)")
        crop_all += planes
        targets.append(target)
        transforms.append(xf)
        info = {"target": Path(inputs[i]).name, "method": align, "applied": xf.as_dict(),
                "crop_planes": len(fixed_planes) + len(planes)}
        if align != "none":
            info["apex"] = al.as_dict()
        if lms is not None:
            lal = align_landmarks(lms[0], lms[i])
            info["landmarks_rigid_for_comparison"] = lal.as_dict()
            # the two rigid parts compared where it matters (a rotation about the far-away world
            # origin makes the translations themselves incomparable): at the moving lung's centroid
            c = moving.vertices.mean(axis=0)[None]
            info["landmarks_minus_apex_at_lung_centroid_mm"] = (lal.transform.apply(c) - xf.apply(c))[0].tolist()
            gap = float(np.linalg.norm(info["landmarks_minus_apex_at_lung_centroid_mm"]))
            if align != "none" and gap > LANDMARK_ALIGNMENT_GAP_MM:
                warnings.append(f"{landmarks[i]}: the landmarks' rigid motion differs from the apex alignment by "
                                f"{gap:.0f} mm at the lung centroid (expected a few mm): are the landmark files in "
                                f"the inputs' order and frame?")
            aligned_lms.append(xf.apply(lms[i]))
        alignments.append(info)
        say(f"aligned {inputs[i]} ({align}): translation {np.round(xf.translation, 2).tolist()} mm")
    keep = ~near_planes(rest.vertices, crop_all)  # model vertices near any crop face are not measured

    say(f"fitting ({len(targets)} target(s), model mesh {rest.n_vertices} vertices)")
    fit_opt = fit_lung(rest, side, targets, mode=mode, keep=keep, fit_stiffness=stiffness,
                       max_evaluations=max_evaluations, translate=align == "joint",
                       direction_degree=direction_degree, progress=say)
    if align == "joint":  # move every target (and its landmarks, crop faces) by its fitted translation
        crop_all = list(fixed_planes)
        for ti, (tg, t) in enumerate(zip(targets, fit_opt.translations)):
            shift = RigidTransform(np.eye(3), np.asarray(t, float))
            total = transforms[ti] = shift.compose(transforms[ti])
            targets[ti], planes = _place(surfaces[ti + 1], read[ti + 1][1], total, fixed_planes, tg.volume_ml, tg.name)
            crop_all += planes
            if lms is not None:
                aligned_lms[ti] = shift.apply(aligned_lms[ti])
            alignments[ti].update(applied=total.as_dict(), joint_translation_mm=[float(x) for x in t])
            say(f"joint alignment of {tg.name}: translation {np.round(t, 2).tolist()} mm on top of the apex alignment")
        keep = ~near_planes(rest.vertices, crop_all)
    at_bound = [f"c{i + 1}" for i in range(6) if np.isclose(fit_opt.constants[i], DIRECTION_LO[i], rtol=0, atol=1e-6)
                or np.isclose(fit_opt.constants[i], DIRECTION_HI[i], rtol=0, atol=1e-6)]
    if at_bound:
        warnings.append(f"{', '.join(at_bound)} ended on the bound of the search ({', '.join(f'{n} = {fit_opt.constants[int(n[1:]) - 1]:g}' for n in at_bound)}): "
                        "the surfaces may not be one lung at two volumes, or the alignment is off")
    fits = {"optimizer": fit_opt}
    if grid:
        fits["grid"] = fit_lung(rest, side, targets, mode="grid", keep=keep, grid_span=0.1, progress=say)
    use_lm = lms is not None and landmark_fit
    # the sliding interpolation from the kept model vertices to the landmarks: one dense solve,
    # shared by every landmark-informed fit (rows per fold) and by the metrics of every method
    lm0 = lms[0] if lms is not None else None
    lm_w = B.landmark_matrix(rest, lm0, keep) if lms is not None else None
    cv, cv_stiff = None, None
    if use_lm and landmark_comparisons:
        lm_targets = {ti: aligned_lms[ti] for ti in range(len(targets))}
        say(f"landmark-informed fit ({folds}-fold cross-validation over {len(lms[0])} landmarks)")
        cv = cross_validate_landmarks(rest, side, targets, lms[0], lm_targets, folds=lm_folds, keep=keep,
                                      initial=fit_opt.constants, mode=mode,
                                      max_evaluations=max(100, max_evaluations * 2 // 3),
                                      landmark_weight=landmark_weight, landmark_matrix=lm_w, progress=say)
        fits["landmarks"] = cv.final
        if stiffness:
            say("landmark-informed fit with a stiffness field (cross-validated)")
            cv_stiff = cross_validate_landmarks(rest, side, targets, lms[0], lm_targets, folds=lm_folds, keep=keep,
                                                initial=fit_opt.constants, fit_stiffness=True, mode=mode,
                                                max_evaluations=max(100, max_evaluations * 2 // 3),
                                                landmark_weight=landmark_weight, landmark_matrix=lm_w, progress=say)
    headline = fit_opt
    surface_name = "model_surface_only" if use_lm else "model"
    corrected = fit_opt.paper_displacement is not None
    kind = ", ".join(["c1…c9"] + (["stiffness field"] if fit_opt.stiffness_fitted else [])
                     + ([f"direction correction of degree {direction_degree}"] if corrected else []))
    protocols = {surface_name: f"surface fit ({kind}; no landmark used); landmarks moved by the sliding "
                               "interpolation of its surface displacement"}
    interior = None
    if use_lm:  # the landmark correction of the interior field (lungdeform.interior.field), held out per fold
        say("interior landmark correction (cross-validated)")
        interior = _interior_correction(fit_opt, lms[0], aligned_lms, targets, lm_folds, keep, lm_w, rest)

    metrics = {"inputs": [str(p) for p in inputs], "side": side, "volumes_ml": vols, "volumes_given_ml": given,
               "warnings": warnings,
               "model_mesh_vertices": rest.n_vertices, "alignment": alignments, "targets": {}}
    predictions = {}
    for ti, tg in enumerate(targets):
        td = SurfaceDistance(tg.surface.vertices, tg.surface.faces)
        lmt = aligned_lms[ti] if lms is not None else None
        methods = {}  # name -> (predicted vertices, held-out landmark predictions or None)
        s_opt = (tg.volume_ml - fit_opt.volume_ee_ml) / fit_opt.unit_ml
        if use_lm:
            methods["model"] = (fit_opt.positions_at(rest, tg.volume_ml), interior["held_out"][ti])
            protocols["model"] = (f"surface fit ({kind}; no landmark used) with the interior landmark correction "
                                  f"(lungdeform.interior.field): landmarks moved by the surface-driven sliding field "
                                  f"plus the sliding correction through the training landmarks' residual motion (it keeps the "
                                  f"surface's normal motion; smoothing chosen by inner cross-validation); "
                                  f"held-out landmark errors ({folds}-fold)")
        if cv is not None:
            methods["model_landmark_fit"] = (cv.final.positions_at(rest, tg.volume_ml), cv.predicted[ti])
            protocols["model_landmark_fit"] = (f"landmark-informed fit: c1…c9 (paper directions) on the surfaces and the "
                                               f"training landmarks, landmarks moved by the surface-driven field only; "
                                               f"held-out landmark errors ({folds}-fold), surface from the fit on all "
                                               f"landmarks")
            if cv_stiff is not None:
                methods["model_landmarks_stiffness"] = (cv_stiff.final.positions_at(rest, tg.volume_ml), cv_stiff.predicted[ti])
                protocols["model_landmarks_stiffness"] = protocols["model_landmark_fit"] + ", with a fitted stiffness field"
        methods[surface_name] = (fit_opt.positions_at(rest, tg.volume_ml), None)
        if corrected:
            methods["model_paper_directions"] = (rest.vertices + s_opt * fit_opt.paper_displacement, None)
            protocols["model_paper_directions"] = (f"the same fit with the paper's directions (15)–(17), no direction "
                                                   f"correction{' (stiffness field kept)' if fit_opt.stiffness_fitted else ''}; "
                                                   f"landmarks moved by the sliding interpolation of its surface")
        if fit_opt.uniform_displacement is not None:
            methods["model_uniform_stiffness"] = (rest.vertices + s_opt * fit_opt.uniform_displacement, None)
            protocols["model_uniform_stiffness"] = ("the paper's model: c1…c9 fitted to the surfaces, uniform stiffness, "
                                                    "the paper's directions; landmarks moved by the sliding "
                                                    "interpolation of its surface")
        if "grid" in fits:
            methods["model_grid"] = (fits["grid"].positions_at(rest, tg.volume_ml), None)
            protocols["model_grid"] = ("the paper's grid search of c1…c6 (uniform stiffness, paper directions); "
                                       "landmarks moved by the sliding interpolation of its surface")
        if baselines:
            say("baselines")
            methods["no_motion"] = (B.no_motion(rest), None)
            methods["affine"] = (B.affine_fit(rest, tg.surface, keep=keep, keep_target=tg.keep)[0], None)
            methods["apex_scaling"] = (B.apex_scaling(rest, tg.volume_ml), None)
            try:
                methods["cpd"] = (B.cpd_deformable(rest, tg.surface, keep=keep, keep_target=tg.keep), None)
            except ImportError as exc:  # pycpd missing: reported, not fatal
                metrics.setdefault("skipped", {})["cpd"] = str(exc)
            for name in ("no_motion", "affine", "apex_scaling", "cpd"):
                protocols[name] = "baseline from the surfaces only; landmarks moved by the same sliding interpolation"
            if use_lm:
                methods["affine_landmarks"] = B.affine_landmarks_cv(rest, tg.surface, lm0, lmt, lm_folds, keep=keep,
                                                                    keep_target=tg.keep, landmark_weight=landmark_weight)
                protocols["affine_landmarks"] = ("reference: affine fitted on the surfaces and the training landmarks "
                                                 "(same weighting and folds as the model); held-out landmark errors")
                methods["landmarks_tps"] = B.landmark_tps_cv(rest, lm0, lmt, lm_folds)
                protocols["landmarks_tps"] = ("reference without surfaces: thin-plate spline through the training "
                                              "landmarks; held-out landmark errors; its surface is that spline applied "
                                              "to the end-exhale surface")
        per = {}
        for name, (x, held) in methods.items():
            m, per_vertex, lm_err = B.measure(rest, x, tg.surface, keep=keep, keep_target=tg.keep,
                                              landmarks=lm0, landmarks_target=lmt, target_distance=td,
                                              landmark_weights=lm_w, landmarks_predicted=held)
            per[name] = m.as_dict()
            predictions[(tg.name, name)] = (x, per_vertex, lm_err)
        metrics["targets"][tg.name] = per
    # the headline (last, largest-volume target) at the top level, as issue 3 item 7 asks
    last = targets[-1].name
    metrics.update(metrics["targets"][last])
    metrics["protocols"] = protocols
    metrics["headline_fit"] = "optimizer"  # the key in metrics["fit"] of the saved constants
    metrics["interior_correction"] = interior is not None
    metrics["fit"] = {k: r.as_dict() for k, r in fits.items()}
    metrics["fit"]["optimizer"]["uniform_objective_rms_mm"] = fit_opt.uniform_objective_mm
    if use_lm:
        metrics["landmark_cv"] = {"folds": int(folds), "landmarks": int(len(lms[0])), "seed": 0,
                                  "landmark_weight": float(landmark_weight),
                                  "interior_smoothing_mm": interior["smoothing"]}
        if cv is not None:
            metrics["landmark_cv"].update(fold_constants=cv.fold_constants.tolist(),
                                          fold_constants_spread=cv.fold_constants.std(axis=0).tolist())
    metrics["bounding_box"] = _bounding_boxes(rest, headline, surfaces, vols)
    metrics["seconds"] = time.perf_counter() - t_start

    out.mkdir(parents=True, exist_ok=True)
    # the crop faces (image boundary, motion never fitted) do not drive the interior field
    lung = replace(to_lung_model(rest, side, headline), interior_vertices=None if keep.all() else keep.copy())
    if interior is not None:
        lung = replace(lung, landmarks=lms[0], landmark_correction=interior["correction"],
                       landmark_smoothing=interior["smoothing"])
    model = Model({side: lung}, provenance(command, inputs=[str(p) for p in inputs], volumes_ml=vols,
                                          fit=headline.as_dict(), alignment=alignments,
                                          fit_kind=metrics["headline_fit"],
                                          interior_correction=interior is not None))
    save_model(out / "model.npz", model)
    write_json(out / "metrics.json", metrics, strict=True, default=_json)
    write_report(out / "report.html", rest=rest, targets=targets, fits=fits, predictions=predictions,
                 metrics=metrics, headline=metrics["headline_fit"], keep=keep)
    return metrics


def _interior_correction(fit, landmarks, aligned, targets, folds, keep, weights, rest) -> dict:
    """The interior field's landmark correction for ``fit`` (:mod:`lungdeform.interior.field`): held-out
    landmark positions per target (k-fold), and the correction and its smoothing from all landmarks.
    The surface-driven part is the one the saved model plays back: the sliding interpolation from
    its kept vertices (``LungModel.interior_vertices``), here as the metrics' operator ``weights``
    (:func:`lungdeform.fit.baselines.landmark_matrix`, the same interpolant); the correction is the
    sliding correction through the same kept vertices of ``rest``."""

    unit = weights @ fit.displacement[keep]  # mm per unit
    observed = [np.asarray(a) - landmarks for a in aligned]
    scales = [(tg.volume_ml - fit.volume_ee_ml) / fit.unit_ml for tg in targets]
    correction = correction_per_unit(observed, scales, unit)
    solvers = correction_solvers(rest.vertices[keep], rest.vertex_normals[keep], landmarks)
    return {"held_out": held_out_sliding(observed, scales, unit, folds, solvers),
            "correction": correction,
            "smoothing": select_correction_smoothing(solvers, np.arange(len(landmarks)), correction)}


def _place(surface, planes, transform, fixed_planes, volume_ml: float, name: str):
    """Target ``surface`` placed in the end-exhale frame by the rigid ``transform`` (moving →
    end-exhale): ``(Target, its crop planes moved by transform)``; the target's vertices near any
    of those planes or of the end-exhale ``fixed_planes`` are not measured."""

    placed = transform.apply_surface(surface)
    moved = [p.transformed(transform) for p in planes]
    return Target(placed, volume_ml, ~near_planes(placed.vertices, fixed_planes + moved), name), moved


def _bounding_boxes(rest, fit, surfaces, vols):
    """Bounding-box dimensions (mm) and volume / box-volume ratio against volume: observed surfaces
    and the model's prediction over the same volume range (paper Fig. 4)."""
    obs = [{"volume_ml": v, "dims_mm": np.ptp(s.vertices, axis=0).tolist(),
            "ratio": v * 1000.0 / float(np.prod(np.ptp(s.vertices, axis=0)))} for s, v in zip(surfaces, vols)]
    model = []
    for v in np.linspace(vols[0], vols[-1], 6):
        x = fit.positions_at(rest, v)
        dims = np.ptp(x, axis=0)
        model.append({"volume_ml": float(v), "dims_mm": dims.tolist(), "ratio": float(v * 1000.0 / np.prod(dims))})
    return {"observed": obs, "model": model}


def _json(o):

    try:
        return jsonable(o)
    except TypeError:
        return str(o)
