"""k-fold splits of landmarks and the held-out choice of a landmark correction's smoothing.

Evaluation, not playback: :func:`landmark_folds` splits landmark indices into seeded folds (used by
the fit's landmark cross-validation, :mod:`lungdeform.evaluate.crossval`, by the held-out landmark
figures, :mod:`lungdeform.evaluate.heldout`, and by ``validate itk-pair``); the ``select_*``
functions pick the smoothing of the interior field's landmark correction
(:func:`lungdeform.interior.sliding.sliding_correction`, or the thin-plate one of older files) by
k-fold error on the landmarks themselves; the ``held_out_*`` functions predict each landmark with a
correction that did not see it (:mod:`lungdeform.interior.field`, "landmark correction").
Arrays: landmarks ``(m, 3) float`` mm (LPS, end-exhale frame); folds ``(k,) int`` index arrays.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices
from lungdeform.interior.field import (
    CORRECTION_SMOOTHING_MM,
    MAX_SURFACE_POINTS,
    SMOOTHING_MM2,
    correction_per_unit,
    spline_predict,
)
from lungdeform.interior.sliding import CorrectionSolver


def landmark_folds(n: int, folds: int = 5, seed: int = 0, *, parameter: str = "folds") -> list[np.ndarray]:
    """``folds`` disjoint index arrays covering ``range(n)`` (seeded random split, sizes within 1).
    ``parameter``: how the error for a bad ``folds`` names it (e.g. ``"--folds"``)."""
    if not 2 <= int(folds) <= n:
        raise InputError(f"{parameter} must be between 2 and the number of landmarks ({n}), got {folds}")
    idx = np.random.default_rng(seed).permutation(int(n))
    return [np.sort(part) for part in np.array_split(idx, int(folds))]


def _select(candidates, predict, index, values, folds: int, seed: int) -> float:
    """The candidate whose ``predict(candidate, train, values[train], test)`` (landmark indices
    into ``index``'s space) has the least summed held-out error over a seeded ``folds``-fold split
    of ``index``; fewer than 10 points: the largest candidate (too few to judge; the smoothest is
    safest)."""
    idx = np.asarray(index, int).ravel()
    v = as_vertices(values, "values")
    if len(idx) < 10:
        return float(max(candidates))

    parts = landmark_folds(len(idx), min(int(folds), len(idx)), seed)
    best, best_err = None, np.inf
    for cand in candidates:
        err = 0.0
        for test in parts:
            train = np.setdiff1d(np.arange(len(idx)), test)
            err += np.linalg.norm(predict(cand, idx[train], v[train], idx[test]) - v[test], axis=1).sum()
        if err < best_err - 1e-9:
            best, best_err = float(cand), err
    return best


def _held_out(q, observed, scales, predicted_unit, folds, select, predict) -> list[np.ndarray]:
    """Per fold, the correction through the other folds' landmarks (``select(train, c)`` picks its
    smoothing on them, ``predict(smoothing, train, c, test)`` moves the fold's own): the landmarks
    ``q : (m, 3)`` mm moved to each target, ``(m, 3) float`` mm per target."""
    p = as_vertices(predicted_unit, "predicted_unit")
    if len(p) != len(q):
        raise InputError(f"predicted_unit: need one row per landmark ({len(q)}), got {len(p)}")
    out = [np.full_like(q, np.nan) for _ in scales]
    for test in folds:
        train = np.setdiff1d(np.arange(len(q)), test)
        c = correction_per_unit([np.asarray(o)[train] for o in observed], scales, p[train])
        v = p[test] + predict(select(train, c), train, c, test)
        for i, s in enumerate(scales):
            out[i][test] = q[test] + float(s) * v
    return out


def _spline_predictor(points):
    p = as_vertices(points, "points")
    return lambda sm, train, values, test: spline_predict(p[train], values, p[test], sm)


def select_smoothing(points, values, candidates=SMOOTHING_MM2, folds: int = 5, seed: int = 0) -> float:
    """The candidate smoothing (mm²) with the least mean held-out error of the thin-plate spline
    through ``values : (k, 3)`` at ``points : (k, 3)`` (``folds``-fold, seeded split).
    Fewer than 10 points: the largest candidate (too few to judge; the smoothest is safest)."""
    p = as_vertices(points, "points")
    return _select(candidates, _spline_predictor(p), np.arange(len(p)), values, folds, seed)


def held_out_positions(landmarks, observed, scales, predicted_unit, folds, *, candidates=SMOOTHING_MM2,
                       seed: int = 0) -> list[np.ndarray]:
    """Landmarks moved by the corrected field, each predicted by a correction that did not see it.

    landmarks : (m, 3) float, mm (end-exhale); observed : per target (m, 3) mm displacement;
    scales : per target, units; predicted_unit : (m, 3) mm per unit (surface-driven);
    folds : index arrays partitioning ``range(m)``. Per fold, the correction and its smoothing
    (:func:`select_smoothing`, inner folds) come from the other folds' landmarks only.
    Returns per target ``(m, 3) float`` mm predicted positions.
    """
    q = as_vertices(landmarks, "landmarks")
    predict = _spline_predictor(q)
    return _held_out(q, observed, scales, predicted_unit, folds,
                     lambda train, c: _select(candidates, predict, train, c, 5, seed), predict)


def correction_solvers(points, normals, landmarks, candidates=CORRECTION_SMOOTHING_MM, *,
                       seed: int = 0) -> dict[float, CorrectionSolver]:
    """One :class:`~lungdeform.interior.sliding.CorrectionSolver` per candidate surface smoothing (mm): the
    sliding landmark correction from the surface ``points : (k, 3)`` mm (unit ``normals``) through
    any subset of ``landmarks : (m, 3)`` mm, each solved once (what does not depend on the smoothing
    formed once for all, :meth:`~lungdeform.interior.sliding.CorrectionSolver.for_smoothings`)."""
    return CorrectionSolver.for_smoothings(points, normals, landmarks, [float(lam) for lam in candidates],
                                           max_points=MAX_SURFACE_POINTS, seed=seed)


def _solver_predictor(solvers: dict):
    return lambda lam, train, values, test: solvers[lam].predict(train, values, test)


def select_correction_smoothing(solvers: dict, index, values, folds: int = 5, seed: int = 0) -> float:
    """The surface smoothing (mm, a key of ``solvers``) whose sliding correction through
    ``values : (len(index), 3)`` at the solvers' landmarks ``index`` has the least mean held-out
    error (``folds``-fold, seeded split). Fewer than 10 landmarks: the largest (the smoothest)."""
    return _select(solvers, _solver_predictor(solvers), index, values, folds, seed)


def held_out_sliding(observed, scales, predicted_unit, folds, solvers: dict, *, seed: int = 0) -> list[np.ndarray]:
    """As :func:`held_out_positions`, with the sliding landmark correction: per fold, the
    correction and its surface smoothing (:func:`select_correction_smoothing`, inner folds) come
    from the other folds' landmarks only. ``solvers``: :func:`correction_solvers` over every
    landmark (end-exhale, mm). Returns per target ``(m, 3) float`` mm predicted positions."""
    predict = _solver_predictor(solvers)
    return _held_out(next(iter(solvers.values())).anchors, observed, scales, predicted_unit, folds,
                     lambda train, c: _select(solvers, predict, train, c, 5, seed), predict)
