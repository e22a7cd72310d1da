"""Every method's prediction of each target and its metrics (step 6 of :func:`lungdeform.evaluate.pipeline.run_fit`).

The methods: the fitted model (with landmarks and ``landmark_fit``, the headline ``model`` is the
surface fit with the interior landmark correction and ``model_surface_only`` the surface-driven
field alone), its variants (paper directions, uniform stiffness, the paper's grid search, the
landmark-informed fits) and the baselines and landmark-informed references
(:mod:`lungdeform.evaluate.baselines`), all measured with the same metrics
(:func:`lungdeform.evaluate.baselines.measure`), crop faces left out. :func:`protocols` says, per method,
what it saw and how its landmark error was measured.
"""

from __future__ import annotations

import time

import numpy as np

from lungdeform.fit.config import FitConfig
from lungdeform.fit.fitting import FitOutcome
from lungdeform.fit.objective import Target
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.progress import Progress, silent

from . import baselines as B
from .heldout import HeldOut
from .outcome import Fits, Scores
from .placement import Placement

#: The baselines from the surfaces only, in the order they are reported.
SURFACE_BASELINES = ("no_motion", "affine", "apex_scaling", "cpd")


def protocols(fit: FitOutcome, held: HeldOut, config: FitConfig, grid: bool) -> dict[str, str]:
    """Per method reported, what it saw and how its landmark error was measured (``metrics["protocols"]``);
    ``fit`` is the surface fit, ``held`` the landmark step, ``grid``: a grid fit is reported."""

    use_lm, folds = held.interior is not None, config.folds
    corrected = fit.paper_displacement is not None
    fitted = ", ".join(["c1…c9"] + (["stiffness field"] if fit.stiffness_fitted else [])
                     + ([f"direction correction of degree {config.direction_degree}"] if corrected else []))
    kind = fitted + (f", surface refinement down to {config.refine_mm:g} mm" if fit.refinement is not None else "")
    if held.surface_unit is not None:
        out = {surface_name(held): f"surface fit ({kind}; no landmark used); landmarks moved by the correspondence "
                                   "field (lungdeform.fit.registration: the smooth map of the end-exhale surface "
                                   "onto the largest-volume target, with any motion prior folded in)",
               "model_surface_sliding": f"surface fit ({kind}; no landmark used); landmarks moved by the sliding "
                                        "interpolation of its surface displacement (the other interior field)"}
    else:
        out = {surface_name(held): f"surface fit ({kind}; no landmark used); landmarks moved by the sliding "
                                   "interpolation of its surface displacement"}
    if use_lm:
        out["model"] = (f"surface fit ({kind}; no landmark used) with the interior landmark correction "
                        f"(lungdeform.interior): landmarks moved by the surface-driven field "
                        f"plus the sliding correction through the training landmarks' residual motion (it keeps the "
                        f"surface's normal motion; smoothing chosen by inner cross-validation); "
                        f"held-out landmark errors ({folds}-fold)")
    if held.cv is not None:
        out["model_landmark_fit"] = (f"landmark-informed fit: c1…c9 (paper directions) on the surfaces and the "
                                     f"training landmarks, landmarks moved by the surface-driven field only; "
                                     f"held-out landmark errors ({folds}-fold), surface from the fit on all "
                                     f"landmarks")
        if held.cv_stiffness is not None:
            out["model_landmarks_stiffness"] = out["model_landmark_fit"] + ", with a fitted stiffness field"
    if fit.refinement is not None:
        out["model_unrefined"] = ("the same fit without the surface refinement (lungdeform.fit.refinement): "
                                  f"the fitted k·F·d ({fitted}); landmarks moved by the sliding interpolation of "
                                  "its surface")
    if corrected:
        out["model_paper_directions"] = (f"the same fit with the paper's directions (15)–(17), no direction "
                                         f"correction{' (stiffness field kept)' if fit.stiffness_fitted else ''}; "
                                         f"landmarks moved by the sliding interpolation of its surface")
    if fit.uniform_displacement is not None:
        out["model_uniform_stiffness"] = ("the paper's model: c1…c9 fitted to the surfaces, uniform stiffness, "
                                          "the paper's directions; landmarks moved by the sliding "
                                          "interpolation of its surface")
    if grid:
        out["model_grid"] = ("the paper's grid search of c1…c6 (uniform stiffness, paper directions); "
                             "landmarks moved by the sliding interpolation of its surface")
    if config.baselines:
        for name in SURFACE_BASELINES:
            out[name] = ("baseline from the surfaces only, aligned by its own translation (ICP from the "
                         "centroids; the affine fit's own); landmarks moved by the same sliding interpolation")
        if use_lm:
            out["affine_landmarks"] = ("reference: affine fitted on the surfaces and the training landmarks "
                                       "(same weighting and folds as the model); held-out landmark errors")
            out["landmarks_tps"] = ("reference without surfaces: thin-plate spline through the training "
                                    "landmarks, its smoothing chosen by inner cross-validation on them; held-out "
                                    "landmark errors; its surface is that spline applied to the end-exhale surface")
    return out


def surface_name(held: HeldOut) -> str:
    """The name of the surface-only fit's row: ``model`` unless the interior correction is the headline."""
    return "model_surface_only" if held.interior is not None else "model"


def model_methods(ti: int, target: Target, fits: Fits, held: HeldOut, rest, landmarks=None) -> dict:
    """The fitted models' predictions of target ``ti``: name → ``(predicted vertices (n, 3) mm,
    landmark predictions (m, 3) mm or None: moved by the sliding operator)``; ``fits``: the run's
    fits; ``landmarks : (m, 3)`` mm the end-exhale ones."""

    fit = fits.optimizer
    s = fit.scale_at(target.volume_ml)
    methods = {}
    if held.interior is not None:
        methods["model"] = (fit.positions_at(rest, target.volume_ml), held.interior["held_out"][ti])
    if held.cv is not None:
        methods["model_landmark_fit"] = (held.cv.final.positions_at(rest, target.volume_ml), held.cv.predicted[ti])
        if held.cv_stiffness is not None:
            methods["model_landmarks_stiffness"] = (held.cv_stiffness.final.positions_at(rest, target.volume_ml),
                                                    held.cv_stiffness.predicted[ti])
    surface_only = None
    if held.surface_unit is not None:  # the correspondence field moves the landmarks; the sliding one for comparison
        surface_only = landmarks + s * held.surface_unit
        methods["model_surface_sliding"] = (fit.positions_at(rest, target.volume_ml), None)
    methods[surface_name(held)] = (fit.positions_at(rest, target.volume_ml), surface_only)
    if fit.refinement is not None:
        methods["model_unrefined"] = (rest.vertices + s * fit.refinement.before, None)
    if fit.paper_displacement is not None:
        methods["model_paper_directions"] = (rest.vertices + s * fit.paper_displacement, None)
    if fit.uniform_displacement is not None:
        methods["model_uniform_stiffness"] = (rest.vertices + s * fit.uniform_displacement, None)
    if fits.grid is not None:
        methods["model_grid"] = (fits.grid.positions_at(rest, target.volume_ml), None)
    return methods


def baseline_methods(target: Target, placed: Placement, landmarks, landmarks_target, held: HeldOut, folds,
                     landmark_weight: float, skipped: dict) -> dict:
    """The baselines' predictions of ``target`` (and with the interior correction, the
    landmark-informed references on the same ``folds``), as in :func:`model_methods`. Every baseline
    runs (their packages are required), so nothing is added to ``skipped`` here."""

    rest, kw = placed.rest, {"keep": placed.keep, "keep_target": target.keep}
    # each baseline aligns itself (its own translation, from the centroids), not by the model's alignment
    shift = B.best_translation(rest, target.surface, **kw)
    methods = {"no_motion": (B.no_motion(rest) + shift, None),
               "affine": (B.affine_fit(rest, target.surface, **kw)[0], None),
               "apex_scaling": (B.self_aligned(rest, B.apex_scaling(rest, target.volume_ml), target.surface, **kw),
                                None),
               "cpd": (B.cpd_deformable(rest.deformed(np.broadcast_to(shift, rest.vertices.shape)), target.surface,
                                        **kw), None)}
    if held.interior is not None:
        methods["affine_landmarks"] = B.affine_landmarks_cv(rest, target.surface,
                                                            B.LandmarkPairs(landmarks, landmarks_target), folds,
                                                            **kw, landmark_weight=landmark_weight)
        methods["landmarks_tps"] = B.landmark_tps_cv(rest, landmarks, landmarks_target, folds)
    return methods


def score_targets(placed: Placement, landmarks, fits: Fits, held: HeldOut, config: FitConfig, folds,
                  progress: Progress | None = None) -> Scores:
    """Every method measured on every target (:class:`~lungdeform.evaluate.outcome.Scores`: metrics
    per target name → method name → metrics dict, predictions (target name, method name) →
    (vertices, per-vertex error, landmark errors), skipped baselines name → reason, seconds spent
    computing and measuring the baselines and references, wall and CPU). ``landmarks : (m, 3)`` mm:
    the end-exhale ones, or None."""

    say = progress or silent
    per_target, predictions, skipped, baseline_seconds, baseline_cpu = {}, {}, {}, 0.0, 0.0
    for ti, tg in enumerate(placed.targets):
        td = SurfaceDistance(tg.surface.vertices, tg.surface.faces)
        lmt = placed.landmarks[ti] if landmarks is not None else None
        per = {}

        def record(methods: dict) -> None:
            for name, (x, held_out) in methods.items():
                pairs = None if landmarks is None else B.LandmarkPairs(landmarks, lmt, held.matrix, held_out)
                m, per_vertex, lm_err = B.measure(placed.rest, x, tg.surface, keep=placed.keep, keep_target=tg.keep,
                                                  landmarks=pairs, target_distance=td)
                per[name] = m.as_dict()
                predictions[(tg.name, name)] = (x, per_vertex, lm_err)

        record(model_methods(ti, tg, fits, held, placed.rest, landmarks))
        if config.baselines:
            say("baselines")
            t0, c0 = time.perf_counter(), time.process_time()  # the baselines' time: computing and measuring them
            record(baseline_methods(tg, placed, landmarks, lmt, held, folds, config.landmark_weight, skipped))
            baseline_seconds += time.perf_counter() - t0
            baseline_cpu += time.process_time() - c0
        per_target[tg.name] = per
    return Scores(per_target, predictions, skipped, baseline_seconds, baseline_cpu)


def bounding_boxes(rest, fit, surfaces, vols):
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
