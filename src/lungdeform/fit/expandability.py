"""Heterogeneous stiffness field: an inverse estimate of regional alveolar expandability (paper
Sec. VI; optional beyond the paper, ``fit_lung`` with ``FitSettings(fit_stiffness=True)``).

Given the fitted direction constants and applied force of :func:`lungdeform.fit.fitting.fit_lung`, the
per-vertex Young's modulus ``E`` is adjusted so that the forward force of the fitted applied force
reproduces the smoothed observed ray magnitudes (:func:`fit_stiffness_field`), with ``log E``
smoothed over the mesh (:func:`smooth_observations`) and bounded (:data:`STIFFNESS_RANGE`); the
field is kept only when it lowers the fit objective (:func:`fit_stiffness_if_better`). The model
keeps its run-time form ``u = k·F·d``. Crop faces (``keep`` False) give no observations.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
from scipy import sparse

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.geometry.remesh import umbrella_operator
from lungdeform.model.response import ResponseSolver

if TYPE_CHECKING:  # annotations only
    from .objective import LungFitter

#: Bound of the fitted stiffness field: ``E ∈ [1/STIFFNESS_RANGE, STIFFNESS_RANGE]`` (relative).
STIFFNESS_RANGE = 4.0


def smooth_observations(values: np.ndarray, weights: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Normalised convolution on the mesh: weighted umbrella averaging of ``values (n,)`` with
    ``weights (n,) ≥ 0`` (0 = no observation, filled from the neighbours)."""

    n = len(values)
    avg = (umbrella_operator(n, faces) + sparse.identity(n)).tocsr()  # D⁻¹A: mean of neighbours
    a = np.asarray(values, float) * weights
    b = np.asarray(weights, float).copy()
    for _ in range(int(iterations)):
        a = 0.5 * a + 0.5 * (avg @ a)
        b = 0.5 * b + 0.5 * (avg @ b)
    return a / np.maximum(b, 1e-12)


def fit_stiffness_field(fitter: LungFitter, c_dir, *, iterations: int = 20, smoothing: int = 10,
                        target_smoothing: int = 10, log_range: float = float(np.log(STIFFNESS_RANGE)),
                        force=None, directions=None) -> np.ndarray:
    """Inverse estimate of alveolar expandability: ``log E (n,)``, a per-vertex stiffness whose
    forward force F(E) (for the fitted applied force) matches the observed magnitudes along the
    fitted directions ``c_dir`` — or ``directions (n, 3)`` when given (a corrected field,
    :mod:`lungdeform.fit.direction_correction`) — (ray hits of kept vertices, smoothed by
    ``target_smoothing`` normalised-convolution steps, misses filled by neighbours).

    Softer nodes keep and attract more force ((8)–(9), docs/METHOD_NOTES.md §3), so ``log E`` is updated by the damped
    log-ratio of the predicted to the observed magnitude, then smoothed (``smoothing`` umbrella
    steps) and bounded to ``|log E| ≤ log_range``, for ``iterations`` fixed-point steps. The
    smoothing and the bound are the regularisation: without them (2 steps, ±4) the field was rough,
    pinned a twentieth of the surface at near-zero motion and, on the ITK pair, raised the landmark
    error from 5.5 to 9.3 mm while lowering the surface error (with them: 6.1 mm; along directions
    fitted to surfaces, matching the surface better moves the interior worse). Leaves ``fitter``'s
    stiffness unchanged.
    """
    if directions is not None and force is None:
        raise InputError("stiffness fit: corrected directions need the fitted c7…c9 (force)")
    _, parts = fitter.evaluate(c_dir, full=True, force=force, directions=directions)
    if parts is None:
        raise ConvergenceError("stiffness fit: the direction constants give no usable model")
    hits = parts["hits"]
    w = np.where(hits.valid & fitter.keep, np.nan_to_num(hits.cosine), 0.0)
    target = smooth_observations(np.nan_to_num(hits.distance), w, fitter.surface.faces, target_smoothing)
    target = np.maximum(target, 0.05 * max(float(np.abs(target).max()), 1e-9))
    f = parts["constants"][6:] @ fitter.applied_fields
    log_e = np.zeros(fitter.n)
    for _ in range(int(iterations)):
        force = ResponseSolver(fitter.graph, np.exp(log_e), d_min=fitter.d_min).response(f)
        scale = float(target @ force) / float(force @ force)
        log_e = log_e + 0.7 * np.log(np.maximum(scale * force, 1e-3 * target) / target)
        log_e = smooth_observations(log_e, np.ones(fitter.n), fitter.surface.faces, smoothing)
        log_e = np.clip(log_e - np.median(log_e), -log_range, log_range)  # only ratios of E matter
    return log_e


def fit_stiffness_if_better(fitter: LungFitter, c_dir, best, say: Callable[[str], None], force=None, shifts=None,
                            directions=None, **kwargs):
    """:func:`fit_stiffness_field`, kept only if it lowers the objective; returns
    ``(log E (n,) or None, objective)`` and leaves the kept stiffness in ``fitter``. ``force`` /
    ``shifts``: fixed c7…c9 and target translations (least-squares mode), else rays;
    ``directions (n, 3)``: a corrected direction field to use instead of that of ``c_dir``."""
    previous = fitter.stiffness
    log_e = fit_stiffness_field(fitter, c_dir, force=force, directions=directions, **kwargs)
    fitter.set_stiffness(np.exp(log_e))
    obj = fitter.evaluate(c_dir, force=force, shifts=shifts, directions=directions)
    if not obj < best:
        fitter.set_stiffness(previous)
        say(f"stiffness field: RMS {obj:.3f} mm, not better than {best:.3f} mm: kept the previous one")
        return None, best
    say(f"stiffness field: RMS {best:.3f} -> {obj:.3f} mm")
    return log_e, obj
