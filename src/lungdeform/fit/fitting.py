"""Fitting the model's constants to surfaces at two or more lung volumes (paper Sec. IV-B; docs/FITTING.md).

:func:`fit_lung` searches the constants c1…c9 of one lung that minimise the fit objective of
:class:`lungdeform.fit.objective.LungFitter`: the area-weighted RMS forward symmetric surface distance
between the predicted surface ``p + s·u`` and the targets in ``fit_on`` (the model's form, the
evaluation of one candidate and the landmark term are documented in :mod:`lungdeform.fit.objective`).
It returns a :class:`FitOutcome` with an explicit failure state; :func:`to_lung_model` turns it into
a model-file ready :class:`lungdeform.model.lung.LungModel`.

Search modes (:mod:`lungdeform.fit.search`): ``"least_squares"`` (the default ``"optimizer"``; c3 held
as the gauge, c7…c9 refined against the surface, optionally a translation per target), ``"powell"``
and ``"grid"`` (the paper's grid at step 0.01 as cyclic coordinate search).

Optional beyond the paper (``fit_stiffness=True``): a heterogeneous per-vertex stiffness field, an
inverse estimate of regional alveolar expandability (paper Sec. VI; :mod:`lungdeform.fit.expandability`),
kept only when it lowers the fit objective. The model keeps its run-time form. Also optional
(``direction_degree > 0``): a smooth polynomial correction of the directions fitted to the same
surfaces (:mod:`lungdeform.fit.direction_correction`), kept only when it lowers the objective.

Landmark-informed fitting (optional; paper Sec. IV-B fitted its constants on corresponding points
of 4-D CT): the objective gains a landmark term (:mod:`lungdeform.fit.objective`). Landmark errors of
such a fit are only meaningful on landmarks held out from it:
:func:`lungdeform.evaluate.crossval.cross_validate_landmarks` runs the k-fold protocol.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from lungdeform.constants import gravity_vector, table_constants
from lungdeform.errors import ConvergenceError, InputError
from lungdeform.geometry.frame import lung_frame
from lungdeform.geometry.mesh import Surface
from lungdeform.model.force import field_basis
from lungdeform.model.lung import LungModel
from lungdeform.model.response import solve_response
from lungdeform.progress import Progress, silent

from .direction_correction import DirectionCorrection, fit_direction_correction
from .expandability import fit_stiffness_if_better
from .objective import LandmarkTerm, LungFitter, ObjectiveSettings, Target
from .rays import RayHits
from .refinement import Refinement
from .search import grid_search, least_squares_search, powell_search

#: Bounds of c1…c6 searched (scales c1, c3, c5; exponents c2, c4, c6).
DIRECTION_BOUNDS = ((0.01, 3.0), (0.05, 4.0), (0.01, 3.0), (0.05, 4.0), (0.01, 3.0), (0.05, 4.0))
#: The same bounds as two (6,) arrays, lower and upper (read-only).
DIRECTION_LO = np.array([b[0] for b in DIRECTION_BOUNDS])
DIRECTION_HI = np.array([b[1] for b in DIRECTION_BOUNDS])
DIRECTION_LO.flags.writeable = False
DIRECTION_HI.flags.writeable = False

#: Objective value given to the optimiser for a candidate that gives no usable model (mm).
UNUSABLE_MM = 1.0e3

#: Search modes of :func:`fit_lung`; ``"optimizer"`` is :data:`DEFAULT_OPTIMIZER`.
MODES = ("optimizer", "least_squares", "powell", "grid")
DEFAULT_OPTIMIZER = "least_squares"


@dataclass(frozen=True, eq=False)
class FitOutcome:
    """Outcome of :func:`fit_lung`.

    Attributes
    ----------
    constants : (9,) float
        Fitted c1…c9 (c7…c9 scaled so that the largest |c| among them is 1).
    stiffness : (n,) float
        Young's modulus per vertex used (uniform unless a stiffness field was fitted).
    displacement : (n, 3) float
        ``u``, mm per ``unit_ml``, LPS: the model's displacement for one unit of volume.
    unit_ml : float
        ΔV of one unit (mL).
    volume_ee_ml : float
        End-exhale volume (mL).
    calibration_ml : float
        Volume change at which ``u`` is exact (mL).
    directions : (n, 3) float
        Fitted unit directions.
    force : (n,) float
        Elastostatic force ``F`` from the fitted c7…c9.
    inverse_force : (n,) float
        Applied force recovered from the observed magnitudes (step 3 of :mod:`lungdeform.fit.objective`),
        normalised by its max.
    force_constants_inverse : (3,) float
        c7…c9 fitted on ``inverse_force`` directly (the paper's reading), same normalisation.
    rays : RayHits
        Correspondences for the fitted directions.
    residuals : dict[str, (k,) float]
        Per target name: forward symmetric distances (mm) of the fit samples.
    objective_mm : float
        Final objective (area-weighted RMS symmetric distance over ``fit_on``), mm.
    failure : str or None
        The failure state: None when the search converged; otherwise why it did not, in one line
        (its evaluation budget spent, the grid still improving after its last cycle, Powell's own
        reason). A failed search still returns the best point it evaluated: usable, not a minimum.
    convergence : str
        With ``failure`` None, how the search converged in its own words (``"converged"``,
        ``"least squares converged (…)"``, ``"grid converged after 4 cycles"``); ``""`` otherwise.
    success : bool
        Property: ``failure is None`` (``metrics.json``'s ``success``).
    message : str
        Property: ``failure``, or ``convergence`` when it converged (``metrics.json``'s ``message``).
    mode : str
    evaluations : int
    seconds : float
    history : (h,) float
        Best objective after each evaluation (mm).
    surface_rms_mm, landmark_rms_mm : float
        The two parts of the objective (mm): area-weighted RMS symmetric surface distance, and RMS
        error of the landmarks used in the fit (NaN without landmarks; an in-sample figure).
    landmarks_used : int
        Number of landmark pairs in the objective (0: surfaces only).
    refinement : Refinement or None
        With the surface refinement (:mod:`lungdeform.fit.refinement`): what it did;
        :attr:`displacement` is then the refined one and ``refinement.before`` the fitted ``k·F·d``.
    translations : (k, 3) float or None
        With ``translate=True``: the translation (mm) fitted jointly for each target; the model was
        fitted to ``target + translations[i]`` (zeros for targets outside ``fit_on``).
    uniform_displacement : (n, 3) float or None
        With a fitted stiffness field: ``u`` with uniform stiffness and the paper's directions.
    direction_correction : DirectionCorrection or None
        With ``direction_degree > 0``: the fitted correction of the directions
        (:mod:`lungdeform.fit.direction_correction`); :attr:`directions` and :attr:`displacement` include
        it when it was accepted.
    paper_displacement : (n, 3) float or None
        With an accepted correction: ``u`` with the paper's directions (same final stiffness and
        c7…c9).
    paper_objective_mm : float
        The objective with the paper's directions (final stiffness), mm.
    """

    constants: np.ndarray
    stiffness: np.ndarray
    displacement: np.ndarray
    unit_ml: float
    volume_ee_ml: float
    calibration_ml: float
    directions: np.ndarray
    force: np.ndarray
    inverse_force: np.ndarray
    force_constants_inverse: np.ndarray
    rays: RayHits
    residuals: dict
    objective_mm: float
    failure: str | None
    convergence: str
    mode: str
    evaluations: int
    seconds: float
    history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stiffness_fitted: bool = False
    uniform_displacement: np.ndarray | None = None
    uniform_objective_mm: float = float("nan")
    direction_correction: DirectionCorrection | None = None
    paper_displacement: np.ndarray | None = None
    paper_objective_mm: float = float("nan")
    surface_rms_mm: float = float("nan")
    landmark_rms_mm: float = float("nan")
    landmarks_used: int = 0
    translations: np.ndarray | None = None
    refinement: Refinement | None = None

    @property
    def success(self) -> bool:
        """Whether the search converged (no :attr:`failure`)."""
        return self.failure is None

    @property
    def message(self) -> str:
        """How the search stopped: :attr:`failure`, or :attr:`convergence` when it converged."""
        return self.convergence if self.failure is None else self.failure

    def scale_at(self, volume_ml: float) -> float:
        """The model's scale ``s = (V − V_EE) / unit_ml`` (units) at lung volume ``volume_ml`` (mL)."""
        return (float(volume_ml) - self.volume_ee_ml) / self.unit_ml

    def positions_at(self, surface: Surface, volume_ml: float) -> np.ndarray:
        """Predicted vertices ``p + s·u`` (mm) at lung volume ``volume_ml`` (linear in volume, :meth:`scale_at`)."""
        return surface.vertices + self.scale_at(volume_ml) * self.displacement

    def as_dict(self) -> dict:
        return {"constants": [float(c) for c in self.constants], "objective_rms_mm": self.objective_mm,
                "success": self.success, "message": self.message, "mode": self.mode,
                "evaluations": self.evaluations, "seconds": self.seconds,
                "force_constants_inverse": [float(c) for c in self.force_constants_inverse],
                "rays": self.rays.summary(), "stiffness_fitted": self.stiffness_fitted,
                "stiffness_range": [float(self.stiffness.min()), float(self.stiffness.max())],
                "surface_rms_mm": self.surface_rms_mm, "landmarks_used": self.landmarks_used,
                "landmark_rms_in_fit_mm": self.landmark_rms_mm,
                "translations_mm": None if self.translations is None else np.asarray(self.translations).tolist(),
                "direction_correction": None if self.direction_correction is None else self.direction_correction.as_dict(),
                "refinement": None if self.refinement is None else self.refinement.as_dict()}


@dataclass(frozen=True, eq=False)
class FitSettings:
    """How :func:`fit_lung` searches c1…c9 (the module docstring gives the steps).

    Attributes
    ----------
    mode : str
        ``"optimizer"`` (= :data:`DEFAULT_OPTIMIZER`), ``"least_squares"``, ``"powell"`` or ``"grid"``.
    initial : (6,) or (9,) float, optional
        c1…c6 (or c1…c9) to start from; default Table I (the least-squares mode keeps the start's
        c3 as the gauge and takes c7…c9 from ``initial`` when given, else from the rays at the start).
    fit_stiffness : bool
        Also fit a stiffness field (:mod:`lungdeform.fit.expandability`), kept only if it lowers the objective.
    max_evaluations : int
        Budget of forward model evaluations. The least-squares mode takes at most
        ``max_evaluations // (free constants + 1)`` iterations, the budget of its finite-difference
        Jacobians until 0.8; its Jacobian now costs one evaluation
        (:func:`lungdeform.fit.search.least_squares_search`), so it evaluates far fewer.
    grid_span : float
        Half-width around the start that the grid scans per constant (step 0.01).
    translate : bool
        Least squares only: fit a translation of each target in ``fit_on`` jointly with the
        constants (:attr:`FitOutcome.translations`).
    direction_degree : int
        > 0: after the constants (and stiffness), fit a smooth correction of that polynomial degree
        to the directions (:mod:`lungdeform.fit.direction_correction`), kept only if it lowers the objective.
    objective : ObjectiveSettings
        How each candidate is measured (:class:`lungdeform.fit.objective.LungFitter`).
    """

    mode: str = "optimizer"
    initial: np.ndarray | None = None
    fit_stiffness: bool = False
    max_evaluations: int = 600
    grid_span: float = 0.3
    translate: bool = False
    direction_degree: int = 0
    objective: ObjectiveSettings = ObjectiveSettings()

    @property
    def method(self) -> str:
        """The search :data:`MODES` name that runs: ``"optimizer"`` is :data:`DEFAULT_OPTIMIZER`."""
        return DEFAULT_OPTIMIZER if self.mode == "optimizer" else self.mode


def fit_lung(surface: Surface, side: str, targets: Sequence[Target], settings: FitSettings = FitSettings(), *,
             landmarks: LandmarkTerm | None = None, fit_on=None, keep=None,
             progress: Progress | None = None) -> FitOutcome:
    """Fit c1…c9 (and optionally a stiffness field) of one lung; see the module docstring.

    ``settings``: the search (:class:`FitSettings`). ``landmarks``: the optional landmark term of
    the objective (:class:`~lungdeform.fit.objective.LandmarkTerm`); the landmark error of the result
    is in-sample, use :func:`lungdeform.evaluate.crossval.cross_validate_landmarks` for a held-out
    figure. ``fit_on`` and ``keep``: the targets in the objective and the model vertices measured
    (:class:`~lungdeform.fit.objective.LungFitter`).
    Raises :class:`InputError` for bad input; a fit whose objective is not finite raises
    :class:`ConvergenceError`; a search that stops on its evaluation budget returns its best point
    with the reason in :attr:`FitOutcome.failure` (``success`` False).
    """
    if settings.mode not in MODES:
        raise InputError(f"mode must be one of {', '.join(MODES)}, got {settings.mode!r}")
    if settings.translate and settings.method != "least_squares":
        raise InputError(f"translate=True needs the least-squares mode, not {settings.method!r}")
    say = progress or silent
    t0 = time.perf_counter()
    fitter = LungFitter(surface, side, targets, fit_on=fit_on, keep=keep, settings=settings.objective,
                        landmarks=landmarks)
    start_c = table_constants(side) if settings.initial is None else np.asarray(settings.initial, float)
    if start_c.shape not in ((6,), (9,)) or not np.all(np.isfinite(start_c)):
        raise InputError(f"initial must be 6 or 9 finite constants (c1…c6 or c1…c9), got shape {start_c.shape}")
    history: list[float] = []
    found = _search(fitter, side, settings, start_c, history, say)
    return _finish(fitter, side, found, settings, history, t0, say)


@dataclass(frozen=True, eq=False)
class _Found:
    """The best point of a search (:func:`_search`): c1…c6 ``x`` (clipped to the bounds), its
    objective (mm), the least-squares mode's c7…c9 ``force`` and per-target ``shifts`` (else
    None), and its stop: ``failure`` (None: it converged, then ``convergence`` says how), as in
    :class:`FitOutcome`."""

    x: np.ndarray
    objective: float
    force: np.ndarray | None
    shifts: np.ndarray | None
    failure: str | None
    convergence: str


def _search(fitter: LungFitter, side: str, settings: FitSettings, start_c: np.ndarray, history: list, say) -> _Found:
    """Search c1…c6 from ``start_c`` with ``method`` (:mod:`lungdeform.fit.search`); ``history``
    gets the best objective after each evaluation. Never returns a point worse than one evaluated."""

    method, max_evaluations = settings.method, settings.max_evaluations
    x0 = start_c[:6]
    lo, hi = DIRECTION_LO, DIRECTION_HI
    seen = {"x": None, "f": np.inf}  # the best point evaluated (Powell may return a worse last point)
    force, shifts = None, None

    def fun(x):
        xc = np.clip(x, lo, hi)
        v = fitter.evaluate(xc)
        history.append(min(v, history[-1]) if history else v)
        if v < seen["f"]:
            seen["x"], seen["f"] = xc.copy(), v
        # an unusable candidate (no growth, no hits) is a large finite value, not inf: Powell's
        # Brent line search interpolates through the values and an inf derails it
        return v if np.isfinite(v) else UNUSABLE_MM

    start = fun(x0)
    if not np.isfinite(start):
        raise ConvergenceError(f"the starting constants {x0} give no usable model (no ray hits or no volume growth)")
    say(f"{side}: start RMS {start:.3f} mm ({method})")
    success, message = True, "converged"
    if method == "least_squares":
        force0 = start_c[6:] if len(start_c) == 9 else None
        x, force, shifts, best, success, message = least_squares_search(
            fitter, np.clip(x0, lo, hi), force0, lo=lo, hi=hi, translate=settings.translate,
            max_evaluations=max_evaluations, history=history)
        say(f"{side}: least squares RMS {best:.3f} mm after {fitter.evaluations} evaluations")
    elif method == "powell":
        x, best, success, message = powell_search(fun, x0, lo, hi, max_evaluations)
        say(f"{side}: optimiser RMS {best:.3f} mm after {fitter.evaluations} evaluations")
    else:
        x, best, cycles, converged = grid_search(fun, x0, DIRECTION_BOUNDS, 0.01, span=[settings.grid_span] * 6,
                                                 progress=say)
        if converged:
            message = f"grid converged after {cycles} cycles"
        else:
            success, message = False, f"grid stopped after {cycles} cycles, still improving (not converged)"
    best_x = np.clip(x, lo, hi)
    if force is None and seen["f"] < best:  # never return a point worse than one already evaluated
        best_x, best = seen["x"], seen["f"]
    return _Found(best_x, best, force, shifts, None if success else message, message if success else "")


def _finish(fitter: LungFitter, side: str, found: _Found, settings: FitSettings, history: list, t0: float,
            say) -> FitOutcome:
    """The :class:`FitOutcome` of the search's best point: the stiffness field (optional), the
    direction correction (optional) and the inverse force of the final evaluation."""

    best_x, best, force, shifts = found.x, found.objective, found.force, found.shifts
    log_e = None
    uniform_u, uniform_obj = None, float(best)
    if settings.fit_stiffness:
        _, uparts = fitter.evaluate(best_x, full=True, force=force, shifts=shifts)
        uniform_u = uparts["u"] if uparts is not None else None
        log_e, best = fit_stiffness_if_better(fitter, best_x, best, say, force=force, shifts=shifts)
    obj, parts = fitter.evaluate(best_x, full=True, force=force, shifts=shifts)
    if parts is None or not np.isfinite(obj):
        raise ConvergenceError(f"{side}: the fitted constants give no usable model")
    correction, paper_u, paper_obj = None, None, float(obj)
    if settings.direction_degree:
        correction, log_e = _correct_directions(fitter, parts, best_x, shifts, settings.direction_degree, log_e, say)
        if correction.accepted:
            c_force = parts["constants"][6:]
            # the paper's directions with the final stiffness (the alternation may have refitted it)
            paper_obj, paper_parts = fitter.evaluate(best_x, full=True, force=c_force, shifts=shifts)
            paper_u = None if paper_parts is None else paper_parts["u"]
            obj, parts = fitter.evaluate(best_x, full=True, force=c_force, shifts=shifts,
                                         directions=correction.directions)
    w = np.where(parts["hits"].valid & fitter.keep, fitter.areas, 0.0)
    f_inv, c_inv = fitter.inverse_parts(np.nan_to_num(parts["hits"].distance), w)
    return FitOutcome(
        constants=parts["constants"], stiffness=fitter.stiffness, displacement=parts["u"],
        unit_ml=fitter.delta_ml, volume_ee_ml=fitter.v_ee, calibration_ml=fitter.delta_ml,
        directions=parts["directions"], force=parts["force"], inverse_force=f_inv,
        force_constants_inverse=c_inv, rays=parts["hits"], residuals=parts["residuals"],
        objective_mm=obj, failure=found.failure, convergence=found.convergence, mode=settings.method,
        evaluations=fitter.evaluations, seconds=time.perf_counter() - t0, history=np.asarray(history),
        stiffness_fitted=log_e is not None, uniform_displacement=uniform_u,
        uniform_objective_mm=uniform_obj, surface_rms_mm=parts["surface_rms"],
        landmark_rms_mm=parts["landmark_rms"], landmarks_used=len(fitter.lm_rest) if fitter.lm_targets else 0,
        translations=shifts, direction_correction=correction, paper_displacement=paper_u,
        paper_objective_mm=paper_obj,
    )


def _correct_directions(fitter: LungFitter, parts: dict, c_dir, shifts, degree: int, log_e, say,
                        rounds: int = 3):
    """The direction correction of :func:`fit_lung`; with a fitted stiffness field, alternated with a
    refit of that field along the corrected directions (``rounds`` corrections at most, each kept
    only if it lowers the objective). Returns ``(DirectionCorrection relative to the paper's
    directions, log E or None)``; the kept stiffness stays in ``fitter``."""
    d0, c_force = parts["directions"], parts["constants"][6:]
    first = fit_direction_correction(fitter, d0, c_force, shifts, degree=degree, progress=say)
    best = first
    for _ in range(rounds - 1 if log_e is not None else 0):
        if not best.accepted:
            break
        new_log_e, obj = fit_stiffness_if_better(fitter, c_dir, best.objective_mm, say, force=c_force,
                                                 shifts=shifts, directions=best.directions)
        if new_log_e is None:
            break
        log_e = new_log_e
        again = fit_direction_correction(fitter, d0, c_force, shifts, degree=degree, initial=best.coefficients,
                                         progress=say)
        best = replace(again, accepted=True) if again.accepted else replace(best, objective_mm=obj)
    return replace(best, start_objective_mm=first.start_objective_mm), log_e


def __getattr__(name: str):
    """``FitResult`` (≤ 0.7) fails with one line naming :class:`FitOutcome` (an ImportError, so that
    ``from lungdeform.fit.fitting import FitResult`` shows it too, as :mod:`lungdeform.plot` does for
    its moved names); other names are missing as usual."""
    if name == "FitResult":
        raise ImportError(f"{__name__}.FitResult was renamed {__name__}.FitOutcome in 0.8 (docs/CHANGELOG.md)")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def to_lung_model(surface: Surface, side: str, result: FitOutcome, gravity="supine", d_min: float = 1.0) -> LungModel:
    """A :class:`LungModel` (model-file ready) whose displacement is the fitted ``u``.

    The force basis is recomputed with the fitted stiffness; the stored displacement is the
    fitted one (same ``k·F·d``), per ``unit_ml`` = ΔV of the calibration target.
    """
    frame = lung_frame(surface.vertices, side)
    xyz = frame.normalized(surface.vertices)
    basis = solve_response(surface, field_basis(xyz), result.stiffness, d_min=d_min)
    return LungModel(side, surface, np.asarray(result.constants, float), result.stiffness, frame,
                     result.directions, basis, gravity_vector(gravity), result.displacement,
                     float(result.unit_ml), float(result.calibration_ml), float(d_min))
