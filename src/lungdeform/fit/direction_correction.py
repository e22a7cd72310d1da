"""A smooth correction to the paper's direction field, fitted to the surfaces (beyond the paper).

The paper's directions (15)–(17) have six constants; on real lungs they cannot follow every
region (on the ITK pair their in-sample surface error stays near 2 mm whatever c1…c6 are). This
module rotates them by a low-order polynomial field, fitted to the same surfaces:

    d_i = normalise(d⁰_i + Cᵀ φ(x̂_i)),   φ = the monomials of degree ≤ ``degree`` in the lung-frame
                                         coordinates 2·x̂ − 1 ∈ [−1, 1]³ (20 per axis at degree 3),

with ``C (K, 3)`` in LPS. The magnitude ``k·F_i`` (force, stiffness, calibration) is unchanged, and
so is playback: the model still stores one displacement per vertex, ``u = k·F·d``.

Fit (:func:`fit_direction_correction`): Gauss–Newton steps on closest-point correspondences of the
symmetric surface distance (model vertices → target surface, target samples → nearest model
vertex), with the linearised normalisation ``∂d = (I − d dᵀ)/|d⁰ + Cᵀφ| · ∂(Cᵀφ)`` and a ridge
of 1 % of the mean curvature of the normal equations; every step is scored by the fit's own exact
objective (:meth:`lungdeform.fit.objective.LungFitter.residual_vector`) and the best is kept, only if it
lowers the objective. Measured on the ITK right lung (stiffness field fitted): surface mean
distance 1.95 → 1.53 mm at degree 3 (degree 2: 1.65 mm; degree 4 does no better).

The correction belongs to the posture of the fitted scans: :meth:`LungModel.oriented` recomputes
the paper's directions for another gravity and so drops it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from lungdeform.errors import InputError
from lungdeform.model.direction import corrected_directions, polynomial_basis
from lungdeform.progress import Progress, silent

if TYPE_CHECKING:  # annotations only
    from .objective import LungFitter

#: Default polynomial degree of the correction (0: the paper's directions only).
DEFAULT_DEGREE = 3


@dataclass(frozen=True, eq=False)
class DirectionCorrection:
    """Outcome of :func:`fit_direction_correction`.

    Attributes
    ----------
    degree : int
    coefficients : (K, 3) float
        ``C`` (LPS); zeros when not accepted.
    directions : (n, 3) float
        Corrected unit directions (the paper's when not accepted).
    displacement : (n, 3) float
        ``u`` with them, mm per the fitter's unit.
    start_objective_mm, objective_mm : float
        The fit objective with the paper's directions and with the correction, mm.
    accepted : bool
        Whether the correction lowered the objective (else the paper's field is kept).
    steps : int
        Gauss–Newton steps taken.
    """

    degree: int
    coefficients: np.ndarray
    directions: np.ndarray
    displacement: np.ndarray
    start_objective_mm: float
    objective_mm: float
    accepted: bool
    steps: int

    def as_dict(self) -> dict:
        return {"degree": self.degree, "accepted": self.accepted, "steps": self.steps,
                "start_objective_rms_mm": self.start_objective_mm, "objective_rms_mm": self.objective_mm,
                "coefficients": self.coefficients.tolist()}


def _correspondence(fitter: LungFitter, u, shifts):
    """For the displacement ``u : (n, 3)`` and each target in the fit: per model vertex, the mean of
    its closest-point residuals (mm; its own closest point on the target, and the target samples
    whose nearest model vertex it is). Returns ``(rows (r,) vertex index, s (r,) the target's
    scale, residual (r, 3) mm)``."""
    rows, scales, res = [], [], []
    keep = np.flatnonzero(fitter.keep)
    for i in fitter.fit_on:
        pt = fitter.prepared[i]
        s = fitter.scale_at(i)
        t = np.zeros(3) if shifts is None else np.asarray(shifts[i], float)
        xi = fitter.p + s * u
        _, closest, _ = fitter.target_query(i, xi[keep] - t)  # what the objective at u just found
        acc = np.zeros((fitter.n, 3))
        cnt = np.zeros(fitter.n)
        acc[keep] += closest + t - xi[keep]
        cnt[keep] += 1.0
        _, nn = cKDTree(xi[keep]).query(pt.samples + t)
        np.add.at(acc, keep[nn], pt.samples + t - xi[keep[nn]])
        np.add.at(cnt, keep[nn], 1.0)
        m = np.flatnonzero(cnt > 0)
        rows.append(m)
        scales.append(np.full(len(m), s))
        res.append(acc[m] / cnt[m, None])
    return np.concatenate(rows), np.concatenate(scales), np.concatenate(res)


@dataclass(frozen=True)
class CorrectionSearch:
    """The Gauss–Newton search of :func:`fit_direction_correction`: at most ``steps`` steps, each
    damped by ``ridge`` × the mean diagonal of the normal matrix, stopping after ``patience``
    steps without improvement."""

    steps: int = 10
    ridge: float = 0.01
    patience: int = 3


def fit_direction_correction(fitter: LungFitter, d0, c_force, shifts=None, *, degree: int = DEFAULT_DEGREE,
                             initial=None, search: CorrectionSearch = CorrectionSearch(),
                             progress: Progress | None = None) -> DirectionCorrection:
    """Fit ``C`` for the paper's directions ``d0 : (n, 3)`` and c7…c9 ``c_force (3,)`` (see the
    module docstring), starting from ``initial (K, 3)`` (default zeros); ``shifts : (k, 3)`` mm,
    the targets' fitted translations; ``search``: steps, damping and patience
    (:class:`CorrectionSearch`). ``accepted``: the result beats the start (the paper's field, or
    ``initial``)."""
    say = progress or silent
    steps, ridge, patience = search.steps, search.ridge, search.patience
    basis = polynomial_basis(fitter.xyz, degree)
    k = basis.shape[1]
    force = np.asarray(c_force, float) @ fitter.fields
    coef = np.zeros((k, 3)) if initial is None else np.array(initial, float)
    if coef.shape != (k, 3):
        raise InputError(f"initial direction correction has shape {coef.shape}, expected ({k}, 3) for degree {degree}")
    d_start = corrected_directions(d0, basis, coef)
    u0 = fitter.displacement(d_start, c_force)
    if u0 is None:
        raise InputError("direction correction: the starting directions give no usable model")
    start = fitter.objective(u0, shifts)
    best = (start, coef.copy(), d_start, u0)
    d, u = d_start, u0  # the field at the current coefficients
    since, taken = 0, 0
    for taken in range(1, int(steps) + 1):
        length = np.linalg.norm(np.asarray(d0, float) + basis @ coef, axis=1)
        raw_u = force[:, None] * d
        gain = float(np.sum(u * raw_u) / max(np.sum(raw_u * raw_u), 1e-30))  # the calibration k
        rows, s, res = _correspondence(fitter, u, shifts)
        # ∂x/∂C for vertex v at scale s: s·k·F_v/|raw_v| · (I − d dᵀ) ⊗ φ_v
        proj = np.eye(3)[None] - d[rows, :, None] * d[rows, None, :]  # (r, 3, 3)
        g = (s * gain * force[rows] / np.maximum(length[rows], 1e-12))[:, None, None] * proj
        jac = np.einsum("rij,rk->rikj", g, basis[rows]).reshape(len(rows) * 3, k * 3)
        normal = jac.T @ jac
        lam = ridge * np.trace(normal) / normal.shape[0]
        step = np.linalg.solve(normal + lam * np.eye(normal.shape[0]), jac.T @ res.reshape(-1))
        coef = coef + step.reshape(k, 3)
        d_new = corrected_directions(d0, basis, coef)
        u_new = fitter.displacement(d_new, c_force)
        if u_new is None:
            break
        d, u = d_new, u_new
        obj = fitter.objective(u, shifts)
        if obj < best[0] - 1e-6:
            best, since = (obj, coef.copy(), d_new, u_new), 0
        else:
            since += 1
            if since >= patience:
                break
    accepted = best[0] < start
    say(f"direction correction (degree {degree}): RMS {start:.3f} -> {best[0]:.3f} mm "
        f"after {taken} step(s){'' if accepted else ', not better: kept the starting directions'}")
    return DirectionCorrection(int(degree), best[1], best[2], best[3], float(start), float(best[0]),
                               bool(accepted), int(taken))
