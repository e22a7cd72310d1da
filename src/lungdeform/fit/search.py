"""Search strategies over the model's constants for :func:`lungdeform.fit.fitting.fit_lung` (docs/FITTING.md).

``least_squares`` (the default optimiser): a trust-region least-squares solver
(``scipy.optimize.least_squares``, finite differences) on the per-point residual vector of
:meth:`lungdeform.fit.objective.LungFitter.residual_vector`, whose sum of squares is the objective squared.
Two findings on synthetic lungs made by the model itself (known truth) shape it: (a) directions are
normalised, so c1, c3, c5 are defined only up to a common factor (a zero singular value): c3 is
held at its start (:data:`GAUGE`, Table I) and the ratios c1/c3, c5/c3 are what is determined;
(b) c7…c9 fitted to ray magnitudes are biased (about a tenth of the rays hit another part of the
target first, a quarter are dropped as grazing), so the truth is not the minimum of the objective
with ray-fitted force constants: they are refined against the surface objective itself, started
from the ray fit, the largest held at ±1 (the scale is fixed by the volume calibration). With
``translate=True`` a translation per target is fitted jointly (removes a table shift without
assuming that any region of the lung stays put). On noise-free synthetic lungs this recovers the
displacement to a few µm per vertex; Powell on the RMS stopped on its budget with errors of about
a millimetre.

``powell`` (the former optimiser): Powell over c1…c6 (c7…c9 from the rays at every candidate), in
variables that map onto the bounds through a sine (:func:`from_unbounded`), so that every
candidate is inside them.

``grid`` (the paper's grid with step 0.01, read as cyclic coordinate search on that grid,
:func:`grid_search`: each constant in turn is scanned over its range at step 0.01 with the others
fixed, until a full cycle brings no improvement; a full 6-D grid at 0.01 would be 10¹² models).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import optimize

from lungdeform.errors import ConvergenceError
from lungdeform.progress import Progress

if TYPE_CHECKING:  # annotations only
    from .objective import LungFitter

#: Bound of the free force constants in the least-squares mode, relative to the fixed one (|c| ≤).
FORCE_BOUND = 3.0

#: RMS (mm) of the residual vector handed to the least-squares solver for an unusable candidate.
UNUSABLE_RESIDUAL_MM = 50.0

#: Index of the direction constant held fixed in the least-squares mode (the gauge): c3.
GAUGE = 2


def least_squares_search(fitter: LungFitter, x0: np.ndarray, force0, *, lo, hi, translate: bool,
                         max_evaluations: int, history: list):
    """Trust-region least squares (scipy ``least_squares``, ``trf``) on the per-point residual vector
    (:meth:`LungFitter.residual_vector`), its Jacobian from one evaluation's closest points (:func:`_jacobian`).

    Free: c1, c2, c4, c5, c6 (c3 held at its start: directions are normalised, so c1, c3, c5 are
    defined only up to a common factor, a zero singular value; the ratios c1/c3 and c5/c3 are what
    the data determine); the two force constants other than the largest at the start (held at ±1,
    the overall scale being fixed by the volume calibration), within ±:data:`FORCE_BOUND`; with
    ``translate``, a translation (mm) of each target in ``fit_on``. c7…c9 start from ``force0`` or
    the ray fit at ``x0``, which is only a start: rays that hit another part of the target or graze
    bias it, so the force constants are refined against the surface objective itself. ``lo``,
    ``hi``: ``(6,)`` bounds of c1…c6 (:data:`lungdeform.fit.fitting.DIRECTION_LO`, ``DIRECTION_HI``).

    Returns ``(c1…c6 (6,), c7…c9 (3,), shifts (k, 3) or None, objective mm, success, message)``.
    """
    lo6, hi6 = np.asarray(lo, float), np.asarray(hi, float)
    if force0 is None:
        d0 = fitter.directions(x0)
        force0 = fitter.ray_force_constants(d0, fitter.rays(d0))
        if force0 is None:
            raise ConvergenceError(f"the starting constants {x0} give no ray hits to start c7…c9 from")
    force0 = np.asarray(force0, float)
    if not np.abs(force0).max() > 0:
        raise ConvergenceError("the starting force constants c7…c9 are all zero")
    pivot = int(np.argmax(np.abs(force0)))
    force0 = force0 / abs(force0[pivot])
    free_dir = [i for i in range(6) if i != GAUGE]
    free_force = [i for i in range(3) if i != pivot]
    n_shift = 3 * len(fitter.fit_on) if translate else 0
    lo = np.concatenate([lo6[free_dir], [-FORCE_BOUND] * 2, [-np.inf] * n_shift])
    hi = np.concatenate([hi6[free_dir], [FORCE_BOUND] * 2, [np.inf] * n_shift])
    theta0 = np.concatenate([x0[free_dir], np.clip(force0[free_force], -FORCE_BOUND, FORCE_BOUND), np.zeros(n_shift)])
    scale = np.concatenate([np.abs(theta0[: len(free_dir) + 2]) + 0.05, np.ones(n_shift)])

    def unpack(theta):
        c = x0.copy()
        c[free_dir] = theta[: len(free_dir)]
        f = force0.copy()
        f[free_force] = theta[len(free_dir): len(free_dir) + 2]
        sh = None
        if translate:
            sh = np.zeros((len(fitter.targets), 3))
            sh[fitter.fit_on] = theta[len(free_dir) + 2:].reshape(-1, 3)
        return c, f, sh

    size = {"n": None}
    best = {"f": np.inf, "theta": theta0}

    def resid(theta):
        c, f, sh = unpack(theta)
        r = fitter.residuals(c, f, sh).vector
        if r is None or not np.all(np.isfinite(r)):
            if size["n"] is None:
                raise ConvergenceError(f"the starting constants {x0}, {force0} give no usable model")
            r = np.full(size["n"], UNUSABLE_RESIDUAL_MM / np.sqrt(size["n"]))
        size["n"] = len(r)
        v = float(np.sqrt(np.sum(r**2)))
        history.append(min(v, history[-1]) if history else v)
        if v < best["f"]:
            best["f"], best["theta"] = v, theta.copy()
        return r

    def jac(theta):
        return _jacobian(fitter, unpack, theta, scale, lo, hi, translate, size["n"])

    n_free = len(theta0)
    max_nfev = max(1, int(max_evaluations) // (n_free + 1))
    res = optimize.least_squares(resid, theta0, jac=jac, bounds=(lo, hi), x_scale=scale, method="trf",
                                 ftol=1e-6, xtol=1e-6, gtol=1e-8, max_nfev=max_nfev)
    theta, obj = res.x, float(np.sqrt(np.sum(res.fun**2)))
    if best["f"] < obj:  # never return a point worse than one already evaluated
        theta, obj = best["theta"], best["f"]
    c, f, sh = unpack(theta)
    if res.status > 0:
        return c, f, sh, obj, True, f"least squares converged ({res.message})"
    return c, f, sh, obj, False, (f"least squares stopped on its evaluation budget ({max_evaluations} evaluations: "
                                  f"{res.nfev} iterations, the most at {n_free + 1} per iteration; "
                                  f"{fitter.evaluations} evaluated): not converged")


#: Step of the forward differences of the displacement ``u`` (not of the residuals), relative to
#: each free constant's scale: ``u`` is smooth in the constants, so a small step is accurate.
U_STEP = 1e-6


def _jacobian(fitter: LungFitter, unpack, theta, scale, lo, hi, translate: bool, rows) -> np.ndarray:
    """The Jacobian of the least-squares residuals at ``theta`` (:func:`least_squares_search`): the
    displacement's derivative in each free constant by a forward difference of ``u`` alone (no
    distance is measured), then the residuals' derivatives through the closest points of one forward
    evaluation (:meth:`LungFitter.residual_jacobian`); the translations' columns exactly. Zeros
    (``rows`` of them) where ``theta`` gives no usable model (never an accepted point)."""
    n_const = len(theta) - (3 * len(fitter.fit_on) if translate else 0)
    c, f, sh = unpack(theta)
    u = fitter.displacement(fitter.directions(c), f)
    if u is None:
        return np.zeros((rows, len(theta)))
    du = np.zeros(u.shape + (n_const,))
    for k in range(n_const):
        h = U_STEP * scale[k] * (1.0 if theta[k] + U_STEP * scale[k] <= hi[k] else -1.0)
        step = theta.copy()
        step[k] += h
        ck, fk, _ = unpack(step)
        uk = fitter.displacement(fitter.directions(ck), fk)
        du[..., k] = 0.0 if uk is None else (uk - u) / h
    jp, jt = fitter.residual_jacobian(u, du, sh, translations=translate)
    return np.hstack([jp, jt]) if translate else jp


def from_unbounded(z: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Map unbounded ``z`` into the box ``[lo, hi]``: ``lo + (hi − lo)·(1 + sin z)/2``."""
    return lo + (hi - lo) * (1.0 + np.sin(z)) / 2.0


def grid_search(fun, x0, bounds, step=0.01, max_cycles=20, span=None, progress: Progress | None = None):
    """Cyclic coordinate search on a grid of ``step``; returns (x, f, cycles, converged)."""
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
            return x, best, cycle, True
    return x, best, max_cycles, False


def powell_search(fun, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_evaluations: int):
    """Powell over ``fun`` (c1…c6 (6,) → objective, mm) inside the box ``[lo, hi]`` from ``x0``;
    returns ``(x (6,), objective, success, message)`` (message "converged" on success).

    The bounds are built into the variables, x = lo + (hi − lo)·(1 + sin z)/2, and Powell runs
    unbounded in z. Not scipy's bounded Powell: its line search (fminbound) can return a point
    worse than the current one on a rough objective such as this one, and Powell accepts it
    (seen: a landmark-informed fit ending 1.5 mm above its start). Not clipping either: the
    flat region outside the box wastes a small budget on bracket searches.
    """
    z0 = np.arcsin(np.clip(2.0 * (np.clip(x0, lo, hi) - lo) / (hi - lo) - 1.0, -1.0, 1.0))
    res = optimize.minimize(lambda z: fun(from_unbounded(z, lo, hi)), z0, method="Powell",
                            options={"maxfev": max_evaluations, "xtol": 1e-3, "ftol": 1e-5})
    x, best = from_unbounded(res.x, lo, hi), res.fun
    if not res.success:
        return x, best, False, f"Powell: {res.message}"
    return x, best, True, "converged"
