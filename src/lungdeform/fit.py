"""Fitting the model's constants to surfaces at two or more lung volumes (paper Sec. IV-B; METHOD §8).

The model keeps the paper's form: per vertex ``u_i = k·F_i·d_i`` with ``d_i`` from c1…c6 (15)–(17),
``F`` the elastostatic response of the applied force (18) ``f = c7·x̂ + c8·ŷ + c9·ẑ`` through the
spring-node graph, and ``k`` fixed by the exact volume of the calibration target. At volume V the
surface is ``p + s·u`` with ``s = (V − V_EE)/ΔV``: three additions per vertex at run time.

Pipeline for one candidate c1…c6 (:meth:`LungFitter.evaluate`):

1. directions ``d`` from c1…c6;
2. rays from the end-exhale vertices along ``±d`` to the calibration target
   (:func:`lungdeform.correspond.correspond`: bounded, both directions, grazing rejected, misses
   explicit) → observed magnitudes ``t`` (mm);
3. observed force ``F_obs ∝ t``; **inverse force** ``f = (I − Qᵀ)(F_obs / T_e[i→i])`` (one sparse
   product; spring nodes take the mean of their two mass nodes' F, METHOD §4);
4. c7…c9 by weighted linear least squares (weights: vertex area; misses 0; one robust pass drops
   rays more than 3 robust standard deviations, at least 1 mm, from the first fit). Reading chosen: the fit is done on the forward side,
   ``F_obs ≈ c7·F_x + c8·F_y + c9·F_z`` (``F_x`` = precomputed response to the field x̂, …), which
   is the same linear model as ``f ≈ c7·x̂ + c8·ŷ + c9·ẑ`` pushed through the solver but does not
   amplify the ray noise by the sparse differentiation of step 3; the paper's reading (least
   squares on the inverse force ``f / max f``) is also computed and reported
   (:attr:`FitResult.force_constants_inverse`). Misses have zero weight;
5. forward check: ``F`` from the fitted c7…c9, ``u = k·F·d`` calibrated to the exact target volume,
   predicted surface ``p + s·u`` measured against every target by the exact symmetric surface
   distance (:mod:`lungdeform.distance`).

The objective minimised over c1…c6 is the RMS of that forward symmetric surface distance (area
weighted) over the targets in ``fit_on``: the predicted surface, not ray agreement, is judged.
Two search modes: ``"optimizer"`` (bounded Powell from Table I, then Nelder–Mead polish) and
``"grid"`` (the paper's grid with step 0.01, read as cyclic coordinate search on that grid:
each constant in turn is scanned over its range at step 0.01 with the others fixed, until a
full cycle brings no improvement; a full 6-D grid at 0.01 would be 10¹² models).

Optional beyond the paper (``fit_stiffness=True``): a heterogeneous per-vertex stiffness field, an
inverse estimate of regional alveolar expandability (paper Sec. VI): ``E`` is adjusted so that
the forward force of the fitted applied force reproduces the (lightly smoothed) observed
magnitudes; it is kept only when it lowers the fit objective. The model keeps its run-time form.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy import optimize, sparse

from .constants import gravity_vector, table_constants
from .correspond import RayCaster, RayHits, correspond
from .direction import directions as direction_field
from .displacement import calibrate
from .distance import SurfaceDistance, vertex_areas
from .errors import ConvergenceError, InputError, LungdeformError
from .force import field_basis, height_weights
from .frame import lung_frame
from .graph import spring_graph
from .mesh import Surface
from .model import LungModel
from .solve import ForceSolver
from .stiffness import as_moduli, uniform
from .transfer import local_transfer, split_transfer

#: Bounds of c1…c6 searched (scales c1, c3, c5; exponents c2, c4, c6).
DIRECTION_BOUNDS = ((0.01, 3.0), (0.05, 4.0), (0.01, 3.0), (0.05, 4.0), (0.01, 3.0), (0.05, 4.0))


@dataclass(frozen=True, eq=False)
class Target:
    """One observed surface at a larger volume, in the end-exhale scan's frame (aligned).

    Attributes
    ----------
    surface : Surface
        mm LPS, already rigidly aligned to the end-exhale scan.
    volume_ml : float
        Its lung volume (mL), measured or given.
    keep : (n_target,) bool
        Target vertices measured (False: an artefact such as a crop face).
    name : str
    """

    surface: Surface
    volume_ml: float
    keep: np.ndarray | None = None
    name: str = "target"


@dataclass(frozen=True, eq=False)
class _PreparedTarget:
    target: Target
    distance: SurfaceDistance
    caster: RayCaster
    samples: np.ndarray  # (k, 3) target points used by the fit objective
    sample_weights: np.ndarray


@dataclass(frozen=True, eq=False)
class FitResult:
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
        Applied force recovered from the observed magnitudes (step 3), normalised by its max.
    force_constants_inverse : (3,) float
        c7…c9 fitted on ``inverse_force`` directly (the paper's reading), same normalisation.
    rays : RayHits
        Correspondences for the fitted directions.
    residuals : dict[str, (k,) float]
        Per target name: forward symmetric distances (mm) of the fit samples.
    objective_mm : float
        Final objective (area-weighted RMS symmetric distance over ``fit_on``), mm.
    success : bool
    message : str
    mode : str
    evaluations : int
    seconds : float
    history : (h,) float
        Best objective after each evaluation (mm).
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
    success: bool
    message: str
    mode: str
    evaluations: int
    seconds: float
    history: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stiffness_fitted: bool = False
    uniform_displacement: np.ndarray | None = None
    uniform_objective_mm: float = float("nan")

    def positions_at(self, surface: Surface, volume_ml: float) -> np.ndarray:
        """Predicted vertices ``p + s·u`` (mm) at lung volume ``volume_ml`` (linear in volume)."""
        s = (float(volume_ml) - self.volume_ee_ml) / self.unit_ml
        return surface.vertices + s * self.displacement

    def as_dict(self) -> dict:
        return {"constants": [float(c) for c in self.constants], "objective_rms_mm": self.objective_mm,
                "success": self.success, "message": self.message, "mode": self.mode,
                "evaluations": self.evaluations, "seconds": self.seconds,
                "force_constants_inverse": [float(c) for c in self.force_constants_inverse],
                "rays": self.rays.summary(), "stiffness_fitted": self.stiffness_fitted,
                "stiffness_range": [float(self.stiffness.min()), float(self.stiffness.max())]}


# --------------------------------------------------------------------------- free functions
def inverse_force(transfer, kept_mass: np.ndarray, spring_ends: np.ndarray) -> np.ndarray:
    """Applied force on all graph nodes from the kept force on mass nodes (METHOD §8).

    ``f = (I − Qᵀ)(F / T_e[i→i])`` with spring-node F the mean of its two mass nodes.
    ``kept_mass : (n,) float``; ``spring_ends : (e, 2) int``; returns ``f : (n + e,) float``.
    """
    keep, q = split_transfer(transfer)
    fm = np.asarray(kept_mass, float)
    f_all = np.concatenate([fm, 0.5 * (fm[spring_ends[:, 0]] + fm[spring_ends[:, 1]])])
    x = f_all / keep
    return x - q.T @ x


def least_squares_constants(fields: np.ndarray, values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted linear least squares ``values ≈ c @ fields``: ``fields (k, n)``, ``values (n,)`` →
    ``c (k,)``. Rows with zero weight are ignored."""
    a = np.asarray(fields, float).T
    b = np.asarray(values, float)
    w = np.ones(len(b)) if weights is None else np.asarray(weights, float)
    m = w > 0
    if m.sum() < a.shape[1]:
        raise LungdeformError(f"too few observations ({int(m.sum())}) to fit {a.shape[1]} constants")
    sw = np.sqrt(w[m])
    c, *_ = np.linalg.lstsq(a[m] * sw[:, None], b[m] * sw, rcond=None)
    return c


def _sample(surface: Surface, keep: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``count`` kept vertices (random, reproducible) with area weights rescaled to the kept area."""
    idx = np.nonzero(keep)[0]
    w = vertex_areas(surface.vertices, surface.faces)
    if len(idx) > count:
        idx = np.sort(np.random.default_rng(seed).choice(idx, count, replace=False))
    return surface.vertices[idx], w[idx]


# --------------------------------------------------------------------------- the fitter
class LungFitter:
    """Precompute once for one end-exhale surface, then evaluate many candidate constants.

    Parameters
    ----------
    surface : Surface
        End-exhale surface p (the model mesh; a few thousand vertices), mm LPS.
    side : 'left' | 'right'
    targets : sequence of Target
        Aligned surfaces at larger volumes (volumes must increase, all above V_EE).
    fit_on : sequence of int, optional
        Indices of the targets in the objective (default: all). The first is the calibration
        target (``k`` makes its volume exact) and the one rays are cast to.
    keep : (n,) bool, optional
        Model vertices measured by the objective (False: e.g. the crop face).
    gravity : str or (3,)
    max_distance, min_cosine : ray search bound (mm) and grazing threshold.
    samples : int
        Target points per target used by the objective.
    """

    def __init__(self, surface: Surface, side: str, targets: Sequence[Target], *, fit_on=None,
                 keep=None, gravity="supine", max_distance: float = 25.0, min_cosine: float = 0.25,
                 samples: int = 6000, d_min: float = 1.0, stiffness=None):
        if not targets:
            raise InputError("targets: fitting needs at least one larger-volume surface")
        self.surface = surface
        self.side = side
        self.p = surface.vertices
        self.n = surface.n_vertices
        self.v_ee = surface.volume_ml
        vols = [float(t.volume_ml) for t in targets]
        for t, v in zip(targets, vols):
            if not np.isfinite(v) or v <= self.v_ee:
                raise InputError(
                    f"{t.name}: volume {v:.1f} mL is not larger than the end-exhale volume "
                    f"{self.v_ee:.1f} mL; volumes must increase from the end-exhale surface")
        if any(b <= a for a, b in zip(vols, vols[1:])):
            raise InputError(f"target volumes must increase strictly, got {', '.join(f'{v:.1f}' for v in vols)} mL")
        self.targets = list(targets)
        self.fit_on = list(range(len(targets))) if fit_on is None else [int(i) for i in fit_on]
        if not self.fit_on or any(i < 0 or i >= len(targets) for i in self.fit_on):
            raise InputError(f"fit_on must index the {len(targets)} targets, got {fit_on!r}")
        self.keep = np.ones(self.n, bool) if keep is None else np.asarray(keep, bool)
        self.gravity = gravity_vector(gravity)
        self.max_distance = float(max_distance)
        self.min_cosine = float(min_cosine)
        self.d_min = float(d_min)
        self.frame = lung_frame(self.p, side)
        self.xyz = self.frame.normalized(self.p)
        self.graph = spring_graph(self.p, surface.edges)
        self.areas = vertex_areas(self.p, surface.faces)
        self.prepared = []
        for i, t in enumerate(self.targets):
            k = np.ones(t.surface.n_vertices, bool) if t.keep is None else np.asarray(t.keep, bool)
            pts, w = _sample(t.surface, k, samples, seed=i)
            self.prepared.append(_PreparedTarget(t, SurfaceDistance(t.surface.vertices, t.surface.faces),
                                                 RayCaster(t.surface.vertices, t.surface.faces), pts, w))
        self.calib = self.fit_on[0]
        self.delta_ml = vols[self.calib] - self.v_ee
        self.set_stiffness(uniform(self.n) if stiffness is None else as_moduli(stiffness, self.n))
        self.evaluations = 0

    # ----------------------------------------------------------------- stiffness-dependent part
    def set_stiffness(self, stiffness: np.ndarray) -> None:
        """(Re)build the transfer and the force responses for a stiffness field ``(n,)``."""
        self.stiffness = stiffness
        self.transfer = local_transfer(self.graph, stiffness, self.d_min)
        solver = ForceSolver(self.transfer, "bicgstab", n_mass=self.n, tol=1e-10)
        self.basis = np.stack([solver.solve(fld)[: self.n] for fld in field_basis(self.xyz)])  # (4, n)
        w = height_weights(self.frame, self.gravity)
        # the three fields of (18) for this gravity: x̂, ĥ(gravity), ẑ
        self.fields = np.stack([self.basis[1], w @ self.basis, self.basis[3]])  # responses F_x, F_h, F_z
        self.applied_fields = np.stack([self.xyz[:, 0], w @ field_basis(self.xyz), self.xyz[:, 2]])

    # ----------------------------------------------------------------- one candidate
    def evaluate(self, c_dir: np.ndarray, *, full: bool = False):
        """Objective (mm) for direction constants ``c_dir (6,)``; with ``full`` also the parts."""
        self.evaluations += 1
        c_dir = np.asarray(c_dir, float)
        c_full = np.concatenate([c_dir, [0.0, 1.0, 0.0]])
        d = direction_field(self.frame, self.p, c_full)
        target = self.prepared[self.calib]
        hits = correspond(self.p, d, target.caster, max_distance=self.max_distance, min_cosine=self.min_cosine)
        w = np.where(hits.valid, self.areas, 0.0)
        t = np.nan_to_num(hits.distance)
        if (w > 0).sum() < 10:
            return (np.inf, None) if full else np.inf
        c_force = least_squares_constants(self.fields, t, w)
        # one robust pass: rays whose magnitude is far from the fitted force (a wrong wall) are dropped
        resid = np.abs(c_force @ self.fields - t)
        mad = 1.4826 * np.median(resid[w > 0])
        w2 = np.where(resid <= max(3.0 * mad, 1.0), w, 0.0)
        if (w2 > 0).sum() >= 10:
            c_force = least_squares_constants(self.fields, t, w2)
        force = c_force @ self.fields
        raw = force[:, None] * d
        try:
            u = calibrate(self.p, self.surface.faces, raw, calibration_ml=self.delta_ml, unit_ml=self.delta_ml)
        except LungdeformError:
            return (np.inf, None) if full else np.inf
        residuals = {}
        dists, weights = [], []
        for i in self.fit_on:
            pt = self.prepared[i]
            s = (pt.target.volume_ml - self.v_ee) / self.delta_ml
            a_to_b, b_to_a, wa, wb = self._two_sided(self.p + s * u, pt)
            residuals[pt.target.name] = np.concatenate([a_to_b, b_to_a])
            dists += [a_to_b, b_to_a]
            weights += [wa / wa.sum(), wb / wb.sum()]
        dd, ww = np.concatenate(dists), np.concatenate(weights)
        obj = float(np.sqrt(np.average(dd**2, weights=ww)))
        if not full:
            return obj
        scale = np.abs(c_force).max()
        parts = dict(directions=d, hits=hits, force=force, u=u, residuals=residuals,
                     constants=np.concatenate([c_dir, c_force / scale]))
        return obj, parts

    def _two_sided(self, positions: np.ndarray, pt: _PreparedTarget):
        a_to_b = pt.distance.distance(positions[self.keep])
        b_to_a = SurfaceDistance(positions, self.surface.faces).distance(pt.samples)
        return a_to_b, b_to_a, self.areas[self.keep], pt.sample_weights

    def inverse_parts(self, force_obs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(f (n,) normalised by max |f|, c7…c9 (3,))``: inverse force and its paper-style fit."""
        f = inverse_force(self.transfer, force_obs, self.graph.spring_ends)[: self.n]
        scale = np.abs(f[weights > 0]).max() if np.any(weights > 0) else 1.0
        f = f / (scale or 1.0)
        c = least_squares_constants(self.applied_fields, f, weights)
        return f, c / (np.abs(c).max() or 1.0)


def _grid_search(fun, x0, bounds, step=0.01, max_cycles=20, span=None, progress=None):
    """Cyclic coordinate search on a grid of ``step``; returns (x, f, cycles)."""
    x = np.round(np.asarray(x0, float) / step) * step
    best = fun(x)
    for cycle in range(1, max_cycles + 1):
        improved = False
        for k in range(len(x)):
            lo, hi = bounds[k]
            if span is not None:
                lo, hi = max(lo, x[k] - span[k]), min(hi, x[k] + span[k])
            grid = np.arange(np.ceil(lo / step) * step, hi + step / 2, step)
            vals = []
            for g in grid:
                y = x.copy()
                y[k] = g
                vals.append(fun(y))
            j = int(np.argmin(vals))
            if vals[j] < best - 1e-9:
                best, x[k], improved = vals[j], grid[j], True
        if progress:
            progress(f"grid cycle {cycle}: RMS {best:.3f} mm")
        if not improved:
            return x, best, cycle
    return x, best, max_cycles


def fit_lung(
    surface: Surface,
    side: str,
    targets: Sequence[Target],
    *,
    mode: str = "optimizer",
    initial=None,
    fit_on=None,
    keep=None,
    gravity="supine",
    fit_stiffness: bool = False,
    max_distance: float = 25.0,
    min_cosine: float = 0.25,
    samples: int = 6000,
    max_evaluations: int = 600,
    grid_span: float = 0.3,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit c1…c9 (and optionally a stiffness field) of one lung; see the module docstring.

    ``mode``: ``"optimizer"`` or ``"grid"``. ``initial``: c1…c6 (or c1…c9) to start from;
    default Table I. ``grid_span``: half-width around the start that the grid scans per constant
    (step 0.01). Raises :class:`InputError` for bad input; a fit whose objective is not finite
    raises :class:`ConvergenceError`; an optimiser that stops on its evaluation budget returns
    ``success=False`` with the reason in ``message``.
    """
    if mode not in ("optimizer", "grid"):
        raise InputError(f"mode must be 'optimizer' or 'grid', got {mode!r}")
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    fitter = LungFitter(surface, side, targets, fit_on=fit_on, keep=keep, gravity=gravity,
                        max_distance=max_distance, min_cosine=min_cosine, samples=samples)
    x0 = (table_constants(side) if initial is None else np.asarray(initial, float))[:6]
    history: list[float] = []

    def fun(x):
        v = fitter.evaluate(np.clip(x, [b[0] for b in DIRECTION_BOUNDS], [b[1] for b in DIRECTION_BOUNDS]))
        history.append(min(v, history[-1]) if history else v)
        return v

    start = fun(x0)
    if not np.isfinite(start):
        raise ConvergenceError(f"the starting constants {x0} give no usable model (no ray hits or no volume growth)")
    say(f"{side}: start RMS {start:.3f} mm ({mode})")
    success, message = True, "converged"
    if mode == "optimizer":
        res = optimize.minimize(fun, x0, method="Powell", bounds=DIRECTION_BOUNDS,
                                options={"maxfev": max_evaluations, "xtol": 1e-3, "ftol": 1e-5})
        x, best = res.x, res.fun
        if not res.success:
            success, message = False, f"Powell: {res.message}"
        say(f"{side}: optimiser RMS {best:.3f} mm after {fitter.evaluations} evaluations")
    else:
        x, best, cycles = _grid_search(fun, x0, DIRECTION_BOUNDS, 0.01, span=[grid_span] * 6, progress=say)
        message = f"grid converged after {cycles} cycles"
    best_x = np.clip(x, [b[0] for b in DIRECTION_BOUNDS], [b[1] for b in DIRECTION_BOUNDS])
    log_e = None
    uniform_u, uniform_obj = None, float(best)
    if fit_stiffness:
        _, uparts = fitter.evaluate(best_x, full=True)
        uniform_u = uparts["u"] if uparts is not None else None
        log_e, best = _fit_stiffness(fitter, best_x, best, say)
    obj, parts = fitter.evaluate(best_x, full=True)
    if parts is None or not np.isfinite(obj):
        raise ConvergenceError(f"{side}: the fitted constants give no usable model")
    w = np.where(parts["hits"].valid, fitter.areas, 0.0)
    f_inv, c_inv = fitter.inverse_parts(np.nan_to_num(parts["hits"].distance), w)
    return FitResult(
        constants=parts["constants"], stiffness=fitter.stiffness, displacement=parts["u"],
        unit_ml=fitter.delta_ml, volume_ee_ml=fitter.v_ee, calibration_ml=fitter.delta_ml,
        directions=parts["directions"], force=parts["force"], inverse_force=f_inv,
        force_constants_inverse=c_inv, rays=parts["hits"], residuals=parts["residuals"],
        objective_mm=obj, success=success, message=message, mode=mode,
        evaluations=fitter.evaluations, seconds=time.perf_counter() - t0, history=np.asarray(history),
        stiffness_fitted=log_e is not None, uniform_displacement=uniform_u,
        uniform_objective_mm=uniform_obj,
    )


def smooth_observations(values: np.ndarray, weights: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Normalised convolution on the mesh: weighted umbrella averaging of ``values (n,)`` with
    ``weights (n,) ≥ 0`` (0 = no observation, filled from the neighbours)."""
    from .mask import umbrella_operator

    n = len(values)
    avg = (umbrella_operator(n, faces) + sparse.identity(n)).tocsr()  # D⁻¹A: mean of neighbours
    a = np.asarray(values, float) * weights
    b = np.asarray(weights, float).copy()
    for _ in range(int(iterations)):
        a = 0.5 * a + 0.5 * (avg @ a)
        b = 0.5 * b + 0.5 * (avg @ b)
    return a / np.maximum(b, 1e-12)


def _fit_stiffness(fitter: LungFitter, c_dir, best, say, iterations: int = 20, smoothing: int = 2):
    """Inverse estimate of alveolar expandability: a per-vertex stiffness E whose forward force
    F(E) (for the fitted applied force) matches the observed magnitudes along the fitted
    directions (ray hits, lightly smoothed, misses filled by neighbours).

    Softer nodes keep and attract more force (METHOD §3), so ``log E`` is updated by the log-ratio
    of the predicted to the observed magnitude, then smoothed (``smoothing`` umbrella steps), for
    ``iterations`` fixed-point steps. Kept only if it lowers the objective; returns
    ``(log E (n,) or None, objective)``.
    """
    _, parts = fitter.evaluate(c_dir, full=True)
    hits = parts["hits"]
    w = np.where(hits.valid, np.nan_to_num(hits.cosine), 0.0)
    target = np.maximum(smooth_observations(np.nan_to_num(hits.distance), w, fitter.surface.faces, smoothing), 0.1)
    c = parts["constants"]
    f = c[6:] @ fitter.applied_fields
    log_e = np.zeros(fitter.n)
    uniform_e = fitter.stiffness
    for _ in range(int(iterations)):
        solver = ForceSolver(local_transfer(fitter.graph, np.exp(log_e), fitter.d_min), "bicgstab",
                             n_mass=fitter.n, tol=1e-10)
        force = solver.solve(f)[: fitter.n]
        scale = float(target @ force) / float(force @ force)
        log_e = np.clip(log_e + 0.7 * np.log(np.maximum(scale * force, 1e-3) / target), -4.0, 4.0)
        log_e = smooth_observations(log_e, np.ones(fitter.n), fitter.surface.faces, 2)
    fitter.set_stiffness(np.exp(log_e))
    obj = fitter.evaluate(c_dir)
    if not obj < best:
        fitter.set_stiffness(uniform_e)
        say(f"stiffness field: RMS {obj:.3f} mm, not better than {best:.3f} mm: kept uniform")
        return None, best
    say(f"stiffness field: RMS {best:.3f} -> {obj:.3f} mm")
    return log_e, obj


def to_lung_model(surface: Surface, side: str, result: FitResult, gravity="supine", d_min: float = 1.0) -> LungModel:
    """A :class:`LungModel` (model-file ready) whose displacement is the fitted ``u``.

    The force basis is recomputed with the fitted stiffness; the stored displacement is the
    fitted one (same ``k·F·d``), per ``unit_ml`` = ΔV of the calibration target.
    """
    frame = lung_frame(surface.vertices, side)
    xyz = frame.normalized(surface.vertices)
    graph = spring_graph(surface.vertices, surface.edges)
    solver = ForceSolver(local_transfer(graph, result.stiffness, d_min), "bicgstab", n_mass=surface.n_vertices)
    basis = np.stack([solver.solve(fld)[: surface.n_vertices] for fld in field_basis(xyz)])
    return LungModel(side, surface, np.asarray(result.constants, float), result.stiffness, frame,
                     result.directions, basis, gravity_vector(gravity), result.displacement,
                     float(result.unit_ml), float(result.calibration_ml), float(d_min))
