"""Inversion of the breathing driver: its control parameters from a measured trace.

The forward model is :mod:`lungdeform.breathing.pv`: the single-compartment equation of motion

    I·V''(t) + R·V'(t) + E·(V(t) − V_r) = P_mus(t),        P_mus(t) = Σ_{k=1..5} a_k·φ_k(θ(t)),

with the five basis functions φ_k of the breathing phase θ described there (and why they were
chosen). This module estimates the a_k (and the shape constants) from a volume trace, predicts and
refits held-out cycles with the fitted shape, and, with a measured driving pressure alongside,
estimates E, R, I and the a_k directly.

Because the equation is linear, ``V − V_r = Σ a_k·y_k(t)`` where ``y_k`` is the response to ``φ_k``.
For given (E, R, I, ρ, κ) the inversion is therefore an ordinary linear least-squares problem in
``a`` (five well-separated columns); the few shape constants (τ = R/E, I/E, ρ, κ) are found by a
bounded outer search (variable projection). From volume alone the equation is invariant to scaling
(E, R, I, a) together, so only τ = R/E and I/E are identifiable and E is fixed at a given value;
with a measured pressure alongside, E, R and I are estimated too (:func:`estimate_mechanics`).

Per-cycle timing. Real breaths differ in length and in the length of the end-expiratory pause; a
fixed ρ cannot follow that. When each cycle's end-inhale time is known (RPM 'P' marks, or detected
peaks), :func:`invert` gives each cycle its own inspiratory time T_i,c = t_peak,c − t_start,c − δ with
one shared lag δ (s) between the end of the drive and the volume peak, fitted with τ, I/E and κ.
Measured on synthetic breaths (tests): with E, R, I, ρ, κ known the a_k come back to within the
noise; with everything free the curve is reproduced to the noise and τ, ρ are recovered.

Units: parameters in cmH2O, L, L/s, s (as :mod:`lungdeform.breathing.pv`); traces and fits in mL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from lungdeform.errors import InputError

from .pv import N_CONTROL, BreathingParams, Mechanics, basis, interp_periodic, periodic_response


# --------------------------------------------------------------------------- inversion
@dataclass(frozen=True)
class BreathingFit:
    """Result of :func:`invert`.

    params : fitted :class:`BreathingParams` (period_s = mean cycle duration); success, message;
    t_s, volume_ml, model_ml, residual_ml : (n,) float (samples used, mL);
    rms_percent : RMS residual as % of the median per-cycle peak-to-peak volume;
    gains, offsets_ml : (k,) per-cycle calibration (1 and 0 unless per_cycle_calibration);
    cycle_starts_s : (k+1,) float, s; shared / per_cycle : names of the parameters fitted once /
    per cycle; peak_lag_s : δ (s) when each cycle's inspiratory time came from its peak, else None.
    """

    params: BreathingParams
    success: bool
    message: str
    t_s: np.ndarray
    volume_ml: np.ndarray
    model_ml: np.ndarray
    residual_ml: np.ndarray
    rms_percent: float
    gains: np.ndarray
    offsets_ml: np.ndarray
    cycle_starts_s: np.ndarray
    shared: tuple = ()
    per_cycle: tuple = ()
    peak_lag_s: float | None = None


def insp_fractions(cycle_starts_s, peaks_s, peak_lag_s: float) -> np.ndarray:
    """Per-cycle ρ_c = (t_peak − t_start − lag)/T_c, clipped to [0.1, 0.9]: the drive's inspiration
    ends ``peak_lag_s`` before the observed end-inhale. Returns (k,) float."""
    starts = np.asarray(cycle_starts_s, dtype=float)
    peaks = np.asarray(peaks_s, dtype=float)
    if peaks.shape != (starts.size - 1,):
        raise InputError(f"peaks_s must hold one end-inhale time per cycle ({starts.size - 1}), got {peaks.shape}")
    return np.clip((peaks - starts[:-1] - peak_lag_s) / np.diff(starts), 0.1, 0.9)


def cycle_design(t_s, cycle_starts_s, mechanics: Mechanics, insp_fraction, decay: float):
    """Response matrix of the five basis functions at samples ``t_s`` inside the given cycles.

    insp_fraction : float, or (k,) float one per cycle. Returns (cycle_index (n,) int (−1 outside
    every cycle), Y (n, 5) L per cmH2O, F (n, 5) L/s per cmH2O). Each cycle is treated as one period
    of its own duration and inspiratory fraction (its periodic steady state).
    """
    t = np.asarray(t_s, dtype=float)
    starts = np.asarray(cycle_starts_s, dtype=float)
    idx = np.searchsorted(starts, t, side="right") - 1
    idx[(idx < 0) | (idx >= starts.size - 1)] = -1
    y = np.zeros((t.size, N_CONTROL))
    f = np.zeros((t.size, N_CONTROL))
    cache: dict = {}
    rhos = np.broadcast_to(np.asarray(insp_fraction, dtype=float), (max(starts.size - 1, 0),))
    for c in np.unique(idx[idx >= 0]):
        dur = starts[c + 1] - starts[c]
        key = (round(dur, 4), round(float(rhos[c]), 4))
        if key not in cache:
            cache[key] = periodic_response(dur, mechanics, float(rhos[c]), decay, n_phase=256)
        vol, flo = cache[key]
        sel = idx == c
        theta = (t[sel] - starts[c]) / dur
        y[sel] = interp_periodic(vol, theta)
        f[sel] = interp_periodic(flo, theta)
    return idx, y, f


def _per_cycle_p2p(idx, values) -> float:
    p2p = [np.ptp(values[idx == c]) for c in np.unique(idx[idx >= 0])]
    return float(np.median(p2p)) if p2p else float(np.ptp(values))


def calibration_design(shape, phase, drift: bool = False) -> np.ndarray:
    """Per-cycle calibration columns for one cycle: [shape, 1] or, with ``drift``, [shape, 1, θ − ½].

    shape : (m,) model values in the cycle; phase : (m,) θ in [0, 1). The drift column lets the
    baseline move linearly across the cycle (surrogate-signal baseline drift).
    """
    cols = [np.asarray(shape, float), np.ones(len(shape))]
    if drift:
        cols.append(np.asarray(phase, float) - 0.5)
    return np.column_stack(cols)


def _solve_linear(idx, theta, y, v, per_cycle_calibration: bool, drift: bool = False):
    """Least squares for a (and per-cycle gain/offset[/drift]). Returns (a, gains, offsets, model).

    With per-cycle calibration the problem is kept exactly linear: each cycle's gain is its observed
    peak-to-peak over the mean one (fixed from the data), its offset (and drift) are indicator
    columns solved together with a_2..a_5 (a_1, the tonic term, is absorbed by the offsets).
    """
    cycles = np.unique(idx[idx >= 0])
    if not per_cycle_calibration:
        a, *_ = np.linalg.lstsq(y, v, rcond=None)
        return a, np.ones(cycles.size), np.zeros(cycles.size), y @ a
    sels = [idx == c for c in cycles]
    p2p = np.array([np.ptp(v[sel]) for sel in sels])
    gains = p2p / p2p.mean() if p2p.mean() > 0 else np.ones(cycles.size)
    pos = np.searchsorted(cycles, idx)
    g = gains[pos]
    X = y[:, 1:] * g[:, None]
    # Frisch–Waugh: project the per-cycle offset (and drift) columns out of X and v within each
    # cycle, solve the small problem for a_2..a_5, then recover the offsets. Same solution as the
    # full least squares with k indicator columns, at a fraction of the cost.
    Z = [np.ones_like(v)] + ([theta - 0.5] if drift else [])
    Xr, vr = X.copy(), v.copy()
    for z in Z:
        zz = np.bincount(pos, z * z, minlength=cycles.size)
        zz = np.where(zz > 0, zz, 1.0)
        vr = vr - z * (np.bincount(pos, z * vr, minlength=cycles.size) / zz)[pos]
        for j in range(Xr.shape[1]):
            Xr[:, j] = Xr[:, j] - z * (np.bincount(pos, z * Xr[:, j], minlength=cycles.size) / zz)[pos]
    coef = np.linalg.lstsq(Xr, vr, rcond=None)[0]
    a = np.concatenate([[0.0], coef])
    model_noff = X @ coef
    resid = v - model_noff
    model = model_noff.copy()
    offsets = np.zeros(cycles.size)
    for j, sel in enumerate(sels):
        A = np.column_stack(Z)[sel]
        c = np.linalg.lstsq(A, resid[sel], rcond=None)[0]
        offsets[j] = c[0]
        model[sel] += A @ c
    return a, gains, offsets, model


#: Default bounds of the shape search: τ = R/E (s), I/E (s²), ρ, δ (s), κ.
SHAPE_BOUNDS = {"tau": (0.02, 4.0), "inert_ratio": (1e-4, 5e-3), "insp_fraction": (0.2, 0.75),
                "peak_lag_s": (-0.3, 1.5), "decay": (0.03, 0.6)}


def _samples_in_cycles(t_s, volume_ml, cycle_starts_s, peaks_s):
    """Checked ``(t (n,) s, volume (n,) mL, starts (k+1,) s)``, the samples cut to the given cycles."""
    t = np.asarray(t_s, dtype=float)
    v_ml = np.asarray(volume_ml, dtype=float)
    if t.ndim != 1 or t.shape != v_ml.shape:
        raise InputError(f"t_s and volume_ml must be (n,) arrays of one length, got {t.shape} and {v_ml.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v_ml))):
        raise InputError("t_s and volume_ml must be finite (no NaN)")
    starts = np.asarray(cycle_starts_s, dtype=float)
    if starts.ndim != 1 or starts.size < 2 or np.any(np.diff(starts) <= 0):
        raise InputError("cycle_starts_s must hold at least 2 increasing end-exhale times (one cycle)")
    if peaks_s is not None:
        insp_fractions(starts, peaks_s, 0.0)  # validates the shape
    inside = (t >= starts[0]) & (t < starts[-1])
    if inside.sum() < 4 * N_CONTROL:
        raise InputError(f"only {inside.sum()} samples lie inside the given cycles; need >= {4 * N_CONTROL}")
    return t[inside], v_ml[inside], starts


@dataclass(frozen=True, eq=False)
class _ShapeProblem:
    """The variable-projection objective of :func:`invert`.

    The shape vector is ``x = (log τ, log I/E, ρ or δ, log κ)``; for each ``x`` the a_k (and the
    per-cycle calibration) are the linear least-squares solution. t : (n,) s; starts : (k+1,) s;
    theta : (n,) cycle phase; v_l : (n,) L above V_r.
    """

    t: np.ndarray
    starts: np.ndarray
    theta: np.ndarray
    v_l: np.ndarray
    elastance: float
    peaks_s: object
    per_cycle_calibration: bool
    drift: bool

    @property
    def use_peaks(self) -> bool:
        return self.peaks_s is not None

    def unpack(self, x):
        """(Mechanics, ρ float or (k,), κ) of the shape vector ``x``."""
        e = self.elastance
        mech = Mechanics(e, e * np.exp(x[0]), e * np.exp(x[1]))
        rho = insp_fractions(self.starts, self.peaks_s, x[2]) if self.use_peaks else float(x[2])
        return mech, rho, float(np.exp(x[3]))

    def solve(self, x):
        """(cycle index (n,), a (5,), gains, offsets (L), model (n,) L) at the shape ``x``."""
        mech, rho, kappa = self.unpack(x)
        idx, y, _ = cycle_design(self.t, self.starts, mech, rho, kappa)
        a, g, o, model = _solve_linear(idx, self.theta, y, self.v_l, self.per_cycle_calibration, self.drift)
        return idx, a, g, o, model

    def cost(self, x) -> float:
        """Mean squared misfit (L²) at the shape ``x``."""
        *_, model = self.solve(x)
        return float(np.mean((model - self.v_l) ** 2))


def _search_box(init: BreathingParams, bounds: dict, use_peaks: bool):
    """Start ``x0`` and bounds ``lo, hi`` (4,) of the shape vector (see :class:`_ShapeProblem`)."""
    third = "peak_lag_s" if use_peaks else "insp_fraction"
    b = bounds
    x0 = np.array([np.log(init.mechanics.time_constant_s),
                   np.log(max(init.mechanics.inertance / init.mechanics.elastance, b["inert_ratio"][0])),
                   0.2 if use_peaks else init.insp_fraction, np.log(init.decay)])
    lo = np.array([np.log(b["tau"][0]), np.log(b["inert_ratio"][0]), b[third][0], np.log(b["decay"][0])])
    hi = np.array([np.log(b["tau"][1]), np.log(b["inert_ratio"][1]), b[third][1], np.log(b["decay"][1])])
    return np.clip(x0, lo, hi), lo, hi


def _search_shape(problem: _ShapeProblem, x0, lo, hi, n_polish: int, max_evals: int):
    """Best shape vector: a coarse multi-start grid over τ, the timing constant and κ (the objective
    has shallow local minima), then a bounded L-BFGS-B polish (numerical gradient) from the
    ``n_polish`` best starts. The misfit is steep in ρ/δ: a 0.05 error in ρ costs ~4 % of the tidal
    volume. Returns ``(x (4,), success, message)``."""
    starts0 = []
    thirds = np.linspace(lo[2], hi[2], 11)
    for third0 in thirds:
        for tau0 in (0.1, 0.3, 1.0):
            for kappa0 in (0.1, 0.3):
                xs = np.clip(np.array([np.log(tau0), x0[1], third0, np.log(kappa0)]), lo, hi)
                starts0.append((problem.cost(xs), tuple(xs)))
    starts0.sort()
    res = None
    for _, xs in starts0[:n_polish]:
        r = minimize(problem.cost, np.array(xs), method="L-BFGS-B", bounds=list(zip(lo, hi)),
                     options={"maxfun": max_evals, "ftol": 1e-10, "gtol": 1e-9, "eps": 1e-5})
        if res is None or r.fun < res.fun:
            res = r
    return res.x, bool(res.success), str(res.message)


def _fit_result(problem: _ShapeProblem, x, success: bool, message: str, v_ml, v_rel: float,
                period: float) -> BreathingFit:
    """The :class:`BreathingFit` at the shape ``x``, with the physical checks on the result."""
    idx, a, g, o, model = problem.solve(x)
    mech, rho, kappa = problem.unpack(x)
    rho_mean = float(np.mean(rho))
    p_peak = float(np.max(basis(np.linspace(0, 1, 200, endpoint=False), rho_mean, kappa) @ a))
    if success and not np.all(np.isfinite(a)):
        success, message = False, "non-finite control parameters"
    params = BreathingParams(mech, tuple(a), period_s=period, insp_fraction=rho_mean, decay=kappa,
                             relaxation_ml=v_rel)
    model_ml = v_rel + 1000.0 * model
    resid = v_ml - model_ml
    rms = float(np.sqrt(np.mean(resid ** 2)) / _per_cycle_p2p(idx, v_ml) * 100.0)
    if success and p_peak <= 0:
        success, message = False, "fitted muscle pressure never becomes inspiratory (peak P_mus <= 0)"
    use_peaks, cal = problem.use_peaks, problem.per_cycle_calibration
    shared = ("tau", "inert_ratio", "peak_lag_s" if use_peaks else "insp_fraction", "decay", "a_1..a_5")
    return BreathingFit(params, success, message, problem.t, v_ml, model_ml, resid, rms, g, 1000.0 * o,
                        problem.starts, shared=shared,
                        per_cycle=(("gain", "offset") if cal else ())
                        + (("drift",) if cal and problem.drift else ())
                        + (("insp_fraction from the peak time",) if use_peaks else ()),
                        peak_lag_s=float(x[2]) if use_peaks else None)


@dataclass(frozen=True)
class InversionSettings:
    """How :func:`invert` fits.

    elastance : E (cmH2O/L) held fixed — volume alone cannot separate E from the a_k scale.
    per_cycle_calibration : let each cycle have its own gain and offset (amplitude drift of an
    external surrogate); the five a_k then describe the shape shared by all cycles. ``drift`` adds
    a per-cycle linear baseline drift to that calibration.
    relaxation_ml : the relaxation volume, mL (None: the trace's minimum).
    fit_shape : False keeps τ, I/E, ρ (or δ), κ of ``init`` and solves only the linear a_k.
    bounds : overrides of :data:`SHAPE_BOUNDS`.
    n_polish, max_evals : L-BFGS-B polishes from the best grid starts, and their evaluation budget.
    """

    elastance: float = 10.0
    per_cycle_calibration: bool = False
    drift: bool = False
    relaxation_ml: float | None = None
    fit_shape: bool = True
    bounds: dict | None = None
    n_polish: int = 2
    max_evals: int = 500


def invert(t_s, volume_ml, cycle_starts_s, peaks_s=None, *, settings: InversionSettings = InversionSettings(),
           init: BreathingParams | None = None) -> BreathingFit:
    """Estimate the five control parameters (and τ = R/E, I/E, ρ, κ) from a volume trace.

    t_s : (n,) float, s; volume_ml : (n,) float, mL; cycle_starts_s : (k+1,) float, s, the
    inspiration onsets that bound k ≥ 1 cycles (samples outside them are ignored).
    peaks_s : (k,) float, s, optional end-inhale times: then each cycle's drive has its own
    inspiratory time, ending a shared lag δ (fitted, s) before the observed peak, instead of one ρ.
    settings : elastance, calibration, relaxation volume, search (:class:`InversionSettings`).
    init : the start of the search (``fit_shape=False``: the shape kept).
    Returns a :class:`BreathingFit`; ``success`` is False (with the reason) when the outer search
    fails to converge or the fitted system is non-physical.
    """
    elastance, relaxation_ml, bounds = settings.elastance, settings.relaxation_ml, settings.bounds
    per_cycle_calibration, drift = settings.per_cycle_calibration, settings.drift
    fit_shape, n_polish, max_evals = settings.fit_shape, settings.n_polish, settings.max_evals
    t, v_ml, starts = _samples_in_cycles(t_s, volume_ml, cycle_starts_s, peaks_s)
    v_rel = relaxation_ml if relaxation_ml is not None else float(np.min(v_ml))
    cidx = np.searchsorted(starts, t, side="right") - 1
    theta = (t - starts[cidx]) / (starts[cidx + 1] - starts[cidx])
    problem = _ShapeProblem(t, starts, theta, (v_ml - v_rel) / 1000.0, elastance, peaks_s,
                            per_cycle_calibration, drift)
    period = float(np.mean(np.diff(starts)))
    init = init or BreathingParams(Mechanics(elastance, 0.25 * elastance, 0.001 * elastance), (0, 1, 0, 0, 0),
                                   period_s=period)
    x, lo, hi = _search_box(init, {**SHAPE_BOUNDS, **(bounds or {})}, problem.use_peaks)
    success, message = True, "converged"
    if fit_shape:
        x, success, message = _search_shape(problem, x, lo, hi, n_polish, max_evals)
    return _fit_result(problem, x, success, message, v_ml, v_rel, period)


def _rho_for(fit_or_params, cycle_starts_s, peaks_s):
    if isinstance(fit_or_params, BreathingFit):
        params, lag = fit_or_params.params, fit_or_params.peak_lag_s
    else:
        params, lag = fit_or_params, None
    if lag is not None:
        if peaks_s is None:
            raise InputError("this fit times each cycle from its peak: pass peaks_s")
        return params, insp_fractions(cycle_starts_s, peaks_s, lag)
    return params, params.insp_fraction


def predict_cycles(fit, t_s, cycle_starts_s, volume_ml=None, peaks_s=None, calibrate: bool = True,
                   drift: bool = False):
    """Model volume (mL) at ``t_s`` for the given cycles, with the fitted shape.

    fit : :class:`BreathingFit` (or :class:`BreathingParams`). With ``volume_ml`` and ``calibrate``,
    each cycle gets its own least-squares gain and offset (2 numbers per cycle, the same freedom the
    baselines get; 3 with ``drift``). Samples outside the cycles are NaN.
    """
    params, rho = _rho_for(fit, cycle_starts_s, peaks_s)
    starts = np.asarray(cycle_starts_s, dtype=float)
    t = np.asarray(t_s, dtype=float)
    idx, y, _ = cycle_design(t, cycle_starts_s, params.mechanics, rho, params.decay)
    shape = params.relaxation_ml + 1000.0 * (y @ params.a)
    out = np.full(t.shape, np.nan)
    for c in np.unique(idx[idx >= 0]):
        sel = idx == c
        if calibrate and volume_ml is not None:
            theta = (t[sel] - starts[c]) / (starts[c + 1] - starts[c])
            A = calibration_design(shape[sel], theta, drift)
            coef = np.linalg.lstsq(A, np.asarray(volume_ml, float)[sel], rcond=None)[0]
            out[sel] = A @ coef
        else:
            out[sel] = shape[sel]
    return out


def refit_control(fit, t_s, volume_ml, cycle_starts_s, peaks_s=None):
    """Per-cycle refit of the five a_k (mechanics, ρ/δ, κ held). Returns (model_ml (n,), a (k, 5))."""
    params, rho = _rho_for(fit, cycle_starts_s, peaks_s)
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(volume_ml, dtype=float)
    idx, y, _ = cycle_design(t, cycle_starts_s, params.mechanics, rho, params.decay)
    out = np.full(t.shape, np.nan)
    coefs = []
    for c in np.unique(idx[idx >= 0]):
        sel = idx == c
        a = np.linalg.lstsq(y[sel], (v[sel] - params.relaxation_ml) / 1000.0, rcond=None)[0]
        out[sel] = params.relaxation_ml + 1000.0 * (y[sel] @ a)
        coefs.append(a)
    return out, np.asarray(coefs)


# --------------------------------------------------------------------------- with pressure data
def estimate_mechanics(t_s, volume_ml, pressure_cmH2O) -> tuple[Mechanics, float, float]:
    """E, R, I and V_r from a measured driving pressure and volume (linear least squares).

    Regresses P = E·V + R·V' + I·V'' − E·V_r with V', V'' by central differences.
    Returns (Mechanics, relaxation_ml, rms residual cmH2O). Raises InputError on degenerate data.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(volume_ml, dtype=float) / 1000.0
    p = np.asarray(pressure_cmH2O, dtype=float)
    if not (t.shape == v.shape == p.shape) or t.size < 10:
        raise InputError("t_s, volume_ml and pressure_cmH2O must be (n,) arrays of one length, n >= 10")
    dv = np.gradient(v, t)
    d2v = np.gradient(dv, t)
    A = np.column_stack([v, dv, d2v, np.ones_like(v)])
    coef, *_ = np.linalg.lstsq(A[2:-2], p[2:-2], rcond=None)
    e, r, inert, c = coef
    if e <= 0 or r <= 0:
        raise InputError(f"pressure and volume give non-physical mechanics (E={e:.3g}, R={r:.3g})")
    rms = float(np.sqrt(np.mean((A[2:-2] @ coef - p[2:-2]) ** 2)))
    return Mechanics(float(e), float(r), float(max(inert, 0.0))), float(-c / e * 1000.0), rms


def fit_control_to_pressure(theta, pressure_cmH2O, insp_fraction: float, decay: float) -> np.ndarray:
    """a_k (5,) cmH2O by least squares of a measured P_mus against the basis at phases ``theta``."""
    phi = basis(theta, insp_fraction, decay)
    return np.linalg.lstsq(phi, np.asarray(pressure_cmH2O, dtype=float), rcond=None)[0]
