"""Baseline breathing-curve models to compare the PV driver against.

- Lujan et al., Med Phys 1999;26:715 ("A method for incorporating organ motion due to breathing into
  3D dose calculations"): z(t) = z0 − b·cos^{2n}(πt/τ − φ). With inhalation positive and time
  measured as the cycle phase θ ∈ [0, 1) from one end-exhale to the next, we write it
  a(θ) = c0 + b·|cos(πθ − φ)|^{2n}: c0 the end-exhale level, b the amplitude, n the shape (larger n
  = longer end-exhale dwell), φ the phase. Linear in (c0, b) for given (n, φ).
- A truncated Fourier series per cycle: a(θ) = c0 + Σ_{h=1..K} (α_h cos 2πhθ + β_h sin 2πhθ).
  K = 2 has five coefficients, as many as the PV driver's five control parameters.

Both work on the same cycles (end-exhale to end-exhale) and the same phase variable as
:mod:`lungdeform.breathing.pv`. Arrays: ``theta : (n,) float`` phase, ``values : (n,) float`` in the
trace's unit (mL after calibration).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from lungdeform.errors import InputError

from .inversion import calibration_design


def cycle_phase(t_s, cycle_starts_s, peaks_s=None, peak_phase: float | None = None):
    """(cycle index (n,) int, −1 outside; phase θ (n,) float in [0, 1)) of times in the given cycles.

    With ``peaks_s`` (k,) and ``peak_phase``, the phase is warped piecewise-linearly so that every
    cycle's end-inhale falls at θ = peak_phase (onset -> 0, peak -> peak_phase, next onset -> 1).
    """
    t = np.asarray(t_s, dtype=float)
    starts = np.asarray(cycle_starts_s, dtype=float)
    idx = np.searchsorted(starts, t, side="right") - 1
    idx[(idx < 0) | (idx >= starts.size - 1)] = -1
    theta = np.zeros_like(t)
    ok = idx >= 0
    c = idx[ok]
    t0, t1 = starts[c], starts[c + 1]
    if peaks_s is None or peak_phase is None:
        theta[ok] = (t[ok] - t0) / (t1 - t0)
    else:
        tp = np.asarray(peaks_s, dtype=float)[c]
        tt = t[ok]
        theta[ok] = np.where(tt < tp, peak_phase * (tt - t0) / (tp - t0),
                             peak_phase + (1 - peak_phase) * (tt - tp) / (t1 - tp))
    return idx, theta


def median_peak_phase(cycle_starts_s, peaks_s) -> float:
    """Median of (t_peak − t_start)/T over cycles: the reference end-inhale phase."""
    starts = np.asarray(cycle_starts_s, dtype=float)
    return float(np.median((np.asarray(peaks_s, float) - starts[:-1]) / np.diff(starts)))


# --------------------------------------------------------------------------- Lujan
def lujan_shape(theta, n: float, phi: float) -> np.ndarray:
    """|cos(πθ − φ)|^{2n} (n,) in [0, 1]."""
    return np.abs(np.cos(np.pi * np.asarray(theta, float) - phi)) ** (2.0 * n)


@dataclass(frozen=True)
class LujanFit:
    """n (shape exponent), phi (rad); success/message; rms of the fit in the data unit."""

    n: float
    phi: float
    success: bool
    message: str
    rms: float


def calibrated(idx, shape, values, frac, drift: bool = False) -> np.ndarray:
    """Per-cycle least-squares gain and offset (and drift along the cycle fraction ``frac``) of
    ``shape`` to ``values``; returns the model (n,), NaN outside the cycles.

    ``idx`` : (n,) int cycle index (−1 outside), ``frac`` : (n,) float cycle fraction (both from
    :func:`cycle_phase`), ``shape``, ``values`` : (n,) float."""
    model = np.full(values.shape, np.nan)
    for c in np.unique(idx[idx >= 0]):
        sel = idx == c
        A = calibration_design(shape[sel], frac[sel], drift)
        coef = np.linalg.lstsq(A, values[sel], rcond=None)[0]
        model[sel] = A @ coef
    return model


def fit_lujan(t_s, values, cycle_starts_s, per_cycle: bool = False, peaks_s=None,
              peak_phase: float | None = None, drift: bool = False) -> LujanFit | list[LujanFit]:
    """Fit (n, φ) shared by all cycles, with a per-cycle (c0, b); or, ``per_cycle``, one fit per cycle.

    The outer search is a grid over n ∈ [0.5, 5] and φ ∈ [0.35, 2.85], then a bounded Powell polish. With
    ``peaks_s``/``peak_phase`` the phase is warped (see :func:`cycle_phase`).
    """

    idx, theta = cycle_phase(t_s, cycle_starts_s, peaks_s, peak_phase)
    frac = cycle_phase(t_s, cycle_starts_s)[1]
    v = np.asarray(values, dtype=float)
    if not np.any(idx >= 0):
        raise InputError("no samples inside the given cycles")
    groups = [idx >= 0] if not per_cycle else [idx == c for c in np.unique(idx[idx >= 0])]
    fits = []
    for sel in groups:
        ii, th, vv, ff = idx[sel], theta[sel], v[sel], frac[sel]

        def cost(x, ii=ii, th=th, vv=vv, ff=ff):
            m = calibrated(ii, lujan_shape(th, x[0], x[1]), vv, ff, drift)
            return float(np.mean((m - vv) ** 2))

        # grid over the whole bounded range (φ every 0.1 rad: a narrow cos^{2n} needs it), then a
        # bounded Powell polish from the three best starts; a polish that ends worse than its start
        # (bounded Powell can jump basins) is discarded
        grid = sorted((cost((n0, phi0)), n0, phi0) for n0 in (0.5, 1.0, 2.0, 3.0, 5.0)
                      for phi0 in np.linspace(0.35, 2.85, 26))
        best = (grid[0][0], np.array(grid[0][1:]), True, "grid point")
        for c0, n0, phi0 in grid[:3]:
            res = minimize(cost, np.array([n0, phi0]), method="Powell", bounds=[(0.3, 8.0), (0.3, 2.9)],
                           options={"xtol": 1e-3, "ftol": 1e-8})
            if float(res.fun) < best[0]:
                best = (float(res.fun), res.x, bool(res.success), str(res.message))
        fun, x, ok, msg = best
        fits.append(LujanFit(float(x[0]), float(x[1]), ok, msg, float(np.sqrt(fun))))
    return fits if per_cycle else fits[0]


def predict_lujan(fit, t_s, values, cycle_starts_s, peaks_s=None, peak_phase: float | None = None,
                  drift: bool = False) -> np.ndarray:
    """Model values at ``t_s``: the fitted shape with each cycle's own (c0, b). NaN outside cycles.

    ``fit`` is one :class:`LujanFit` (shared shape) or a list, one per cycle (per-cycle refit).
    """
    idx, theta = cycle_phase(t_s, cycle_starts_s, peaks_s, peak_phase)
    v = np.asarray(values, dtype=float)
    if isinstance(fit, list):
        shape = np.zeros_like(theta)
        for j, c in enumerate(np.unique(idx[idx >= 0])):
            sel = idx == c
            shape[sel] = lujan_shape(theta[sel], fit[j].n, fit[j].phi)
    else:
        shape = lujan_shape(theta, fit.n, fit.phi)
    return calibrated(idx, shape, v, cycle_phase(t_s, cycle_starts_s)[1], drift)


# --------------------------------------------------------------------------- Fourier
def fourier_design(theta, harmonics: int = 2) -> np.ndarray:
    """(n, 2K+1) columns [1, cos 2πθ, sin 2πθ, …, cos 2πKθ, sin 2πKθ]."""
    th = np.asarray(theta, float)
    cols = [np.ones_like(th)]
    for h in range(1, harmonics + 1):
        cols += [np.cos(2 * np.pi * h * th), np.sin(2 * np.pi * h * th)]
    return np.column_stack(cols)


def fit_fourier_per_cycle(t_s, values, cycle_starts_s, harmonics: int = 2):
    """Least-squares Fourier series fitted to each cycle on its own. Returns (model (n,), coefs (k, 2K+1))."""
    idx, theta = cycle_phase(t_s, cycle_starts_s)
    v = np.asarray(values, dtype=float)
    model = np.full(v.shape, np.nan)
    coefs = []
    for c in np.unique(idx[idx >= 0]):
        sel = idx == c
        X = fourier_design(theta[sel], harmonics)
        coef = np.linalg.lstsq(X, v[sel], rcond=None)[0]
        model[sel] = X @ coef
        coefs.append(coef)
    return model, np.asarray(coefs)


def fit_fourier_shape(t_s, values, cycle_starts_s, harmonics: int = 2, n_iter: int = 8, peaks_s=None,
                      peak_phase: float | None = None, drift: bool = False) -> np.ndarray:
    """Mean cycle shape: Fourier coefficients (2K,) (no constant) shared by all cycles, each cycle with
    its own gain and offset (and drift) by alternating least squares. Normalised to unit peak-to-peak.
    With ``peaks_s``/``peak_phase`` the phase is warped (see :func:`cycle_phase`)."""
    idx, theta = cycle_phase(t_s, cycle_starts_s, peaks_s, peak_phase)
    frac = cycle_phase(t_s, cycle_starts_s)[1]
    v = np.asarray(values, dtype=float)
    ok = idx >= 0
    X = fourier_design(theta[ok], harmonics)[:, 1:]
    ii, vv, ff = idx[ok], v[ok], frac[ok]
    sels = [ii == c for c in np.unique(ii)]
    cal = np.zeros((len(sels), 3 if drift else 2))
    cal[:, 0] = 1.0
    cal[:, 1] = [vv[sel].mean() for sel in sels]
    coef = np.zeros(X.shape[1])
    for _ in range(n_iter):
        g = np.empty_like(vv)
        o = np.empty_like(vv)
        for j, sel in enumerate(sels):
            g[sel] = cal[j, 0]
            o[sel] = calibration_design(np.zeros(sel.sum()), ff[sel], drift)[:, 1:] @ cal[j, 1:]
        coef = np.linalg.lstsq(X * g[:, None], vv - o, rcond=None)[0]
        m = X @ coef
        for j, sel in enumerate(sels):
            cal[j] = np.linalg.lstsq(calibration_design(m[sel], ff[sel], drift), vv[sel], rcond=None)[0]
    grid = fourier_design(np.linspace(0, 1, 256, endpoint=False), harmonics)[:, 1:] @ coef
    p2p = np.ptp(grid)
    return coef / p2p if p2p > 0 else coef

