"""The fit pipeline: a lung model fitted to surfaces, masks or CTs at two or more volumes.

Library code behind ``lungdeform fit``, ``lungdeform validate itk-pair``
(:mod:`lungdeform.validate.itk_pair`) and the cohort runner (:mod:`lungdeform.cohort.job`); it
imports nothing from the CLI. :func:`run_fit` takes one lung's inputs
(:class:`~lungdeform.fit.config.FitInputs`) and a validated :class:`~lungdeform.fit.config.FitConfig`,
and runs these steps, each a function of its own:

1. read and check every input (:func:`lungdeform.evaluate.inputs.read_inputs`): surfaces, crop faces,
   one side, volumes increasing from end-exhale (equal ones allowed), landmarks inside their images;
   a 4-D CT's hysteresis measured (:mod:`lungdeform.fit.cycle`); the landmark folds are
   split (and ``folds`` checked against the landmark count) before any fitting;
2. and 3. the model mesh (the end-exhale surface decimated) and every other surface in its frame
   (``align``, ``"auto"`` resolved by :func:`lungdeform.fit.cycle.choose_alignment`;
   :func:`lungdeform.evaluate.placement.place_targets`);
4. the surface fit of c1…c9 (:func:`fit_surfaces`: :func:`lungdeform.fit.fitting.fit_lung`, and
   optionally the paper's grid search); with ``align="joint"`` its fitted translations move the
   targets (and their landmarks) before everything after it; then the surface refinement of the
   headline fit (:func:`refine_surface`, :mod:`lungdeform.fit.refinement`);
5. with landmarks, what they give scored on held-out landmarks (k-fold;
   :func:`lungdeform.evaluate.heldout.held_out_landmarks`): the interior landmark correction
   (:mod:`lungdeform.interior.field`) of the headline ``model`` and, with ``landmark_comparisons``,
   the landmark-informed fits of c1…c9;
6. every method, the baselines and references measured on every target with the same metrics, crop
   faces left out (:mod:`lungdeform.evaluate.scoring`). Steps 1 to 6 are :func:`fit_pipeline`; what they
   give is one frozen :class:`~lungdeform.evaluate.outcome.FitRun`, from which the metrics dictionary
   is built once (:func:`fit_metrics`; nothing is added to it afterwards);
7. ``model.npz`` (docs/MODEL_FORMAT.md), ``metrics.json`` and ``report.html`` written (:func:`write_outputs`).
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lungdeform import blas
from lungdeform.atomic import jsonable, write_json, write_npz
from lungdeform.errors import InputError
from lungdeform.fit.config import CROP_LIMIT, FitConfig, FitInputs
from lungdeform.fit.cycle import choose_alignment
from lungdeform.fit.fitting import DIRECTION_HI, DIRECTION_LO, FitOutcome, FitSettings, fit_lung, to_lung_model
from lungdeform.fit.refinement import refine_displacement
from lungdeform.fit.registration import surface_map_field
from lungdeform.geometry.mesh import Surface
from lungdeform.interior.motion_prior import MotionPrior, lung_normaliser
from lungdeform.io.modelfile import provenance, save_model
from lungdeform.model.lung import Model
from lungdeform.progress import Progress, silent

from .folds import landmark_folds
from .heldout import held_out_landmarks
from .inputs import ReadInputs, read_inputs
from .outcome import AlignmentChoice, FitRun, Fits
from .placement import Placement, place_targets, shift_targets
from .report import write_report
from .scoring import bounding_boxes, protocols, score_targets


def run_fit(inputs: FitInputs, out: Path, config: FitConfig = FitConfig(), *,
            progress: Progress | None = None, prior: MotionPrior | None = None) -> dict:
    """Run the whole pipeline (module docstring) on ``inputs``; write model.npz, metrics.json and
    report.html in the folder ``out`` (created if missing); return the metrics dictionary, built
    once from the run's outcome (:func:`fit_pipeline`, :func:`fit_metrics`).

    Without landmarks (or with ``config.landmark_fit`` False) the headline ``model`` is the
    surface-only fit. With landmarks and ``landmark_fit`` it is the same surface fit whose interior
    field carries the landmark correction (stored in ``model.npz``), with landmark errors measured
    on landmarks held out from the correction (``folds``-fold); the surface-driven field alone is
    reported as ``model_surface_only``. ``metrics["protocols"]`` says, per method, what it saw and
    how its landmark error was measured; ``metrics["alignment"][i]["applied"]`` is the rigid
    transform (moving → end-exhale) the fitted target went through, ``metrics["alignment_choice"]``
    the alignment asked, used and why; for a 4-D CT ``metrics["cycle"]`` its phases, Frame of
    Reference and hysteresis (:attr:`lungdeform.evaluate.inputs.ReadInputs.cycle`). ``progress``: called with one
    line of text per step. ``prior``: a population motion prior (:mod:`lungdeform.interior.motion_prior`)
    added to the correspondence field, tapered to zero at the surface (``config.interior == "correspondence"`` only)."""

    run = fit_pipeline(inputs, config, progress=progress, prior=prior)
    metrics = fit_metrics(run)
    write_outputs(Path(out), run, metrics)
    return metrics


def fit_pipeline(inputs: FitInputs, config: FitConfig = FitConfig(), *, progress: Progress | None = None,
                 prior: MotionPrior | None = None) -> FitRun:
    """Steps 1 to 6 of the pipeline (module docstring) on ``inputs``, nothing written: the run's
    outcome (:class:`~lungdeform.evaluate.outcome.FitRun`); ``progress`` and ``prior`` as in :func:`run_fit`.
    The BLAS libraries run on one thread inside it (:func:`lungdeform.blas.limited`): its dense products
    are small (a least-squares Jacobian of about 10 000 × 10, systems of a few thousand rows), and
    threads on a busy machine spin at their barriers (an SVD of the Jacobian: 29 ms CPU with the
    default threads under load, 2 ms with one)."""

    with blas.limited():  # the whole fit's dense steps on one BLAS thread (lungdeform.blas)
        return _fit_pipeline(inputs, config, progress or silent, prior)


def _fit_pipeline(inputs: FitInputs, config: FitConfig, say: Progress, prior: MotionPrior | None) -> FitRun:
    check_prior(config, prior)  # an explicit sliding interior: refused before any reading
    t_start = time.perf_counter()
    read = read_inputs(inputs, config.side_check, say)
    # the landmark folds, split (and folds checked) once, before any fitting
    folds = (landmark_folds(len(read.landmarks[0]), config.folds)
             if read.landmarks is not None and config.landmark_fit else None)
    frame_uid = None if read.cycle is None else read.cycle["frame_of_reference"]
    align, why = choose_alignment(config.align, frame_uid)
    say(f"alignment: {align} ({why})")
    alignment = AlignmentChoice(config.align, align, why)
    config = replace(config, align=align)  # "auto" resolved once, on the inputs read
    placed = place_targets(read, read.paths, inputs.landmarks, config.align, say)
    kind = interior_kind(placed, config)  # resolved once ("auto": on the crop faces), then passed on
    check_prior(config, prior, kind)
    if kind == "sliding" and config.interior == "auto":
        say("interior: the sliding field (cropped scans)")
    fit, grid, placed, warnings = fit_surfaces(placed, read, inputs.side, config, say)
    fit = refine_surface(placed, fit, config, say)
    landmarks = read.landmarks[0] if read.landmarks is not None else None
    surface_field = interior_surface(placed, fit, inputs.side, kind, prior, say, whole=read.surfaces[0])
    held = held_out_landmarks(placed, landmarks, fit, inputs.side, config, folds, say, surface_field)
    fits = Fits(fit, grid, None if held.cv is None else held.cv.final)
    scores = score_targets(placed, landmarks, fits, held, config, folds, say)
    return FitRun(inputs, config, read, placed, fits, held, scores, alignment,
                  tuple(read.warnings + placed.warnings + warnings), time.perf_counter() - t_start,
                  surface_field, prior)


def interior_kind(placed: Placement, config: FitConfig) -> str:
    """``"correspondence"`` or ``"sliding"``: ``config.interior``, with ``"auto"`` resolved on the
    crop faces of ``placed`` (:data:`lungdeform.fit.config.CROP_LIMIT`)."""
    if config.interior != "auto":
        return config.interior
    cropped = max([1.0 - float(np.mean(placed.keep))] + [1.0 - float(np.mean(tg.keep)) for tg in placed.targets])
    return "sliding" if cropped > CROP_LIMIT else "correspondence"


def check_prior(config: FitConfig, prior: MotionPrior | None, kind: str | None = None) -> None:
    """InputError when ``prior`` cannot go with the interior: ``kind`` as resolved by
    :func:`interior_kind` (None: ``config.interior`` as asked, before any input is read)."""
    if prior is None or (config.interior if kind is None else kind) != "sliding":
        return
    if config.interior == "auto":
        raise InputError("prior needs the correspondence interior, and these scans are cropped: the interior "
                         "is the sliding field (interior 'auto')")
    raise InputError(f"prior needs the correspondence interior, not {config.interior!r}")


def interior_surface(placed: Placement, fit, side: str, kind: str, prior: MotionPrior | None,
                     progress: Progress | None = None, *, whole: Surface | None = None):
    """The correspondence field (mm per unit) of the end-exhale surface onto the model's
    largest-volume target (:func:`lungdeform.fit.registration.surface_map_field`), with ``prior``
    on top, tapered to zero at the model mesh (:meth:`~lungdeform.interior.motion_prior.MotionPrior.tapered`); None for the sliding interior (``kind``, :func:`interior_kind`; a prior with it is
    refused by :func:`check_prior`). ``whole``: the end-exhale surface at full resolution, in the
    model's frame (the model mesh is its decimation); default the model mesh."""
    say = progress or silent
    if kind == "sliding":
        return None
    scales = [fit.scale_at(tg.volume_ml) for tg in placed.targets]
    i = int(np.argmax(np.abs(scales)))
    say(f"interior: surface correspondence onto {placed.targets[i].name}")
    # whole closed surfaces, crop faces included: the map is between the two solids (their moments
    # include the cropped region too); leaving a crop face out of one side only pulls the other
    # side's points elsewhere (DIR-Lab COPDgene case 1 left: 9.3 mm with, 6.6 mm without)
    field = surface_map_field(placed.rest if whole is None else whole, placed.targets[i].surface, scales[i])
    if prior is None:
        return field
    # tapered to zero on the model's surface, so the lung keeps the field's surface and volume change
    return field.with_prior(prior.tapered(placed.rest, side, 1.0 / scales[i]))


def fit_surfaces(placed: Placement, read: ReadInputs, side: str, config: FitConfig,
                 progress: Progress | None = None) -> tuple[FitOutcome, FitOutcome | None, Placement, list[str]]:
    """The surface fits of the model mesh to the placed targets: ``(fit, grid, placement, warnings)``;
    ``fit`` is the headline fit (``config.mode``), ``grid`` the paper's grid search (with
    ``config.grid``, else None); with ``align="joint"`` the placement returned has every target
    moved by its fitted translation. A warning when c1…c6 end on the bound of the search."""

    say = progress or silent
    say(f"fitting ({len(placed.targets)} target(s), model mesh {placed.rest.n_vertices} vertices)")
    settings = FitSettings(mode=config.mode, fit_stiffness=config.stiffness, max_evaluations=config.max_evaluations,
                           translate=config.align == "joint", direction_degree=config.direction_degree)
    fit = fit_lung(placed.rest, side, placed.targets, settings, keep=placed.keep, progress=say)
    if config.align == "joint":  # move every target (and its landmarks, crop faces) by its fitted translation
        placed = shift_targets(placed, read, fit.translations, say)
    warnings = []
    at_bound = [f"c{i + 1}" for i in range(6) if np.isclose(fit.constants[i], DIRECTION_LO[i], rtol=0, atol=1e-6)
                or np.isclose(fit.constants[i], DIRECTION_HI[i], rtol=0, atol=1e-6)]
    if at_bound:
        values = ", ".join(f"{n} = {fit.constants[int(n[1:]) - 1]:g}" for n in at_bound)
        warnings.append(f"{', '.join(at_bound)} ended on the bound of the search ({values}): "
                        "the surfaces may not be one lung at two volumes, or the alignment is off")
    grid = (fit_lung(placed.rest, side, placed.targets, FitSettings(mode="grid", grid_span=0.1), keep=placed.keep,
                     progress=say) if config.grid else None)
    return fit, grid, placed, warnings


def refine_surface(placed: Placement, fit, config: FitConfig, progress: Progress | None = None):
    """``fit`` with its displacement brought onto the placed targets by the surface refinement
    (:func:`lungdeform.fit.refinement.refine_displacement`, finest width ``config.refine_mm``);
    ``fit`` unchanged when ``config.refine_mm`` is 0."""
    if not config.refine_mm:
        return fit
    say = progress or silent
    scales = [fit.scale_at(tg.volume_ml) for tg in placed.targets]
    ref = refine_displacement(placed.rest.vertices, fit.displacement, [tg.surface for tg in placed.targets], scales,
                              placed.keep, finest_mm=config.refine_mm)
    say(f"surface refinement (down to {config.refine_mm:g} mm): mean change {ref.mean_change_mm:.2f} mm, "
        f"largest {ref.max_change_mm:.1f} mm")
    return replace(fit, displacement=ref.displacement, refinement=ref)


def fit_metrics(run: FitRun) -> dict:
    """The metrics dictionary (``metrics.json``), built once from the run's outcome: inputs, volumes,
    warnings, alignment, every method's metrics per target (the last, largest-volume target's also
    at the top level), the protocols, the fits, the landmark cross-validation, the bounding boxes,
    the alignment choice, the 4-D CT's cycle, the interior and the timings."""

    read, placed, fits, held, config = run.read, run.placed, run.fits, run.held, run.config
    fit, per_target, skipped = fits.optimizer, run.scores.per_target, run.scores.skipped
    return {"inputs": list(read.paths), "side": run.inputs.side, "volumes_ml": placed.volumes_ml,
            "volumes_given_ml": read.given_ml, "warnings": list(run.warnings), "notes": read.notes,
            "model_mesh_vertices": placed.rest.n_vertices, "alignment": placed.alignments,
            "targets": per_target,
            **({"skipped": skipped} if skipped else {}),
            **per_target[placed.targets[-1].name],  # the headline: the last, largest-volume target
            "protocols": protocols(fit, held, config, fits.grid is not None),
            "headline_fit": "optimizer",  # the key in metrics["fit"] of the saved constants
            "interior_correction": held.interior is not None,
            "fit": {name: ({**r.as_dict(), "uniform_objective_rms_mm": r.uniform_objective_mm} if name == "optimizer"
                           else r.as_dict()) for name, r in fits.named().items()},
            **({"landmark_cv": landmark_cv_metrics(run)} if held.interior is not None else {}),
            "bounding_box": bounding_boxes(placed.rest, fit, read.surfaces, placed.volumes_ml),
            "alignment_choice": run.alignment.as_dict(),
            **({"cycle": read.cycle} if read.cycle is not None else {}),
            "interior": {"surface_part": "sliding" if run.surface_field is None else "correspondence",
                         "asked": config.interior, "prior": None if run.prior is None else run.prior.as_dict()},
            "seconds": run.seconds,
            # the model's own fit, the baselines and landmark-informed references (timed apart) left out
            "baseline_seconds": run.scores.baseline_seconds,
            "baseline_cpu_seconds": run.scores.baseline_cpu_seconds,
            "model_seconds": run.model_seconds}


def landmark_cv_metrics(run: FitRun) -> dict:
    """``metrics["landmark_cv"]`` (with the interior landmark correction): the folds, landmark count,
    seed, landmark weight and the correction's smoothing; with the landmark-informed fits, the
    c1…c9 of each fold and their spread."""
    held, config = run.held, run.config
    cv = {} if held.cv is None else {"fold_constants": held.cv.fold_constants.tolist(),
                                     "fold_constants_spread": held.cv.fold_constants.std(axis=0).tolist()}
    return {"folds": config.folds, "landmarks": int(len(run.read.landmarks[0])), "seed": 0,
            "landmark_weight": config.landmark_weight, "interior_smoothing_mm": held.interior["smoothing"], **cv}


def write_outputs(out: Path, run: FitRun, metrics: dict) -> None:
    """Write ``model.npz`` (the headline fit, with the interior correction when there is one, at the
    end-exhale landmarks, and the surface-map field when there is one), ``metrics.json`` (``metrics``,
    :func:`fit_metrics` of ``run``) and ``report.html`` in ``out``."""

    inputs, placed, fits, held, landmarks = run.inputs, run.placed, run.fits, run.held, run.landmarks
    out.mkdir(parents=True, exist_ok=True)
    fit, keep = fits.optimizer, placed.keep
    # the crop faces (image boundary, motion never fitted) do not drive the interior field
    lung = replace(to_lung_model(placed.rest, inputs.side, fit), interior_vertices=None if keep.all() else keep.copy(),
                   interior_map=run.surface_field)
    if held.interior is not None:
        lung = replace(lung, landmarks=landmarks, landmark_correction=held.interior["correction"],
                       landmark_smoothing=held.interior["smoothing"])
    model = Model({inputs.side: lung}, provenance(run.config.command, inputs=metrics["inputs"],
                                                  volumes_ml=placed.volumes_ml, fit=fit.as_dict(), scans=run.read.scans,
                                                  alignment=placed.alignments, fit_kind=metrics["headline_fit"],
                                                  interior_correction=held.interior is not None))
    save_model(out / "model.npz", model)
    if landmarks is not None and held.surface_unit is not None:
        write_landmark_motion(out / "landmarks.npz", placed, fit, landmarks, held.surface_unit)
    write_json(out / "metrics.json", metrics, strict=True, default=_json)
    write_report(out / "report.html", rest=placed.rest, targets=placed.targets, fits=fits.named(),
                 predictions=run.scores.predictions, metrics=metrics, headline=metrics["headline_fit"], keep=keep)


def write_landmark_motion(path: Path, placed: Placement, fit, landmarks, surface_unit) -> Path:
    """``landmarks.npz``: the end-exhale ``landmarks (m, 3)`` mm, per target the ``observed (t, m, 3)``
    mm positions (aligned to the end-exhale frame) and the correspondence field's ``surface_only
    (t, m, 3)`` mm, ``volumes_ml (t,)``, and the lung's solid ``centroid (3,)`` and ``scale (3,)`` mm
    (:func:`lungdeform.interior.motion_prior.lung_normaliser`): what a motion prior learns from."""
    scales = [fit.scale_at(tg.volume_ml) for tg in placed.targets]
    centroid, scale = lung_normaliser(placed.rest)
    arrays = {"landmarks": np.asarray(landmarks, float), "observed": np.stack([np.asarray(a, float) for a in placed.landmarks]),
              "surface_only": np.stack([landmarks + s * surface_unit for s in scales]),
              "volumes_ml": np.array([tg.volume_ml for tg in placed.targets]), "centroid": centroid, "scale": scale}
    write_npz(path, arrays)
    return path


def _json(o):
    try:
        return jsonable(o)
    except TypeError:
        return str(o)
